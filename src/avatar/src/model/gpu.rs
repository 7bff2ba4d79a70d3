//! `GpuNetworks`: the f32 twin of [`Networks`] on wgpu, built on the `nn` kernels
//! (`seqavatar_compute::nn::gpu::NnGpu`: dense layers, positional encoding).
//!
//! Parameters and gradients live on the device, one buffer per named array (the names and
//! layouts of the `cpu` networks), so Adam can run there
//! ([`NnGpu::adam_update`] on [`GpuNetworks::parameters`]). Each forward uploads its inputs,
//! records the whole network into one command encoder, submits and downloads the outputs; the
//! activations stay on the device in the returned cache for the backward, which likewise
//! takes host gradients and returns the host position gradient.
//!
//! The resident step uses the other entry points ([`GpuNetworks::record_forward`],
//! [`GpuNetworks::record_backward`], [`GpuNetworks::record_adam`] and their per-network
//! forms, in `resident`): inputs and output gradients are device buffers, outputs and input
//! gradients stay in buffers of a workspace sized for a Gaussian capacity, and each pass is a
//! replayed [`seqavatar_compute::nn::gpu::NnProgram`] recorded into the caller's encoder with
//! no upload, read-back or allocation in the steady state.
//!
//! Each network is run from its description ([`NetworkSpec`]) by one forward and one
//! backward ([`GpuNetworks::forward_net`], [`GpuNetworks::backward_net`]) that drive the
//! `nn` kernels by layer index, exactly as the `cpu` interpreter ([`super::network`]) does.
//! Per-frame values read by a per-Gaussian layer are folded as on `cpu`: a 1-row product whose
//! result is the bias of the per-Gaussian product; its input has a leading block of zeros in
//! place of the per-Gaussian rows, so both products read the one weight buffer (the zero
//! block costs one row and contributes nothing, to outputs or gradients).

mod resident;

use std::collections::HashMap;
use std::sync::Arc;

use seqavatar_compute::backend::GpuContext;
use seqavatar_compute::nn::gpu::{
    GpuInput, GpuInputGrad, GpuInputPart, GpuLinear, GpuLinearGrads, NnGpu,
};
use seqavatar_compute::nn::{LinearShape, NnScalar, Precision};

use super::dense::Dense;
use super::network::folded_shapes;
use super::non_rigid::{heads_gradient, split_heads};
use super::pose_refiner::{rotation_vectors_backward, rotations_from_vectors};
use super::spec::{NetworkSpec, Part, Rows, Value, window_blocks};
use super::{
    FrameInputs, GaussianInputs, ModelError, NetworkConfig, NetworkGroup, Networks, NonRigidOutput,
    check_input,
};

/// One layer's parameter and gradient buffers.
#[derive(Debug)]
struct GpuDense {
    name: String,
    group: NetworkGroup,
    shape: LinearShape,
    weight: wgpu::Buffer,
    bias: wgpu::Buffer,
    d_weight: wgpu::Buffer,
    d_bias: wgpu::Buffer,
}

/// One parameter array on the device (for Adam and checkpoints).
#[derive(Debug)]
pub struct GpuNamedParam<'a> {
    /// The stable name (as on `cpu`).
    pub name: String,
    /// Number of f32 values.
    pub len: usize,
    /// The values.
    pub values: &'a wgpu::Buffer,
    /// The accumulated gradient.
    pub grads: &'a wgpu::Buffer,
    /// The optimiser group.
    pub group: NetworkGroup,
}

/// The device values of one forward pass of one network (see [`super::network::Activations`]).
#[derive(Debug)]
struct GpuActivations {
    rows: usize,
    /// False when a network with per-Gaussian inputs got none: nothing ran, and every
    /// gradient is zero (the per-frame values reach the output through no row).
    ran: bool,
    /// Per input, its (encoded) blocks.
    inputs: Vec<Vec<wgpu::Buffer>>,
    /// Per layer, its output blocks.
    outputs: Vec<Vec<wgpu::Buffer>>,
    /// Per layer, the zero placeholder and the per-frame bias of a folded layer.
    frame_bias: Vec<Option<(wgpu::Buffer, wgpu::Buffer)>>,
}

impl GpuActivations {
    fn empty() -> Self {
        GpuActivations {
            rows: 0,
            ran: false,
            inputs: Vec::new(),
            outputs: Vec::new(),
            frame_bias: Vec::new(),
        }
    }
}

