//! Per-frame body parameters as flat tracks (what the solver works on). They are read from
//! and written to an entry's arrays in [`crate::fit`] (`BodySequence::read`, `write`), with
//! the ingest entry's array readers and writers: the fit stage writes the same parameter
//! arrays as ingest, so a later stage reads a fit entry and an ingest entry the same way.

use seqavatar_core::body::BodyParams;
use seqavatar_core::glam::DVec3;

/// Body parameters of every frame of a sequence, flat and frame-major.
#[derive(Clone, Debug, PartialEq)]
pub struct BodySequence {
    pub num_frames: usize,
    pub num_joints: usize,
    pub num_betas: usize,
    pub num_expression: usize,
    /// `(frame, joint)` local axis-angle rotations, root first.
    pub pose: Vec<DVec3>,
    /// `(frame)` world rotation (axis-angle, `Rh`).
    pub world_rotation: Vec<DVec3>,
    /// `(frame)` world translation (`Th`).
    pub world_translation: Vec<DVec3>,
    /// `(frame, beta)`.
    pub betas: Vec<f64>,
    /// `(frame, expression)`; empty when the model has no expression components.
    pub expression: Vec<f64>,
}

impl BodySequence {
    /// Packs per-frame parameters; every frame must have the same counts.
    pub fn from_params(params: &[BodyParams]) -> Result<Self, String> {
        let first = params.first();
        let num_joints = first.map_or(0, |p| p.pose.len());
        let num_betas = first.map_or(0, |p| p.betas.len());
        let num_expression = first.map_or(0, |p| p.expression.len());
        for (f, p) in params.iter().enumerate() {
            if p.pose.len() != num_joints
                || p.betas.len() != num_betas
                || p.expression.len() != num_expression
            {
                return Err(format!(
                    "frame {f} has {} joints, {} betas, {} expression coefficients; frame 0 has {num_joints}, {num_betas}, {num_expression}",
                    p.pose.len(),
                    p.betas.len(),
                    p.expression.len()
                ));
            }
        }
        Ok(Self {
            num_frames: params.len(),
            num_joints,
            num_betas,
            num_expression,
            pose: params.iter().flat_map(|p| p.pose.iter().copied()).collect(),
            world_rotation: params.iter().map(|p| p.world_rotation).collect(),
            world_translation: params.iter().map(|p| p.world_translation).collect(),
            betas: params
                .iter()
                .flat_map(|p| p.betas.iter().copied())
                .collect(),
            expression: params
                .iter()
                .flat_map(|p| p.expression.iter().copied())
                .collect(),
        })
    }

    /// Every frame's parameters.
    pub fn to_params(&self) -> Vec<BodyParams> {
        (0..self.num_frames).map(|t| self.params(t)).collect()
    }

    /// Names the first non-finite value, as `field ... at frame f[, joint j]`.
    pub fn check_finite(&self, prefix: &str) -> Result<(), String> {
        let joints = self.num_joints.max(1);
        if let Some(i) = self.pose.iter().position(|v| !v.is_finite()) {
            return Err(format!(
                "array `{prefix}_pose` is not finite at frame {}, joint {} ({:?})",
                i / joints,
                i % joints,
                self.pose[i]
            ));
        }
        for (field, values) in [
            ("world_rotation", &self.world_rotation),
            ("world_translation", &self.world_translation),
        ] {
            if let Some(f) = values.iter().position(|v| !v.is_finite()) {
                return Err(format!(
                    "array `{prefix}_{field}` is not finite at frame {f}"
                ));
            }
        }
        for (field, values, width) in [
            ("betas", &self.betas, self.num_betas),
            ("expression", &self.expression, self.num_expression),
        ] {
            if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                return Err(format!(
                    "array `{prefix}_{field}` is not finite at frame {}",
                    i / width.max(1)
                ));
            }
        }
        Ok(())
    }

    /// The parameters of one frame.
    pub fn params(&self, frame: usize) -> BodyParams {
        let j = self.num_joints;
        BodyParams {
            pose: self.pose[frame * j..(frame + 1) * j].to_vec(),
            betas: self.betas[frame * self.num_betas..(frame + 1) * self.num_betas].to_vec(),
            expression: self.expression
                [frame * self.num_expression..(frame + 1) * self.num_expression]
                .to_vec(),
            world_rotation: self.world_rotation[frame],
            world_translation: self.world_translation[frame],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(frames: usize, joints: usize) -> Vec<BodyParams> {
        (0..frames)
            .map(|t| BodyParams {
                pose: (0..joints)
                    .map(|j| DVec3::splat(0.01 * (t + j) as f64))
                    .collect(),
                betas: vec![0.1, 0.2],
                expression: Vec::new(),
                world_rotation: DVec3::ZERO,
                world_translation: DVec3::new(t as f64, 0.0, 0.0),
            })
            .collect()
    }

    #[test]
    fn round_trips_and_names_a_nan_pose() {
        let p = params(4, 6);
        let s = BodySequence::from_params(&p).unwrap();
        assert_eq!(s.to_params(), p);
        assert!(s.check_finite("body").is_ok());
        let mut bad = p.clone();
        bad[2].pose[5].y = f64::NAN;
        let message = BodySequence::from_params(&bad)
            .unwrap()
            .check_finite("body")
            .unwrap_err();
        assert!(
            message.contains("`body_pose`") && message.contains("frame 2, joint 5"),
            "{message}"
        );
        let mut bad = p.clone();
        bad[3].world_translation.z = f64::INFINITY;
        let message = BodySequence::from_params(&bad)
            .unwrap()
            .check_finite("gt_body")
            .unwrap_err();
        assert!(
            message.contains("`gt_body_world_translation`") && message.contains("frame 3"),
            "{message}"
        );
        let mut ragged = p;
        ragged[1].pose.pop();
        assert!(
            BodySequence::from_params(&ragged)
                .unwrap_err()
                .contains("frame 1")
        );
    }
}
