//! What rendering a trained avatar needs of the configuration it was trained with: the
//! networks' shapes and switches, the motion window, the scale bounds of skinning and the
//! background. The train stage derives an [`AvatarConfig`] from its `TrainConfig` and writes
//! it into its entry (attribute `avatar`); eval and `pipeline render` read it from there, so
//! neither depends on the trainer (learning rates, schedules and losses stay in `train`).

use seqavatar_compute::nn::Precision;
use seqavatar_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};

use crate::model::Widths;

/// The paper's ablation rows (a) to (e): which motion conditions feed the non-rigid network.
/// Each level includes the previous ones; a disabled condition's encoder is not built at all.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum MotionContext {
    /// (a) No non-rigid deformation: skinning only.
    None,
    /// (b) Non-rigid network on position and current pose.
    Pose,
    /// (c) Plus the skeleton motion sequence (Delta P).
    Skeleton,
    /// (d) Plus KNN vertex velocities at the single smallest scale.
    Velocity,
    /// (e) Plus all scales.
    Multiscale,
}

impl MotionContext {
    pub fn has_non_rigid(self) -> bool {
        self >= Self::Pose
    }
    pub fn has_skeleton_motion(self) -> bool {
        self >= Self::Skeleton
    }
    pub fn has_velocity(self) -> bool {
        self >= Self::Velocity
    }
    pub fn is_multiscale(self) -> bool {
        self == Self::Multiscale
    }
    /// The ablation row letter.
    pub fn row(self) -> char {
        match self {
            Self::None => 'a',
            Self::Pose => 'b',
            Self::Skeleton => 'c',
            Self::Velocity => 'd',
            Self::Multiscale => 'e',
        }
    }
}

/// The colour the avatar is rendered on during training, and the training targets composited
/// onto (the ground truth is the person over its mask, on this background).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// Black, as docs/method.md trains every dataset.
    Black,
    /// White.
    White,
    /// A uniformly random colour per iteration (the same for the render and the target of
    /// that iteration), the usual remedy against the model painting the background.
    Random,
}

impl Background {
    /// The colour of one training iteration: the fixed colour, or for `random` three
    /// uniform draws from `rng` (the only background that draws, so black and white runs
    /// keep their random streams).
    pub fn draw(self, rng: &mut SplitMix64) -> [f64; 3] {
        match self {
            Self::Random => [rng.next_f64(), rng.next_f64(), rng.next_f64()],
            fixed => fixed.render_colour(),
        }
    }

    /// The colour a trained avatar renders on by default (`pipeline render`): the fixed
    /// colour; black for `random`. (The held-out PSNR and eval render on the evaluation
    /// protocol's background.)
    pub fn render_colour(self) -> [f64; 3] {
        match self {
            Self::Black | Self::Random => [0.0; 3],
            Self::White => [1.0; 3],
        }
    }
}

/// The evaluation protocol's background (docs/method.md: black for every dataset). The held-out
/// PSNR renders the avatar on it and sets the truth outside the mask to it, whatever the
/// training background, so it is the number eval reports with its default protocol.
pub const PROTOCOL_BACKGROUND: [f64; 3] = [0.0; 3];

/// Upper bounds of the network sizes (far above the paper's settings; larger values would
/// abort on allocation or run for days).
pub const MAX_TRUNK_WIDTH: usize = 4096;
pub const MAX_TRUNK_DEPTH: usize = 32;
pub const MAX_TAU: usize = 64;
pub const MAX_SEQUENCE_LENGTH: usize = 64;

/// The part of a training configuration that rendering the trained avatar needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvatarConfig {
    pub motion_context: MotionContext,
    /// Width of the non-rigid trunk's hidden layers.
    pub trunk_width: usize,
    /// Number of hidden layers of the non-rigid trunk.
    pub trunk_depth: usize,
    /// Nearest template vertices per Gaussian for the velocity context (tau).
    pub tau: usize,
    /// Sequence length L of the motion window.
    pub sequence_length: usize,
    /// Whether the body-pose refiner exists.
    pub pose_refiner: bool,
    /// Whether the LBS-offset network exists.
    pub lbs_offsets: bool,
    /// Largest SH degree of the run (the entry's `sh_degree` is the active one).
    pub sh_degree: u32,
    /// Bounds of the linear scale after the non-rigid offset, metres.
    pub scale_min: f64,
    pub scale_max: f64,
    /// The training background (`random` renders on black).
    pub background: Background,
    /// How the networks' dense layers run on the `gpu` backend (the train config's
    /// `precision`, stored only where it was set, so entries of configs without it are
    /// written as before): `None` is [`Precision::Mixed`] ([`AvatarConfig::networks_precision`]).
    /// `pipeline render`, `export` and `view` use the value stored in the train entry; eval
    /// replaces it with its own config's `precision`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub precision: Option<Precision>,
    /// Width (metres, the kernel's sigma) over which the template's skinning weights are
    /// diffused across the canonical template before training
    /// ([`crate::rig::BodyRig::smooth_template_weights`]); absent or 0: the template's own
    /// weights, and the key of configs without it is unchanged (serialised only where set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skinning_smoothing: Option<f64>,
    /// The networks' block widths where they differ from the published code's
    /// ([`Widths::PAPER`]; the fields not given keep it). Absent (every preset) is the paper's,
    /// and the key of configs without it is unchanged (serialised only where set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub network_widths: Option<Widths>,
}

