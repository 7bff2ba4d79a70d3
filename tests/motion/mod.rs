//! The motion stage through the engine, downstream of ingest and fit: what its entry holds,
//! and which settings leave its key alone.

use seqavatar_engine::{
    EntryId, LocalStore, PictureOptions, Pipeline, Registry, RunOptions, StageContext, StageKind,
    Store, compute_keys, run,
};
use seqavatar_motion::MotionStage;
use seqavatar_schema::motion::{VelocityNormalisation, read_input_scales};
use std::path::Path;

/// A tiny synthetic scene through ingest, fit and motion.
const PIPELINE: &str = r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 2, frames: 9, width: 32, height: 32, supersample: 1, garment: false, body_grid_spacing: 0.04}
      past_frames: 0
  - name: fit
    kind: fit
    inputs: [ingest]
  - name: motion
    kind: motion
    inputs: [ingest, fit]
    config: {scales: [1, 3], knn: 4}
"#;

fn registry() -> Registry {
    let mut registry = seqavatar_registry::registry();
    registry.add(Box::new(TrainingSettingsProbe));
    registry
}

/// Test fixture standing for any downstream consumer with training settings (sequence
/// length, iterations): only its own key may change when those change.
struct TrainingSettingsProbe;

impl StageKind for TrainingSettingsProbe {
    type Config = serde_json::Value;
    fn kind(&self) -> &'static str {
        "training_settings_probe"
    }
    fn version(&self) -> u32 {
        1
    }
    fn input_kinds(&self) -> &'static [&'static str] {
        &["motion"]
    }
    fn run(&self, _config: &Self::Config, _ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        anyhow::bail!("never run")
    }
}

fn keys(text: &str, store: &LocalStore) -> std::collections::BTreeMap<String, String> {
    let registry = registry();
    let pipeline = Pipeline::parse(text, Path::new("test.yaml"), &registry, &[]).unwrap();
    compute_keys(&pipeline, &registry, store)
        .unwrap()
        .into_iter()
        .map(|(name, key)| (name, key.key))
        .collect()
}

#[test]
fn changing_only_training_settings_keeps_the_motion_key() {
    let dir = tempfile::tempdir().unwrap();
    let store = LocalStore::open(dir.path()).unwrap();
    let with = |length: u32, iterations: u32| {
        format!(
            "{PIPELINE}  - name: train\n    kind: training_settings_probe\n    inputs: [motion]\n    config: {{sequence_length: {length}, iterations: {iterations}}}\n"
        )
    };
    let a = keys(&with(3, 3000), &store);
    let b = keys(&with(8, 15000), &store);
    assert_eq!(a["motion"], b["motion"]);
    assert_eq!(a["fit"], b["fit"]);
    assert_ne!(a["train"], b["train"]);
    // Scale order is canonical; a different scale set is a different entry.
    let reordered = keys(&PIPELINE.replace("[1, 3]", "[3, 1]"), &store);
    assert_eq!(reordered["motion"], a["motion"]);
    let other = keys(&PIPELINE.replace("[1, 3]", "[1, 2]"), &store);
    assert_ne!(other["motion"], a["motion"]);
    // Training settings cannot leak into the motion config.
    let registry = registry();
    let leaked = PIPELINE.replace("knn: 4}", "knn: 4, sequence_length: 8}");
    assert!(Pipeline::parse(&leaked, Path::new("test.yaml"), &registry, &[]).is_err());
}

