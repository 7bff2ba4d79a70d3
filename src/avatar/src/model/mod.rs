//! The SeqAvatar networks on `cpu` (generic over f32/f64) and `gpu` (f32): non-rigid
//! deformation conditioned on pose and motion context, body-pose refiner, LBS-weight offsets.
//!
//! # Architecture (`docs/method.md`, "Networks")
//!
//! - Canonical positions are NeRF-encoded (10 bands, input included: 63 values).
//! - `PoseEncoder`: local pose without root (`3 (J - 1)`) -> 32 -> 32, ReLU. One row per frame.
//! - `SeqPoseEncoder`: skeleton motion `(L, |S|, motion_joints, 3)`: each of the `L` rows
//!   `Linear(3 motion_joints |S|, 16)` + ReLU, the `L` rows flattened, `Linear(16 L, 32)` +
//!   ReLU. One row per frame.
//! - `SeqXYZEncoder`: per Gaussian and window element `l`, the velocities of its `tau` nearest
//!   template vertices over all scales (`[neighbour][scale, largest first][xyz]`),
//!   `Linear(3 tau |S|, 64)` + ReLU, concatenated with `Linear(63, 32)` + ReLU of the
//!   encoding, `Linear(96, 96)` + ReLU; the `L` results flattened, `Linear(96 L, 256)` + ReLU,
//!   `Linear(256, 96)` + ReLU.
//! - Trunk: `concat(encoding 63, seq-xyz 96, pose 32, seq-pose 32)` -> `depth` x
//!   (`Linear(width)` + ReLU) -> heads `d_xyz` (3), `d_rot` (4, plus 1 on `w` so a fresh
//!   network starts near the identity quaternion), `d_scale` (3), stored as one layer of 10.
//!   The per-frame inputs (pose, seq-pose) are never copied to every Gaussian: their product
//!   with their rows of the first weight, plus the bias, is one per-frame bias of the
//!   per-Gaussian product (identical maths), and its gradient is the column sum.
//!   **Row order of `non_rigid.trunk.0.weight`**: per-Gaussian inputs first (encoding, then
//!   seq-xyz), then per-frame inputs (pose, then seq-pose). This is a permutation of the
//!   reference concatenation order `(63, 32, 32, 96)`; the function class and the
//!   initialisation distribution are the same.
//! - `BodyPoseRefiner`: `3 (J - 1)` -> 128 -> 128 -> `3 (J - 1)` (last layer `U(+-1e-5)`, bias
//!   0), each 3-vector to a matrix by the reference's regularised Rodrigues
//!   ([`pose_refiner::regularised_rodrigues`]), to be right-multiplied onto the joint's
//!   rotation by the caller.
//! - `LbsOffsetNet`: encoding (detached) 63 -> 128 -> 128 -> 128, skip `concat(128, 63)` -> 128
//!   -> `J`; [`lbs::blend_weights`] turns offsets into skinning weights
//!   `softmax(log(w_template + 1e-9) + offset)`.
//!
//! Each network is written once, as a description ([`spec::NetworkSpec::non_rigid`],
//! [`spec::NetworkSpec::pose_refiner`], [`spec::NetworkSpec::lbs_offsets`]: input blocks,
//! layers with what they read, widths, activations, initialisation), and run by one forward
//! and one backward per backend: [`network::Network`] on `cpu` (generic over f32/f64) and
//! [`gpu::GpuNetworks`]' resident programs on the `nn` kernels. Adding an input block or a layer is a change to
//! the description (and, for an input, to the caller that supplies it).
//!
//! [`NetworkConfig::motion_context`] decides which blocks exist: `none` has no non-rigid
//! network at all (no encoding, no buffers), `pose` the encoding, `PoseEncoder` and trunk,
//! `skeleton` adds `SeqPoseEncoder`, `velocity` adds `SeqXYZEncoder`, `multiscale` uses all
//! scales (the other levels use one scale slot, chosen by the caller). The pose refiner and
//! the LBS offsets are independent switches.

