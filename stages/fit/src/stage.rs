//! The `fit` stage kind: configuration, run, and its picture.
//!
//! Output arrays and attributes: `seqavatar_schema::fit`, where they are written and read.

use anyhow::Context;
use serde::{Deserialize, Serialize};

use seqavatar_engine::{
    ConfigError, EntryReader, PictureKind, PictureOptions, StageContext, StageKind,
};

use crate::evidence::{EvidenceSources, Silhouettes, choose_tracks, track_name};
use crate::keypoints::{KeypointObservations, KeypointWeights, refine_with_keypoints};
use crate::refine::{
    joint_jitter, joint_positions, mean_distance, refine_sequence, vertex_velocity_error,
};
use crate::smooth::SmoothingPlan;
use seqavatar_engine::picture;
use seqavatar_schema::body::BodySequence;
use seqavatar_schema::fit::{Jitter, SilhouetteIou, TrackVerdicts};
use seqavatar_schema::ingest::{Keypoints3d, read_body_model, read_keypoints_3d};

/// What the stage does with the input fits. In YAML a bare `off` reads as the boolean
/// `false`; that is accepted as `off` too.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FitMode {
    /// Pass the fits through unchanged (no solve).
    Off,
    /// Data term (stay close to the input fit) plus temporal term, per track.
    #[default]
    Smooth,
    /// Smooth mode's terms plus the ingest entry's 3D keypoints, solved jointly over all
    /// frames ([`crate::keypoints`]).
    Keypoints,
}

impl<'de> Deserialize<'de> for FitMode {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Name(String),
            Flag(bool),
        }
        const MODES: &[&str] = &["off", "smooth", "keypoints"];
        match Raw::deserialize(deserializer)? {
            Raw::Flag(false) => Ok(Self::Off),
            Raw::Flag(true) => Err(D::Error::custom(
                "`true` is not a fit mode; expected one of off, smooth, keypoints",
            )),
            Raw::Name(name) => match name.as_str() {
                "off" => Ok(Self::Off),
                "smooth" => Ok(Self::Smooth),
                "keypoints" => Ok(Self::Keypoints),
                other => Err(D::Error::unknown_variant(other, MODES)),
            },
        }
    }
}

/// The `fit` stage configuration (all fields optional in the YAML).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FitConfig {
    pub mode: FitMode,
    /// Expected error of an input joint rotation, degrees; `null` (the default): estimated
    /// per track from the fits themselves ([`crate::smooth`], "Weights from the data").
    pub rotation_noise_deg: Option<f64>,
    /// Expected angular acceleration of a joint, degrees per frame squared; `null`:
    /// estimated per track.
    pub rotation_acceleration_deg: Option<f64>,
    /// Expected error of an input translation, metres; `null`: estimated.
    pub translation_noise_m: Option<f64>,
    /// Expected acceleration of the translation, metres per frame squared; `null`:
    /// estimated.
    pub translation_acceleration_m: Option<f64>,
    /// Scale of the Cauchy kernel on acceleration residuals, in standard deviations: much
    /// larger jumps are treated as genuine (a flip, a teleport) and kept sharp.
    pub robust_threshold: f64,
    /// Levenberg-Marquardt iteration limit per track (per sequence in keypoints mode).
    pub max_iterations: usize,
    /// Expected error of a 3D keypoint position, metres (keypoints mode).
    pub keypoint_noise_m: f64,
}

impl Default for FitConfig {
    fn default() -> Self {
        let w = SmoothingPlan::default();
        Self {
            mode: FitMode::Smooth,
            rotation_noise_deg: None,
            rotation_acceleration_deg: None,
            translation_noise_m: None,
            translation_acceleration_m: None,
            robust_threshold: w.robust_threshold,
            max_iterations: w.max_iterations,
            keypoint_noise_m: 0.02,
        }
    }
}

