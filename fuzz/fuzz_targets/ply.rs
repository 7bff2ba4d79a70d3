//! Fuzz target: the 3D Gaussian Splatting PLY reader (header parsing, property layout, the
//! data length check, non-finite values). A cloud it accepts must be consistent and survive
//! a round trip through the writer unchanged.
#![no_main]

use libfuzzer_sys::fuzz_target;
use seqavatar_formats::ply::{coefficient_count, read_ply, write_ply};

fuzz_target!(|data: &[u8]| {
    let Ok(cloud) = read_ply(data) else {
        return;
    };
    let n = cloud.len();
    let k = coefficient_count(cloud.sh_degree);
    assert_eq!(cloud.xyz.len(), 3 * n);
    assert_eq!(cloud.sh.len(), 3 * k * n);
    assert_eq!(cloud.log_scale.len(), 3 * n);
    assert_eq!(cloud.rotation.len(), 4 * n);
    let back = read_ply(&write_ply(&cloud).expect("write_ply")).expect("read_ply of write_ply");
    assert_eq!(back.xyz, cloud.xyz);
    assert_eq!(back.opacity, cloud.opacity);
    assert_eq!(back.log_scale, cloud.log_scale);
    assert_eq!(back.rotation, cloud.rotation);
    // Written as degree 3: the cloud's coefficients, zeros after them.
    for g in 0..3 * n {
        for coeff in 0..16 {
            let want = if coeff < k {
                cloud.sh[g * k + coeff]
            } else {
                0.0
            };
            assert_eq!(back.sh[g * 16 + coeff], want);
        }
    }
});
