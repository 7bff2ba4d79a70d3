//! Training on a tiny synthetic scene through the real ingest and motion stages: the loss
//! falls, checkpoints resume exactly (also after really killing a process), the gpu
//! backend matches cpu, divergence names iteration and tensor, densification keeps every
//! column consistent across real steps.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use seqavatar_avatar::TrainedAvatar;
use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_compute::lpips::LpipsNet;
use seqavatar_engine::{
    EntryId, EntryReader, LocalStore, Pipeline, Registry, RunOptions, Store, run,
};
use seqavatar_train::TrainStage;
use seqavatar_train::checkpoint;
use seqavatar_train::config::{Background, TrainConfig};
use seqavatar_train::data::TrainingData;
use seqavatar_train::trainer::{Divergence, Phase, Trainer};

const UPSTREAM: &str = r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 3, frames: 4, width: 40, height: 40, supersample: 1, garment: false, body_grid_spacing: 0.05}
      past_frames: 0
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {scales: [1, 2], knn: 4}
"#;

/// JSON, which is also a YAML flow mapping.
/// `precision: f32`: the gpu runs are compared with `cpu` at f32's tolerances; the
/// tensor-core path (`mixed` on adapters that have it) is tested against f32 in the compute
/// crate (`nn::gpu` tests).
const TRAIN_CONFIG: &str = r#"{"preset": "fast", "device": "cpu", "precision": "f32", "seed": 3, "iterations": ITERATIONS, "motion_context": "none", "pose_refiner": false, "lbs_offsets": false, "checkpoint_every": 10, "resolution_scale": 1.0, "sh_degree": 1, "sh_degree_interval": 20, "learning_rates": {"position_initial": 0.0016, "position_final": 0.000016}}"#;

fn pipeline_text(iterations: u32) -> String {
    format!(
        "{UPSTREAM}  - name: train\n    kind: train\n    inputs: [ingest, motion]\n    config: {}\n",
        TRAIN_CONFIG.replace("ITERATIONS", &iterations.to_string())
    )
}

/// A synthetic recording whose used frames start at frame 3, with `past_frames` before them.
fn late_start_upstream(past_frames: usize) -> String {
    format!(
        r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {{kind: synthetic, cameras: 2, frames: 6, width: 24, height: 24, supersample: 1, garment: false, body_grid_spacing: 0.05}}
      split: {{train_frames: {{start: 3, step: 1}}, test_frames: {{start: 3, step: 2}}}}
      past_frames: {past_frames}
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {{scales: [1, 2], knn: 4}}
"#
    )
}

/// A train config whose motion window (sequence_length 2 x the `skeleton` context's smallest
/// scale 1 = 2 frames) reaches further back than the ingest entry holds (past_frames 1, and
/// the recording starts before it) fails before training with an error naming both values;
/// with past_frames 2 it fits, and with past_frames 4 ingest reaches the recording's first
/// frame (windows clamp there).
#[test]
fn a_window_reaching_past_the_ingested_frames_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let train = TRAIN_CONFIG.replace("ITERATIONS", "2").replace(
        r#""motion_context": "none""#,
        r#""motion_context": "skeleton", "sequence_length": 2"#,
    );
    let text = format!(
        "{}  - name: train\n    kind: train\n    inputs: [ingest, motion]\n    config: {train}\n",
        late_start_upstream(1)
    );
    let error = format!(
        "{:#}",
        run_pipeline(&cache, &text).expect_err("window too long")
    );
    assert!(
        error.contains("reaches 2 frames back") && error.contains("past_frames = 1"),
        "{error}"
    );
    assert!(error.contains("sequence_length 2"), "{error}");
    let config = TrainConfig::resolve(&serde_json::from_str(&train).unwrap()).unwrap();
    for (past_frames, starts_recording, fits) in
        [(1, false, false), (2, false, true), (4, true, true)]
    {
        let reports = run_pipeline(&cache, &late_start_upstream(past_frames)).unwrap();
        let ingest = entry(&cache, &reports, "ingest");
        let motion = entry(&cache, &reports, "motion");
        let data = TrainingData::read(&ingest, &ingest, &motion, 1.0).unwrap();
        assert_eq!(data.motion.axis.starts_recording, starts_recording);
        assert_eq!(data.motion.axis.past_frames, past_frames);
        let checked = seqavatar_train::stage::check_motion_window(&config, &data);
        assert_eq!(
            checked.is_ok(),
            fits,
            "past_frames {past_frames}: {checked:?}"
        );
    }
}

fn registry() -> Registry {
    seqavatar_registry::registry()
}

fn run_pipeline(cache: &Path, text: &str) -> anyhow::Result<Vec<seqavatar_engine::StageReport>> {
    let registry = registry();
    let store = LocalStore::open(cache)?;
    let pipeline = Pipeline::parse(text, Path::new("test.yaml"), &registry, &[])?;
    run(&pipeline, &registry, &store, &RunOptions::default())
}

fn entry(cache: &Path, reports: &[seqavatar_engine::StageReport], name: &str) -> EntryReader {
    let store = LocalStore::open(cache).unwrap();
    let report = reports.iter().find(|r| r.name == name).unwrap();
    store
        .open_entry(&EntryId::new(&report.kind, &report.key))
        .unwrap()
}