/// The largest [`AvatarConfig::skinning_smoothing`] (metres): half a body height already
/// blends every joint into every other.
pub const MAX_SKINNING_SMOOTHING: f64 = 1.0;

/// A rejected avatar configuration, naming the field.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("avatar config field `{field}`: {message}")]
pub struct AvatarConfigError {
    pub field: String,
    pub message: String,
}

impl AvatarConfig {
    /// Checks ranges and cross-field rules (the train config's checks of these fields).
    pub fn validate(&self) -> Result<(), AvatarConfigError> {
        let bad = |field: &str, message: String| {
            Err(AvatarConfigError {
                field: field.into(),
                message,
            })
        };
        if self.motion_context.has_non_rigid() && (self.trunk_width == 0 || self.trunk_depth == 0) {
            return bad(
                "trunk_width",
                "the non-rigid trunk needs width and depth >= 1".into(),
            );
        }
        if self.motion_context.has_velocity() && self.tau == 0 {
            return bad("tau", "velocity context needs tau >= 1".into());
        }
        if self.motion_context.has_skeleton_motion() && self.sequence_length == 0 {
            return bad("sequence_length", "must be at least 1".into());
        }
        for (name, value, max) in [
            ("trunk_width", self.trunk_width, MAX_TRUNK_WIDTH),
            ("trunk_depth", self.trunk_depth, MAX_TRUNK_DEPTH),
            ("tau", self.tau, MAX_TAU),
            ("sequence_length", self.sequence_length, MAX_SEQUENCE_LENGTH),
        ] {
            if value > max {
                return bad(name, format!("must be at most {max}, got {value}"));
            }
        }
        if self.sh_degree > 3 {
            return bad(
                "sh_degree",
                format!("must be 0..=3, got {}", self.sh_degree),
            );
        }
        if !(self.scale_min > 0.0 && self.scale_max > self.scale_min && self.scale_max.is_finite())
        {
            return bad("scale_min", "need 0 < scale_min < scale_max".into());
        }
        if let Some(widths) = &self.network_widths {
            widths
                .validate()
                .map_err(|(field, message)| AvatarConfigError {
                    field: format!("network_widths.{field}"),
                    message,
                })?;
        }
        if let Some(sigma) = self.skinning_smoothing
            && !(0.0..=MAX_SKINNING_SMOOTHING).contains(&sigma)
        {
            return bad(
                "skinning_smoothing",
                format!("must be in [0, {MAX_SKINNING_SMOOTHING}] metres, got {sigma}"),
            );
        }
        Ok(())
    }

    /// Whether the avatar has networks (a non-rigid deformation or a refiner).
    pub fn needs_networks(&self) -> bool {
        self.motion_context.has_non_rigid() || self.pose_refiner || self.lbs_offsets
    }

    /// The body rig this avatar skins with: `model`'s, its template weights diffused by
    /// [`AvatarConfig::skinning_smoothing`]. Training and every reader of a trained avatar
    /// build it here, so they skin alike.
    pub fn rig(
        &self,
        model: seqavatar_core::body::BodyModel,
    ) -> anyhow::Result<crate::rig::BodyRig> {
        let mut rig = crate::rig::BodyRig::new(model)?;
        rig.smooth_template_weights(self.skinning_smoothing.unwrap_or(0.0));
        Ok(rig)
    }

    /// The precision the networks' gpu kernels are built with: [`AvatarConfig::precision`],
    /// `mixed` where it is absent.
    pub fn networks_precision(&self) -> Precision {
        self.precision.unwrap_or_default()
    }
}

