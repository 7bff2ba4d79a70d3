//! The `gpu` splatting backend: the contract of `src/compute/SPLATTING.md` as WGSL kernels
//! (`shaders/splat_*.wgsl`) run through wgpu.
//!
//! Per call the Gaussians are uploaded once and stay resident for forward and backward. Per
//! camera: `project_forward` (one thread per Gaussian), a GPU radix sort of the visible
//! Gaussians by depth, per-Gaussian tile counts in depth order, a prefix scan, pair emission,
//! a stable GPU radix sort of the pairs by tile (so each tile's list stays in depth order, ties
//! by Gaussian index), tile ranges, then `rasterize_forward` (one 16x16 workgroup per tile).
//! The only host round trip is the 4-byte pair count needed to size the pair buffers. When the
//! pairs of a camera do not fit one storage binding, the image is split into bands of tile
//! rows that are binned and composited one after another. Backward walks the same lists back
//! to front and adds per-Gaussian screen-space gradients with f32 atomics (native, or a
//! compare-exchange fallback), then `project_backward` chains them to the inputs.

use std::borrow::Cow;

use seqavatar_core::camera::Camera;

use super::{
    GaussianSet, ImageGradient, RasterOptions, RenderedImage, SplatDiagnostics, SplatError,
    SplatGradients, TILE_SIZE, validate_call,
};
use crate::backend::primitives::{exclusive_scan, radix_sort};
use crate::backend::shaders::{AtomicAdd, with_atomic_add};
use crate::backend::{BackendError, GpuBuffer, GpuContext, KernelSource};

const PROJECT_WGSL: &str = include_str!("../../../../../shaders/splat_project.wgsl");
const BIN_WGSL: &str = include_str!("../../../../../shaders/splat_bin.wgsl");
const RASTERIZE_WGSL: &str = include_str!("../../../../../shaders/splat_rasterize.wgsl");
const RASTERIZE_BACKWARD_WGSL: &str =
    include_str!("../../../../../shaders/splat_rasterize_backward.wgsl");

/// Threads per workgroup of the one-thread-per-item kernels.
const GROUP: u32 = 256;
/// Screen-space gradient values per Gaussian: mean (2), conic (3), opacity, colour (3), depth.
const SCREEN_GRADIENTS: usize = 10;
/// Diagnostics counters written by the projection kernels (see `splat_project.wgsl`).
const DIAGNOSTICS: usize = 8;

/// A gpu splatting call failed: bad input, or the GPU could not do the work.
#[derive(Debug, thiserror::Error)]
pub enum GpuSplatError {
    #[error(transparent)]
    Splat(#[from] SplatError),
    #[error(transparent)]
    Backend(#[from] BackendError),
}

/// Knobs of the gpu backend that do not change results.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GpuOptions {
    /// How the backward pass adds gradients; `None` picks native f32 atomics when the adapter
    /// has them. Tests force [`AtomicAdd::CompareExchange`] to cover the fallback.
    pub atomic_add: Option<AtomicAdd>,
    /// Caps the Gaussian-tile pairs of one band below the binding-size limit (tests use it to
    /// exercise band splitting on small scenes).
    pub max_pairs_per_band: Option<u32>,
}

/// The camera uniform shared by every splat kernel (`SplatCamera` in
/// `shaders/splat_types.wgsl`, which they include).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CameraUniform {
    rotation: [[f32; 4]; 3],
    intrinsics: [f32; 4],
    center: [f32; 4],
    background: [f32; 4],
    image: [u32; 4],
    counts: [u32; 4],
    flags: [u32; 4],
}

/// `BinParams` in `splat_bin.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct BinParams {
    gaussians: u32,
    pairs: u32,
    tiles_x: u32,
    row_begin: u32,
    row_end: u32,
    pad: [u32; 3],
}

