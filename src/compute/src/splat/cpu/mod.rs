//! The `cpu` splatting backend: plain Rust parallelised with rayon, generic over `f32`/`f64`.
//!
//! It is a production backend and the reference the `gpu` backend is tested against, so it
//! follows `src/compute/SPLATTING.md` literally. Per camera: project every Gaussian
//! (parallel over Gaussians), bin the visible ones into 16x16 tiles (one global depth sort,
//! then a stable counting scatter), composite each tile front to back (parallel over tile
//! rows). The backward pass walks the same lists back to front, writes one gradient per
//! Gaussian-tile intersection, then reduces them per Gaussian (parallel over Gaussians, in a
//! fixed order, so results are deterministic) and chains through the projection.
//! `f32` runs composite and walk tiles eight pixels at a time (`lanes.rs`, AVX2 or AVX-512VL
//! when the CPU has it); `f64` runs (gradient checks) use the generic per-pixel loops of
//! `raster.rs`. [`ForwardPhases`] and [`BackwardPhases`] time the phases.

mod lanes;
mod project;
mod raster;
mod tile;

#[cfg(test)]
mod tests;

use std::time::Instant;

use rayon::prelude::*;
use seqavatar_core::camera::Camera;

use self::project::{CameraParams, Cull, Splat2d, Splat2dGradient, TileRect};
use self::raster::{Binning, Compositing};
use self::tile::{PixelState, Upstream};
use super::{
    GaussianSet, ImageGradient, RasterOptions, RenderedImage, SplatDiagnostics, SplatError,
    SplatGradients, validate_call,
};
use crate::scalar::Scalar;

/// What one camera's forward pass keeps for the backward pass.
struct CameraState<S> {
    params: CameraParams<S>,
    /// Visible splats in depth order.
    splats: Vec<Splat2d<S>>,
    binning: Binning,
    pixels: PixelState<S>,
}

/// Result of [`forward`]: the images, per-camera diagnostics, and the state [`backward`]
/// needs.
pub struct CpuForward<S> {
    /// One per camera, in the order given.
    pub images: Vec<RenderedImage<S>>,
    /// One per camera.
    pub diagnostics: Vec<SplatDiagnostics>,
    states: Vec<CameraState<S>>,
    /// Wall time of each phase, summed over the cameras.
    pub phases: ForwardPhases,
    options: RasterOptions,
    gaussian_count: usize,
    sh_degree: u32,
}

/// Wall milliseconds of the phases of one [`forward`] call, summed over its cameras (for
/// profiling: `cargo bench -p seqavatar-compute --bench splat` prints them).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ForwardPhases {
    /// Projecting every Gaussian (parallel over Gaussians).
    pub project_ms: f64,
    /// The depth sort, the tile binning and the permutation of the splats.
    pub bin_ms: f64,
    /// Compositing the tiles (parallel over tile rows), image buffers included.
    pub composite_ms: f64,
}

/// Wall milliseconds of the phases of one [`backward_with_phases`] call, summed over the
/// cameras.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BackwardPhases {
    /// Validating the upstream gradients and allocating the outputs.
    pub check_ms: f64,
    /// The back-to-front walk of the tiles (one gradient per intersection).
    pub walk_ms: f64,
    /// Summing each Gaussian's intersection gradients and the projection's backward.
    pub reduce_ms: f64,
}

/// Milliseconds since `start`, and restarts it.
fn lap(start: &mut Instant) -> f64 {
    let now = Instant::now();
    let ms = (now - *start).as_secs_f64() * 1e3;
    *start = now;
    ms
}

/// Renders the Gaussians from every camera.
pub fn forward<S: Scalar>(
    gaussians: &GaussianSet<'_, S>,
    cameras: &[Camera],
    options: &RasterOptions,
) -> Result<CpuForward<S>, SplatError> {
    gaussians.validate()?;
    validate_call(cameras, options)?;
    let background = options.background.map(S::from_f64);
    let mut images = Vec::with_capacity(cameras.len());
    let mut diagnostics = Vec::with_capacity(cameras.len());
    let mut states = Vec::with_capacity(cameras.len());
    let mut phases = ForwardPhases::default();
    for camera in cameras {
        let mut clock = Instant::now();
        let params = CameraParams::<S>::new(camera);
        let (splats, rects, diag) = project_all(&params, gaussians);
        phases.project_ms += lap(&mut clock);
        let tiles = (params.tiles_x * params.tiles_y) as usize;
        let binning = raster::bin(&splats, &rects, tiles, params.tiles_x)?;
        let splats = raster::sort_splats(&splats, &binning);
        phases.bin_ms += lap(&mut clock);
        let buffers = raster::forward(
            &splats,
            fast_splats(&splats),
            &binning,
            Compositing {
                width: params.width,
                height: params.height,
                background,
                smooth: options.smooth_cutoff,
            },
        );
        phases.composite_ms += lap(&mut clock);
        images.push(RenderedImage {
            width: params.width,
            height: params.height,
            colour: buffers.colour,
            alpha: buffers.alpha,
            depth: buffers.depth,
        });
        diagnostics.push(SplatDiagnostics {
            intersections: binning.tile_gaussians.len(),
            ..diag
        });
        states.push(CameraState {
            params,
            splats,
            binning,
            pixels: buffers.pixels,
        });
    }
    Ok(CpuForward {
        images,
        diagnostics,
        states,
        phases,
        options: options.clone(),
        gaussian_count: gaussians.len(),
        sh_degree: gaussians.sh_degree,
    })
}