pub mod dense;
pub mod gpu;
pub mod lbs;
pub mod network;
pub mod non_rigid;
pub mod pose_refiner;
pub mod spec;
#[cfg(test)]
mod tests;

use seqavatar_compute::nn::{NnError, NnScalar, PositionalEncoding, Rng};

use crate::config::{AvatarConfig, MotionContext};
use dense::Dense;
use network::Network;
use spec::NetworkSpec;

pub use lbs::LbsOffsetsCache;
pub use non_rigid::{FrameInputs, GaussianInputs, NonRigidCache, NonRigidOutput};
pub use pose_refiner::PoseRefinerCache;

/// Width of the heads layer: `d_xyz` (3), `d_rot` (4), `d_scale` (3).
pub const HEAD_WIDTH: usize = 10;

/// Errors of the networks: each names the input, field or parameter it is about.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModelError {
    /// An input array does not have the length the configuration implies.
    #[error("{field}: expected {expected} values, got {actual}")]
    InputLength {
        field: String,
        expected: usize,
        actual: usize,
    },
    /// An input the configuration needs is missing, or one it does not use is given.
    #[error("{field}: {message}")]
    Input { field: String, message: String },
    /// The network configuration is invalid.
    #[error("network config {field}: {message}")]
    Config { field: String, message: String },
    /// A parameter array being loaded is missing or has the wrong size.
    #[error("parameter {name}: {message}")]
    Parameter { name: String, message: String },
    /// A backward pass was asked of a block that is disabled by the configuration.
    #[error("{block} is disabled by the network configuration")]
    Disabled { block: &'static str },
    /// A dense-layer operation failed (an internal shape error).
    #[error(transparent)]
    Nn(#[from] NnError),
    /// The gpu could not run the networks.
    #[error("gpu: {0}")]
    Gpu(String),
}

/// The optimiser group of a parameter; each has its own learning rate (docs/method.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NetworkGroup {
    /// Encoders and trunk of the non-rigid deformation (lr 1e-3).
    NonRigid,
    /// The body-pose refiner (lr 5e-5).
    PoseRefiner,
    /// The LBS-weight offsets (lr 5e-5).
    LbsOffsets,
}

impl NetworkGroup {
    /// The group's place in parameter order (non-rigid, pose refiner, LBS offsets).
    pub(crate) fn index(self) -> usize {
        self as usize
    }

    /// The block's name in errors.
    pub(crate) fn block(self) -> &'static str {
        match self {
            NetworkGroup::NonRigid => "the non-rigid network",
            NetworkGroup::PoseRefiner => "the pose refiner",
            NetworkGroup::LbsOffsets => "the LBS offsets",
        }
    }
}

/// Hidden and output widths of the blocks; [`Widths::PAPER`] is the reference architecture.
/// A train config's `network_widths` replaces any of them ([`AvatarConfig::network_widths`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Widths {
    /// NeRF bands of the position encoding (63 values with 10).
    pub encoding_frequencies: usize,
    /// `PoseEncoder` hidden and output width (32).
    pub pose_encoder: usize,
    /// `SeqPoseEncoder` per-frame width (16).
    pub seq_pose_frame: usize,
    /// `SeqPoseEncoder` output width (32).
    pub seq_pose: usize,
    /// `SeqXYZEncoder` velocity branch width (64).
    pub seq_xyz_velocity: usize,
    /// `SeqXYZEncoder` position branch width (32).
    pub seq_xyz_position: usize,
    /// `SeqXYZEncoder` per-frame fused width (96).
    pub seq_xyz_frame: usize,
    /// `SeqXYZEncoder` hidden width after flattening the frames (256).
    pub seq_xyz_hidden: usize,
    /// `SeqXYZEncoder` output width (96).
    pub seq_xyz: usize,
    /// `BodyPoseRefiner` hidden width (128).
    pub pose_refiner_hidden: usize,
    /// `LbsOffsetNet` hidden width (128).
    pub lbs_hidden: usize,
}

