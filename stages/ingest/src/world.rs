//! The world ingest writes in: the offset that re-centres it on the subject
//! (`seqavatar_schema::ingest`'s `world_offset`), and the warnings about where the cameras
//! stand against the body.
//!
//! Training and rendering compute in f32, whose resolution at 10 km is a millimetre: a scene
//! far from its world's origin would lose the detail of the avatar with no word. Re-centred,
//! the same scene is stored (up to the rounding of f64) as it would be at the origin.

use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec3;

use rayon::prelude::*;

/// The farthest a body's mean world translation may be from the dataset's origin, in metres:
/// about the Earth's radius, as geographic coordinates can be; farther is garbage.
pub const MAX_WORLD_OFFSET: f64 = 1e7;

/// The point of the dataset's world that becomes the entry's origin: the mean world
/// translation of `fits` (the finite ones; a non-finite fit is refused later, by name),
/// rounded to whole metres, so that a scene moved by whole metres stores the same arrays and
/// one near the origin keeps its coordinates.
pub fn world_offset(fits: &[BodyParams], describe: &str) -> anyhow::Result<DVec3> {
    let finite: Vec<DVec3> = fits
        .iter()
        .map(|params| params.world_translation)
        .filter(|translation| translation.is_finite())
        .collect();
    if finite.is_empty() {
        return Ok(DVec3::ZERO);
    }
    let mean = finite.iter().fold(DVec3::ZERO, |sum, t| sum + *t) / finite.len() as f64;
    anyhow::ensure!(
        mean.abs().max_element() <= MAX_WORLD_OFFSET,
        "{describe}: the body fits' mean world translation {mean} is farther than \
         {MAX_WORLD_OFFSET} m from the world's origin"
    );
    // `+ 0.0` makes a -0 (a small negative mean rounded) the plain 0 it means.
    Ok(mean.round() + DVec3::ZERO)
}

/// One view as the warnings name it.
pub struct NamedCamera<'a> {
    pub id: i64,
    pub camera: &'a Camera,
}

/// Cameras inside the body's bounding box, and frames whose body no camera sees, as
/// warnings naming the camera and the frames (`frame_ids[i]` names `fits[i]`). Neither
/// stops ingest (a camera among outstretched arms may be meant), but both train a worse
/// avatar.
pub fn geometry_warnings(
    model: &BodyModel,
    fits: &[BodyParams],
    frame_ids: &[i64],
    cameras: &[NamedCamera<'_>],
) -> anyhow::Result<Vec<String>> {
    // Per frame: the cameras inside its box, and whether any camera sees a vertex.
    let per_frame = fits
        .par_iter()
        .map(|params| {
            let vertices = model.forward(params)?.vertices;
            let (lo, hi) = vertices
                .iter()
                .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(*v), hi.max(*v))
                });
            let inside: Vec<usize> = (0..cameras.len())
                .filter(|&c| {
                    let centre = cameras[c].camera.center();
                    centre.cmpge(lo).all() && centre.cmple(hi).all()
                })
                .collect();
            let seen = cameras.iter().any(|named| {
                let camera = named.camera;
                let (width, height) = (f64::from(camera.width), f64::from(camera.height));
                vertices.iter().any(|v| {
                    camera.project(*v).is_some_and(|p| {
                        (0.0..width).contains(&p.x) && (0.0..height).contains(&p.y)
                    })
                })
            });
            Ok((inside, seen))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut warnings = Vec::new();
    for (c, named) in cameras.iter().enumerate() {
        let frames: Vec<i64> = (0..fits.len())
            .filter(|&f| per_frame[f].0.contains(&c))
            .map(|f| frame_ids[f])
            .collect();
        if !frames.is_empty() {
            warnings.push(format!(
                "camera {} is inside the body's bounding box at {}: it sees the body from \
                 within",
                named.id,
                listed(&frames, fits.len())
            ));
        }
    }
    let unseen: Vec<i64> = (0..fits.len())
        .filter(|&f| !per_frame[f].1)
        .map(|f| frame_ids[f])
        .collect();
    if !unseen.is_empty() {
        warnings.push(format!(
            "the body is outside every camera's view at {}: no camera sees it",
            listed(&unseen, fits.len())
        ));
    }
    Ok(warnings)
}