/// Upstream entries (ingest, motion) of the tiny scene and the data a run reads.
fn tiny_data(cache: &Path, iterations: u32) -> (TrainingData, TrainConfig) {
    let reports = run_pipeline(cache, UPSTREAM).unwrap();
    let ingest = entry(cache, &reports, "ingest");
    let motion = entry(cache, &reports, "motion");
    let raw: serde_json::Value =
        serde_json::from_str(&TRAIN_CONFIG.replace("ITERATIONS", &iterations.to_string())).unwrap();
    let config = TrainConfig::resolve(&raw).unwrap();
    let data = TrainingData::read(&ingest, &ingest, &motion, config.resolution_scale).unwrap();
    (data, config)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn tiny_training_runs_as_a_stage_and_its_loss_falls() {
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let reports = run_pipeline(dir.path(), &pipeline_text(60)).unwrap();
    let train = entry(dir.path(), &reports, "train");
    let loss = train.read::<f64>("loss_total").unwrap().data;
    assert_eq!(loss.len(), 60);
    let (first, last) = (mean(&loss[..5]), mean(&loss[55..]));
    eprintln!(
        "tiny stage run: loss {first:.4} -> {last:.4} in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    assert!(last < first / 2.0, "loss {first} -> {last}");
    let test_psnr = train.read::<f64>("test_psnr").unwrap().data;
    assert!(!test_psnr.is_empty() && test_psnr.iter().all(|p| p.is_finite()));
    let mean_attr = train.attribute("test_psnr_mean").unwrap().as_f64().unwrap();
    assert!((mean_attr - mean(&test_psnr)).abs() < 1e-9);
    // The entry carries the ingest cameras.
    let ingest = entry(dir.path(), &reports, "ingest");
    assert_eq!(
        seqavatar_schema::ingest::read_cameras(&train).unwrap(),
        seqavatar_schema::ingest::read_cameras(&ingest).unwrap()
    );
    // The stored avatar renders, and its pictures draw.
    let avatar = TrainedAvatar::load(&train).unwrap();
    assert_eq!(
        avatar.gaussians.len() as u64,
        train.attribute("gaussians").unwrap().as_u64().unwrap()
    );
    let plot = seqavatar_engine::StageKind::draw_picture(
        &TrainStage,
        &train,
        "loss_curve",
        &Default::default(),
    )
    .unwrap();
    assert_eq!((plot.width(), plot.height()), (900, 400));
}

#[test]
fn stored_avatar_renders_exactly_like_the_trainer() {
    stored_avatar_renders_like_the_trainer(None);
}

/// Diffused skinning weights are part of the avatar: the stage trains with them and every
/// reader of its entry skins with the same weights.
#[test]
fn stored_avatar_with_diffused_skinning_renders_exactly_like_the_trainer() {
    stored_avatar_renders_like_the_trainer(Some(0.05));
}

fn stored_avatar_renders_like_the_trainer(skinning_smoothing: Option<f64>) {
    let dir = tempfile::tempdir().unwrap();
    let (mut data, mut config) = tiny_data(dir.path(), 5);
    config.skinning_smoothing = skinning_smoothing;
    let template = data.rig.template_weights.clone();
    data.rig = config.avatar().rig(data.rig.model.clone()).unwrap();
    assert_eq!(
        data.rig.template_weights == template,
        skinning_smoothing.is_none()
    );
    let mut trainer = Trainer::new(config, &data, cpu_backend()).unwrap();
    for _ in 0..5 {
        trainer.step().unwrap();
    }
    let avatar = trainer.avatar().unwrap();
    let record = &data.images[0];
    let inputs = avatar
        .frame_inputs(&data.motion, &data.params[record.frame], record.frame)
        .unwrap();
    let camera = &data.cameras[record.view];
    let device = avatar.backend(cpu_backend()).unwrap();
    let direct = avatar.render(&inputs, camera, &device).unwrap();
    assert!(direct.alpha.iter().any(|a| *a > 0.5), "the body is visible");

    // The same 5 iterations as a stage: its entry loads and renders identically.
    let text = match skinning_smoothing {
        Some(sigma) => pipeline_text(5).replace(
            r#""lbs_offsets": false"#,
            &format!(r#""lbs_offsets": false, "skinning_smoothing": {sigma}"#),
        ),
        None => pipeline_text(5),
    };
    let reports = run_pipeline(dir.path(), &text).unwrap();
    let train = entry(dir.path(), &reports, "train");
    let loaded = TrainedAvatar::load(&train).unwrap();
    assert_eq!(loaded.gaussians, avatar.gaussians);
    assert_eq!(loaded.config, avatar.config);
    assert_eq!(loaded.rig.template_weights, data.rig.template_weights);
    assert_eq!(loaded.sh_degree, avatar.sh_degree);
    let again = loaded
        .render(&inputs, camera, &loaded.backend(cpu_backend()).unwrap())
        .unwrap();
    assert_eq!(again.colour, direct.colour);
    assert_eq!(again.alpha, direct.alpha);
}

#[test]
fn checkpoint_resume_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_data(dir.path(), 40);
    let mut straight = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    for _ in 0..12 {
        straight.step().unwrap();
    }
    let mut first = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    for _ in 0..7 {
        first.step().unwrap();
    }
    let ckpt_dir = dir.path().join("ckpt");
    checkpoint::save(&ckpt_dir, &first.checkpoint().unwrap()).unwrap();
    drop(first);
    let loaded = checkpoint::load_latest(&ckpt_dir).unwrap().unwrap();
    let mut resumed = Trainer::resume(config.clone(), &data, cpu_backend(), &loaded).unwrap();
    assert_eq!(resumed.iteration, 7);
    for _ in 0..5 {
        resumed.step().unwrap();
    }
    assert_eq!(resumed.state, straight.state);
    assert_eq!(resumed.curve, straight.curve);
    assert_eq!(resumed.rng.state(), straight.rng.state());
    // A different configuration refuses the checkpoint.
    let mut other = config;
    other.seed += 1;
    assert!(Trainer::resume(other, &data, cpu_backend(), &loaded).is_err());
}

/// With every network (multiscale context, pose refiner, LBS offsets): the network
/// parameters and their Adam moments resume exactly too.
#[test]
fn checkpoint_resume_is_exact_with_networks() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    config.motion_context = seqavatar_train::config::MotionContext::Multiscale;
    config.pose_refiner = true;
    config.lbs_offsets = true;
    config.trunk_width = 16;
    config.trunk_depth = 2;
    let mut straight = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    for _ in 0..6 {
        straight.step().unwrap();
    }
    let mut first = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    for _ in 0..3 {
        first.step().unwrap();
    }
    let ckpt_dir = dir.path().join("ckpt");
    checkpoint::save(&ckpt_dir, &first.checkpoint().unwrap()).unwrap();
    drop(first);
    let loaded = checkpoint::load_latest(&ckpt_dir).unwrap().unwrap();
    let mut resumed = Trainer::resume(config, &data, cpu_backend(), &loaded).unwrap();
    for _ in 0..3 {
        resumed.step().unwrap();
    }
    assert_eq!(resumed.state, straight.state);
    assert_eq!(resumed.curve, straight.curve);
    assert!(resumed.networks.is_some());
    assert!(
        resumed.networks == straight.networks,
        "network parameters differ"
    );
    assert!(
        resumed.checkpoint().unwrap() == straight.checkpoint().unwrap(),
        "Adam moments differ"
    );
}

/// Largest non-rigid centre and scale offsets of a fresh run's networks at frame 1.
fn initial_offsets(data: &TrainingData, config: &TrainConfig) -> (f64, f64) {
    use seqavatar_avatar::avatar::{deform, frame_pose, template_grid};
    let mut trainer = Trainer::new(config.clone(), data, cpu_backend()).unwrap();
    let avatar = trainer.avatar().unwrap();
    let inputs = avatar
        .frame_inputs(&data.motion, &data.params[1], 1)
        .unwrap();
    let networks = avatar.networks.as_ref();
    let posed = frame_pose(&avatar.rig, networks, &inputs.params).unwrap();
    let grid = template_grid(&avatar.rig);
    let d = deform(
        &avatar.rig,
        &grid,
        networks,
        &avatar.backend(cpu_backend()).unwrap(),
        &avatar.gaussians,
        &inputs,
        &posed.pose,
        &config.avatar(),
        0,
    )
    .unwrap();
    let moved = d
        .positions
        .iter()
        .zip(&avatar.gaussians.xyz)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let scaled = d.d_scales.iter().map(|s| s.abs()).fold(0.0, f64::max);
    (moved, scaled)
}

#[test]
fn fresh_non_rigid_network_starts_at_the_identity() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    config.motion_context = seqavatar_train::config::MotionContext::Multiscale;
    config.trunk_width = 16;
    config.trunk_depth = 2;
    let (moved, scaled) = initial_offsets(&data, &config);
    assert!(
        moved < 1e-3 && scaled < 1e-3,
        "offsets {moved} m, {scaled} m"
    );
    // The reference initialisation moves the Gaussians from the start.
    config.non_rigid_head_init = 0.0;
    let (moved, scaled) = initial_offsets(&data, &config);
    assert!(
        moved > 1e-2 || scaled > 1e-2,
        "offsets {moved} m, {scaled} m"
    );
}

