//! The standard benchmark scene of `rasterizer.md`, reproducible from this documentation
//! alone so that other rasterisers can be timed on the identical input.
//!
//! # Definition
//!
//! Image 512 x 512; pinhole `fx = fy = 600`, `cx = cy = 256` (continuous pixel convention);
//! camera at the origin looking down `+z` (world-to-camera is the identity). `N` Gaussians.
//!
//! Random numbers come from SplitMix64 seeded with `seed`:
//! `state += 0x9E3779B97F4A7C15; z = state; z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9;
//! z = (z ^ (z >> 27)) * 0x94D049BB133111EB; return z ^ (z >> 31)` (wrapping arithmetic).
//! A uniform `U[0, 1)` is `(next >> 11) * 2^-53`; `U[a, b)` is `a + (b - a) U[0, 1)`. A
//! standard normal is Box-Muller on two consecutive uniforms `u1, u2`:
//! `sqrt(-2 ln(1 - u1)) cos(2 pi u2)`.
//!
//! For each Gaussian in order, the draws are: `x ~ U[-1, 1)`, `y ~ U[-1, 1)`, `z ~ U[2, 4)`;
//! three log-scales `~ U[ln 0.005, ln 0.03)` (scale = `exp`); a rotation `[w, x, y, z]` of
//! four standard normals, normalised; opacity `~ U[0.1, 0.9)`; colour `r, g, b ~ U[0, 1)`,
//! stored as degree-0 SH `(c - 0.5) / 0.28209479177387814`. After all Gaussians, the upstream
//! image gradient: one standard normal per pixel and channel, row-major `H x W x 3`.
//! Covariances are `R diag(scale)^2 R^T`. All values are drawn in `f64`.

use glam::{DMat3, DVec3};
use seqavatar_core::camera::{Camera, Intrinsics};

use super::GaussianBuffers;
use super::covariance::covariance_from_scale_rotation;
use super::sh::SH_C0;

/// Image side of the standard scene, in pixels.
pub const SCENE_SIZE: u32 = 512;
/// The seed the benchmark uses.
pub const STANDARD_SEED: u64 = 42;

/// SplitMix64, the scene's documented generator (the project's one, in `seqavatar_core`).
pub use seqavatar_core::rng::SplitMix64;

/// The standard scene: camera, Gaussians (with the scales and rotations they came from) and
/// the upstream colour gradient of the backward benchmark.
#[derive(Clone, Debug)]
pub struct BenchmarkScene {
    pub camera: Camera,
    pub gaussians: GaussianBuffers<f64>,
    /// `N x 3` linear scales.
    pub scales: Vec<f64>,
    /// `N x 4` unit quaternions `[w, x, y, z]`.
    pub rotations: Vec<f64>,
    /// `512 x 512 x 3` standard normals.
    pub upstream_colour: Vec<f64>,
}

/// The camera of the standard scene.
pub fn standard_camera() -> Camera {
    Camera {
        width: SCENE_SIZE,
        height: SCENE_SIZE,
        intrinsics: Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 256.0,
            cy: 256.0,
        },
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
        distortion: [0.0; 5],
    }
}

/// Generates the standard scene with `count` Gaussians (see the module documentation).
pub fn standard_scene(count: usize, seed: u64) -> BenchmarkScene {
    let mut rng = SplitMix64::new(seed);
    let mut means = Vec::with_capacity(count * 3);
    let mut scales = Vec::with_capacity(count * 3);
    let mut rotations = Vec::with_capacity(count * 4);
    let mut opacities = Vec::with_capacity(count);
    let mut sh = Vec::with_capacity(count * 3);
    let (log_lo, log_hi) = (0.005_f64.ln(), 0.03_f64.ln());
    for _ in 0..count {
        means.push(rng.uniform(-1.0, 1.0));
        means.push(rng.uniform(-1.0, 1.0));
        means.push(rng.uniform(2.0, 4.0));
        for _ in 0..3 {
            scales.push(rng.uniform(log_lo, log_hi).exp());
        }
        let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        rotations.extend(q.map(|v| v / norm));
        opacities.push(rng.uniform(0.1, 0.9));
        for _ in 0..3 {
            sh.push((rng.next_f64() - 0.5) / SH_C0);
        }
    }
    let pixels = (SCENE_SIZE * SCENE_SIZE) as usize;
    let upstream_colour = (0..pixels * 3).map(|_| rng.normal()).collect();
    let covariances = covariance_from_scale_rotation(&scales, &rotations)
        .map(|out| out.covariances)
        .unwrap_or_default();
    BenchmarkScene {
        camera: standard_camera(),
        gaussians: GaussianBuffers {
            means,
            covariances,
            opacities,
            sh,
            sh_degree: 0,
        },
        scales,
        rotations,
        upstream_colour,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_is_deterministic_and_in_range() {
        let a = standard_scene(500, STANDARD_SEED);
        let b = standard_scene(500, STANDARD_SEED);
        assert_eq!(a.gaussians, b.gaussians);
        assert_eq!(a.gaussians.covariances.len(), 500 * 6);
        for m in a.gaussians.means.chunks(3) {
            assert!((-1.0..1.0).contains(&m[0]) && (-1.0..1.0).contains(&m[1]));
            assert!((2.0..4.0).contains(&m[2]));
        }
        assert!(a.scales.iter().all(|&s| (0.005..0.03).contains(&s)));
        assert!(
            a.gaussians
                .opacities
                .iter()
                .all(|&o| (0.1..0.9).contains(&o))
        );
        let colour_range = (-0.5 / SH_C0)..(0.5 / SH_C0);
        assert!(a.gaussians.sh.iter().all(|c| colour_range.contains(c)));
        let mean: f64 = a.upstream_colour.iter().sum::<f64>() / a.upstream_colour.len() as f64;
        let var: f64 =
            a.upstream_colour.iter().map(|v| v * v).sum::<f64>() / a.upstream_colour.len() as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.01,
            "normal draws: mean {mean}, var {var}"
        );
    }
}
