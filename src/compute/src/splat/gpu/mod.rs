//! The `gpu` splatting backend: the contract of `src/compute/SPLATTING.md` as WGSL kernels
//! (`shaders/splat_*.wgsl`) run through wgpu.
//!
//! Everything lives in a [`SplatWorkspace`], allocated once and reused. Per camera:
//! `project_forward` (one thread per Gaussian), a GPU radix sort of the Gaussians by depth,
//! per-Gaussian tile counts in depth order, a prefix scan whose total stays on the device,
//! pair emission up to the pair capacity (the slots past the total get a sentinel tile and an
//! overflow is flagged in a device status buffer), a stable GPU radix sort of the capacity's
//! pairs by tile (so each tile's list stays in depth order, ties by Gaussian index), tile
//! ranges, then `rasterize_forward` (one 16x16 workgroup per tile). Nothing is read back:
//! the host reads the status when it wants to ([`SplatWorkspace::check_status`]) and grows
//! the capacity after an overflow; [`SplatWorkspace::forward_checked`] re-runs at once. The
//! image's tile rows are split into bands, each with its own pairs, so that one band's pairs
//! fit a storage binding. Backward walks the same lists back to front and adds per-Gaussian
//! screen-space gradients with f32 atomics (native, or a compare-exchange fallback), then
//! `project_backward` chains them to the inputs.
//!
//! The host-slice entry points ([`forward`], [`forward_with`], [`backward`]) upload, run
//! the workspace checked and download.

use std::borrow::Cow;

use seqavatar_core::camera::Camera;

use bytemuck::Zeroable;

use super::{
    GaussianSet, ImageGradient, RasterOptions, RenderedImage, SplatDiagnostics, SplatError,
    SplatGradients, TILE_SIZE, check_degree_and_count, sh_coefficient_count, validate_call,
};
use crate::backend::primitives::{ScanWorkspace, SortWorkspace};
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
    slot: u32,
    tiles: u32,
    pad: u32,
}

/// This module's uniform structs for the layout test in `backend::shaders`.
#[cfg(test)]
pub(crate) fn wgsl_twins() -> Vec<crate::backend::shaders::tests::WgslTwin> {
    use crate::backend::shaders::tests::wgsl_twin;
    vec![
        wgsl_twin!(CameraUniform as "SplatCamera" in [
            "splat_project.wgsl",
            "splat_rasterize.wgsl",
            "splat_rasterize_backward.wgsl",
        ] {
            rotation[0] as "rotation0", rotation[1] as "rotation1", rotation[2] as "rotation2",
            intrinsics, center, background, image, counts, flags,
        }),
        wgsl_twin!(BinParams as "BinParams" in ["splat_bin.wgsl"] {
            gaussians, pairs, tiles_x, row_begin, row_end, slot, tiles, pad as "_pad",
        }),
    ]
}

fn tiles(camera: &Camera) -> (u32, u32) {
    (
        camera.width.div_ceil(TILE_SIZE),
        camera.height.div_ceil(TILE_SIZE),
    )
}

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

/// The Gaussians of one call, uploaded and owned (the host path; a resident step passes its
/// own buffers as [`DeviceGaussians`]).
pub struct ResidentGaussians {
    means: GpuBuffer,
    covariances: GpuBuffer,
    opacities: GpuBuffer,
    sh: GpuBuffer,
    count: u32,
    sh_degree: u32,
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
        })
    }

    /// The uploaded buffers as a borrowed [`DeviceGaussians`].
    pub fn view(&self) -> DeviceGaussians<'_> {
        DeviceGaussians {
            means: &self.means,
            covariances: &self.covariances,
            opacities: &self.opacities,
            sh: &self.sh,
            count: self.count,
            sh_degree: self.sh_degree,
        }
    }

    pub fn len(&self) -> usize {
        self.count as usize
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }
}

/// Gaussians on the device, borrowed from whoever writes them (f32, the `cpu` layouts; each
/// buffer may be longer than `count` needs, the excess is ignored):
/// `means` `N x 3`, `covariances` `N x 6` (upper triangle `xx xy xz yy yz zz`), `opacities`
/// `N` (activated, in (0, 1)), `sh` `N x k x 3` with `k = (sh_degree + 1)^2`.
#[derive(Clone, Copy, Debug)]
pub struct DeviceGaussians<'a> {
    pub means: &'a GpuBuffer,
    pub covariances: &'a GpuBuffer,
    pub opacities: &'a GpuBuffer,
    pub sh: &'a GpuBuffer,
    /// `N`.
    pub count: u32,
    pub sh_degree: u32,
}