/// The device activations of one non-rigid forward pass.
#[derive(Debug)]
pub struct GpuNonRigidCache {
    activations: GpuActivations,
}

impl GpuNonRigidCache {
    /// Number of Gaussians of the forward pass.
    pub fn rows(&self) -> usize {
        self.activations.rows
    }
}

/// The device activations of one pose-refiner forward pass.
#[derive(Debug)]
pub struct GpuPoseRefinerCache {
    activations: GpuActivations,
    rotation_vectors: Vec<f32>,
}

/// The device activations of one LBS-offset forward pass.
#[derive(Debug)]
pub struct GpuLbsOffsetsCache {
    activations: GpuActivations,
}

/// One network on the device: its description and its first layer in
/// [`GpuNetworks`]' layer list.
#[derive(Debug)]
struct GpuNet {
    spec: NetworkSpec,
    first: usize,
}

/// All networks of one avatar on the gpu (f32).
#[derive(Debug)]
pub struct GpuNetworks {
    context: Arc<GpuContext>,
    nn: NnGpu,
    config: NetworkConfig,
    layers: Vec<GpuDense>,
    non_rigid: Option<GpuNet>,
    pose_refiner: Option<GpuNet>,
    lbs_offsets: Option<GpuNet>,
    /// The resident workspaces, by network group (non-rigid, pose refiner, LBS offsets).
    resident: [Option<resident::ResidentNet>; 3],
    /// Adam of every parameter on the device (created by the first resident update).
    adam: Option<resident::ResidentAdam>,
    /// Resident programs built so far (forward/backward pairs and Adam programs): constant
    /// over steady-state iterations.
    programs_built: std::sync::atomic::AtomicUsize,
}

pub use resident::{NetworkNonFinite, NonRigidDeviceInputs};

fn gpu_error(error: impl std::fmt::Display) -> ModelError {
    ModelError::Gpu(error.to_string())
}

/// Gradient sinks of one backward: the layer's parameter gradients, and write, add or skip
/// per input part.
fn grads<'a>(layer: &'a GpuDense, inputs: &'a [GpuInputGrad<'a>]) -> GpuLinearGrads<'a> {
    GpuLinearGrads {
        weight: &layer.d_weight,
        bias: &layer.d_bias,
        inputs,
    }
}

fn input(buffer: &wgpu::Buffer, cols: usize) -> GpuInputPart<'_> {
    GpuInputPart { buffer, cols }
}

impl GpuNetworks {
    /// Uploads the parameters of `networks` (gradients start at zero), with the dense
    /// layers' products on the path `precision` chooses on this context, once
    /// ([`NnGpu::for_context`]).
    pub fn upload(
        context: Arc<GpuContext>,
        networks: &Networks<f32>,
        precision: Precision,
    ) -> Result<Self, ModelError> {
        let nn = NnGpu::for_context(&context, precision)?
            .with_max_workgroups_per_dimension(context.max_workgroups_per_dimension());
        let mut layers = Vec::new();
        let mut nets = [None, None, None];
        for (slot, network) in nets.iter_mut().zip([
            &networks.non_rigid,
            &networks.pose_refiner,
            &networks.lbs_offsets,
        ]) {
            let Some(network) = network else { continue };
            *slot = Some(GpuNet {
                spec: network.spec().clone(),
                first: layers.len(),
            });
            for layer in &network.layers {
                let Dense {
                    name,
                    group,
                    shape,
                    weight,
                    bias,
                    ..
                } = layer;
                let upload = |what: &str, values: &[f32]| {
                    context
                        .upload(&format!("{name}.{what}"), values)
                        .map(|buffer| buffer.buffer)
                        .map_err(gpu_error)
                };
                let zeros = |what: &str, len: usize| {
                    context
                        .zeros(&format!("{name}.{what}"), len, 4)
                        .map(|buffer| buffer.buffer)
                        .map_err(gpu_error)
                };
                layers.push(GpuDense {
                    name: name.clone(),
                    group: *group,
                    shape: *shape,
                    weight: upload("weight", weight)?,
                    bias: upload("bias", bias)?,
                    d_weight: zeros("weight gradient", weight.len())?,
                    d_bias: zeros("bias gradient", bias.len())?,
                });
            }
        }
        let [non_rigid, pose_refiner, lbs_offsets] = nets;
        Ok(GpuNetworks {
            context,
            nn,
            config: networks.config().clone(),
            layers,
            non_rigid,
            pose_refiner,
            lbs_offsets,
            resident: [None, None, None],
            adam: None,
            programs_built: std::sync::atomic::AtomicUsize::new(0),
        })
    }

