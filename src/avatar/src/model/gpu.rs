//! `GpuNetworks`: the f32 twin of [`Networks`] on wgpu, built on the `nn` kernels
//! (`seqavatar_compute::nn::gpu::NnGpu`: dense layers, positional encoding, Adam).
//!
//! Parameters and gradients live on the device, one buffer per named array (the names and
//! layouts of the `cpu` networks, [`GpuNetworks::parameters`]). The networks run resident
//! (`resident`: [`GpuNetworks::record_forward`], [`GpuNetworks::record_backward`],
//! [`GpuNetworks::record_adam`] and their per-network forms): inputs and output gradients are
//! device buffers, outputs and input gradients stay in buffers of a workspace sized for a
//! Gaussian capacity, and each pass is a replayed [`seqavatar_compute::nn::gpu::NnProgram`]
//! recorded into the caller's encoder with no upload, read-back or allocation in the steady
//! state.
//!
//! Each network is run from its description ([`NetworkSpec`]), driving the `nn` kernels by
//! layer index exactly as the `cpu` interpreter ([`super::network`]) does. Per-frame values
//! read by a per-Gaussian layer are folded as on `cpu`: a 1-row product whose result is the
//! bias of the per-Gaussian product; its input has a leading block of zeros in place of the
//! per-Gaussian rows, so both products read the one weight buffer (the zero block costs one
//! row and contributes nothing, to outputs or gradients).

mod resident;

use std::sync::Arc;

use seqavatar_compute::backend::GpuContext;
use seqavatar_compute::nn::gpu::{GpuInputGrad, GpuInputPart, GpuLinearGrads, NnGpu};
use seqavatar_compute::nn::{LinearShape, Precision};

use super::dense::Dense;
use super::spec::NetworkSpec;
use super::{ModelError, NetworkConfig, NetworkGroup, Networks};

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
    pub values: &'a wgpu::Buffer,
    /// The accumulated gradient.
    pub grads: &'a wgpu::Buffer,
    pub group: NetworkGroup,
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
    /// The networks, by network group (non-rigid, pose refiner, LBS offsets).
    nets: [Option<GpuNet>; 3],
    /// The resident workspaces, by network group.
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
        for (slot, network) in nets.iter_mut().zip(&networks.nets) {
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
        Ok(GpuNetworks {
            context,
            nn,
            config: networks.config().clone(),
            layers,
            nets,
            resident: [None, None, None],
            adam: None,
            programs_built: std::sync::atomic::AtomicUsize::new(0),
        })
    }

    /// The compiled `nn` kernels (their matrix-product path: [`NnGpu::matmul_path`]).
    pub fn kernels(&self) -> &NnGpu {
        &self.nn
    }

    /// Every parameter buffer with its gradient buffer, in the order of
    /// [`Networks::parameters`].
    pub fn parameters(&self) -> Vec<GpuNamedParam<'_>> {
        let mut params = Vec::with_capacity(2 * self.layers.len());
        for layer in &self.layers {
            for (what, len, values, grads) in [
                (
                    "weight",
                    layer.shape.weight_len(),
                    &layer.weight,
                    &layer.d_weight,
                ),
                ("bias", layer.shape.out_features, &layer.bias, &layer.d_bias),
            ] {
                params.push(GpuNamedParam {
                    name: format!("{}.{what}", layer.name),
                    len,
                    values,
                    grads,
                    group: layer.group,
                });
            }
        }
        params
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

    fn zeros(&self, what: &str, len: usize) -> Result<wgpu::Buffer, ModelError> {
        self.context
            .zeros(what, len, 4)
            .map(|buffer| buffer.buffer)
            .map_err(gpu_error)
    }
}
