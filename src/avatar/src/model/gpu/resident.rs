//! The resident networks: forward and backward of each network recorded into a caller's
//! encoder on device input buffers, into device buffers the networks own, and Adam of every
//! network parameter on the device (`docs/resident-step.md`).
//!
//! Each network has a workspace ([`ResidentNet`]) sized for a capacity of Gaussians: copies
//! of its input blocks, the encoded inputs, every layer's output blocks, the folded per-frame
//! biases, and the gradients of every value. Its forward and backward are two
//! [`NnProgram`]s (uniform blocks and bind groups created once), rebuilt only when the
//! Gaussian count changes (densification) and reallocated only when it grows, so a
//! steady-state iteration records device copies and replayed dispatches: no upload, no
//! read-back, no buffer creation.
//!
//! The caller's input blocks are copied into the workspace by a device copy at the start of
//! the forward (a few bytes per Gaussian; the copy frees the programs from the identity of
//! the caller's buffers), and the output gradient likewise at the start of the backward.

use std::collections::HashMap;

use seqavatar_compute::nn::adam::{AdamState, AdamStepFactors};
use seqavatar_compute::nn::gpu::{
    GpuAdamValues, GpuInput, GpuInputGrad, GpuInputPart, GpuLinear, GpuLinearGrads, NnProgram,
    Record, adam_factors_record, first_non_finite,
};
use seqavatar_compute::nn::{AdamConfig, LinearShape};

use super::super::network::folded_shapes;
use super::super::pose_refiner::THETA_SQUARED_EPSILON;
use super::super::spec::{NetworkSpec, Value};
use super::super::{ModelError, NetworkGroup};
use super::{GpuDense, GpuNet, GpuNetworks, gpu_error, grads, input};

/// The device input blocks of the non-rigid network for [`GpuNetworks::record_non_rigid_forward`].
#[derive(Clone, Copy, Debug)]
pub struct NonRigidDeviceInputs<'a> {
    /// The frame's local pose without the root, `1 x 3 (J - 1)` (`FrameInputs::local_pose`).
    pub local_pose: &'a wgpu::Buffer,
    /// The frame's skeleton-motion window, `L x seq_pose_row` (`FrameInputs::skeleton_motion`);
    /// `None` exactly when the motion context has no skeleton motion.
    pub skeleton_motion: Option<&'a wgpu::Buffer>,
    /// Canonical centres, `n x 3` (encoded on the device).
    pub xyz: &'a wgpu::Buffer,
    /// The KNN velocities as `L` buffers of `n x seq_xyz_row`, one per window element (the
    /// element-`l` slices of `GaussianInputs::knn_velocity`); empty exactly when the motion
    /// context has no velocity.
    pub knn_velocity: &'a [&'a wgpu::Buffer],
}

/// A non-finite network value found on the device (the `cpu` trainer's `Divergence`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NetworkNonFinite {
    /// `network.{parameter name}`, as the `cpu` trainer names it.
    pub tensor: String,
    /// Whether the gradient (before the update) was non-finite, else the values (after it).
    pub gradient: bool,
    /// The first non-finite index in the array.
    pub index: usize,
}

/// The workspace and programs of one network (see the module documentation).
#[derive(Debug)]
pub(super) struct ResidentNet {
    /// Per-Gaussian rows the buffers hold.
    capacity: usize,
    /// The Gaussian count the programs were built for.
    built_for: Option<usize>,
    /// Per input, per block: the caller's values, copied in.
    raw: Vec<Vec<wgpu::Buffer>>,
    /// Per input, per block: the values the layers read (the encoding of `raw`, or `raw`).
    values: Vec<Vec<wgpu::Buffer>>,
    /// Per layer, per block: its output.
    outputs: Vec<Vec<wgpu::Buffer>>,
    /// Per layer: the zero placeholder, the per-frame bias and its gradient of a folded layer.
    frame_bias: Vec<Option<[wgpu::Buffer; 3]>>,
    /// Per input, per block: the gradient of its values (inputs returning a gradient only).
    d_values: Vec<Vec<Option<wgpu::Buffer>>>,
    /// Per input: the gradient of its raw values (inputs returning a gradient only).
    d_raw: Vec<Option<wgpu::Buffer>>,
    /// Per layer, per block: the gradient of its output.
    d_outputs: Vec<Vec<wgpu::Buffer>>,
    /// The pose refiner's `(J - 1) x 9` matrices and their gradient.
    rotations: Option<[wgpu::Buffer; 2]>,
    forward: NnProgram,
    backward: NnProgram,
    /// Whether a forward was recorded since the programs were built (the backward reads its
    /// activations).
    forward_recorded: bool,
}