/// This module's uniform structs for the layout test in `backend::shaders`.
#[cfg(test)]
pub(crate) fn wgsl_twins() -> Vec<crate::backend::shaders::WgslTwin> {
    use crate::backend::shaders::wgsl_twin;
    vec![
        wgsl_twin!(CameraUniform as "SplatCamera" in [
            "splat_project.wgsl",
            "splat_rasterize.wgsl",
            "splat_rasterize_backward.wgsl",
        ] {
            "rotation0" => rotation[0],
            "rotation1" => rotation[1],
            "rotation2" => rotation[2],
            "intrinsics" => intrinsics,
            "center" => center,
            "background" => background,
            "image" => image,
            "counts" => counts,
            "flags" => flags,
        }),
        wgsl_twin!(BinParams as "BinParams" in ["splat_bin.wgsl"] {
            "gaussians" => gaussians,
            "pairs" => pairs,
            "tiles_x" => tiles_x,
            "row_begin" => row_begin,
            "row_end" => row_end,
            "_pad0" => pad[0],
            "_pad1" => pad[1],
            "_pad2" => pad[2],
        }),
    ]
}

fn tiles(camera: &Camera) -> (u32, u32) {
    (
        camera.width.div_ceil(TILE_SIZE),
        camera.height.div_ceil(TILE_SIZE),
    )
}

#[allow(clippy::too_many_arguments)]
fn camera_uniform(
    camera: &Camera,
    gaussians: u32,
    sh_coefficients: u32,
    rows: (u32, u32),
    options: &RasterOptions,
    has_alpha_gradient: bool,
    has_depth_gradient: bool,
) -> CameraUniform {
    let r = camera.rotation;
    let t = camera.translation;
    let row = |i: usize| {
        [
            r.col(0)[i] as f32,
            r.col(1)[i] as f32,
            r.col(2)[i] as f32,
            t[i] as f32,
        ]
    };
    let intr = camera.intrinsics;
    let centre = camera.center();
    let (tiles_x, tiles_y) = tiles(camera);
    CameraUniform {
        rotation: [row(0), row(1), row(2)],
        intrinsics: [
            intr.fx as f32,
            intr.fy as f32,
            intr.cx as f32,
            intr.cy as f32,
        ],
        center: [centre.x as f32, centre.y as f32, centre.z as f32, 0.0],
        background: [
            options.background[0] as f32,
            options.background[1] as f32,
            options.background[2] as f32,
            0.0,
        ],
        image: [camera.width, camera.height, tiles_x, tiles_y],
        counts: [gaussians, sh_coefficients, rows.0, rows.1],
        flags: [
            u32::from(options.smooth_cutoff),
            u32::from(has_alpha_gradient),
            u32::from(has_depth_gradient),
            0,
        ],
    }
}

fn kernel_source(
    name: &'static str,
    wgsl: &'static str,
    entry_point: &'static str,
) -> KernelSource {
    KernelSource {
        name,
        wgsl: Cow::Borrowed(wgsl),
        entry_point,
    }
}

/// The Gaussians of one call, resident on the GPU.
pub struct ResidentGaussians {
    means: GpuBuffer,
    covariances: GpuBuffer,
    opacities: GpuBuffer,
    sh: GpuBuffer,
    count: u32,
    sh_degree: u32,
    sh_coefficients: u32,
}

impl ResidentGaussians {
    /// Validates and uploads the Gaussians.
    pub fn upload(
        context: &GpuContext,
        gaussians: &GaussianSet<'_, f32>,
    ) -> Result<Self, GpuSplatError> {
        gaussians.validate()?;
        let count = u32::try_from(gaussians.len()).map_err(|_| SplatError::TooManyGaussians {
            count: gaussians.len(),
        })?;
        Ok(Self {
            means: context.upload("means", gaussians.means)?,
            covariances: context.upload("covariances", gaussians.covariances)?,
            opacities: context.upload("opacities", gaussians.opacities)?,
            sh: context.upload("sh", gaussians.sh)?,
            count,
            sh_degree: gaussians.sh_degree,
            sh_coefficients: gaussians.sh_coefficients() as u32,
        })
    }

    pub fn len(&self) -> usize {
        self.count as usize
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }
}

/// The Gaussian-tile pairs of one band of tile rows, sorted by tile then depth.
struct Band {
    rows: (u32, u32),
    pair_gaussians: GpuBuffer,
    pairs: u32,
}

/// What one camera's forward pass keeps on the GPU for the image download and backward.
struct CameraState {
    camera: Camera,
    projected: GpuBuffer,
    ranges: GpuBuffer,
    bands: Vec<Band>,
    colour: GpuBuffer,
    alpha: GpuBuffer,
    depth: GpuBuffer,
    transmittance: GpuBuffer,
    contributors: GpuBuffer,
    diagnostics: GpuBuffer,
    intersections: u64,
}