#[test]
fn absurd_learning_rate_stops_with_iteration_and_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    config.learning_rates.position_initial = 1e308;
    config.learning_rates.position_final = 1e308;
    let mut trainer = Trainer::new(config, &data, cpu_backend()).unwrap();
    let err = trainer.step().unwrap_err();
    let divergence = err
        .downcast_ref::<Divergence>()
        .expect("a divergence error");
    assert_eq!(divergence.iteration, 1);
    assert_eq!(divergence.tensor, "gaussians/xyz");
    let text = err.to_string();
    assert!(
        text.contains("iteration 1") && text.contains("gaussians/xyz"),
        "{text}"
    );
}

#[test]
fn densification_keeps_columns_consistent_across_real_steps() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    config.densify = true;
    config.densify_from = 1;
    config.densify_until = 4;
    config.densify_interval = 2;
    config.densify_grad_threshold = 1e-9;
    config.max_gaussians = 100_000;
    let mut trainer = Trainer::new(config, &data, cpu_backend()).unwrap();
    let start = trainer.state.len();
    trainer.step().unwrap();
    let visible_before = trainer
        .state
        .values("grad_count")
        .unwrap()
        .iter()
        .filter(|c| **c > 0.0)
        .count();
    assert!(visible_before > 0);
    let stats = trainer.step().unwrap();
    let report = stats.densified.expect("iteration 2 densifies");
    assert_eq!(
        report.count,
        start + report.cloned + report.split - report.pruned,
        "a clone adds one, a split replaces its parent by two"
    );
    assert!(report.cloned + report.split > 0, "{report:?}");
    assert_eq!(trainer.state.len(), report.count);
    for column in &trainer.state.columns {
        assert_eq!(
            column.values.len(),
            column.width * report.count,
            "{}",
            column.name
        );
    }
    // Statistics restart; Adam moments of new Gaussians are zero; training continues.
    assert!(
        trainer
            .state
            .values("grad_count")
            .unwrap()
            .iter()
            .all(|c| *c == 0.0)
    );
    let moments = trainer.state.values("xyz.adam_v").unwrap();
    assert!(moments[3 * (report.count - 1)..].iter().all(|m| *m == 0.0));
    let next = trainer.step().unwrap();
    assert!(next.total.is_finite());
    assert_eq!(next.gaussians, report.count);
}

/// The `cpu` backend, as the train stage selects it.
fn cpu_backend() -> Backend {
    Backend::select(DeviceChoice::Cpu).unwrap()
}

/// The gpu backend on the software adapter allowed, or `None` (skipped, with the reason
/// printed) without one, except under `CI`, where that fails the test.
fn gpu_backend() -> Option<Backend> {
    seqavatar_compute::backend::test_support::gpu_test_backend()
}