impl Widths {
    /// The widths of the published code.
    pub const PAPER: Widths = Widths {
        encoding_frequencies: 10,
        pose_encoder: 32,
        seq_pose_frame: 16,
        seq_pose: 32,
        seq_xyz_velocity: 64,
        seq_xyz_position: 32,
        seq_xyz_frame: 96,
        seq_xyz_hidden: 256,
        seq_xyz: 96,
        pose_refiner_hidden: 128,
        lbs_hidden: 128,
    };

    /// Each block width in `1..=MAX_TRUNK_WIDTH` and at most 30 encoding bands; the error
    /// names the field.
    pub fn validate(&self) -> Result<(), (String, String)> {
        if self.encoding_frequencies > 30 {
            let bands = self.encoding_frequencies;
            return Err((
                "encoding_frequencies".into(),
                format!("{bands} bands exceed 30"),
            ));
        }
        let max = crate::config::MAX_TRUNK_WIDTH;
        for (name, width) in [
            ("pose_encoder", self.pose_encoder),
            ("seq_pose_frame", self.seq_pose_frame),
            ("seq_pose", self.seq_pose),
            ("seq_xyz_velocity", self.seq_xyz_velocity),
            ("seq_xyz_position", self.seq_xyz_position),
            ("seq_xyz_frame", self.seq_xyz_frame),
            ("seq_xyz_hidden", self.seq_xyz_hidden),
            ("seq_xyz", self.seq_xyz),
            ("pose_refiner_hidden", self.pose_refiner_hidden),
            ("lbs_hidden", self.lbs_hidden),
        ] {
            if !(1..=max).contains(&width) {
                return Err((name.into(), format!("must be in 1..={max}, got {width}")));
            }
        }
        Ok(())
    }

    /// The encoding of 3D positions with these widths.
    pub fn encoding(&self) -> PositionalEncoding {
        PositionalEncoding {
            frequencies: self.encoding_frequencies,
            include_input: true,
        }
    }

    /// Width of the position encoding (63 for the paper).
    pub fn encoding_width(&self) -> usize {
        self.encoding().out_features(3)
    }
}

impl Default for Widths {
    fn default() -> Self {
        Widths::PAPER
    }
}

/// Everything that fixes the networks' shapes.
#[derive(Clone, Debug, PartialEq)]
pub struct NetworkConfig {
    /// Which conditioning blocks exist.
    pub motion_context: MotionContext,
    /// Trunk width (512 in the paper).
    pub trunk_width: usize,
    /// Number of `Linear(width) + ReLU` layers of the trunk (3 in the paper).
    pub trunk_depth: usize,
    /// Skinning joints `J`, root included (24 for SMPL, 55 for SMPL-X). The pose refiner and
    /// the pose encoder read `3 (J - 1)` values, the LBS offsets have `J` outputs.
    pub skinning_joints: usize,
    /// Joints per skeleton-motion frame (the motion entry's `joint` axis).
    pub motion_joints: usize,
    /// Nearest template vertices per Gaussian in the velocity context.
    pub tau: usize,
    /// Window length `L`.
    pub sequence_length: usize,
    /// Scale slots the encoders read: all of them for `multiscale`, else 1.
    pub n_scales: usize,
    /// Whether the body-pose refiner exists.
    pub pose_refiner: bool,
    /// Whether the LBS-offset network exists.
    pub lbs_offsets: bool,
    /// Block widths.
    pub widths: Widths,
}