/// `frame 3`, or `frames 3, 4, 5, 6, 7 and 12 more (17 of 40)`.
fn listed(frames: &[i64], total: usize) -> String {
    const SHOWN: usize = 5;
    if let [one] = frames {
        return format!("frame {one}");
    }
    let shown: Vec<String> = frames.iter().take(SHOWN).map(i64::to_string).collect();
    let more = match frames.len().saturating_sub(SHOWN) {
        0 => String::new(),
        more => format!(" and {more} more"),
    };
    format!(
        "frames {}{more} ({} of {total})",
        shown.join(", "),
        frames.len()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::camera::Intrinsics;

    fn looking_at(eye: DVec3, target: DVec3) -> Camera {
        let intrinsics = Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 24.0,
            cy: 24.0,
        };
        Camera::look_at(48, 48, intrinsics, eye, target, DVec3::Y)
    }

    #[test]
    fn the_offset_is_the_mean_translation_in_whole_metres() {
        let model = procedural_body(0.05);
        let at = |x: f64, y: f64, z: f64| BodyParams {
            world_translation: DVec3::new(x, y, z),
            ..model.zero_params()
        };
        let fits = [at(10_000.2, 0.9, -3.7), at(10_000.6, 0.9, -3.9)];
        assert_eq!(
            world_offset(&fits, "d").unwrap(),
            DVec3::new(10_000.0, 1.0, -4.0)
        );
        // A non-finite fit is left to the parameter check, which names its frame.
        let with_nan = [at(2.2, 0.0, 0.0), at(f64::NAN, 0.0, 0.0)];
        assert_eq!(
            world_offset(&with_nan, "d").unwrap(),
            DVec3::new(2.0, 0.0, 0.0)
        );
        let error = world_offset(&[at(2e7, 0.0, 0.0)], "dataset X")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("dataset X") && error.contains("farther"),
            "{error}"
        );
    }

    /// A camera placed in the body, and a frame whose body has walked out of every view,
    /// are named; a ring of cameras around the body gives no warning.
    #[test]
    fn cameras_in_the_body_and_bodies_out_of_view_are_named() {
        let model = procedural_body(0.05);
        let standing = model.zero_params();
        let centre = {
            let vertices = model.forward(&standing).unwrap().vertices;
            vertices.iter().fold(DVec3::ZERO, |sum, v| sum + *v) / vertices.len() as f64
        };
        let away = BodyParams {
            world_translation: DVec3::new(0.0, 0.0, 100.0),
            ..standing.clone()
        };
        let ring = [
            looking_at(centre + DVec3::new(3.0, 0.0, 0.0), centre),
            looking_at(centre + DVec3::new(-3.0, 0.0, 0.0), centre),
        ];
        let inside = looking_at(centre, centre + DVec3::X);
        fn named(cameras: &[Camera]) -> Vec<NamedCamera<'_>> {
            cameras
                .iter()
                .enumerate()
                .map(|(i, camera)| NamedCamera {
                    id: 10 + i as i64,
                    camera,
                })
                .collect()
        }
        let fits = [standing.clone(), standing.clone()];
        assert!(
            geometry_warnings(&model, &fits, &[0, 1], &named(&ring))
                .unwrap()
                .is_empty()
        );
        let with_inside = [ring[0].clone(), ring[1].clone(), inside];
        let fits = [standing.clone(), away, standing];
        let warnings = geometry_warnings(&model, &fits, &[4, 5, 6], &named(&with_inside)).unwrap();
        assert_eq!(
            warnings,
            [
                "camera 12 is inside the body's bounding box at frames 4, 6 (2 of 3): it sees \
                 the body from within",
                "the body is outside every camera's view at frame 5: no camera sees it",
            ],
            "{warnings:#?}"
        );
        assert_eq!(
            listed(&(0..9).collect::<Vec<_>>(), 40),
            "frames 0, 1, 2, 3, 4 and 4 more (9 of 40)"
        );
    }
}