/// The projection's inputs, bound alike by `project_forward` and `project_backward`: the
/// camera uniform (band 0's) and the Gaussians.
fn project_inputs<'a>(
    camera: &'a wgpu::Buffer,
    gaussians: &DeviceGaussians<'a>,
) -> [(u32, &'a wgpu::Buffer); 5] {
    [
        (0, camera),
        (1, &gaussians.means.buffer),
        (2, &gaussians.covariances.buffer),
        (3, &gaussians.opacities.buffer),
        (4, &gaussians.sh.buffer),
    ]
}

/// The bindings of one band's rasterization, forward and backward alike: `images` are the
/// colour, alpha and depth images (bindings 4-6) the forward writes and whose gradients the
/// backward reads.
fn rasterize_bindings<'a>(
    band: &'a BandSlot,
    slot: &'a CameraSlot,
    images: [&'a GpuBuffer; 3],
) -> [(u32, &'a wgpu::Buffer); 9] {
    [
        (0, &band.camera),
        (1, &slot.ranges.buffer),
        (2, &band.pair_gaussians.buffer),
        (3, &slot.projected.buffer),
        (4, &images[0].buffer),
        (5, &images[1].buffer),
        (6, &images[2].buffer),
        (7, &slot.transmittance.buffer),
        (8, &slot.contributors.buffer),
    ]
}

/// `Err(Length)` when `buffer` holds fewer than `needed` values.
fn check_at_least(
    field: &'static str,
    buffer: &GpuBuffer,
    needed: usize,
) -> Result<(), SplatError> {
    if buffer.len < needed {
        return Err(SplatError::Length {
            field,
            expected: needed,
            actual: buffer.len,
        });
    }
    Ok(())
}

impl DeviceGaussians<'_> {
    /// SH coefficients per colour channel.
    pub fn sh_coefficients(&self) -> u32 {
        sh_coefficient_count(self.sh_degree) as u32
    }

    fn validate(&self) -> Result<(), SplatError> {
        let n = self.count as usize;
        check_degree_and_count(self.sh_degree, n)?;
        check_at_least("means", self.means, n * 3)?;
        check_at_least("covariances", self.covariances, n * 6)?;
        check_at_least("opacities", self.opacities, n)?;
        check_at_least("sh", self.sh, n * self.sh_coefficients() as usize * 3)
    }
}

/// One camera's upstream image gradients on the device (f32, written by another piece):
/// `colour` `H x W x 3` (row-major pixels, RGB), `alpha` and `depth` `H x W`; an absent alpha
/// or depth gradient is zero. Buffers may be longer than the image; the excess is ignored.
#[derive(Clone, Copy, Debug)]
pub struct DeviceImageGradient<'a> {
    pub colour: &'a GpuBuffer,
    pub alpha: Option<&'a GpuBuffer>,
    pub depth: Option<&'a GpuBuffer>,
}

/// What [`SplatWorkspace::check_status`] read from the device status buffer: the pair
/// capacity overflows since the previous check, and what it did about them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SplatStatus {
    /// Bands (over cameras and calls) whose Gaussian-tile pairs exceeded the capacity: those
    /// bands rendered without their last pairs (in depth order).
    pub overflowed_bands: u32,
    /// The most pairs one band needed.
    pub largest_band_pairs: u32,
    /// Whether the capacity was grown (after an overflow) for the next call.
    pub grown: bool,
}

/// Device status words (`status` in `splat_bin.wgsl`): overflowed bands, largest band total.
const STATUS_WORDS: usize = 4;

/// The buffers that depend on the Gaussian count.
struct GaussianParts {
    capacity: u32,
    sh_coefficients: u32,
    rects: GpuBuffer,
    depth_keys: GpuBuffer,
    depth_indices: GpuBuffer,
    depth_sort: SortWorkspace,
    tile_counts: GpuBuffer,
    tile_scan: ScanWorkspace,
    screen: GpuBuffer,
    gradients: ResidentGradients,
}

impl GaussianParts {
    fn new(
        context: &GpuContext,
        capacity: u32,
        sh_coefficients: u32,
    ) -> Result<Self, BackendError> {
        let n = capacity as usize;
        let k = sh_coefficients as usize;
        Ok(Self {
            capacity,
            sh_coefficients,
            rects: context.zeros("tile rects", n, 16)?,
            depth_keys: context.zeros("depth keys", n, 4)?,
            depth_indices: context.zeros("depth order", n, 4)?,
            depth_sort: SortWorkspace::new(context, capacity)?,
            tile_counts: context.zeros("tile counts", n, 4)?,
            tile_scan: ScanWorkspace::new(context, capacity)?,
            screen: context.zeros("screen gradients", n * SCREEN_GRADIENTS, 4)?,
            gradients: ResidentGradients {
                means: context.zeros("grad means", n * 3, 4)?,
                covariances: context.zeros("grad covariances", n * 6, 4)?,
                opacities: context.zeros("grad opacities", n, 4)?,
                sh: context.zeros("grad sh", n * k * 3, 4)?,
                mean_2d_norm: context.zeros("grad mean 2d norm", n, 4)?,
                diagnostics: context.zeros("backward diagnostics", DIAGNOSTICS, 4)?,
                count: 0,
                sh_coefficients: 0,
            },
        })
    }
}

/// One band of tile rows of one camera: its uniforms and its sorted pairs.
struct BandSlot {
    /// The camera uniform with this band's rows (band 0's also serves the projection).
    camera: wgpu::Buffer,
    bin_params: wgpu::Buffer,
    /// What `bin_params` holds now (rewritten only on a change).
    written: BinParams,
    /// The band's Gaussian per pair, sorted by tile then depth (pair capacity long).
    pair_gaussians: GpuBuffer,
}

/// The per-camera buffers, sized for a pixel and tile count and the pair capacity.
struct CameraSlot {
    pixels: usize,
    tiles: usize,
    projected: GpuBuffer,
    ranges: GpuBuffer,
    colour: GpuBuffer,
    alpha: GpuBuffer,
    depth: GpuBuffer,
    transmittance: GpuBuffer,
    contributors: GpuBuffer,
    diagnostics: GpuBuffer,
    bands: Vec<BandSlot>,
}

impl CameraSlot {
    fn new(
        context: &GpuContext,
        gaussians: u32,
        pixels: usize,
        tiles: usize,
        bands: u32,
        pairs_per_band: u32,
    ) -> Result<Self, BackendError> {
        let zero_camera = CameraUniform::zeroed();
        let bands = (0..bands)
            .map(|_| {
                Ok(BandSlot {
                    camera: context.uniform("splat camera band", &zero_camera),
                    bin_params: context.uniform("bin params", &BinParams::zeroed()),
                    written: BinParams::zeroed(),
                    pair_gaussians: context.zeros("pair gaussians", pairs_per_band as usize, 4)?,
                })
            })
            .collect::<Result<Vec<_>, BackendError>>()?;
        Ok(Self {
            pixels,
            tiles,
            projected: context.zeros("projected", gaussians as usize * 3, 16)?,
            ranges: context.zeros("tile ranges", tiles, 8)?,
            colour: context.zeros("colour", pixels * 3, 4)?,
            alpha: context.zeros("alpha", pixels, 4)?,
            depth: context.zeros("depth", pixels, 4)?,
            transmittance: context.zeros("final transmittance", pixels, 4)?,
            contributors: context.zeros("contributors", pixels, 4)?,
            diagnostics: context.zeros("diagnostics", DIAGNOSTICS, 4)?,
            bands,
        })
    }
}

