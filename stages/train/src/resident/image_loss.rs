//! The photometric losses of the device-resident training step (`docs/resident-step.md`,
//! piece "image losses"): the ground truth uploaded once as 8-bit RGBA, and per iteration and
//! chosen camera, on the device, the target composited onto the iteration's background, the
//! L1, mask MSE and D-SSIM terms on the bound-box rect with their gradients with respect to
//! the rendered colour and alpha, PSNR on the rect, and the scalars accumulated into a device
//! log record the host reads only when it logs. The kernels are `shaders/train_image_loss.wgsl`;
//! the oracle is [`crate::losses::image_loss`] with [`crate::gaussians::psnr`], which this
//! computes in f32 with the same weights, normalisation, SSIM window and constants.
//!
//! An iteration, recorded into one encoder:
//! 1. [`ImageLoss::begin_iteration`]: one `GpuContext::write` of the iteration's record
//!    (32 + 64 bytes per camera) and the log's `current` cleared on the device;
//! 2. per chosen camera `c`: [`ImageLoss::record_camera`] (writes the camera's gradients);
//!    with LPIPS on, [`ImageLoss::record_target`], the resident LPIPS
//!    (`seqavatar_compute::lpips::gpu::ResidentLpips::record`, slot `c`, on the crop
//!    `LpipsLoss::crop` of the rect, factor `lpips_weight / cameras`; it adds into the colour
//!    gradient) and [`ImageLoss::record_lpips`] with its value buffer;
//! 3. [`ImageLoss::finish_iteration`].
//!
//! Nothing is read back; [`ImageLoss::download_log`] reads the log record when the host logs.

use std::borrow::Cow;
use std::sync::Arc;

use anyhow::{Context, bail, ensure};
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};
use seqavatar_compute::ssim::{SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, gaussian_window};

use crate::data::{ImageRecord, TrainingData};
use crate::losses::{ImageLossWeights, Rect};

const WGSL: &str = include_str!("../../../../shaders/train_image_loss.wgsl");
/// Threads per workgroup of every pixel kernel (`WORKGROUP` in the shader).
const WORKGROUP: usize = 256;
/// Words of one camera in the record (`LossCamera`).
const CAMERA_WORDS: usize = 16;
/// Words of the record's header (`LossRecord` before its cameras).
const HEADER_WORDS: usize = 8;
/// Words of the log record (`LossLog`).
const LOG_WORDS: usize = 20;
/// Planes of the first SSIM workspace (five window means per channel).
const MEAN_PLANES: usize = 15;
/// Planes of the second SSIM workspace (three adjoints per channel, then the SSIM map).
const ADJOINT_PLANES: usize = 10;

/// Where one image of [`GroundTruth`] lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TruthSlot {
    /// Index of the chunk buffer holding the image.
    pub chunk: usize,
    /// First pixel of the image in its chunk.
    pub offset: usize,
    pub width: usize,
    pub height: usize,
}

/// One ground-truth image as [`GroundTruth::upload`] takes it: `H x W x 3` colour bytes and
/// `H x W` mask bytes (255 = foreground), the layout of [`ImageRecord`].
#[derive(Clone, Copy, Debug)]
pub struct TruthImage<'a> {
    pub width: usize,
    pub height: usize,
    pub rgb: &'a [u8],
    pub mask: &'a [u8],
}

/// Every training image on the device, uploaded once: one `u32` per pixel,
/// `r | g << 8 | b << 16 | mask << 24` (4 bytes a pixel, the bytes the data already holds),
/// row-major per image, images packed in order into chunk buffers of at most the device's
/// storage-binding size (an image never straddles two chunks).
///
/// Sizes: the demo (`pipelines/synthetic.yaml`: 8 cameras x 48 frames at 256 x 256, 6
/// training cameras) takes 288 x 256 KiB = 72 MiB for its training split (96 MiB for all 384
/// images); a DNA-Rendering sequence of 48 cameras x 150 frames at 1024 x 1224 (after
/// `resolution_scale`) takes 7200 x 4.78 MiB = 33.6 GiB (its default split, 24 training
/// cameras x 100 frames, 11.2 GiB), more than any one binding: it is split over chunks and
/// needs that much device memory. The device's total memory is not queried (wgpu does not expose it): only the
/// per-buffer limits are checked, and an image larger than one binding is an error naming
/// the sizes. Streaming images in from the host in chunks, for sequences larger than the
/// device, can come later.
pub struct GroundTruth {
    chunks: Vec<GpuBuffer>,
    /// Per image index: its place, or `None` for an image not uploaded.
    slots: Vec<Option<TruthSlot>>,
    bytes: u64,
}