impl FitConfig {
    /// The solver's plan in radians (fixed values, or per-track estimates).
    pub fn plan(&self) -> SmoothingPlan {
        SmoothingPlan {
            rotation_noise: self.rotation_noise_deg.map(f64::to_radians),
            rotation_acceleration: self.rotation_acceleration_deg.map(f64::to_radians),
            translation_noise: self.translation_noise_m,
            translation_acceleration: self.translation_acceleration_m,
            robust_threshold: self.robust_threshold,
            max_iterations: self.max_iterations,
        }
    }
}

/// The keypoints `mode: keypoints` uses, from what the ingest entry at `location` holds;
/// errors name the entry and the modes that work without keypoints.
pub fn keypoint_observations(
    location: &str,
    keypoints: Option<Keypoints3d>,
    num_joints: usize,
) -> anyhow::Result<KeypointObservations> {
    let keypoints = keypoints.ok_or_else(|| {
        anyhow::anyhow!(
            "entry {location}: fit `mode: keypoints` needs 3D keypoints (arrays `keypoints_3d`, `keypoints_3d_confidence`) and this ingest entry has none; `mode: smooth` and `mode: off` work without them"
        )
    })?;
    KeypointObservations::new(&keypoints, num_joints).map_err(|e| {
        anyhow::anyhow!(
            "entry {location}: 3D keypoints: {e}; `mode: smooth` and `mode: off` work without keypoints"
        )
    })
}

