//! The non-rigid deformation network: position encoding, pose / skeleton-motion / velocity
//! encoders and the trunk with its three heads, forward and backward on `cpu`.
//!
//! Layouts (row-major): positions `n x 3`; the velocity window `n x L x tau x |S| x 3`
//! (`[gaussian][window element][neighbour][scale, largest first][xyz]`); skeleton motion
//! `L x |S| x motion_joints x 3`. Window elements are processed as `L` separate `n`-row
//! blocks, so the per-Gaussian position branch of the `SeqXYZEncoder` is read by every
//! element without being copied, and the flattening `Linear(96 L, 256)` reads the `L` blocks
//! as the column blocks of its input.

use seqavatar_compute::nn::linear::{InputGrad, LinearGrads};
use seqavatar_compute::nn::{
    Activation, InputPart, LinearShape, NnScalar, Rng, linear_backward, linear_forward,
    positional_encoding_backward, positional_encoding_forward,
};

use super::dense::{Dense, Init, part};
use super::{HEAD_WIDTH, ModelError, NetworkConfig, NetworkGroup, check_finite, check_input};

/// The per-frame inputs of the non-rigid network.
#[derive(Clone, Copy, Debug)]
pub struct FrameInputs<'a, S> {
    /// The local pose without the root joint, `3 (J - 1)` axis-angle values.
    pub local_pose: &'a [S],
    /// The skeleton-motion window `L x |S| x motion_joints x 3`; required exactly when the
    /// motion context includes skeleton motion.
    pub skeleton_motion: Option<&'a [S]>,
}

/// The per-Gaussian inputs of the non-rigid network.
#[derive(Clone, Copy, Debug)]
pub struct GaussianInputs<'a, S> {
    /// Canonical positions (before the non-rigid offset), `n x 3`.
    pub xyz: &'a [S],
    /// Velocities of each Gaussian's `tau` nearest template vertices,
    /// `n x L x tau x |S| x 3`; required exactly when the motion context includes velocity.
    pub knn_velocity: Option<&'a [S]>,
}

/// The deformation of `n` Gaussians.
#[derive(Clone, Debug, PartialEq)]
pub struct NonRigidOutput<S> {
    /// Position offsets, `n x 3`.
    pub d_xyz: Vec<S>,
    /// Rotation quaternions `[w, x, y, z]`, unnormalised, `n x 4`; the head's output plus 1
    /// on `w` (identity bias).
    pub d_rot: Vec<S>,
    /// Linear-space scale offsets, `n x 3`.
    pub d_scale: Vec<S>,
}

/// The activations of one forward pass, for its backward.
#[derive(Clone, Debug, Default)]
pub struct NonRigidCache<S> {
    rows: usize,
    encoding: Vec<S>,
    local_pose: Vec<S>,
    pose_hidden: Vec<S>,
    pose_out: Vec<S>,
    skeleton_motion: Vec<S>,
    seq_pose_frames: Vec<S>,
    seq_pose_out: Vec<S>,
    seq_xyz: Option<SeqXyzCache<S>>,
    frame_bias: Vec<S>,
    trunk: Vec<Vec<S>>,
    heads: Vec<S>,
}

impl<S> NonRigidCache<S> {
    /// Number of Gaussians of the forward pass.
    pub fn rows(&self) -> usize {
        self.rows
    }
}

#[derive(Clone, Debug, Default)]
struct SeqXyzCache<S> {
    /// Per window element, `n x (tau |S| 3)`.
    inputs: Vec<Vec<S>>,
    /// Per window element, `n x 64`.
    velocity: Vec<Vec<S>>,
    /// `n x 32`.
    position: Vec<S>,
    /// Per window element, `n x 96`.
    frames: Vec<Vec<S>>,
    /// `n x 256`.
    hidden: Vec<S>,
    /// `n x 96`.
    out: Vec<S>,
}

#[derive(Clone, Debug, PartialEq)]
struct SeqXyzNet<S> {
    velocity: Dense<S>,
    position: Dense<S>,
    frame: Dense<S>,
    hidden: Dense<S>,
    out: Dense<S>,
}

/// The non-rigid network's layers.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct NonRigidNet<S> {
    pose_encoder: [Dense<S>; 2],
    seq_pose: Option<[Dense<S>; 2]>,
    seq_xyz: Option<SeqXyzNet<S>>,
    /// `trunk[0]` reads `gaussian_in` per-Gaussian rows, then the per-frame rows.
    trunk: Vec<Dense<S>>,
    heads: Dense<S>,
    gaussian_in: usize,
}

