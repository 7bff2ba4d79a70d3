//! The train stage's load-time checks against the ingest stage's plan: the memory a run
//! will hold, estimated from the configs before anything runs.

use std::time::Instant;

use seqavatar_engine::StageKind as _;
use seqavatar_schema::ingest::IngestImages;
use seqavatar_train::TrainStage;
use seqavatar_train::config::TrainConfig;
use serde_json::json;

/// The ingest and train configs of `pipelines/synthetic.yaml` (the demo), resolved, with
/// the ingest's scene size replaced by `scene`.
fn demo_configs(scene: serde_json::Value) -> (seqavatar_ingest::IngestConfig, TrainConfig) {
    let mut dataset =
        json!({"kind": "synthetic", "cameras": 8, "frames": 48, "width": 256, "height": 256});
    for (key, value) in scene.as_object().unwrap() {
        dataset[key] = value.clone();
    }
    let ingest = seqavatar_ingest::Ingest
        .resolve_config(&json!({"dataset": dataset, "resolution_scale": 1.0, "past_frames": 18}))
        .unwrap();
    let train = TrainStage
        .resolve_config(&json!({"preset": "fast", "device": "auto", "resolution_scale": 1.0, "iterations": 800}))
        .unwrap();
    (ingest, train)
}

/// The images the ingest config plans, as the train stage's load-time check sees them.
fn planned_images(ingest: &seqavatar_ingest::IngestConfig) -> Option<IngestImages> {
    let planned = seqavatar_ingest::Ingest.planned(ingest);
    let input = seqavatar_engine::StageInput {
        name: "ingest",
        kind: "ingest",
        planned: &planned,
    };
    let plan = seqavatar_schema::ingest::PlannedIngest::of(&input).unwrap();
    plan.images
}

fn check(ingest: &seqavatar_ingest::IngestConfig, train: &TrainConfig) -> Result<(), String> {
    let planned = seqavatar_ingest::Ingest.planned(ingest);
    let inputs = [
        seqavatar_engine::StageInput {
            name: "ingest",
            kind: "ingest",
            planned: &planned,
        },
        seqavatar_engine::StageInput {
            name: "motion",
            kind: "motion",
            planned: &serde_json::Value::Null,
        },
    ];
    TrainStage.check_inputs(train, &inputs)
}

/// Training holds every image of the split in memory: 64 cameras x 1000 frames at
/// 2048 x 2048 pass every range check but need over 200 GB. Refused when the pipeline
/// loads, from the configs alone, in well under a second, naming the fields.
#[test]
fn a_run_over_the_memory_budget_is_refused_at_load() {
    let started = Instant::now();
    let (ingest, train) =
        demo_configs(json!({"cameras": 64, "frames": 1000, "width": 2048, "height": 2048}));
    let images = planned_images(&ingest).unwrap();
    // The default split: 48 training views on every frame, 16 test views on every other.
    assert_eq!(images.count, 48 * 1000 + 16 * 500);
    let config = &train;
    // The demo trains at full resolution: 2048 x 2048, RGB and mask bytes.
    assert_eq!(config.resolution_scale, 1.0);
    let estimate = config.run_memory_estimate_bytes(Some(&images));
    assert!(estimate > images.count * 2048 * 2048 * 4, "{estimate}");
    let error = config.check_memory(Some(&images), 16 << 30).unwrap_err();
    for field in [
        "dataset.cameras",
        "dataset.frames",
        "dataset.width",
        "train.resolution_scale",
        "train.max_gaussians",
        "train.cameras_per_step",
        "SEQAVATAR_MEMORY_BUDGET",
    ] {
        assert!(error.contains(field), "{field}: {error}");
    }
    // Through the stage's load-time check, against this machine's budget.
    if seqavatar_engine::memory_budget_bytes()
        .unwrap()
        .is_some_and(|budget| budget < estimate)
    {
        let error = check(&ingest, &train).unwrap_err();
        assert!(
            error.contains("SEQAVATAR_MEMORY_BUDGET") && error.contains("input ingest"),
            "{error}"
        );
    }
    assert!(started.elapsed() < std::time::Duration::from_secs(1));
}

/// The demo's run fits a small budget: its images, Gaussians and renders take well under
/// 1 GB; the load-time check accepts it.
#[test]
fn the_demo_run_is_within_the_memory_budget() {
    let (ingest, train) = demo_configs(json!({}));
    let images = planned_images(&ingest).unwrap();
    // 6 training views on 48 frames, 2 test views on 24.
    assert_eq!(
        (images.count, images.width, images.height),
        (6 * 48 + 2 * 24, 256, 256)
    );
    let config = &train;
    // At the demo's full resolution: 256 x 256 pixels per image and render.
    assert_eq!(config.resolution_scale, 1.0);
    let estimate = config.run_memory_estimate_bytes(Some(&images));
    assert_eq!(
        estimate,
        config.memory_estimate_bytes()
            + images.count * 256 * 256 * 4
            + config.cameras_per_step as u64 * 256 * 256 * 256
    );
    config.check_memory(Some(&images), 1 << 30).unwrap();
    if seqavatar_engine::memory_budget_bytes()
        .unwrap()
        .is_none_or(|budget| budget >= 1 << 30)
    {
        check(&ingest, &train).unwrap();
    }
}