#[test]
fn motion_entry_is_consistent_with_its_definition() {
    let dir = tempfile::tempdir().unwrap();
    let store = LocalStore::open(dir.path()).unwrap();
    let registry = registry();
    let pipeline = Pipeline::parse(PIPELINE, Path::new("test.yaml"), &registry, &[]).unwrap();
    let reports = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
    let key = &reports.iter().find(|r| r.name == "motion").unwrap().key;
    let entry = store.open_entry(&EntryId::new("motion", key)).unwrap();

    let posed = entry.read::<f32>("posed_vertices").unwrap();
    let velocity = entry.read::<f32>("vertex_velocity").unwrap();
    let skeleton = entry.read::<f32>("skeleton_motion").unwrap();
    let steps = entry.read::<u32>("scale_steps").unwrap().data;
    assert_eq!(entry.read::<u32>("scales").unwrap().data, vec![3, 1]);
    assert_eq!(steps, vec![3, 1]);
    let (f, v) = (posed.shape[0], posed.shape[1]);
    assert_eq!(f, 9);
    assert_eq!(velocity.shape, vec![f, 2, v, 3]);
    assert_eq!(skeleton.shape[..2], [f, 2]);
    // Velocity is the displacement over the scale times the recorded factor (RMS 1 per
    // scale), zero at the first frame.
    let factors = entry.read::<f64>("vertex_velocity_scale").unwrap().data;
    assert_eq!(entry.attribute("input_scaling"), Some("rms".into()));
    for (slot, rms) in seqavatar_schema::motion::block_rms(&velocity.data, 2, v)
        .into_iter()
        .enumerate()
    {
        assert!((rms - 1.0).abs() < 1e-4, "slot {slot}: RMS {rms}");
        assert!(
            factors[slot] > 1.0,
            "metres per frame are below 1: {factors:?}"
        );
    }
    let (normalisation, scales_read) = read_input_scales(&entry).unwrap();
    assert_eq!(normalisation, VelocityNormalisation::PerScale);
    assert_eq!(scales_read.vertex_velocity, factors);
    for t in 0..f {
        for (slot, &k) in steps.iter().enumerate() {
            let former = t.saturating_sub(k as usize);
            for vertex in [0, v / 2, v - 1] {
                for c in 0..3 {
                    let expected = (posed.data[(t * v + vertex) * 3 + c]
                        - posed.data[(former * v + vertex) * 3 + c])
                        / k as f32
                        * factors[slot] as f32;
                    let got = velocity.data[((t * 2 + slot) * v + vertex) * 3 + c];
                    assert!(
                        (got - expected).abs() < 1e-5 * factors[slot] as f32,
                        "t={t} slot={slot}"
                    );
                }
            }
        }
    }
    // A window is a gather of these rows.
    let w = seqavatar_schema::motion::window(
        7,
        3,
        &steps.iter().map(|&s| s as usize).collect::<Vec<_>>(),
    );
    assert_eq!(w.frames, vec![7, 7, 4, 6, 1, 5]);
    // The KNN graph starts with the vertex itself.
    let knn = entry.read::<u32>("canonical_knn").unwrap();
    assert_eq!(knn.shape, vec![v, 4]);
    assert!((0..v).all(|i| knn.data[i * 4] == i as u32));
    // Pictures draw.
    let stage = MotionStage;
    let speed = stage
        .draw_picture(
            &entry,
            "speed",
            &PictureOptions::parse(&["frame=5".into(), "scale=1".into()]).unwrap(),
        )
        .unwrap();
    assert_eq!((speed.width(), speed.height()), (32 + 70, 32));
    let plot = stage
        .draw_picture(&entry, "skeleton_motion", &PictureOptions::default())
        .unwrap();
    assert!(plot.width() > 0);
    assert!(
        stage
            .draw_picture(
                &entry,
                "speed",
                &PictureOptions::parse(&["scale=2".into()]).unwrap()
            )
            .is_err()
    );
    assert!(
        stage
            .draw_picture(
                &entry,
                "speed",
                &PictureOptions::parse(&["frame=9".into()]).unwrap()
            )
            .is_err()
    );
    // The fit entry reports jitter and, on the synthetic scene, ground-truth errors.
    let fit_key = &reports.iter().find(|r| r.name == "fit").unwrap().key;
    let fit = store.open_entry(&EntryId::new("fit", fit_key)).unwrap();
    let before = fit
        .attribute("joint_error_before")
        .unwrap()
        .as_f64()
        .unwrap();
    let after = fit
        .attribute("joint_error_after")
        .unwrap()
        .as_f64()
        .unwrap();
    assert!(after < before, "{before} -> {after}");
    let jitter = seqavatar_fit::FitStage
        .draw_picture(&fit, "jitter", &PictureOptions::default())
        .unwrap();
    assert_eq!((jitter.width(), jitter.height()), (800, 300));
}

