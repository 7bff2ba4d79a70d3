//! The `gpu` LPIPS trunk and its image gradient: the kernels of `shaders/lpips_forward.wgsl`
//! and `shaders/lpips_backward.wgsl` run through the shared [`GpuContext`]. Weights are
//! uploaded once; a batch larger than the device's buffer limit is split into groups of pairs.
//!
//! The gradient keeps every forward activation on the device, records the backward passes
//! into the forward's encoder and downloads the maps and the gradient once per group.

use std::borrow::Cow;
use std::sync::Arc;

use crate::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};

use super::{ConvSpec, DistanceMaps, LpipsError, LpipsNet, LpipsWeights, Step, TrunkInput, steps};

const FORWARD_WGSL: &str = include_str!("../../../../shaders/lpips_forward.wgsl");
const BACKWARD_WGSL: &str = include_str!("../../../../shaders/lpips_backward.wgsl");
const WORKGROUP: u32 = 64;
/// Channels one convolution thread handles (`CHANNELS_PER_THREAD` in both shaders).
const CHANNELS_PER_THREAD: usize = 4;

/// The kernels: (cache name, WGSL text, entry point).
const CONV: (&str, &str, &str) = ("lpips_conv2d_relu", FORWARD_WGSL, "conv2d_relu");
const POOL: (&str, &str, &str) = ("lpips_max_pool", FORWARD_WGSL, "max_pool");
const DISTANCE: (&str, &str, &str) = ("lpips_layer_distance", FORWARD_WGSL, "layer_distance");
const DISTANCE_BACKWARD: (&str, &str, &str) = (
    "lpips_distance_backward",
    BACKWARD_WGSL,
    "distance_backward",
);
const RELU_MASK: (&str, &str, &str) = ("lpips_relu_mask", BACKWARD_WGSL, "relu_mask");
const CONV_BACKWARD: (&str, &str, &str) = (
    "lpips_conv2d_backward_data",
    BACKWARD_WGSL,
    "conv2d_backward_data",
);
const POOL_BACKWARD: (&str, &str, &str) = (
    "lpips_max_pool_backward",
    BACKWARD_WGSL,
    "max_pool_backward",
);

fn source((name, wgsl, entry_point): (&'static str, &'static str, &'static str)) -> KernelSource {
    KernelSource {
        name,
        wgsl: Cow::Borrowed(wgsl),
        entry_point,
    }
}

/// The uniform block shared by all kernels (`LpipsParams` in `shaders/lpips_types.wgsl`;
/// see the kernels for each one's reading).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Params {
    images: u32,
    in_channels: u32,
    in_height: u32,
    in_width: u32,
    out_channels: u32,
    out_height: u32,
    out_width: u32,
    kernel: u32,
    stride: u32,
    padding: u32,
    total: u32,
    pad: u32,
}

/// This module's uniform struct for the layout test in `backend::shaders`.
#[cfg(test)]
pub(crate) fn wgsl_twins() -> Vec<crate::backend::shaders::WgslTwin> {
    use crate::backend::shaders::wgsl_twin;
    vec![
        wgsl_twin!(Params as "LpipsParams" in ["lpips_forward.wgsl", "lpips_backward.wgsl"] {
            "images" => images,
            "in_channels" => in_channels,
            "in_height" => in_height,
            "in_width" => in_width,
            "out_channels" => out_channels,
            "out_height" => out_height,
            "out_width" => out_width,
            "kernel" => kernel,
            "stride" => stride,
            "padding" => padding,
            "total" => total,
            "_pad" => pad,
        }),
    ]
}

/// Converts a size to the u32 the kernels index with, or an error naming it.
fn to_u32(what: &str, value: usize) -> Result<u32, LpipsError> {
    u32::try_from(value).map_err(|_| LpipsError::Input {
        message: format!("{what} = {value} exceeds the gpu's 32-bit indexing"),
    })
}

/// The shape of one convolution: `images` NCHW inputs of `in_channels x in_height x in_width`
/// to `out_channels x out_height x out_width`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct ConvShape {
    pub images: usize,
    pub in_channels: usize,
    pub in_height: usize,
    pub in_width: usize,
    pub out_channels: usize,
    pub out_height: usize,
    pub out_width: usize,
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
}

/// The shape of one max pool (no padding, floor mode) over `planes` planes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct PoolShape {
    pub planes: usize,
    pub in_height: usize,
    pub in_width: usize,
    pub out_height: usize,
    pub out_width: usize,
    pub kernel: usize,
    pub stride: usize,
}

impl ConvShape {
    /// Convolution `spec` over `images` inputs of `channels x height x width` (an empty
    /// output where the kernel does not fit).
    fn of(spec: &ConvSpec, images: usize, channels: usize, height: usize, width: usize) -> Self {
        Self {
            images,
            in_channels: channels,
            in_height: height,
            in_width: width,
            out_channels: spec.out_channels,
            out_height: spec.output_extent(height).unwrap_or(0),
            out_width: spec.output_extent(width).unwrap_or(0),
            kernel: spec.kernel,
            stride: spec.stride,
            padding: spec.padding,
        }
    }
}

impl PoolShape {
    /// A `kernel`/`stride` max pool over `planes` planes of `height x width` (an empty output
    /// where the kernel does not fit).
    fn of(kernel: usize, stride: usize, planes: usize, height: usize, width: usize) -> Self {
        Self {
            planes,
            in_height: height,
            in_width: width,
            out_height: Step::pool_extent(kernel, stride, height).unwrap_or(0),
            out_width: Step::pool_extent(kernel, stride, width).unwrap_or(0),
            kernel,
            stride,
        }
    }
}