/// Result of [`forward`]: images and diagnostics per camera, and the GPU state [`backward`]
/// needs (the Gaussians stay resident).
pub struct GpuForward {
    /// One per camera, in the order given.
    pub images: Vec<RenderedImage<f32>>,
    /// One per camera.
    pub diagnostics: Vec<SplatDiagnostics>,
    resident: ResidentForward,
}

/// A forward pass whose outputs are still on the GPU (the benchmark times this part).
pub struct ResidentForward {
    gaussians: ResidentGaussians,
    states: Vec<CameraState>,
    options: RasterOptions,
    gpu_options: GpuOptions,
}

/// Renders the Gaussians from every camera on the GPU.
pub fn forward(
    context: &GpuContext,
    gaussians: &GaussianSet<'_, f32>,
    cameras: &[Camera],
    options: &RasterOptions,
) -> Result<GpuForward, GpuSplatError> {
    forward_with(context, gaussians, cameras, options, GpuOptions::default())
}

/// [`forward`] with gpu-specific options.
pub fn forward_with(
    context: &GpuContext,
    gaussians: &GaussianSet<'_, f32>,
    cameras: &[Camera],
    options: &RasterOptions,
    gpu_options: GpuOptions,
) -> Result<GpuForward, GpuSplatError> {
    validate_call(cameras, options)?;
    let buffers = ResidentGaussians::upload(context, gaussians)?;
    let resident = forward_resident(context, buffers, cameras, options, gpu_options)?;
    let (images, diagnostics) = resident.download(context)?;
    Ok(GpuForward {
        images,
        diagnostics,
        resident,
    })
}

/// Runs the forward kernels for every camera, leaving the outputs on the GPU.
pub fn forward_resident(
    context: &GpuContext,
    gaussians: ResidentGaussians,
    cameras: &[Camera],
    options: &RasterOptions,
    gpu_options: GpuOptions,
) -> Result<ResidentForward, GpuSplatError> {
    validate_call(cameras, options)?;
    let states = cameras
        .iter()
        .map(|camera| forward_camera(context, &gaussians, camera, options, gpu_options))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(ResidentForward {
        gaussians,
        states,
        options: options.clone(),
        gpu_options,
    })
}

