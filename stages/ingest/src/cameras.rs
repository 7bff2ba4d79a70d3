//! The one reader of the ingest schema's camera arrays (`camera_K`, `camera_R`, `camera_t`,
//! `camera_image_size`), used by every later stage and by `pipeline render`.

use anyhow::Context;
use seqavatar_core::camera::{Camera, Intrinsics};
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_engine::EntryReader;

/// Reads the distortion-free cameras `camera_K`, `camera_R`, `camera_t`, `camera_image_size` of an entry.
pub fn read_cameras(entry: &EntryReader) -> anyhow::Result<Vec<Camera>> {
    let k = entry.read::<f64>("camera_K")?;
    let r = entry.read::<f64>("camera_R")?;
    let t = entry.read::<f64>("camera_t")?;
    let size = entry.read::<u32>("camera_image_size")?;
    let views = k.shape.first().copied().unwrap_or(0);
    let location = entry.location();
    for (name, shape, expected) in [
        ("camera_K", &k.shape, vec![views, 3, 3]),
        ("camera_R", &r.shape, vec![views, 3, 3]),
        ("camera_t", &t.shape, vec![views, 3]),
        ("camera_image_size", &size.shape, vec![views, 2]),
    ] {
        anyhow::ensure!(
            *shape == expected,
            "entry {location}: array `{name}` has shape {shape:?}, expected {expected:?}"
        );
    }
    (0..views)
        .map(|view| {
            let kk = &k.data[view * 9..view * 9 + 9];
            let rr = &r.data[view * 9..view * 9 + 9];
            let tt = &t.data[view * 3..view * 3 + 3];
            let hw = &size.data[view * 2..view * 2 + 2];
            let camera = Camera {
                width: hw[1],
                height: hw[0],
                intrinsics: Intrinsics {
                    fx: kk[0],
                    fy: kk[4],
                    cx: kk[2],
                    cy: kk[5],
                },
                rotation: DMat3::from_cols_array(&[
                    rr[0], rr[3], rr[6], rr[1], rr[4], rr[7], rr[2], rr[5], rr[8],
                ]),
                translation: DVec3::new(tt[0], tt[1], tt[2]),
                distortion: [0.0; 5],
            };
            camera
                .validate()
                .with_context(|| format!("entry {location}: camera of view {view}"))?;
            Ok(camera)
        })
        .collect()
}
