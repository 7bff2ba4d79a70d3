//! Fuzz target: the dataset image and mask decoder (format sniffing, JPEG in strict mode,
//! PNG, the header size checks). Pictures up to 1024 x 1024 are decoded as the datasets do,
//! with their header size as the expected size; larger claims only read the header (their
//! allocation bound is measured by `stages/ingest/tests/bombs.rs`).
#![no_main]

use libfuzzer_sys::fuzz_target;
use seqavatar_formats::images;

fuzz_target!(|data: &[u8]| {
    let Ok((width, height)) = images::dimensions(data) else {
        return;
    };
    if u64::from(width) * u64::from(height) > 1 << 20 {
        return;
    }
    if let Ok(rgb) = images::decode_rgb(data, Some((width, height))) {
        assert_eq!(rgb.dimensions(), (width, height));
    }
    if let Ok(mask) = images::decode_mask(data, Some((width, height)), true) {
        assert_eq!(mask.dimensions(), (width, height));
        assert!(mask.iter().all(|&v| v == 0 || v == 255));
    }
});