impl AvatarConfig {
    /// A small configuration for tests: every network, the `fast` preset's sizes.
    #[cfg(test)]
    pub(crate) fn for_tests() -> Self {
        Self {
            motion_context: MotionContext::Multiscale,
            trunk_width: 64,
            trunk_depth: 3,
            tau: 4,
            sequence_length: 2,
            pose_refiner: true,
            lbs_offsets: true,
            sh_degree: 1,
            scale_min: 1e-5,
            scale_max: 0.5,
            background: Background::Black,
            // The gpu paths are compared with `cpu` at f32's tolerances.
            precision: Some(Precision::F32),
            skinning_smoothing: None,
            network_widths: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> AvatarConfig {
        AvatarConfig::for_tests()
    }

    /// The stored avatar config of entries written before `precision` existed reads as
    /// `mixed`; an absent precision is not written, a set one is.
    #[test]
    fn precision_is_optional_in_the_stored_config() {
        let mut value = serde_json::to_value(config()).unwrap();
        value.as_object_mut().unwrap().remove("precision");
        let old: AvatarConfig = serde_json::from_value(value).unwrap();
        assert_eq!(old.precision, None);
        assert_eq!(old.networks_precision(), Precision::Mixed);
        assert!(
            serde_json::to_value(&old)
                .unwrap()
                .get("precision")
                .is_none()
        );
        let set = AvatarConfig {
            precision: Some(Precision::F32),
            ..old
        };
        assert_eq!(serde_json::to_value(&set).unwrap()["precision"], "f32");
        assert_eq!(set.networks_precision(), Precision::F32);
    }

    #[test]
    fn validation_names_the_field() {
        config().validate().unwrap();
        type Change = fn(&mut AvatarConfig);
        let cases: [(Change, &str); 10] = [
            (|c| c.trunk_depth = 0, "trunk_width"),
            (|c| c.tau = 0, "tau"),
            (
                |c| c.sequence_length = MAX_SEQUENCE_LENGTH + 1,
                "sequence_length",
            ),
            (|c| c.sh_degree = 4, "sh_degree"),
            (|c| c.scale_max = c.scale_min, "scale_min"),
            (|c| c.trunk_width = MAX_TRUNK_WIDTH + 1, "trunk_width"),
            (|c| c.skinning_smoothing = Some(-0.1), "skinning_smoothing"),
            (
                |c| c.skinning_smoothing = Some(f64::NAN),
                "skinning_smoothing",
            ),
            (
                |c| {
                    c.network_widths = Some(Widths {
                        lbs_hidden: 0,
                        ..Widths::PAPER
                    })
                },
                "network_widths.lbs_hidden",
            ),
            (
                |c| {
                    c.network_widths = Some(Widths {
                        seq_xyz_hidden: MAX_TRUNK_WIDTH + 1,
                        ..Widths::PAPER
                    })
                },
                "network_widths.seq_xyz_hidden",
            ),
        ];
        for (change, field) in cases {
            let mut c = config();
            change(&mut c);
            let err = c.validate().unwrap_err();
            assert_eq!(err.field, field, "{err}");
            assert!(err.to_string().contains(field));
        }
        // Without a non-rigid network, trunk sizes and the window do not matter.
        let mut rigid = config();
        rigid.motion_context = MotionContext::None;
        rigid.trunk_depth = 0;
        rigid.tau = 0;
        rigid.sequence_length = 0;
        rigid.validate().unwrap();
        assert!(rigid.needs_networks());
        rigid.pose_refiner = false;
        rigid.lbs_offsets = false;
        assert!(!rigid.needs_networks());
    }

    /// `network_widths` is stored only where set; the fields it does not give keep the
    /// paper's widths, and the networks are built with them.
    #[test]
    fn network_widths_default_to_the_papers_and_shape_the_networks() {
        assert!(
            serde_json::to_value(config())
                .unwrap()
                .get("network_widths")
                .is_none()
        );
        let mut value = serde_json::to_value(config()).unwrap();
        value["network_widths"] = serde_json::json!({"lbs_hidden": 32, "seq_xyz_hidden": 48});
        let narrow: AvatarConfig = serde_json::from_value(value.clone()).unwrap();
        let widths = narrow.network_widths.unwrap();
        assert_eq!((widths.lbs_hidden, widths.seq_xyz_hidden), (32, 48));
        assert_eq!(widths.seq_xyz_frame, Widths::PAPER.seq_xyz_frame);
        let network = crate::model::NetworkConfig::from_avatar(&narrow, 24, 24, 2).unwrap();
        assert_eq!(network.widths, widths);
        value["network_widths"]["lbs_width"] = serde_json::json!(8);
        let error = serde_json::from_value::<AvatarConfig>(value).unwrap_err();
        assert!(error.to_string().contains("lbs_width"), "{error}");
    }

    #[test]
    fn round_trips_and_rejects_unknown_fields() {
        let c = config();
        let value = serde_json::to_value(&c).unwrap();
        assert_eq!(
            serde_json::from_value::<AvatarConfig>(value.clone()).unwrap(),
            c
        );
        let mut extra = value;
        extra["learning_rates"] = serde_json::json!({});
        assert!(serde_json::from_value::<AvatarConfig>(extra).is_err());
    }
}