impl GroundTruth {
    /// The training-split images of `data` (`split == 0`), indexed like `data.images`
    /// (held-out images get no slot).
    pub fn upload_training(context: &GpuContext, data: &TrainingData) -> anyhow::Result<Self> {
        let images: Vec<Option<TruthImage<'_>>> = data
            .images
            .iter()
            .map(|record: &ImageRecord| {
                let camera = &data.cameras[record.view];
                (record.split == 0).then_some(TruthImage {
                    width: camera.width as usize,
                    height: camera.height as usize,
                    rgb: &record.rgb,
                    mask: &record.mask,
                })
            })
            .collect();
        Self::upload(context, &images)
    }

    /// Uploads `images` (`None` entries keep their index without an upload).
    pub fn upload(context: &GpuContext, images: &[Option<TruthImage<'_>>]) -> anyhow::Result<Self> {
        Self::upload_with_chunk_limit(context, images, context.max_binding_bytes())
    }

    /// [`Self::upload`] with chunks of at most `chunk_bytes` (tests: several chunks from small
    /// images).
    pub fn upload_with_chunk_limit(
        context: &GpuContext,
        images: &[Option<TruthImage<'_>>],
        chunk_bytes: u64,
    ) -> anyhow::Result<Self> {
        let chunk_pixels = (chunk_bytes.min(context.max_binding_bytes()) / 4) as usize;
        let mut slots = Vec::with_capacity(images.len());
        // Pixels of each chunk, as planned.
        let mut plan: Vec<Vec<usize>> = Vec::new();
        let mut filled = chunk_pixels;
        let mut bytes = 0u64;
        for (index, image) in images.iter().enumerate() {
            let Some(image) = image else {
                slots.push(None);
                continue;
            };
            let pixels = image.width * image.height;
            ensure!(
                image.rgb.len() == 3 * pixels && image.mask.len() == pixels,
                "ground truth image {index}: {} colour and {} mask bytes for {} x {} pixels",
                image.rgb.len(),
                image.mask.len(),
                image.width,
                image.height
            );
            ensure!(
                pixels > 0,
                "ground truth image {index} is empty ({} x {})",
                image.width,
                image.height
            );
            if pixels > chunk_pixels {
                bail!(
                    "ground truth image {index} ({} x {} px, {} bytes as 8-bit RGBA) exceeds the \
                     device's storage binding of {} bytes",
                    image.width,
                    image.height,
                    4 * pixels,
                    4 * chunk_pixels
                );
            }
            if filled + pixels > chunk_pixels {
                plan.push(Vec::new());
                filled = 0;
            }
            let chunk = plan.len() - 1;
            slots.push(Some(TruthSlot {
                chunk,
                offset: filled,
                width: image.width,
                height: image.height,
            }));
            plan[chunk].push(index);
            filled += pixels;
            bytes += 4 * pixels as u64;
        }
        let mut chunks = Vec::with_capacity(plan.len());
        for (chunk, members) in plan.iter().enumerate() {
            let mut words = Vec::new();
            for &index in members {
                let image = images[index].expect("planned images exist");
                words.extend(
                    image
                        .rgb
                        .chunks_exact(3)
                        .zip(image.mask)
                        .map(|(rgb, &mask)| {
                            u32::from(rgb[0])
                                | u32::from(rgb[1]) << 8
                                | u32::from(rgb[2]) << 16
                                | u32::from(mask) << 24
                        }),
                );
            }
            chunks.push(
                context
                    .upload(&format!("ground truth chunk {chunk}"), &words)
                    .with_context(|| {
                        format!(
                            "uploading ground truth chunk {chunk} of {} ({} bytes of {bytes} in all)",
                            plan.len(),
                            4 * words.len()
                        )
                    })?,
            );
        }
        Ok(Self {
            chunks,
            slots,
            bytes,
        })
    }

    /// The place of image `index`, or `None` when it was not uploaded.
    pub fn slot(&self, index: usize) -> Option<TruthSlot> {
        self.slots.get(index).copied().flatten()
    }

    /// Bytes on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    pub fn chunks(&self) -> usize {
        self.chunks.len()
    }
}

/// One chosen camera of an iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossCamera {
    /// Index of the ground-truth image (as given to [`GroundTruth::upload`]).
    pub image: usize,
    /// First pixel of this camera's image in the rendered colour (`3` values a pixel) and
    /// alpha buffers, and of its gradient in the gradient buffers.
    pub pixel_offset: usize,
    /// The padded bound box (`trainer::pad_rect` of the image's bound).
    pub rect: Rect,
    /// The iteration's background colour.
    pub background: [f64; 3],
}

