//! The `train` stage kind: configuration, the resumable run, outputs, pictures.
//!
//! Inputs: an `ingest` entry (cameras, images, split, body model), a `motion` entry (windows)
//! and optionally a `fit` entry (refined body parameters; without one the ingest fits are
//! used).
//!
//! The run checkpoints into the stage's work folder every `checkpoint_every` iterations
//! ([`crate::checkpoint`]) and resumes from the newest checkpoint when it starts again with
//! the same key. Divergence stops it with an error naming the iteration and the tensor; the
//! last good checkpoint stays.
//!
//! With `lpips_weight > 0` the LPIPS weights file (`lpips_weights`) is an external file: its
//! content enters the key.
//!
//! Output: the arrays and attributes of `seqavatar_schema::train` (docs/schema.md).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use serde_json::json;

use seqavatar_avatar::avatar::TrainedAvatar;
use seqavatar_avatar::sequence::{History, SequenceRenderer};
use seqavatar_compute::backend::Backend;
use seqavatar_compute::nn::gpu::MatmulPath;
use seqavatar_engine::picture;
use seqavatar_engine::{
    ConfigError, EntryReader, EntryWriter, PictureKind, PictureOptions, StageContext, StageKind,
};

use crate::checkpoint;
use crate::config::TrainConfig;
use crate::data::TrainingData;
use crate::trainer::{LossCurve, Phase, Trainer};
use seqavatar_schema::ingest::{IngestImages, PlannedIngest};

/// The stage kind.
pub struct TrainStage;

/// Bump whenever the code changes the result (6: the networks train and render in f32;
/// 7: train-image PSNR, input RMS and first-layer weight norms per input block; 8: the cpu
/// backend splats in f32 on the lane path, and on the gpu backend the held-out PSNR renders
/// with the gpu copy of the per-Gaussian networks, as eval does; 9: on the gpu backend the
/// held-out PSNR renders each image on the device).
///
/// `precision` did not bump it: the f32 path is unchanged, so on machines
/// without tensor cores every output is as before, and a config without `precision` keeps
/// its key (the field is serialised only where set). An explicit `precision` enters the key
/// through the canonical config. `mixed`, the default, changes results only on adapters
/// with tensor cores, which the key does not name, as it names no adapter (`device: auto`
/// is keyed the same on a gpu and on `cpu`; the entry's `backend` attribute says which ran).
const VERSION: u32 = 9;

/// Training images (spread evenly over the training split) scored for the train-image PSNR.
pub const TRAIN_PSNR_IMAGES: usize = 64;

pub use seqavatar_avatar::config::PROTOCOL_BACKGROUND;

/// Checks that the config's motion window (`sequence_length` x the largest scale it uses)
/// stays inside what the ingest entry holds ([`MotionTrack::check_window`]); motion contexts
/// without skeleton motion gather no window.
///
/// [`MotionTrack::check_window`]: seqavatar_schema::motion::MotionTrack::check_window
pub fn check_motion_window(config: &TrainConfig, data: &TrainingData) -> anyhow::Result<()> {
    if !config.motion_context.has_skeleton_motion() {
        return Ok(());
    }
    let scales = config
        .effective_scales(&data.motion.scales)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let slots = data.motion.slots(&scales)?;
    data.motion.check_window(config.sequence_length, &slots)
}

/// Held-out PSNR of one rendered image by the evaluation protocol of docs/method.md: rendered
/// pixels outside the bound box set to the background, ground-truth pixels outside the mask
/// set to the background (the colour the image was rendered on), PSNR over the whole image.
pub fn protocol_psnr(
    colour: &[f64],
    target: &[u8],
    mask: &[u8],
    width: usize,
    height: usize,
    bound: Option<crate::losses::Rect>,
    background: [f64; 3],
) -> f64 {
    let mut sum = 0.0;
    for row in 0..height {
        for col in 0..width {
            let inside =
                bound.is_some_and(|b| col >= b.x0 && col < b.x1 && row >= b.y0 && row < b.y1);
            let foreground = mask[row * width + col] > 127;
            for c in 0..3 {
                let i = 3 * (row * width + col) + c;
                let rendered = if inside { colour[i] } else { background[c] };
                let truth = if foreground {
                    f64::from(target[i]) / 255.0
                } else {
                    background[c]
                };
                sum += (rendered - truth).powi(2);
            }
        }
    }
    let mse = sum / (3 * width * height).max(1) as f64;
    -10.0 * mse.max(1e-20).log10()
}