/// Adam of every network parameter on the device.
#[derive(Debug)]
pub(super) struct ResidentAdam {
    config: AdamConfig,
    /// Per parameter array (order of [`GpuNetworks::parameters`]): first and second moments.
    moments: Vec<[wgpu::Buffer; 2]>,
    /// `[step_size, correction]` per network group (slot = [`NetworkGroup::index`]).
    record: wgpu::Buffer,
    /// Non-finite flags (`nn_finite.wgsl`), `u32`: per parameter array `p`, slot `2 p` for its
    /// gradient (checked before the update) and `2 p + 1` for its values (after).
    status: wgpu::Buffer,
    program: NnProgram,
    /// Updates applied so far.
    step: u64,
}

const GROUPS: [NetworkGroup; 3] = [
    NetworkGroup::NonRigid,
    NetworkGroup::PoseRefiner,
    NetworkGroup::LbsOffsets,
];

fn per_gaussian(spec: &NetworkSpec) -> bool {
    spec.inputs.iter().any(|i| i.rows.per_gaussian())
}

fn byte_len(values: usize) -> u64 {
    4 * values as u64
}

/// An error unless the device buffer `buffer` holds at least `len` f32 values.
fn check_holds(buffer: &wgpu::Buffer, len: usize, field: String) -> Result<(), ModelError> {
    if buffer.size() < byte_len(len) {
        return Err(ModelError::Input {
            field,
            message: format!(
                "a device buffer of {} bytes holds fewer than {len} values",
                buffer.size()
            ),
        });
    }
    Ok(())
}

/// The two products of a layer whose per-frame inputs fold into a per-frame bias: the
/// per-Gaussian one (the leading `rows_in` weight rows) and the 1-row per-frame one, whose
/// input is `frame` after the zero `placeholder` of the per-Gaussian rows (so that it reads
/// the one weight buffer whole), with that input.
fn folded<'a>(
    layer: &'a GpuDense,
    rows_in: usize,
    placeholder: &'a wgpu::Buffer,
    frame: Vec<GpuInputPart<'a>>,
) -> (GpuLinear<'a>, GpuLinear<'a>, Vec<GpuInputPart<'a>>) {
    let (rows_shape, frame_shape) = folded_shapes(layer.shape, rows_in);
    let frame_shape = LinearShape {
        in_features: layer.shape.in_features,
        ..frame_shape
    };
    let mut parts = vec![input(placeholder, rows_in)];
    parts.extend(frame);
    (
        GpuLinear::new(rows_shape, &layer.weight),
        GpuLinear::new(frame_shape, &layer.weight),
        parts,
    )
}

impl GpuNetworks {
    /// The description of a network, or that it is disabled.
    fn resident_net(&self, group: NetworkGroup) -> Result<&GpuNet, ModelError> {
        self.nets[group.index()]
            .as_ref()
            .ok_or(ModelError::Disabled {
                block: group.block(),
            })
    }