/// Device buffers of rendered images (`colour` `P x 3`, `alpha` `P`, f32) or of their
/// gradients, with the cameras' images at their [`LossCamera::pixel_offset`]s.
#[derive(Clone, Copy, Debug)]
pub struct DeviceImages<'a> {
    pub colour: &'a GpuBuffer,
    pub alpha: &'a GpuBuffer,
}

/// The logged scalars of one iteration or their mean over iterations: `IterationStats`'s
/// image terms (the trainer adds AIAP into its total).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossValues {
    pub l1: f64,
    pub mask_mse: f64,
    /// `1 - SSIM` on the crop.
    pub dssim: f64,
    /// Unweighted LPIPS (0 when off).
    pub lpips: f64,
    pub psnr: f64,
    /// `l1 + mask_weight mask_mse + ssim_weight dssim + lpips_weight lpips`.
    pub total: f64,
}

impl LossValues {
    /// The values in `words`, each divided by `divisor`.
    fn from_words(words: &[f32], divisor: f64) -> Self {
        let v = |i: usize| f64::from(words[i]) / divisor;
        Self {
            l1: v(0),
            mask_mse: v(1),
            dssim: v(2),
            lpips: v(3),
            psnr: v(4),
            total: v(5),
        }
    }
}

/// The device log record as read back ([`ImageLoss::download_log`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossLog {
    /// The last finished iteration's values (its cameras' terms averaged: each times
    /// `1 / cameras`), what `IterationStats` of that iteration holds.
    pub last: LossValues,
    /// The mean of the per-iteration values over the iterations since the last reset.
    pub mean: LossValues,
    /// Iterations finished since the last reset.
    pub iterations: u32,
    /// The number of the last finished iteration.
    pub last_iteration: u32,
    /// The first iteration since the last reset whose values were not all finite, if any
    /// (the host reports it as the cpu path's `Divergence`).
    pub first_nonfinite_iteration: Option<u32>,
}

/// The workspace of the resident image losses: kernels, the per-iteration record, the SSIM
/// planes and reduction partials sized for the largest image, and the log record. Device
/// buffers:
/// - record: `8 + 16 x max_cameras` words (`LossRecord` of the shader);
/// - planes: `15 x max_pixels` f32, adjoints: `10 x max_pixels` f32;
/// - partials: `ceil(max_pixels / 256)` x 4 f32;
/// - log: 20 words (`LossLog`: `current[8]`, `sum[8]` f32 with entries l1, mask_mse, dssim,
///   lpips, psnr, total; then iterations, non-finite iterations, first non-finite iteration,
///   last iteration as u32).
pub struct ImageLoss {
    context: Arc<GpuContext>,
    weights: ImageLossWeights,
    lpips_weight: f64,
    max_pixels: usize,
    record: GpuBuffer,
    /// Per camera slot: the uniform naming it (with the plane stride and SSIM constants).
    slots: Vec<wgpu::Buffer>,
    planes: GpuBuffer,
    adjoints: GpuBuffer,
    partials: GpuBuffer,
    log: GpuBuffer,
    /// One image's composited target, `max_pixels x 3` (LPIPS on) or one value (off).
    targets: GpuBuffer,
    /// The cameras of the iteration being recorded (host copy, for dispatch sizes).
    cameras: Vec<(LossCamera, TruthSlot)>,
    kernels: Kernels,
}