/// The garment oracle: on the history scene the motion entry appends the garment's true
/// state, normalised to RMS 1 per component, to every skeleton-motion block (the track reads
/// two more rows per block, the joints' rows unchanged); off, the key is that of a config
/// without the field; on a scene without a garment state it is refused, naming the field.
#[test]
fn garment_oracle_appends_the_true_garment_state_to_the_skeleton_motion() {
    let pipeline_text = |dataset: &str| {
        format!(
            r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {dataset}
      past_frames: 0
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {{scales: [2, 1], knn: 4}}
  - name: motion_off
    kind: motion
    inputs: [ingest]
    config: {{scales: [2, 1], knn: 4, garment_oracle: false}}
  - name: motion_oracle
    kind: motion
    inputs: [ingest]
    config: {{scales: [2, 1], knn: 4, garment_oracle: true}}
"#
        )
    };
    let history = "{kind: synthetic, scene: history, fps: 30, frames: 40, cameras: 2, width: 32, height: 32, supersample: 1, body_grid_spacing: 0.04, jitter: {pose_radians: 0.0, translation_metres: 0.0, betas: 0.0}}";
    let dir = tempfile::tempdir().unwrap();
    let store = LocalStore::open(dir.path()).unwrap();
    let registry = registry();
    let pipeline = Pipeline::parse(
        &pipeline_text(history),
        Path::new("test.yaml"),
        &registry,
        &[],
    )
    .unwrap();
    let reports = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
    let key = |name: &str| reports.iter().find(|r| r.name == name).unwrap().key.clone();
    assert_eq!(key("motion"), key("motion_off"));
    assert_ne!(key("motion"), key("motion_oracle"));
    let open = |name: &str| {
        store
            .open_entry(&EntryId::new("motion", &key(name)))
            .unwrap()
    };
    let plain = seqavatar_schema::motion::MotionTrack::read(&open("motion")).unwrap();
    let oracle = seqavatar_schema::motion::MotionTrack::read(&open("motion_oracle")).unwrap();
    assert_eq!(plain.garment_rows, 0);
    assert_eq!(oracle.garment_rows, 2);
    assert_eq!(oracle.num_joints, plain.num_joints + 2);
    let ingest = store
        .open_entry(&EntryId::new("ingest", &key("ingest")))
        .unwrap();
    let states = seqavatar_schema::ingest::read_garment_history(&ingest)
        .unwrap()
        .unwrap()
        .states;
    let (j, rows) = (plain.num_joints, oracle.num_joints);
    let mut sums = [0.0f64; seqavatar_schema::ingest::GARMENT_STATE_COMPONENTS];
    assert_eq!(states.len(), plain.num_frames);
    for (frame, state) in states.iter().enumerate() {
        for slot in 0..2 {
            let joints = &plain.skeleton_motion[(frame * 2 + slot) * j * 3..][..j * 3];
            let block = &oracle.skeleton_motion[(frame * 2 + slot) * rows * 3..][..rows * 3];
            assert_eq!(&block[..j * 3], joints, "frame {frame}");
            let garment = &block[j * 3..];
            for (c, sum) in sums.iter_mut().enumerate() {
                // Same sign as the state, and zero exactly where it is.
                assert_eq!(
                    garment[c] == 0.0,
                    state[c] == 0.0,
                    "frame {frame} component {c}"
                );
                assert!(f64::from(garment[c]) * state[c] >= 0.0);
                if slot == 0 {
                    *sum += f64::from(garment[c]).powi(2);
                }
            }
        }
    }
    // RMS 1 per component, but for one that is zero throughout (no turn in 40 frames: no
    // deflection across the body, nor twist), which stays zero.
    let moving = states.iter().fold([false; 6], |mut any, s| {
        for (moved, value) in any.iter_mut().zip(s) {
            *moved |= *value != 0.0;
        }
        any
    });
    assert!(moving[0] && moving[2], "the hem swings forward and back");
    for (c, sum) in sums.iter().enumerate() {
        let rms = (sum / plain.num_frames as f64).sqrt();
        let want = if moving[c] { 1.0 } else { 0.0 };
        assert!((rms - want).abs() < 1e-4, "component {c}: RMS {rms}");
    }
    // The walk scene knows no garment state: the oracle is refused, naming the field.
    let walk = "{kind: synthetic, cameras: 2, frames: 6, width: 32, height: 32, supersample: 1, body_grid_spacing: 0.04}";
    let pipeline =
        Pipeline::parse(&pipeline_text(walk), Path::new("test.yaml"), &registry, &[]).unwrap();
    let error = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap_err();
    let text = format!("{error:#}");
    assert!(text.contains("garment_oracle"), "{text}");
}
