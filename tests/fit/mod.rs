//! The fit stage through the engine, downstream of ingest.

use seqavatar_engine::{EntryId, LocalStore, Pipeline, RunOptions, Store, run};
use seqavatar_fit::evidence::track_name;
use seqavatar_schema::body::BodySequence;
use seqavatar_schema::fit::{Jitter, SilhouetteIou, TrackVerdicts};

/// The three modes through the engine on a tiny synthetic scene: `off` copies the fits,
/// `keypoints` reads the ingest entry's keypoint arrays and beats `smooth` against the
/// ground truth.
#[test]
fn modes_through_the_engine() {
    let text = r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 1, frames: 12, width: 16, height: 16, supersample: 1, garment: false, body_grid_spacing: 0.04}
      past_frames: 0
  - {name: unchanged, kind: fit, inputs: [ingest], config: {mode: off}}
  - {name: smooth, kind: fit, inputs: [ingest], config: {mode: smooth}}
  - {name: keypoints, kind: fit, inputs: [ingest], config: {mode: keypoints}}
  - name: exact
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 1, frames: 12, width: 16, height: 16, supersample: 1, garment: false, body_grid_spacing: 0.04, jitter: {pose_radians: 0.0, translation_metres: 0.0, betas: 0.0, keypoints_metres: 0.0}}
      past_frames: 0
  - {name: smooth_exact, kind: fit, inputs: [exact], config: {mode: smooth}}
"#;
    let dir = tempfile::tempdir().unwrap();
    let store = LocalStore::open(dir.path()).unwrap();
    let registry = seqavatar_registry::registry();
    let pipeline = Pipeline::parse(text, std::path::Path::new("t.yaml"), &registry, &[]).unwrap();
    let reports = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
    let entry = |name: &str| {
        let key = &reports.iter().find(|r| r.name == name).unwrap().key;
        store
            .open_entry(&EntryId::new(name_kind(name), key))
            .unwrap()
    };
    fn name_kind(name: &str) -> &'static str {
        if name == "ingest" || name == "exact" {
            "ingest"
        } else {
            "fit"
        }
    }
    let attribute =
        |name: &str, key: &str| entry(name).attribute(key).and_then(|v| v.as_f64()).unwrap();
    let ingest = entry("ingest");
    assert_eq!(
        entry("unchanged").read::<f64>("body_pose").unwrap().data,
        ingest.read::<f64>("body_pose").unwrap().data
    );
    let input = attribute("keypoints", "joint_error_before");
    let smooth = attribute("smooth", "joint_error_after");
    let keypoints = attribute("keypoints", "joint_error_after");
    println!(
        "12-frame scene through the engine: joint error input {:.2} mm, smooth {:.2} mm, keypoints {:.2} mm",
        input * 1e3,
        smooth * 1e3,
        keypoints * 1e3
    );
    assert!(keypoints < smooth && smooth < input);
    assert!(
        attribute("keypoints", "keypoint_distance_after")
            < attribute("keypoints", "keypoint_distance_before")
    );
    assert_eq!(
        entry("keypoints").attribute("mode"),
        Some("keypoints".into())
    );
    // Evidence in both refining modes, none when passing through.
    for name in ["smooth", "keypoints"] {
        let fit = entry(name);
        // Read back through the schema: 24 joints + rotation + translation, one view,
        // and the kept tracks' names match the verdicts.
        let verdicts = TrackVerdicts::read(&fit).unwrap().unwrap();
        assert_eq!(verdicts.0.len(), 26);
        let kept: Vec<String> = verdicts
            .0
            .iter()
            .enumerate()
            .filter(|(_, v)| v.kept_input)
            .map(|(track, _)| track_name(track, 24))
            .collect();
        assert_eq!(
            fit.attribute("tracks_kept_input"),
            Some(serde_json::to_value(&kept).unwrap())
        );
        let iou = SilhouetteIou::read(&fit).unwrap().unwrap();
        assert_eq!((iou.before.len(), iou.after.len()), (1, 1));
        assert!((iou.after[0] - attribute(name, "mean_silhouette_iou_after")).abs() < 1e-12);
        let (before, after) = (
            attribute(name, "mean_silhouette_iou_before"),
            attribute(name, "mean_silhouette_iou_after"),
        );
        println!("{name}: silhouette IoU {before:.4} -> {after:.4}");
        assert!(before > 0.3 && before <= 1.0 && after > 0.3 && after <= 1.0);
        assert!(fit.attribute("tracks_kept_input").unwrap().is_array());
        // The synthetic scene's keypoints name joints: smooth mode is judged by them too.
        assert!(
            attribute(name, "keypoint_distance_after")
                <= attribute(name, "keypoint_distance_before")
        );
    }
    let unchanged = entry("unchanged");
    assert_eq!(TrackVerdicts::read(&unchanged).unwrap(), None);
    assert_eq!(SilhouetteIou::read(&unchanged).unwrap(), None);
    assert_eq!(
        BodySequence::read(&unchanged, "body").unwrap(),
        BodySequence::read(&ingest, "body").unwrap()
    );
    // Jitter of every frame; its mean is the attribute.
    for name in ["unchanged", "smooth", "keypoints"] {
        let jitter = Jitter::read(&entry(name)).unwrap();
        assert_eq!(jitter.before.len(), 12);
        let mean = jitter.after.iter().sum::<f64>() / 12.0;
        assert!((mean - attribute(name, "mean_jitter_after")).abs() <= 1e-12 * mean.abs());
    }
    assert_eq!(
        Jitter::read(&entry("unchanged")).unwrap().before,
        Jitter::read(&entry("unchanged")).unwrap().after
    );
    // Exact fits stay put: their joint error (zero before) stays far below a millimetre.
    let moved = attribute("smooth_exact", "joint_error_after");
    println!(
        "exact fits through the stage: joints moved {:.4} mm",
        moved * 1e3
    );
    assert_eq!(attribute("smooth_exact", "joint_error_before"), 0.0);
    assert!(moved < 2e-4, "{moved}");
}