fn forward_camera(
    context: &GpuContext,
    gaussians: &ResidentGaussians,
    camera: &Camera,
    options: &RasterOptions,
    gpu_options: GpuOptions,
) -> Result<CameraState, GpuSplatError> {
    let n = gaussians.count;
    let (tiles_x, tiles_y) = tiles(camera);
    // Tile kernels run on a tiles_x by tiles_y grid of workgroups.
    let max_grid = context.max_workgroups_per_dimension();
    if tiles_x > max_grid || tiles_y > max_grid {
        return Err(BackendError::Gpu {
            message: format!(
                "image {}x{} has more than {max_grid} tiles along one side",
                camera.width, camera.height
            ),
        }
        .into());
    }
    let pixels = camera.width as usize * camera.height as usize;
    let uniform = camera_uniform(
        camera,
        n,
        gaussians.sh_coefficients,
        (0, tiles_y),
        options,
        false,
        false,
    );
    let camera_buffer = context.uniform("splat camera", &uniform);
    let projected = context.zeros("projected", n as usize * 3, 16)?;
    let rects = context.zeros("tile rects", n as usize, 16)?;
    let depth_keys = context.zeros("depth keys", n as usize, 4)?;
    let indices = context.zeros("depth order", n as usize, 4)?;
    let diagnostics = context.zeros("diagnostics", DIAGNOSTICS, 4)?;

    let project = context.kernel(&kernel_source(
        "project_forward",
        PROJECT_WGSL,
        "project_forward",
    ))?;
    let mut encoder = context.encoder();
    context.dispatch(
        &mut encoder,
        &project,
        &[
            (0, &camera_buffer),
            (1, &gaussians.means.buffer),
            (2, &gaussians.covariances.buffer),
            (3, &gaussians.opacities.buffer),
            (4, &gaussians.sh.buffer),
            (5, &projected.buffer),
            (6, &rects.buffer),
            (7, &depth_keys.buffer),
            (8, &indices.buffer),
            (9, &diagnostics.buffer),
        ],
        n.div_ceil(GROUP),
    );
    // Stable sort by depth: culled Gaussians carry the largest key and sort last; ties keep
    // index order because the values start as 0..N.
    let (_, sorted_indices) = radix_sort(context, &mut encoder, depth_keys, indices, n, 32)?;

    let ranges = context.zeros("tile ranges", (tiles_x * tiles_y) as usize, 8)?;
    let max_pairs = gpu_options
        .max_pairs_per_band
        .map_or(u64::MAX, u64::from)
        .min(context.max_binding_bytes() / 4)
        .min(u64::from(u32::MAX));
    let mut bands = Vec::new();
    let mut pending = vec![(0, tiles_y)];
    let mut intersections = 0_u64;
    let counts = context.zeros("tile counts", n as usize, 4)?;
    let count_kernel = context.kernel(&kernel_source("count_tiles", BIN_WGSL, "count_tiles"))?;
    let emit_kernel = context.kernel(&kernel_source("emit_pairs", BIN_WGSL, "emit_pairs"))?;
    let ranges_kernel = context.kernel(&kernel_source("tile_ranges", BIN_WGSL, "tile_ranges"))?;
    while let Some(rows) = pending.pop() {
        let count_params = context.uniform(
            "bin params",
            &BinParams {
                gaussians: n,
                pairs: 0,
                tiles_x,
                row_begin: rows.0,
                row_end: rows.1,
                pad: [0; 3],
            },
        );
        context.dispatch(
            &mut encoder,
            &count_kernel,
            &[
                (0, &count_params),
                (1, &sorted_indices.buffer),
                (2, &rects.buffer),
                (3, &counts.buffer),
            ],
            n.div_ceil(GROUP),
        );
        let total = exclusive_scan(context, &mut encoder, &counts.buffer, n)?;
        let finished = std::mem::replace(&mut encoder, context.encoder());
        // The one host round trip: the pair count sizes the pair buffers.
        let pairs = u64::from(context.download::<u32>(finished, &total.buffer, 1)?[0]);
        if pairs > max_pairs {
            if rows.1 - rows.0 <= 1 {
                return Err(BackendError::BufferTooLarge {
                    what: format!("Gaussian-tile pairs of tile row {}", rows.0),
                    bytes: pairs * 4,
                    limit: max_pairs * 4,
                }
                .into());
            }
            let middle = rows.0 + (rows.1 - rows.0) / 2;
            // Popped in order: the upper half first.
            pending.push((middle, rows.1));
            pending.push((rows.0, middle));
            continue;
        }
        let pairs = pairs as u32;
        intersections += u64::from(pairs);
        let keys = context.zeros("pair tiles", pairs as usize, 4)?;
        let pair_gaussians = context.zeros("pair gaussians", pairs as usize, 4)?;
        let params = context.uniform(
            "bin params",
            &BinParams {
                gaussians: n,
                pairs,
                tiles_x,
                row_begin: rows.0,
                row_end: rows.1,
                pad: [0; 3],
            },
        );
        context.dispatch(
            &mut encoder,
            &emit_kernel,
            &[
                (0, &params),
                (1, &sorted_indices.buffer),
                (2, &rects.buffer),
                (3, &counts.buffer),
                (4, &keys.buffer),
                (5, &pair_gaussians.buffer),
            ],
            n.div_ceil(GROUP),
        );
        let tile_bits = 32 - (tiles_x * tiles_y).saturating_sub(1).leading_zeros();
        let (keys, pair_gaussians) = radix_sort(
            context,
            &mut encoder,
            keys,
            pair_gaussians,
            pairs,
            tile_bits,
        )?;
        context.dispatch(
            &mut encoder,
            &ranges_kernel,
            &[(0, &params), (4, &keys.buffer), (6, &ranges.buffer)],
            pairs.div_ceil(GROUP),
        );
        bands.push(Band {
            rows,
            pair_gaussians,
            pairs,
        });
    }

    let colour = context.zeros("colour", pixels * 3, 4)?;
    let alpha = context.zeros("alpha", pixels, 4)?;
    let depth = context.zeros("depth", pixels, 4)?;
    let transmittance = context.zeros("final transmittance", pixels, 4)?;
    let contributors = context.zeros("contributors", pixels, 4)?;
    let rasterize = context.kernel(&kernel_source(
        "rasterize_forward",
        RASTERIZE_WGSL,
        "rasterize_forward",
    ))?;
    for band in &bands {
        let band_uniform = context.uniform(
            "splat camera band",
            &camera_uniform(
                camera,
                n,
                gaussians.sh_coefficients,
                band.rows,
                options,
                false,
                false,
            ),
        );
        context.dispatch_grid(
            &mut encoder,
            &rasterize,
            &[
                (0, &band_uniform),
                (1, &ranges.buffer),
                (2, &band.pair_gaussians.buffer),
                (3, &projected.buffer),
                (4, &colour.buffer),
                (5, &alpha.buffer),
                (6, &depth.buffer),
                (7, &transmittance.buffer),
                (8, &contributors.buffer),
            ],
            tiles_x,
            band.rows.1 - band.rows.0,
        );
    }
    context.submit_and_wait(encoder)?;
    Ok(CameraState {
        camera: camera.clone(),
        projected,
        ranges,
        bands,
        colour,
        alpha,
        depth,
        transmittance,
        contributors,
        diagnostics,
        intersections,
    })
}