impl StageKind for TrainStage {
    type Config = TrainConfig;

    fn kind(&self) -> &'static str {
        "train"
    }

    fn version(&self) -> u32 {
        VERSION
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &["ingest", "fit", "motion"]
    }

    fn check_inputs(
        &self,
        config: &TrainConfig,
        inputs: &[seqavatar_engine::StageInput<'_>],
    ) -> Result<(), String> {
        seqavatar_engine::require_one_input_of_each(inputs, &["ingest", "motion"])?;
        // The images join the memory estimate where the ingest config determines them.
        let ingest = inputs
            .iter()
            .find(|input| input.kind == "ingest")
            .expect("checked above");
        let Some(images) = PlannedIngest::of(ingest)?.images else {
            return Ok(());
        };
        match seqavatar_engine::memory_budget_bytes()? {
            Some(budget) => config
                .check_memory(Some(&images), budget)
                .map_err(|e| format!("{e} (images from input {})", ingest.name)),
            None => Ok(()),
        }
    }

    fn planned(&self, config: &TrainConfig) -> serde_json::Value {
        let motion_context = serde_json::to_value(config.motion_context)
            .ok()
            .and_then(|name| name.as_str().map(str::to_owned))
            .unwrap_or_else(|| format!("{:?}", config.motion_context));
        serde_json::to_value(seqavatar_schema::train::PlannedTrain {
            motion_context,
            renders_from_motion_entry: config.motion_context.has_skeleton_motion(),
        })
        .unwrap_or_default()
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<TrainConfig, ConfigError> {
        TrainConfig::resolve(raw).map_err(|e| match e {
            crate::config::ConfigError::Field { field, message } => {
                let top = field.split(['.', '[']).next().unwrap_or("").to_owned();
                if top.is_empty() {
                    ConfigError::new(vec![], message)
                } else {
                    ConfigError::at_key(&top, format!("{field}: {message}"))
                }
            }
            other => ConfigError::new(vec![], other.to_string()),
        })
    }

    fn external_files(&self, config: &TrainConfig) -> anyhow::Result<Vec<PathBuf>> {
        Ok(if config.lpips_enabled() {
            config.lpips_weights.iter().cloned().collect()
        } else {
            Vec::new()
        })
    }

    fn run(&self, config: &TrainConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        let ingest = ctx.input("ingest")?.clone();
        let motion = ctx.input("motion")?.clone();
        let fit = ctx.inputs().iter().find(|i| i.kind() == "fit").cloned();
        let params_entry = fit.as_ref().unwrap_or(&ingest);
        // Refused before any image is read when the run would not fit the memory budget.
        if let Some(budget) = seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)? {
            let images = IngestImages::of_entry(&ingest)?;
            config
                .check_memory(Some(&images), budget)
                .map_err(anyhow::Error::msg)?;
        }
        let mut data = TrainingData::read(&ingest, params_entry, &motion, config.resolution_scale)?;
        // The rig every reader of the trained avatar builds (`AvatarConfig::rig`).
        data.rig = config.avatar().rig(data.rig.model.clone())?;
        check_motion_window(config, &data).with_context(|| {
            format!(
                "train config against ingest entry {} (via motion entry {})",
                ingest.location(),
                motion.location()
            )
        })?;
        let backend = Backend::select(config.device)
            .with_context(|| format!("config `device: {}`", config.device))?;
        ctx.log(&format!("backend: {}", backend.describe()));
        // The path every network built for this run takes (`NnGpu::for_context` makes the
        // same choice from the same context and precision).
        ctx.log(&MatmulPath::of_backend(&backend, config.networks_precision()).describe());
        log_lpips_setting(ctx, config);
        let mut trainer = start_or_resume(ctx, config, &data, &backend)?;
        let timing = train_to_the_end(ctx, config, &mut trainer)?;
        if timing.ran > 0 {
            log_iteration_costs(ctx, &trainer, &timing)?;
        }
        let avatar = trainer.avatar()?;
        // On the gpu the avatar and the sequence are uploaded once and each image is
        // rendered on the device (one read-back per image).
        let motion = avatar
            .config
            .motion_context
            .has_skeleton_motion()
            .then(|| data.motion.clone());
        let mut frames = SequenceRenderer::new(&avatar, &backend, data.params.clone(), motion)
            .context("the trained avatar's renderer")?;

        // Held-out PSNR on the test split, and on training images by the same protocol.
        let mut scorer = ProtocolScorer {
            config,
            data: &data,
            avatar: &avatar,
            frames: &mut frames,
        };
        let test = data.split(1);
        let test_psnr = scorer.psnrs(&test)?;
        let train_split = data.split(0);
        let train_picks: Vec<usize> = (0..TRAIN_PSNR_IMAGES.min(train_split.len()))
            .map(|k| train_split[k * train_split.len() / TRAIN_PSNR_IMAGES.min(train_split.len())])
            .collect();
        let train_psnr = scorer.psnrs(&train_picks)?;
        let train_image_psnr = (!train_psnr.is_empty())
            .then(|| train_psnr.iter().sum::<f64>() / train_psnr.len() as f64);
        let diagnostics = network_diagnostics(ctx, config, &data, &trainer, &train_split)?;
        let test_mean = if test_psnr.is_empty() {
            f64::NAN
        } else {
            test_psnr.iter().sum::<f64>() / test_psnr.len() as f64
        };
        let tail = (trainer.curve.psnr.len() / 10).max(1);
        let final_train_psnr = trainer.curve.psnr[trainer.curve.psnr.len() - tail..]
            .iter()
            .sum::<f64>()
            / tail as f64;
        let TrainingTiming {
            resumed_from,
            wall,
            ran,
            rate,
        } = timing;
        ctx.log(&format!(
            "{} iterations in {wall:.1} s ({rate:.2} it/s), {} Gaussians, train PSNR {final_train_psnr:.2} dB, held-out PSNR {test_mean:.2} dB over {} test images, train-image PSNR {} over {} training images (same protocol)",
            ran,
            avatar.gaussians.len(),
            test_psnr.len(),
            train_image_psnr.map_or_else(|| "-".to_owned(), |p| format!("{p:.2} dB")),
            train_psnr.len()
        ));

        let out = ctx.output();
        avatar.write(out, data.extent, &data.body_model_kind)?;
        out.set_attribute("config", serde_json::to_value(config)?)?;
        write_curves_and_cameras(out, &trainer.curve, &ingest)?;
        let t = test.len() as u64;
        out.write_array("test_psnr", &["image"], &[t], &[t.max(1)], &test_psnr)?;
        let indices: Vec<u32> = test.iter().map(|&i| i as u32).collect();
        out.write_array("test_image", &["image"], &[t], &[t.max(1)], &indices)?;
        out.set_attribute("wall_seconds", json!(wall))?;
        out.set_attribute("iterations_per_second", json!(rate))?;
        out.set_attribute("resumed_from", json!(resumed_from))?;
        out.set_attribute("final_train_psnr", json!(final_train_psnr))?;
        out.set_attribute(
            "test_psnr_mean",
            if test_mean.is_finite() {
                json!(test_mean)
            } else {
                serde_json::Value::Null
            },
        )?;
        out.set_attribute("train_image_psnr_mean", json!(train_image_psnr))?;
        out.set_attribute("train_image_psnr_images", json!(train_psnr.len()))?;
        out.set_attribute("input_rms", serde_json::to_value(&diagnostics.input_rms)?)?;
        out.set_attribute(
            "first_layer_norms",
            serde_json::to_value(&diagnostics.first_layer_norms.blocks)?,
        )?;
        out.set_attribute("backend", json!(backend.describe()))?;
        out.set_attribute("gaussians", json!(avatar.gaussians.len()))?;
        Ok(())
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![PictureKind {
            name: "loss_curve",
            description: "training loss (blue) and train PSNR / 10 (orange) per iteration; options: width, height, smooth (moving-average window, iterations)",
        }]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        match picture {
            "loss_curve" => draw_loss_curve(entry, options),
            _ => Err(seqavatar_engine::unknown_picture(self, picture)),
        }
    }
}