const GROUP: NetworkGroup = NetworkGroup::NonRigid;

impl<S: NnScalar> NonRigidNet<S> {
    pub(crate) fn new(config: &NetworkConfig, rng: &mut Rng) -> Self {
        let w = &config.widths;
        let relu = Activation::Relu;
        let mut dense = |name: &str, input: usize, output: usize, activation: Activation| {
            Dense::new(
                format!("non_rigid.{name}"),
                GROUP,
                input,
                output,
                activation,
                Init::PytorchDefault,
                rng,
            )
        };
        let encoding = w.encoding_width();
        let pose_encoder = [
            dense("pose_encoder.0", config.pose_dim(), w.pose_encoder, relu),
            dense("pose_encoder.1", w.pose_encoder, w.pose_encoder, relu),
        ];
        let seq_pose = config.motion_context.has_skeleton_motion().then(|| {
            [
                dense(
                    "seq_pose_encoder.frame",
                    config.seq_pose_row(),
                    w.seq_pose_frame,
                    relu,
                ),
                dense(
                    "seq_pose_encoder.sequence",
                    w.seq_pose_frame * config.sequence_length,
                    w.seq_pose,
                    relu,
                ),
            ]
        });
        let seq_xyz = config.motion_context.has_velocity().then(|| SeqXyzNet {
            velocity: dense(
                "seq_xyz_encoder.velocity",
                config.seq_xyz_row(),
                w.seq_xyz_velocity,
                relu,
            ),
            position: dense(
                "seq_xyz_encoder.position",
                encoding,
                w.seq_xyz_position,
                relu,
            ),
            frame: dense(
                "seq_xyz_encoder.frame",
                w.seq_xyz_velocity + w.seq_xyz_position,
                w.seq_xyz_frame,
                relu,
            ),
            hidden: dense(
                "seq_xyz_encoder.sequence.0",
                w.seq_xyz_frame * config.sequence_length,
                w.seq_xyz_hidden,
                relu,
            ),
            out: dense(
                "seq_xyz_encoder.sequence.1",
                w.seq_xyz_hidden,
                w.seq_xyz,
                relu,
            ),
        });
        let gaussian_in = encoding + if seq_xyz.is_some() { w.seq_xyz } else { 0 };
        let frame_in = w.pose_encoder + if seq_pose.is_some() { w.seq_pose } else { 0 };
        let mut trunk = vec![dense(
            "trunk.0",
            gaussian_in + frame_in,
            config.trunk_width,
            relu,
        )];
        for index in 1..config.trunk_depth {
            trunk.push(dense(
                &format!("trunk.{index}"),
                config.trunk_width,
                config.trunk_width,
                relu,
            ));
        }
        let heads = dense(
            "heads",
            config.trunk_width,
            HEAD_WIDTH,
            Activation::Identity,
        );
        NonRigidNet {
            pose_encoder,
            seq_pose,
            seq_xyz,
            trunk,
            heads,
            gaussian_in,
        }
    }

    pub(crate) fn layers(&self) -> Vec<&Dense<S>> {
        let mut layers: Vec<&Dense<S>> = self.pose_encoder.iter().collect();
        if let Some(seq_pose) = &self.seq_pose {
            layers.extend(seq_pose.iter());
        }
        if let Some(net) = &self.seq_xyz {
            layers.extend([
                &net.velocity,
                &net.position,
                &net.frame,
                &net.hidden,
                &net.out,
            ]);
        }
        layers.extend(self.trunk.iter());
        layers.push(&self.heads);
        layers
    }

    pub(crate) fn layers_mut(&mut self) -> Vec<&mut Dense<S>> {
        let mut layers: Vec<&mut Dense<S>> = self.pose_encoder.iter_mut().collect();
        if let Some(seq_pose) = &mut self.seq_pose {
            layers.extend(seq_pose.iter_mut());
        }
        if let Some(net) = &mut self.seq_xyz {
            layers.extend([
                &mut net.velocity,
                &mut net.position,
                &mut net.frame,
                &mut net.hidden,
                &mut net.out,
            ]);
        }
        layers.extend(self.trunk.iter_mut());
        layers.push(&mut self.heads);
        layers
    }

