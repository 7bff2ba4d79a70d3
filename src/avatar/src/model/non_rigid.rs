//! The non-rigid deformation network's inputs, outputs and cache around its description
//! ([`NetworkSpec::non_rigid`](super::spec::NetworkSpec::non_rigid): position encoding, pose /
//! skeleton-motion / velocity encoders and the trunk with its three heads).
//!
//! Layouts (row-major): positions `n x 3`; the velocity window `n x L x tau x |S| x 3`
//! (`[gaussian][window element][neighbour][scale, largest first][xyz]`); skeleton motion
//! `L x |S| x motion_joints x 3`. Window elements are processed as `L` separate `n`-row
//! blocks, so the per-Gaussian position branch of the `SeqXYZEncoder` is read by every
//! element without being copied, and the flattening `Linear(96 L, 256)` reads the `L` blocks
//! as the column blocks of its input.

use seqavatar_compute::nn::NnScalar;

use super::network::Activations;
use super::{HEAD_WIDTH, ModelError, NetworkConfig, check_input};

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
    pub(crate) activations: Activations<S>,
}

impl<S> NonRigidCache<S> {
    /// Number of Gaussians of the forward pass.
    pub fn rows(&self) -> usize {
        self.activations.rows()
    }
}

/// The input blocks of [`NetworkSpec::non_rigid`](super::spec::NetworkSpec::non_rigid), in
/// its order: local pose, skeleton motion (if used), positions, velocities (if used). Checks
/// that exactly the inputs the configuration uses are given (the interpreters check lengths
/// and values).
pub(crate) fn inputs<'a, S: NnScalar>(
    config: &NetworkConfig,
    frame: &FrameInputs<'a, S>,
    gaussians: &GaussianInputs<'a, S>,
) -> Result<Vec<&'a [S]>, ModelError> {
    let mut blocks = vec![frame.local_pose];
    let context = config.motion_context;
    match (context.has_skeleton_motion(), frame.skeleton_motion) {
        (true, Some(motion)) => blocks.push(motion),
        (false, None) => {}
        (true, None) => return Err(missing("frame.skeleton_motion", config)),
        (false, Some(_)) => return Err(unused("frame.skeleton_motion", config)),
    }
    blocks.push(gaussians.xyz);
    match (context.has_velocity(), gaussians.knn_velocity) {
        (true, Some(velocity)) => blocks.push(velocity),
        (false, None) => {}
        (true, None) => return Err(missing("gaussians.knn_velocity", config)),
        (false, Some(_)) => return Err(unused("gaussians.knn_velocity", config)),
    }
    Ok(blocks)
}

/// The `n x 10` gradient of the heads layer from those of `d_xyz`, `d_rot` and `d_scale`.
pub(crate) fn heads_gradient<S: NnScalar>(
    n: usize,
    d_dxyz: &[S],
    d_drot: &[S],
    d_dscale: &[S],
) -> Result<Vec<S>, ModelError> {
    check_input("d_dxyz", 3 * n, d_dxyz.len())?;
    check_input("d_drot", 4 * n, d_drot.len())?;
    check_input("d_dscale", 3 * n, d_dscale.len())?;
    let mut d_heads = Vec::with_capacity(n * HEAD_WIDTH);
    for g in 0..n {
        d_heads.extend_from_slice(&d_dxyz[3 * g..3 * g + 3]);
        d_heads.extend_from_slice(&d_drot[4 * g..4 * g + 4]);
        d_heads.extend_from_slice(&d_dscale[3 * g..3 * g + 3]);
    }
    Ok(d_heads)
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