impl NetworkConfig {
    /// The configuration of an avatar: trunk size, `tau`, `L`, switches from `config`,
    /// body sizes from the body model and the motion entry, `available_scales` the motion
    /// entry's scale count (only `multiscale` uses more than one).
    pub fn from_avatar(
        config: &AvatarConfig,
        skinning_joints: usize,
        motion_joints: usize,
        available_scales: usize,
    ) -> Result<Self, ModelError> {
        let n_scales = if config.motion_context.is_multiscale() {
            available_scales
        } else {
            1
        };
        let network = NetworkConfig {
            motion_context: config.motion_context,
            trunk_width: config.trunk_width,
            trunk_depth: config.trunk_depth,
            skinning_joints,
            motion_joints,
            tau: config.tau,
            sequence_length: config.sequence_length,
            n_scales,
            pose_refiner: config.pose_refiner,
            lbs_offsets: config.lbs_offsets,
            widths: config.network_widths.unwrap_or(Widths::PAPER),
        };
        network.validate()?;
        Ok(network)
    }

    /// Local pose values without the root: `3 (J - 1)`.
    pub fn pose_dim(&self) -> usize {
        3 * self.skinning_joints.saturating_sub(1)
    }

    /// Skeleton-motion values per frame: `L |S| motion_joints 3`.
    pub fn skeleton_motion_len(&self) -> usize {
        self.sequence_length * self.seq_pose_row()
    }

    /// One window element of skeleton motion: `|S| motion_joints 3`.
    pub fn seq_pose_row(&self) -> usize {
        self.n_scales * self.motion_joints * 3
    }

    /// One window element of one Gaussian's velocities: `tau |S| 3`.
    pub fn seq_xyz_row(&self) -> usize {
        self.tau * self.n_scales * 3
    }

    /// Checks every size the enabled blocks use.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |field: &str, message: String| {
            Err(ModelError::Config {
                field: field.into(),
                message,
            })
        };
        // Every width, enabled block or not: one place owns the bounds (the train config's
        // `network_widths` is checked by the same function).
        if let Err((field, message)) = self.widths.validate() {
            return bad(&format!("widths.{field}"), message);
        }
        let needs_pose = self.motion_context.has_non_rigid() || self.pose_refiner;
        if needs_pose && self.skinning_joints < 2 {
            return bad(
                "skinning_joints",
                format!(
                    "the pose encoder and refiner need a non-root joint, got J = {}",
                    self.skinning_joints
                ),
            );
        }
        if self.lbs_offsets && self.skinning_joints == 0 {
            return bad("skinning_joints", "the LBS offsets need J >= 1".into());
        }
        if self.motion_context.has_non_rigid() && (self.trunk_width == 0 || self.trunk_depth == 0) {
            return bad(
                "trunk_width",
                format!(
                    "the trunk needs width and depth >= 1, got {} and {}",
                    self.trunk_width, self.trunk_depth
                ),
            );
        }
        if self.motion_context.has_skeleton_motion()
            && (self.sequence_length == 0 || self.n_scales == 0 || self.motion_joints == 0)
        {
            return bad(
                "sequence_length",
                format!(
                    "skeleton motion needs L, scales and motion joints >= 1, got {}, {}, {}",
                    self.sequence_length, self.n_scales, self.motion_joints
                ),
            );
        }
        if self.motion_context.has_velocity() && self.tau == 0 {
            return bad("tau", "velocity context needs tau >= 1".into());
        }
        if self.motion_context.has_non_rigid()
            && !self.motion_context.is_multiscale()
            && self.n_scales > 1
        {
            return bad(
                "n_scales",
                format!(
                    "motion context {:?} reads one scale, got {}",
                    self.motion_context, self.n_scales
                ),
            );
        }
        Ok(())
    }
}

/// One parameter array, read-only.
#[derive(Debug)]
pub struct NamedParam<'a, S> {
    /// Stable name (a Zarr array name in checkpoints and the trained avatar).
    pub name: String,
    /// `[in, out]` for weights, `[out]` for biases.
    pub shape: Vec<usize>,
    /// The values, row-major.
    pub values: &'a [S],
    /// The accumulated gradient, same layout.
    pub grads: &'a [S],
    pub group: NetworkGroup,
}