struct Kernels {
    ssim_rows: Arc<Kernel>,
    ssim_columns: Arc<Kernel>,
    ssim_gradient_rows: Arc<Kernel>,
    gradient: Arc<Kernel>,
    reduce: Arc<Kernel>,
    add_lpips: Arc<Kernel>,
    composite_target: Arc<Kernel>,
    finish: Arc<Kernel>,
}

impl ImageLoss {
    /// A workspace for images of at most `max_pixels` pixels and at most `max_cameras`
    /// cameras per iteration, with the run's loss weights (`lpips_weight` 0 when LPIPS is
    /// off).
    pub fn new(
        context: Arc<GpuContext>,
        weights: ImageLossWeights,
        lpips_weight: f64,
        max_cameras: usize,
        max_pixels: usize,
    ) -> anyhow::Result<Self> {
        ensure!(
            max_cameras > 0,
            "image losses: max_cameras must be at least 1"
        );
        ensure!(
            max_pixels > 0,
            "image losses: max_pixels must be at least 1"
        );
        ensure!(
            u32::try_from(3 * max_pixels).is_ok()
                && u32::try_from(MEAN_PLANES * max_pixels).is_ok(),
            "image losses: {max_pixels} pixels exceed the kernels' 32-bit indexing"
        );
        let kernel = |name, entry_point| {
            context.kernel(&KernelSource {
                name,
                wgsl: Cow::Borrowed(WGSL),
                entry_point,
            })
        };
        let kernels = Kernels {
            ssim_rows: kernel("train_image_loss_ssim_rows", "ssim_rows")?,
            ssim_columns: kernel("train_image_loss_ssim_columns", "ssim_columns")?,
            ssim_gradient_rows: kernel(
                "train_image_loss_ssim_gradient_rows",
                "ssim_gradient_rows",
            )?,
            gradient: kernel("train_image_loss_gradient", "image_loss_gradient")?,
            reduce: kernel("train_image_loss_reduce", "image_loss_reduce")?,
            add_lpips: kernel("train_image_loss_add_lpips", "add_lpips")?,
            composite_target: kernel("train_image_loss_composite_target", "composite_target")?,
            finish: kernel("train_image_loss_finish_iteration", "finish_iteration")?,
        };
        let window = gaussian_window(SSIM_WINDOW, SSIM_SIGMA);
        let slots = (0..max_cameras)
            .map(|camera| {
                let mut words = [0u32; 16];
                words[0] = camera as u32;
                words[1] = max_pixels as u32;
                words[2] = (SSIM_C1 as f32).to_bits();
                words[3] = (SSIM_C2 as f32).to_bits();
                for (tap, &weight) in window.iter().enumerate() {
                    words[4 + tap] = (weight as f32).to_bits();
                }
                context.uniform("image loss camera slot", &words)
            })
            .collect();
        let log_words = [0u32; LOG_WORDS];
        Ok(Self {
            record: context.zeros(
                "image loss record",
                HEADER_WORDS + CAMERA_WORDS * max_cameras,
                4,
            )?,
            planes: context.zeros("image loss SSIM planes", MEAN_PLANES * max_pixels, 4)?,
            adjoints: context.zeros("image loss SSIM adjoints", ADJOINT_PLANES * max_pixels, 4)?,
            partials: context.zeros(
                "image loss partial sums",
                4 * max_pixels.div_ceil(WORKGROUP),
                4,
            )?,
            log: context.upload("image loss log", &log_words)?,
            targets: context.zeros(
                "image loss LPIPS target",
                if lpips_weight != 0.0 {
                    3 * max_pixels
                } else {
                    1
                },
                4,
            )?,
            slots,
            weights,
            lpips_weight,
            max_pixels,
            cameras: Vec::new(),
            kernels,
            context,
        })
    }

