//! Fuzz target: the `.npz` reader (our zip central-directory parser, inflate, CRC, `.npy`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = seqavatar_formats::npz::read(data);
});