    /// The per-Gaussian and per-frame shapes of the first trunk layer.
    fn first_shapes(&self) -> (LinearShape, LinearShape) {
        let first = &self.trunk[0].shape;
        (
            LinearShape {
                in_features: self.gaussian_in,
                out_features: first.out_features,
                activation: Activation::Relu,
            },
            LinearShape {
                in_features: first.in_features - self.gaussian_in,
                out_features: first.out_features,
                activation: Activation::Identity,
            },
        )
    }

    pub(crate) fn forward(
        &self,
        config: &NetworkConfig,
        frame: &FrameInputs<'_, S>,
        gaussians: &GaussianInputs<'_, S>,
    ) -> Result<(NonRigidOutput<S>, NonRigidCache<S>), ModelError> {
        let w = &config.widths;
        let n = check_inputs(
            config,
            self.seq_pose.is_some(),
            self.seq_xyz.is_some(),
            frame,
            gaussians,
        )?;
        let mut cache = NonRigidCache {
            rows: n,
            local_pose: frame.local_pose.to_vec(),
            ..NonRigidCache::default()
        };

        let encoding = w.encoding();
        let encoding_width = w.encoding_width();
        cache.encoding = vec![S::ZERO; n * encoding_width];
        positional_encoding_forward(encoding, gaussians.xyz, n, 3, &mut cache.encoding)?;

        let [pose0, pose1] = &self.pose_encoder;
        pose0.forward(
            &[part(frame.local_pose, config.pose_dim())],
            1,
            &mut cache.pose_hidden,
        )?;
        pose1.forward(
            &[part(&cache.pose_hidden, w.pose_encoder)],
            1,
            &mut cache.pose_out,
        )?;

        if let (Some([frame_layer, sequence_layer]), Some(motion)) =
            (&self.seq_pose, frame.skeleton_motion)
        {
            cache.skeleton_motion = motion.to_vec();
            frame_layer.forward(
                &[part(motion, config.seq_pose_row())],
                config.sequence_length,
                &mut cache.seq_pose_frames,
            )?;
            sequence_layer.forward(
                &[part(
                    &cache.seq_pose_frames,
                    w.seq_pose_frame * config.sequence_length,
                )],
                1,
                &mut cache.seq_pose_out,
            )?;
        }

        if let (Some(net), Some(velocity)) = (&self.seq_xyz, gaussians.knn_velocity) {
            let row = config.seq_xyz_row();
            let length = config.sequence_length;
            let mut xyz = SeqXyzCache {
                inputs: (0..length).map(|_| Vec::with_capacity(n * row)).collect(),
                ..SeqXyzCache::default()
            };
            for gaussian in velocity.chunks_exact(length * row) {
                for (element, input) in gaussian.chunks_exact(row).zip(&mut xyz.inputs) {
                    input.extend_from_slice(element);
                }
            }
            net.position.forward(
                &[part(&cache.encoding, encoding_width)],
                n,
                &mut xyz.position,
            )?;
            xyz.velocity = vec![Vec::new(); length];
            xyz.frames = vec![Vec::new(); length];
            for l in 0..length {
                net.velocity
                    .forward(&[part(&xyz.inputs[l], row)], n, &mut xyz.velocity[l])?;
                net.frame.forward(
                    &[
                        part(&xyz.velocity[l], w.seq_xyz_velocity),
                        part(&xyz.position, w.seq_xyz_position),
                    ],
                    n,
                    &mut xyz.frames[l],
                )?;
            }
            let frame_parts: Vec<InputPart<'_, S>> = xyz
                .frames
                .iter()
                .map(|frame| part(frame, w.seq_xyz_frame))
                .collect();
            net.hidden.forward(&frame_parts, n, &mut xyz.hidden)?;
            net.out
                .forward(&[part(&xyz.hidden, w.seq_xyz_hidden)], n, &mut xyz.out)?;
            cache.seq_xyz = Some(xyz);
        }

        // First trunk layer: the per-frame inputs become a bias of the per-Gaussian product.
        let first = &self.trunk[0];
        let width = first.out_features();
        let (gaussian_shape, frame_shape) = self.first_shapes();
        let (gaussian_weight, frame_weight) = first.weight.split_at(self.gaussian_in * width);
        let frame_parts = self.frame_parts(w, &cache);
        let mut frame_bias = vec![S::ZERO; width];
        linear_forward(
            frame_shape,
            frame_weight,
            &first.bias,
            &frame_parts,
            1,
            &mut frame_bias,
        )?;
        cache.frame_bias = frame_bias;
        let gaussian_parts = self.gaussian_parts(w, &cache);
        let mut first_out = vec![S::ZERO; n * width];
        linear_forward(
            gaussian_shape,
            gaussian_weight,
            &cache.frame_bias,
            &gaussian_parts,
            n,
            &mut first_out,
        )?;
        cache.trunk.push(first_out);
        for layer in &self.trunk[1..] {
            let mut out = Vec::new();
            layer.forward(
                &[part(
                    cache.trunk.last().map_or(&[][..], Vec::as_slice),
                    width,
                )],
                n,
                &mut out,
            )?;
            cache.trunk.push(out);
        }
        self.heads.forward(
            &[part(
                cache.trunk.last().map_or(&[][..], Vec::as_slice),
                width,
            )],
            n,
            &mut cache.heads,
        )?;
        let output = split_heads(&cache.heads);
        Ok((output, cache))
    }

