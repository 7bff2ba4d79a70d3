//! The train stage's configuration: presets `fast`, `balanced` and `paper`, each field
//! overridable, validated once into a [`TrainConfig`] whose canonical JSON enters the key.
//!
//! The YAML names a `preset` (default `balanced`) and any fields to change; resolution fills
//! every other field from the preset, so the stored config is always explicit.

use std::path::PathBuf;

use seqavatar_avatar::model::NetworkGroup;
pub use seqavatar_compute::backend::DeviceChoice;
use seqavatar_compute::lpips::{LpipsInput, LpipsNet};
use seqavatar_compute::nn::Precision;
use seqavatar_compute::nn::adam::AdamConfig;
use seqavatar_schema::ingest::IngestImages;
use serde::{Deserialize, Serialize};

pub use seqavatar_avatar::config::{
    AvatarConfig, Background, MAX_SEQUENCE_LENGTH, MAX_TAU, MAX_TRUNK_DEPTH, MAX_TRUNK_WIDTH,
    MotionContext,
};
use seqavatar_avatar::model::Widths;

/// Named starting points trading speed for accuracy.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// The demo: minutes on 2 CPU cores.
    Fast,
    /// A reasonable single-GPU run.
    Balanced,
    /// The paper's I3D-Human settings.
    Paper,
}

/// Learning rates (docs/method.md, "Optimisation").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearningRates {
    /// Times the scene extent; decays exponentially to `position_final` over
    /// `position_decay_steps`.
    pub position_initial: f64,
    pub position_final: f64,
    pub position_decay_steps: u32,
    pub sh_dc: f64,
    pub sh_rest: f64,
    pub opacity: f64,
    pub scaling: f64,
    pub rotation: f64,
    pub pose_refiner: f64,
    pub lbs_offsets: f64,
    pub non_rigid: f64,
    /// Per-step factor of the network rates is `network_decay^(1 / iterations)`.
    pub network_decay: f64,
    pub adam_eps: f64,
}

impl LearningRates {
    /// Rates are finite and >= 0, the decays in (0, 1] with at least one step, Adam's
    /// epsilon finite and > 0.
    fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, message: String| {
            Err(ConfigError::Field {
                field: format!("learning_rates.{field}"),
                message,
            })
        };
        for (name, value) in [
            ("position_initial", self.position_initial),
            ("position_final", self.position_final),
            ("sh_dc", self.sh_dc),
            ("sh_rest", self.sh_rest),
            ("opacity", self.opacity),
            ("scaling", self.scaling),
            ("rotation", self.rotation),
            ("pose_refiner", self.pose_refiner),
            ("lbs_offsets", self.lbs_offsets),
            ("non_rigid", self.non_rigid),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(name, format!("must be finite and >= 0, got {value}"));
            }
        }
        if self.position_initial > 0.0 && self.position_final <= 0.0 {
            return bad(
                "position_final",
                "must be > 0 when position_initial is (the decay is exponential)".into(),
            );
        }
        if self.position_decay_steps == 0 {
            return bad("position_decay_steps", "must be at least 1".into());
        }
        if !(self.network_decay > 0.0 && self.network_decay <= 1.0) {
            return bad(
                "network_decay",
                format!("must be in (0, 1], got {}", self.network_decay),
            );
        }
        if !(self.adam_eps.is_finite() && self.adam_eps > 0.0) {
            return bad(
                "adam_eps",
                format!("must be finite and > 0, got {}", self.adam_eps),
            );
        }
        Ok(())
    }
}

impl Default for LearningRates {
    fn default() -> Self {
        Self {
            position_initial: 1.6e-4,
            position_final: 1.6e-6,
            position_decay_steps: 30_000,
            sh_dc: 2.5e-3,
            sh_rest: 1.25e-4,
            opacity: 0.05,
            scaling: 5e-3,
            rotation: 1e-3,
            pose_refiner: 5e-5,
            lbs_offsets: 5e-5,
            non_rigid: 1e-3,
            network_decay: 0.1,
            adam_eps: 1e-15,
        }
    }
}