/// What the last forward rendered (the backward and the downloads use it).
struct Call {
    cameras: Vec<Camera>,
    options: RasterOptions,
    gaussians: u32,
    sh_degree: u32,
    /// Per camera, the tile rows of each of its bands.
    bands: Vec<Vec<(u32, u32)>>,
}

/// Everything a splatting forward and backward need on the device, allocated once and
/// reused: per Gaussian (rects, depth keys and their sort, tile counts and their scan,
/// screen-space and input gradients), per camera (projected Gaussians, tile ranges, images,
/// final transmittance, contributor counts, diagnostics, camera uniforms) and per camera band
/// (sorted pairs, `pairs_per_band` long), plus the pair keys and their sort and the status.
///
/// Sizes follow the calls: a call with more Gaussians, SH coefficients, cameras or pixels
/// than allocated grows the workspace first (an allocation, as after densification); the pair
/// capacity grows only in [`SplatWorkspace::check_status`] after an overflow was flagged.
/// The pair count never leaves the device: each band's pairs are emitted up to the capacity,
/// the slots past the device total carry a sentinel tile that sorts last, and the pair sort
/// and range kernels run over the whole capacity.
///
/// Bands: the image's tile rows are split into `bands` equal bands (fewer when the image has
/// fewer tile rows), each with its own pairs, so that one band's pairs fit a storage binding
/// (`max_binding_bytes`, or [`GpuOptions::max_pairs_per_band`]); the count doubles when one
/// band needs more pairs than that.
///
/// One forward (then at most one backward) per submission: the camera uniforms are written
/// with [`GpuContext::write`], which lands before the next submission.
pub struct SplatWorkspace {
    gpu_options: GpuOptions,
    pairs_per_band: u32,
    bands: u32,
    gaussians: Option<GaussianParts>,
    pair_keys: GpuBuffer,
    pair_sort: SortWorkspace,
    cameras: Vec<CameraSlot>,
    /// `STATUS_WORDS` u32: see `status` in `splat_bin.wgsl`.
    status: GpuBuffer,
    /// Per (camera, band) slot, the pair total of the last forward.
    band_pairs: GpuBuffer,
    placeholder: GpuBuffer,
    call: Option<Call>,
}

/// Per camera of a forward, its image and diagnostics as read back.
pub type CameraImages = (Vec<RenderedImage<f32>>, Vec<SplatDiagnostics>);

/// Pair capacity of the first call when the caller gives none: at most every tile of every
/// Gaussian, else sixteen tiles per Gaussian (at least a few thousand).
fn estimate_pairs(gaussians: u32, tiles: u32) -> u64 {
    let n = u64::from(gaussians);
    (n * u64::from(tiles)).min((16 * n).max(4096)).max(1)
}

impl SplatWorkspace {
    /// An empty workspace; the first forward sizes it. `pairs_per_band` seeds the pair
    /// capacity (else it is estimated from the first call).
    pub fn new(
        context: &GpuContext,
        gpu_options: GpuOptions,
        pairs_per_band: Option<u32>,
    ) -> Result<Self, GpuSplatError> {
        let mut workspace = Self {
            gpu_options,
            pairs_per_band: 0,
            bands: 1,
            gaussians: None,
            pair_keys: context.zeros("pair tiles", 1, 4)?,
            pair_sort: SortWorkspace::new(context, 1)?,
            cameras: Vec::new(),
            status: context.zeros("splat status", STATUS_WORDS, 4)?,
            band_pairs: context.zeros("band pairs", 1, 4)?,
            placeholder: context.zeros("absent gradient", 1, 4)?,
            call: None,
        };
        if let Some(pairs) = pairs_per_band {
            workspace.set_pair_capacity(context, u64::from(pairs))?;
        }
        Ok(workspace)
    }

    /// Gaussian-tile pairs each band can hold.
    pub fn pairs_per_band(&self) -> u32 {
        self.pairs_per_band
    }

    /// Bands of tile rows each camera's pairs are binned in (at most; fewer for an image with
    /// fewer tile rows).
    pub fn bands(&self) -> u32 {
        self.bands
    }

    fn max_pairs_per_band(&self, context: &GpuContext) -> u64 {
        self.gpu_options
            .max_pairs_per_band
            .map_or(u64::MAX, u64::from)
            .min(context.max_binding_bytes() / 4)
            .min(u64::from(u32::MAX))
            .max(1)
    }

    /// Sets the total pair capacity per camera to `pairs`, split into as many bands as the
    /// binding limit needs, and reallocates the pair buffers.
    fn set_pair_capacity(&mut self, context: &GpuContext, pairs: u64) -> Result<(), GpuSplatError> {
        let max = self.max_pairs_per_band(context);
        let bands = pairs.div_ceil(max).max(u64::from(self.bands));
        self.bands = u32::try_from(bands).unwrap_or(u32::MAX);
        self.reallocate_pairs(context, pairs.div_ceil(bands).clamp(1, max) as u32)
    }

    fn reallocate_pairs(&mut self, context: &GpuContext, pairs: u32) -> Result<(), GpuSplatError> {
        self.pairs_per_band = pairs;
        self.pair_keys = context.zeros("pair tiles", pairs as usize, 4)?;
        self.pair_sort = SortWorkspace::new(context, pairs)?;
        // Camera slots hold per-band pair buffers: rebuilt at the next forward.
        self.cameras.clear();
        Ok(())
    }