/// The splats as `f32` when the scalar type is `f32` (the speed path, on the best lanes
/// this CPU has), `None` for `f64` (the exact path gradient checks use). Takes the `Vec`
/// because the type test needs a `'static` sized type to downcast.
#[allow(clippy::ptr_arg)]
fn fast_splats<S: Scalar>(splats: &Vec<Splat2d<S>>) -> Option<lanes::LanePath<'_>> {
    (splats as &dyn std::any::Any)
        .downcast_ref::<Vec<Splat2d<f32>>>()
        .map(|splats| lanes::LanePath {
            splats,
            isa: lanes::isa(),
        })
}

/// Projects every Gaussian; culled ones get an empty tile rectangle.
fn project_all<S: Scalar>(
    params: &CameraParams<S>,
    gaussians: &GaussianSet<'_, S>,
) -> (Vec<Splat2d<S>>, Vec<TileRect>, SplatDiagnostics) {
    let n = gaussians.len();
    let mut splats = vec![Splat2d::default(); n];
    let mut rects = vec![TileRect::default(); n];
    let diag = splats
        .par_iter_mut()
        .zip(rects.par_iter_mut())
        .enumerate()
        .with_min_len(256)
        .fold(
            SplatDiagnostics::default,
            |mut diag, (index, (splat, rect))| {
                match project::project(params, gaussians, index) {
                    Ok((s, r)) => {
                        *splat = s;
                        *rect = r;
                        diag.visible += 1;
                    }
                    Err(Cull::NonFiniteInput) => diag.non_finite_inputs += 1,
                    Err(Cull::NonFiniteProjection) => diag.non_finite_projections += 1,
                    Err(Cull::Depth) => diag.culled_depth += 1,
                    Err(Cull::Covariance) => diag.culled_covariance += 1,
                    Err(Cull::Opacity) => diag.culled_opacity += 1,
                    Err(Cull::Offscreen) => diag.culled_offscreen += 1,
                }
                diag
            },
        )
        .reduce(SplatDiagnostics::default, |a, b| SplatDiagnostics {
            gaussians: 0,
            non_finite_inputs: a.non_finite_inputs + b.non_finite_inputs,
            non_finite_projections: a.non_finite_projections + b.non_finite_projections,
            culled_depth: a.culled_depth + b.culled_depth,
            culled_covariance: a.culled_covariance + b.culled_covariance,
            culled_opacity: a.culled_opacity + b.culled_opacity,
            culled_offscreen: a.culled_offscreen + b.culled_offscreen,
            visible: a.visible + b.visible,
            intersections: 0,
        });
    (
        splats,
        rects,
        SplatDiagnostics {
            gaussians: n,
            ..diag
        },
    )
}