/// Upper bounds of the batch sizes (far above the paper's settings; larger values would
/// abort on allocation or run for days; the network bounds are the avatar config's).
pub const MAX_GAUSSIANS: usize = 10_000_000;
pub const MAX_CAMERAS_PER_STEP: usize = 256;
pub const MAX_AIAP_NEIGHBOURS: usize = 64;
pub const MAX_BOUND_PADDING: usize = 4096;

/// The effective configuration of one training run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: Preset,
    pub device: DeviceChoice,
    pub seed: u64,
    pub iterations: u32,
    /// Image scale applied to the ingest images (1 = as ingested).
    pub resolution_scale: f64,
    pub motion_context: MotionContext,
    /// Width of the non-rigid trunk's hidden layers.
    pub trunk_width: usize,
    /// Number of hidden layers of the non-rigid trunk.
    pub trunk_depth: usize,
    /// Nearest template vertices per Gaussian for the velocity context (tau).
    pub tau: usize,
    /// Sequence length L.
    pub sequence_length: usize,
    /// Temporal scales to use (must exist in the motion entry); empty: all of them.
    /// `velocity` uses only the smallest one.
    pub scales: Vec<u32>,
    pub max_gaussians: usize,
    pub densify: bool,
    pub densify_from: u32,
    pub densify_until: u32,
    pub densify_interval: u32,
    pub densify_grad_threshold: f64,
    pub prune_opacity: f64,
    pub percent_dense: f64,
    pub cameras_per_step: usize,
    pub pose_refiner: bool,
    pub lbs_offsets: bool,
    /// Bound of the uniform initialisation of the non-rigid heads' weights (biases 0), so a
    /// fresh network starts at the identity deformation; 0 keeps PyTorch's default
    /// initialisation of the reference code, whose initial offsets are centimetres to
    /// decimetres and cost the short runs several dB (see the ablation in the report).
    pub non_rigid_head_init: f64,
    pub sh_degree: u32,
    pub sh_degree_interval: u32,
    pub mask_weight: f64,
    pub ssim_weight: f64,
    /// Weight of the LPIPS loss on the bound-box crop; 0 (every preset) turns it off and
    /// nothing LPIPS loads or runs. Above 0 it needs `lpips_weights`.
    pub lpips_weight: f64,
    /// The `lpips` package weights as written by `tests/lpips/convert_weights.py` (their
    /// content enters the stage key when the loss is on).
    pub lpips_weights: Option<PathBuf>,
    /// The LPIPS trunk (`vgg` as in the paper, or `alex`).
    pub lpips_net: LpipsNet,
    /// Feed images in [0, 1] to LPIPS unmapped, as the authors' code does (docs/method.md); the
    /// default maps them to [-1, 1] as the package expects.
    pub lpips_unnormalised_input: bool,
    pub aiap_centre_weight: f64,
    pub aiap_covariance_weight: f64,
    pub aiap_neighbours: usize,
    pub bound_padding: usize,
    /// Bounds of the linear scale after the non-rigid offset, metres.
    pub scale_min: f64,
    pub scale_max: f64,
    pub learning_rates: LearningRates,
    pub checkpoint_every: u32,
    /// The background renders and targets are composited on (`black`, `white`, `random`).
    pub background: Background,
    /// How the networks' dense layers run on the `gpu` backend: `f32`, or `mixed` (f16
    /// operands with f32 accumulation on tensor cores where the adapter has them, else f32;
    /// parameters, gradients and Adam stay f32). Absent means `mixed`, and leaves the key of
    /// configs written before the setting existed unchanged (it is serialised only where set).
    /// `cpu` ignores it. Chosen once per run; the log's `networks:` line names the path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub precision: Option<Precision>,
    /// Diffuses the template's skinning weights over this width (metres) before training
    /// (`AvatarConfig::skinning_smoothing`): loose garments, whose Gaussians start on the
    /// legs but follow the pelvis, need it; absent or 0 (every preset) keeps the template's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skinning_smoothing: Option<f64>,
    /// Adds Gaussians on the masks' visual hull where the body template has no surface
    /// (`crate::hull`: a loose garment's hem, hair); absent (every preset) starts from the
    /// template alone, as the paper does. Serialised only where set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hull_init: Option<crate::hull::HullInit>,
    /// The networks' block widths where they differ from the published code's (any of
    /// `AvatarConfig::network_widths`' fields; the rest keep the paper's); absent (every
    /// preset) is the paper's. Serialised only where set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub network_widths: Option<Widths>,
}