    /// Grows whatever the call needs beyond the current sizes.
    fn reserve(
        &mut self,
        context: &GpuContext,
        gaussians: &DeviceGaussians<'_>,
        cameras: &[Camera],
    ) -> Result<(), GpuSplatError> {
        let k = gaussians.sh_coefficients();
        let grow_gaussians = self
            .gaussians
            .as_ref()
            .is_none_or(|parts| parts.capacity < gaussians.count || parts.sh_coefficients < k);
        if grow_gaussians {
            // Headroom over the current capacity, so densification does not reallocate at
            // every step.
            let current = self.gaussians.as_ref().map_or(0, |parts| parts.capacity);
            let capacity = if current == 0 {
                gaussians.count
            } else {
                gaussians.count.max(current.saturating_add(current / 4))
            };
            let k = k.max(self.gaussians.as_ref().map_or(0, |p| p.sh_coefficients));
            self.gaussians = Some(GaussianParts::new(context, capacity, k)?);
            self.cameras.clear();
        }
        if self.pairs_per_band == 0 {
            let most_tiles = cameras
                .iter()
                .map(|camera| {
                    let (x, y) = tiles(camera);
                    x * y
                })
                .max()
                .unwrap_or(1);
            self.set_pair_capacity(context, estimate_pairs(gaussians.count, most_tiles))?;
        }
        let capacity = self.gaussians.as_ref().map_or(0, |parts| parts.capacity);
        for (index, camera) in cameras.iter().enumerate() {
            let pixels = camera.width as usize * camera.height as usize;
            let (tiles_x, tiles_y) = tiles(camera);
            let tile_count = (tiles_x * tiles_y) as usize;
            let fits = self
                .cameras
                .get(index)
                .is_some_and(|slot| slot.pixels >= pixels && slot.tiles >= tile_count);
            if !fits {
                let (pixels, tile_count) = match self.cameras.get(index) {
                    Some(slot) => (pixels.max(slot.pixels), tile_count.max(slot.tiles)),
                    None => (pixels, tile_count),
                };
                let slot = CameraSlot::new(
                    context,
                    capacity,
                    pixels,
                    tile_count,
                    self.bands,
                    self.pairs_per_band,
                )?;
                if index < self.cameras.len() {
                    self.cameras[index] = slot;
                } else {
                    self.cameras.push(slot);
                }
            }
        }
        let slots = self.cameras.len() * self.bands as usize;
        if self.band_pairs.len < slots {
            self.band_pairs = context.zeros("band pairs", slots, 4)?;
        }
        Ok(())
    }

