//! Skinned body models (SMPL, SMPL-X or the built-in procedural body): the model arrays,
//! per-frame parameters, forward kinematics, linear blend skinning and its derivatives.
//!
//! Conventions (ARCHITECTURE.md, "Body models"):
//! - Joints follow the model's kinematic tree; every parent index is smaller than its child's
//!   (true for SMPL and SMPL-X), so one forward pass computes every global transform.
//! - A pose is one local axis-angle per joint, the root included: `pose[0]` is what SMPL calls
//!   `global_orient` and rotates the body about the root joint.
//! - After skinning, a world transform `world = R(world_rotation) x + world_translation` is
//!   applied about the origin. This is ZJU-MoCap's and I3D-Human's `Rh`, `Th`; for
//!   DNA-Rendering (SMPL-X `transl`) the rotation is zero.
//! - The canonical space is the "big pose" ([`big_pose`]).

mod kinematics;
mod model;
pub mod procedural;
#[cfg(test)]
mod tests;

pub use kinematics::{BodyGradient, Posed};
pub use model::{BodyModel, BodyModelArrays, BodyModelError, BodyParams, BodyParamsError};

use glam::DVec3;

/// SMPL's joint names in SMPL's joint order (the first 22 are also SMPL-X's body joints).
pub const SMPL_JOINT_NAMES: [&str; 24] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
];

/// SMPL's kinematic tree: the parent of each joint (`None` for the root).
pub const SMPL_PARENTS: [Option<usize>; 24] = [
    None,
    Some(0),
    Some(0),
    Some(0),
    Some(1),
    Some(2),
    Some(3),
    Some(4),
    Some(5),
    Some(6),
    Some(7),
    Some(8),
    Some(9),
    Some(9),
    Some(9),
    Some(12),
    Some(13),
    Some(14),
    Some(16),
    Some(17),
    Some(18),
    Some(19),
    Some(20),
    Some(21),
];

/// The canonical "big pose" for a model with `num_joints` joints (root included).
///
/// The authors' code sets, in SMPL's flat 72-vector, `pose[5] = +45 deg`, `pose[8] = -45 deg`,
/// `pose[23] = -30 deg`, `pose[26] = +30 deg`, and for SMPL-X the same angles at `body_pose`
/// indices 2, 5, 20, 23 (body_pose has no root). Both are the z components of joints 1, 2
/// (hips: legs spread) and 7, 8 (ankles: feet flat again), which share their index in
/// SMPL and SMPL-X. Models with fewer than 9 joints get the rotations that exist.
pub fn big_pose(num_joints: usize) -> Vec<DVec3> {
    let mut pose = vec![DVec3::ZERO; num_joints];
    let degrees = std::f64::consts::PI / 180.0;
    for (joint, angle) in [(1, 45.0), (2, -45.0), (7, -30.0), (8, 30.0)] {
        if joint < num_joints {
            pose[joint].z = angle * degrees;
        }
    }
    pose
}

#[cfg(test)]
mod tree_tests {
    use super::*;

    #[test]
    fn big_pose_matches_the_flat_smpl_indices() {
        let pose = big_pose(24);
        let flat: Vec<f64> = pose.iter().flat_map(|v| v.to_array()).collect();
        let deg = std::f64::consts::PI / 180.0;
        for (i, value) in flat.iter().enumerate() {
            let expected = match i {
                5 => 45.0 * deg,
                8 => -45.0 * deg,
                23 => -30.0 * deg,
                26 => 30.0 * deg,
                _ => 0.0,
            };
            assert_eq!(*value, expected, "index {i}");
        }
        // SMPL-X: body_pose (no root) indices 2, 5, 20, 23.
        let smplx = big_pose(55);
        let body: Vec<f64> = smplx[1..].iter().flat_map(|v| v.to_array()).collect();
        assert_eq!(body[2], 45.0 * deg);
        assert_eq!(body[5], -45.0 * deg);
        assert_eq!(body[20], -30.0 * deg);
        assert_eq!(body[23], 30.0 * deg);
        assert_eq!(body.iter().filter(|v| **v != 0.0).count(), 4);
        assert_eq!(big_pose(3).len(), 3);
    }

    #[test]
    fn smpl_tree_is_topologically_ordered() {
        for (joint, parent) in SMPL_PARENTS.iter().enumerate() {
            match parent {
                None => assert_eq!(joint, 0),
                Some(p) => assert!(*p < joint),
            }
        }
    }
}