/// A config error naming `field`.
fn bad(field: &str, message: String) -> Result<(), ConfigError> {
    Err(ConfigError::Field {
        field: field.into(),
        message,
    })
}

impl TrainConfig {
    /// The Adam configuration of the run (both the Gaussians' and the networks').
    pub fn adam(&self) -> AdamConfig {
        AdamConfig {
            eps: self.learning_rates.adam_eps,
            ..AdamConfig::default()
        }
    }

    /// The rate of network group `group` at (1-based) `iteration`: its learning rate decayed
    /// by `network_decay^((iteration - 1) / iterations)`.
    pub fn network_rate(&self, group: NetworkGroup, iteration: u64) -> f64 {
        let lr = &self.learning_rates;
        let decay = lr
            .network_decay
            .powf((iteration - 1) as f64 / f64::from(self.iterations));
        decay
            * match group {
                NetworkGroup::NonRigid => lr.non_rigid,
                NetworkGroup::PoseRefiner => lr.pose_refiner,
                NetworkGroup::LbsOffsets => lr.lbs_offsets,
            }
    }

    /// The preset's full configuration.
    pub fn preset(preset: Preset) -> Self {
        let base = Self {
            preset,
            device: DeviceChoice::Auto,
            seed: 0,
            iterations: 3000,
            resolution_scale: 1.0,
            motion_context: MotionContext::Multiscale,
            trunk_width: 256,
            trunk_depth: 3,
            tau: 6,
            sequence_length: 3,
            scales: Vec::new(),
            max_gaussians: 120_000,
            densify: true,
            densify_from: 400,
            densify_until: 1200,
            densify_interval: 100,
            densify_grad_threshold: 2e-4,
            prune_opacity: 0.005,
            percent_dense: 0.01,
            cameras_per_step: 1,
            pose_refiner: true,
            lbs_offsets: true,
            non_rigid_head_init: 1e-5,
            sh_degree: 3,
            sh_degree_interval: 1000,
            mask_weight: 0.1,
            ssim_weight: 0.1,
            lpips_weight: 0.0,
            lpips_weights: None,
            lpips_net: LpipsNet::Vgg,
            lpips_unnormalised_input: false,
            aiap_centre_weight: 1.0,
            aiap_covariance_weight: 100.0,
            aiap_neighbours: 5,
            bound_padding: 5,
            scale_min: 1e-5,
            scale_max: 0.5,
            learning_rates: LearningRates::default(),
            checkpoint_every: 500,
            background: Background::Black,
            precision: None,
            skinning_smoothing: None,
            hull_init: None,
            network_widths: None,
        };
        match preset {
            Preset::Balanced => base,
            Preset::Fast => Self {
                iterations: 400,
                resolution_scale: 0.5,
                trunk_width: 64,
                tau: 4,
                sequence_length: 2,
                max_gaussians: 20_000,
                densify: false,
                sh_degree: 1,
                sh_degree_interval: 200,
                checkpoint_every: 100,
                ..base
            },
            Preset::Paper => Self {
                iterations: 15_000,
                trunk_width: 512,
                tau: 8,
                sequence_length: 8,
                densify_until: 1800,
                checkpoint_every: 1000,
                ..base
            },
        }
    }

    /// Resolves a raw YAML/JSON config: the preset, then the given overrides, then checks.
    pub fn resolve(raw: &serde_json::Value) -> Result<Self, ConfigError> {
        let object = match raw {
            serde_json::Value::Null => serde_json::Map::new(),
            serde_json::Value::Object(map) => map.clone(),
            _ => return Err(ConfigError::NotAMapping),
        };
        let preset: Preset = match object.get("preset") {
            Some(value) => Preset::deserialize(value).map_err(|e| ConfigError::Field {
                field: "preset".into(),
                message: e.to_string(),
            })?,
            None => Preset::Balanced,
        };
        let mut merged = serde_json::to_value(Self::preset(preset)).expect("config serialises");
        merge(&mut merged, &serde_json::Value::Object(object));
        let config: Self =
            serde_path_to_error::deserialize(merged).map_err(|e| ConfigError::Field {
                field: e.path().to_string(),
                message: e.inner().to_string(),
            })?;
        config.validate()?;
        Ok(config)
    }

