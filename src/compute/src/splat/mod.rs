//! Differentiable Gaussian splatting: the operation's types, shared by the `cpu` and `gpu`
//! backends, which both implement the contract in `src/compute/SPLATTING.md`.
//!
//! One call renders one frame's Gaussians from one or more cameras:
//!
//! ```text
//! cpu::forward(&gaussians, &cameras, &options) -> CpuForward { images, diagnostics, .. }
//! cpu::backward(&forward, &gaussians, &upstream) -> SplatGradients (summed over cameras)
//! ```
//!
//! Gaussians come as flat row-major slices ([`GaussianSet`]); covariances are built by the
//! [`covariance`] op from scales and rotations; [`scene`] is the seeded benchmark scene
//! documented in `rasterizer.md`.

pub mod covariance;
pub mod cpu;
pub mod gpu;
pub mod scene;
pub mod sh;

use seqavatar_core::camera::{Camera, CameraError};

use crate::scalar::Scalar;

/// Side of the square screen tiles Gaussians are binned into, in pixels.
pub const TILE_SIZE: u32 = 16;
/// Gaussians nearer than this (camera z, metres) are culled.
pub const NEAR_PLANE: f64 = 0.01;
/// Gaussians farther than this (camera z, metres) are culled.
pub const FAR_PLANE: f64 = 1e10;
/// Variance (px^2) added to the diagonal of every projected covariance (anti-aliasing blur).
pub const BLUR_VARIANCE: f64 = 0.3;
/// The guard band widens the clamp of `x/z`, `y/z` by this fraction of the field of view.
pub const GUARD_BAND: f64 = 0.3;
/// Alphas below this are skipped; opacities below it are culled.
pub const ALPHA_THRESHOLD: f64 = 1.0 / 255.0;
/// Alphas are clamped to at most this.
pub const MAX_ALPHA: f64 = 0.99;
/// A pixel stops before the Gaussian that would bring its transmittance to this or below.
pub const MIN_TRANSMITTANCE: f64 = 1e-4;
/// Upper bound of the opacity-aware extent, in standard deviations.
pub const MAX_EXTENT_SIGMAS: f64 = 3.33;
/// Highest supported spherical-harmonics degree.
pub const MAX_SH_DEGREE: u32 = 3;

/// Number of SH coefficients per colour channel for a degree: `(degree + 1)^2`.
pub const fn sh_coefficient_count(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// One frame's Gaussians as flat row-major slices (`N` Gaussians).
#[derive(Clone, Copy, Debug)]
pub struct GaussianSet<'a, S> {
    /// `N x 3` world-space centres (metres).
    pub means: &'a [S],
    /// `N x 6` upper triangle `(xx, xy, xz, yy, yz, zz)` of the world-space covariance.
    pub covariances: &'a [S],
    /// `N` activated opacities in `[0, 1]`.
    pub opacities: &'a [S],
    /// `N x K x 3` SH coefficients, `K = (sh_degree + 1)^2`, coefficient-major per Gaussian.
    pub sh: &'a [S],
    /// SH degree, `0..=3`.
    pub sh_degree: u32,
}

impl<S: Scalar> GaussianSet<'_, S> {
    /// Number of Gaussians (the length of `opacities`).
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// SH coefficients per colour channel.
    pub fn sh_coefficients(&self) -> usize {
        sh_coefficient_count(self.sh_degree)
    }

    /// Checks the degree and that every slice has the length `N` implies.
    pub fn validate(&self) -> Result<(), SplatError> {
        let n = self.len();
        check_degree_and_count(self.sh_degree, n)?;
        check_len("means", self.means.len(), n * 3)?;
        check_len("covariances", self.covariances.len(), n * 6)?;
        check_len("sh", self.sh.len(), n * self.sh_coefficients() * 3)?;
        Ok(())
    }
}

/// Owned storage for a [`GaussianSet`] (scenes, tests, benchmarks).
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianBuffers<S> {
    pub means: Vec<S>,
    pub covariances: Vec<S>,
    pub opacities: Vec<S>,
    pub sh: Vec<S>,
    pub sh_degree: u32,
}