#[test]
fn gpu_steps_match_cpu() {
    let Some(gpu) = gpu_backend() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_data(dir.path(), 40);
    let mut cpu = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    let mut gpu = Trainer::new(config, &data, gpu).unwrap();
    assert!(gpu.resident(), "the gpu backend trains on the device");
    gpu.set_log_every(1);
    for step in 0..4 {
        let a = cpu.step().unwrap();
        let b = gpu.step().unwrap();
        let relative = (a.total - b.total).abs() / a.total.abs();
        eprintln!(
            "step {step}: cpu loss {} gpu loss {} (relative {relative:e})",
            a.total, b.total
        );
        assert!(relative < 1e-3, "step {step}: {} vs {}", a.total, b.total);
    }
    gpu.sync().unwrap();
    // Norms, not elements: the device's f32 Adam turns a gradient rounded near zero into a
    // full step of either sign, so single centres may differ by a step.
    let initial = Trainer::new(cpu.config.clone(), &data, cpu_backend()).unwrap();
    let x0 = initial.state.values("xyz").unwrap();
    let xa = cpu.state.values("xyz").unwrap();
    let xb = gpu.state.values("xyz").unwrap();
    let norm = |x: &[f64], y: &[f64]| {
        x.iter()
            .zip(y)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let (moved, apart) = (norm(xa, x0), norm(xa, xb));
    eprintln!("centres: moved {moved:.3e}, apart {apart:.3e}");
    assert!(
        moved > 0.0 && apart <= 0.1 * moved,
        "centres {apart} apart, moved {moved}"
    );
}

/// With every network (multiscale context, pose refiner, LBS offsets; tiny sizes) from the
/// identity deformation (the default small head weights): on the gpu backend the whole
/// iteration runs on the device and a few steps follow the `cpu` run's losses closely.
#[test]
fn gpu_steps_with_networks_match_cpu() {
    networks_follow_cpu(1e-5, 1e-3, 1e-2, 0.5, 0.25);
}

/// The same from the reference initialisation (head weights at PyTorch's default: offsets of
/// centimetres to decimetres from step one, so every network's output and gradient matters
/// at once). Nearest template vertices of the moved centres then sit close to ties, which
/// f32 on the device and f64 on the host can resolve differently for a few Gaussians: the
/// runs stay within a few 1e-3 (a wrong gradient departs by far more within a few steps).
#[test]
fn gpu_steps_with_large_offsets_follow_cpu() {
    networks_follow_cpu(0.0, 1e-2, 1e-2, 0.5, 0.25);
}

/// Steps both backends with every network and compares the image terms and AIAP per step
/// (relative tolerances), then how far the trained parameters are apart relative to how
/// far they moved (`parameter_tolerance`: Adam turns an f32-rounded gradient near zero into
/// a full step of either sign, and the per-frame encoders' gradients are column sums over
/// every Gaussian that cancel to near zero, so those tensors drift apart by up to a third of
/// their motion in five steps; an unrelated gradient sends them about 1.4 times as far apart
/// as they moved, a sign error twice), and the canonical centres (`centre_tolerance`: their
/// gradient joins the non-rigid network's through the positional encoding's high
/// frequencies); prints the milliseconds per iteration of both.
fn networks_follow_cpu(
    head_init: f64,
    image_tolerance: f64,
    aiap_tolerance: f64,
    parameter_tolerance: f64,
    centre_tolerance: f64,
) {
    let Some(gpu) = gpu_backend() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    config.motion_context = seqavatar_train::config::MotionContext::Multiscale;
    config.trunk_width = 16;
    config.trunk_depth = 2;
    config.non_rigid_head_init = head_init;
    config.lbs_offsets = true;
    config.pose_refiner = true;
    let mut cpu = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    let mut gpu = Trainer::new(config, &data, gpu).unwrap();
    assert!(!cpu.resident());
    assert!(gpu.resident());
    gpu.set_log_every(1);
    let steps = 5;
    let (mut cpu_time, mut gpu_time) = (Duration::ZERO, Duration::ZERO);
    for step in 0..steps {
        let started = Instant::now();
        let a = cpu.step().unwrap();
        let cpu_elapsed = started.elapsed();
        let started = Instant::now();
        let b = gpu.step().unwrap();
        // The first step builds the splatting pipelines: left out of the timing.
        if step > 0 {
            cpu_time += cpu_elapsed;
            gpu_time += started.elapsed();
        }
        let relative = (a.total - b.total).abs() / a.total.abs();
        eprintln!(
            "step {step}: cpu loss {} gpu loss {} (relative {relative:e}); l1 {} / {}, mask {} / {}, dssim {} / {}, aiap {} / {}",
            a.total, b.total, a.l1, b.l1, a.mask_mse, b.mask_mse, a.dssim, b.dssim, a.aiap, b.aiap
        );
        let image = |s: &seqavatar_train::trainer::IterationStats| s.total - s.aiap;
        let image_relative = (image(&a) - image(&b)).abs() / image(&a).abs();
        let aiap_relative = (a.aiap - b.aiap).abs() / a.aiap.abs();
        assert!(
            image_relative < image_tolerance,
            "step {step}: image terms {} vs {}",
            image(&a),
            image(&b)
        );
        assert!(
            aiap_relative < aiap_tolerance,
            "step {step}: aiap {} vs {}",
            a.aiap,
            b.aiap
        );
    }
    eprintln!(
        "ms per iteration with the non-rigid network: cpu {:.1}, gpu {:.1}",
        cpu_time.as_secs_f64() * 1e3 / f64::from(steps - 1),
        gpu_time.as_secs_f64() * 1e3 / f64::from(steps - 1)
    );
    // The gpu run trained the networks on the device: they moved like the cpu run's.
    gpu.sync().unwrap();
    let (a, b) = (
        cpu.networks.as_ref().unwrap(),
        gpu.networks.as_ref().unwrap(),
    );
    let initial = Trainer::new(cpu.config.clone(), &data, cpu_backend()).unwrap();
    let start = initial.networks.as_ref().unwrap();
    // Norms, not elements: Adam turns an f32-rounded gradient near zero into a full step
    // of either sign, so single values may differ by a step.
    fn norm<T: Copy + Into<f64>>(x: &[T], y: &[T]) -> f64 {
        x.iter()
            .zip(y)
            .map(|(&a, &b)| (a.into() - b.into()).powi(2))
            .sum::<f64>()
            .sqrt()
    }
    for ((pa, pb), p0) in a
        .parameters()
        .iter()
        .zip(b.parameters())
        .zip(start.parameters())
    {
        assert_eq!(pa.name, pb.name);
        let moved = norm(pa.values, p0.values);
        let moved_gpu = norm(pb.values, p0.values);
        let apart = norm(pa.values, pb.values);
        eprintln!(
            "{}: moved {moved:.3e} (gpu {moved_gpu:.3e}), apart {apart:.3e}",
            pa.name
        );
        assert!(
            moved > 0.0 && moved_gpu > 0.0,
            "{}: a run did not train it",
            pa.name
        );
        assert!(
            apart <= parameter_tolerance * moved,
            "{}: gpu and cpu parameters {apart} apart, moved {moved}",
            pa.name
        );
    }
    // The centres likewise (the densification has not started: same Gaussians).
    let xa = cpu.state.values("xyz").unwrap();
    let xb = gpu.state.values("xyz").unwrap();
    let x0 = initial.state.values("xyz").unwrap();
    let (moved, apart) = (norm(xa, x0), norm(xa, xb));
    eprintln!("centres: moved {moved:.3e}, apart {apart:.3e}");
    assert!(
        moved > 0.0 && apart <= centre_tolerance * moved,
        "centres {apart} apart, moved {moved}"
    );
}

/// The `paper` preset's steady-state iteration on the gpu backend reads nothing back and
/// uploads under 16 KiB (its per-iteration records), with the logged scalars read only
/// every `log_every` iterations.
#[test]
fn resident_paper_iteration_reads_nothing_back() {
    // A context of its own: the counters see this trainer's traffic only.
    let Some(gpu) = seqavatar_compute::backend::test_support::gpu_test_backend_alone() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (data, _) = tiny_data(dir.path(), 40);
    let mut config = TrainConfig::preset(seqavatar_train::config::Preset::Paper);
    config.device = DeviceChoice::Gpu;
    config.trunk_width = 32;
    config.sequence_length = 2;
    let traffic = |backend: &Backend| backend.transfers();
    let mut trainer = Trainer::new(config, &data, gpu.clone()).unwrap();
    assert!(trainer.resident());
    trainer.set_log_every(1000);
    for _ in 0..3 {
        trainer.step().unwrap();
    }
    let before = traffic(&gpu);
    let steps: u32 = 4;
    for _ in 0..steps {
        trainer.step().unwrap();
    }
    let moved = traffic(&gpu).since(&before);
    eprintln!(
        "paper preset, steady state: {} readbacks, {:.2} KiB up, {:.2} KiB down per iteration",
        moved.readbacks as f64 / f64::from(steps),
        moved.bytes_up as f64 / 1024.0 / f64::from(steps),
        moved.bytes_down as f64 / 1024.0 / f64::from(steps)
    );
    assert_eq!(moved.readbacks, 0, "{moved:?}");
    assert_eq!(moved.bytes_down, 0, "{moved:?}");
    assert!(
        moved.bytes_up < 16 * 1024 * u64::from(steps),
        "{} bytes up in {steps} iterations",
        moved.bytes_up
    );
    // Timed on the device (where the adapter has timestamps): every phase of the recorded
    // iteration but densification takes device time; reading the times reads the log.
    if trainer.time_device_phases().unwrap() {
        for _ in 0..2 {
            trainer.step().unwrap();
        }
        let times = trainer.device_phase_times().unwrap().expect("timing is on");
        assert_eq!(times.iterations(), 2);
        for phase in [Phase::Deform, Phase::Splat, Phase::Losses, Phase::Backward] {
            assert!(times.seconds(phase) > 0.0, "{phase:?}: {times:?}");
        }
        assert_eq!(times.seconds(Phase::Densify), 0.0);
    } else {
        eprintln!("device phase times skipped: the adapter has no timestamps inside encoders");
        for _ in 0..2 {
            trainer.step().unwrap();
        }
    }
    // Syncing reads the log and the state back, and the curve holds every iteration.
    trainer.sync().unwrap();
    assert_eq!(trainer.curve.total.len(), 9);
    assert!(
        trainer
            .curve
            .total
            .iter()
            .all(|v| v.is_finite() && *v > 0.0)
    );
}

/// A short training run on the gpu backend (the device-resident step) ends at the held-out
/// PSNR of the same run on `cpu` (same seed, same draws), within 0.1 dB, by the train
/// stage's protocol (`stage::protocol_psnr` on the test split).
#[test]
fn resident_training_matches_cpu_held_out_psnr() {
    let Some(gpu) = gpu_backend() else { return };
    let dir = tempfile::tempdir().unwrap();
    let iterations = 60;
    let (data, config) = tiny_data(dir.path(), iterations);
    let held_out = |backend: Backend| {
        let mut trainer = Trainer::new(config.clone(), &data, backend.clone()).unwrap();
        for _ in 0..iterations {
            trainer.step().unwrap();
        }
        let avatar = trainer.avatar().unwrap();
        // Rendered on the host: the comparison is of the two training steps.
        let device = avatar.backend(cpu_backend()).unwrap();
        let test = data.split(1);
        assert!(!test.is_empty());
        let psnr: Vec<f64> = test
            .iter()
            .map(|&i| {
                let record = &data.images[i];
                let inputs = avatar
                    .frame_inputs(&data.motion, &data.params[record.frame], record.frame)
                    .unwrap();
                let camera = &data.cameras[record.view];
                let background = seqavatar_avatar::config::PROTOCOL_BACKGROUND;
                let image = avatar
                    .render_on(&inputs, camera, &device, background)
                    .unwrap();
                let (w, h) = (camera.width as usize, camera.height as usize);
                let bound = record
                    .bound
                    .map(|b| seqavatar_train::trainer::pad_rect(b, config.bound_padding, w, h));
                seqavatar_train::stage::protocol_psnr(
                    &image.colour,
                    &record.rgb,
                    &record.mask,
                    w,
                    h,
                    bound,
                    background,
                )
            })
            .collect();
        mean(&psnr)
    };
    let (cpu, gpu) = (held_out(cpu_backend()), held_out(gpu));
    eprintln!("held-out PSNR after {iterations} iterations: cpu {cpu:.3} dB, gpu {gpu:.3} dB");
    assert!((cpu - gpu).abs() <= 0.1, "cpu {cpu} dB, gpu {gpu} dB");
}

/// A Gaussian cap below the template's vertex count (the starting Gaussians) is refused,
/// naming the field, instead of being silently exceeded.
#[test]
fn a_gaussian_cap_below_the_starting_count_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 10);
    let vertices = data.rig.vertex_count();
    config.max_gaussians = vertices - 1;
    let error = Trainer::new(config.clone(), &data, cpu_backend())
        .err()
        .expect("a cap below the template is refused")
        .to_string();
    assert!(
        error.contains("max_gaussians") && error.contains(&vertices.to_string()),
        "{error}"
    );
    config.max_gaussians = vertices;
    assert!(Trainer::new(config, &data, cpu_backend()).is_ok());
}