    /// Iterations, resolution, the avatar's fields and the size bounds (Gaussians, cameras,
    /// neighbours, padding, scales).
    fn validate_sizes(&self) -> Result<(), ConfigError> {
        if let Some(Err((field, message))) = self.hull_init.as_ref().map(|h| h.validate()) {
            return bad(&field, message);
        }
        if self.iterations == 0 {
            return bad("iterations", "must be at least 1".into());
        }
        if !(self.resolution_scale > 0.0 && self.resolution_scale <= 4.0) {
            return bad(
                "resolution_scale",
                format!("must be in (0, 4], got {}", self.resolution_scale),
            );
        }
        // The fields the avatar keeps (network sizes, window, SH degree, scale bounds).
        self.avatar().validate().map_err(|e| ConfigError::Field {
            field: e.field,
            message: e.message,
        })?;
        // Upper bounds: far above the paper's settings, below what aborts.
        for (name, value, max) in [
            ("max_gaussians", self.max_gaussians, MAX_GAUSSIANS),
            (
                "cameras_per_step",
                self.cameras_per_step,
                MAX_CAMERAS_PER_STEP,
            ),
            ("aiap_neighbours", self.aiap_neighbours, MAX_AIAP_NEIGHBOURS),
            ("bound_padding", self.bound_padding, MAX_BOUND_PADDING),
        ] {
            if value > max {
                return bad(name, format!("must be at most {max}, got {value}"));
            }
        }
        if self.scales.contains(&0) {
            return bad("scales", "a temporal scale must be at least 1 frame".into());
        }
        if self.max_gaussians == 0 {
            return bad("max_gaussians", "must be at least 1".into());
        }
        if self.cameras_per_step == 0 {
            return bad("cameras_per_step", "must be at least 1".into());
        }
        Ok(())
    }

