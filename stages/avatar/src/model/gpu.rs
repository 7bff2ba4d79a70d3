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
//! The per-frame trunk contribution is computed as on `cpu`, as a 1-row product whose result
//! is the bias of the per-Gaussian product; its input has a leading block of zeros in place
//! of the per-Gaussian rows, so both products read the one `non_rigid.trunk.0.weight` buffer
//! (the zero block costs one row and contributes nothing, to outputs or gradients).

use std::collections::HashMap;
use std::sync::Arc;

use seqavatar_compute::backend::GpuContext;
use seqavatar_compute::nn::gpu::{GpuInputGrad, GpuInputPart, GpuLinearGrads, NnGpu};
use seqavatar_compute::nn::{Activation, LinearShape, NnScalar};

use super::dense::Dense;
use super::non_rigid::{check_inputs, split_heads};
use super::pose_refiner::{rotation_vectors_backward, rotations_from_vectors};
use super::{
    FrameInputs, GaussianInputs, HEAD_WIDTH, ModelError, NetworkConfig, NetworkGroup, Networks,
    NonRigidOutput, check_finite, check_input,
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

/// The device activations of one non-rigid forward pass.
#[derive(Debug)]
pub struct GpuNonRigidCache {
    rows: usize,
    encoding: Option<wgpu::Buffer>,
    pose_input: wgpu::Buffer,
    pose_hidden: wgpu::Buffer,
    pose_out: wgpu::Buffer,
    seq_pose: Option<[wgpu::Buffer; 3]>,
    seq_xyz: Option<GpuSeqXyz>,
    frame_zeros: wgpu::Buffer,
    frame_bias: wgpu::Buffer,
    trunk: Vec<wgpu::Buffer>,
    heads: Option<wgpu::Buffer>,
}

impl GpuNonRigidCache {
    /// Number of Gaussians of the forward pass.
    pub fn rows(&self) -> usize {
        self.rows
    }
}

#[derive(Debug)]
struct GpuSeqXyz {
    inputs: Vec<wgpu::Buffer>,
    velocity: Vec<wgpu::Buffer>,
    position: wgpu::Buffer,
    frames: Vec<wgpu::Buffer>,
    hidden: wgpu::Buffer,
    out: wgpu::Buffer,
}

/// The device activations of one pose-refiner forward pass.
#[derive(Debug)]
pub struct GpuPoseRefinerCache {
    input: wgpu::Buffer,
    hidden: [wgpu::Buffer; 2],
    output: wgpu::Buffer,
    rotation_vectors: Vec<f32>,
}

/// The device activations of one LBS-offset forward pass.
#[derive(Debug)]
pub struct GpuLbsOffsetsCache {
    rows: usize,
    encoding: wgpu::Buffer,
    outputs: Vec<wgpu::Buffer>,
}

/// All networks of one avatar on the gpu (f32).
#[derive(Debug)]
pub struct GpuNetworks {
    context: Arc<GpuContext>,
    nn: NnGpu,
    config: NetworkConfig,
    layers: Vec<GpuDense>,
    index: HashMap<String, usize>,
}

fn gpu_error(error: impl std::fmt::Display) -> ModelError {
    ModelError::Gpu(error.to_string())
}

/// Gradient sinks of one backward: write, add or skip.
fn grads(layer: &GpuDense) -> GpuLinearGrads<'_> {
    GpuLinearGrads {
        weight: &layer.d_weight,
        bias: &layer.d_bias,
    }
}

fn input(buffer: &wgpu::Buffer, cols: usize) -> GpuInputPart<'_> {
    GpuInputPart { buffer, cols }
}