/// Gradients of the loss with respect to the Gaussians, summed over the forward call's
/// cameras. `gaussians` must be the set passed to [`forward`]; `upstream` has one entry per
/// camera.
pub fn backward<S: Scalar>(
    forward: &CpuForward<S>,
    gaussians: &GaussianSet<'_, S>,
    upstream: &[ImageGradient<'_, S>],
) -> Result<SplatGradients<S>, SplatError> {
    backward_with_phases(forward, gaussians, upstream).map(|(gradients, _)| gradients)
}

/// [`backward`], also returning the wall time of its phases.
pub fn backward_with_phases<S: Scalar>(
    forward: &CpuForward<S>,
    gaussians: &GaussianSet<'_, S>,
    upstream: &[ImageGradient<'_, S>],
) -> Result<(SplatGradients<S>, BackwardPhases), SplatError> {
    let mut clock = Instant::now();
    let mut phases = BackwardPhases::default();
    gaussians.validate()?;
    if gaussians.len() != forward.gaussian_count || gaussians.sh_degree != forward.sh_degree {
        return Err(SplatError::GaussiansChanged {
            expected: forward.gaussian_count,
            actual: gaussians.len(),
        });
    }
    if upstream.len() != forward.states.len() {
        return Err(SplatError::GradientCount {
            expected: forward.states.len(),
            actual: upstream.len(),
        });
    }
    let checked: Vec<Upstream<'_, S>> = upstream
        .iter()
        .zip(&forward.states)
        .enumerate()
        .map(|(camera, (grad, state))| check_upstream(camera, grad, state))
        .collect::<Result<_, _>>()?;

    let n = gaussians.len();
    let k = gaussians.sh_coefficients();
    let mut out = SplatGradients::zeros(n, k);
    let background = forward.options.background.map(S::from_f64);
    phases.check_ms += lap(&mut clock);
    for (state, up) in forward.states.iter().zip(&checked) {
        let slots = raster::backward(
            &state.splats,
            fast_splats(&state.splats),
            &state.binning,
            &state.pixels,
            up,
            Compositing {
                width: state.params.width,
                height: state.params.height,
                background,
                smooth: forward.options.smooth_cutoff,
            },
        );
        phases.walk_ms += lap(&mut clock);
        let dropped = accumulate_camera(state, gaussians, &slots, &mut out);
        drop(slots);
        out.non_finite_gradients += dropped;
        phases.reduce_ms += lap(&mut clock);
    }
    Ok((out, phases))
}

/// Reduces one camera's intersection gradients per Gaussian, chains them through the
/// projection and adds them to `out`. Returns how many Gaussians' gradients were dropped.
fn accumulate_camera<S: Scalar>(
    state: &CameraState<S>,
    gaussians: &GaussianSet<'_, S>,
    slots: &[tile::Slot<S>],
    out: &mut SplatGradients<S>,
) -> usize {
    let k = gaussians.sh_coefficients();
    let binning = &state.binning;
    out.means
        .par_chunks_mut(3)
        .zip(out.covariances.par_chunks_mut(6))
        .zip(out.opacities.par_iter_mut())
        .zip(out.sh.par_chunks_mut(3 * k))
        .zip(out.mean_2d_norm.par_iter_mut())
        .enumerate()
        .with_min_len(256)
        .map(|(index, ((((d_mean, d_cov), d_opacity), d_sh), norm))| {
            let (begin, end) = (
                binning.gaussian_offsets[index] as usize,
                binning.gaussian_offsets[index + 1] as usize,
            );
            if begin == end {
                return 0;
            }
            let mut sum = [S::ZERO; 10];
            for &position in &binning.intersection_positions[begin..end] {
                for (acc, v) in sum.iter_mut().zip(&slots[position as usize]) {
                    *acc += *v;
                }
            }
            let grad = Splat2dGradient {
                mean: [sum[0], sum[1]],
                conic: [sum[2], sum[3], sum[4]],
                opacity: sum[5],
                colour: [sum[6], sum[7], sum[8]],
                depth: sum[9],
            };
            let Some(input) = project::project_backward(&state.params, gaussians, index, &grad)
            else {
                return 0;
            };
            let mean_norm = (grad.mean[0] * grad.mean[0] + grad.mean[1] * grad.mean[1]).sqrt();
            let finite = input
                .mean
                .iter()
                .chain(&input.covariance)
                .chain(&input.sh[..3 * k])
                .all(|v| v.is_finite())
                && input.opacity.is_finite()
                && mean_norm.is_finite();
            if !finite {
                return 1;
            }
            for (o, v) in d_mean.iter_mut().zip(&input.mean) {
                *o += *v;
            }
            for (o, v) in d_cov.iter_mut().zip(&input.covariance) {
                *o += *v;
            }
            *d_opacity += input.opacity;
            for (o, v) in d_sh.iter_mut().zip(&input.sh) {
                *o += *v;
            }
            *norm += mean_norm;
            0
        })
        .sum()
}

/// Checks the sizes and finiteness of one camera's upstream gradient.
fn check_upstream<'a, S: Scalar>(
    camera: usize,
    grad: &ImageGradient<'a, S>,
    state: &CameraState<S>,
) -> Result<Upstream<'a, S>, SplatError> {
    grad.check(
        camera,
        state.params.width as usize * state.params.height as usize,
    )?;
    Ok(Upstream {
        colour: grad.colour,
        alpha: grad.alpha,
        depth: grad.depth,
    })
}
