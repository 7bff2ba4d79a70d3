//! Fuzz target: the `.npy` reader (numeric arrays and pickled object arrays).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(value) = seqavatar_formats::npy::read(data) {
        // Exercise the accessors the dataset readers use on decoded values.
        let _ = value.unwrap_object_scalar().to_f64_array();
    }
});