impl GpuNetworks {
    /// Uploads the parameters of `networks` (gradients start at zero).
    pub fn upload(context: Arc<GpuContext>, networks: &Networks<f32>) -> Result<Self, ModelError> {
        let nn = NnGpu::new(context.device())?;
        let mut layers = Vec::new();
        let mut index = HashMap::new();
        for layer in networks.layers() {
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
            index.insert(name.clone(), layers.len());
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
        Ok(GpuNetworks {
            context,
            nn,
            config: networks.config().clone(),
            layers,
            index,
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
        let mut encoder = self.context.encoder();
        let sources: Vec<(&wgpu::Buffer, usize)> = params
            .iter()
            .map(|p| (if grads { p.grads } else { p.values }, p.len))
            .collect();
        let mut pending = self
            .context
            .download_many::<f32>(&mut encoder, &sources)
            .map_err(gpu_error)?;
        self.context
            .finish_downloads(encoder, &mut pending)
            .map_err(gpu_error)?;
        Ok(pending.into_iter().map(|p| p.values).collect())
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
        let queue = self.context.queue();
        for (gpu, cpu) in self.layers.iter().zip(networks.layers()) {
            queue.write_buffer(&gpu.weight, 0, &f32_bytes(&cpu.weight));
            queue.write_buffer(&gpu.bias, 0, &f32_bytes(&cpu.bias));
        }
        Ok(())
    }

    /// Uploads the f64 host networks (rounded to f32 once); the gpu twin of the `cpu`
    /// parameter master a trainer keeps. Gradients start at zero.
    pub fn upload_f64(
        context: Arc<GpuContext>,
        networks: &Networks<f64>,
    ) -> Result<Self, ModelError> {
        let mut narrow = Networks::<f32>::new(networks.config(), 0)?;
        let values: HashMap<String, Vec<f32>> = networks
            .parameters()
            .iter()
            .map(|p| (p.name.clone(), p.values.iter().map(|&v| v as f32).collect()))
            .collect();
        narrow.load_parameters(|name| values.get(name).cloned())?;
        Self::upload(context, &narrow)
    }

    /// The groups that [`crate::avatar::deform_on`] evaluates on the gpu: the non-rigid
    /// network and the LBS offsets (both per Gaussian). The pose refiner is one row per frame
    /// and stays on `cpu` (a device round trip costs more than the whole network;
    /// see `deform_on`).
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
        let narrow = |v: &[S]| -> Vec<u8> {
            v.iter()
                .flat_map(|&x| (x.to_f64() as f32).to_ne_bytes())
                .collect()
        };
        let queue = self.context.queue();
        for (gpu, cpu) in self.layers.iter().zip(networks.layers()) {
            if groups.contains(&gpu.group) {
                queue.write_buffer(&gpu.weight, 0, &narrow(&cpu.weight));
                queue.write_buffer(&gpu.bias, 0, &narrow(&cpu.bias));
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
        let mut encoder = self.context.encoder();
        let mut pending = self
            .context
            .download_many::<f32>(&mut encoder, &sources)
            .map_err(gpu_error)?;
        self.context
            .finish_downloads(encoder, &mut pending)
            .map_err(gpu_error)?;
        let mut arrays = pending.into_iter().map(|p| p.values);
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

    fn layer(&self, name: &str) -> Result<&GpuDense, ModelError> {
        self.index
            .get(name)
            .map(|&i| &self.layers[i])
            .ok_or(ModelError::Disabled {
                block: "a network block",
            })
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

    /// Records `layer` over `rows` rows of `parts` into a new output buffer.
    fn forward_layer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        layer: &GpuDense,
        parts: &[GpuInputPart<'_>],
        rows: usize,
    ) -> Result<wgpu::Buffer, ModelError> {
        let output = self.zeros(&layer.name, rows * layer.shape.out_features)?;
        self.nn.linear_forward(
            encoder,
            layer.shape,
            &layer.weight,
            &layer.bias,
            parts,
            rows,
            &output,
        )?;
        Ok(output)
    }

    /// Records the backward of `layer`.
    #[allow(clippy::too_many_arguments)]
    fn backward_layer(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        layer: &GpuDense,
        parts: &[GpuInputPart<'_>],
        rows: usize,
        output: &wgpu::Buffer,
        d_output: &wgpu::Buffer,
        d_parts: &[GpuInputGrad<'_>],
    ) -> Result<(), ModelError> {
        self.nn.linear_backward(
            encoder,
            layer.shape,
            &layer.weight,
            parts,
            rows,
            output,
            d_output,
            grads(layer),
            d_parts,
        )?;
        Ok(())
    }

    /// The gpu twin of [`Networks::non_rigid_forward`].
    pub fn non_rigid_forward(
        &self,
        frame: &FrameInputs<'_, f32>,
        gaussians: &GaussianInputs<'_, f32>,
    ) -> Result<(NonRigidOutput<f32>, GpuNonRigidCache), ModelError> {
        let config = &self.config;
        if !config.motion_context.has_non_rigid() {
            return Err(ModelError::Disabled {
                block: "the non-rigid network",
            });
        }
        let w = config.widths;
        let has_seq_pose = config.motion_context.has_skeleton_motion();
        let has_seq_xyz = config.motion_context.has_velocity();
        let n = check_inputs(config, has_seq_pose, has_seq_xyz, frame, gaussians)?;
        let length = config.sequence_length;
        let mut encoder = self.context.encoder();

        let pose_input = self.upload_values("local pose", frame.local_pose)?;
        let pose0 = self.layer("non_rigid.pose_encoder.0")?;
        let pose1 = self.layer("non_rigid.pose_encoder.1")?;
        let pose_hidden = self.forward_layer(
            &mut encoder,
            pose0,
            &[input(&pose_input, config.pose_dim())],
            1,
        )?;
        let pose_out = self.forward_layer(
            &mut encoder,
            pose1,
            &[input(&pose_hidden, w.pose_encoder)],
            1,
        )?;
        let seq_pose = match frame.skeleton_motion.filter(|_| has_seq_pose) {
            Some(motion) => {
                let motion = self.upload_values("skeleton motion", motion)?;
                let frames = self.forward_layer(
                    &mut encoder,
                    self.layer("non_rigid.seq_pose_encoder.frame")?,
                    &[input(&motion, config.seq_pose_row())],
                    length,
                )?;
                let out = self.forward_layer(
                    &mut encoder,
                    self.layer("non_rigid.seq_pose_encoder.sequence")?,
                    &[input(&frames, w.seq_pose_frame * length)],
                    1,
                )?;
                Some([motion, frames, out])
            }
            None => None,
        };
        let trunk0 = self.layer("non_rigid.trunk.0")?;
        let width = trunk0.shape.out_features;
        let gaussian_in = w.encoding_width() + if has_seq_xyz { w.seq_xyz } else { 0 };
        let frame_zeros = self.zeros("trunk per-Gaussian placeholder", gaussian_in)?;
        let mut frame_parts = vec![
            input(&frame_zeros, gaussian_in),
            input(&pose_out, w.pose_encoder),
        ];
        if let Some([_, _, out]) = &seq_pose {
            frame_parts.push(input(out, w.seq_pose));
        }
        let frame_bias = self.zeros("trunk per-frame bias", width)?;
        self.nn.linear_forward(
            &mut encoder,
            LinearShape {
                activation: Activation::Identity,
                ..trunk0.shape
            },
            &trunk0.weight,
            &trunk0.bias,
            &frame_parts,
            1,
            &frame_bias,
        )?;
        let mut cache = GpuNonRigidCache {
            rows: n,
            encoding: None,
            pose_input,
            pose_hidden,
            pose_out,
            seq_pose,
            seq_xyz: None,
            frame_zeros,
            frame_bias,
            trunk: Vec::new(),
            heads: None,
        };
        if n == 0 {
            self.context.submit_and_wait(encoder).map_err(gpu_error)?;
            return Ok((split_heads(&[]), cache));
        }

        let xyz = self.upload_values("canonical xyz", gaussians.xyz)?;
        let encoding_width = w.encoding_width();
        let encoding = self.zeros("xyz encoding", n * encoding_width)?;
        self.nn
            .positional_encoding_forward(&mut encoder, w.encoding(), &xyz, n, 3, &encoding)?;
        if let Some(velocity) = gaussians.knn_velocity.filter(|_| has_seq_xyz) {
            let row = config.seq_xyz_row();
            let mut inputs = Vec::with_capacity(length);
            let mut gathered = Vec::with_capacity(n * row);
            for l in 0..length {
                gathered.clear();
                for gaussian in velocity.chunks_exact(length * row) {
                    gathered.extend_from_slice(&gaussian[l * row..(l + 1) * row]);
                }
                inputs.push(self.upload_values("knn velocity", &gathered)?);
            }
            let position = self.forward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.position")?,
                &[input(&encoding, encoding_width)],
                n,
            )?;
            let velocity_layer = self.layer("non_rigid.seq_xyz_encoder.velocity")?;
            let frame_layer = self.layer("non_rigid.seq_xyz_encoder.frame")?;
            let mut velocities = Vec::with_capacity(length);
            let mut frames = Vec::with_capacity(length);
            for l in 0..length {
                let v =
                    self.forward_layer(&mut encoder, velocity_layer, &[input(&inputs[l], row)], n)?;
                let f = self.forward_layer(
                    &mut encoder,
                    frame_layer,
                    &[
                        input(&v, w.seq_xyz_velocity),
                        input(&position, w.seq_xyz_position),
                    ],
                    n,
                )?;
                velocities.push(v);
                frames.push(f);
            }
            let frame_parts: Vec<GpuInputPart<'_>> =
                frames.iter().map(|f| input(f, w.seq_xyz_frame)).collect();
            let hidden = self.forward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.sequence.0")?,
                &frame_parts,
                n,
            )?;
            let out = self.forward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.sequence.1")?,
                &[input(&hidden, w.seq_xyz_hidden)],
                n,
            )?;
            cache.seq_xyz = Some(GpuSeqXyz {
                inputs,
                velocity: velocities,
                position,
                frames,
                hidden,
                out,
            });
        }

        let mut gaussian_parts = vec![input(&encoding, encoding_width)];
        if let Some(xyz) = &cache.seq_xyz {
            gaussian_parts.push(input(&xyz.out, w.seq_xyz));
        }
        let first = self.zeros("non_rigid.trunk.0", n * width)?;
        self.nn.linear_forward(
            &mut encoder,
            LinearShape {
                in_features: gaussian_in,
                ..trunk0.shape
            },
            &trunk0.weight,
            &cache.frame_bias,
            &gaussian_parts,
            n,
            &first,
        )?;
        drop(gaussian_parts);
        cache.trunk.push(first);
        for index in 1..config.trunk_depth {
            let layer = self.layer(&format!("non_rigid.trunk.{index}"))?;
            let previous = cache.trunk.last().ok_or_else(|| gpu_error("empty trunk"))?;
            let out = self.forward_layer(&mut encoder, layer, &[input(previous, width)], n)?;
            cache.trunk.push(out);
        }
        let last = cache.trunk.last().ok_or_else(|| gpu_error("empty trunk"))?;
        let heads = self.forward_layer(
            &mut encoder,
            self.layer("non_rigid.heads")?,
            &[input(last, width)],
            n,
        )?;
        let values = self.download(encoder, &heads, n * HEAD_WIDTH)?;
        cache.encoding = Some(encoding);
        cache.heads = Some(heads);
        Ok((split_heads(&values), cache))
    }

    /// The gpu twin of [`Networks::non_rigid_backward`].
    pub fn non_rigid_backward(
        &self,
        cache: &GpuNonRigidCache,
        d_dxyz: &[f32],
        d_drot: &[f32],
        d_dscale: &[f32],
    ) -> Result<Vec<f32>, ModelError> {
        let config = &self.config;
        let w = config.widths;
        let n = cache.rows;
        check_input("d_dxyz", 3 * n, d_dxyz.len())?;
        check_input("d_drot", 4 * n, d_drot.len())?;
        check_input("d_dscale", 3 * n, d_dscale.len())?;
        // No rows: every gradient is zero (the per-frame bias has no consumer).
        let (Some(encoding), Some(heads)) = (&cache.encoding, &cache.heads) else {
            return Ok(Vec::new());
        };
        let length = config.sequence_length;
        let mut d_heads = Vec::with_capacity(n * HEAD_WIDTH);
        for g in 0..n {
            d_heads.extend_from_slice(&d_dxyz[3 * g..3 * g + 3]);
            d_heads.extend_from_slice(&d_drot[4 * g..4 * g + 4]);
            d_heads.extend_from_slice(&d_dscale[3 * g..3 * g + 3]);
        }
        let d_heads = self.upload_values("heads gradient", &d_heads)?;
        let mut encoder = self.context.encoder();
        let trunk0 = self.layer("non_rigid.trunk.0")?;
        let width = trunk0.shape.out_features;
        let mut d_current = self.zeros("trunk gradient", n * width)?;
        let mut d_previous = self.zeros("trunk gradient", n * width)?;
        let depth = cache.trunk.len();
        self.backward_layer(
            &mut encoder,
            self.layer("non_rigid.heads")?,
            &[input(&cache.trunk[depth - 1], width)],
            n,
            heads,
            &d_heads,
            &[GpuInputGrad::Write(&d_current)],
        )?;
        for index in (1..depth).rev() {
            self.backward_layer(
                &mut encoder,
                self.layer(&format!("non_rigid.trunk.{index}"))?,
                &[input(&cache.trunk[index - 1], width)],
                n,
                &cache.trunk[index],
                &d_current,
                &[GpuInputGrad::Write(&d_previous)],
            )?;
            std::mem::swap(&mut d_current, &mut d_previous);
        }

        // First trunk layer: per-Gaussian product (its bias gradient is the per-frame bias
        // gradient), then the 1-row per-frame product.
        let encoding_width = w.encoding_width();
        let gaussian_in = encoding_width
            + if cache.seq_xyz.is_some() {
                w.seq_xyz
            } else {
                0
            };
        let d_encoding = self.zeros("encoding gradient", n * encoding_width)?;
        let seq_xyz_len = if cache.seq_xyz.is_some() {
            n * w.seq_xyz
        } else {
            0
        };
        let d_seq_xyz = self.zeros("seq-xyz gradient", seq_xyz_len)?;
        let d_frame_bias = self.zeros("per-frame bias gradient", width)?;
        let mut gaussian_parts = vec![input(encoding, encoding_width)];
        let mut d_gaussian_parts = vec![GpuInputGrad::Write(&d_encoding)];
        if let Some(xyz) = &cache.seq_xyz {
            gaussian_parts.push(input(&xyz.out, w.seq_xyz));
            d_gaussian_parts.push(GpuInputGrad::Write(&d_seq_xyz));
        }
        self.nn.linear_backward(
            &mut encoder,
            LinearShape {
                in_features: gaussian_in,
                ..trunk0.shape
            },
            &trunk0.weight,
            &gaussian_parts,
            n,
            &cache.trunk[0],
            &d_current,
            GpuLinearGrads {
                weight: &trunk0.d_weight,
                bias: &d_frame_bias,
            },
            &d_gaussian_parts,
        )?;
        let d_pose_out = self.zeros("pose encoding gradient", w.pose_encoder)?;
        let d_seq_pose_out = self.zeros("seq-pose encoding gradient", w.seq_pose)?;
        let mut frame_parts = vec![
            input(&cache.frame_zeros, gaussian_in),
            input(&cache.pose_out, w.pose_encoder),
        ];
        let mut d_frame_parts = vec![GpuInputGrad::Skip, GpuInputGrad::Write(&d_pose_out)];
        if let Some([_, _, out]) = &cache.seq_pose {
            frame_parts.push(input(out, w.seq_pose));
            d_frame_parts.push(GpuInputGrad::Write(&d_seq_pose_out));
        }
        self.nn.linear_backward(
            &mut encoder,
            LinearShape {
                activation: Activation::Identity,
                ..trunk0.shape
            },
            &trunk0.weight,
            &frame_parts,
            1,
            &cache.frame_bias,
            &d_frame_bias,
            grads(trunk0),
            &d_frame_parts,
        )?;

        let d_pose_hidden = self.zeros("pose hidden gradient", w.pose_encoder)?;
        self.backward_layer(
            &mut encoder,
            self.layer("non_rigid.pose_encoder.1")?,
            &[input(&cache.pose_hidden, w.pose_encoder)],
            1,
            &cache.pose_out,
            &d_pose_out,
            &[GpuInputGrad::Write(&d_pose_hidden)],
        )?;
        self.backward_layer(
            &mut encoder,
            self.layer("non_rigid.pose_encoder.0")?,
            &[input(&cache.pose_input, config.pose_dim())],
            1,
            &cache.pose_hidden,
            &d_pose_hidden,
            &[GpuInputGrad::Skip],
        )?;

        if let Some([motion, frames, out]) = &cache.seq_pose {
            let frames_width = w.seq_pose_frame * length;
            let d_frames = self.zeros("seq-pose frames gradient", frames_width)?;
            self.backward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_pose_encoder.sequence")?,
                &[input(frames, frames_width)],
                1,
                out,
                &d_seq_pose_out,
                &[GpuInputGrad::Write(&d_frames)],
            )?;
            self.backward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_pose_encoder.frame")?,
                &[input(motion, config.seq_pose_row())],
                length,
                frames,
                &d_frames,
                &[GpuInputGrad::Skip],
            )?;
        }

        if let Some(xyz) = &cache.seq_xyz {
            let d_hidden = self.zeros("seq-xyz hidden gradient", n * w.seq_xyz_hidden)?;
            self.backward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.sequence.1")?,
                &[input(&xyz.hidden, w.seq_xyz_hidden)],
                n,
                &xyz.out,
                &d_seq_xyz,
                &[GpuInputGrad::Write(&d_hidden)],
            )?;
            let d_frames = (0..length)
                .map(|_| self.zeros("seq-xyz frame gradient", n * w.seq_xyz_frame))
                .collect::<Result<Vec<_>, _>>()?;
            let frame_parts: Vec<GpuInputPart<'_>> = xyz
                .frames
                .iter()
                .map(|f| input(f, w.seq_xyz_frame))
                .collect();
            let d_frame_parts: Vec<GpuInputGrad<'_>> =
                d_frames.iter().map(GpuInputGrad::Write).collect();
            self.backward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.sequence.0")?,
                &frame_parts,
                n,
                &xyz.hidden,
                &d_hidden,
                &d_frame_parts,
            )?;
            let d_position = self.zeros("seq-xyz position gradient", n * w.seq_xyz_position)?;
            let d_velocity = self.zeros("seq-xyz velocity gradient", n * w.seq_xyz_velocity)?;
            let row = config.seq_xyz_row();
            let frame_layer = self.layer("non_rigid.seq_xyz_encoder.frame")?;
            let velocity_layer = self.layer("non_rigid.seq_xyz_encoder.velocity")?;
            for l in 0..length {
                self.backward_layer(
                    &mut encoder,
                    frame_layer,
                    &[
                        input(&xyz.velocity[l], w.seq_xyz_velocity),
                        input(&xyz.position, w.seq_xyz_position),
                    ],
                    n,
                    &xyz.frames[l],
                    &d_frames[l],
                    &[
                        GpuInputGrad::Write(&d_velocity),
                        GpuInputGrad::Accumulate(&d_position),
                    ],
                )?;
                self.backward_layer(
                    &mut encoder,
                    velocity_layer,
                    &[input(&xyz.inputs[l], row)],
                    n,
                    &xyz.velocity[l],
                    &d_velocity,
                    &[GpuInputGrad::Skip],
                )?;
            }
            self.backward_layer(
                &mut encoder,
                self.layer("non_rigid.seq_xyz_encoder.position")?,
                &[input(encoding, encoding_width)],
                n,
                &xyz.position,
                &d_position,
                &[GpuInputGrad::Accumulate(&d_encoding)],
            )?;
        }

        let d_xyz = self.zeros("xyz gradient", 3 * n)?;
        self.nn.positional_encoding_backward(
            &mut encoder,
            w.encoding(),
            encoding,
            &d_encoding,
            n,
            3,
            &d_xyz,
        )?;
        self.download(encoder, &d_xyz, 3 * n)
    }

    /// The gpu twin of [`Networks::pose_refiner_forward`].
    pub fn pose_refiner_forward(
        &self,
        local_pose: &[f32],
    ) -> Result<(Vec<f32>, GpuPoseRefinerCache), ModelError> {
        if !self.config.pose_refiner {
            return Err(ModelError::Disabled {
                block: "the pose refiner",
            });
        }
        let pose = self.config.pose_dim();
        let hidden = self.config.widths.pose_refiner_hidden;
        check_input("local_pose", pose, local_pose.len())?;
        check_finite("local_pose", local_pose)?;
        let mut encoder = self.context.encoder();
        let pose_input = self.upload_values("refiner input", local_pose)?;
        let h0 = self.forward_layer(
            &mut encoder,
            self.layer("pose_refiner.0")?,
            &[input(&pose_input, pose)],
            1,
        )?;
        let h1 = self.forward_layer(
            &mut encoder,
            self.layer("pose_refiner.1")?,
            &[input(&h0, hidden)],
            1,
        )?;
        let output = self.forward_layer(
            &mut encoder,
            self.layer("pose_refiner.2")?,
            &[input(&h1, hidden)],
            1,
        )?;
        let rotation_vectors = self.download(encoder, &output, pose)?;
        let rotations = rotations_from_vectors(&rotation_vectors);
        Ok((
            rotations,
            GpuPoseRefinerCache {
                input: pose_input,
                hidden: [h0, h1],
                output,
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
        let pose = self.config.pose_dim();
        let hidden = self.config.widths.pose_refiner_hidden;
        check_input("d_rotations", 3 * pose, d_rotations.len())?;
        let d_vectors = rotation_vectors_backward(&cache.rotation_vectors, d_rotations);
        let d_output = self.upload_values("refiner output gradient", &d_vectors)?;
        let d_h1 = self.zeros("refiner hidden gradient", hidden)?;
        let d_h0 = self.zeros("refiner hidden gradient", hidden)?;
        let mut encoder = self.context.encoder();
        let [h0, h1] = &cache.hidden;
        self.backward_layer(
            &mut encoder,
            self.layer("pose_refiner.2")?,
            &[input(h1, hidden)],
            1,
            &cache.output,
            &d_output,
            &[GpuInputGrad::Write(&d_h1)],
        )?;
        self.backward_layer(
            &mut encoder,
            self.layer("pose_refiner.1")?,
            &[input(h0, hidden)],
            1,
            h1,
            &d_h1,
            &[GpuInputGrad::Write(&d_h0)],
        )?;
        self.backward_layer(
            &mut encoder,
            self.layer("pose_refiner.0")?,
            &[input(&cache.input, pose)],
            1,
            h0,
            &d_h0,
            &[GpuInputGrad::Skip],
        )?;
        self.context.submit_and_wait(encoder).map_err(gpu_error)
    }

    /// The gpu twin of [`Networks::lbs_offsets_forward`].
    pub fn lbs_offsets_forward(
        &self,
        xyz: &[f32],
    ) -> Result<(Vec<f32>, GpuLbsOffsetsCache), ModelError> {
        if !self.config.lbs_offsets {
            return Err(ModelError::Disabled {
                block: "the LBS offsets",
            });
        }
        if !xyz.len().is_multiple_of(3) {
            return Err(ModelError::Input {
                field: "lbs xyz".into(),
                message: format!("{} values is not a whole number of 3-vectors", xyz.len()),
            });
        }
        check_finite("lbs xyz", xyz)?;
        let n = xyz.len() / 3;
        let w = self.config.widths;
        let joints = self.config.skinning_joints;
        let encoding_width = w.encoding_width();
        let hidden = w.lbs_hidden;
        let encoding = self.zeros("lbs encoding", n * encoding_width)?;
        if n == 0 {
            return Ok((
                Vec::new(),
                GpuLbsOffsetsCache {
                    rows: 0,
                    encoding,
                    outputs: Vec::new(),
                },
            ));
        }
        let mut encoder = self.context.encoder();
        let points = self.upload_values("lbs xyz", xyz)?;
        self.nn.positional_encoding_forward(
            &mut encoder,
            w.encoding(),
            &points,
            n,
            3,
            &encoding,
        )?;
        let mut outputs: Vec<wgpu::Buffer> = Vec::with_capacity(5);
        for index in 0..5 {
            let layer = self.layer(&format!("lbs_offsets.{index}"))?;
            let out = match index {
                0 => {
                    self.forward_layer(&mut encoder, layer, &[input(&encoding, encoding_width)], n)?
                }
                3 => self.forward_layer(
                    &mut encoder,
                    layer,
                    &[input(&outputs[2], hidden), input(&encoding, encoding_width)],
                    n,
                )?,
                _ => self.forward_layer(
                    &mut encoder,
                    layer,
                    &[input(&outputs[index - 1], hidden)],
                    n,
                )?,
            };
            outputs.push(out);
        }
        let offsets = self.download(encoder, &outputs[4], n * joints)?;
        Ok((
            offsets,
            GpuLbsOffsetsCache {
                rows: n,
                encoding,
                outputs,
            },
        ))
    }

    /// The gpu twin of [`Networks::lbs_offsets_backward`].
    pub fn lbs_offsets_backward(
        &self,
        cache: &GpuLbsOffsetsCache,
        d_offsets: &[f32],
    ) -> Result<(), ModelError> {
        let n = cache.rows;
        let joints = self.config.skinning_joints;
        check_input("d_offsets", n * joints, d_offsets.len())?;
        if n == 0 {
            return Ok(());
        }
        let w = self.config.widths;
        let encoding_width = w.encoding_width();
        let hidden = w.lbs_hidden;
        let d_output = self.upload_values("lbs offsets gradient", d_offsets)?;
        let mut d_current = self.zeros("lbs gradient", n * hidden)?;
        let mut d_previous = self.zeros("lbs gradient", n * hidden)?;
        let mut encoder = self.context.encoder();
        for index in (0..5).rev() {
            let layer = self.layer(&format!("lbs_offsets.{index}"))?;
            let d_out = if index == 4 { &d_output } else { &d_current };
            let out = &cache.outputs[index];
            match index {
                0 => self.backward_layer(
                    &mut encoder,
                    layer,
                    &[input(&cache.encoding, encoding_width)],
                    n,
                    out,
                    d_out,
                    &[GpuInputGrad::Skip],
                )?,
                3 => self.backward_layer(
                    &mut encoder,
                    layer,
                    &[
                        input(&cache.outputs[2], hidden),
                        input(&cache.encoding, encoding_width),
                    ],
                    n,
                    out,
                    d_out,
                    &[GpuInputGrad::Write(&d_previous), GpuInputGrad::Skip],
                )?,
                _ => self.backward_layer(
                    &mut encoder,
                    layer,
                    &[input(&cache.outputs[index - 1], hidden)],
                    n,
                    out,
                    d_out,
                    &[GpuInputGrad::Write(&d_previous)],
                )?,
            }
            std::mem::swap(&mut d_current, &mut d_previous);
        }
        self.context.submit_and_wait(encoder).map_err(gpu_error)
    }
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_ne_bytes()).collect()
}