impl ResidentForward {
    /// Per camera, the number of bands of tile rows its pairs were binned in.
    pub fn band_counts(&self) -> Vec<usize> {
        self.states.iter().map(|state| state.bands.len()).collect()
    }

    /// Copies every camera's images and diagnostics to the host.
    pub fn download(
        &self,
        context: &GpuContext,
    ) -> Result<(Vec<RenderedImage<f32>>, Vec<SplatDiagnostics>), GpuSplatError> {
        let mut images = Vec::with_capacity(self.states.len());
        let mut diagnostics = Vec::with_capacity(self.states.len());
        for state in &self.states {
            let mut encoder = context.encoder();
            let mut floats = context.download_many::<f32>(
                &mut encoder,
                &[
                    (&state.colour.buffer, state.colour.len),
                    (&state.alpha.buffer, state.alpha.len),
                    (&state.depth.buffer, state.depth.len),
                ],
            )?;
            let mut counters = context
                .download_many::<u32>(&mut encoder, &[(&state.diagnostics.buffer, DIAGNOSTICS)])?;
            context.finish_downloads(encoder, &mut floats)?;
            context.finish_downloads(context.encoder(), &mut counters)?;
            let [colour, alpha, depth] = [0, 1, 2].map(|i| std::mem::take(&mut floats[i].values));
            images.push(RenderedImage {
                width: state.camera.width,
                height: state.camera.height,
                colour,
                alpha,
                depth,
            });
            let c = &counters[0].values;
            diagnostics.push(SplatDiagnostics {
                gaussians: self.gaussians.len(),
                non_finite_inputs: c[0] as usize,
                non_finite_projections: c[1] as usize,
                culled_depth: c[2] as usize,
                culled_covariance: c[3] as usize,
                culled_opacity: c[4] as usize,
                culled_offscreen: c[5] as usize,
                visible: c[6] as usize,
                intersections: state.intersections as usize,
            });
        }
        Ok((images, diagnostics))
    }
}

