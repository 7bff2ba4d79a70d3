//! The `gpu` LPIPS trunk: the kernels of `shaders/lpips_forward.wgsl` run through the shared
//! [`GpuContext`]. Weights are uploaded once; a batch larger than the device's buffer limit is
//! split into groups of pairs.

use std::borrow::Cow;
use std::sync::Arc;

use crate::backend::{GpuBuffer, GpuContext, KernelSource};

use super::{DistanceMaps, LpipsError, LpipsNet, LpipsWeights, Step, TrunkInput, steps};

const WGSL: &str = include_str!("../../../../shaders/lpips_forward.wgsl");
const WORKGROUP: u32 = 64;

fn source(name: &'static str, entry_point: &'static str) -> KernelSource {
    KernelSource {
        name,
        wgsl: Cow::Borrowed(WGSL),
        entry_point,
    }
}

/// The uniform block shared by the three kernels (see the WGSL for each one's reading).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
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

/// Converts a size to the u32 the kernels index with, or an error naming it.
fn to_u32(what: &str, value: usize) -> Result<u32, LpipsError> {
    u32::try_from(value).map_err(|_| LpipsError::Input {
        message: format!("{what} = {value} exceeds the gpu's 32-bit indexing"),
    })
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
        for (name, entry) in [
            ("lpips_conv2d_relu", "conv2d_relu"),
            ("lpips_max_pool", "max_pool"),
            ("lpips_layer_distance", "layer_distance"),
        ] {
            context.kernel(&source(name, entry))?;
        }
        Ok(Self {
            context,
            net: weights.net,
            convs,
            lins,
        })
    }

    /// The largest activation of one image, in f32 values.
    fn largest_activation(&self, height: usize, width: usize) -> Result<usize, LpipsError> {
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
        Ok(largest)
    }

    /// Per-layer, per-pixel distance maps (same layout as [`super::cpu::distance_maps`]).
    pub fn distance_maps(&self, input: &TrunkInput) -> Result<DistanceMaps, LpipsError> {
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
        let per_image = self.largest_activation(input.height, input.width)?;
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
            let group_maps = self.run_group(&data, group, input.height, input.width)?;
            for (layer, map) in group_maps.into_iter().enumerate() {
                maps[layer].extend(map);
            }
        }
        Ok(maps)
    }

    fn run_group(
        &self,
        data: &[f32],
        pairs: usize,
        height: usize,
        width: usize,
    ) -> Result<DistanceMaps, LpipsError> {
        let context = &self.context;
        let conv_kernel = context.kernel(&source("lpips_conv2d_relu", "conv2d_relu"))?;
        let pool_kernel = context.kernel(&source("lpips_max_pool", "max_pool"))?;
        let distance_kernel = context.kernel(&source("lpips_layer_distance", "layer_distance"))?;
        let images = 2 * pairs;
        let mut encoder = context.encoder();
        let mut activation = context.upload("lpips input", data)?;
        let (mut channels, mut h, mut w) = (3_usize, height, width);
        let mut convs = self.convs.iter();
        let mut outputs: Vec<GpuBuffer> = Vec::new();
        let mut map_buffers: Vec<GpuBuffer> = Vec::new();
        // Keeps uniforms and intermediate buffers alive until the work is submitted.
        let mut keep = Vec::new();
        for step in steps(self.net) {
            match step {
                Step::Conv(spec) => {
                    let (weight, bias) = convs.next().ok_or_else(|| LpipsError::Input {
                        message: "missing convolution weights".to_owned(),
                    })?;
                    let (out_h, out_w) = (
                        spec.output_extent(h).unwrap_or(0),
                        spec.output_extent(w).unwrap_or(0),
                    );
                    let groups = spec.out_channels.div_ceil(4);
                    let total = to_u32("conv threads", images * groups * out_h * out_w)?;
                    let params = Params {
                        images: to_u32("images", images)?,
                        in_channels: to_u32("channels", channels)?,
                        in_height: to_u32("height", h)?,
                        in_width: to_u32("width", w)?,
                        out_channels: to_u32("channels", spec.out_channels)?,
                        out_height: to_u32("height", out_h)?,
                        out_width: to_u32("width", out_w)?,
                        kernel: to_u32("kernel", spec.kernel)?,
                        stride: to_u32("stride", spec.stride)?,
                        padding: to_u32("padding", spec.padding)?,
                        total,
                        pad: 0,
                    };
                    let uniform = context.uniform("lpips conv params", &params);
                    let output =
                        context.zeros(&spec.name, images * spec.out_channels * out_h * out_w, 4)?;
                    context.dispatch(
                        &mut encoder,
                        &conv_kernel,
                        &[
                            (0, &uniform),
                            (1, &activation.buffer),
                            (2, &weight.buffer),
                            (3, &bias.buffer),
                            (4, &output.buffer),
                        ],
                        total.div_ceil(WORKGROUP),
                    );
                    keep.push(uniform);
                    outputs.push(std::mem::replace(&mut activation, output));
                    (channels, h, w) = (spec.out_channels, out_h, out_w);
                }
                Step::MaxPool { kernel, stride } => {
                    let out_h = Step::pool_extent(kernel, stride, h).unwrap_or(0);
                    let out_w = Step::pool_extent(kernel, stride, w).unwrap_or(0);
                    let total = to_u32("pool threads", images * channels * out_h * out_w)?;
                    let params = Params {
                        images: to_u32("planes", images * channels)?,
                        in_height: to_u32("height", h)?,
                        in_width: to_u32("width", w)?,
                        out_height: to_u32("height", out_h)?,
                        out_width: to_u32("width", out_w)?,
                        kernel: to_u32("kernel", kernel)?,
                        stride: to_u32("stride", stride)?,
                        total,
                        ..Params::default()
                    };
                    let uniform = context.uniform("lpips pool params", &params);
                    let output =
                        context.zeros("lpips max pool", images * channels * out_h * out_w, 4)?;
                    context.dispatch(
                        &mut encoder,
                        &pool_kernel,
                        &[(0, &uniform), (1, &activation.buffer), (4, &output.buffer)],
                        total.div_ceil(WORKGROUP),
                    );
                    keep.push(uniform);
                    outputs.push(std::mem::replace(&mut activation, output));
                    (h, w) = (out_h, out_w);
                }
                Step::Tap => {
                    let lin =
                        self.lins
                            .get(map_buffers.len())
                            .ok_or_else(|| LpipsError::Input {
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
                        &distance_kernel,
                        &[
                            (0, &uniform),
                            (1, &activation.buffer),
                            (2, &lin.buffer),
                            (4, &map.buffer),
                        ],
                        total.div_ceil(WORKGROUP),
                    );
                    keep.push(uniform);
                    map_buffers.push(map);
                }
            }
        }
        let sources: Vec<_> = map_buffers
            .iter()
            .map(|map| (&map.buffer, map.len))
            .collect();
        let mut pending = context.download_many::<f32>(&mut encoder, &sources)?;
        context.finish_downloads(encoder, &mut pending)?;
        drop((keep, outputs, activation));
        Ok(pending
            .into_iter()
            .map(|download| download.values)
            .collect())
    }
}
