//! The `gpu` LPIPS trunk and its image gradient: the kernels of `shaders/lpips_forward.wgsl`
//! and `shaders/lpips_backward.wgsl` run through the shared [`GpuContext`]. Weights are
//! uploaded once; a batch larger than the device's buffer limit is split into groups of pairs.
//!
//! The gradient keeps every forward activation on the device, records the backward passes
//! into the forward's encoder and downloads the maps and the gradient once per group.

use std::borrow::Cow;
use std::sync::Arc;

use crate::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};

use super::{DistanceMaps, LpipsError, LpipsNet, LpipsWeights, Step, TrunkInput, steps};

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
        // Keeps uniforms alive until the work is submitted.
        let mut uniforms = Vec::new();
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
                    let shape = ConvShape {
                        images,
                        in_channels: channels,
                        in_height: h,
                        in_width: w,
                        out_channels: spec.out_channels,
                        out_height: spec.output_extent(h).unwrap_or(0),
                        out_width: spec.output_extent(w).unwrap_or(0),
                        kernel: spec.kernel,
                        stride: spec.stride,
                        padding: spec.padding,
                    };
                    let output = context.zeros(
                        &spec.name,
                        images * shape.out_channels * shape.out_height * shape.out_width,
                        4,
                    )?;
                    uniforms.push(self.record_conv(
                        &mut encoder,
                        shape,
                        &activations[current],
                        weight,
                        bias,
                        &output,
                    )?);
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
                    let shape = PoolShape {
                        planes: images * channels,
                        in_height: h,
                        in_width: w,
                        out_height: Step::pool_extent(kernel, stride, h).unwrap_or(0),
                        out_width: Step::pool_extent(kernel, stride, w).unwrap_or(0),
                        kernel,
                        stride,
                    };
                    let output = context.zeros(
                        "lpips max pool",
                        shape.planes * shape.out_height * shape.out_width,
                        4,
                    )?;
                    uniforms.push(self.record_max_pool(
                        &mut encoder,
                        shape,
                        &activations[current],
                        &output,
                    )?);
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
                    let uniform = context.uniform("lpips distance params", &params);
                    let map = context.zeros("lpips distance map", pairs * h * w, 4)?;
                    context.dispatch(
                        &mut encoder,
                        &*self.kernel(DISTANCE)?,
                        &[
                            (0, &uniform),
                            (1, &activations[current].buffer),
                            (2, &lin.buffer),
                            (4, &map.buffer),
                        ],
                        total.div_ceil(WORKGROUP),
                    );
                    uniforms.push(uniform);
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
                        uniforms.push(self.record_distance_backward(
                            &mut encoder,
                            pairs,
                            [channels, height, width],
                            &activations[features],
                            &self.lins[layer],
                            &target,
                        )?);
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
                        uniforms.extend(self.record_conv_backward(
                            &mut encoder,
                            shape,
                            &activations[output],
                            &upstream,
                            &self.convs[conv].0,
                            &target,
                        )?);
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
                        uniforms.push(self.record_max_pool_backward(
                            &mut encoder,
                            shape,
                            &activations[input],
                            &upstream,
                            &target,
                        )?);
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
        drop((uniforms, activations, gradients));
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
    ) -> Result<wgpu::Buffer, LpipsError> {
        let groups = shape.out_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = to_u32(
            "conv threads",
            shape.images * groups * shape.out_height * shape.out_width,
        )?;
        let uniform = self
            .context
            .uniform("lpips conv params", &conv_params(shape, total)?);
        self.context.dispatch(
            encoder,
            &*self.kernel(CONV)?,
            &[
                (0, &uniform),
                (1, &input.buffer),
                (2, &weight.buffer),
                (3, &bias.buffer),
                (4, &output.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(uniform)
    }

    /// Records the max pool of `shape.planes` planes.
    pub(super) fn record_max_pool(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        shape: PoolShape,
        input: &GpuBuffer,
        output: &GpuBuffer,
    ) -> Result<wgpu::Buffer, LpipsError> {
        let total = to_u32(
            "pool threads",
            shape.planes * shape.out_height * shape.out_width,
        )?;
        let uniform = self
            .context
            .uniform("lpips pool params", &pool_params(shape, total)?);
        self.context.dispatch(
            encoder,
            &*self.kernel(POOL)?,
            &[(0, &uniform), (1, &input.buffer), (4, &output.buffer)],
            total.div_ceil(WORKGROUP),
        );
        Ok(uniform)
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
    ) -> Result<wgpu::Buffer, LpipsError> {
        let total = to_u32("distance gradient threads", pairs * height * width)?;
        let params = Params {
            images: to_u32("pairs", pairs)?,
            in_channels: to_u32("channels", channels)?,
            in_height: to_u32("height", height)?,
            in_width: to_u32("width", width)?,
            total,
            ..Params::default()
        };
        let uniform = self
            .context
            .uniform("lpips distance gradient params", &params);
        self.context.dispatch(
            encoder,
            &*self.kernel(DISTANCE_BACKWARD)?,
            &[
                (0, &uniform),
                (1, &features.buffer),
                (2, &lin.buffer),
                (4, &target.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(uniform)
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
    ) -> Result<[wgpu::Buffer; 2], LpipsError> {
        let mask_total = to_u32(
            "relu mask threads",
            shape.images * shape.out_channels * shape.out_height * shape.out_width,
        )?;
        let mask_uniform = self.context.uniform(
            "lpips relu mask params",
            &Params {
                total: mask_total,
                ..Params::default()
            },
        );
        self.context.dispatch(
            encoder,
            &*self.kernel(RELU_MASK)?,
            &[
                (0, &mask_uniform),
                (1, &output.buffer),
                (4, &upstream.buffer),
            ],
            mask_total.div_ceil(WORKGROUP),
        );
        let groups = shape.in_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = to_u32(
            "conv gradient threads",
            shape.images * groups * shape.in_height * shape.in_width,
        )?;
        let uniform = self
            .context
            .uniform("lpips conv gradient params", &conv_params(shape, total)?);
        self.context.dispatch(
            encoder,
            &*self.kernel(CONV_BACKWARD)?,
            &[
                (0, &uniform),
                (2, &weight.buffer),
                (3, &upstream.buffer),
                (4, &target.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok([mask_uniform, uniform])
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
    ) -> Result<wgpu::Buffer, LpipsError> {
        let total = to_u32(
            "pool gradient threads",
            shape.planes * shape.in_height * shape.in_width,
        )?;
        let uniform = self
            .context
            .uniform("lpips pool gradient params", &pool_params(shape, total)?);
        self.context.dispatch(
            encoder,
            &*self.kernel(POOL_BACKWARD)?,
            &[
                (0, &uniform),
                (1, &input.buffer),
                (3, &upstream.buffer),
                (4, &target.buffer),
            ],
            total.div_ceil(WORKGROUP),
        );
        Ok(uniform)
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