    /// Starts an iteration: checks the cameras, writes the iteration's record (one
    /// `GpuContext::write` of `32 + 64 x cameras` bytes) and clears the log's `current` on
    /// the device. Each camera's terms and gradients are scaled by `1 / cameras.len()`.
    pub fn begin_iteration(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        iteration: u64,
        cameras: &[LossCamera],
        truth: &GroundTruth,
    ) -> anyhow::Result<()> {
        ensure!(
            !cameras.is_empty() && cameras.len() <= self.slots.len(),
            "image losses: {} cameras, the workspace holds 1 to {}",
            cameras.len(),
            self.slots.len()
        );
        let scale = 1.0 / cameras.len() as f64;
        let mut words = Vec::with_capacity(HEADER_WORDS + CAMERA_WORDS * cameras.len());
        words.extend([
            iteration as u32,
            cameras.len() as u32,
            (self.weights.mask as f32).to_bits(),
            (self.weights.ssim as f32).to_bits(),
            (self.lpips_weight as f32).to_bits(),
            0,
            0,
            0,
        ]);
        self.cameras.clear();
        for (index, camera) in cameras.iter().enumerate() {
            let slot = truth.slot(camera.image).with_context(|| {
                format!(
                    "image losses: camera {index} names image {} which has no ground truth on the device",
                    camera.image
                )
            })?;
            let (w, h, rect) = (slot.width, slot.height, camera.rect);
            ensure!(
                rect.x0 < rect.x1 && rect.y0 < rect.y1 && rect.x1 <= w && rect.y1 <= h,
                "image losses: camera {index}: rect {rect:?} is empty or outside the {w} x {h} image"
            );
            ensure!(
                w * h <= self.max_pixels,
                "image losses: camera {index}: a {w} x {h} image exceeds the workspace's {} pixels",
                self.max_pixels
            );
            words.extend([
                slot.offset as u32,
                camera.pixel_offset as u32,
                w as u32,
                h as u32,
                rect.x0 as u32,
                rect.y0 as u32,
                rect.x1 as u32,
                rect.y1 as u32,
                (camera.background[0] as f32).to_bits(),
                (camera.background[1] as f32).to_bits(),
                (camera.background[2] as f32).to_bits(),
                (scale as f32).to_bits(),
                0,
                0,
                0,
                0,
            ]);
            self.cameras.push((*camera, slot));
        }
        self.context.write(&self.record.buffer, 0, &words)?;
        encoder.clear_buffer(&self.log.buffer, 0, Some(32));
        Ok(())
    }

    /// Camera `camera` of the iteration and its ground truth slot; an error when
    /// [`Self::begin_iteration`] did not begin it.
    fn begun(&self, camera: usize) -> anyhow::Result<(LossCamera, TruthSlot)> {
        self.cameras
            .get(camera)
            .copied()
            .with_context(|| format!("image losses: camera {camera} was not begun"))
    }

    /// Records camera `camera`'s losses (in [`Self::begin_iteration`]'s order): its
    /// gradients written into `gradients` (`=`, full image at the camera's pixel offset,
    /// zeros outside the rect, times `1 / cameras`) and its terms added into the log.
    pub fn record_camera(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        camera: usize,
        truth: &GroundTruth,
        rendered: DeviceImages<'_>,
        gradients: DeviceImages<'_>,
    ) -> anyhow::Result<()> {
        let (info, slot) = self.begun(camera)?;
        let pixels = slot.width * slot.height;
        let end = info.pixel_offset + pixels;
        for (what, images) in [("rendered", rendered), ("gradient", gradients)] {
            ensure!(
                images.colour.len >= 3 * end && images.alpha.len >= end,
                "image losses: camera {camera}: the {what} buffers hold {} colour and {} alpha \
                 values, pixels {}..{end} need {} and {end}",
                images.colour.len,
                images.alpha.len,
                info.pixel_offset,
                3 * end
            );
        }
        let uniform = &self.slots[camera];
        let chunk = &truth.chunks[slot.chunk].buffer;
        let crop_groups = (info.rect.area().div_ceil(WORKGROUP)) as u32;
        let context = &self.context;
        if self.weights.ssim != 0.0 {
            context.dispatch(
                encoder,
                &self.kernels.ssim_rows,
                &[
                    (0, uniform),
                    (1, &self.record.buffer),
                    (2, chunk),
                    (3, &rendered.colour.buffer),
                    (5, &self.planes.buffer),
                ],
                crop_groups,
            );
            // Both read one of the two plane workspaces and write the other.
            for kernel in [&self.kernels.ssim_columns, &self.kernels.ssim_gradient_rows] {
                context.dispatch(
                    encoder,
                    kernel,
                    &[
                        (0, uniform),
                        (1, &self.record.buffer),
                        (5, &self.planes.buffer),
                        (6, &self.adjoints.buffer),
                    ],
                    crop_groups,
                );
            }
        }
        context.dispatch(
            encoder,
            &self.kernels.gradient,
            &[
                (0, uniform),
                (1, &self.record.buffer),
                (2, chunk),
                (3, &rendered.colour.buffer),
                (4, &rendered.alpha.buffer),
                (5, &self.planes.buffer),
                (6, &self.adjoints.buffer),
                (7, &gradients.colour.buffer),
                (8, &gradients.alpha.buffer),
                (9, &self.partials.buffer),
            ],
            pixels.div_ceil(WORKGROUP) as u32,
        );
        context.dispatch(
            encoder,
            &self.kernels.reduce,
            &[
                (0, uniform),
                (1, &self.record.buffer),
                (9, &self.partials.buffer),
                (10, &self.log.buffer),
            ],
            1,
        );
        Ok(())
    }

