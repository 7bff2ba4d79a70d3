//! The `gpu` LPIPS trunk and its image gradient (`shaders/lpips_forward.wgsl`,
//! `shaders/lpips_backward.wgsl`). A [`Plan`] lists one evaluation's [`Call`]s (forward, then
//! backward; [`Call`]'s constructors are each kernel's bindings) and its [`Workspace`]'s sizes.
//! [`GpuLpips`] (weights uploaded once) records it once per group of pairs (a batch over the
//! buffer limit is split) on a workspace of its own and downloads the maps and the gradient;
//! [`ResidentLpips`] records it on device crops every training step, on one workspace.

use std::sync::Arc;

use crate::backend::{GpuBuffer, GpuContext, Kernel};

use super::{ConvSpec, DistanceMaps, LpipsError, LpipsNet, LpipsWeights, Step, TrunkInput, steps};

const FORWARD_WGSL: &str = include_str!("../../../../shaders/lpips_forward.wgsl");
const BACKWARD_WGSL: &str = include_str!("../../../../shaders/lpips_backward.wgsl");
const WORKGROUP: u32 = 64;
/// Channels one convolution thread handles (`CHANNELS_PER_THREAD` in both shaders).
const CHANNELS_PER_THREAD: usize = 4;

/// A kernel: (cache name, WGSL text, entry point).
type Source = (&'static str, &'static str, &'static str);
const CONV: Source = ("lpips_conv2d_relu", FORWARD_WGSL, "conv2d_relu");
const POOL: Source = ("lpips_max_pool", FORWARD_WGSL, "max_pool");
const DISTANCE: Source = ("lpips_layer_distance", FORWARD_WGSL, "layer_distance");
const DISTANCE_BACKWARD: Source = (
    "lpips_distance_backward",
    BACKWARD_WGSL,
    "distance_backward",
);
const RELU_MASK: Source = ("lpips_relu_mask", BACKWARD_WGSL, "relu_mask");
const CONV_BACKWARD: Source = (
    "lpips_conv2d_backward_data",
    BACKWARD_WGSL,
    "conv2d_backward_data",
);
const POOL_BACKWARD: Source = (
    "lpips_max_pool_backward",
    BACKWARD_WGSL,
    "max_pool_backward",
);

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
pub(crate) fn wgsl_twins() -> Vec<crate::backend::shaders::tests::WgslTwin> {
    use crate::backend::shaders::tests::wgsl_twin;
    vec![
        wgsl_twin!(Params as "LpipsParams" in ["lpips_forward.wgsl", "lpips_backward.wgsl"] {
            images, in_channels, in_height, in_width, out_channels, out_height, out_width, kernel,
            stride, padding, total, pad as "_pad",
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
        size: [usize; 3],
    },
}

/// The buffer a [`Call`] binds: of the [`Workspace`] or of the weights.
#[derive(Clone, Copy, Debug)]
pub(super) enum Slot {
    Activation(usize),
    Gradient(usize),
    Map(usize),
    Weight(usize),
    Bias(usize),
    Lin(usize),
}

/// One kernel call of the trunk: its kernel, its uniform block (binding 0), its buffers by
/// binding; `params.total` threads in workgroups of [`WORKGROUP`]. The constructors are the
/// one list of each kernel's bindings.
#[derive(Clone, Debug)]
pub(super) struct Call {
    kernel: Source,
    params: Params,
    bindings: Vec<(u32, Slot)>,
}

impl Call {
    /// `relu(conv(input) + bias)` with convolution `conv` for `shape.images` images, from
    /// activation `input` into `input + 1`.
    pub(super) fn conv(shape: ConvShape, conv: usize, input: usize) -> Result<Self, LpipsError> {
        let groups = shape.out_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = shape.images * groups * shape.out_height * shape.out_width;
        Ok(Self {
            kernel: CONV,
            params: conv_params(shape, to_u32("conv threads", total)?)?,
            bindings: vec![
                (1, Slot::Activation(input)),
                (2, Slot::Weight(conv)),
                (3, Slot::Bias(conv)),
                (4, Slot::Activation(input + 1)),
            ],
        })
    }

    /// The max pool of `shape.planes` planes, from activation `input` into `input + 1`.
    pub(super) fn pool(shape: PoolShape, input: usize) -> Result<Self, LpipsError> {
        let total = shape.planes * shape.out_height * shape.out_width;
        Ok(Self {
            kernel: POOL,
            params: pool_params(shape, to_u32("pool threads", total)?)?,
            bindings: vec![
                (1, Slot::Activation(input)),
                (4, Slot::Activation(input + 1)),
            ],
        })
    }

    /// Distance `layer` of `pairs` pairs whose `[channels, height, width]` features (first
    /// images, then second images) are activation `features`: into `Slot::Map(layer)`, or
    /// `d(its spatial mean) / d(first features)` added (`+=`) into a `Slot::Gradient`.
    pub(super) fn distance(
        pairs: usize,
        [channels, height, width]: [usize; 3],
        layer: usize,
        features: usize,
        into: Slot,
    ) -> Result<Self, LpipsError> {
        let total = to_u32("distance threads", pairs * height * width)?;
        Ok(Self {
            kernel: match into {
                Slot::Map(_) => DISTANCE,
                _ => DISTANCE_BACKWARD,
            },
            params: Params {
                images: to_u32("pairs", pairs)?,
                in_channels: to_u32("channels", channels)?,
                in_height: to_u32("height", height)?,
                in_width: to_u32("width", width)?,
                total,
                ..Params::default()
            },
            bindings: vec![
                (1, Slot::Activation(features)),
                (2, Slot::Lin(layer)),
                (4, into),
            ],
        })
    }

    /// The backward of `relu(conv(x) + bias)` for the first `shape.images` images: masks
    /// gradient `upstream` in place where the forward output (activation `output`) is not
    /// positive, then writes the transposed convolution of it into gradient `1 - upstream`.
    pub(super) fn conv_backward(
        shape: ConvShape,
        conv: usize,
        output: usize,
        upstream: usize,
    ) -> Result<[Self; 2], LpipsError> {
        let mask_total = shape.images * shape.out_channels * shape.out_height * shape.out_width;
        let groups = shape.in_channels.div_ceil(CHANNELS_PER_THREAD);
        let total = shape.images * groups * shape.in_height * shape.in_width;
        Ok([
            Self {
                kernel: RELU_MASK,
                params: Params {
                    total: to_u32("relu mask threads", mask_total)?,
                    ..Params::default()
                },
                bindings: vec![(1, Slot::Activation(output)), (4, Slot::Gradient(upstream))],
            },
            Self {
                kernel: CONV_BACKWARD,
                params: conv_params(shape, to_u32("conv gradient threads", total)?)?,
                bindings: vec![
                    (2, Slot::Weight(conv)),
                    (3, Slot::Gradient(upstream)),
                    (4, Slot::Gradient(1 - upstream)),
                ],
            },
        ])
    }

    /// The max pool's backward for `shape.planes` planes: gradient `1 - upstream` (the pool
    /// input's) gathers gradient `upstream` at each window's first arg-max in activation
    /// `input`.
    pub(super) fn pool_backward(
        shape: PoolShape,
        input: usize,
        upstream: usize,
    ) -> Result<Self, LpipsError> {
        let total = shape.planes * shape.in_height * shape.in_width;
        Ok(Self {
            kernel: POOL_BACKWARD,
            params: pool_params(shape, to_u32("pool gradient threads", total)?)?,
            bindings: vec![
                (1, Slot::Activation(input)),
                (3, Slot::Gradient(upstream)),
                (4, Slot::Gradient(1 - upstream)),
            ],
        })
    }
}

/// The calls of one evaluation of `pairs` pairs of images (the forward, then the backward
/// for the first images) and the sizes of the buffers they bind.
struct Plan {
    calls: Vec<Call>,
    /// Where the backward starts in `calls`.
    backward: usize,
    /// Values of gradient buffer 0 to zero before the backward (the last tap's features).
    clear: usize,
    /// The gradient buffer holding the input's gradient after the backward.
    input_gradient: usize,
    /// Values of each activation (0: the input), of each gradient buffer and of each
    /// distance map (`pairs x height x width`).
    activations: Vec<usize>,
    gradient_len: usize,
    maps: Vec<usize>,
}

impl Plan {
    /// The plan of `pairs` pairs of `height x width` images through `net`'s trunk.
    fn new(net: LpipsNet, pairs: usize, height: usize, width: usize) -> Result<Self, LpipsError> {
        super::tap_sizes(net, height, width)?;
        let mut calls = Vec::new();
        let mut trace = Vec::new();
        let mut activations = vec![2 * pairs * 3 * height * width];
        let mut gradient_len = pairs * 3 * height * width;
        let mut maps = Vec::new();
        let (mut channels, mut h, mut w) = (3_usize, height, width);
        let mut conv = 0;
        for step in steps(net) {
            let current = activations.len() - 1;
            match step {
                Step::Conv(spec) => {
                    let shape = ConvShape::of(&spec, 2 * pairs, channels, h, w);
                    calls.push(Call::conv(shape, conv, current)?);
                    let shape = ConvShape {
                        images: pairs,
                        ..shape
                    };
                    let output = current + 1;
                    trace.push(Traced::Conv {
                        conv,
                        shape,
                        output,
                    });
                    conv += 1;
                    (channels, h, w) = (shape.out_channels, shape.out_height, shape.out_width);
                }
                Step::MaxPool { kernel, stride } => {
                    let shape = PoolShape::of(kernel, stride, 2 * pairs * channels, h, w);
                    calls.push(Call::pool(shape, current)?);
                    let shape = PoolShape {
                        planes: pairs * channels,
                        ..shape
                    };
                    trace.push(Traced::Pool {
                        shape,
                        input: current,
                    });
                    (h, w) = (shape.out_height, shape.out_width);
                }
                Step::Tap => {
                    let (layer, size) = (maps.len(), [channels, h, w]);
                    calls.push(Call::distance(
                        pairs,
                        size,
                        layer,
                        current,
                        Slot::Map(layer),
                    )?);
                    let features = current;
                    trace.push(Traced::Tap {
                        layer,
                        features,
                        size,
                    });
                    maps.push(pairs * h * w);
                    continue;
                }
            }
            activations.push(2 * pairs * channels * h * w);
            gradient_len = gradient_len.max(pairs * channels * h * w);
        }
        let backward = calls.len();
        // The gradient with respect to the current activation lives in gradient buffer `at`
        // (`None` while it is still zero).
        let (mut at, mut clear) = (None, 0);
        for traced in trace.iter().rev() {
            match *traced {
                Traced::Tap {
                    layer,
                    features,
                    size,
                } => {
                    let target = at.unwrap_or_else(|| {
                        clear = pairs * size.iter().product::<usize>();
                        0
                    });
                    let into = Slot::Gradient(target);
                    calls.push(Call::distance(pairs, size, layer, features, into)?);
                    at = Some(target);
                }
                Traced::Conv {
                    conv,
                    shape,
                    output,
                } => {
                    let Some(upstream) = at else { continue };
                    calls.extend(Call::conv_backward(shape, conv, output, upstream)?);
                    at = Some(1 - upstream);
                }
                Traced::Pool { shape, input } => {
                    let Some(upstream) = at else { continue };
                    calls.push(Call::pool_backward(shape, input, upstream)?);
                    at = Some(1 - upstream);
                }
            }
        }
        let input_gradient = at.ok_or_else(|| LpipsError::Input {
            message: "LPIPS: the trunk has no tap".to_owned(),
        })?;
        Ok(Self {
            calls,
            backward,
            clear,
            input_gradient,
            activations,
            gradient_len,
            maps,
        })
    }
}

/// The buffers a [`Plan`]'s calls bind besides the weights: activations, two gradient
/// buffers (ping-pong) and the distance maps.
pub(super) struct Workspace {
    pub activations: Vec<GpuBuffer>,
    pub gradients: [GpuBuffer; 2],
    pub maps: Vec<GpuBuffer>,
}

impl Workspace {
    /// Zeroed buffers for `plan`; every extent grows with the input's, so they hold the plan
    /// of any smaller input too.
    fn new(context: &GpuContext, plan: &Plan) -> Result<Self, LpipsError> {
        let zeros = |what: &str, len: usize| context.zeros(what, len, 4);
        let all = |what: &str, lens: &[usize]| {
            lens.iter()
                .map(|&len| zeros(what, len))
                .collect::<Result<Vec<_>, _>>()
        };
        Ok(Self {
            activations: all("lpips activation", &plan.activations)?,
            gradients: [
                zeros("lpips gradient ping", plan.gradient_len)?,
                zeros("lpips gradient pong", plan.gradient_len)?,
            ],
            maps: all("lpips distance map", &plan.maps)?,
        })
    }
}

/// LPIPS weights resident on the gpu.
pub struct GpuLpips {
    context: Arc<GpuContext>,
    net: LpipsNet,
    /// The weights' input normalisation (the resident path applies it on the device).
    shift: [f32; 3],
    scale: [f32; 3],
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
            context.static_kernel(kernel.0, kernel.1, kernel.2)?;
        }
        Ok(Self {
            context,
            net: weights.net,
            shift: weights.shift,
            scale: weights.scale,
            convs,
            lins,
        })
    }

    fn kernel(&self, kernel: Source) -> Result<Arc<Kernel>, LpipsError> {
        let (name, wgsl, entry_point) = kernel;
        Ok(self.context.static_kernel(name, wgsl, entry_point)?)
    }

    /// Records `calls` on `workspace`, the uniform block of each one of `uniforms` (blocks a
    /// resident workspace rewrites every call) or, without them, a new one holding its
    /// params.
    pub(super) fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        workspace: &Workspace,
        calls: &[Call],
        uniforms: Option<&[wgpu::Buffer]>,
    ) -> Result<(), LpipsError> {
        for (index, call) in calls.iter().enumerate() {
            let mut bindings = Vec::new();
            for &(binding, slot) in &call.bindings {
                let buffer = match slot {
                    Slot::Activation(i) => workspace.activations.get(i),
                    Slot::Gradient(i) => workspace.gradients.get(i),
                    Slot::Map(i) => workspace.maps.get(i),
                    Slot::Weight(i) => self.convs.get(i).map(|(weight, _)| weight),
                    Slot::Bias(i) => self.convs.get(i).map(|(_, bias)| bias),
                    Slot::Lin(i) => self.lins.get(i),
                };
                let buffer = buffer.ok_or_else(|| LpipsError::Input {
                    message: format!("LPIPS: no buffer {slot:?} (missing weights?)"),
                })?;
                bindings.push((binding, &buffer.buffer));
            }
            let kernel = self.kernel(call.kernel)?;
            let workgroups = call.params.total.div_ceil(WORKGROUP);
            match uniforms {
                None => {
                    self.context
                        .call(encoder, &kernel, &call.params, &bindings, workgroups);
                }
                Some(uniforms) => {
                    let uniform = uniforms.get(index).ok_or_else(|| LpipsError::Input {
                        message: "LPIPS: more calls than uniform blocks".to_owned(),
                    })?;
                    bindings.insert(0, (0, uniform));
                    self.context
                        .dispatch(encoder, &kernel, &bindings, workgroups);
                }
            }
        }
        Ok(())
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
        let per_pair = Plan::new(self.net, 1, input.height, input.width)?
            .activations
            .into_iter()
            .max()
            .unwrap_or(0);
        let limit = (self.context.max_binding_bytes() / 4) as usize;
        let pairs_per_group = limit / per_pair.max(1);
        if pairs_per_group == 0 {
            return Err(LpipsError::Input {
                message: format!(
                    "a {} x {} image needs {} MB activations, more than the gpu's {} MB buffer limit",
                    input.height,
                    input.width,
                    per_pair * 4 / (1 << 20),
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

    /// Forward (and, when asked, backward) of one group of pairs, on a workspace of its own:
    /// `data` holds the group's first images then its second images.
    fn run_group(
        &self,
        data: &[f32],
        pairs: usize,
        height: usize,
        width: usize,
        with_gradient: bool,
    ) -> Result<(DistanceMaps, Vec<f32>), LpipsError> {
        let mut plan = Plan::new(self.net, pairs, height, width)?;
        if !with_gradient {
            // The forward alone: no backward calls, no gradient buffers.
            plan.calls.truncate(plan.backward);
            plan.gradient_len = 0;
        }
        let workspace = Workspace::new(&self.context, &plan)?;
        self.context
            .write(&workspace.activations[0].buffer, 0, data)?;
        let mut encoder = self.context.encoder();
        self.record(&mut encoder, &workspace, &plan.calls, None)?;
        let mut sources: Vec<_> = workspace
            .maps
            .iter()
            .map(|map| (&map.buffer, map.len))
            .collect();
        let input_gradient = &workspace.gradients[plan.input_gradient].buffer;
        if with_gradient {
            sources.push((input_gradient, pairs * 3 * height * width));
        }
        let mut values = self.context.download_all::<f32>(encoder, &sources)?;
        let gradient = if with_gradient {
            values.pop().unwrap_or_default()
        } else {
            Vec::new()
        };
        Ok((values, gradient))
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
const CROP_TO_TRUNK: Source = (
    "lpips_resident_crop_to_trunk",
    RESIDENT_WGSL,
    "crop_to_trunk",
);
const REDUCE_DISTANCE: Source = (
    "lpips_resident_reduce_distance",
    RESIDENT_WGSL,
    "reduce_distance",
);
const ADD_IMAGE_GRADIENT: Source = (
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
pub(crate) fn resident_wgsl_twins() -> Vec<crate::backend::shaders::tests::WgslTwin> {
    use crate::backend::shaders::tests::wgsl_twin;
    vec![
        wgsl_twin!(ResidentParams as "LpipsResidentParams" in ["lpips_resident.wgsl"] {
            render_offset, render_width, target_offset, target_width, x0, y0, crop_width,
            crop_height, gradient_factor, signed_mapping, pad[0] as "_pad0", pad[1] as "_pad1",
            shift, scale, layer_pixels[0] as "layer_pixels0", layer_pixels[1] as "layer_pixels1",
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

/// Per camera slot: its staging buffer (the call's record), its uniforms and its value.
struct ResidentSlot {
    /// `ResidentParams` then one `Params` per call, written with one `GpuContext::write` per
    /// call and copied into the uniforms on the device.
    staging: GpuBuffer,
    resident_uniform: wgpu::Buffer,
    call_uniforms: Vec<wgpu::Buffer>,
    value: GpuBuffer,
}

/// The LPIPS loss on device buffers, for the resident training step: the [`Workspace`] (for
/// one pair of crops of at most `max_height x max_width`) allocated once, per camera slot a
/// staging buffer, the kernels' uniforms and a value buffer (one f32).
///
/// [`ResidentLpips::record`] records, into the caller's encoder: the render and target crops
/// cut from device images into the trunk input, the trunk forward and backward (the calls of
/// one plan, as [`GpuLpips::distance_gradient`]'s), the distance reduced to one value
/// (written to [`ResidentLpips::value`]), and `factor x` the image gradient added (`+=`) into
/// the render's colour gradient buffer on the crop. The one upload per call is its record,
/// one `GpuContext::write`: the crop and images (112 bytes) and the trunk's kernel
/// parameters for the crop's shape (48 bytes per call: 57 calls for VGG, 2848 bytes in all;
/// 29 for AlexNet, 1504 bytes), since the crop's shape changes from call to call (computing
/// them on the device from the crop's size would remove all but the first 112 bytes).
pub struct ResidentLpips {
    trunk: GpuLpips,
    input: super::LpipsInput,
    max_height: usize,
    max_width: usize,
    workspace: Workspace,
    slots: Vec<ResidentSlot>,
}

impl GpuLpips {
    /// This trunk with a resident workspace for crops of at most `max_height x max_width` and
    /// `cameras` calls per submission (one slot each), feeding images through `input`.
    pub fn resident(
        self,
        input: super::LpipsInput,
        max_height: usize,
        max_width: usize,
        cameras: usize,
    ) -> Result<ResidentLpips, LpipsError> {
        let plan = Plan::new(self.net, 1, max_height, max_width)?;
        let context = &self.context;
        let calls = plan.calls.len();
        let slots = (0..cameras.max(1))
            .map(|_| -> Result<ResidentSlot, LpipsError> {
                Ok(ResidentSlot {
                    staging: context.zeros(
                        "lpips resident record",
                        size_of::<ResidentParams>() / 4 + PARAMS_WORDS * calls,
                        4,
                    )?,
                    resident_uniform: context
                        .uniform("lpips resident params", &ResidentParams::default()),
                    call_uniforms: (0..calls)
                        .map(|_| context.uniform("lpips resident call params", &Params::default()))
                        .collect(),
                    value: context.zeros("lpips resident value", 1, 4)?,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        for kernel in [CROP_TO_TRUNK, REDUCE_DISTANCE, ADD_IMAGE_GRADIENT] {
            context.static_kernel(kernel.0, kernel.1, kernel.2)?;
        }
        Ok(ResidentLpips {
            workspace: Workspace::new(context, &plan)?,
            trunk: self,
            input,
            max_height,
            max_width,
            slots,
        })
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
        let gpu = &self.trunk;
        let plan = Plan::new(gpu.net, 1, crop.height, crop.width)?;
        let mut layer_pixels = [[0_u32; 4]; 2];
        for (layer, &pixels) in plan.maps.iter().enumerate() {
            layer_pixels[layer / 4][layer % 4] = to_u32("layer pixels", pixels)?;
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
            shift: [gpu.shift[0], gpu.shift[1], gpu.shift[2], 0.0],
            scale: [gpu.scale[0], gpu.scale[1], gpu.scale[2], 1.0],
            layer_pixels,
        };
        // The call's record: one write, then device copies into the uniforms.
        let mut words: Vec<u32> = bytemuck::cast_slice(&[resident]).to_vec();
        for call in &plan.calls {
            words.extend_from_slice(bytemuck::cast_slice(&[call.params]));
        }
        let context = &gpu.context;
        context.write(&slot_state.staging.buffer, 0, &words)?;
        let resident_bytes = size_of::<ResidentParams>() as u64;
        encoder.copy_buffer_to_buffer(
            &slot_state.staging.buffer,
            0,
            &slot_state.resident_uniform,
            0,
            resident_bytes,
        );
        let call_bytes = (4 * PARAMS_WORDS) as u64;
        for (index, uniform) in slot_state.call_uniforms.iter().enumerate() {
            encoder.copy_buffer_to_buffer(
                &slot_state.staging.buffer,
                resident_bytes + index as u64 * call_bytes,
                uniform,
                0,
                call_bytes,
            );
        }
        let Workspace {
            activations,
            gradients,
            maps,
        } = &self.workspace;
        let crop_groups = to_u32("crop pixels", crop.width * crop.height)?.div_ceil(WORKGROUP);
        context.dispatch(
            encoder,
            &*gpu.kernel(CROP_TO_TRUNK)?,
            &[
                (0, &slot_state.resident_uniform),
                (1, &render.buffer.buffer),
                (2, &target.buffer.buffer),
                (3, &activations[0].buffer),
            ],
            crop_groups,
        );
        // The backward's first tap adds into gradient buffer 0.
        let clear = (4 * plan.clear.max(1)) as u64;
        encoder.clear_buffer(&gradients[0].buffer, 0, Some(clear));
        gpu.record(
            encoder,
            &self.workspace,
            &plan.calls,
            Some(&slot_state.call_uniforms),
        )?;
        let mut bindings = vec![(0, &slot_state.resident_uniform)];
        for (layer, map) in maps.iter().enumerate() {
            bindings.push((6 + layer as u32, &map.buffer));
        }
        bindings.push((11, &slot_state.value.buffer));
        context.dispatch(encoder, &*gpu.kernel(REDUCE_DISTANCE)?, &bindings, 1);
        context.dispatch(
            encoder,
            &*gpu.kernel(ADD_IMAGE_GRADIENT)?,
            &[
                (0, &slot_state.resident_uniform),
                (4, &gradients[plan.input_gradient].buffer),
                (5, &gradient.buffer),
            ],
            crop_groups,
        );
        Ok(())
    }
}