impl<S: Scalar> GaussianBuffers<S> {
    /// Borrows the buffers as the operation's input.
    pub fn view(&self) -> GaussianSet<'_, S> {
        GaussianSet {
            means: &self.means,
            covariances: &self.covariances,
            opacities: &self.opacities,
            sh: &self.sh,
            sh_degree: self.sh_degree,
        }
    }

    /// The same values in another precision.
    pub fn convert<T: Scalar>(&self) -> GaussianBuffers<T> {
        let cast = |v: &[S]| v.iter().map(|x| T::from_f64(x.to_f64())).collect();
        GaussianBuffers {
            means: cast(&self.means),
            covariances: cast(&self.covariances),
            opacities: cast(&self.opacities),
            sh: cast(&self.sh),
            sh_degree: self.sh_degree,
        }
    }
}

/// The SH degree is supported and the count fits the 32-bit indices (with room to spare).
pub(crate) fn check_degree_and_count(sh_degree: u32, count: usize) -> Result<(), SplatError> {
    if sh_degree > MAX_SH_DEGREE {
        return Err(SplatError::ShDegree { degree: sh_degree });
    }
    if count > u32::MAX as usize / 2 {
        return Err(SplatError::TooManyGaussians { count });
    }
    Ok(())
}

pub(crate) fn check_len(
    field: &'static str,
    actual: usize,
    expected: usize,
) -> Result<(), SplatError> {
    if actual == expected {
        Ok(())
    } else {
        Err(SplatError::Length {
            field,
            expected,
            actual,
        })
    }
}

/// Rendering options shared by forward and backward.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RasterOptions {
    /// Linear RGB composited behind the Gaussians (`colour + T * background`).
    pub background: [f64; 3],
    /// Tests only: replace the hard `alpha < 1/255` cutoff with Brush's C1 cutoff so central
    /// finite differences are meaningful (see SPLATTING.md).
    pub smooth_cutoff: bool,
}

/// The rendered outputs of one camera.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedImage<S> {
    pub width: u32,
    pub height: u32,
    /// `H x W x 3` linear RGB, background included.
    pub colour: Vec<S>,
    /// `H x W` accumulated alpha `1 - T` (the mask the loss compares).
    pub alpha: Vec<S>,
    /// `H x W` expected depth `sum alpha_i T_i z_i` (not normalised by alpha).
    pub depth: Vec<S>,
}

/// What a forward call did with the Gaussians of one camera. Counts are of Gaussians, except
/// `intersections` (Gaussian-tile pairs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SplatDiagnostics {
    /// Gaussians in the input.
    pub gaussians: usize,
    /// Gaussians with a NaN or infinite mean, covariance, opacity or SH coefficient (culled).
    pub non_finite_inputs: usize,
    /// Gaussians whose projected values overflowed (conic, radius, colour; culled).
    pub non_finite_projections: usize,
    /// Culled by the near or far plane.
    pub culled_depth: usize,
    /// Culled because the projected covariance is not positive definite.
    pub culled_covariance: usize,
    /// Culled because the opacity is below `1/255`.
    pub culled_opacity: usize,
    /// Culled because the screen box misses the image or has zero radius.
    pub culled_offscreen: usize,
    /// Gaussians that reached the rasteriser.
    pub visible: usize,
    /// Gaussian-tile pairs sorted and composited.
    pub intersections: usize,
}

/// Upstream gradient of the loss with respect to one camera's rendered outputs.
#[derive(Clone, Copy, Debug)]
pub struct ImageGradient<'a, S> {
    /// `H x W x 3`, gradient with respect to `RenderedImage::colour`.
    pub colour: &'a [S],
    /// `H x W`, gradient with respect to `RenderedImage::alpha`, if the loss uses it.
    pub alpha: Option<&'a [S]>,
    /// `H x W`, gradient with respect to `RenderedImage::depth`, if the loss uses it.
    pub depth: Option<&'a [S]>,
}

impl<S: Scalar> ImageGradient<'_, S> {
    /// Checks the sizes and finiteness of camera `camera`'s upstream gradient of an image of
    /// `pixels` pixels.
    pub(crate) fn check(&self, camera: usize, pixels: usize) -> Result<(), SplatError> {
        use rayon::prelude::*;
        let check = |field: &'static str, values: &[S], expected: usize| {
            check_len(field, values.len(), expected)?;
            // Parallel over chunks, each a branch-free (vectorised) test; the first bad index
            // wins, so the error does not depend on the scheduling.
            const CHUNK: usize = 1 << 14;
            let first_bad = values
                .par_chunks(CHUNK)
                .position_first(|chunk| !chunk.iter().fold(true, |ok, v| ok & v.is_finite()))
                .and_then(|k| {
                    let chunk = &values[k * CHUNK..values.len().min((k + 1) * CHUNK)];
                    chunk
                        .iter()
                        .position(|v| !v.is_finite())
                        .map(|i| k * CHUNK + i)
                });
            match first_bad {
                Some(index) => Err(SplatError::NonFiniteGradient {
                    camera,
                    field,
                    index,
                }),
                None => Ok(()),
            }
        };
        check("colour", self.colour, pixels * 3)?;
        if let Some(alpha) = self.alpha {
            check("alpha", alpha, pixels)?;
        }
        if let Some(depth) = self.depth {
            check("depth", depth, pixels)?;
        }
        Ok(())
    }
}