/// One forward step as the backward needs it: which activation buffers it read and wrote.
enum Traced {
    Conv {
        conv: usize,
        shape: ConvShape,
        output: usize,
    },
    Pool {
        shape: PoolShape,
        input: usize,
    },
    Tap {
        layer: usize,
        features: usize,
        channels: usize,
        height: usize,
        width: usize,
    },
}

/// LPIPS weights resident on the gpu.
pub struct GpuLpips {
    context: Arc<GpuContext>,
    net: LpipsNet,
    /// Per convolution: (weight, bias).
    convs: Vec<(GpuBuffer, GpuBuffer)>,
    lins: Vec<GpuBuffer>,
}

impl GpuLpips {
    pub fn new(context: Arc<GpuContext>, weights: &LpipsWeights) -> Result<Self, LpipsError> {
        let mut convs = Vec::new();
        for conv in &weights.convs {
            convs.push((
                context.upload(&format!("{}.weight", conv.spec.name), &conv.weight)?,
                context.upload(&format!("{}.bias", conv.spec.name), &conv.bias)?,
            ));
        }
        let lins = weights
            .lins
            .iter()
            .enumerate()
            .map(|(layer, lin)| context.upload(&format!("lin{layer}"), lin))
            .collect::<Result<_, _>>()?;
        for kernel in [
            CONV,
            POOL,
            DISTANCE,
            DISTANCE_BACKWARD,
            RELU_MASK,
            CONV_BACKWARD,
            POOL_BACKWARD,
        ] {
            context.kernel(&source(kernel))?;
        }
        Ok(Self {
            context,
            net: weights.net,
            convs,
            lins,
        })
    }