    /// Allocates the workspace of `group` for `capacity` Gaussians.
    fn allocate_resident(
        &self,
        group: NetworkGroup,
        capacity: usize,
    ) -> Result<ResidentNet, ModelError> {
        let net = self.resident_net(group)?;
        let spec = &net.spec;
        let window = spec.window;
        let zeros = |what: &str, len: usize| self.zeros(what, len.max(1));
        let mut raw = Vec::new();
        let mut values = Vec::new();
        let mut d_values = Vec::new();
        let mut d_raw = Vec::new();
        for input in &spec.inputs {
            let rows = input.rows.block_rows(capacity, window);
            let blocks = input.rows.calls(window);
            let raw_blocks = (0..blocks)
                .map(|_| zeros(&input.name, rows * input.width))
                .collect::<Result<Vec<_>, _>>()?;
            let value_blocks = match input.encoding {
                None => raw_blocks.clone(),
                Some(_) => (0..blocks)
                    .map(|_| zeros(&input.name, rows * input.value_width()))
                    .collect::<Result<Vec<_>, _>>()?,
            };
            if input.gradient {
                let d_value = zeros("input gradient", rows * input.value_width())?;
                d_raw.push(Some(match input.encoding {
                    None => d_value.clone(),
                    Some(_) => zeros("input gradient", rows * input.width)?,
                }));
                d_values.push(vec![Some(d_value)]);
            } else {
                d_raw.push(None);
                d_values.push(vec![None; blocks]);
            }
            raw.push(raw_blocks);
            values.push(value_blocks);
        }
        let mut outputs = Vec::new();
        let mut d_outputs = Vec::new();
        let mut frame_bias = Vec::new();
        for (index, layer) in spec.layers.iter().enumerate() {
            let rows = layer.rows.block_rows(capacity, window);
            let blocks = layer.rows.calls(window);
            let name = spec.parameter_name(index);
            outputs.push(
                (0..blocks)
                    .map(|_| zeros(&name, rows * layer.out))
                    .collect::<Result<Vec<_>, _>>()?,
            );
            d_outputs.push(
                (0..blocks)
                    .map(|_| zeros(&format!("{name} gradient"), rows * layer.out))
                    .collect::<Result<Vec<_>, _>>()?,
            );
            let plan = spec.plan(index, 0);
            frame_bias.push(if plan.frame.is_empty() {
                None
            } else {
                Some([
                    zeros("per-Gaussian placeholder", plan.rows_in())?,
                    zeros("per-frame bias", layer.out)?,
                    zeros("per-frame bias gradient", layer.out)?,
                ])
            });
        }
        let rotations = if group == NetworkGroup::PoseRefiner {
            let count = spec.layers[spec.output].out / 3;
            Some([
                zeros("pose refiner rotations", 9 * count)?,
                zeros("pose refiner rotation gradient", 9 * count)?,
            ])
        } else {
            None
        };
        Ok(ResidentNet {
            capacity,
            built_for: None,
            raw,
            values,
            outputs,
            frame_bias,
            d_values,
            d_raw,
            d_outputs,
            rotations,
            forward: NnProgram::new(),
            backward: NnProgram::new(),
            forward_recorded: false,
        })
    }

    /// Records the forward and backward programs of `group` for `n` Gaussians.
    fn build_programs(
        &self,
        group: NetworkGroup,
        work: &mut ResidentNet,
        n: usize,
    ) -> Result<(), ModelError> {
        let net = self.resident_net(group)?;
        let spec = &net.spec;
        let window = spec.window;
        self.programs_built
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut forward = NnProgram::new();
        let mut backward = NnProgram::new();
        if n == 0 && per_gaussian(spec) {
            // Nothing runs (as on `cpu`): every input gradient is zero.
            for d_raw in work.d_raw.iter().flatten() {
                backward.record_clear(d_raw);
            }
            work.forward = forward;
            work.backward = backward;
            work.built_for = Some(n);
            return Ok(());
        }
        let parts_of = |parts: &[super::super::spec::Part]| -> Vec<GpuInputPart<'_>> {
            parts
                .iter()
                .map(|part| input(part.pick(&work.values, &work.outputs), part.cols))
                .collect()
        };