/// Gradients of the loss with respect to the Gaussians, summed over the forward call's
/// cameras. `gaussians` must be the set passed to [`forward`].
pub fn backward(
    context: &GpuContext,
    forward: &GpuForward,
    gaussians: &GaussianSet<'_, f32>,
    upstream: &[ImageGradient<'_, f32>],
) -> Result<SplatGradients<f32>, GpuSplatError> {
    gaussians.validate()?;
    let resident = &forward.resident;
    if gaussians.len() != resident.gaussians.len()
        || gaussians.sh_degree != resident.gaussians.sh_degree
    {
        return Err(SplatError::GaussiansChanged {
            expected: resident.gaussians.len(),
            actual: gaussians.len(),
        }
        .into());
    }
    let upstream = ResidentImageGradient::upload_all(context, resident, upstream)?;
    let gradients = backward_resident(context, resident, &upstream)?;
    gradients.download(context)
}

/// Input gradients still on the GPU.
pub struct ResidentGradients {
    means: GpuBuffer,
    covariances: GpuBuffer,
    opacities: GpuBuffer,
    sh: GpuBuffer,
    mean_2d_norm: GpuBuffer,
    diagnostics: GpuBuffer,
}

impl ResidentGradients {
    pub fn download(&self, context: &GpuContext) -> Result<SplatGradients<f32>, GpuSplatError> {
        let mut encoder = context.encoder();
        let mut floats = context.download_many::<f32>(
            &mut encoder,
            &[
                (&self.means.buffer, self.means.len),
                (&self.covariances.buffer, self.covariances.len),
                (&self.opacities.buffer, self.opacities.len),
                (&self.sh.buffer, self.sh.len),
                (&self.mean_2d_norm.buffer, self.mean_2d_norm.len),
            ],
        )?;
        let mut counters = context
            .download_many::<u32>(&mut encoder, &[(&self.diagnostics.buffer, DIAGNOSTICS)])?;
        context.finish_downloads(encoder, &mut floats)?;
        context.finish_downloads(context.encoder(), &mut counters)?;
        let [means, covariances, opacities, sh, mean_2d_norm] =
            [0, 1, 2, 3, 4].map(|i| std::mem::take(&mut floats[i].values));
        Ok(SplatGradients {
            means,
            covariances,
            opacities,
            sh,
            mean_2d_norm,
            non_finite_gradients: counters[0].values[7] as usize,
        })
    }
}

fn check_upstream(
    camera_index: usize,
    gradient: &ImageGradient<'_, f32>,
    camera: &Camera,
) -> Result<(), SplatError> {
    let pixels = camera.width as usize * camera.height as usize;
    let check = |field: &'static str, values: &[f32], expected: usize| {
        super::check_len(field, values.len(), expected)?;
        match values.iter().position(|v| !v.is_finite()) {
            Some(index) => Err(SplatError::NonFiniteGradient {
                camera: camera_index,
                field,
                index,
            }),
            None => Ok(()),
        }
    };
    check("colour", gradient.colour, pixels * 3)?;
    if let Some(alpha) = gradient.alpha {
        check("alpha", alpha, pixels)?;
    }
    if let Some(depth) = gradient.depth {
        check("depth", depth, pixels)?;
    }
    Ok(())
}

/// One camera's upstream gradient, uploaded (checked first: sizes and finiteness).
pub struct ResidentImageGradient {
    colour: GpuBuffer,
    alpha: Option<GpuBuffer>,
    depth: Option<GpuBuffer>,
}