/// Logs whether the LPIPS loss is on, and with what.
fn log_lpips_setting(ctx: &StageContext<'_>, config: &TrainConfig) {
    if config.lpips_enabled() {
        ctx.log(&format!(
            "LPIPS loss on: weight {}, {} trunk from {}, inputs {}",
            config.lpips_weight,
            config.lpips_net.name(),
            config
                .lpips_weights
                .as_ref()
                .map_or_else(String::new, |p| p.display().to_string()),
            if config.lpips_unnormalised_input {
                "in [0, 1] unmapped (the authors' code)"
            } else {
                "mapped to [-1, 1]"
            }
        ));
    } else {
        ctx.log(
            "LPIPS loss off: lpips_weight is 0 (set lpips_weight and lpips_weights to enable it)",
        );
    }
}

/// The trainer resumed from the newest good checkpoint of the work folder, else a fresh one.
/// A damaged checkpoint is deleted and the previous one used (or training restarts), so one
/// bad file never blocks the stage.
fn start_or_resume<'d>(
    ctx: &StageContext<'_>,
    config: &TrainConfig,
    data: &'d TrainingData,
    backend: &Backend,
) -> anyhow::Result<Trainer<'d>> {
    let work = ctx.work_dir().join("checkpoints");
    let (resumed, notes) = checkpoint::resume_newest_good(&work, |ckpt| {
        Trainer::resume(config.clone(), data, backend.clone(), &ckpt)
    })?;
    for note in &notes {
        ctx.warn(note);
    }
    Ok(match resumed {
        Some(t) => {
            ctx.log(&format!("resumed from iteration {}", t.iteration));
            t
        }
        None => {
            if !notes.is_empty() {
                ctx.warn("no usable checkpoint left: training starts over");
            }
            let started = std::time::Instant::now();
            let trainer = Trainer::new(config.clone(), data, backend.clone())?;
            if config.hull_init.is_some() {
                let added = trainer.state.len() - data.rig.vertex_count();
                ctx.log(&format!(
                    "hull_init: {added} Gaussians added where the masks' visual hull leaves the \
                     body template, every Gaussian coloured from the images ({:.1} s)",
                    started.elapsed().as_secs_f64()
                ));
            }
            trainer
        }
    })
}