/// A [`NamedParam`] with its values writable (an optimiser step).
#[derive(Debug)]
pub struct NamedParamMut<'a, S> {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: &'a mut [S],
    pub grads: &'a [S],
    pub group: NetworkGroup,
}

/// All networks of one avatar, on `cpu`.
#[derive(Clone, Debug, PartialEq)]
pub struct Networks<S> {
    config: NetworkConfig,
    /// By [`NetworkGroup::index`].
    nets: [Option<Network<S>>; 3],
}

/// A generator per block, so switching one block off leaves the others' initial values as
/// they were.
fn block_rng(seed: u64, block: u64) -> Rng {
    Rng::new(seed ^ block.wrapping_mul(0x9e37_79b9_7f4a_7c15))
}

impl NetworkConfig {
    /// The descriptions of the enabled networks, in parameter order (non-rigid, pose
    /// refiner, LBS offsets), each with its initialisation stream (1, 2, 3 of
    /// [`Networks::new`]'s seed).
    pub fn specs(&self) -> Vec<(u64, NetworkSpec)> {
        let mut specs = Vec::new();
        if self.motion_context.has_non_rigid() {
            specs.push((1, NetworkSpec::non_rigid(self)));
        }
        if self.pose_refiner {
            specs.push((2, NetworkSpec::pose_refiner(self)));
        }
        if self.lbs_offsets {
            specs.push((3, NetworkSpec::lbs_offsets(self)));
        }
        specs
    }

    /// Forward FLOPs of every enabled network for `n` Gaussians
    /// ([`NetworkSpec::forward_flops`]; a backward costs twice this).
    pub fn forward_flops(&self, n: usize) -> f64 {
        self.specs()
            .iter()
            .map(|(_, spec)| spec.forward_flops(n))
            .sum()
    }
}

impl<S: NnScalar> Networks<S> {
    /// The enabled blocks, initialised from `seed` (PyTorch-default initialisation, the pose
    /// refiner's last layer `U(-1e-5, 1e-5)` with zero bias).
    pub fn new(config: &NetworkConfig, seed: u64) -> Result<Self, ModelError> {
        config.validate()?;
        let mut nets = [None, None, None];
        for (stream, spec) in config.specs() {
            let group = spec.group.index();
            nets[group] = Some(Network::new(spec, &mut block_rng(seed, stream))?);
        }
        Ok(Networks {
            config: config.clone(),
            nets,
        })
    }

    /// The configuration the networks were built from.
    pub fn config(&self) -> &NetworkConfig {
        &self.config
    }

    /// Whether the non-rigid network exists (`motion_context` is not `none`).
    pub fn has_non_rigid(&self) -> bool {
        self.nets[NetworkGroup::NonRigid.index()].is_some()
    }

    /// Whether the body-pose refiner exists.
    pub fn has_pose_refiner(&self) -> bool {
        self.nets[NetworkGroup::PoseRefiner.index()].is_some()
    }

    /// Whether the LBS-offset network exists.
    pub fn has_lbs_offsets(&self) -> bool {
        self.nets[NetworkGroup::LbsOffsets.index()].is_some()
    }

    /// The network of `group`, or that it is disabled.
    fn net(&self, group: NetworkGroup) -> Result<&Network<S>, ModelError> {
        self.nets[group.index()]
            .as_ref()
            .ok_or(ModelError::Disabled {
                block: group.block(),
            })
    }

    fn net_mut(&mut self, group: NetworkGroup) -> Result<&mut Network<S>, ModelError> {
        self.nets[group.index()]
            .as_mut()
            .ok_or(ModelError::Disabled {
                block: group.block(),
            })
    }

    /// The enabled networks in parameter order (non-rigid, pose refiner, LBS offsets).
    pub fn networks(&self) -> impl Iterator<Item = &Network<S>> {
        self.nets.iter().flatten()
    }

    /// Every layer, in a fixed order (non-rigid, pose refiner, LBS offsets).
    pub(crate) fn layers(&self) -> Vec<&Dense<S>> {
        self.networks().flat_map(|net| net.layers.iter()).collect()
    }

