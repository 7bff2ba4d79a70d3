//! Fuzz target: the DNA-Rendering `.smc` (HDF5) reader: opens the input and reads every
//! group, dataset and attribute under the reader's size limits.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = seqavatar_datasets::smc::read_all(data);
});