/// How long this run of the training loop took.
#[derive(Clone, Copy)]
struct TrainingTiming {
    /// The iteration the loop started from (0, or a checkpoint's).
    resumed_from: u64,
    /// Wall seconds of the loop.
    wall: f64,
    /// Iterations run.
    ran: u64,
    /// Iterations per second.
    rate: f64,
}

/// Runs the training loop to `config.iterations` behind a progress bar, saving a checkpoint
/// every `checkpoint_every` iterations.
fn train_to_the_end(
    ctx: &StageContext<'_>,
    config: &TrainConfig,
    trainer: &mut Trainer<'_>,
) -> anyhow::Result<TrainingTiming> {
    let work = ctx.work_dir().join("checkpoints");
    let resumed_from = trainer.iteration;
    let total = u64::from(config.iterations);
    let bar = ctx.progress_bar(total, "training");
    bar.set_position(trainer.iteration);
    let started = Instant::now();
    while trainer.iteration < total {
        let stats = trainer.step()?;
        let elapsed = started.elapsed().as_secs_f64();
        let rate = (trainer.iteration - resumed_from) as f64 / elapsed.max(1e-9);
        bar.set_position(trainer.iteration);
        let lpips = if trainer.lpips_active() {
            format!(", LPIPS {:.4}", stats.lpips)
        } else {
            String::new()
        };
        bar.set_message(format!(
            "{}: training, loss {:.4}{lpips}, PSNR {:.2}, {} Gaussians, {:.2} it/s",
            ctx.stage_name(),
            stats.total,
            stats.psnr,
            stats.gaussians,
            rate
        ));
        if let Some(report) = stats.densified {
            ctx.log(&format!(
                "iteration {}: densified ({} cloned, {} split, {} pruned) -> {} Gaussians",
                stats.iteration, report.cloned, report.split, report.pruned, report.count
            ));
        }
        if trainer
            .iteration
            .is_multiple_of(u64::from(config.checkpoint_every))
            && trainer.iteration < total
        {
            checkpoint::save(&work, &trainer.checkpoint()?)?;
        }
    }
    bar.finish_and_clear();
    let wall = started.elapsed().as_secs_f64();
    let ran = trainer.iteration - resumed_from;
    let rate = ran as f64 / wall.max(1e-9);
    Ok(TrainingTiming {
        resumed_from,
        wall,
        ran,
        rate,
    })
}