/// `hull_init` on the tiny scene in its skirt: Gaussians are added beside the template's,
/// at most `max_gaussians` of them, the template's Gaussians take their colours from the
/// images instead of the random draw, the cap on the total counts them, and training runs.
#[test]
fn hull_init_adds_gaussians_and_colours_the_template() {
    let dir = tempfile::tempdir().unwrap();
    let upstream = UPSTREAM.replace("garment: false", "garment: true");
    let reports = run_pipeline(dir.path(), &upstream).unwrap();
    let ingest = entry(dir.path(), &reports, "ingest");
    let motion = entry(dir.path(), &reports, "motion");
    let raw: serde_json::Value =
        serde_json::from_str(&TRAIN_CONFIG.replace("ITERATIONS", "3")).unwrap();
    let config = TrainConfig::resolve(&raw).unwrap();
    let data = TrainingData::read(&ingest, &ingest, &motion, config.resolution_scale).unwrap();
    let vertices = data.rig.vertex_count();
    let plain = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();

    let mut with_hull = config.clone();
    with_hull.hull_init = Some(seqavatar_train::hull::HullInit {
        max_gaussians: 40,
        ..Default::default()
    });
    let mut trainer = Trainer::new(with_hull.clone(), &data, cpu_backend()).unwrap();
    let added = trainer.state.len() - vertices;
    assert!((1..=40).contains(&added), "{added} Gaussians added");
    let sh = |t: &Trainer<'_>| t.state.values("sh").unwrap().to_vec();
    let stride = sh(&plain).len() / vertices;
    let (before, after) = (sh(&plain), sh(&trainer));
    let recoloured = (0..vertices)
        .filter(|v| before[v * stride..v * stride + 3] != after[v * stride..v * stride + 3])
        .count();
    assert!(
        recoloured > vertices / 2,
        "{recoloured} of {vertices} recoloured"
    );
    for _ in 0..3 {
        trainer.step().unwrap();
    }
    assert!(trainer.curve.total.iter().all(|l| l.is_finite()));

    with_hull.max_gaussians = vertices + added - 1;
    let error = Trainer::new(with_hull, &data, cpu_backend()).err().unwrap();
    assert!(error.to_string().contains("hull_init"), "{error}");
}