    /// Records the composited target of camera `camera` into the workspace's target buffer
    /// and returns it: `H x W x 3` f32 from pixel 0, what the resident LPIPS
    /// (`compute::lpips::gpu::ResidentLpips::record`) compares the render with. Valid until
    /// the next camera's call; needs a workspace made with a nonzero `lpips_weight`.
    pub fn record_target(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        camera: usize,
        truth: &GroundTruth,
    ) -> anyhow::Result<&GpuBuffer> {
        let (_, slot) = self.begun(camera)?;
        ensure!(
            self.targets.len >= 3 * slot.width * slot.height,
            "image losses: the workspace was made without LPIPS (lpips_weight 0), it holds no target"
        );
        self.context.dispatch(
            encoder,
            &self.kernels.composite_target,
            &[
                (0, &self.slots[camera]),
                (1, &self.record.buffer),
                (2, &truth.chunks[slot.chunk].buffer),
                (12, &self.targets.buffer),
            ],
            (slot.width * slot.height).div_ceil(WORKGROUP) as u32,
        );
        Ok(&self.targets)
    }

    /// Adds camera `camera`'s LPIPS value (one f32 in `value`, as the resident LPIPS writes
    /// it) into the log: `lpips += value / cameras`, `total += lpips_weight value / cameras`.
    pub fn record_lpips(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        camera: usize,
        value: &GpuBuffer,
    ) -> anyhow::Result<()> {
        self.begun(camera)?;
        self.context.dispatch(
            encoder,
            &self.kernels.add_lpips,
            &[
                (0, &self.slots[camera]),
                (1, &self.record.buffer),
                (10, &self.log.buffer),
                (11, &value.buffer),
            ],
            1,
        );
        Ok(())
    }

    /// The device log record (layout in the type's documentation): its first words are
    /// the current iteration's `l1, mask_mse, dssim, lpips, psnr, total`, complete after
    /// [`ImageLoss::finish_iteration`] (the step copies them into its log ring).
    pub fn log_buffer(&self) -> &GpuBuffer {
        &self.log
    }

    /// Closes the iteration in the log (its values become `last` and join the mean).
    pub fn finish_iteration(&self, encoder: &mut wgpu::CommandEncoder) {
        self.context.dispatch(
            encoder,
            &self.kernels.finish,
            &[(1, &self.record.buffer), (10, &self.log.buffer)],
            1,
        );
    }

    /// Reads the log record back (one readback; submits `encoder` first).
    pub fn download_log(&self, encoder: wgpu::CommandEncoder) -> anyhow::Result<LossLog> {
        let words: Vec<u32> = self
            .context
            .download(encoder, &self.log.buffer, LOG_WORDS)?;
        let floats: Vec<f32> = words.iter().map(|&w| f32::from_bits(w)).collect();
        let iterations = words[16];
        Ok(LossLog {
            last: LossValues::from_words(&floats[0..8], 1.0),
            mean: LossValues::from_words(&floats[8..16], f64::from(iterations.max(1))),
            iterations,
            last_iteration: words[19],
            first_nonfinite_iteration: (words[17] > 0).then_some(words[18]),
        })
    }
}

#[cfg(test)]
mod tests;