/// Logs the milliseconds per iteration of each phase, and how often AIAP searched its
/// neighbours afresh.
fn log_iteration_costs(
    ctx: &StageContext<'_>,
    trainer: &Trainer<'_>,
    timing: &TrainingTiming,
) -> anyhow::Result<()> {
    let (wall, ran) = (timing.wall, timing.ran);
    let times = trainer.phase_times();
    let per_phase = Phase::ALL
        .iter()
        .map(|&phase| {
            format!(
                "{} {:.1}",
                phase.name(),
                1e3 * times.seconds(phase) / ran as f64
            )
        })
        .collect::<Vec<_>>()
        .join(", ");
    // The rest of the loop's wall time: checkpoints, progress and logging.
    let other = 1e3 * (wall - times.total()).max(0.0) / ran as f64;
    ctx.log(&format!(
        "ms per iteration: {per_phase}, checkpoints and logging {other:.1}"
    ));
    let (searches, calls) = trainer.aiap_neighbour_searches()?;
    if calls > 0 {
        ctx.log(&format!(
            "AIAP neighbours: {searches} full searches in {calls} iterations (the others reused their candidate lists)"
        ));
    }
    Ok(())
}

/// Renders images of the training data with the trained avatar and scores them by the
/// evaluation protocol.
struct ProtocolScorer<'a> {
    config: &'a TrainConfig,
    data: &'a TrainingData,
    avatar: &'a TrainedAvatar,
    /// The avatar's renderer over the training sequence (on the device on the gpu).
    frames: &'a mut SequenceRenderer,
}

impl ProtocolScorer<'_> {
    /// The protocol PSNR of each image of `indices`.
    fn psnrs(&mut self, indices: &[usize]) -> anyhow::Result<Vec<f64>> {
        indices.iter().map(|&i| self.psnr(i)).collect()
    }

    /// The protocol PSNR of image `index`, within its padded bound box.
    fn psnr(&mut self, index: usize) -> anyhow::Result<f64> {
        let data = self.data;
        let record = &data.images[index];
        let camera = &data.cameras[record.view];
        let image = self.frames.render(
            self.avatar,
            record.frame,
            History::Own,
            camera,
            PROTOCOL_BACKGROUND,
        )?;
        let bound = data.padded_bound(index, self.config.bound_padding);
        Ok(protocol_psnr(
            &image.colour,
            &record.rgb,
            &record.mask,
            camera.width as usize,
            camera.height as usize,
            bound,
            PROTOCOL_BACKGROUND,
        ))
    }
}

/// Diagnostics of the non-rigid network's inputs.
struct NetworkDiagnostics {
    input_rms: crate::diagnostics::InputRms,
    first_layer_norms: crate::diagnostics::FirstLayerNorms,
}