    /// Records the forward pass of `gaussians` seen from every camera into `encoder`: per
    /// camera the projection, the depth sort, the binning of each band with the pair count
    /// kept on the device, the pair sort, the tile ranges and the compositing. Writes each
    /// camera's uniforms (144 bytes per band); reads nothing back. When the call needs more
    /// room than the workspace has (Gaussians, SH coefficients, cameras, pixels) it grows
    /// first. Images stay in the workspace ([`SplatWorkspace::colour`] and friends).
    pub fn forward(
        &mut self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: DeviceGaussians<'_>,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> Result<(), GpuSplatError> {
        validate_call(cameras, options)?;
        gaussians.validate()?;
        let max_grid = context.max_workgroups_per_dimension();
        for camera in cameras {
            // Tile kernels run on a tiles_x by tiles_y grid of workgroups.
            let (tiles_x, tiles_y) = tiles(camera);
            if tiles_x > max_grid || tiles_y > max_grid {
                return Err(BackendError::Gpu {
                    message: format!(
                        "image {}x{} has more than {max_grid} tiles along one side",
                        camera.width, camera.height
                    ),
                }
                .into());
            }
        }
        self.reserve(context, &gaussians, cameras)?;
        let n = gaussians.count;
        let k = gaussians.sh_coefficients();
        let project = context.static_kernel("project_forward", PROJECT_WGSL, "project_forward")?;
        let count_kernel = context.static_kernel("count_tiles", BIN_WGSL, "count_tiles")?;
        let emit_kernel = context.static_kernel("emit_pairs", BIN_WGSL, "emit_pairs")?;
        let finish_kernel = context.static_kernel("finish_pairs", BIN_WGSL, "finish_pairs")?;
        let ranges_kernel = context.static_kernel("tile_ranges", BIN_WGSL, "tile_ranges")?;
        let rasterize =
            context.static_kernel("rasterize_forward", RASTERIZE_WGSL, "rasterize_forward")?;
        let pairs = self.pairs_per_band;
        let Some(parts) = self.gaussians.as_mut() else {
            unreachable!("reserve allocates the per-Gaussian buffers");
        };
        let mut call_bands = Vec::with_capacity(cameras.len());
        for (index, camera) in cameras.iter().enumerate() {
            let slot = &mut self.cameras[index];
            let (tiles_x, tiles_y) = tiles(camera);
            let tile_count = tiles_x * tiles_y;
            let band_count = self.bands.min(tiles_y).max(1);
            let rows: Vec<(u32, u32)> = (0..band_count)
                .map(|band| {
                    let row =
                        |b: u32| (u64::from(b) * u64::from(tiles_y) / u64::from(band_count)) as u32;
                    (row(band), row(band + 1))
                })
                .collect();
            for (band, rows) in slot.bands.iter().zip(&rows) {
                context.write(
                    &band.camera,
                    0,
                    &[camera_uniform(camera, n, k, *rows, options, false, false)],
                )?;
            }
            encoder.clear_buffer(&slot.diagnostics.buffer, 0, None);
            encoder.clear_buffer(&slot.ranges.buffer, 0, None);
            let bindings = [
                project_inputs(&slot.bands[0].camera, &gaussians).as_slice(),
                &[
                    (5, &slot.projected.buffer),
                    (6, &parts.rects.buffer),
                    (7, &parts.depth_keys.buffer),
                    (8, &parts.depth_indices.buffer),
                    (9, &slot.diagnostics.buffer),
                ],
            ]
            .concat();
            context.dispatch(encoder, &project, &bindings, n.div_ceil(GROUP));
            // Stable sort by depth: culled Gaussians carry the largest key and sort last; ties
            // keep index order because the values start as 0..N.
            let in_scratch = parts.depth_sort.record(
                context,
                encoder,
                &parts.depth_keys.buffer,
                &parts.depth_indices.buffer,
                n,
                32,
            )?;
            let sorted_indices = if in_scratch {
                &parts.depth_sort.scratch_values().buffer
            } else {
                &parts.depth_indices.buffer
            };
            // The sentinel tile `tile_count` must fit the sorted bits.
            let tile_bits = 32 - tile_count.leading_zeros();
            for (band_index, (band, rows)) in slot.bands.iter_mut().zip(&rows).enumerate() {
                let params = BinParams {
                    gaussians: n,
                    pairs,
                    tiles_x,
                    row_begin: rows.0,
                    row_end: rows.1,
                    slot: (index * self.bands as usize + band_index) as u32,
                    tiles: tile_count,
                    pad: 0,
                };
                if bytemuck::bytes_of(&params) != bytemuck::bytes_of(&band.written) {
                    context.write(&band.bin_params, 0, &[params])?;
                    band.written = params;
                }
                context.dispatch(
                    encoder,
                    &count_kernel,
                    &[
                        (0, &band.bin_params),
                        (1, sorted_indices),
                        (2, &parts.rects.buffer),
                        (3, &parts.tile_counts.buffer),
                    ],
                    n.div_ceil(GROUP),
                );
                parts
                    .tile_scan
                    .record(context, encoder, &parts.tile_counts.buffer, n)?;
                context.dispatch(
                    encoder,
                    &emit_kernel,
                    &[
                        (0, &band.bin_params),
                        (1, sorted_indices),
                        (2, &parts.rects.buffer),
                        (3, &parts.tile_counts.buffer),
                        (4, &self.pair_keys.buffer),
                        (5, &band.pair_gaussians.buffer),
                    ],
                    n.div_ceil(GROUP),
                );
                context.dispatch(
                    encoder,
                    &finish_kernel,
                    &[
                        (0, &band.bin_params),
                        (4, &self.pair_keys.buffer),
                        (5, &band.pair_gaussians.buffer),
                        (7, &parts.tile_scan.total().buffer),
                        (8, &self.status.buffer),
                        (9, &self.band_pairs.buffer),
                    ],
                    pairs.div_ceil(GROUP),
                );
                let in_scratch = self.pair_sort.record(
                    context,
                    encoder,
                    &self.pair_keys.buffer,
                    &band.pair_gaussians.buffer,
                    pairs,
                    tile_bits,
                )?;
                let sorted_keys = if in_scratch {
                    encoder.copy_buffer_to_buffer(
                        &self.pair_sort.scratch_values().buffer,
                        0,
                        &band.pair_gaussians.buffer,
                        0,
                        u64::from(pairs) * 4,
                    );
                    &self.pair_sort.scratch_keys().buffer
                } else {
                    &self.pair_keys.buffer
                };
                context.dispatch(
                    encoder,
                    &ranges_kernel,
                    &[
                        (0, &band.bin_params),
                        (4, sorted_keys),
                        (6, &slot.ranges.buffer),
                    ],
                    pairs.div_ceil(GROUP),
                );
            }
            for (band, rows) in slot.bands.iter().zip(&rows) {
                let images = [&slot.colour, &slot.alpha, &slot.depth];
                context.dispatch(
                    encoder,
                    &rasterize,
                    &rasterize_bindings(band, slot, images),
                    (tiles_x, rows.1 - rows.0),
                );
            }
            call_bands.push(rows);
        }
        self.call = Some(Call {
            cameras: cameras.to_vec(),
            options: options.clone(),
            gaussians: n,
            sh_degree: gaussians.sh_degree,
            bands: call_bands,
        });
        Ok(())
    }

    /// Reads the status buffer (one read-back: call it with the logs), resets it and, when a
    /// band overflowed its pair capacity, grows the capacity for the next call: to the
    /// largest band total plus a quarter, or, beyond the per-band limit, twice the bands.
    /// Fails when one tile row alone needs more pairs than a binding holds.
    pub fn check_status(&mut self, context: &GpuContext) -> Result<SplatStatus, GpuSplatError> {
        let words: Vec<u32> =
            context.download(context.encoder(), &self.status.buffer, STATUS_WORDS)?;
        self.apply_status(context, &words)
    }

    /// Acts on status words read back: resets the status buffer and grows the pair capacity
    /// after an overflow ([`SplatWorkspace::check_status`]).
    fn apply_status(
        &mut self,
        context: &GpuContext,
        words: &[u32],
    ) -> Result<SplatStatus, GpuSplatError> {
        let mut encoder = context.encoder();
        encoder.clear_buffer(&self.status.buffer, 0, None);
        context.queue().submit([encoder.finish()]);
        let mut status = SplatStatus {
            overflowed_bands: words[0],
            largest_band_pairs: words[1],
            grown: false,
        };
        if status.overflowed_bands == 0 {
            return Ok(status);
        }
        let largest = u64::from(status.largest_band_pairs);
        let max = self.max_pairs_per_band(context);
        if largest > max {
            let most_rows = self.call.as_ref().map_or(1, |call| {
                call.cameras
                    .iter()
                    .map(|camera| tiles(camera).1)
                    .max()
                    .unwrap_or(1)
            });
            if self.bands >= most_rows {
                return Err(BackendError::BufferTooLarge {
                    what: "Gaussian-tile pairs of one tile row".to_owned(),
                    bytes: largest * 4,
                    limit: max * 4,
                }
                .into());
            }
            self.bands = self.bands.saturating_mul(2).min(most_rows);
            self.reallocate_pairs(context, max as u32)?;
        } else {
            let wanted = (largest + largest / 4 + 256).min(max) as u32;
            self.reallocate_pairs(context, wanted.max(self.pairs_per_band))?;
        }
        status.grown = true;
        Ok(status)
    }

