//! Splatting with f64 at the boundary, for the host path (called through
//! [`crate::device::AvatarBackend`]): it splats in f32 (inputs rounded once, outputs widened;
//! the lane-parallel speed path of `compute::splat::cpu`, about 4x the f64 generic one), so
//! the loss and everything around the splatting stays in f64. The f64 cpu splatting remains the oracle of the splatting's own gradient tests.

use anyhow::Context;
use seqavatar_compute::splat::{
    self, GaussianBuffers, ImageGradient, RasterOptions, RenderedImage, SplatGradients,
};
use seqavatar_core::camera::Camera;

/// One frame's Gaussians in world space, f64 (`sh`: `N x K x 3` for the active degree).
pub type WorldGaussians = GaussianBuffers<f64>;

/// A forward pass kept for its backward, with the f32 copy it splatted.
pub struct SplatPass {
    pub images: Vec<RenderedImage<f64>>,
    forward: splat::cpu::CpuForward<f32>,
    narrow: GaussianBuffers<f32>,
}

fn widen(image: &RenderedImage<f32>) -> RenderedImage<f64> {
    let w = |v: &[f32]| v.iter().map(|x| f64::from(*x)).collect::<Vec<f64>>();
    RenderedImage {
        width: image.width,
        height: image.height,
        colour: w(&image.colour),
        alpha: w(&image.alpha),
        depth: w(&image.depth),
    }
}

/// Renders `gaussians` from `cameras` on `cpu` in f32 on the lane path, from a rounded copy
/// kept for the backward pass (the `cpu` backend's
/// [`crate::device::AvatarBackend::splat_forward`]).
pub fn forward_cpu(
    gaussians: &WorldGaussians,
    cameras: &[Camera],
    options: &RasterOptions,
) -> anyhow::Result<SplatPass> {
    let narrow = gaussians.convert::<f32>();
    let f =
        splat::cpu::forward(&narrow.view(), cameras, options).context("splatting forward (cpu)")?;
    Ok(SplatPass {
        images: f.images.iter().map(widen).collect(),
        forward: f,
        narrow,
    })
}

/// Gradients with respect to the Gaussians given to [`forward_cpu`] (the pass keeps their
/// f32 copy).
pub fn backward_cpu(
    pass: &SplatPass,
    colour: &[Vec<f64>],
    alpha: &[Vec<f64>],
) -> anyhow::Result<SplatGradients<f64>> {
    let (c32, a32) = (narrow_planes(colour), narrow_planes(alpha));
    let g = splat::cpu::backward(
        &pass.forward,
        &pass.narrow.view(),
        &upstream_f32(&c32, &a32),
    )
    .context("splatting backward (cpu)")?;
    Ok(widen_gradients(g))
}

/// Per-camera f64 images rounded to f32.
fn narrow_planes(planes: &[Vec<f64>]) -> Vec<Vec<f32>> {
    planes
        .iter()
        .map(|p| p.iter().map(|x| *x as f32).collect())
        .collect()
}

/// Upstream gradients of colour and alpha per camera (no depth term).
fn upstream_f32<'a>(colour: &'a [Vec<f32>], alpha: &'a [Vec<f32>]) -> Vec<ImageGradient<'a, f32>> {
    colour
        .iter()
        .zip(alpha)
        .map(|(c, a)| ImageGradient {
            colour: c,
            alpha: Some(a),
            depth: None,
        })
        .collect()
}

fn widen_gradients(g: SplatGradients<f32>) -> SplatGradients<f64> {
    let w = |v: Vec<f32>| v.into_iter().map(f64::from).collect::<Vec<f64>>();
    SplatGradients {
        means: w(g.means),
        covariances: w(g.covariances),
        opacities: w(g.opacities),
        sh: w(g.sh),
        mean_2d_norm: w(g.mean_2d_norm),
        non_finite_gradients: g.non_finite_gradients,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_compute::splat::scene::{STANDARD_SEED, standard_scene};

    /// Relative distance `|a - b| / |b|` of two vectors.
    fn relative_error(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let diff: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        let norm: f64 = b.iter().map(|y| y * y).sum();
        (diff / norm.max(1e-300)).sqrt()
    }

    /// The `cpu` arm (f32 lanes on a rounded copy) against the f64 generic splatting of
    /// `compute` on the same scene: images within f32 rounding, and every gradient (the
    /// colour and the alpha upstream both feeding it) within 1e-3 of the f64 one.
    #[test]
    fn cpu_splatting_in_f32_matches_the_f64_splatting() {
        let scene = standard_scene(300, STANDARD_SEED);
        let g = &scene.gaussians;
        let world = WorldGaussians {
            means: g.means.clone(),
            covariances: g.covariances.clone(),
            opacities: g.opacities.clone(),
            sh: g.sh.clone(),
            sh_degree: g.sh_degree,
        };
        let cameras = std::slice::from_ref(&scene.camera);
        let options = RasterOptions {
            background: [0.2, 0.4, 0.6],
            smooth_cutoff: false,
        };
        let pass = forward_cpu(&world, cameras, &options).unwrap();
        let exact = splat::cpu::forward(&world.view(), cameras, &options).unwrap();
        let (ours, theirs) = (&pass.images[0], &exact.images[0]);
        for (name, a, b) in [
            ("colour", &ours.colour, &theirs.colour),
            ("alpha", &ours.alpha, &theirs.alpha),
        ] {
            let worst = a
                .iter()
                .zip(b.iter())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(worst < 1e-4, "{name}: largest difference {worst}");
        }
        assert!(
            theirs.alpha.iter().any(|&a| a > 0.5),
            "the scene covers pixels"
        );

        let colour = vec![scene.upstream_colour.clone()];
        // An alpha upstream unlike the colour one, so that dropping either would show.
        let alpha: Vec<Vec<f64>> = vec![
            scene
                .upstream_colour
                .chunks(3)
                .map(|c| c[1] - 0.5 * c[2])
                .collect(),
        ];
        let grads = backward_cpu(&pass, &colour, &alpha).unwrap();
        let upstream = [ImageGradient {
            colour: &colour[0],
            alpha: Some(&alpha[0]),
            depth: None,
        }];
        let reference = splat::cpu::backward(&exact, &world.view(), &upstream).unwrap();
        for (name, a, b) in [
            ("means", &grads.means, &reference.means),
            ("covariances", &grads.covariances, &reference.covariances),
            ("opacities", &grads.opacities, &reference.opacities),
            ("sh", &grads.sh, &reference.sh),
            ("mean_2d_norm", &grads.mean_2d_norm, &reference.mean_2d_norm),
        ] {
            let error = relative_error(a, b);
            assert!(error < 1e-3, "{name}: relative error {error}");
        }
        // Without the alpha upstream the opacity gradient moves well beyond that tolerance.
        let no_alpha = [ImageGradient {
            colour: &colour[0],
            alpha: None,
            depth: None,
        }];
        let colour_only = splat::cpu::backward(&exact, &world.view(), &no_alpha).unwrap();
        assert!(relative_error(&colour_only.opacities, &reference.opacities) > 1e-2);
    }
}