    /// Intervals, densification and pruning thresholds, and the loss weights.
    fn validate_schedule_and_weights(&self) -> Result<(), ConfigError> {
        for (name, value) in [
            ("sh_degree_interval", self.sh_degree_interval),
            ("densify_interval", self.densify_interval),
            ("checkpoint_every", self.checkpoint_every),
        ] {
            if value == 0 {
                return bad(
                    name,
                    "must be at least 1 (an interval in iterations)".into(),
                );
            }
        }
        for (name, value) in [
            ("densify_grad_threshold", self.densify_grad_threshold),
            ("percent_dense", self.percent_dense),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return bad(name, format!("must be finite and > 0, got {value}"));
            }
        }
        if !(0.0..1.0).contains(&self.prune_opacity) {
            return bad(
                "prune_opacity",
                format!("must be in [0, 1), got {}", self.prune_opacity),
            );
        }
        if self.aiap_neighbours < 2 {
            return bad(
                "aiap_neighbours",
                "needs self plus at least one neighbour".into(),
            );
        }
        if !(self.non_rigid_head_init.is_finite() && self.non_rigid_head_init >= 0.0) {
            return bad(
                "non_rigid_head_init",
                format!("must be finite and >= 0, got {}", self.non_rigid_head_init),
            );
        }
        for (name, value) in [
            ("mask_weight", self.mask_weight),
            ("ssim_weight", self.ssim_weight),
            ("lpips_weight", self.lpips_weight),
            ("aiap_centre_weight", self.aiap_centre_weight),
            ("aiap_covariance_weight", self.aiap_covariance_weight),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(name, format!("must be finite and >= 0, got {value}"));
            }
        }
        if self.lpips_weight > 0.0 && self.lpips_weights.is_none() {
            return bad(
                "lpips_weights",
                format!(
                    "lpips_weight {} needs the LPIPS weights file (converted by \
                     tests/lpips/convert_weights.py); set lpips_weights or lpips_weight: 0",
                    self.lpips_weight
                ),
            );
        }
        Ok(())
    }

    /// Checks ranges and cross-field rules.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.validate_sizes()?;
        self.validate_schedule_and_weights()?;
        self.learning_rates.validate()?;
        // The Gaussians alone against the budget; the images join the estimate where they are
        // known (`check_memory`: at load for a synthetic scene, else when the stage starts).
        let budget =
            seqavatar_engine::memory_budget_bytes().map_err(|message| ConfigError::Field {
                field: "max_gaussians".into(),
                message,
            })?;
        if let Some(budget) = budget {
            self.check_memory(None, budget)
                .map_err(|message| ConfigError::Field {
                    field: "max_gaussians".into(),
                    message,
                })?;
        }
        Ok(())
    }

    /// A lower bound of the memory a run allocates, in bytes: the Gaussians' parameters
    /// with their gradients and Adam moments (59 values of 8 bytes, four copies), the
    /// trunk's activations for every Gaussian (forward and backward, f32), its weights (f64,
    /// four copies) and the velocity context (`tau` neighbours over the sequence).
    pub fn memory_estimate_bytes(&self) -> u64 {
        let gaussians = self.max_gaussians as u64;
        let width = self.trunk_width as u64;
        let depth = self.trunk_depth as u64;
        let per_gaussian = 59 * 8 * 4
            + width.saturating_mul(depth).saturating_mul(4 * 2)
            + (self.tau as u64)
                .saturating_mul(self.sequence_length as u64)
                .saturating_mul(3 * 8);
        let weights = width
            .saturating_mul(width)
            .saturating_mul(depth)
            .saturating_mul(8 * 4);
        gaussians
            .saturating_mul(per_gaussian)
            .saturating_add(weights)
    }

    /// The memory a run needs at its peak, in bytes: [`Self::memory_estimate_bytes`], the
    /// images held in memory for the whole run (every image of the ingest entry, training and
    /// test, RGB and mask bytes at the training resolution), and the per-pixel state of the
    /// `cameras_per_step` renders of one iteration (forward, losses and backward).
    pub fn run_memory_estimate_bytes(&self, images: Option<&IngestImages>) -> u64 {
        let Some(images) = images else {
            return self.memory_estimate_bytes();
        };
        let pixels = pixels_at(images, self.resolution_scale);
        let held = images
            .count
            .saturating_mul(pixels)
            .saturating_mul(HELD_IMAGE_BYTES_PER_PIXEL);
        let renders = (self.cameras_per_step as u64)
            .saturating_mul(pixels)
            .saturating_mul(RENDER_BYTES_PER_PIXEL);
        self.memory_estimate_bytes()
            .saturating_add(held)
            .saturating_add(renders)
    }

    /// Refuses a run whose [`Self::run_memory_estimate_bytes`] exceeds `budget` bytes,
    /// naming the fields that make it large and how to raise the budget.
    pub fn check_memory(&self, images: Option<&IngestImages>, budget: u64) -> Result<(), String> {
        let estimate = self.run_memory_estimate_bytes(images);
        if estimate <= budget {
            return Ok(());
        }
        let images_part = images.map_or_else(String::new, |images| {
            let pixels = pixels_at(images, self.resolution_scale);
            format!(
                ", {} images of the ingest split ({}) at train.resolution_scale {} \
                 ({pixels} pixels each) and train.cameras_per_step {} renders",
                images.count, images.source, self.resolution_scale, self.cameras_per_step
            )
        });
        Err(format!(
            "training would need about {:.1} GB (train.max_gaussians {} x trunk {}x{}, tau {}, \
             sequence_length {}{images_part}), over the memory budget of {:.1} GB (set {} to \
             raise it)",
            estimate as f64 / 1e9,
            self.max_gaussians,
            self.trunk_width,
            self.trunk_depth,
            self.tau,
            self.sequence_length,
            budget as f64 / 1e9,
            seqavatar_engine::MEMORY_BUDGET_VAR
        ))
    }

    /// What rendering the trained avatar needs of this configuration (written into the
    /// train entry, read by eval and `pipeline render`).
    pub fn avatar(&self) -> AvatarConfig {
        AvatarConfig {
            motion_context: self.motion_context,
            trunk_width: self.trunk_width,
            trunk_depth: self.trunk_depth,
            tau: self.tau,
            sequence_length: self.sequence_length,
            pose_refiner: self.pose_refiner,
            lbs_offsets: self.lbs_offsets,
            sh_degree: self.sh_degree,
            scale_min: self.scale_min,
            scale_max: self.scale_max,
            background: self.background,
            precision: self.precision,
            skinning_smoothing: self.skinning_smoothing,
            network_widths: self.network_widths,
        }
    }

    /// The precision the networks' gpu kernels are built with (`precision`, `mixed` where
    /// absent).
    pub fn networks_precision(&self) -> Precision {
        self.precision.unwrap_or_default()
    }

    /// Whether the LPIPS loss runs (a positive weight; validation ensures the weights file).
    pub fn lpips_enabled(&self) -> bool {
        self.lpips_weight > 0.0
    }

    /// How rendered and ground-truth images enter LPIPS.
    pub fn lpips_input(&self) -> LpipsInput {
        if self.lpips_unnormalised_input {
            LpipsInput::UnitAsSigned
        } else {
            LpipsInput::Unit
        }
    }

    /// Scales to feed the networks given those the motion entry holds (largest first).
    pub fn effective_scales(&self, available: &[u32]) -> Result<Vec<u32>, ConfigError> {
        let mut chosen: Vec<u32> = if self.scales.is_empty() {
            available.to_vec()
        } else {
            self.scales.clone()
        };
        if let Some(missing) = chosen.iter().find(|s| !available.contains(s)) {
            return Err(ConfigError::Field {
                field: "scales".into(),
                message: format!(
                    "scale {missing} is not in the motion entry (it has {available:?})"
                ),
            });
        }
        chosen.sort_unstable_by(|a, b| b.cmp(a));
        chosen.dedup();
        if chosen.is_empty() {
            return Err(ConfigError::Field {
                field: "scales".into(),
                message: "no temporal scales".into(),
            });
        }
        if !self.motion_context.is_multiscale() {
            let smallest = *chosen.last().expect("not empty");
            chosen = vec![smallest];
        }
        Ok(chosen)
    }
}