    /// [`SplatWorkspace::forward`] submitted and checked: when a band overflowed, the
    /// capacity grows and the forward runs again, until every band fits (an exact render for
    /// evaluation and tests; one read-back per try).
    pub fn forward_checked(
        &mut self,
        context: &GpuContext,
        gaussians: DeviceGaussians<'_>,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> Result<SplatStatus, GpuSplatError> {
        // A status left from unchecked calls is not this call's.
        let mut encoder = context.encoder();
        encoder.clear_buffer(&self.status.buffer, 0, None);
        loop {
            self.forward(context, &mut encoder, gaussians, cameras, options)?;
            context.submit_and_wait(encoder)?;
            let status = self.check_status(context)?;
            if !status.grown {
                return Ok(status);
            }
            encoder = context.encoder();
        }
    }

    /// Records the backward pass of the last forward into `encoder`: per camera and band the
    /// compositing backward (screen-space gradients added with f32 atomics), then the
    /// projection backward into the input gradients, summed over cameras. `gaussians` must be
    /// the forward's (their buffers unchanged since). Clears the gradient buffers first;
    /// writes 16 bytes per camera band (the gradient flags); reads nothing back. The
    /// gradients stay in the workspace ([`SplatWorkspace::gradients`]).
    pub fn backward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: DeviceGaussians<'_>,
        upstream: &[DeviceImageGradient<'_>],
    ) -> Result<(), GpuSplatError> {
        let (Some(call), Some(parts)) = (self.call.as_ref(), self.gaussians.as_ref()) else {
            return Err(BackendError::Gpu {
                message: "splatting backward before any forward".to_owned(),
            }
            .into());
        };
        if gaussians.count != call.gaussians || gaussians.sh_degree != call.sh_degree {
            return Err(SplatError::GaussiansChanged {
                expected: call.gaussians as usize,
                actual: gaussians.count as usize,
            }
            .into());
        }
        gaussians.validate()?;
        if upstream.len() != call.cameras.len() {
            return Err(SplatError::GradientCount {
                expected: call.cameras.len(),
                actual: upstream.len(),
            }
            .into());
        }
        for (gradient, camera) in upstream.iter().zip(&call.cameras) {
            let pixels = camera.width as usize * camera.height as usize;
            check_at_least("colour", gradient.colour, pixels * 3)?;
            if let Some(alpha) = gradient.alpha {
                check_at_least("alpha", alpha, pixels)?;
            }
            if let Some(depth) = gradient.depth {
                check_at_least("depth", depth, pixels)?;
            }
        }
        let rasterize = rasterize_backward_kernel(context, self.gpu_options)?;
        let project =
            context.static_kernel("project_backward", PROJECT_WGSL, "project_backward")?;
        let out = &parts.gradients;
        for buffer in out.buffers() {
            encoder.clear_buffer(&buffer.buffer, 0, None);
        }
        for ((slot, gradient), (camera, rows)) in self
            .cameras
            .iter()
            .zip(upstream)
            .zip(call.cameras.iter().zip(&call.bands))
        {
            let (tiles_x, _) = tiles(camera);
            // An absent alpha or depth gradient binds a placeholder the kernel never reads.
            let d_alpha = gradient.alpha.unwrap_or(&self.placeholder);
            let d_depth = gradient.depth.unwrap_or(&self.placeholder);
            let flags = [
                u32::from(call.options.smooth_cutoff),
                u32::from(gradient.alpha.is_some()),
                u32::from(gradient.depth.is_some()),
                0,
            ];
            encoder.clear_buffer(&parts.screen.buffer, 0, None);
            for (band, rows) in slot.bands.iter().zip(rows) {
                context.write(&band.camera, CAMERA_FLAGS_OFFSET, &[flags])?;
                let images = [gradient.colour, d_alpha, d_depth];
                let bindings = [
                    rasterize_bindings(band, slot, images).as_slice(),
                    &[(15, &parts.screen.buffer)],
                ]
                .concat();
                context.dispatch(encoder, &rasterize, &bindings, (tiles_x, rows.1 - rows.0));
            }
            let bindings = [
                project_inputs(&slot.bands[0].camera, &gaussians).as_slice(),
                &[
                    (9, &out.diagnostics.buffer),
                    (10, &parts.screen.buffer),
                    (11, &out.means.buffer),
                    (12, &out.covariances.buffer),
                    (13, &out.opacities.buffer),
                    (14, &out.sh.buffer),
                    (15, &out.mean_2d_norm.buffer),
                ],
            ]
            .concat();
            context.dispatch(encoder, &project, &bindings, call.gaussians.div_ceil(GROUP));
        }
        Ok(())
    }

    fn call(&self) -> Result<&Call, GpuSplatError> {
        self.call.as_ref().ok_or_else(|| {
            BackendError::Gpu {
                message: "splatting workspace read before any forward".to_owned(),
            }
            .into()
        })
    }

    fn slot(&self, camera: usize) -> Result<&CameraSlot, GpuSplatError> {
        let cameras = self.call()?.cameras.len();
        self.cameras
            .get(camera)
            .filter(|_| camera < cameras)
            .ok_or_else(|| {
                BackendError::Gpu {
                    message: format!("camera {camera} of a forward with {cameras} cameras"),
                }
                .into()
            })
    }

    /// Camera `camera`'s rendered colour of the last forward: `H x W x 3` f32 (the buffer
    /// may be longer; the excess is stale).
    pub fn colour(&self, camera: usize) -> Result<&GpuBuffer, GpuSplatError> {
        Ok(&self.slot(camera)?.colour)
    }