    fn kernel(
        &self,
        kernel: (&'static str, &'static str, &'static str),
    ) -> Result<Arc<Kernel>, LpipsError> {
        Ok(self.context.kernel(&source(kernel))?)
    }

    /// The largest activation of one image, in f32 values.
    fn largest_activation(&self, height: usize, width: usize) -> usize {
        let (mut channels, mut h, mut w) = (3, height, width);
        let mut largest = channels * h * w;
        for step in steps(self.net) {
            match step {
                Step::Conv(spec) => {
                    h = spec.output_extent(h).unwrap_or(0);
                    w = spec.output_extent(w).unwrap_or(0);
                    channels = spec.out_channels;
                }
                Step::MaxPool { kernel, stride } => {
                    h = Step::pool_extent(kernel, stride, h).unwrap_or(0);
                    w = Step::pool_extent(kernel, stride, w).unwrap_or(0);
                }
                Step::Tap => {}
            }
            largest = largest.max(channels * h * w);
        }
        largest
    }

    /// Per-layer, per-pixel distance maps (same layout as [`super::cpu::distance_maps`]).
    pub fn distance_maps(&self, input: &TrunkInput) -> Result<DistanceMaps, LpipsError> {
        Ok(self.run(input, false)?.0)
    }

    /// The distance maps and the gradient of every pair's total (the sum over layers of each
    /// map's spatial mean) with respect to the pair's FIRST trunk input image (the second is a
    /// constant): `(pairs, 3, height, width)` row-major, images `0..pairs` of `input`.
    pub fn distance_gradient(
        &self,
        input: &TrunkInput,
    ) -> Result<(DistanceMaps, Vec<f32>), LpipsError> {
        self.run(input, true)
    }

    fn run(
        &self,
        input: &TrunkInput,
        with_gradient: bool,
    ) -> Result<(DistanceMaps, Vec<f32>), LpipsError> {
        super::tap_sizes(self.net, input.height, input.width)?;
        let pairs = input.batch / 2;
        let image_values = 3 * input.height * input.width;
        if !input.batch.is_multiple_of(2) || input.data.len() != input.batch * image_values {
            return Err(LpipsError::Input {
                message: format!(
                    "trunk input of {} values does not hold {} images",
                    input.data.len(),
                    input.batch
                ),
            });
        }
        // Every buffer holds at most one activation of the group's 2 * group images (the
        // gradients hold only the first half).
        let per_image = self.largest_activation(input.height, input.width);
        let limit = (self.context.max_binding_bytes() / 4) as usize;
        let pairs_per_group = limit / (2 * per_image).max(1);
        if pairs_per_group == 0 {
            return Err(LpipsError::Input {
                message: format!(
                    "a {} x {} image needs {} MB activations, more than the gpu's {} MB buffer limit",
                    input.height,
                    input.width,
                    2 * per_image * 4 / (1 << 20),
                    limit * 4 / (1 << 20)
                ),
            });
        }
        let mut maps: DistanceMaps = vec![Vec::new(); 5];
        let mut gradient = Vec::with_capacity(if with_gradient {
            pairs * image_values
        } else {
            0
        });
        for group_start in (0..pairs).step_by(pairs_per_group) {
            let group = pairs_per_group.min(pairs - group_start);
            // The group's first images, then its second images.
            let mut data = Vec::with_capacity(2 * group * image_values);
            data.extend_from_slice(
                &input.data[group_start * image_values..(group_start + group) * image_values],
            );
            data.extend_from_slice(
                &input.data[(pairs + group_start) * image_values
                    ..(pairs + group_start + group) * image_values],
            );
            let (group_maps, group_gradient) =
                self.run_group(&data, group, input.height, input.width, with_gradient)?;
            for (layer, map) in group_maps.into_iter().enumerate() {
                maps[layer].extend(map);
            }
            gradient.extend(group_gradient);
        }
        Ok((maps, gradient))
    }

    /// Forward (and, when asked, backward) of one group of pairs: `data` holds the group's
    /// first images then its second images.
    fn run_group(
        &self,
        data: &[f32],
        pairs: usize,
        height: usize,
        width: usize,
        with_gradient: bool,
    ) -> Result<(DistanceMaps, Vec<f32>), LpipsError> {
        let context = &self.context;
        let images = 2 * pairs;
        let mut encoder = context.encoder();
        // activations[0] is the input; every conv and pool appends its output.
        let mut activations = vec![context.upload("lpips input", data)?];
        let mut trace = Vec::new();
        let mut map_buffers: Vec<GpuBuffer> = Vec::new();
        let (mut channels, mut h, mut w) = (3_usize, height, width);
        let mut conv_index = 0;
        for step in steps(self.net) {
            let current = activations.len() - 1;
            match step {
                Step::Conv(spec) => {
                    let (weight, bias) =
                        self.convs
                            .get(conv_index)
                            .ok_or_else(|| LpipsError::Input {
                                message: "missing convolution weights".to_owned(),
                            })?;
                    let shape = ConvShape::of(&spec, images, channels, h, w);
                    let output = context.zeros(
                        &spec.name,
                        images * shape.out_channels * shape.out_height * shape.out_width,
                        4,
                    )?;
                    self.record_conv(
                        &mut encoder,
                        shape,
                        &activations[current],
                        weight,
                        bias,
                        &output,
                    )?;
                    activations.push(output);
                    trace.push(Traced::Conv {
                        conv: conv_index,
                        shape: ConvShape {
                            images: pairs,
                            ..shape
                        },
                        output: current + 1,
                    });
                    conv_index += 1;
                    (channels, h, w) = (shape.out_channels, shape.out_height, shape.out_width);
                }
                Step::MaxPool { kernel, stride } => {
                    let shape = PoolShape::of(kernel, stride, images * channels, h, w);
                    let output = context.zeros(
                        "lpips max pool",
                        shape.planes * shape.out_height * shape.out_width,
                        4,
                    )?;
                    self.record_max_pool(&mut encoder, shape, &activations[current], &output)?;
                    activations.push(output);
                    trace.push(Traced::Pool {
                        shape: PoolShape {
                            planes: pairs * channels,
                            ..shape
                        },
                        input: current,
                    });
                    (h, w) = (shape.out_height, shape.out_width);
                }
                Step::Tap => {
                    let layer = map_buffers.len();
                    let lin = self.lins.get(layer).ok_or_else(|| LpipsError::Input {
                        message: "more taps than lin layers".to_owned(),
                    })?;
                    let total = to_u32("distance threads", pairs * h * w)?;
                    let params = Params {
                        images: to_u32("pairs", pairs)?,
                        in_channels: to_u32("channels", channels)?,
                        in_height: to_u32("height", h)?,
                        in_width: to_u32("width", w)?,
                        total,
                        ..Params::default()
                    };
                    let map = context.zeros("lpips distance map", pairs * h * w, 4)?;
                    context.call(
                        &mut encoder,
                        &*self.kernel(DISTANCE)?,
                        &params,
                        &[
                            (1, &activations[current].buffer),
                            (2, &lin.buffer),
                            (4, &map.buffer),
                        ],
                        total.div_ceil(WORKGROUP),
                    );
                    map_buffers.push(map);
                    trace.push(Traced::Tap {
                        layer,
                        features: current,
                        channels,
                        height: h,
                        width: w,
                    });
                }
            }
        }
        let mut gradients: Vec<GpuBuffer> = Vec::new();
        if with_gradient {
            // The gradient with respect to the current activation of the first images;
            // `None` while it is still zero (no tap after this point).
            let mut current: Option<GpuBuffer> = None;
            for traced in trace.iter().rev() {
                match *traced {
                    Traced::Tap {
                        layer,
                        features,
                        channels,
                        height,
                        width,
                    } => {
                        let target = match current.take() {
                            Some(buffer) => buffer,
                            None => context.zeros(
                                "lpips feature gradient",
                                pairs * channels * height * width,
                                4,
                            )?,
                        };
                        self.record_distance_backward(
                            &mut encoder,
                            pairs,
                            [channels, height, width],
                            &activations[features],
                            &self.lins[layer],
                            &target,
                        )?;
                        current = Some(target);
                    }
                    Traced::Conv {
                        conv,
                        shape,
                        output,
                    } => {
                        let Some(upstream) = current.take() else {
                            continue;
                        };
                        let target = context.zeros(
                            "lpips conv input gradient",
                            pairs * shape.in_channels * shape.in_height * shape.in_width,
                            4,
                        )?;
                        self.record_conv_backward(
                            &mut encoder,
                            shape,
                            &activations[output],
                            &upstream,
                            &self.convs[conv].0,
                            &target,
                        )?;
                        gradients.push(upstream);
                        current = Some(target);
                    }
                    Traced::Pool { shape, input } => {
                        let Some(upstream) = current.take() else {
                            continue;
                        };
                        let target = context.zeros(
                            "lpips pool input gradient",
                            shape.planes * shape.in_height * shape.in_width,
                            4,
                        )?;
                        self.record_max_pool_backward(
                            &mut encoder,
                            shape,
                            &activations[input],
                            &upstream,
                            &target,
                        )?;
                        gradients.push(upstream);
                        current = Some(target);
                    }
                }
            }
            gradients.push(match current {
                Some(buffer) => buffer,
                None => context.zeros("lpips input gradient", pairs * 3 * height * width, 4)?,
            });
        }
        let mut sources: Vec<_> = map_buffers
            .iter()
            .map(|map| (&map.buffer, map.len))
            .collect();
        if let Some(input_gradient) = gradients.last() {
            sources.push((&input_gradient.buffer, input_gradient.len));
        }
        let mut values = context.download_all::<f32>(encoder, &sources)?;
        drop((activations, gradients));
        let gradient = if with_gradient {
            values.pop().unwrap_or_default()
        } else {
            Vec::new()
        };
        Ok((values, gradient))
    }

    /// Records `output = relu(conv(input) + bias)` for `shape.images` images.
    pub(super) fn record_conv(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        shape: ConvShape,
        input: &GpuBuffer,
        weight: &GpuBuffer,
        bias: &GpuBuffer,
        output: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let groups = shape.out_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = to_u32(
            "conv threads",
            shape.images * groups * shape.out_height * shape.out_width,
        )?;
        self.context.call(
            encoder,
            &*self.kernel(CONV)?,
            &conv_params(shape, total)?,
            &[
                (1, &input.buffer),
                (2, &weight.buffer),
                (3, &bias.buffer),
                (4, &output.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(())
    }

    /// Records the max pool of `shape.planes` planes.
    pub(super) fn record_max_pool(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        shape: PoolShape,
        input: &GpuBuffer,
        output: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let total = to_u32(
            "pool threads",
            shape.planes * shape.out_height * shape.out_width,
        )?;
        self.context.call(
            encoder,
            &*self.kernel(POOL)?,
            &pool_params(shape, total)?,
            &[(1, &input.buffer), (4, &output.buffer)],
            total.div_ceil(WORKGROUP),
        );
        Ok(())
    }

    /// Records `target += d(spatial mean of the layer distance) / d(first features)` for
    /// `pairs` pairs whose `[channels, height, width]` features (first images, then second
    /// images) are in `features`.
    pub(super) fn record_distance_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pairs: usize,
        [channels, height, width]: [usize; 3],
        features: &GpuBuffer,
        lin: &GpuBuffer,
        target: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let total = to_u32("distance gradient threads", pairs * height * width)?;
        let params = Params {
            images: to_u32("pairs", pairs)?,
            in_channels: to_u32("channels", channels)?,
            in_height: to_u32("height", height)?,
            in_width: to_u32("width", width)?,
            total,
            ..Params::default()
        };
        self.context.call(
            encoder,
            &*self.kernel(DISTANCE_BACKWARD)?,
            &params,
            &[(1, &features.buffer), (2, &lin.buffer), (4, &target.buffer)],
            total.div_ceil(WORKGROUP),
        );
        Ok(())
    }

    /// Records the backward of `relu(conv(x) + bias)` for the first `shape.images` images:
    /// masks `upstream` in place where the forward `output` is not positive, then writes the
    /// transposed convolution of it into `target` (`shape.images` inputs' gradient).
    pub(super) fn record_conv_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        shape: ConvShape,
        output: &GpuBuffer,
        upstream: &GpuBuffer,
        weight: &GpuBuffer,
        target: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let mask_total = to_u32(
            "relu mask threads",
            shape.images * shape.out_channels * shape.out_height * shape.out_width,
        )?;
        self.context.call(
            encoder,
            &*self.kernel(RELU_MASK)?,
            &Params {
                total: mask_total,
                ..Params::default()
            },
            &[(1, &output.buffer), (4, &upstream.buffer)],
            mask_total.div_ceil(WORKGROUP),
        );
        let groups = shape.in_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = to_u32(
            "conv gradient threads",
            shape.images * groups * shape.in_height * shape.in_width,
        )?;
        self.context.call(
            encoder,
            &*self.kernel(CONV_BACKWARD)?,
            &conv_params(shape, total)?,
            &[
                (2, &weight.buffer),
                (3, &upstream.buffer),
                (4, &target.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(())
    }

    /// Records the max pool's backward for `shape.planes` planes: `target` (the pool input's
    /// gradient) gathers `upstream` at each window's first arg-max in the forward `input`.
    pub(super) fn record_max_pool_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        shape: PoolShape,
        input: &GpuBuffer,
        upstream: &GpuBuffer,
        target: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let total = to_u32(
            "pool gradient threads",
            shape.planes * shape.in_height * shape.in_width,
        )?;
        self.context.call(
            encoder,
            &*self.kernel(POOL_BACKWARD)?,
            &pool_params(shape, total)?,
            &[
                (1, &input.buffer),
                (3, &upstream.buffer),
                (4, &target.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(())
    }
}

fn conv_params(shape: ConvShape, total: u32) -> Result<Params, LpipsError> {
    Ok(Params {
        images: to_u32("images", shape.images)?,
        in_channels: to_u32("channels", shape.in_channels)?,
        in_height: to_u32("height", shape.in_height)?,
        in_width: to_u32("width", shape.in_width)?,
        out_channels: to_u32("channels", shape.out_channels)?,
        out_height: to_u32("height", shape.out_height)?,
        out_width: to_u32("width", shape.out_width)?,
        kernel: to_u32("kernel", shape.kernel)?,
        stride: to_u32("stride", shape.stride)?,
        padding: to_u32("padding", shape.padding)?,
        total,
        pad: 0,
    })
}

fn pool_params(shape: PoolShape, total: u32) -> Result<Params, LpipsError> {
    Ok(Params {
        images: to_u32("planes", shape.planes)?,
        in_height: to_u32("height", shape.in_height)?,
        in_width: to_u32("width", shape.in_width)?,
        out_height: to_u32("height", shape.out_height)?,
        out_width: to_u32("width", shape.out_width)?,
        kernel: to_u32("kernel", shape.kernel)?,
        stride: to_u32("stride", shape.stride)?,
        total,
        ..Params::default()
    })
}

const RESIDENT_WGSL: &str = include_str!("../../../../shaders/lpips_resident.wgsl");
const CROP_TO_TRUNK: (&str, &str, &str) = (
    "lpips_resident_crop_to_trunk",
    RESIDENT_WGSL,
    "crop_to_trunk",
);
const REDUCE_DISTANCE: (&str, &str, &str) = (
    "lpips_resident_reduce_distance",
    RESIDENT_WGSL,
    "reduce_distance",
);
const ADD_IMAGE_GRADIENT: (&str, &str, &str) = (
    "lpips_resident_add_image_gradient",
    RESIDENT_WGSL,
    "add_image_gradient",
);
/// Words of one [`Params`] block.
const PARAMS_WORDS: usize = 12;

/// The per-call uniform of `shaders/lpips_resident.wgsl` (`LpipsResidentParams`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ResidentParams {
    render_offset: u32,
    render_width: u32,
    target_offset: u32,
    target_width: u32,
    x0: u32,
    y0: u32,
    crop_width: u32,
    crop_height: u32,
    gradient_factor: f32,
    signed_mapping: u32,
    pad: [u32; 2],
    shift: [f32; 4],
    scale: [f32; 4],
    layer_pixels: [[u32; 4]; 2],
}

/// The resident path's uniform struct for the layout test in `backend::shaders`.
#[cfg(test)]
pub(crate) fn resident_wgsl_twins() -> Vec<crate::backend::shaders::WgslTwin> {
    use crate::backend::shaders::wgsl_twin;
    vec![
        wgsl_twin!(ResidentParams as "LpipsResidentParams" in ["lpips_resident.wgsl"] {
            "render_offset" => render_offset,
            "render_width" => render_width,
            "target_offset" => target_offset,
            "target_width" => target_width,
            "x0" => x0,
            "y0" => y0,
            "crop_width" => crop_width,
            "crop_height" => crop_height,
            "gradient_factor" => gradient_factor,
            "signed_mapping" => signed_mapping,
            "_pad0" => pad[0],
            "_pad1" => pad[1],
            "shift" => shift,
            "scale" => scale,
            "layer_pixels0" => layer_pixels[0],
            "layer_pixels1" => layer_pixels[1],
        }),
    ]
}

/// A device image as the resident LPIPS reads it: an interleaved `H x W x 3` f32 image
/// starting at pixel `offset` of `buffer`, rows of `width` pixels.
#[derive(Clone, Copy, Debug)]
pub struct DeviceImage<'a> {
    pub buffer: &'a GpuBuffer,
    pub offset: usize,
    pub width: usize,
    pub height: usize,
}

/// The images one [`ResidentLpips::record`] call compares: `crop` of `render` and of
/// `target`.
#[derive(Clone, Copy, Debug)]
pub struct CropPair<'a> {
    pub render: DeviceImage<'a>,
    pub target: DeviceImage<'a>,
    pub crop: Crop,
}

/// A crop `[x0, x0 + width) x [y0, y0 + height)` of a [`DeviceImage`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crop {
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
}

/// Which buffer of the resident workspace an op reads or writes.
#[derive(Clone, Copy, Debug)]
enum Planned {
    /// Forward conv from activation `input` into `input + 1`.
    Conv { conv: usize, input: usize },
    /// Forward max pool from activation `input` into `input + 1`.
    Pool { input: usize },
    /// Distance map `layer` of activation `features`.
    Distance { layer: usize, features: usize },
    /// Zeroes `len` values of gradient buffer `target` (before the last tap's backward).
    Clear { target: usize, len: usize },
    DistanceBackward {
        layer: usize,
        features: usize,
        target: usize,
    },
    /// ReLU mask of gradient `upstream` by activation `output`.
    ReluMask { output: usize, upstream: usize },
    ConvBackward {
        conv: usize,
        upstream: usize,
        target: usize,
    },
    PoolBackward {
        input: usize,
        upstream: usize,
        target: usize,
    },
}

/// One op of a resident LPIPS evaluation: what it touches, its kernel parameters and its
/// workgroups (none for `Clear`).
#[derive(Clone, Copy, Debug)]
struct PlannedOp {
    op: Planned,
    params: Params,
    workgroups: u32,
}

/// Per camera slot: its staging buffer (the call's record), its uniforms and its value.
struct ResidentSlot {
    /// `ResidentParams` then one `Params` per op, written with one `GpuContext::write` per
    /// call and copied into the uniforms on the device.
    staging: GpuBuffer,
    resident_uniform: wgpu::Buffer,
    op_uniforms: Vec<wgpu::Buffer>,
    value: GpuBuffer,
}

/// The LPIPS loss on device buffers, for the resident training step: the workspace
/// (activations for two crops of at most `max_height x max_width`, two gradient buffers,
/// the distance maps) allocated once, per camera slot a staging buffer, the kernels'
/// uniforms and a value buffer (one f32).
///
/// [`ResidentLpips::record`] records, into the caller's encoder: the render and target crops
/// cut from device images into the trunk input, the trunk forward, the distance reduced to
/// one value (written to [`ResidentLpips::value`]), the backward, and `factor x` the image
/// gradient added (`+=`) into the render's colour gradient buffer on the crop. The one
/// upload per call is its record, one `GpuContext::write`: the crop and images (112 bytes)
/// and the trunk's kernel parameters for the crop's shape (48 bytes per op: 57 ops for VGG,
/// 2848 bytes in all; 29 for AlexNet, 1504 bytes), since the crop's shape changes from call
/// to call (computing them on the device from the crop's size would remove all but the first
/// 112 bytes).
pub struct ResidentLpips {
    context: Arc<GpuContext>,
    net: LpipsNet,
    input: super::LpipsInput,
    shift: [f32; 3],
    scale: [f32; 3],
    max_height: usize,
    max_width: usize,
    /// activations[0] is the trunk input; every conv and pool appends its output (two
    /// images each).
    activations: Vec<GpuBuffer>,
    gradients: [GpuBuffer; 2],
    maps: Vec<GpuBuffer>,
    slots: Vec<ResidentSlot>,
}

impl GpuLpips {
    /// A resident workspace for crops of at most `max_height x max_width` and `cameras`
    /// calls per submission (one slot each), feeding images through `input`.
    pub fn resident(
        &self,
        weights: &LpipsWeights,
        input: super::LpipsInput,
        max_height: usize,
        max_width: usize,
        cameras: usize,
    ) -> Result<ResidentLpips, LpipsError> {
        if weights.net != self.net {
            return Err(LpipsError::Input {
                message: format!(
                    "resident LPIPS: weights of {} for a {} trunk",
                    weights.net.name(),
                    self.net.name()
                ),
            });
        }
        let plan = self.plan(max_height, max_width)?;
        let context = &self.context;
        // Every buffer is sized for the largest crop (every extent grows with the input's).
        let mut activations =
            vec![context.zeros("lpips trunk input", 6 * max_height * max_width, 4)?];
        let mut gradient_len = 3 * max_height * max_width;
        let (mut channels, mut h, mut w) = (3_usize, max_height, max_width);
        for step in steps(self.net) {
            match step {
                Step::Conv(spec) => {
                    channels = spec.out_channels;
                    h = spec.output_extent(h).unwrap_or(0);
                    w = spec.output_extent(w).unwrap_or(0);
                }
                Step::MaxPool { kernel, stride } => {
                    h = Step::pool_extent(kernel, stride, h).unwrap_or(0);
                    w = Step::pool_extent(kernel, stride, w).unwrap_or(0);
                }
                Step::Tap => continue,
            }
            gradient_len = gradient_len.max(channels * h * w);
            activations.push(context.zeros("lpips activation", 2 * channels * h * w, 4)?);
        }
        let gradients = [
            context.zeros("lpips gradient ping", gradient_len, 4)?,
            context.zeros("lpips gradient pong", gradient_len, 4)?,
        ];
        let maps = plan
            .iter()
            .filter(|op| matches!(op.op, Planned::Distance { .. }))
            .map(|op| {
                context.zeros(
                    "lpips distance map",
                    (op.params.in_height * op.params.in_width) as usize,
                    4,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        let with_params = plan
            .iter()
            .filter(|op| !matches!(op.op, Planned::Clear { .. }))
            .count();
        let slots = (0..cameras.max(1))
            .map(|_| -> Result<ResidentSlot, LpipsError> {
                Ok(ResidentSlot {
                    staging: context.zeros(
                        "lpips resident record",
                        size_of::<ResidentParams>() / 4 + PARAMS_WORDS * with_params,
                        4,
                    )?,
                    resident_uniform: context
                        .uniform("lpips resident params", &ResidentParams::default()),
                    op_uniforms: (0..with_params)
                        .map(|_| context.uniform("lpips resident op params", &Params::default()))
                        .collect(),
                    value: context.zeros("lpips resident value", 1, 4)?,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        for kernel in [CROP_TO_TRUNK, REDUCE_DISTANCE, ADD_IMAGE_GRADIENT] {
            context.kernel(&source(kernel))?;
        }
        Ok(ResidentLpips {
            context: context.clone(),
            net: self.net,
            input,
            shift: weights.shift,
            scale: weights.scale,
            max_height,
            max_width,
            activations,
            gradients,
            maps,
            slots,
        })
    }

    /// The ops of one evaluation (forward, then backward for the first image) of one pair
    /// of `height x width` crops, with their kernel parameters.
    fn plan(&self, height: usize, width: usize) -> Result<Vec<PlannedOp>, LpipsError> {
        super::tap_sizes(self.net, height, width)?;
        let mut plan = Vec::new();
        // Forward, with what the backward needs.
        let mut trace = Vec::new();
        let (mut channels, mut h, mut w) = (3_usize, height, width);
        let (mut conv_index, mut layer, mut current) = (0, 0, 0);
        for step in steps(self.net) {
            match step {
                Step::Conv(spec) => {
                    let shape = ConvShape::of(&spec, 2, channels, h, w);
                    let groups = shape.out_channels.div_ceil(CHANNELS_PER_THREAD);
                    let total = to_u32(
                        "conv threads",
                        2 * groups * shape.out_height * shape.out_width,
                    )?;
                    plan.push(PlannedOp {
                        op: Planned::Conv {
                            conv: conv_index,
                            input: current,
                        },
                        params: conv_params(shape, total)?,
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    trace.push(Traced::Conv {
                        conv: conv_index,
                        shape: ConvShape { images: 1, ..shape },
                        output: current + 1,
                    });
                    conv_index += 1;
                    current += 1;
                    (channels, h, w) = (shape.out_channels, shape.out_height, shape.out_width);
                }
                Step::MaxPool { kernel, stride } => {
                    let shape = PoolShape::of(kernel, stride, 2 * channels, h, w);
                    let total = to_u32(
                        "pool threads",
                        shape.planes * shape.out_height * shape.out_width,
                    )?;
                    plan.push(PlannedOp {
                        op: Planned::Pool { input: current },
                        params: pool_params(shape, total)?,
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    trace.push(Traced::Pool {
                        shape: PoolShape {
                            planes: channels,
                            ..shape
                        },
                        input: current,
                    });
                    current += 1;
                    (h, w) = (shape.out_height, shape.out_width);
                }
                Step::Tap => {
                    let total = to_u32("distance threads", h * w)?;
                    plan.push(PlannedOp {
                        op: Planned::Distance {
                            layer,
                            features: current,
                        },
                        params: Params {
                            images: 1,
                            in_channels: to_u32("channels", channels)?,
                            in_height: to_u32("height", h)?,
                            in_width: to_u32("width", w)?,
                            total,
                            ..Params::default()
                        },
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    trace.push(Traced::Tap {
                        layer,
                        features: current,
                        channels,
                        height: h,
                        width: w,
                    });
                    layer += 1;
                }
            }
        }
        // Backward: the gradient with respect to the current activation lives in gradient
        // buffer `at` (`None` while it is still zero).
        let mut at: Option<usize> = None;
        for traced in trace.iter().rev() {
            match *traced {
                Traced::Tap {
                    layer,
                    features,
                    channels,
                    height,
                    width,
                } => {
                    let target = match at {
                        Some(target) => target,
                        None => {
                            plan.push(PlannedOp {
                                op: Planned::Clear {
                                    target: 0,
                                    len: channels * height * width,
                                },
                                params: Params::default(),
                                workgroups: 0,
                            });
                            0
                        }
                    };
                    let total = to_u32("distance gradient threads", height * width)?;
                    plan.push(PlannedOp {
                        op: Planned::DistanceBackward {
                            layer,
                            features,
                            target,
                        },
                        params: Params {
                            images: 1,
                            in_channels: to_u32("channels", channels)?,
                            in_height: to_u32("height", height)?,
                            in_width: to_u32("width", width)?,
                            total,
                            ..Params::default()
                        },
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    at = Some(target);
                }
                Traced::Conv {
                    conv,
                    shape,
                    output,
                } => {
                    let Some(upstream) = at else {
                        continue;
                    };
                    let mask_total = to_u32(
                        "relu mask threads",
                        shape.out_channels * shape.out_height * shape.out_width,
                    )?;
                    plan.push(PlannedOp {
                        op: Planned::ReluMask { output, upstream },
                        params: Params {
                            total: mask_total,
                            ..Params::default()
                        },
                        workgroups: mask_total.div_ceil(WORKGROUP),
                    });
                    let groups = shape.in_channels.div_ceil(CHANNELS_PER_THREAD);
                    let total = to_u32(
                        "conv gradient threads",
                        groups * shape.in_height * shape.in_width,
                    )?;
                    plan.push(PlannedOp {
                        op: Planned::ConvBackward {
                            conv,
                            upstream,
                            target: 1 - upstream,
                        },
                        params: conv_params(shape, total)?,
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    at = Some(1 - upstream);
                }
                Traced::Pool { shape, input } => {
                    let Some(upstream) = at else {
                        continue;
                    };
                    let total = to_u32(
                        "pool gradient threads",
                        shape.planes * shape.in_height * shape.in_width,
                    )?;
                    plan.push(PlannedOp {
                        op: Planned::PoolBackward {
                            input,
                            upstream,
                            target: 1 - upstream,
                        },
                        params: pool_params(shape, total)?,
                        workgroups: total.div_ceil(WORKGROUP),
                    });
                    at = Some(1 - upstream);
                }
            }
        }
        if at.is_none() {
            return Err(LpipsError::Input {
                message: "resident LPIPS: the trunk has no tap".to_owned(),
            });
        }
        Ok(plan)
    }
}

impl ResidentLpips {
    /// The value buffer of camera slot `slot` (one f32, the last recorded distance).
    pub fn value(&self, slot: usize) -> &GpuBuffer {
        &self.slots[slot].value
    }

    /// Camera slots (calls per submission).
    pub fn slots(&self) -> usize {
        self.slots.len()
    }

    /// Records, with camera slot `slot` (one call per slot per submission): LPIPS between
    /// `crop` of `render` and of `target` ([`CropPair`]) into [`Self::value`], and `factor x` its gradient
    /// with respect to the render added into `gradient` (same layout as `render`) on the crop.
    pub fn record(
        &self,
        gpu: &GpuLpips,
        encoder: &mut wgpu::CommandEncoder,
        slot: usize,
        CropPair {
            render,
            target,
            crop,
        }: CropPair<'_>,
        factor: f32,
        gradient: &GpuBuffer,
    ) -> Result<(), LpipsError> {
        let input_error = |message: String| LpipsError::Input { message };
        let slot_state = self.slots.get(slot).ok_or_else(|| {
            input_error(format!(
                "resident LPIPS: slot {slot} of a workspace with {}",
                self.slots.len()
            ))
        })?;
        if gpu.net != self.net {
            return Err(input_error(
                "resident LPIPS: another trunk's workspace".to_owned(),
            ));
        }
        if crop.height > self.max_height || crop.width > self.max_width {
            return Err(input_error(format!(
                "resident LPIPS: a {} x {} crop exceeds the workspace's {} x {}",
                crop.height, crop.width, self.max_height, self.max_width
            )));
        }
        for (what, image) in [("render", render), ("target", target)] {
            if crop.x0 + crop.width > image.width || crop.y0 + crop.height > image.height {
                return Err(input_error(format!(
                    "resident LPIPS: crop {crop:?} outside the {what}'s {} x {} image",
                    image.width, image.height
                )));
            }
            if image.buffer.len < 3 * (image.offset + image.width * image.height) {
                return Err(input_error(format!(
                    "resident LPIPS: the {what} buffer holds {} values, a {} x {} image at pixel {} needs {}",
                    image.buffer.len,
                    image.width,
                    image.height,
                    image.offset,
                    3 * (image.offset + image.width * image.height)
                )));
            }
        }
        if gradient.len < 3 * (render.offset + render.width * render.height) {
            return Err(input_error(format!(
                "resident LPIPS: the gradient buffer holds {} values, the render needs {}",
                gradient.len,
                3 * (render.offset + render.width * render.height)
            )));
        }
        let plan = gpu.plan(crop.height, crop.width)?;
        let mut layer_pixels = [[0_u32; 4]; 2];
        for op in &plan {
            if let Planned::Distance { layer, .. } = op.op {
                layer_pixels[layer / 4][layer % 4] = op.params.in_height * op.params.in_width;
            }
        }
        let resident = ResidentParams {
            render_offset: to_u32("render offset", render.offset)?,
            render_width: to_u32("render width", render.width)?,
            target_offset: to_u32("target offset", target.offset)?,
            target_width: to_u32("target width", target.width)?,
            x0: to_u32("crop x0", crop.x0)?,
            y0: to_u32("crop y0", crop.y0)?,
            crop_width: to_u32("crop width", crop.width)?,
            crop_height: to_u32("crop height", crop.height)?,
            gradient_factor: factor,
            signed_mapping: u32::from(self.input == super::LpipsInput::Unit),
            pad: [0; 2],
            shift: [self.shift[0], self.shift[1], self.shift[2], 0.0],
            scale: [self.scale[0], self.scale[1], self.scale[2], 1.0],
            layer_pixels,
        };
        // The call's record: one write, then device copies into the uniforms.
        let mut words: Vec<u32> = bytemuck::cast_slice(&[resident]).to_vec();
        for op in plan
            .iter()
            .filter(|op| !matches!(op.op, Planned::Clear { .. }))
        {
            words.extend_from_slice(bytemuck::cast_slice(&[op.params]));
        }
        let context = &self.context;
        context.write(&slot_state.staging.buffer, 0, &words)?;
        let resident_bytes = size_of::<ResidentParams>() as u64;
        encoder.copy_buffer_to_buffer(
            &slot_state.staging.buffer,
            0,
            &slot_state.resident_uniform,
            0,
            resident_bytes,
        );
        let op_bytes = (4 * PARAMS_WORDS) as u64;
        for (index, uniform) in slot_state.op_uniforms.iter().enumerate() {
            encoder.copy_buffer_to_buffer(
                &slot_state.staging.buffer,
                resident_bytes + index as u64 * op_bytes,
                uniform,
                0,
                op_bytes,
            );
        }
        let crop_groups = to_u32("crop pixels", crop.width * crop.height)?.div_ceil(WORKGROUP);
        context.dispatch(
            encoder,
            &*gpu.kernel(CROP_TO_TRUNK)?,
            &[
                (0, &slot_state.resident_uniform),
                (1, &render.buffer.buffer),
                (2, &target.buffer.buffer),
                (3, &self.activations[0].buffer),
            ],
            crop_groups,
        );
        let mut uniforms = slot_state.op_uniforms.iter();
        let mut next_uniform = || {
            uniforms
                .next()
                .ok_or_else(|| input_error("resident LPIPS: plan longer than its uniforms".into()))
        };
        let mut forward_done = false;
        for op in &plan {
            let a = |index: usize| &self.activations[index].buffer;
            let g = |index: usize| &self.gradients[index].buffer;
            match op.op {
                Planned::Conv { conv, input } => {
                    let (weight, bias) = &gpu.convs[conv];
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(CONV)?,
                        &[
                            (0, next_uniform()?),
                            (1, a(input)),
                            (2, &weight.buffer),
                            (3, &bias.buffer),
                            (4, a(input + 1)),
                        ],
                        op.workgroups,
                    );
                }
                Planned::Pool { input } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(POOL)?,
                        &[(0, next_uniform()?), (1, a(input)), (4, a(input + 1))],
                        op.workgroups,
                    );
                }
                Planned::Distance { layer, features } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(DISTANCE)?,
                        &[
                            (0, next_uniform()?),
                            (1, a(features)),
                            (2, &gpu.lins[layer].buffer),
                            (4, &self.maps[layer].buffer),
                        ],
                        op.workgroups,
                    );
                }
                Planned::Clear { target, len } => {
                    if !forward_done {
                        forward_done = true;
                        self.record_reduce(gpu, encoder, slot_state)?;
                    }
                    encoder.clear_buffer(g(target), 0, Some((4 * len.max(1)) as u64));
                }
                Planned::DistanceBackward {
                    layer,
                    features,
                    target,
                } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(DISTANCE_BACKWARD)?,
                        &[
                            (0, next_uniform()?),
                            (1, a(features)),
                            (2, &gpu.lins[layer].buffer),
                            (4, g(target)),
                        ],
                        op.workgroups,
                    );
                }
                Planned::ReluMask { output, upstream } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(RELU_MASK)?,
                        &[(0, next_uniform()?), (1, a(output)), (4, g(upstream))],
                        op.workgroups,
                    );
                }
                Planned::ConvBackward {
                    conv,
                    upstream,
                    target,
                } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(CONV_BACKWARD)?,
                        &[
                            (0, next_uniform()?),
                            (2, &gpu.convs[conv].0.buffer),
                            (3, g(upstream)),
                            (4, g(target)),
                        ],
                        op.workgroups,
                    );
                }
                Planned::PoolBackward {
                    input,
                    upstream,
                    target,
                } => {
                    context.dispatch(
                        encoder,
                        &*gpu.kernel(POOL_BACKWARD)?,
                        &[
                            (0, next_uniform()?),
                            (1, a(input)),
                            (3, g(upstream)),
                            (4, g(target)),
                        ],
                        op.workgroups,
                    );
                }
            }
        }
        let last = plan
            .iter()
            .rev()
            .find_map(|op| match op.op {
                Planned::ConvBackward { target, .. } | Planned::PoolBackward { target, .. } => {
                    Some(target)
                }
                _ => None,
            })
            .ok_or_else(|| input_error("resident LPIPS: no backward to the input".into()))?;
        context.dispatch(
            encoder,
            &*gpu.kernel(ADD_IMAGE_GRADIENT)?,
            &[
                (0, &slot_state.resident_uniform),
                (4, &self.gradients[last].buffer),
                (5, &gradient.buffer),
            ],
            crop_groups,
        );
        Ok(())
    }

    fn record_reduce(
        &self,
        gpu: &GpuLpips,
        encoder: &mut wgpu::CommandEncoder,
        slot: &ResidentSlot,
    ) -> Result<(), LpipsError> {
        let mut bindings: Vec<(u32, &wgpu::Buffer)> = vec![(0, &slot.resident_uniform)];
        for (layer, map) in self.maps.iter().enumerate() {
            bindings.push((6 + layer as u32, &map.buffer));
        }
        bindings.push((11, &slot.value.buffer));
        self.context
            .dispatch(encoder, &*gpu.kernel(REDUCE_DISTANCE)?, &bindings, 1);
        Ok(())
    }
}