/// The RMS of the network inputs over the training frames and the norms of the first-layer
/// weights per input block, logged.
fn network_diagnostics(
    ctx: &StageContext<'_>,
    config: &TrainConfig,
    data: &TrainingData,
    trainer: &Trainer<'_>,
    train_split: &[usize],
) -> anyhow::Result<NetworkDiagnostics> {
    let mut train_frames: Vec<usize> = train_split.iter().map(|&i| data.images[i].frame).collect();
    train_frames.sort_unstable();
    train_frames.dedup();
    let input_rms = crate::diagnostics::input_rms(
        &config.avatar(),
        &trainer.scales,
        &data.motion,
        &data.params,
        &train_frames,
    )?;
    let first_layer_norms = match &trainer.networks {
        Some(networks) => crate::diagnostics::first_layer_norms(networks, &trainer.scales)?,
        None => crate::diagnostics::FirstLayerNorms::default(),
    };
    if let Some(pose) = input_rms.pose {
        ctx.log(&format!(
            "input RMS over {} training frames: pose {pose:.3}, skeleton motion {:?}, vertex velocity {:?} (scales {:?})",
            train_frames.len(),
            input_rms.skeleton_motion,
            input_rms.vertex_velocity,
            input_rms.scales
        ));
    }
    for block in &first_layer_norms.blocks {
        ctx.log(&format!(
            "first-layer weights of {} ({}, {} rows): norm {:.4}, RMS {:.5}",
            block.block, block.layer, block.rows, block.norm, block.rms
        ));
    }
    Ok(NetworkDiagnostics {
        input_rms,
        first_layer_norms,
    })
}

/// The loss curves, and the cameras of the ingest entry (its resolution), so that renders
/// and checks of the avatar need only this entry.
fn write_curves_and_cameras(
    out: &EntryWriter,
    curve: &LossCurve,
    ingest: &EntryReader,
) -> anyhow::Result<()> {
    let iterations = curve.total.len() as u64;
    for name in LossCurve::NAMES {
        let values = curve.get(name).expect("known curve");
        out.write_array(
            &format!("loss_{name}"),
            &["iteration"],
            &[iterations],
            &[iterations.max(1)],
            values,
        )?;
    }
    seqavatar_schema::ingest::copy_cameras(out, ingest, false)
}

/// Moving average over a trailing window of `window` values.
fn smooth(values: &[f64], window: usize) -> Vec<f64> {
    let window = window.max(1);
    let mut sum = 0.0;
    let mut out = Vec::with_capacity(values.len());
    for i in 0..values.len() {
        sum += values[i];
        if i >= window {
            sum -= values[i - window];
        }
        out.push(sum / (i + 1).min(window) as f64);
    }
    out
}