    /// Camera `camera`'s accumulated opacity of the last forward: `H x W` f32.
    pub fn alpha(&self, camera: usize) -> Result<&GpuBuffer, GpuSplatError> {
        Ok(&self.slot(camera)?.alpha)
    }

    /// Camera `camera`'s alpha-weighted depth of the last forward: `H x W` f32.
    pub fn depth(&self, camera: usize) -> Result<&GpuBuffer, GpuSplatError> {
        Ok(&self.slot(camera)?.depth)
    }

    /// The input gradients of the last backward (see [`ResidentGradients`] for layouts).
    pub fn gradients(&self) -> Result<ResidentGradients, GpuSplatError> {
        let call = self.call()?;
        let Some(parts) = self.gaussians.as_ref() else {
            unreachable!("a forward allocated the per-Gaussian buffers");
        };
        let n = call.gaussians as usize;
        let k = sh_coefficient_count(call.sh_degree);
        let lens = [n * 3, n * 6, n, n * k * 3, n, DIAGNOSTICS];
        let [means, covariances, opacities, sh, mean_2d_norm, diagnostics] =
            std::array::from_fn(|i| share(parts.gradients.buffers()[i], lens[i]));
        Ok(ResidentGradients {
            means,
            covariances,
            opacities,
            sh,
            mean_2d_norm,
            diagnostics,
            count: call.gaussians,
            sh_coefficients: k as u32,
        })
    }

    /// Per camera, the bands of tile rows the last forward binned its pairs in.
    pub fn band_counts(&self) -> Vec<usize> {
        self.call
            .as_ref()
            .map(|call| call.bands.iter().map(Vec::len).collect())
            .unwrap_or_default()
    }

    /// Copies every camera's images and diagnostics of the last forward to the host (one
    /// read-back). `intersections` counts every pair the bands needed, also past an overflow.
    pub fn download_images(&self, context: &GpuContext) -> Result<CameraImages, GpuSplatError> {
        let (images, _) = self.download_images_and_status(context)?;
        Ok(images)
    }

    /// The images of the last forward, submitted unchecked, with its status read in the same
    /// read-back: `None` when a band overflowed its pair capacity (the images are incomplete;
    /// the capacity has grown, record the forward again). One read-back per try, so a render
    /// costs one round trip once the capacity fits.
    pub fn download_checked_images(
        &mut self,
        context: &GpuContext,
    ) -> Result<Option<CameraImages>, GpuSplatError> {
        let (images, words) = self.download_images_and_status(context)?;
        let status = self.apply_status(context, &words)?;
        Ok((!status.grown).then_some(images))
    }

    fn download_images_and_status(
        &self,
        context: &GpuContext,
    ) -> Result<(CameraImages, Vec<u32>), GpuSplatError> {
        let call = self.call()?;
        let mut sources: Vec<(&wgpu::Buffer, usize)> = Vec::new();
        for (slot, camera) in self.cameras.iter().zip(&call.cameras) {
            let pixels = camera.width as usize * camera.height as usize;
            sources.extend([
                (&slot.colour.buffer, pixels * 3),
                (&slot.alpha.buffer, pixels),
                (&slot.depth.buffer, pixels),
                (&slot.diagnostics.buffer, DIAGNOSTICS),
            ]);
        }
        let slots = call.cameras.len() * self.bands as usize;
        sources.push((&self.band_pairs.buffer, slots));
        sources.push((&self.status.buffer, STATUS_WORDS));
        let mut words = context.download_all::<u32>(context.encoder(), &sources)?;
        let status = words.pop().unwrap_or_default();
        let band_pairs = words.pop().unwrap_or_default();
        let floats = |bits: Vec<u32>| bits.into_iter().map(f32::from_bits).collect::<Vec<_>>();
        let mut words = words.into_iter();
        let mut images = Vec::with_capacity(call.cameras.len());
        let mut diagnostics = Vec::with_capacity(call.cameras.len());
        for (index, (camera, rows)) in call.cameras.iter().zip(&call.bands).enumerate() {
            let mut next = || words.next().unwrap_or_default();
            let (colour, alpha, depth, c) = (next(), next(), next(), next());
            images.push(RenderedImage {
                width: camera.width,
                height: camera.height,
                colour: floats(colour),
                alpha: floats(alpha),
                depth: floats(depth),
            });
            let first = index * self.bands as usize;
            let intersections: u64 = band_pairs[first..first + rows.len()]
                .iter()
                .map(|&pairs| u64::from(pairs))
                .sum();
            diagnostics.push(SplatDiagnostics {
                gaussians: call.gaussians as usize,
                non_finite_inputs: c[0] as usize,
                non_finite_projections: c[1] as usize,
                culled_depth: c[2] as usize,
                culled_covariance: c[3] as usize,
                culled_opacity: c[4] as usize,
                culled_offscreen: c[5] as usize,
                visible: c[6] as usize,
                intersections: intersections as usize,
            });
        }
        Ok(((images, diagnostics), status))
    }
}

/// The camera uniform's `flags`, in 16-byte elements from its start.
const CAMERA_FLAGS_OFFSET: usize = 8;

/// A second handle on `buffer`'s first `len` values.
fn share(buffer: &GpuBuffer, len: usize) -> GpuBuffer {
    GpuBuffer {
        buffer: buffer.buffer.clone(),
        len,
    }
}

fn rasterize_backward_kernel(
    context: &GpuContext,
    gpu_options: GpuOptions,
) -> Result<std::sync::Arc<crate::backend::Kernel>, GpuSplatError> {
    let mode = gpu_options
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
    Ok(context.kernel(&KernelSource {
        name,
        wgsl: Cow::Owned(wgsl),
        entry_point: "rasterize_backward",
    })?)
}