    fn layers_mut(&mut self) -> Vec<&mut Dense<S>> {
        self.nets
            .iter_mut()
            .flatten()
            .flat_map(|net| net.layers.iter_mut())
            .collect()
    }

    /// Every parameter array with its gradient, weights before biases, layers in order.
    pub fn parameters(&self) -> Vec<NamedParam<'_, S>> {
        let mut params = Vec::new();
        for layer in self.layers() {
            let (shape, group) = (layer.shape, layer.group);
            for (what, dims, values, grads) in [
                (
                    "weight",
                    vec![shape.in_features, shape.out_features],
                    &layer.weight,
                    &layer.d_weight,
                ),
                ("bias", vec![shape.out_features], &layer.bias, &layer.d_bias),
            ] {
                params.push(NamedParam {
                    name: format!("{}.{what}", layer.name),
                    shape: dims,
                    values,
                    grads,
                    group,
                });
            }
        }
        params
    }

    /// Like [`Networks::parameters`], with writable values (for an optimiser step).
    pub fn parameters_mut(&mut self) -> Vec<NamedParamMut<'_, S>> {
        let mut params = Vec::new();
        for layer in self.layers_mut() {
            let Dense {
                name,
                group,
                shape,
                weight,
                bias,
                d_weight,
                d_bias,
            } = layer;
            for (what, dims, values, grads) in [
                (
                    "weight",
                    vec![shape.in_features, shape.out_features],
                    weight,
                    &*d_weight,
                ),
                ("bias", vec![shape.out_features], bias, &*d_bias),
            ] {
                params.push(NamedParamMut {
                    name: format!("{name}.{what}"),
                    shape: dims,
                    values: values.as_mut_slice(),
                    grads: grads.as_slice(),
                    group: *group,
                });
            }
        }
        params
    }

    /// Total number of trainable values.
    pub fn parameter_count(&self) -> usize {
        self.layers()
            .iter()
            .map(|layer| layer.weight.len() + layer.bias.len())
            .sum()
    }

    /// Sets every gradient to zero.
    pub fn zero_grad(&mut self) {
        for layer in self.layers_mut() {
            layer.zero_grad();
        }
    }

    /// Replaces every parameter by `source(name)` (e.g. a checkpoint's array of that name).
    /// Every array must be present with the exact length; nothing is changed on error.
    pub fn load_parameters(
        &mut self,
        mut source: impl FnMut(&str) -> Option<Vec<S>>,
    ) -> Result<(), ModelError> {
        let mut loaded = Vec::new();
        for param in self.parameters() {
            let bad = |message: String| ModelError::Parameter {
                name: param.name.clone(),
                message,
            };
            let values = source(&param.name).ok_or_else(|| bad("missing".into()))?;
            if values.len() != param.values.len() {
                return Err(bad(format!(
                    "expected {} values (shape {:?}), got {}",
                    param.values.len(),
                    param.shape,
                    values.len()
                )));
            }
            if let Some(index) = values.iter().position(|v| !v.is_finite()) {
                return Err(bad(format!("value {index} is not finite")));
            }
            loaded.push(values);
        }
        for (param, values) in self.parameters_mut().into_iter().zip(loaded) {
            param.values.copy_from_slice(&values);
        }
        Ok(())
    }

    /// The non-rigid deformation of `gaussians` at one frame (see [`non_rigid`]).
    pub fn non_rigid_forward(
        &self,
        frame: &FrameInputs<'_, S>,
        gaussians: &GaussianInputs<'_, S>,
    ) -> Result<(NonRigidOutput<S>, NonRigidCache<S>), ModelError> {
        let net = self.net(NetworkGroup::NonRigid)?;
        let inputs = non_rigid::inputs(&self.config, frame, gaussians)?;
        let activations = net.forward(&inputs)?;
        let output = non_rigid::split_heads(activations.output());
        Ok((output, NonRigidCache { activations }))
    }

    /// Backward of [`Networks::non_rigid_forward`]: accumulates parameter gradients and
    /// returns `dL/d(canonical xyz)` (`n x 3`), which flows through the encoding.
    pub fn non_rigid_backward(
        &mut self,
        cache: &NonRigidCache<S>,
        d_dxyz: &[S],
        d_drot: &[S],
        d_dscale: &[S],
    ) -> Result<Vec<S>, ModelError> {
        let net = self.net_mut(NetworkGroup::NonRigid)?;
        let d_heads = non_rigid::heads_gradient(cache.rows(), d_dxyz, d_drot, d_dscale)?;
        let gradients = net.backward(&cache.activations, &d_heads)?;
        Ok(gradients.into_iter().flatten().next().unwrap_or_default())
    }

    /// The pose corrections: `(J - 1)` row-major 3x3 matrices, one per non-root joint, for
    /// the local pose without root (`3 (J - 1)` values).
    pub fn pose_refiner_forward(
        &self,
        local_pose: &[S],
    ) -> Result<(Vec<S>, PoseRefinerCache<S>), ModelError> {
        let net = self.net(NetworkGroup::PoseRefiner)?;
        let activations = net.forward(&[local_pose])?;
        let rotations = pose_refiner::rotations_from_vectors(activations.output());
        Ok((rotations, PoseRefinerCache { activations }))
    }

    /// Backward of [`Networks::pose_refiner_forward`] from `dL/d(matrices)` (`(J - 1) x 9`).
    pub fn pose_refiner_backward(
        &mut self,
        cache: &PoseRefinerCache<S>,
        d_rotations: &[S],
    ) -> Result<(), ModelError> {
        let net = self.net_mut(NetworkGroup::PoseRefiner)?;
        let vectors = cache.rotation_vectors();
        check_input("d_rotations", 3 * vectors.len(), d_rotations.len())?;
        let d_vectors = pose_refiner::rotation_vectors_backward(vectors, d_rotations);
        net.backward(&cache.activations, &d_vectors)?;
        Ok(())
    }

    /// LBS-weight offsets (`n x J`) for positions `xyz` (`n x 3`; the encoding is detached).
    pub fn lbs_offsets_forward(
        &self,
        xyz: &[S],
    ) -> Result<(Vec<S>, LbsOffsetsCache<S>), ModelError> {
        let net = self.net(NetworkGroup::LbsOffsets)?;
        let activations = net.forward(&[xyz])?;
        Ok((
            activations.output().to_vec(),
            LbsOffsetsCache { activations },
        ))
    }

    /// Backward of [`Networks::lbs_offsets_forward`] from `dL/d(offsets)` (`n x J`).
    pub fn lbs_offsets_backward(
        &mut self,
        cache: &LbsOffsetsCache<S>,
        d_offsets: &[S],
    ) -> Result<(), ModelError> {
        let joints = self.config.skinning_joints;
        let net = self.net_mut(NetworkGroup::LbsOffsets)?;
        check_input("d_offsets", cache.rows() * joints, d_offsets.len())?;
        net.backward(&cache.activations, d_offsets)?;
        Ok(())
    }
}

/// Checks that every input value is finite, naming the field and the first bad index (a NaN
/// would otherwise flow silently into every parameter gradient).
pub(crate) fn check_finite<S: NnScalar>(field: &str, values: &[S]) -> Result<(), ModelError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(ModelError::Input {
            field: field.into(),
            message: format!(
                "value {index} is {}, expected a finite number",
                values[index]
            ),
        }),
    }
}

/// Checks an input length, naming the field.
pub(crate) fn check_input(field: &str, expected: usize, actual: usize) -> Result<(), ModelError> {
    if expected == actual {
        Ok(())
    } else {
        Err(ModelError::InputLength {
            field: field.into(),
            expected,
            actual,
        })
    }
}