    /// The configuration the networks were built from.
    pub fn config(&self) -> &NetworkConfig {
        &self.config
    }

    /// The gpu context the buffers belong to.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.context
    }

    /// The compiled `nn` kernels (e.g. for Adam on [`GpuNetworks::parameters`]).
    pub fn kernels(&self) -> &NnGpu {
        &self.nn
    }

    /// Every parameter buffer with its gradient buffer, in the order of
    /// [`Networks::parameters`].
    pub fn parameters(&self) -> Vec<GpuNamedParam<'_>> {
        let mut params = Vec::with_capacity(2 * self.layers.len());
        for layer in &self.layers {
            params.push(GpuNamedParam {
                name: format!("{}.weight", layer.name),
                len: layer.shape.weight_len(),
                values: &layer.weight,
                grads: &layer.d_weight,
                group: layer.group,
            });
            params.push(GpuNamedParam {
                name: format!("{}.bias", layer.name),
                len: layer.shape.out_features,
                values: &layer.bias,
                grads: &layer.d_bias,
                group: layer.group,
            });
        }
        params
    }

    /// Sets every gradient buffer to zero.
    pub fn zero_grad(&self) -> Result<(), ModelError> {
        let mut encoder = self.context.encoder();
        for layer in &self.layers {
            encoder.clear_buffer(&layer.d_weight, 0, None);
            encoder.clear_buffer(&layer.d_bias, 0, None);
        }
        self.context.submit_and_wait(encoder).map_err(gpu_error)
    }

    fn download_buffers(&self, grads: bool) -> Result<Vec<Vec<f32>>, ModelError> {
        let params = self.parameters();
        let sources: Vec<(&wgpu::Buffer, usize)> = params
            .iter()
            .map(|p| (if grads { p.grads } else { p.values }, p.len))
            .collect();
        self.context
            .download_all::<f32>(self.context.encoder(), &sources)
            .map_err(gpu_error)
    }

    /// Copies the device parameters and gradients into `networks` (same configuration).
    pub fn download_into(&self, networks: &mut Networks<f32>) -> Result<(), ModelError> {
        if networks.config() != &self.config {
            return Err(ModelError::Input {
                field: "networks".into(),
                message: "the cpu networks have another configuration".into(),
            });
        }
        let values = self.download_buffers(false)?;
        let grads = self.download_buffers(true)?;
        let mut arrays = values.into_iter().zip(grads);
        for layer in networks.layers_mut() {
            let (weight, d_weight) = arrays.next().ok_or_else(|| gpu_error("layer count"))?;
            let (bias, d_bias) = arrays.next().ok_or_else(|| gpu_error("layer count"))?;
            layer.weight.copy_from_slice(&weight);
            layer.d_weight.copy_from_slice(&d_weight);
            layer.bias.copy_from_slice(&bias);
            layer.d_bias.copy_from_slice(&d_bias);
        }
        Ok(())
    }

    /// Overwrites the device parameters with those of `networks` (same configuration).
    pub fn upload_parameters(&self, networks: &Networks<f32>) -> Result<(), ModelError> {
        if networks.config() != &self.config {
            return Err(ModelError::Input {
                field: "networks".into(),
                message: "the cpu networks have another configuration".into(),
            });
        }
        for (gpu, cpu) in self.layers.iter().zip(networks.layers()) {
            self.context
                .write(&gpu.weight, 0, &cpu.weight)
                .map_err(gpu_error)?;
            self.context
                .write(&gpu.bias, 0, &cpu.bias)
                .map_err(gpu_error)?;
        }
        Ok(())
    }

    /// Uploads the f64 host networks (rounded to f32 once); the gpu twin of the `cpu`
    /// parameter master a trainer keeps. Gradients start at zero.
    pub fn upload_f64(
        context: Arc<GpuContext>,
        networks: &Networks<f64>,
        precision: Precision,
    ) -> Result<Self, ModelError> {
        let mut narrow = Networks::<f32>::new(networks.config(), 0)?;
        let values: HashMap<String, Vec<f32>> = networks
            .parameters()
            .iter()
            .map(|p| (p.name.clone(), p.values.iter().map(|&v| v as f32).collect()))
            .collect();
        narrow.load_parameters(|name| values.get(name).cloned())?;
        Self::upload(context, &narrow, precision)
    }

    /// The groups that [`crate::avatar::deform`] evaluates on the gpu: the non-rigid
    /// network and the LBS offsets (both per Gaussian). The pose refiner is one row per frame
    /// and stays on `cpu` (a device round trip costs more than the whole network;
    /// see `crate::avatar::deform`).
    pub const DEFORM_GROUPS: &'static [NetworkGroup] =
        &[NetworkGroup::NonRigid, NetworkGroup::LbsOffsets];

    /// Overwrites the device parameters of the layers in `group` with those of the host
    /// networks (f32, or f64 rounded to f32; same configuration).
    pub fn upload_group<S: NnScalar>(
        &self,
        networks: &Networks<S>,
        group: NetworkGroup,
    ) -> Result<(), ModelError> {
        self.upload_groups(networks, &[group])
    }

    /// Overwrites the device parameters of the layers in any of `groups` with those of the
    /// host networks (f32, or f64 rounded to f32; same configuration). Layers of other
    /// groups are neither converted nor written, so refreshing only what the gpu evaluates
    /// ([`GpuNetworks::DEFORM_GROUPS`]) costs nothing for the rest.
    pub fn upload_groups<S: NnScalar>(
        &self,
        networks: &Networks<S>,
        groups: &[NetworkGroup],
    ) -> Result<(), ModelError> {
        self.check_config(networks.config())?;
        let narrow = |v: &[S]| -> Vec<f32> { v.iter().map(|&x| x.to_f64() as f32).collect() };
        for (gpu, cpu) in self.layers.iter().zip(networks.layers()) {
            if groups.contains(&gpu.group) {
                self.context
                    .write(&gpu.weight, 0, &narrow(&cpu.weight))
                    .map_err(gpu_error)?;
                self.context
                    .write(&gpu.bias, 0, &narrow(&cpu.bias))
                    .map_err(gpu_error)?;
            }
        }
        Ok(())
    }

    fn check_config(&self, config: &NetworkConfig) -> Result<(), ModelError> {
        if config != &self.config {
            return Err(ModelError::Input {
                field: "networks".into(),
                message: "the cpu networks have another configuration".into(),
            });
        }
        Ok(())
    }

    /// Downloads the device gradients of the layers in `group` and adds them to the
    /// gradients of the host networks (f32, or widened to f64; same configuration), which
    /// therefore accumulate exactly as a `cpu` backward would.
    pub fn add_group_gradients_into<S: NnScalar>(
        &self,
        networks: &mut Networks<S>,
        group: NetworkGroup,
    ) -> Result<(), ModelError> {
        self.add_groups_gradients_into(networks, &[group])
    }

    /// [`GpuNetworks::add_group_gradients_into`] for every layer in any of `groups`, in one
    /// download.
    pub fn add_groups_gradients_into<S: NnScalar>(
        &self,
        networks: &mut Networks<S>,
        groups: &[NetworkGroup],
    ) -> Result<(), ModelError> {
        self.check_config(networks.config())?;
        let chosen: Vec<&GpuDense> = self
            .layers
            .iter()
            .filter(|l| groups.contains(&l.group))
            .collect();
        if chosen.is_empty() {
            return Ok(());
        }
        let mut sources = Vec::with_capacity(2 * chosen.len());
        for layer in &chosen {
            sources.push((&layer.d_weight, layer.shape.weight_len()));
            sources.push((&layer.d_bias, layer.shape.out_features));
        }
        let mut arrays = self
            .context
            .download_all::<f32>(self.context.encoder(), &sources)
            .map_err(gpu_error)?
            .into_iter();
        for layer in networks
            .layers_mut()
            .into_iter()
            .filter(|l| groups.contains(&l.group))
        {
            let d_weight = arrays.next().ok_or_else(|| gpu_error("layer count"))?;
            let d_bias = arrays.next().ok_or_else(|| gpu_error("layer count"))?;
            if d_weight.len() != layer.d_weight.len() || d_bias.len() != layer.d_bias.len() {
                return Err(gpu_error(format!("gradient length of `{}`", layer.name)));
            }
            for (a, b) in layer.d_weight.iter_mut().zip(&d_weight) {
                *a += S::from_f64(f64::from(*b));
            }
            for (a, b) in layer.d_bias.iter_mut().zip(&d_bias) {
                *a += S::from_f64(f64::from(*b));
            }
        }
        Ok(())
    }

    fn upload_values(&self, what: &str, values: &[f32]) -> Result<wgpu::Buffer, ModelError> {
        self.context
            .upload(what, values)
            .map(|buffer| buffer.buffer)
            .map_err(gpu_error)
    }

    fn zeros(&self, what: &str, len: usize) -> Result<wgpu::Buffer, ModelError> {
        self.context
            .zeros(what, len, 4)
            .map(|buffer| buffer.buffer)
            .map_err(gpu_error)
    }

    fn download(
        &self,
        encoder: wgpu::CommandEncoder,
        buffer: &wgpu::Buffer,
        len: usize,
    ) -> Result<Vec<f32>, ModelError> {
        self.context
            .download(encoder, buffer, len)
            .map_err(gpu_error)
    }

    /// The description of a network, or that it is disabled.
    fn net<'a>(net: &'a Option<GpuNet>, block: &'static str) -> Result<&'a GpuNet, ModelError> {
        net.as_ref().ok_or(ModelError::Disabled { block })
    }

    /// Runs `net` on `inputs` (as [`super::network::Network::forward`]), recording every
    /// layer into one command encoder; returns the downloaded output and the device values.
    fn forward_net(
        &self,
        net: &GpuNet,
        inputs: &[&[f32]],
    ) -> Result<(Vec<f32>, GpuActivations), ModelError> {
        let spec = &net.spec;
        let n = spec.check_inputs(inputs)?;
        let window = spec.window;
        if n == 0 && spec.inputs.iter().any(|i| i.rows.per_gaussian()) {
            return Ok((Vec::new(), GpuActivations::empty()));
        }
        let mut encoder = self.context.encoder();
        let mut raw_buffers = Vec::new();
        let mut cache = GpuActivations {
            rows: n,
            ran: true,
            inputs: Vec::with_capacity(inputs.len()),
            outputs: Vec::with_capacity(spec.layers.len()),
            frame_bias: Vec::with_capacity(spec.layers.len()),
        };
        for (input, data) in spec.inputs.iter().zip(inputs) {
            let raw = match input.rows {
                Rows::GaussianWindow => window_blocks(data, window, input.width)
                    .iter()
                    .map(|block| self.upload_values(&input.name, block))
                    .collect::<Result<Vec<_>, _>>()?,
                _ => vec![self.upload_values(&input.name, data)?],
            };
            let blocks = match input.encoding {
                None => raw,
                Some(encoding) => {
                    let rows = input.rows.block_rows(n, window);
                    let mut encoded = Vec::with_capacity(raw.len());
                    for block in &raw {
                        let out = self.zeros(&input.name, rows * input.value_width())?;
                        self.nn.positional_encoding_forward(
                            &mut encoder,
                            encoding,
                            block,
                            (rows, input.width),
                            &out,
                        )?;
                        encoded.push(out);
                    }
                    raw_buffers.extend(raw);
                    encoded
                }
            };
            cache.inputs.push(blocks);
        }
        for index in 0..spec.layers.len() {
            let layer = &self.layers[net.first + index];
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            let width = layer.shape.out_features;
            let mut blocks = Vec::new();
            let mut frame_bias = None;
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                let parts = gpu_parts(&cache, &plan.rows);
                let out = self.zeros(&layer.name, rows * width)?;
                if plan.frame.is_empty() {
                    self.nn.linear_forward(
                        &mut encoder,
                        GpuLinear::new(layer.shape, &layer.weight),
                        &layer.bias,
                        GpuInput::new(&parts, rows),
                        &out,
                    )?;
                } else {
                    let (rows_shape, frame_shape) = folded_shapes(layer.shape, plan.rows_in());
                    let placeholder = self.zeros("per-Gaussian placeholder", plan.rows_in())?;
                    let bias = self.zeros("per-frame bias", width)?;
                    let mut frame_parts = vec![input(&placeholder, plan.rows_in())];
                    frame_parts.extend(gpu_parts(&cache, &plan.frame));
                    self.nn.linear_forward(
                        &mut encoder,
                        GpuLinear::new(
                            LinearShape {
                                in_features: layer.shape.in_features,
                                ..frame_shape
                            },
                            &layer.weight,
                        ),
                        &layer.bias,
                        GpuInput::new(&frame_parts, 1),
                        &bias,
                    )?;
                    self.nn.linear_forward(
                        &mut encoder,
                        GpuLinear::new(rows_shape, &layer.weight),
                        &bias,
                        GpuInput::new(&parts, rows),
                        &out,
                    )?;
                    frame_bias = Some((placeholder, bias));
                }
                blocks.push(out);
            }
            cache.outputs.push(blocks);
            cache.frame_bias.push(frame_bias);
        }
        let output = &spec.layers[spec.output];
        let len = output.rows.block_rows(n, window) * output.out;
        let values = self.download(encoder, &cache.outputs[spec.output][0], len)?;
        drop(raw_buffers);
        Ok((values, cache))
    }

    /// Backward of [`GpuNetworks::forward_net`] (as [`super::network::Network::backward`]):
    /// accumulates the device parameter gradients and returns, per input, its downloaded
    /// gradient where the description asks for it.
    fn backward_net(
        &self,
        net: &GpuNet,
        cache: &GpuActivations,
        d_output: &[f32],
    ) -> Result<Vec<Option<Vec<f32>>>, ModelError> {
        let spec = &net.spec;
        let window = spec.window;
        let n = cache.rows;
        if !cache.ran {
            check_input(
                &format!("{} output gradient", spec.prefix),
                0,
                d_output.len(),
            )?;
            return Ok(spec
                .inputs
                .iter()
                .map(|input| input.gradient.then(Vec::new))
                .collect());
        }
        if cache.inputs.len() != spec.inputs.len() || cache.outputs.len() != spec.layers.len() {
            return Err(ModelError::Input {
                field: format!("{} cache", spec.prefix),
                message: "does not come from this network's forward pass".into(),
            });
        }
        let output = &spec.layers[spec.output];
        check_input(
            &format!("{} output gradient", spec.prefix),
            output.rows.block_rows(n, window) * output.out,
            d_output.len(),
        )?;
        let mut d_inputs: Vec<Vec<Option<wgpu::Buffer>>> = spec
            .inputs
            .iter()
            .map(|i| (0..i.rows.calls(window)).map(|_| None).collect())
            .collect();
        let mut d_outputs: Vec<Vec<Option<wgpu::Buffer>>> = spec
            .layers
            .iter()
            .map(|l| (0..l.rows.calls(window)).map(|_| None).collect())
            .collect();
        d_outputs[spec.output][0] = Some(self.upload_values("output gradient", d_output)?);
        let mut encoder = self.context.encoder();
        let mut keep = Vec::new();
        for index in (0..spec.layers.len()).rev() {
            let layer = &self.layers[net.first + index];
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                let d_out = d_outputs[index][call]
                    .take()
                    .ok_or_else(|| ModelError::Input {
                        field: spec.parameter_name(index),
                        message: "no gradient reached this layer".into(),
                    })?;
                let mut take =
                    |parts: &[Part]| -> Result<Vec<Option<(wgpu::Buffer, bool)>>, ModelError> {
                        parts
                            .iter()
                            .map(|part| {
                                let wanted = match part.value {
                                    Value::Input(i) => spec.inputs[i].gradient,
                                    Value::Layer(_) => true,
                                };
                                if !wanted {
                                    return Ok(None);
                                }
                                let slot = match part.value {
                                    Value::Input(i) => &mut d_inputs[i][part.block],
                                    Value::Layer(j) => &mut d_outputs[j][part.block],
                                };
                                Ok(Some(match slot.take() {
                                    Some(buffer) => (buffer, true),
                                    None => {
                                        let rows =
                                            spec.value_rows(part.value).block_rows(n, window);
                                        let len = rows * spec.value_width(part.value);
                                        (self.zeros("gradient", len)?, false)
                                    }
                                }))
                            })
                            .collect()
                    };
                let rows_d = take(&plan.rows)?;
                let frame_d = take(&plan.frame)?;
                let parts = gpu_parts_ref(&cache.inputs, &cache.outputs, &plan.rows);
                let out = &cache.outputs[index][call];
                match &cache.frame_bias[index] {
                    None => self.nn.linear_backward(
                        &mut encoder,
                        GpuLinear::new(layer.shape, &layer.weight),
                        GpuInput::new(&parts, rows),
                        out,
                        &d_out,
                        grads(layer, &sinks(&rows_d)),
                    )?,
                    Some((placeholder, bias)) => {
                        let (rows_shape, frame_shape) = folded_shapes(layer.shape, plan.rows_in());
                        let d_bias =
                            self.zeros("per-frame bias gradient", rows_shape.out_features)?;
                        self.nn.linear_backward(
                            &mut encoder,
                            GpuLinear::new(rows_shape, &layer.weight),
                            GpuInput::new(&parts, rows),
                            out,
                            &d_out,
                            GpuLinearGrads {
                                weight: &layer.d_weight,
                                bias: &d_bias,
                                inputs: &sinks(&rows_d),
                            },
                        )?;
                        let mut frame_parts = vec![input(placeholder, plan.rows_in())];
                        frame_parts.extend(gpu_parts_ref(
                            &cache.inputs,
                            &cache.outputs,
                            &plan.frame,
                        ));
                        let mut d_frame = vec![GpuInputGrad::Skip];
                        d_frame.extend(sinks(&frame_d));
                        self.nn.linear_backward(
                            &mut encoder,
                            GpuLinear::new(
                                LinearShape {
                                    in_features: layer.shape.in_features,
                                    ..frame_shape
                                },
                                &layer.weight,
                            ),
                            GpuInput::new(&frame_parts, 1),
                            bias,
                            &d_bias,
                            grads(layer, &d_frame),
                        )?;
                        keep.push(d_bias);
                    }
                }
                keep.push(d_out);
                for (part, buffer) in plan
                    .rows
                    .iter()
                    .chain(&plan.frame)
                    .zip(rows_d.into_iter().chain(frame_d))
                {
                    if let Some((buffer, _)) = buffer {
                        match part.value {
                            Value::Input(i) => d_inputs[i][part.block] = Some(buffer),
                            Value::Layer(j) => d_outputs[j][part.block] = Some(buffer),
                        }
                    }
                }
            }
        }
        let mut downloads = Vec::new();
        for (index, input) in spec.inputs.iter().enumerate() {
            if !input.gradient {
                continue;
            }
            let rows = input.rows.block_rows(n, window);
            let d_value = match d_inputs[index][0].take() {
                Some(buffer) => buffer,
                None => self.zeros("input gradient", rows * input.value_width())?,
            };
            let d_raw = match input.encoding {
                None => d_value,
                Some(encoding) => {
                    let d_raw = self.zeros("input gradient", rows * input.width)?;
                    self.nn.positional_encoding_backward(
                        &mut encoder,
                        encoding,
                        &cache.inputs[index][0],
                        &d_value,
                        (rows, input.width),
                        &d_raw,
                    )?;
                    keep.push(d_value);
                    d_raw
                }
            };
            downloads.push((index, d_raw, rows * input.width));
        }
        let mut gradients: Vec<Option<Vec<f32>>> = vec![None; spec.inputs.len()];
        if downloads.is_empty() {
            self.context.submit_and_wait(encoder).map_err(gpu_error)?;
        } else {
            let sources: Vec<(&wgpu::Buffer, usize)> =
                downloads.iter().map(|(_, b, len)| (b, *len)).collect();
            let arrays = self
                .context
                .download_all::<f32>(encoder, &sources)
                .map_err(gpu_error)?;
            for ((index, _, _), values) in downloads.iter().zip(arrays) {
                gradients[*index] = Some(values);
            }
        }
        drop(keep);
        Ok(gradients)
    }

    /// The gpu twin of [`Networks::non_rigid_forward`].
    pub fn non_rigid_forward(
        &self,
        frame: &FrameInputs<'_, f32>,
        gaussians: &GaussianInputs<'_, f32>,
    ) -> Result<(NonRigidOutput<f32>, GpuNonRigidCache), ModelError> {
        let net = Self::net(&self.non_rigid, "the non-rigid network")?;
        let inputs = super::non_rigid::inputs(&self.config, frame, gaussians)?;
        let (heads, activations) = self.forward_net(net, &inputs)?;
        Ok((split_heads(&heads), GpuNonRigidCache { activations }))
    }

    /// The gpu twin of [`Networks::non_rigid_backward`].
    pub fn non_rigid_backward(
        &self,
        cache: &GpuNonRigidCache,
        d_dxyz: &[f32],
        d_drot: &[f32],
        d_dscale: &[f32],
    ) -> Result<Vec<f32>, ModelError> {
        let net = Self::net(&self.non_rigid, "the non-rigid network")?;
        let d_heads = heads_gradient(cache.rows(), d_dxyz, d_drot, d_dscale)?;
        let gradients = self.backward_net(net, &cache.activations, &d_heads)?;
        Ok(gradients.into_iter().flatten().next().unwrap_or_default())
    }

    /// The gpu twin of [`Networks::pose_refiner_forward`].
    pub fn pose_refiner_forward(
        &self,
        local_pose: &[f32],
    ) -> Result<(Vec<f32>, GpuPoseRefinerCache), ModelError> {
        let net = Self::net(&self.pose_refiner, "the pose refiner")?;
        let (rotation_vectors, activations) = self.forward_net(net, &[local_pose])?;
        let rotations = rotations_from_vectors(&rotation_vectors);
        Ok((
            rotations,
            GpuPoseRefinerCache {
                activations,
                rotation_vectors,
            },
        ))
    }

    /// The gpu twin of [`Networks::pose_refiner_backward`].
    pub fn pose_refiner_backward(
        &self,
        cache: &GpuPoseRefinerCache,
        d_rotations: &[f32],
    ) -> Result<(), ModelError> {
        let net = Self::net(&self.pose_refiner, "the pose refiner")?;
        let vectors = &cache.rotation_vectors;
        check_input("d_rotations", 3 * vectors.len(), d_rotations.len())?;
        let d_vectors = rotation_vectors_backward(vectors, d_rotations);
        self.backward_net(net, &cache.activations, &d_vectors)?;
        Ok(())
    }

    /// The gpu twin of [`Networks::lbs_offsets_forward`].
    pub fn lbs_offsets_forward(
        &self,
        xyz: &[f32],
    ) -> Result<(Vec<f32>, GpuLbsOffsetsCache), ModelError> {
        let net = Self::net(&self.lbs_offsets, "the LBS offsets")?;
        let (offsets, activations) = self.forward_net(net, &[xyz])?;
        Ok((offsets, GpuLbsOffsetsCache { activations }))
    }

    /// The gpu twin of [`Networks::lbs_offsets_backward`].
    pub fn lbs_offsets_backward(
        &self,
        cache: &GpuLbsOffsetsCache,
        d_offsets: &[f32],
    ) -> Result<(), ModelError> {
        let net = Self::net(&self.lbs_offsets, "the LBS offsets")?;
        check_input(
            "d_offsets",
            cache.activations.rows * self.config.skinning_joints,
            d_offsets.len(),
        )?;
        self.backward_net(net, &cache.activations, d_offsets)?;
        Ok(())
    }
}

/// The device column blocks of `parts`.
fn gpu_parts<'a>(cache: &'a GpuActivations, parts: &[Part]) -> Vec<GpuInputPart<'a>> {
    gpu_parts_ref(&cache.inputs, &cache.outputs, parts)
}

fn gpu_parts_ref<'a>(
    inputs: &'a [Vec<wgpu::Buffer>],
    outputs: &'a [Vec<wgpu::Buffer>],
    parts: &[Part],
) -> Vec<GpuInputPart<'a>> {
    parts
        .iter()
        .map(|part| {
            let blocks = match part.value {
                Value::Input(i) => &inputs[i],
                Value::Layer(j) => &outputs[j],
            };
            input(&blocks[part.block], part.cols)
        })
        .collect()
}

/// The input-gradient sinks of taken gradient buffers: skip, write (first contribution) or
/// add.
fn sinks(buffers: &[Option<(wgpu::Buffer, bool)>]) -> Vec<GpuInputGrad<'_>> {
    buffers
        .iter()
        .map(|b| match b {
            None => GpuInputGrad::Skip,
            Some((buffer, true)) => GpuInputGrad::Accumulate(buffer),
            Some((buffer, false)) => GpuInputGrad::Write(buffer),
        })
        .collect()
}
