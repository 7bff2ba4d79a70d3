//! Fuzz target: the safe pickle reader must return `Ok` or `Err` for any bytes, never panic
//! or allocate more than the input justifies.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = seqavatar_formats::pickle::load(data);
});