/// Result of [`forward`]: images and diagnostics per camera, and the GPU state [`backward`]
/// needs (the uploaded Gaussians and the workspace holding the pass).
pub struct GpuForward {
    /// One per camera, in the order given.
    pub images: Vec<RenderedImage<f32>>,
    /// One per camera.
    pub diagnostics: Vec<SplatDiagnostics>,
    gaussians: ResidentGaussians,
    workspace: SplatWorkspace,
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

/// [`forward`] with gpu-specific options: the Gaussians uploaded, rendered in a fresh
/// workspace ([`SplatWorkspace::forward_checked`]) and the images downloaded.
pub fn forward_with(
    context: &GpuContext,
    gaussians: &GaussianSet<'_, f32>,
    cameras: &[Camera],
    options: &RasterOptions,
    gpu_options: GpuOptions,
) -> Result<GpuForward, GpuSplatError> {
    validate_call(cameras, options)?;
    let gaussians = ResidentGaussians::upload(context, gaussians)?;
    let mut workspace = SplatWorkspace::new(context, gpu_options, None)?;
    workspace.forward_checked(context, gaussians.view(), cameras, options)?;
    let (images, diagnostics) = workspace.download_images(context)?;
    Ok(GpuForward {
        images,
        diagnostics,
        gaussians,
        workspace,
    })
}

impl GpuForward {
    /// Per camera, the number of bands of tile rows its pairs were binned in.
    pub fn band_counts(&self) -> Vec<usize> {
        self.workspace.band_counts()
    }
}

/// Gradients of the loss with respect to the Gaussians, summed over the forward call's
/// cameras. `gaussians` must be the set passed to [`forward`]; the upstream gradients are
/// checked (sizes and finiteness), uploaded, and the gradients downloaded.
pub fn backward(
    context: &GpuContext,
    forward: &GpuForward,
    gaussians: &GaussianSet<'_, f32>,
    upstream: &[ImageGradient<'_, f32>],
) -> Result<SplatGradients<f32>, GpuSplatError> {
    gaussians.validate()?;
    let resident = &forward.gaussians;
    if gaussians.len() != resident.len() || gaussians.sh_degree != resident.sh_degree {
        return Err(SplatError::GaussiansChanged {
            expected: resident.len(),
            actual: gaussians.len(),
        }
        .into());
    }
    let cameras = &forward.workspace.call()?.cameras;
    if upstream.len() != cameras.len() {
        return Err(SplatError::GradientCount {
            expected: cameras.len(),
            actual: upstream.len(),
        }
        .into());
    }
    let upload = |what, values: Option<&[f32]>| values.map(|v| context.upload(what, v)).transpose();
    let uploaded = upstream
        .iter()
        .zip(cameras)
        .enumerate()
        .map(|(index, (gradient, camera))| {
            gradient.check(index, camera.width as usize * camera.height as usize)?;
            Ok((
                context.upload("d colour", gradient.colour)?,
                upload("d alpha", gradient.alpha)?,
                upload("d depth", gradient.depth)?,
            ))
        })
        .collect::<Result<Vec<_>, GpuSplatError>>()?;
    let views: Vec<DeviceImageGradient<'_>> = uploaded
        .iter()
        .map(|(colour, alpha, depth)| DeviceImageGradient {
            colour,
            alpha: alpha.as_ref(),
            depth: depth.as_ref(),
        })
        .collect();
    let mut encoder = context.encoder();
    let workspace = &forward.workspace;
    workspace.backward(context, &mut encoder, resident.view(), &views)?;
    context.submit_and_wait(encoder)?;
    workspace.gradients()?.download(context)
}

/// Input gradients on the GPU, summed over the cameras (f32, the layouts of the inputs):
/// `means` `N x 3`, `covariances` `N x 6`, `opacities` `N`, `sh` `N x k x 3`, and
/// `mean_2d_norm` `N` (the norm of each Gaussian's screen-space mean gradient, summed over
/// cameras, for densification).
pub struct ResidentGradients {
    means: GpuBuffer,
    covariances: GpuBuffer,
    opacities: GpuBuffer,
    sh: GpuBuffer,
    mean_2d_norm: GpuBuffer,
    diagnostics: GpuBuffer,
    count: u32,
    sh_coefficients: u32,
}

impl ResidentGradients {
    /// Every buffer, in the order of the fields.
    fn buffers(&self) -> [&GpuBuffer; 6] {
        [
            &self.means,
            &self.covariances,
            &self.opacities,
            &self.sh,
            &self.mean_2d_norm,
            &self.diagnostics,
        ]
    }

    pub fn means(&self) -> &GpuBuffer {
        &self.means
    }

    pub fn covariances(&self) -> &GpuBuffer {
        &self.covariances
    }

    pub fn opacities(&self) -> &GpuBuffer {
        &self.opacities
    }

    pub fn sh(&self) -> &GpuBuffer {
        &self.sh
    }

    pub fn mean_2d_norm(&self) -> &GpuBuffer {
        &self.mean_2d_norm
    }

    /// Copies the gradients to the host (one read-back).
    pub fn download(&self, context: &GpuContext) -> Result<SplatGradients<f32>, GpuSplatError> {
        debug_assert_eq!(self.means.len, self.count as usize * 3);
        debug_assert_eq!(
            self.sh.len,
            (self.count * self.sh_coefficients) as usize * 3
        );
        let sources = self.buffers().map(|buffer| (&buffer.buffer, buffer.len));
        let mut words = context.download_all::<u32>(context.encoder(), &sources)?;
        let diagnostics = words.pop().unwrap_or_default();
        let [means, covariances, opacities, sh, mean_2d_norm] = [0, 1, 2, 3, 4].map(|i| {
            std::mem::take(&mut words[i])
                .into_iter()
                .map(f32::from_bits)
                .collect::<Vec<f32>>()
        });
        Ok(SplatGradients {
            means,
            covariances,
            opacities,
            sh,
            mean_2d_norm,
            non_finite_gradients: diagnostics[7] as usize,
        })
    }
}

#[cfg(test)]
mod tests;