        // Forward.
        for (index, input_spec) in spec.inputs.iter().enumerate() {
            if let Some(encoding) = input_spec.encoding {
                let rows = input_spec.rows.block_rows(n, window);
                for (raw, value) in work.raw[index].iter().zip(&work.values[index]) {
                    self.nn.positional_encoding_forward(
                        &mut forward,
                        encoding,
                        raw,
                        (rows, input_spec.width),
                        value,
                    )?;
                }
            }
        }
        for index in 0..spec.layers.len() {
            let layer = &self.layers[net.first + index];
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                let parts = parts_of(&plan.rows);
                let out = &work.outputs[index][call];
                match &work.frame_bias[index] {
                    None => self.nn.linear_forward(
                        &mut forward,
                        GpuLinear::new(layer.shape, &layer.weight),
                        &layer.bias,
                        GpuInput::new(&parts, rows),
                        out,
                    )?,
                    Some([placeholder, bias, _]) => {
                        let (rows_linear, frame_linear, frame_parts) =
                            folded(layer, plan.rows_in(), placeholder, parts_of(&plan.frame));
                        self.nn.linear_forward(
                            &mut forward,
                            frame_linear,
                            &layer.bias,
                            GpuInput::new(&frame_parts, 1),
                            bias,
                        )?;
                        self.nn.linear_forward(
                            &mut forward,
                            rows_linear,
                            bias,
                            GpuInput::new(&parts, rows),
                            out,
                        )?;
                    }
                }
            }
        }
        let output = &work.outputs[spec.output][0];
        if let Some([rotations, d_rotations]) = &work.rotations {
            let count = spec.layers[spec.output].out / 3;
            self.nn.rodrigues_forward(
                &mut forward,
                THETA_SQUARED_EPSILON,
                output,
                count,
                rotations,
            )?;
            self.nn.rodrigues_backward(
                &mut backward,
                THETA_SQUARED_EPSILON,
                output,
                d_rotations,
                count,
                &work.d_outputs[spec.output][0],
            )?;
        }

        // Backward: a gradient buffer is written by its first contribution and accumulated
        // into by the later ones, in the order of the `cpu` interpreter.
        let mut input_written: Vec<Vec<bool>> = work
            .d_values
            .iter()
            .map(|blocks| vec![false; blocks.len()])
            .collect();
        let mut layer_written: Vec<Vec<bool>> = work
            .d_outputs
            .iter()
            .map(|blocks| vec![false; blocks.len()])
            .collect();
        layer_written[spec.output][0] = true;
        for index in (0..spec.layers.len()).rev() {
            let layer = &self.layers[net.first + index];
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                if !layer_written[index][call] {
                    return Err(ModelError::Input {
                        field: spec.parameter_name(index),
                        message: "no gradient reached this layer".into(),
                    });
                }
                let mut sinks = |parts: &[super::super::spec::Part]| -> Vec<GpuInputGrad<'_>> {
                    parts
                        .iter()
                        .map(|part| {
                            let (buffer, written) = match part.value {
                                Value::Input(i) => (
                                    work.d_values[i][part.block].as_ref(),
                                    &mut input_written[i][part.block],
                                ),
                                Value::Layer(j) => (
                                    Some(&work.d_outputs[j][part.block]),
                                    &mut layer_written[j][part.block],
                                ),
                            };
                            match buffer {
                                None => GpuInputGrad::Skip,
                                Some(buffer) if *written => GpuInputGrad::Accumulate(buffer),
                                Some(buffer) => {
                                    *written = true;
                                    GpuInputGrad::Write(buffer)
                                }
                            }
                        })
                        .collect()
                };
                let rows_d = sinks(&plan.rows);
                let frame_d = sinks(&plan.frame);
                let parts = parts_of(&plan.rows);
                let out = &work.outputs[index][call];
                let d_out = &work.d_outputs[index][call];
                match &work.frame_bias[index] {
                    None => self.nn.linear_backward(
                        &mut backward,
                        GpuLinear::new(layer.shape, &layer.weight),
                        GpuInput::new(&parts, rows),
                        out,
                        d_out,
                        grads(layer, &rows_d),
                    )?,
                    Some([placeholder, bias, d_bias]) => {
                        let (rows_linear, frame_linear, frame_parts) =
                            folded(layer, plan.rows_in(), placeholder, parts_of(&plan.frame));
                        backward.record_clear(d_bias);
                        self.nn.linear_backward(
                            &mut backward,
                            rows_linear,
                            GpuInput::new(&parts, rows),
                            out,
                            d_out,
                            GpuLinearGrads {
                                weight: &layer.d_weight,
                                bias: d_bias,
                                inputs: &rows_d,
                            },
                        )?;
                        let mut d_frame = vec![GpuInputGrad::Skip];
                        d_frame.extend(frame_d);
                        self.nn.linear_backward(
                            &mut backward,
                            frame_linear,
                            GpuInput::new(&frame_parts, 1),
                            bias,
                            d_bias,
                            grads(layer, &d_frame),
                        )?;
                    }
                }
            }
        }
        for (index, input_spec) in spec.inputs.iter().enumerate() {
            let Some(d_raw) = &work.d_raw[index] else {
                continue;
            };
            let written = input_written[index][0];
            match (input_spec.encoding, written) {
                (_, false) => backward.record_clear(d_raw),
                (None, true) => {}
                (Some(encoding), true) => {
                    let d_value = work.d_values[index][0]
                        .as_ref()
                        .ok_or_else(|| gpu_error("input gradient buffer"))?;
                    self.nn.positional_encoding_backward(
                        &mut backward,
                        encoding,
                        &work.values[index][0],
                        d_value,
                        (input_spec.rows.block_rows(n, window), input_spec.width),
                        d_raw,
                    )?;
                }
            }
        }
        work.forward = forward;
        work.backward = backward;
        work.built_for = Some(n);
        Ok(())
    }

    /// Records the forward of network `group` with `n` Gaussians on device input blocks:
    /// `inputs[i]` are the blocks of the description's input `i` (one buffer, or `L` buffers
    /// of `n x width` for a per-Gaussian-window input), each holding at least its rows x
    /// width f32 values in the `cpu` layout. The output (the output layer's `rows x out`
    /// values; for the pose refiner the `(J - 1) x 9` row-major matrices), returned, stays in
    /// a buffer of the networks. Reallocates the workspace only
    /// when `n` exceeds its capacity, and rebuilds the programs only when `n` changed.
    pub fn record_forward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        group: NetworkGroup,
        n: usize,
        inputs: &[&[&wgpu::Buffer]],
    ) -> Result<&wgpu::Buffer, ModelError> {
        let spec = self.resident_net(group)?.spec.clone();
        if inputs.len() != spec.inputs.len() {
            return Err(ModelError::Input {
                field: format!("{} inputs", spec.prefix),
                message: format!(
                    "expected {} blocks, got {}",
                    spec.inputs.len(),
                    inputs.len()
                ),
            });
        }
        for (input_spec, blocks) in spec.inputs.iter().zip(inputs) {
            let expected = input_spec.rows.calls(spec.window);
            if blocks.len() != expected {
                return Err(ModelError::Input {
                    field: input_spec.name.clone(),
                    message: format!("expected {expected} device buffers, got {}", blocks.len()),
                });
            }
            let len = input_spec.rows.block_rows(n, spec.window) * input_spec.width;
            for buffer in blocks.iter() {
                check_holds(buffer, len, input_spec.name.clone())?;
            }
        }
        let slot = group.index();
        let mut work = match self.resident[slot].take() {
            Some(work) if work.capacity >= n => work,
            _ => self.allocate_resident(group, n)?,
        };
        if work.built_for != Some(n)
            && let Err(error) = self.build_programs(group, &mut work, n)
        {
            self.resident[slot] = Some(work);
            return Err(error);
        }
        for ((input_spec, blocks), raw) in spec.inputs.iter().zip(inputs).zip(&work.raw) {
            let len = input_spec.rows.block_rows(n, spec.window) * input_spec.width;
            if len == 0 {
                continue;
            }
            for (source, target) in blocks.iter().zip(raw) {
                encoder.copy_buffer_to_buffer(source, 0, target, 0, byte_len(len));
            }
        }
        work.forward.replay(encoder);
        work.forward_recorded = true;
        let work = self.resident[slot].insert(work);
        Ok(match &work.rotations {
            Some([rotations, _]) => rotations,
            None => &work.outputs[spec.output][0],
        })
    }

    /// Records the backward of the last [`GpuNetworks::record_forward`] of `group` (same
    /// encoder or an earlier submission): `d_output` has the layout of the forward's output
    /// (`rows x out`; for the pose refiner the `(J - 1) x 9` matrices' gradient). The
    /// parameter gradients are accumulated into the device gradient buffers
    /// ([`GpuNetworks::parameters`]); the gradients of the inputs that return one are written
    /// into buffers of the networks ([`GpuNetworks::resident_input_gradient`]).
    pub fn record_backward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        group: NetworkGroup,
        d_output: &wgpu::Buffer,
    ) -> Result<(), ModelError> {
        let net = self.resident_net(group)?;
        let spec = &net.spec;
        let work = self.resident[group.index()]
            .as_ref()
            .filter(|work| work.forward_recorded)
            .ok_or_else(|| ModelError::Input {
                field: format!("{} backward", spec.prefix),
                message: "no resident forward was recorded".into(),
            })?;
        let n = work.built_for.unwrap_or(0);
        let (target, len) = match &work.rotations {
            Some([_, d_rotations]) => (d_rotations, 3 * spec.layers[spec.output].out),
            None => {
                let output = &spec.layers[spec.output];
                (
                    &work.d_outputs[spec.output][0],
                    output.rows.block_rows(n, spec.window) * output.out,
                )
            }
        };
        let ran = n > 0 || !per_gaussian(spec);
        if ran && len > 0 {
            check_holds(d_output, len, format!("{} output gradient", spec.prefix))?;
            encoder.copy_buffer_to_buffer(d_output, 0, target, 0, byte_len(len));
        }
        work.backward.replay(encoder);
        Ok(())
    }

    /// The device gradient of input `input` of `group` (its raw `rows x width` layout) written
    /// by the last resident backward, or `None` when that input returns no gradient (or no
    /// forward was recorded).
    pub fn resident_input_gradient(
        &self,
        group: NetworkGroup,
        input: usize,
    ) -> Option<&wgpu::Buffer> {
        self.resident[group.index()]
            .as_ref()?
            .d_raw
            .get(input)?
            .as_ref()
    }

    /// Records the non-rigid network's forward; returns the heads, `n x 10` per Gaussian
    /// `[d_xyz (3), d_rot - (1, 0, 0, 0) (4, w x y z), d_scale (3)]` (the rotation head before
    /// the identity is added, as `split_heads` does on `cpu`).
    pub fn record_non_rigid_forward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        n: usize,
        inputs: &NonRigidDeviceInputs<'_>,
    ) -> Result<&wgpu::Buffer, ModelError> {
        let spec = &self.resident_net(NetworkGroup::NonRigid)?.spec;
        let mut blocks: Vec<Vec<&wgpu::Buffer>> = Vec::new();
        for input_spec in &spec.inputs {
            blocks.push(match input_spec.name.as_str() {
                "frame.local_pose" => vec![inputs.local_pose],
                "frame.skeleton_motion" => inputs.skeleton_motion.into_iter().collect(),
                "gaussians.xyz" => vec![inputs.xyz],
                "gaussians.knn_velocity" => inputs.knn_velocity.to_vec(),
                other => return Err(gpu_error(format!("unknown non-rigid input `{other}`"))),
            });
        }
        let blocks: Vec<&[&wgpu::Buffer]> = blocks.iter().map(Vec::as_slice).collect();
        self.record_forward(encoder, NetworkGroup::NonRigid, n, &blocks)
    }

    /// Records the non-rigid backward from `d_heads` (`n x 10`, the layout of
    /// [`GpuNetworks::record_non_rigid_forward`]'s output); returns the gradient of the
    /// canonical centres, `n x 3`.
    pub fn record_non_rigid_backward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        d_heads: &wgpu::Buffer,
    ) -> Result<&wgpu::Buffer, ModelError> {
        self.record_backward(encoder, NetworkGroup::NonRigid, d_heads)?;
        let index = self
            .resident_net(NetworkGroup::NonRigid)?
            .spec
            .inputs
            .iter()
            .position(|i| i.name == "gaussians.xyz")
            .ok_or_else(|| gpu_error("the non-rigid network has no xyz input"))?;
        self.resident_input_gradient(NetworkGroup::NonRigid, index)
            .ok_or_else(|| gpu_error("the non-rigid xyz input has no gradient"))
    }

    /// Records the zeroing of every parameter gradient.
    pub fn record_zero_grad(&self, encoder: &mut wgpu::CommandEncoder) {
        for layer in &self.layers {
            encoder.clear_buffer(&layer.d_weight, 0, None);
            encoder.clear_buffer(&layer.d_bias, 0, None);
        }
    }

    /// The Adam program of every parameter for `config`, around `moments` (new zero
    /// moments when `None`).
    fn build_adam(
        &self,
        config: &AdamConfig,
        moments: Option<Vec<[wgpu::Buffer; 2]>>,
        step: u64,
    ) -> Result<ResidentAdam, ModelError> {
        config.validate()?;
        self.programs_built
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let params = self.parameters();
        let moments = match moments {
            Some(moments) => moments,
            None => params
                .iter()
                .map(|param| {
                    Ok([
                        self.zeros(&format!("{} adam m", param.name), param.len)?,
                        self.zeros(&format!("{} adam v", param.name), param.len)?,
                    ])
                })
                .collect::<Result<Vec<_>, ModelError>>()?,
        };
        let record = self.zeros("network adam record", 2 * GROUPS.len())?;
        let status = self.zeros("network non-finite status", 2 * params.len())?;
        let mut program = NnProgram::new();
        for (index, (param, [m, v])) in params.iter().zip(&moments).enumerate() {
            self.nn
                .flag_non_finite(&mut program, param.grads, param.len, &status, 2 * index)?;
            self.nn.adam_update_from_record(
                &mut program,
                config,
                (&record, param.group.index()),
                GpuAdamValues {
                    params: param.values,
                    grads: param.grads,
                    first_moment: m,
                    second_moment: v,
                    len: param.len,
                },
            )?;
            self.nn.flag_non_finite(
                &mut program,
                param.values,
                param.len,
                &status,
                2 * index + 1,
            )?;
        }
        Ok(ResidentAdam {
            config: *config,
            moments,
            record,
            status,
            program,
            step,
        })
    }

    /// Records one Adam update of every network parameter from its accumulated gradient,
    /// group `g` at rate `rate(g)` (the caller's decayed rate: the trainer uses
    /// `lr_g * network_decay^((iteration - 1) / iterations)`), as the `cpu` `adam_update`
    /// does with one shared update count. Writes the 24-byte step record (one
    /// `GpuContext::write`); the moments are created at the first call (or by
    /// [`GpuNetworks::upload_adam`]) and the gradients are left as they are
    /// ([`GpuNetworks::record_zero_grad`] clears them).
    pub fn record_adam(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        config: &AdamConfig,
        rate: impl Fn(NetworkGroup) -> f64,
    ) -> Result<(), ModelError> {
        let mut adam = match self.adam.take() {
            Some(adam) if &adam.config == config => adam,
            Some(adam) => self.build_adam(config, Some(adam.moments), adam.step)?,
            None => self.build_adam(config, None, 0)?,
        };
        adam.step += 1;
        let factors: Vec<AdamStepFactors> = GROUPS
            .iter()
            .map(|&group| AdamStepFactors::new(config, rate(group), adam.step))
            .collect();
        let record = adam_factors_record(&factors);
        let written = self.context.write(&adam.record, 0, &record);
        if let Err(error) = written {
            adam.step -= 1;
            self.adam = Some(adam);
            return Err(gpu_error(error));
        }
        adam.program.replay(encoder);
        self.adam = Some(adam);
        Ok(())
    }

    /// Reads the non-finite flags of the device Adam (one read-back, for the logging
    /// iterations): the first parameter array, in [`GpuNetworks::parameters`] order, whose
    /// gradient (checked before the update) or values (after it) held a NaN or an infinity
    /// since the first update (the flags are never cleared: a run stops at a divergence), with
    /// the first bad index; `None` when all were finite or no update ran.
    pub fn download_non_finite(&self) -> Result<Option<NetworkNonFinite>, ModelError> {
        let Some(adam) = &self.adam else {
            return Ok(None);
        };
        let params = self.parameters();
        let flags = self
            .context
            .download::<u32>(self.context.encoder(), &adam.status, 2 * params.len())
            .map_err(gpu_error)?;
        for (param, pair) in params.iter().zip(flags.chunks_exact(2)) {
            for (gradient, &flag) in [true, false].into_iter().zip(pair) {
                if let Some(index) = first_non_finite(flag) {
                    return Ok(Some(NetworkNonFinite {
                        tensor: format!("network.{}", param.name),
                        gradient,
                        index,
                    }));
                }
            }
        }
        Ok(None)
    }

    /// How many resident programs were built so far (a steady-state iteration builds none).
    pub fn resident_programs_built(&self) -> usize {
        self.programs_built
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Downloads the device Adam moments, by parameter name, as the `cpu` trainer keeps them
    /// (empty before the first update). One read-back.
    pub fn download_adam(&self) -> Result<HashMap<String, AdamState<f32>>, ModelError> {
        let Some(adam) = &self.adam else {
            return Ok(HashMap::new());
        };
        let params = self.parameters();
        let mut sources = Vec::with_capacity(2 * params.len());
        for (param, [m, v]) in params.iter().zip(&adam.moments) {
            sources.push((m, param.len));
            sources.push((v, param.len));
        }
        let mut arrays = self
            .context
            .download_all::<f32>(self.context.encoder(), &sources)
            .map_err(gpu_error)?
            .into_iter();
        let mut states = HashMap::new();
        for param in &params {
            let m = arrays.next().ok_or_else(|| gpu_error("moment count"))?;
            let v = arrays.next().ok_or_else(|| gpu_error("moment count"))?;
            states.insert(
                param.name.clone(),
                AdamState {
                    m,
                    v,
                    step: adam.step,
                },
            );
        }
        Ok(states)
    }

    /// Uploads Adam moments (a resumed checkpoint: the `cpu` trainer's map by parameter
    /// name) for updates with `config`. Every parameter needs its state, all with the same
    /// update count.
    pub fn upload_adam(
        &mut self,
        config: &AdamConfig,
        states: &HashMap<String, AdamState<f32>>,
    ) -> Result<(), ModelError> {
        let mut adam = self.build_adam(config, None, 0)?;
        let mut step = None;
        for (param, [m, v]) in self.parameters().iter().zip(&adam.moments) {
            let bad = |message: String| ModelError::Input {
                field: format!("adam state of {}", param.name),
                message,
            };
            let state = states
                .get(&param.name)
                .ok_or_else(|| bad("missing".into()))?;
            if state.m.len() != param.len || state.v.len() != param.len {
                return Err(bad(format!(
                    "moments of {} and {} values for {} parameters",
                    state.m.len(),
                    state.v.len(),
                    param.len
                )));
            }
            if *step.get_or_insert(state.step) != state.step {
                return Err(bad(format!(
                    "update count {} differs from the others' {}",
                    state.step,
                    step.unwrap_or_default()
                )));
            }
            self.context.write(m, 0, &state.m).map_err(gpu_error)?;
            self.context.write(v, 0, &state.v).map_err(gpu_error)?;
        }
        adam.step = step.unwrap_or(0);
        self.adam = Some(adam);
        Ok(())
    }
}