/// The loss-curve plot of a `train` entry.
pub fn draw_loss_curve(
    entry: &EntryReader,
    options: &PictureOptions,
) -> anyhow::Result<image::RgbImage> {
    let unknown = options.unknown_keys(&["width", "height", "smooth"]);
    anyhow::ensure!(
        unknown.is_empty(),
        "picture loss_curve: unknown options {unknown:?}"
    );
    let total = entry.read::<f64>("loss_total")?.data;
    let psnr = entry.read::<f64>("loss_psnr")?.data;
    let window = options
        .get_u64("smooth", (total.len() as u64 / 50).max(1))?
        .max(1) as usize;
    let width = options.get_u64("width", 900)?.clamp(64, 8192) as u32;
    let height = options.get_u64("height", 400)?.clamp(48, 8192) as u32;
    let psnr_scaled: Vec<f64> = smooth(&psnr, window).iter().map(|p| p / 10.0).collect();
    Ok(picture::line_plot(
        width,
        height,
        &[smooth(&total, window), psnr_scaled],
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `precision: f32 | mixed` resolves into the config and the avatar config the entry
    /// stores; absent, it is `mixed`, and the resolved config, the stored avatar config and
    /// so the key are what they were before the setting existed; a bad value is an error
    /// naming the field and the choices.
    #[test]
    fn precision_parses_defaults_to_mixed_and_leaves_keys_alone() {
        use seqavatar_compute::nn::Precision;
        use seqavatar_engine::key::{KeyMaterial, stage_key};
        for (text, precision) in [("f32", Precision::F32), ("mixed", Precision::Mixed)] {
            let resolved = TrainStage
                .resolve_config(&json!({"preset": "fast", "precision": text}))
                .unwrap();
            let resolved = serde_json::to_value(resolved).unwrap();
            assert_eq!(resolved["precision"], json!(text));
            let config = TrainConfig::resolve(&resolved).unwrap();
            assert_eq!(config.networks_precision(), precision);
            assert_eq!(config.avatar().precision, Some(precision));
            assert_eq!(config.avatar().networks_precision(), precision);
        }
        let absent = TrainStage
            .resolve_config(&json!({"preset": "fast"}))
            .unwrap();
        let absent = serde_json::to_value(absent).unwrap();
        assert!(absent.get("precision").is_none(), "{absent}");
        let config = TrainConfig::resolve(&absent).unwrap();
        assert_eq!(config.networks_precision(), Precision::Mixed);
        let avatar = serde_json::to_value(config.avatar()).unwrap();
        assert!(avatar.get("precision").is_none(), "{avatar}");
        // The key of the `fast` preset at version 9 as it was before `precision` existed
        // (commit 8f18229). A change to the preset or to a field's default changes it
        // (update it then); a new optional field must not.
        let key = stage_key(&KeyMaterial {
            kind: "train",
            version: 9,
            config: &absent,
            input_keys: &[],
            external_digests: &[],
        });
        assert_eq!(
            key,
            "20baf867c35335e4bcf8330fcd9833bd34bccceda594dbab4cd134548c65e7e4"
        );
        let error = TrainStage
            .resolve_config(&json!({"precision": "f16"}))
            .unwrap_err()
            .to_string();
        for part in ["precision", "f16", "f32", "mixed"] {
            assert!(error.contains(part), "`{error}` lacks {part}");
        }
    }

    #[test]
    fn protocol_psnr_closed_form() {
        // 2 x 2 image, one foreground pixel rendered off by 0.1 in every channel, the rest
        // exact: MSE = 0.01 * 3 / 12.
        let target = vec![51u8; 12];
        let mask = vec![255, 0, 0, 0];
        let mut colour = vec![0.0; 12];
        for c in 0..3 {
            colour[c] = 51.0 / 255.0 + 0.1;
        }
        let bound = Some(crate::losses::Rect {
            x0: 0,
            y0: 0,
            x1: 1,
            y1: 1,
        });
        let p = protocol_psnr(&colour, &target, &mask, 2, 2, bound, [0.0; 3]);
        let expected = -10.0 * (0.01f64 * 3.0 / 12.0).log10();
        assert!((p - expected).abs() < 1e-9, "{p} vs {expected}");
        // On white: the render's pixels outside the bound box and the truth's pixels outside
        // the mask are both white, so the error is unchanged; a render that leaves the
        // background black inside the bound box would not be.
        for c in 3..12 {
            colour[c] = 0.7;
        }
        let p = protocol_psnr(&colour, &target, &mask, 2, 2, bound, [1.0; 3]);
        assert!((p - expected).abs() < 1e-9, "{p} vs {expected}");
        let wide = Some(crate::losses::Rect {
            x0: 0,
            y0: 0,
            x1: 2,
            y1: 1,
        });
        let p = protocol_psnr(&colour, &target, &mask, 2, 2, wide, [1.0; 3]);
        let expected = -10.0 * ((0.01f64 * 3.0 + 0.09 * 3.0) / 12.0).log10();
        assert!((p - expected).abs() < 1e-9, "{p} vs {expected}");
    }

    #[test]
    fn smoothing_is_a_trailing_mean() {
        assert_eq!(smooth(&[1.0, 3.0, 5.0, 7.0], 2), vec![1.0, 2.0, 4.0, 6.0]);
    }
}