/// Child mode of the kill test: runs the pipeline in `SEQAVATAR_TRAIN_KILL_CACHE` (the
/// parent kills this process while it trains).
#[test]
fn kill_child() {
    let Some(cache) = std::env::var_os("SEQAVATAR_TRAIN_KILL_CACHE") else {
        return;
    };
    let iterations: u32 = std::env::var("SEQAVATAR_TRAIN_KILL_ITERATIONS")
        .unwrap()
        .parse()
        .unwrap();
    run_pipeline(Path::new(&cache), &pipeline_text(iterations)).unwrap();
}

fn find_checkpoints(root: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with("ckpt-") && !name.ends_with(".partial") {
                    found.push(p);
                } else {
                    stack.push(p);
                }
            }
        }
    }
    found
}

#[test]
fn killed_run_resumes_to_the_uninterrupted_result() {
    let iterations = 60u32;
    let killed = tempfile::tempdir().unwrap();
    let exe = std::env::current_exe().unwrap();
    let mut child = std::process::Command::new(exe)
        .args([
            "--exact",
            "kill_child",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env("SEQAVATAR_TRAIN_KILL_CACHE", killed.path())
        .env("SEQAVATAR_TRAIN_KILL_ITERATIONS", iterations.to_string())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        if !find_checkpoints(killed.path()).is_empty() {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the child finished before writing a checkpoint"
        );
        assert!(Instant::now() < deadline, "no checkpoint after 300 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let left = find_checkpoints(killed.path());
    assert!(!left.is_empty());
    // Resume in this process, and compare with an uninterrupted run.
    let reports = run_pipeline(killed.path(), &pipeline_text(iterations)).unwrap();
    let resumed = entry(killed.path(), &reports, "train");
    let from = resumed.attribute("resumed_from").unwrap().as_u64().unwrap();
    assert!(
        from > 0 && from < u64::from(iterations),
        "resumed from {from}"
    );
    let straight_dir = tempfile::tempdir().unwrap();
    let reports = run_pipeline(straight_dir.path(), &pipeline_text(iterations)).unwrap();
    let straight = entry(straight_dir.path(), &reports, "train");
    assert_eq!(
        straight.attribute("resumed_from").unwrap().as_u64(),
        Some(0)
    );
    for name in [
        "gaussian_xyz",
        "gaussian_sh",
        "gaussian_opacity",
        "gaussian_log_scale",
        "gaussian_rotation",
        "loss_total",
        "test_psnr",
    ] {
        let a = resumed.read::<f64>(name).unwrap();
        let b = straight.read::<f64>(name).unwrap();
        assert_eq!(a.shape, b.shape, "{name}");
        assert!(
            a.data == b.data,
            "{name} differs after resuming from {from}"
        );
    }
}

/// Seeded VGG weights in the converted-weights format, at `path`.
fn write_lpips_weights(path: &Path, seed: u64) {
    use seqavatar_compute::lpips::{LpipsNet, seeded::seeded_weights};
    seeded_weights(LpipsNet::Vgg, seed)
        .write_safetensors(path)
        .unwrap();
}

#[test]
fn lpips_loss_enters_the_total_and_the_gradient() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("lpips_vgg.safetensors");
    write_lpips_weights(&weights, 5);
    let (data, off) = tiny_data(dir.path(), 3);
    let mut on = off.clone();
    on.lpips_weight = 0.1;
    on.lpips_weights = Some(weights.clone());
    let mut without = Trainer::new(off.clone(), &data, cpu_backend()).unwrap();
    let mut with = Trainer::new(on.clone(), &data, cpu_backend()).unwrap();
    assert!(with.lpips_active() && !without.lpips_active());
    let started = Instant::now();
    let (a, b) = (without.step().unwrap(), with.step().unwrap());
    eprintln!(
        "one 40 x 40 step with the LPIPS loss: {:.2} s",
        started.elapsed().as_secs_f64()
    );
    // Same state and image before the first step: the forward terms agree, and the total
    // differs by exactly the weighted LPIPS term.
    assert_eq!(
        (a.l1, a.mask_mse, a.dssim, a.aiap),
        (b.l1, b.mask_mse, b.dssim, b.aiap)
    );
    assert_eq!(a.lpips, 0.0);
    assert!(b.lpips > 0.0 && b.lpips.is_finite(), "{b:?}");
    assert!(
        (b.total - a.total - 0.1 * b.lpips).abs() < 1e-12,
        "{} vs {} + 0.1 x {}",
        b.total,
        a.total,
        b.lpips
    );
    // Its gradient reaches the parameters.
    let moved = |t: &Trainer<'_>| t.state.column("xyz").unwrap().values.clone();
    assert_ne!(moved(&without), moved(&with));
    for _ in 0..2 {
        let stats = with.step().unwrap();
        assert!(stats.lpips > 0.0 && stats.total.is_finite());
    }
    assert_eq!(with.curve.lpips.len(), 3);
    assert!(with.curve.lpips.iter().all(|v| *v > 0.0));
    assert!(without.curve.lpips.iter().all(|v| *v == 0.0));
    // A checkpoint carries the curve and resumes.
    let resumed = Trainer::resume(on, &data, cpu_backend(), &with.checkpoint().unwrap()).unwrap();
    assert_eq!(resumed.curve, with.curve);
}

#[test]
fn lpips_weights_file_errors_name_the_file_and_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 3);
    config.lpips_weight = 0.1;
    let absent = dir.path().join("absent.safetensors");
    config.lpips_weights = Some(absent);
    let error = format!(
        "{:#}",
        Trainer::new(config.clone(), &data, cpu_backend())
            .err()
            .unwrap()
    );
    assert!(error.contains("absent.safetensors"), "{error}");
    // VGG weights read as AlexNet: the first AlexNet tensor has another shape.
    let weights = dir.path().join("vgg.safetensors");
    write_lpips_weights(&weights, 1);
    config.lpips_weights = Some(weights);
    config.lpips_net = seqavatar_compute::lpips::LpipsNet::Alex;
    let error = format!(
        "{:#}",
        Trainer::new(config.clone(), &data, cpu_backend())
            .err()
            .unwrap()
    );
    assert!(
        error.contains("vgg.safetensors") && error.contains("net.slice1.0.weight"),
        "{error}"
    );
    // AlexNet needs 31 px: a 40 px image scaled by 0.5 is too small, and the run says so
    // before training.
    let dir2 = tempfile::tempdir().unwrap();
    let alex = dir2.path().join("alex.safetensors");
    seqavatar_compute::lpips::seeded::seeded_weights(seqavatar_compute::lpips::LpipsNet::Alex, 2)
        .write_safetensors(&alex)
        .unwrap();
    let reports = run_pipeline(dir2.path(), UPSTREAM).unwrap();
    let ingest = entry(dir2.path(), &reports, "ingest");
    let motion = entry(dir2.path(), &reports, "motion");
    let small = TrainingData::read(&ingest, &ingest, &motion, 0.5).unwrap();
    config.resolution_scale = 0.5;
    config.lpips_weights = Some(alex);
    let error = format!(
        "{:#}",
        Trainer::new(config, &small, cpu_backend()).err().unwrap()
    );
    assert!(
        error.contains("31 x 31") && error.contains("20 x 20"),
        "{error}"
    );
}