    /// The per-frame column blocks of the first trunk layer: pose, then seq-pose.
    fn frame_parts<'c>(
        &self,
        w: &super::Widths,
        cache: &'c NonRigidCache<S>,
    ) -> Vec<InputPart<'c, S>> {
        let mut parts = vec![part(&cache.pose_out[..], w.pose_encoder)];
        if self.seq_pose.is_some() {
            parts.push(part(&cache.seq_pose_out[..], w.seq_pose));
        }
        parts
    }

    /// The per-Gaussian column blocks of the first trunk layer: encoding, then seq-xyz.
    fn gaussian_parts<'c>(
        &self,
        w: &super::Widths,
        cache: &'c NonRigidCache<S>,
    ) -> Vec<InputPart<'c, S>> {
        let mut parts = vec![part(&cache.encoding[..], w.encoding_width())];
        if let Some(xyz) = &cache.seq_xyz {
            parts.push(part(&xyz.out[..], w.seq_xyz));
        }
        parts
    }

    pub(crate) fn backward(
        &mut self,
        config: &NetworkConfig,
        cache: &NonRigidCache<S>,
        d_dxyz: &[S],
        d_drot: &[S],
        d_dscale: &[S],
    ) -> Result<Vec<S>, ModelError> {
        let w = config.widths;
        let n = cache.rows;
        check_input("d_dxyz", 3 * n, d_dxyz.len())?;
        check_input("d_drot", 4 * n, d_drot.len())?;
        check_input("d_dscale", 3 * n, d_dscale.len())?;
        if cache.trunk.len() != self.trunk.len()
            || cache.seq_xyz.is_some() != self.seq_xyz.is_some()
        {
            return Err(ModelError::Input {
                field: "non-rigid cache".into(),
                message: "does not come from this network's forward pass".into(),
            });
        }
        let width = self.trunk[0].out_features();
        let mut d_heads = Vec::with_capacity(n * HEAD_WIDTH);
        for g in 0..n {
            d_heads.extend_from_slice(&d_dxyz[3 * g..3 * g + 3]);
            d_heads.extend_from_slice(&d_drot[4 * g..4 * g + 4]);
            d_heads.extend_from_slice(&d_dscale[3 * g..3 * g + 3]);
        }
        let mut d_current = vec![S::ZERO; n * width];
        let mut d_previous = vec![S::ZERO; n * width];
        self.heads.backward(
            &[part(&cache.trunk[self.trunk.len() - 1], width)],
            n,
            &cache.heads,
            &mut d_heads,
            &mut [InputGrad::Write(&mut d_current)],
        )?;
        for index in (1..self.trunk.len()).rev() {
            self.trunk[index].backward(
                &[part(&cache.trunk[index - 1], width)],
                n,
                &cache.trunk[index],
                &mut d_current,
                &mut [InputGrad::Write(&mut d_previous)],
            )?;
            std::mem::swap(&mut d_current, &mut d_previous);
        }
        drop(d_previous);

        // First trunk layer: the gradient of the per-frame bias is the column sum.
        let (gaussian_shape, frame_shape) = self.first_shapes();
        let encoding_width = w.encoding_width();
        let mut d_encoding = vec![S::ZERO; n * encoding_width];
        let mut d_seq_xyz = vec![
            S::ZERO;
            if self.seq_xyz.is_some() {
                n * w.seq_xyz
            } else {
                0
            }
        ];
        let mut d_frame_bias = vec![S::ZERO; width];
        let mut d_pose_out = vec![S::ZERO; w.pose_encoder];
        let mut d_seq_pose_out = vec![
            S::ZERO;
            if self.seq_pose.is_some() {
                w.seq_pose
            } else {
                0
            }
        ];
        {
            let gaussian_parts = self.gaussian_parts(&w, cache);
            let frame_parts = self.frame_parts(&w, cache);
            let split = self.gaussian_in * width;
            let Dense {
                weight,
                d_weight,
                d_bias,
                ..
            } = &mut self.trunk[0];
            let (gaussian_weight, frame_weight) = weight.split_at(split);
            let (d_gaussian_weight, d_frame_weight) = d_weight.split_at_mut(split);
            let mut d_parts = vec![InputGrad::Write(&mut d_encoding[..])];
            if cache.seq_xyz.is_some() {
                d_parts.push(InputGrad::Write(&mut d_seq_xyz[..]));
            }
            linear_backward(
                gaussian_shape,
                gaussian_weight,
                &gaussian_parts,
                n,
                &cache.trunk[0],
                &mut d_current,
                LinearGrads {
                    weight: d_gaussian_weight,
                    bias: &mut d_frame_bias,
                },
                &mut d_parts,
            )?;
            let mut d_parts = vec![InputGrad::Write(&mut d_pose_out[..])];
            if self.seq_pose.is_some() {
                d_parts.push(InputGrad::Write(&mut d_seq_pose_out[..]));
            }
            linear_backward(
                frame_shape,
                frame_weight,
                &frame_parts,
                1,
                &cache.frame_bias,
                &mut d_frame_bias,
                LinearGrads {
                    weight: d_frame_weight,
                    bias: d_bias,
                },
                &mut d_parts,
            )?;
        }
        drop(d_current);

        // Pose encoder (its input, the body pose, is data).
        let mut d_pose_hidden = vec![S::ZERO; w.pose_encoder];
        let [pose0, pose1] = &mut self.pose_encoder;
        pose1.backward(
            &[part(&cache.pose_hidden, w.pose_encoder)],
            1,
            &cache.pose_out,
            &mut d_pose_out,
            &mut [InputGrad::Write(&mut d_pose_hidden)],
        )?;
        pose0.backward(
            &[part(&cache.local_pose, config.pose_dim())],
            1,
            &cache.pose_hidden,
            &mut d_pose_hidden,
            &mut [InputGrad::Skip],
        )?;

        if let Some([frame_layer, sequence_layer]) = &mut self.seq_pose {
            let frames_width = w.seq_pose_frame * config.sequence_length;
            let mut d_frames = vec![S::ZERO; frames_width];
            sequence_layer.backward(
                &[part(&cache.seq_pose_frames, frames_width)],
                1,
                &cache.seq_pose_out,
                &mut d_seq_pose_out,
                &mut [InputGrad::Write(&mut d_frames)],
            )?;
            frame_layer.backward(
                &[part(&cache.skeleton_motion, config.seq_pose_row())],
                config.sequence_length,
                &cache.seq_pose_frames,
                &mut d_frames,
                &mut [InputGrad::Skip],
            )?;
        }

        if let (Some(net), Some(xyz)) = (&mut self.seq_xyz, &cache.seq_xyz) {
            let length = config.sequence_length;
            let mut d_hidden = vec![S::ZERO; n * w.seq_xyz_hidden];
            net.out.backward(
                &[part(&xyz.hidden, w.seq_xyz_hidden)],
                n,
                &xyz.out,
                &mut d_seq_xyz,
                &mut [InputGrad::Write(&mut d_hidden)],
            )?;
            let mut d_frames: Vec<Vec<S>> = vec![vec![S::ZERO; n * w.seq_xyz_frame]; length];
            {
                let frame_parts: Vec<InputPart<'_, S>> = xyz
                    .frames
                    .iter()
                    .map(|frame| part(frame, w.seq_xyz_frame))
                    .collect();
                let mut d_parts: Vec<InputGrad<'_, S>> = d_frames
                    .iter_mut()
                    .map(|d| InputGrad::Write(&mut d[..]))
                    .collect();
                net.hidden
                    .backward(&frame_parts, n, &xyz.hidden, &mut d_hidden, &mut d_parts)?;
            }
            let mut d_position = vec![S::ZERO; n * w.seq_xyz_position];
            let mut d_velocity = vec![S::ZERO; n * w.seq_xyz_velocity];
            let row = config.seq_xyz_row();
            for l in 0..length {
                net.frame.backward(
                    &[
                        part(&xyz.velocity[l], w.seq_xyz_velocity),
                        part(&xyz.position, w.seq_xyz_position),
                    ],
                    n,
                    &xyz.frames[l],
                    &mut d_frames[l],
                    &mut [
                        InputGrad::Write(&mut d_velocity),
                        InputGrad::Accumulate(&mut d_position),
                    ],
                )?;
                net.velocity.backward(
                    &[part(&xyz.inputs[l], row)],
                    n,
                    &xyz.velocity[l],
                    &mut d_velocity,
                    &mut [InputGrad::Skip],
                )?;
            }
            net.position.backward(
                &[part(&cache.encoding, encoding_width)],
                n,
                &xyz.position,
                &mut d_position,
                &mut [InputGrad::Accumulate(&mut d_encoding)],
            )?;
        }

        let mut d_xyz = vec![S::ZERO; 3 * n];
        positional_encoding_backward(w.encoding(), &cache.encoding, &d_encoding, n, 3, &mut d_xyz)?;
        Ok(d_xyz)
    }
}