/// Overlays `patch` onto `base` (objects merged recursively, other values replaced).
fn merge(base: &mut serde_json::Value, patch: &serde_json::Value) {
    match (base, patch) {
        (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
            for (k, v) in p {
                match b.get_mut(k) {
                    Some(slot) if slot.is_object() && v.is_object() => merge(slot, v),
                    _ => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, p) => *b = p.clone(),
    }
}

/// Bytes per pixel of an image held for the whole run: RGB and mask, one byte each.
const HELD_IMAGE_BYTES_PER_PIXEL: u64 = 4;
/// Bytes per pixel of one render in flight during an iteration: the composited colour, the
/// ground truth on the background, their gradient and the SSIM statistics (f64 maps, 216
/// bytes), and the splatting's per-pixel compositing state.
const RENDER_BYTES_PER_PIXEL: u64 = 256;

/// Pixels of one of `images` at the training resolution (`scale` of the entry's, rounded as
/// cameras are rescaled).
fn pixels_at(images: &IngestImages, scale: f64) -> u64 {
    let side = |n: u64| ((n as f64 * scale).round() as u64).max(1);
    side(images.width).saturating_mul(side(images.height))
}

/// A rejected configuration, naming the field.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConfigError {
    #[error("the train config must be a mapping")]
    NotAMapping,
    #[error("train config field `{field}`: {message}")]
    Field { field: String, message: String },
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn presets_resolve_and_are_valid() {
        for preset in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            let c = TrainConfig::preset(preset);
            c.validate().unwrap();
            let raw = json!({ "preset": serde_json::to_value(preset).unwrap() });
            assert_eq!(TrainConfig::resolve(&raw).unwrap(), c);
        }
        let paper = TrainConfig::preset(Preset::Paper);
        assert_eq!(
            (paper.trunk_width, paper.tau, paper.sequence_length),
            (512, 8, 8)
        );
        assert_eq!(
            TrainConfig::resolve(&serde_json::Value::Null)
                .unwrap()
                .preset,
            Preset::Balanced
        );
    }

    #[test]
    fn overrides_apply_and_round_trip() {
        let raw = json!({"preset": "fast", "iterations": 50, "motion_context": "pose",
                         "learning_rates": {"non_rigid": 0.01}});
        let c = TrainConfig::resolve(&raw).unwrap();
        assert_eq!(c.iterations, 50);
        assert_eq!(c.motion_context, MotionContext::Pose);
        assert_eq!(c.learning_rates.non_rigid, 0.01);
        assert_eq!(c.learning_rates.rotation, 1e-3);
        assert_eq!(c.trunk_width, 64);
        // Resolving the resolved config changes nothing (the key is stable).
        let again = TrainConfig::resolve(&serde_json::to_value(&c).unwrap()).unwrap();
        assert_eq!(again, c);
    }

    #[test]
    fn errors_name_the_field() {
        let cases = [
            (json!({"iterations": 0}), "iterations"),
            (json!({"motion_context": "everything"}), "motion_context"),
            (json!({"learning_rates": {"typo": 1.0}}), "learning_rates"),
            (json!({"unknown_field": 1}), "unknown_field"),
            (json!({"sh_degree": 4}), "sh_degree"),
            (json!({"lpips_weight": 0.1}), "lpips_weights"),
            (json!({"lpips_weight": -0.1}), "lpips_weight"),
            (json!({"lpips_net": "resnet"}), "lpips_net"),
            (json!({"lpips_weights": 3}), "lpips_weights"),
            (json!({"preset": "slow"}), "preset"),
            (json!({"scale_min": 0.0}), "scale_min"),
            // Values that passed validation and then aborted (issue 16).
            (json!({"sequence_length": 100_000}), "sequence_length"),
            (json!({"tau": 4_000_000_000u64}), "tau"),
            (json!({"trunk_width": 100_000_000}), "trunk_width"),
            (json!({"max_gaussians": 1_000_000_000}), "max_gaussians"),
            (json!({"checkpoint_every": 0}), "checkpoint_every"),
            (json!({"densify_interval": 0}), "densify_interval"),
            (json!({"sh_degree_interval": 0}), "sh_degree_interval"),
            (json!({"prune_opacity": 1.5}), "prune_opacity"),
            (
                json!({"learning_rates": {"opacity": -0.05}}),
                "learning_rates.opacity",
            ),
            (
                json!({"learning_rates": {"non_rigid": -1e-3}}),
                "learning_rates.non_rigid",
            ),
            (
                json!({"learning_rates": {"network_decay": 0.0}}),
                "learning_rates.network_decay",
            ),
            (
                json!({"learning_rates": {"adam_eps": 0.0}}),
                "learning_rates.adam_eps",
            ),
            (json!({"background": "green"}), "background"),
            (json!({"background": [0.0, 0.0, 0.0]}), "background"),
            (json!({"background": null}), "background"),
            (json!({"hull_init": {"frames": 0}}), "hull_init.frames"),
            (json!({"hull_init": {"voxel": 1e-6}}), "hull_init.voxel"),
            (
                json!({"hull_init": {"min_distance": -1.0}}),
                "hull_init.min_distance",
            ),
            (json!({"hull_init": {"voxels": 0.01}}), "voxels"),
        ];
        for (raw, field) in cases {
            let err = TrainConfig::resolve(&raw).unwrap_err().to_string();
            assert!(err.contains(field), "{raw} gave `{err}`");
        }
        assert_eq!(
            TrainConfig::resolve(&json!([1])),
            Err(ConfigError::NotAMapping)
        );
    }

    /// `device` is the compute crate's `DeviceChoice`, spelled as before (`auto`, `cpu`,
    /// `gpu`: the resolved config, and so the key, is unchanged); an unknown name is an error
    /// naming the field, the value and the choices.
    #[test]
    fn device_is_spelled_as_before_and_unknown_names_are_errors() {
        for (text, choice) in [
            ("auto", DeviceChoice::Auto),
            ("cpu", DeviceChoice::Cpu),
            ("gpu", DeviceChoice::Gpu),
        ] {
            let c = TrainConfig::resolve(&json!({"device": text})).unwrap();
            assert_eq!(c.device, choice);
            assert_eq!(serde_json::to_value(&c).unwrap()["device"], json!(text));
        }
        assert_eq!(TrainConfig::preset(Preset::Fast).device, DeviceChoice::Auto);
        let err = TrainConfig::resolve(&json!({"device": "cuda"}))
            .unwrap_err()
            .to_string();
        for part in ["device", "cuda", "auto", "cpu", "gpu"] {
            assert!(err.contains(part), "`{err}` lacks {part}");
        }
    }

    #[test]
    fn memory_estimate_counts_the_gaussians_and_the_trunk() {
        let mut c = TrainConfig::preset(Preset::Fast);
        let (gaussians, width, depth) = (20_000u64, 64u64, 3u64);
        let per_gaussian = 59 * 32 + width * depth * 8 + 4 * 2 * 24;
        assert_eq!(
            c.memory_estimate_bytes(),
            gaussians * per_gaussian + width * width * depth * 32
        );
        // Within the bounds, the estimate against the machine catches what would not fit.
        c.max_gaussians = MAX_GAUSSIANS;
        c.trunk_width = MAX_TRUNK_WIDTH;
        assert!(c.memory_estimate_bytes() > 1 << 39);
        if seqavatar_engine::memory_budget_bytes()
            .unwrap()
            .is_some_and(|m| m < 1 << 39)
        {
            let err = c.validate().unwrap_err().to_string();
            assert!(err.contains("max_gaussians") && err.contains("GB"), "{err}");
        }
    }

    #[test]
    fn lpips_fields_resolve_and_default_off() {
        for preset in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            let c = TrainConfig::preset(preset);
            assert!(!c.lpips_enabled() && c.lpips_weights.is_none());
            assert_eq!(
                (c.lpips_net, c.lpips_input()),
                (LpipsNet::Vgg, LpipsInput::Unit)
            );
        }
        let raw = json!({"lpips_weight": 0.1, "lpips_weights": "weights/lpips_alex.safetensors",
                         "lpips_net": "alex", "lpips_unnormalised_input": true});
        let c = TrainConfig::resolve(&raw).unwrap();
        assert!(c.lpips_enabled());
        assert_eq!(c.lpips_net, LpipsNet::Alex);
        assert_eq!(c.lpips_input(), LpipsInput::UnitAsSigned);
        assert_eq!(
            c.lpips_weights.as_deref(),
            Some(std::path::Path::new("weights/lpips_alex.safetensors"))
        );
        assert_eq!(
            TrainConfig::resolve(&serde_json::to_value(&c).unwrap()).unwrap(),
            c
        );
        // A weights file with weight 0 is allowed (and unused).
        let c = TrainConfig::resolve(&json!({"lpips_weights": "absent.safetensors"})).unwrap();
        assert!(!c.lpips_enabled());
    }

    #[test]
    fn background_options_resolve_and_draw() {
        for preset in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            assert_eq!(TrainConfig::preset(preset).background, Background::Black);
        }
        for (name, background) in [
            ("black", Background::Black),
            ("white", Background::White),
            ("random", Background::Random),
        ] {
            let c = TrainConfig::resolve(&json!({ "background": name })).unwrap();
            assert_eq!(c.background, background);
            assert_eq!(serde_json::to_value(&c).unwrap()["background"], json!(name));
        }
        // Fixed colours draw nothing from the stream; random draws three uniforms from it.
        let mut rng = crate::rng::Rng::new(5);
        assert_eq!(Background::Black.draw(&mut rng), [0.0; 3]);
        assert_eq!(Background::White.draw(&mut rng), [1.0; 3]);
        assert_eq!(rng.state(), crate::rng::Rng::new(5).state());
        let mut expected = crate::rng::Rng::new(5);
        let first = Background::Random.draw(&mut rng);
        assert_eq!(
            first,
            [
                expected.next_f64(),
                expected.next_f64(),
                expected.next_f64()
            ]
        );
        let second = Background::Random.draw(&mut rng);
        assert_ne!(first, second);
        assert!(first.iter().chain(&second).all(|c| (0.0..1.0).contains(c)));
        assert_eq!(Background::Random.render_colour(), [0.0; 3]);
    }

    #[test]
    fn scales_follow_the_motion_context() {
        let mut c = TrainConfig::preset(Preset::Paper);
        assert_eq!(c.effective_scales(&[24, 42, 33]).unwrap(), vec![42, 33, 24]);
        c.motion_context = MotionContext::Velocity;
        assert_eq!(c.effective_scales(&[24, 42, 33]).unwrap(), vec![24]);
        c.scales = vec![5];
        assert!(
            c.effective_scales(&[24])
                .unwrap_err()
                .to_string()
                .contains("scale 5")
        );
        assert!(MotionContext::Pose < MotionContext::Skeleton);
        assert!(!MotionContext::None.has_non_rigid() && MotionContext::Pose.has_non_rigid());
    }
}