/// Judges the refined fit by the evidence of the ingest entry ([`crate::evidence`]): keeps
/// the input fit of every track whose evidence got worse, records the evidence before and
/// after and the per-track verdicts in the output entry, and says what it kept.
fn judge_tracks(
    ctx: &mut StageContext<'_>,
    ingest: &EntryReader,
    model: &seqavatar_core::body::BodyModel,
    input: &BodySequence,
    refined: &BodySequence,
) -> anyhow::Result<BodySequence> {
    let location = ingest.location();
    let started = std::time::Instant::now();
    let silhouettes = Silhouettes::read(ingest)?;
    // Keypoints are evidence wherever they name joints; entries without them (or with
    // unmapped ones) are judged by the silhouettes alone.
    let keypoints = read_keypoints_3d(ingest)?
        .and_then(|k| KeypointObservations::new(&k, model.num_joints()).ok())
        .filter(|k| k.num_frames == input.num_frames);
    let sources = EvidenceSources {
        model,
        silhouettes: silhouettes.as_ref(),
        keypoints: keypoints.as_ref(),
    };
    if !sources.any() {
        ctx.log(&format!(
            "entry {location} has neither images nor joint keypoints: the refined fit is kept unjudged"
        ));
        return Ok(refined.clone());
    }
    let before = sources
        .evidence(input)
        .with_context(|| format!("entry {location}: evidence of the input fit"))?;
    let (output, verdicts) = choose_tracks(&sources, input, refined)
        .with_context(|| format!("entry {location}: judging the refined tracks"))?;
    let verdicts = TrackVerdicts(verdicts);
    let after = sources
        .evidence(&output)
        .with_context(|| format!("entry {location}: evidence of the output fit"))?;
    let j = input.num_joints;
    let kept: Vec<String> = verdicts
        .0
        .iter()
        .enumerate()
        .filter(|(_, v)| v.kept_input)
        .map(|(track, _)| track_name(track, j))
        .collect();
    let out = ctx.output();
    verdicts.write(out)?;
    out.set_attribute("tracks_kept_input", serde_json::to_value(&kept)?)?;
    let mut message = String::from("evidence");
    if let Some(s) = &silhouettes {
        let per_view = SilhouetteIou {
            before: s.per_view_mean(&before.iou),
            after: s.per_view_mean(&after.iou),
        };
        per_view.write(out)?;
        let (b, a) = (
            before.mean_iou().unwrap_or(f64::NAN),
            after.mean_iou().unwrap_or(f64::NAN),
        );
        out.set_attribute("mean_silhouette_iou_before", b.into())?;
        out.set_attribute("mean_silhouette_iou_after", a.into())?;
        message += &format!(
            ": body silhouette vs masks IoU {b:.5} -> {a:.5} (mean of {} images; per view {})",
            s.images.len(),
            per_view
                .before
                .iter()
                .zip(&per_view.after)
                .map(|(b, a)| format!("{b:.4}->{a:.4}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    if let (Some(b), Some(a)) = (before.keypoint_error(), after.keypoint_error()) {
        out.set_attribute("keypoint_distance_before", b.into())?;
        out.set_attribute("keypoint_distance_after", a.into())?;
        message += &format!(
            "; mean keypoint distance {:.2} -> {:.2} mm",
            b * 1e3,
            a * 1e3
        );
    }
    message += &format!(" ({:.2} s)", started.elapsed().as_secs_f64());
    ctx.log(&message);
    if kept.is_empty() {
        ctx.log(&format!(
            "every refined track did no harm to the evidence ({} tracks)",
            verdicts.0.len()
        ));
    } else {
        ctx.log(&format!(
            "kept the input fit of {} of {} tracks, whose evidence got worse when refined: {}",
            kept.len(),
            verdicts.0.len(),
            kept.join(", ")
        ));
    }
    Ok(output)
}

/// The stage kind.
pub struct FitStage;

/// Bump whenever the code changes the result.
const VERSION: u32 = 3;

impl StageKind for FitStage {
    type Config = FitConfig;

    fn kind(&self) -> &'static str {
        "fit"
    }

    fn version(&self) -> u32 {
        VERSION
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &["ingest"]
    }

    fn check_inputs(
        &self,
        _config: &FitConfig,
        inputs: &[seqavatar_engine::StageInput<'_>],
    ) -> Result<(), String> {
        seqavatar_engine::require_one_input_of_each(inputs, &["ingest"])
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<FitConfig, ConfigError> {
        let config: FitConfig = seqavatar_engine::parse_config(raw)?;
        if !(config.keypoint_noise_m > 0.0 && config.keypoint_noise_m.is_finite()) {
            return Err(ConfigError::at_key(
                "keypoint_noise_m",
                format!(
                    "must be positive and finite, got {}",
                    config.keypoint_noise_m
                ),
            ));
        }
        if let Err(e) = config.plan().validate() {
            // Name the YAML field: the error names the solver's field.
            let field = match &e {
                crate::smooth::SmoothError::BadWeight { name, .. } => match *name {
                    "rotation_noise" => "rotation_noise_deg",
                    "rotation_acceleration" => "rotation_acceleration_deg",
                    "translation_noise" => "translation_noise_m",
                    "translation_acceleration" => "translation_acceleration_m",
                    other => other,
                },
                _ => "mode",
            };
            return Err(ConfigError::at_key(field, e.to_string()));
        }
        Ok(config)
    }

    fn run(&self, config: &FitConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        let ingest = ctx.input("ingest")?.clone();
        let input = BodySequence::read(&ingest, "body")?;
        let model = read_body_model(&ingest)?;
        let (output, betas_averaged) = match config.mode {
            FitMode::Off => (input.clone(), false),
            FitMode::Smooth => {
                let started = std::time::Instant::now();
                let (refined, summary) =
                    refine_sequence(&input, &config.plan()).with_context(|| {
                        format!("entry {}: refining the body fits", ingest.location())
                    })?;
                ctx.log(&format!(
                    "smoothed {} frames x {} joints in {:.2} s: energy {:.4e} -> {:.4e}, at most {} iterations per track",
                    input.num_frames,
                    input.num_joints,
                    started.elapsed().as_secs_f64(),
                    summary.energy_before,
                    summary.energy_after,
                    summary.max_iterations_used
                ));
                (refined, summary.betas_averaged)
            }
            FitMode::Keypoints => {
                let observations = keypoint_observations(
                    ingest.location(),
                    read_keypoints_3d(&ingest)?,
                    model.num_joints(),
                )?;
                let started = std::time::Instant::now();
                let (refined, summary) = refine_with_keypoints(
                    &model,
                    &input,
                    &observations,
                    &config.plan(),
                    &KeypointWeights {
                        noise: config.keypoint_noise_m,
                    },
                )
                .with_context(|| {
                    format!(
                        "entry {}: refining the body fits against 3D keypoints",
                        ingest.location()
                    )
                })?;
                ctx.log(&format!(
                    "keypoint fit of {} frames x {} joints ({} keypoints per frame) in {:.2} s, {} iterations: energy {:.4e} -> {:.4e}, mean keypoint distance {:.2} -> {:.2} mm",
                    input.num_frames,
                    input.num_joints,
                    summary.keypoints_used,
                    started.elapsed().as_secs_f64(),
                    summary.refine.max_iterations_used,
                    summary.refine.energy_before,
                    summary.refine.energy_after,
                    summary.keypoint_distance_before * 1e3,
                    summary.keypoint_distance_after * 1e3,
                ));
                (refined, summary.refine.betas_averaged)
            }
        };
        if betas_averaged {
            ctx.log(
                "per-frame betas differed: replaced by their mean (shape is shared per subject)",
            );
        }
        let output = if config.mode == FitMode::Off {
            output
        } else {
            judge_tracks(ctx, &ingest, &model, &input, &output)?
        };
        output.write(ctx.output(), &model)?;

        let (f, j) = (input.num_frames, input.num_joints);
        let joints_before = joint_positions(&model, &input)?;
        let joints_after = joint_positions(&model, &output)?;
        let out = ctx.output();
        let jitter = Jitter {
            before: joint_jitter(&joints_before, f, j),
            after: joint_jitter(&joints_after, f, j),
        };
        jitter.write(out)?;
        let mean = |v: &[f64]| {
            if v.is_empty() {
                0.0
            } else {
                v.iter().sum::<f64>() / v.len() as f64
            }
        };
        let (mb, ma) = (mean(&jitter.before), mean(&jitter.after));
        out.set_attribute("mode", serde_json::to_value(config.mode)?)?;
        out.set_attribute("mean_jitter_before", mb.into())?;
        out.set_attribute("mean_jitter_after", ma.into())?;
        ctx.log(&format!("mean joint jitter {mb:.3e} -> {ma:.3e} m/frame^2"));

        if ingest.has_array("gt_body_pose") {
            let truth = BodySequence::read(&ingest, "gt_body")?;
            anyhow::ensure!(
                truth.num_frames == f && truth.num_joints == j,
                "entry {}: gt_ arrays have {} frames x {} joints, the fits {f} x {j}",
                ingest.location(),
                truth.num_frames,
                truth.num_joints
            );
            let joints_truth = joint_positions(&model, &truth)?;
            let je_before = mean_distance(&joints_before, &joints_truth);
            let je_after = mean_distance(&joints_after, &joints_truth);
            let ve_before = vertex_velocity_error(&model, &input, &truth)?;
            let ve_after = vertex_velocity_error(&model, &output, &truth)?;
            out.set_attribute("joint_error_before", je_before.into())?;
            out.set_attribute("joint_error_after", je_after.into())?;
            out.set_attribute("velocity_error_before", ve_before.into())?;
            out.set_attribute("velocity_error_after", ve_after.into())?;
            ctx.log(&format!(
                "against ground truth: joint error {:.2} -> {:.2} mm, vertex velocity error {:.3} -> {:.3} mm/frame",
                je_before * 1e3,
                je_after * 1e3,
                ve_before * 1e3,
                ve_after * 1e3
            ));
        }
        Ok(())
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![
            PictureKind {
                name: "jitter",
                description: "per-frame joint jitter before (blue) and after (orange) refinement; options: width, height",
            },
            PictureKind {
                name: "evidence",
                description: "per-view body silhouette vs masks IoU before (blue) and after (orange) refinement; options: width, height",
            },
        ]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        if !matches!(picture, "jitter" | "evidence") {
            return Err(seqavatar_engine::unknown_picture(self, picture));
        }
        let unknown = options.unknown_keys(&["width", "height"]);
        anyhow::ensure!(
            unknown.is_empty(),
            "picture {picture}: unknown options {unknown:?} (known: width, height)"
        );
        let width = options.get_u64("width", 800)?.clamp(64, 8192) as u32;
        let height = options.get_u64("height", 300)?.clamp(48, 8192) as u32;
        let (before, after) = if picture == "jitter" {
            let jitter = Jitter::read(entry)?;
            (jitter.before, jitter.after)
        } else {
            let iou = SilhouetteIou::read(entry)?.ok_or_else(|| {
                anyhow::anyhow!(
                    "entry {}: picture {picture} needs array `silhouette_iou_before`, which this fit entry does not have (mode off, or an ingest entry without images)",
                    entry.location()
                )
            })?;
            (iou.before, iou.after)
        };
        Ok(picture::line_plot(width, height, &[before, after]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::glam::DVec3;

    #[test]
    fn keypoint_mode_errors_name_the_entry_and_the_modes_that_work() {
        let message = keypoint_observations("cache/ingest/abc", None, 24)
            .unwrap_err()
            .to_string();
        for part in [
            "cache/ingest/abc",
            "mode: keypoints",
            "mode: smooth",
            "mode: off",
        ] {
            assert!(message.contains(part), "{message}");
        }
        // Keypoints whose joint correspondence is unknown (DNA-Rendering).
        let unmapped = Keypoints3d {
            joints: vec![None; 3],
            positions: vec![DVec3::ZERO; 6],
            confidence: vec![1.0; 6],
        };
        let message = keypoint_observations("cache/ingest/abc", Some(unmapped), 24)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("cache/ingest/abc")
                && message.contains("none of the 3 keypoints")
                && message.contains("mode: smooth"),
            "{message}"
        );
        // A NaN keypoint that claims confidence.
        let mut bad = Keypoints3d {
            joints: vec![Some(0), None, Some(2)],
            positions: vec![DVec3::ONE; 6],
            confidence: vec![1.0; 6],
        };
        bad.positions[5] = DVec3::new(0.0, f64::NAN, 0.0);
        let message = keypoint_observations("e", Some(bad.clone()), 24)
            .unwrap_err()
            .to_string();
        assert!(message.contains("frame 1 keypoint 2"), "{message}");
        // ... is ignored with confidence 0 (documented in crate::keypoints).
        bad.confidence[5] = 0.0;
        let used = keypoint_observations("e", Some(bad), 24).unwrap();
        assert_eq!(used.joints, vec![0, 2]);
        assert_eq!(used.confidence, vec![1.0, 1.0, 1.0, 0.0]);
    }

    #[test]
    fn config_rejects_a_bad_keypoint_noise() {
        let error = FitStage
            .resolve_config(&serde_json::json!({"mode": "keypoints", "keypoint_noise_m": 0.0}))
            .unwrap_err();
        assert!(error.to_string().contains("keypoint_noise_m"), "{error}");
        let ok = FitStage
            .resolve_config(&serde_json::json!({"mode": "keypoints"}))
            .unwrap();
        assert_eq!(ok.keypoint_noise_m, 0.02);
        // YAML reads a bare `off` as `false`.
        let off = FitStage
            .resolve_config(&serde_json::json!({"mode": false}))
            .unwrap();
        assert_eq!(serde_json::to_value(off.mode).unwrap(), "off");
        for bad in [serde_json::json!(true), serde_json::json!("fast")] {
            let error = FitStage
                .resolve_config(&serde_json::json!({ "mode": bad }))
                .unwrap_err();
            assert!(error.to_string().contains("smooth"), "{error}");
        }
    }
}