/// Checks the inputs against the configuration and returns the number of Gaussians.
pub(crate) fn check_inputs<S: NnScalar>(
    config: &NetworkConfig,
    has_seq_pose: bool,
    has_seq_xyz: bool,
    frame: &FrameInputs<'_, S>,
    gaussians: &GaussianInputs<'_, S>,
) -> Result<usize, ModelError> {
    if !gaussians.xyz.len().is_multiple_of(3) {
        return Err(ModelError::Input {
            field: "gaussians.xyz".into(),
            message: format!(
                "{} values is not a whole number of 3-vectors",
                gaussians.xyz.len()
            ),
        });
    }
    let n = gaussians.xyz.len() / 3;
    check_input(
        "frame.local_pose",
        config.pose_dim(),
        frame.local_pose.len(),
    )?;
    match (has_seq_pose, frame.skeleton_motion) {
        (true, Some(motion)) => check_input(
            "frame.skeleton_motion",
            config.skeleton_motion_len(),
            motion.len(),
        )?,
        (false, None) => {}
        (true, None) => return Err(missing("frame.skeleton_motion", config)),
        (false, Some(_)) => return Err(unused("frame.skeleton_motion", config)),
    }
    match (has_seq_xyz, gaussians.knn_velocity) {
        (true, Some(velocity)) => check_input(
            "gaussians.knn_velocity",
            n * config.sequence_length * config.seq_xyz_row(),
            velocity.len(),
        )?,
        (false, None) => {}
        (true, None) => return Err(missing("gaussians.knn_velocity", config)),
        (false, Some(_)) => return Err(unused("gaussians.knn_velocity", config)),
    }
    check_finite("frame.local_pose", frame.local_pose)?;
    check_finite("gaussians.xyz", gaussians.xyz)?;
    if let Some(motion) = frame.skeleton_motion {
        check_finite("frame.skeleton_motion", motion)?;
    }
    if let Some(velocity) = gaussians.knn_velocity {
        check_finite("gaussians.knn_velocity", velocity)?;
    }
    Ok(n)
}

/// Splits the `n x 10` head output into `d_xyz`, `d_rot` (+1 on `w`) and `d_scale`.
pub(crate) fn split_heads<S: NnScalar>(heads: &[S]) -> NonRigidOutput<S> {
    let n = heads.len() / HEAD_WIDTH;
    let mut output = NonRigidOutput {
        d_xyz: Vec::with_capacity(3 * n),
        d_rot: Vec::with_capacity(4 * n),
        d_scale: Vec::with_capacity(3 * n),
    };
    for row in heads.chunks_exact(HEAD_WIDTH) {
        output.d_xyz.extend_from_slice(&row[0..3]);
        output.d_rot.push(row[3] + S::ONE);
        output.d_rot.extend_from_slice(&row[4..7]);
        output.d_scale.extend_from_slice(&row[7..10]);
    }
    output
}

fn missing(field: &str, config: &NetworkConfig) -> ModelError {
    ModelError::Input {
        field: field.into(),
        message: format!(
            "required by motion context {:?} but not given",
            config.motion_context
        ),
    }
}

fn unused(field: &str, config: &NetworkConfig) -> ModelError {
    ModelError::Input {
        field: field.into(),
        message: format!(
            "given but motion context {:?} does not use it",
            config.motion_context
        ),
    }
}