#[test]
fn lpips_weights_enter_the_key_only_when_the_loss_is_on() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("lpips_vgg.safetensors");
    write_lpips_weights(&weights, 1);
    let registry = registry();
    let store = LocalStore::open(dir.path()).unwrap();
    let key = |lpips_weight: f64| {
        let config = TRAIN_CONFIG.replace("ITERATIONS", "3").replace(
            "\"preset\": \"fast\"",
            &format!(
                "\"preset\": \"fast\", \"lpips_weight\": {lpips_weight}, \"lpips_weights\": \"{}\"",
                weights.display()
            ),
        );
        let text = format!(
            "{UPSTREAM}  - name: train\n    kind: train\n    inputs: [ingest, motion]\n    config: {config}\n"
        );
        let pipeline = Pipeline::parse(&text, Path::new("test.yaml"), &registry, &[]).unwrap();
        let keys = seqavatar_engine::compute_keys(&pipeline, &registry, &store).unwrap();
        (
            keys["train"].key.clone(),
            keys["train"].external_files.len(),
        )
    };
    let (on_before, files) = key(0.1);
    assert_eq!(files, 1);
    let (off_before, files) = key(0.0);
    assert_eq!(files, 0);
    // New file content (same path, size and name): only the key with the loss on changes.
    std::thread::sleep(Duration::from_millis(20));
    write_lpips_weights(&weights, 2);
    assert_ne!(key(0.1).0, on_before);
    assert_eq!(key(0.0).0, off_before);
}

#[test]
fn gpu_steps_with_the_lpips_loss_match_cpu() {
    // The LPIPS term runs on the trainer's backend (cpu gemm trunk vs the WGSL trunk and
    // its gather backward): both runs see the same losses step after step.
    let Some(gpu) = gpu_backend() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    let weights = dir.path().join("lpips_vgg.safetensors");
    write_lpips_weights(&weights, 3);
    config.lpips_weight = 0.1;
    config.lpips_weights = Some(weights);
    config.motion_context = seqavatar_train::config::MotionContext::None;
    let mut cpu = Trainer::new(config.clone(), &data, cpu_backend()).unwrap();
    let mut gpu = Trainer::new(config, &data, gpu).unwrap();
    gpu.set_log_every(1);
    for step in 0..3 {
        let (a, b) = (cpu.step().unwrap(), gpu.step().unwrap());
        eprintln!(
            "step {step}: lpips cpu {} gpu {}, total cpu {} gpu {}",
            a.lpips, b.lpips, a.total, b.total
        );
        assert!(a.lpips > 0.0 && a.lpips.is_finite());
        assert!(
            (a.lpips - b.lpips).abs() <= 1e-3 * a.lpips,
            "step {step}: lpips {} vs {}",
            a.lpips,
            b.lpips
        );
        assert!(
            (a.total - b.total).abs() <= 1e-3 * a.total.abs(),
            "step {step}: total {} vs {}",
            a.total,
            b.total
        );
    }
}

#[test]
fn a_corrupt_checkpoint_restarts_training_and_says_so() {
    let iterations = 20u32;
    let dir = tempfile::tempdir().unwrap();
    let text = pipeline_text(iterations);
    // The only checkpoint of an interrupted run is damaged: it used to fail every run.
    let damaged = train_work_dir(dir.path(), &text).join("checkpoints/ckpt-0000000010");
    std::fs::create_dir_all(&damaged).unwrap();
    std::fs::write(damaged.join("zarr.json"), b"{not json").unwrap();
    let reports = run_pipeline(dir.path(), &text).unwrap();
    let train = entry(dir.path(), &reports, "train");
    assert_eq!(train.attribute("resumed_from").unwrap().as_u64(), Some(0));
    let warnings = &train.manifest().warnings;
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("ckpt-0000000010") && w.contains("unusable and was deleted")),
        "{warnings:?}"
    );
    assert!(
        warnings.iter().any(|w| w.contains("starts over")),
        "{warnings:?}"
    );
}

/// The staging work folder of the train stage of `text`'s pipeline in the cache `cache`.
fn train_work_dir(cache: &Path, text: &str) -> PathBuf {
    let registry = registry();
    let store = LocalStore::open(cache).unwrap();
    let pipeline = Pipeline::parse(text, Path::new("test.yaml"), &registry, &[]).unwrap();
    let keys = seqavatar_engine::compute_keys(&pipeline, &registry, &store).unwrap();
    cache
        .join(".staging/train")
        .join(&keys["train"].key)
        .join("work")
}

/// Runs the pipeline `text` on a thread and fails if it has not finished within `seconds`
/// (a read that blocks on a FIFO would otherwise hang the test).
fn run_within(seconds: u64, cache: &Path, text: &str) -> Vec<seqavatar_engine::StageReport> {
    let (cache, text) = (cache.to_path_buf(), text.to_owned());
    seqavatar_engine::test_support::finishes_within(seconds, move || {
        run_pipeline(&cache, &text).map_err(|e| format!("{e:#}"))
    })
    .unwrap()
}