/// Gradients of the loss, summed over the cameras of a call, in the input layouts.
#[derive(Clone, Debug, PartialEq)]
pub struct SplatGradients<S> {
    /// `N x 3`.
    pub means: Vec<S>,
    /// `N x 6`; an off-diagonal entry's gradient counts both `(i, j)` and `(j, i)`.
    pub covariances: Vec<S>,
    /// `N`.
    pub opacities: Vec<S>,
    /// `N x K x 3`.
    pub sh: Vec<S>,
    /// `N`: per camera the norm of the gradient with respect to the 2D mean (pixels), summed
    /// over cameras (the densification statistic).
    pub mean_2d_norm: Vec<S>,
    /// Gaussians whose gradient overflowed in some camera; their gradient from that camera
    /// was dropped (set to zero) so that nothing non-finite leaves the operation.
    pub non_finite_gradients: usize,
}

impl<S: Scalar> SplatGradients<S> {
    /// All-zero gradients for `n` Gaussians with `k` SH coefficients per channel.
    pub fn zeros(n: usize, k: usize) -> Self {
        Self {
            means: vec![S::ZERO; n * 3],
            covariances: vec![S::ZERO; n * 6],
            opacities: vec![S::ZERO; n],
            sh: vec![S::ZERO; n * k * 3],
            mean_2d_norm: vec![S::ZERO; n],
            non_finite_gradients: 0,
        }
    }
}

/// Structurally wrong input to a splatting operation.
#[derive(Debug, thiserror::Error)]
pub enum SplatError {
    #[error("`{field}` has {actual} values, expected {expected}")]
    Length {
        field: &'static str,
        expected: usize,
        actual: usize,
    },
    #[error("SH degree {degree} is not supported (0..=3)")]
    ShDegree { degree: u32 },
    #[error("too many Gaussians ({count})")]
    TooManyGaussians { count: usize },
    #[error("too many Gaussian-tile intersections ({count}) for 32-bit indices")]
    TooManyIntersections { count: usize },
    #[error("no cameras given")]
    NoCameras,
    // Causes are in the messages, so they are not also `source`s (chains would repeat them).
    #[error("camera {index} is invalid: {error}")]
    Camera { index: usize, error: CameraError },
    #[error("image of camera {index} is too large ({width}x{height})")]
    ImageTooLarge {
        index: usize,
        width: u32,
        height: u32,
    },
    #[error("background colour component {value} is not finite")]
    Background { value: f64 },
    #[error("{actual} upstream gradients given for {expected} cameras")]
    GradientCount { expected: usize, actual: usize },
    #[error("upstream gradient `{field}` of camera {camera} is not finite at index {index}")]
    NonFiniteGradient {
        camera: usize,
        field: &'static str,
        index: usize,
    },
    #[error(
        "the Gaussians passed to backward ({actual}) are not those of the forward pass ({expected})"
    )]
    GaussiansChanged { expected: usize, actual: usize },
}

/// Checks cameras and options once, before any work.
pub(crate) fn validate_call(cameras: &[Camera], options: &RasterOptions) -> Result<(), SplatError> {
    if cameras.is_empty() {
        return Err(SplatError::NoCameras);
    }
    for (index, camera) in cameras.iter().enumerate() {
        camera
            .validate()
            .map_err(|error| SplatError::Camera { index, error })?;
        // Pixel indices are u32 and tile keys hold the tile index in 32 bits.
        let pixels = u64::from(camera.width) * u64::from(camera.height);
        if pixels > u64::from(u32::MAX / 4) {
            return Err(SplatError::ImageTooLarge {
                index,
                width: camera.width,
                height: camera.height,
            });
        }
    }
    if let Some(&value) = options.background.iter().find(|v| !v.is_finite()) {
        return Err(SplatError::Background { value });
    }
    Ok(())
}