impl ResidentImageGradient {
    /// Uploads the gradients of every camera of `forward`.
    pub fn upload_all(
        context: &GpuContext,
        forward: &ResidentForward,
        upstream: &[ImageGradient<'_, f32>],
    ) -> Result<Vec<Self>, GpuSplatError> {
        if upstream.len() != forward.states.len() {
            return Err(SplatError::GradientCount {
                expected: forward.states.len(),
                actual: upstream.len(),
            }
            .into());
        }
        upstream
            .iter()
            .zip(&forward.states)
            .enumerate()
            .map(|(index, (gradient, state))| {
                check_upstream(index, gradient, &state.camera)?;
                Ok(Self {
                    colour: context.upload("d colour", gradient.colour)?,
                    alpha: gradient
                        .alpha
                        .map(|alpha| context.upload("d alpha", alpha))
                        .transpose()?,
                    depth: gradient
                        .depth
                        .map(|depth| context.upload("d depth", depth))
                        .transpose()?,
                })
            })
            .collect()
    }
}

/// Runs the backward kernels for every camera, leaving the gradients on the GPU.
pub fn backward_resident(
    context: &GpuContext,
    forward: &ResidentForward,
    upstream: &[ResidentImageGradient],
) -> Result<ResidentGradients, GpuSplatError> {
    if upstream.len() != forward.states.len() {
        return Err(SplatError::GradientCount {
            expected: forward.states.len(),
            actual: upstream.len(),
        }
        .into());
    }
    let gaussians = &forward.gaussians;
    let n = gaussians.len();
    let k = gaussians.sh_coefficients as usize;
    let out = ResidentGradients {
        means: context.zeros("grad means", n * 3, 4)?,
        covariances: context.zeros("grad covariances", n * 6, 4)?,
        opacities: context.zeros("grad opacities", n, 4)?,
        sh: context.zeros("grad sh", n * k * 3, 4)?,
        mean_2d_norm: context.zeros("grad mean 2d norm", n, 4)?,
        diagnostics: context.zeros("backward diagnostics", DIAGNOSTICS, 4)?,
    };
    let mode = forward
        .gpu_options
        .atomic_add
        .unwrap_or(if context.has_float_atomics() {
            AtomicAdd::NativeFloat
        } else {
            AtomicAdd::CompareExchange
        });
    let (name, wgsl) = match mode {
        AtomicAdd::NativeFloat => (
            "rasterize_backward_float_atomics",
            with_atomic_add(
                "splat_rasterize_backward.wgsl",
                RASTERIZE_BACKWARD_WGSL,
                mode,
            )?,
        ),
        AtomicAdd::CompareExchange => (
            "rasterize_backward_compare_exchange",
            RASTERIZE_BACKWARD_WGSL.to_owned(),
        ),
    };
    let rasterize = context.kernel(&KernelSource {
        name,
        wgsl: Cow::Owned(wgsl),
        entry_point: "rasterize_backward",
    })?;
    let project = context.kernel(&kernel_source(
        "project_backward",
        PROJECT_WGSL,
        "project_backward",
    ))?;
    let screen = context.zeros("screen gradients", n * SCREEN_GRADIENTS, 4)?;
    let placeholder = context.zeros("absent gradient", 1, 4)?;
    let mut encoder = context.encoder();
    for (state, gradient) in forward.states.iter().zip(upstream) {
        let camera = &state.camera;
        let (tiles_x, tiles_y) = tiles(camera);
        // An absent alpha or depth gradient binds a placeholder the kernel never reads.
        let d_alpha = gradient.alpha.as_ref().unwrap_or(&placeholder);
        let d_depth = gradient.depth.as_ref().unwrap_or(&placeholder);
        encoder.clear_buffer(&screen.buffer, 0, None);
        for band in &state.bands {
            let uniform = context.uniform(
                "splat camera band",
                &camera_uniform(
                    camera,
                    gaussians.count,
                    gaussians.sh_coefficients,
                    band.rows,
                    &forward.options,
                    gradient.alpha.is_some(),
                    gradient.depth.is_some(),
                ),
            );
            context.dispatch_grid(
                &mut encoder,
                &rasterize,
                &[
                    (0, &uniform),
                    (1, &state.ranges.buffer),
                    (2, &band.pair_gaussians.buffer),
                    (3, &state.projected.buffer),
                    (4, &gradient.colour.buffer),
                    (5, &d_alpha.buffer),
                    (6, &d_depth.buffer),
                    (7, &state.transmittance.buffer),
                    (8, &state.contributors.buffer),
                    (15, &screen.buffer),
                ],
                tiles_x,
                band.rows.1 - band.rows.0,
            );
            debug_assert!(band.pairs > 0 || band.rows.1 > band.rows.0);
        }
        let uniform = context.uniform(
            "splat camera",
            &camera_uniform(
                camera,
                gaussians.count,
                gaussians.sh_coefficients,
                (0, tiles_y),
                &forward.options,
                false,
                false,
            ),
        );
        context.dispatch(
            &mut encoder,
            &project,
            &[
                (0, &uniform),
                (1, &gaussians.means.buffer),
                (2, &gaussians.covariances.buffer),
                (3, &gaussians.opacities.buffer),
                (4, &gaussians.sh.buffer),
                (9, &out.diagnostics.buffer),
                (10, &screen.buffer),
                (11, &out.means.buffer),
                (12, &out.covariances.buffer),
                (13, &out.opacities.buffer),
                (14, &out.sh.buffer),
                (15, &out.mean_2d_norm.buffer),
            ],
            gaussians.count.div_ceil(GROUP),
        );
    }
    context.submit_and_wait(encoder)?;
    Ok(out)
}

impl GpuForward {
    /// The GPU-resident part, for callers that time kernels apart from transfers.
    pub fn resident(&self) -> &ResidentForward {
        &self.resident
    }
}

#[cfg(test)]
mod tests;