/// A checkpoint chunk replaced by a FIFO used to block every rerun (the open waits for a
/// writer): it is refused at once, naming the file, and training falls back to the previous
/// checkpoint or, as here, starts over, and says so.
#[test]
fn a_fifo_in_place_of_a_checkpoint_chunk_is_refused_and_training_starts_over() {
    let dir = tempfile::tempdir().unwrap();
    let text = pipeline_text(20);
    run_pipeline(dir.path(), UPSTREAM).unwrap();
    let checkpoints = train_work_dir(dir.path(), &text).join("checkpoints");
    let sample = checkpoint::Checkpoint {
        iteration: 10,
        rng_state: 1,
        metadata: serde_json::json!({}),
        tensors: vec![checkpoint::Tensor {
            name: "gaussians/xyz".into(),
            shape: vec![2, 3],
            dimension_names: vec!["gaussian".into(), "axis".into()],
            values: vec![0.5; 6],
        }],
    };
    let saved = checkpoint::save(&checkpoints, &sample).unwrap();
    let chunk = saved.join("gaussians/xyz/c/0/0");
    std::fs::remove_file(&chunk).unwrap();
    seqavatar_engine::test_support::make_fifo(&chunk);
    let reports = run_within(120, dir.path(), &text);
    let train = entry(dir.path(), &reports, "train");
    assert_eq!(train.attribute("resumed_from").unwrap().as_u64(), Some(0));
    let warnings = &train.manifest().warnings;
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("ckpt-0000000010/gaussians/xyz/c/0/0")
                && w.contains("a FIFO")
                && w.contains("unusable and was deleted")),
        "{warnings:?}"
    );
    assert!(
        warnings.iter().any(|w| w.contains("starts over")),
        "{warnings:?}"
    );
}

/// A file in place of the `work/checkpoints` folder used to fail every rerun with "Not a
/// directory": it is deleted with a warning and training runs (and checkpoints) as usual.
#[test]
fn a_file_in_place_of_the_checkpoints_folder_is_deleted_and_training_runs() {
    let dir = tempfile::tempdir().unwrap();
    let text = pipeline_text(20);
    let work = train_work_dir(dir.path(), &text);
    std::fs::create_dir_all(&work).unwrap();
    std::fs::write(work.join("checkpoints"), b"not a folder").unwrap();
    let reports = run_within(120, dir.path(), &text);
    let train = entry(dir.path(), &reports, "train");
    assert_eq!(train.attribute("resumed_from").unwrap().as_u64(), Some(0));
    let warnings = &train.manifest().warnings;
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("work/checkpoints") && w.contains("not a folder")),
        "{warnings:?}"
    );
}

/// The training targets are the person on the iteration's background: replacing what the
/// cameras saw outside the masks changes no loss (L1, mask, SSIM, LPIPS, train PSNR), on
/// black, white and random backgrounds and on both backends. (Comparing the raw images, as
/// the trainer once did, changes every one of them.)
#[test]
fn targets_are_composited_onto_the_background() {
    let dir = tempfile::tempdir().unwrap();
    let (data, mut config) = tiny_data(dir.path(), 40);
    let weights = dir.path().join("lpips_alex.safetensors");
    seqavatar_compute::lpips::seeded::seeded_weights(LpipsNet::Alex, 5)
        .write_safetensors(&weights)
        .unwrap();
    config.lpips_weight = 0.1;
    config.lpips_weights = Some(weights);
    config.lpips_net = LpipsNet::Alex;
    // The same capture with a different backdrop: every pixel outside the masks repainted.
    let mut repainted = data.clone();
    let mut outside = 0;
    for record in &mut repainted.images {
        for (index, pixel) in record.rgb.chunks_exact_mut(3).enumerate() {
            if record.mask[index] == 0 {
                pixel.copy_from_slice(&[(index * 37 % 256) as u8, 255, (index % 7 * 40) as u8]);
                outside += 1;
            }
        }
    }
    assert!(outside > 1000, "{outside} background pixels");
    assert!(
        data.images
            .iter()
            .zip(&repainted.images)
            .any(|(a, b)| a.rgb != b.rgb)
    );
    let mut backends = vec![cpu_backend()];
    backends.extend(gpu_backend());
    for backend in backends {
        for background in [Background::Black, Background::White, Background::Random] {
            config.background = background;
            let mut a = Trainer::new(config.clone(), &data, backend.clone()).unwrap();
            let mut b = Trainer::new(config.clone(), &repainted, backend.clone()).unwrap();
            a.set_log_every(1);
            b.set_log_every(1);
            for step in 0..2 {
                let (sa, sb) = (a.step().unwrap(), b.step().unwrap());
                eprintln!(
                    "{} {background:?} step {step}: total {} vs {}",
                    backend.describe(),
                    sa.total,
                    sb.total
                );
                assert!(sa.lpips > 0.0 && sa.dssim > 0.0 && sa.l1 > 0.0);
                // The first step is bit-identical on both backends, later steps
                // on cpu only: a gpu's backward adds gradients with float atomics in whatever order
                // its threads run, so two runs differ in the last bits of the parameters after
                // one update (an H100 measured 1 ulp of LPIPS at step 1); a backdrop that
                // leaked into a loss changes it in the third digit.
                let tolerance = if step == 0 || !a.resident() {
                    1e-12
                } else {
                    1e-5
                };
                for (name, x, y) in [
                    ("l1", sa.l1, sb.l1),
                    ("mask_mse", sa.mask_mse, sb.mask_mse),
                    ("dssim", sa.dssim, sb.dssim),
                    ("lpips", sa.lpips, sb.lpips),
                    ("psnr", sa.psnr, sb.psnr),
                    ("total", sa.total, sb.total),
                ] {
                    assert!(
                        (x - y).abs() <= tolerance * x.abs().max(1.0),
                        "{} {background:?} step {step}: {name} {x} vs {y}",
                        backend.describe()
                    );
                }
            }
        }
    }
}

/// The same short run on the tiny scene with its textured backdrop and on black reaches the
/// same held-out PSNR (within 0.5 dB): training learns the person, not what stands behind
/// it. Comparing the raw images instead (the trainer before the targets were composited)
/// fails this.
#[test]
fn backdrop_leaves_the_held_out_psnr_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let held_out = |background: &str| {
        let text = pipeline_text(BACKDROP_ITERATIONS).replace(
            "garment: false,",
            &format!("garment: false, background: {background},"),
        );
        let reports = run_pipeline(dir.path(), &text).unwrap();
        let train = entry(dir.path(), &reports, "train");
        train.attribute("test_psnr_mean").unwrap().as_f64().unwrap()
    };
    let (textured, black) = (held_out("textured"), held_out("black"));
    eprintln!("held-out PSNR: textured backdrop {textured:.2} dB, black {black:.2} dB");
    assert!(
        (textured - black).abs() < 0.5,
        "textured backdrop {textured:.2} dB, black {black:.2} dB"
    );
}

/// Iterations of [`backdrop_leaves_the_held_out_psnr_unchanged`].
const BACKDROP_ITERATIONS: u32 = 60;
