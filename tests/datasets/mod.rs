//! The dataset pipelines (`pipelines/{zju_mocap,i3d_human,dna_rendering}.yaml`) run on tiny
//! datasets written in each real layout by `tests/fixtures/write_datasets.py` (numpy, h5py;
//! committed in `tests/fixtures/data`),
//! through the real binary and the committed YAML files, with the dataset roots given the
//! way a user gives them: environment variables. Every stage of each pipeline is validated;
//! ingest, fit and motion run (training would take hours at the datasets' settings), and
//! `pipeline inspect` draws the ingest contact sheet. The readers' numerics are checked in
//! `src/datasets/tests/datasets.rs`; this checks the files users run.

use std::path::{Path, PathBuf};

use crate::support::Sandbox;

/// Copies the committed fixture `kind` (written by `tests/fixtures/write_datasets.py`, see
/// `tests/fixtures/regenerate.py`) into `out`.
fn write_fixture(kind: &str, out: &Path) {
    copy_dir(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/data")
            .join(kind),
        out,
    );
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap_or_else(|e| panic!("{}: {e}", to.display()));
    for entry in std::fs::read_dir(from).unwrap_or_else(|e| panic!("{}: {e}", from.display())) {
        let entry = entry.expect("directory entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("file type").is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target)
                .unwrap_or_else(|e| panic!("{}: {e}", entry.path().display()));
        }
    }
}

fn pipeline_file(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("pipelines")
        .join(name)
        .to_str()
        .expect("utf-8 repository path")
        .to_string()
}

/// Runs `args` with the environment `vars`, asserting success; returns stdout.
fn ok_with_env(sandbox: &Sandbox, vars: &[(&str, &Path)], args: &[&str]) -> String {
    let mut command = sandbox.command(args);
    for (name, value) in vars {
        command.env(name, value);
    }
    let output = command.output().expect("run pipeline binary");
    assert!(
        output.status.success(),
        "pipeline {args:?} failed:\nstdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Ingests with `yaml`, checks the entry's image count and draws its contact sheet.
fn ingest_and_inspect(
    sandbox: &Sandbox,
    yaml: &str,
    vars: &[(&str, &Path)],
    sets: &[&str],
    expected_images: usize,
) {
    let file = pipeline_file(yaml);
    let mut run: Vec<&str> = vec!["run", &file, "--until", "motion"];
    for set in sets {
        run.extend(["--set", set]);
    }
    ok_with_env(sandbox, vars, &run);
    // The whole pipeline (fit, motion, train, eval) validates; the stages up to motion ran.
    let mut status: Vec<&str> = vec!["status", &file];
    for set in sets {
        status.extend(["--set", set]);
    }
    let table = ok_with_env(sandbox, vars, &status);
    let state_of = |stage: &str| -> String {
        table
            .lines()
            .find(|line| line.split_whitespace().next() == Some(stage))
            .and_then(|line| line.split_whitespace().nth(3))
            .unwrap_or_else(|| panic!("{yaml}: no stage {stage} in:\n{table}"))
            .to_string()
    };
    for stage in ["ingest", "fit", "motion"] {
        assert_eq!(state_of(stage), "cached", "{yaml}: {stage}\n{table}");
    }
    for stage in ["train", "eval"] {
        assert_eq!(state_of(stage), "missing", "{yaml}: {stage}\n{table}");
    }

    let target = format!("{file}:ingest");
    let mut inspect: Vec<&str> = vec!["inspect", &target];
    for set in sets {
        inspect.extend(["--set", set]);
    }
    let listing = ok_with_env(sandbox, vars, &inspect);
    let images_line = listing
        .lines()
        .find(|line| line.trim_start().starts_with("images "))
        .unwrap_or_else(|| panic!("no `images` array in the listing:\n{listing}"));
    assert!(
        images_line.contains(&format!("[{expected_images},")),
        "{yaml}: expected {expected_images} images: {images_line}"
    );

    let sheet: PathBuf = sandbox.path().join(format!("{yaml}.png"));
    let sheet_arg = sheet.to_str().expect("utf-8 temp path").to_string();
    inspect.extend(["--png", &sheet_arg, "--picture", "contact_sheet"]);
    ok_with_env(sandbox, vars, &inspect);
    let picture = image::open(&sheet).expect("contact sheet is a PNG");
    assert!(picture.width() > 0 && picture.height() > 0);
}

/// Flips one byte of `file` (same size, modification time set back, as a careless copy
/// would leave it) and checks that the pipeline's ingest key changes (so the ingest is no
/// longer "cached"): every file a dataset reader reads is part of the ingest key.
fn edit_changes_ingest_key(
    sandbox: &Sandbox,
    yaml: &str,
    vars: &[(&str, &Path)],
    sets: &[&str],
    file: &Path,
) {
    let pipeline = pipeline_file(yaml);
    let mut status: Vec<&str> = vec!["status", &pipeline];
    for set in sets {
        status.extend(["--set", set]);
    }
    let ingest_row = || -> Vec<String> {
        let table = ok_with_env(sandbox, vars, &status);
        table
            .lines()
            .find(|line| line.split_whitespace().next() == Some("ingest"))
            .unwrap_or_else(|| panic!("{yaml}: no ingest stage in:\n{table}"))
            .split_whitespace()
            .map(str::to_owned)
            .collect()
    };
    let before = ingest_row();
    let modified = std::fs::metadata(file).unwrap().modified().unwrap();
    let mut bytes = std::fs::read(file).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x55;
    std::fs::write(file, &bytes).unwrap();
    std::fs::File::options()
        .write(true)
        .open(file)
        .unwrap()
        .set_modified(modified)
        .unwrap();
    let after = ingest_row();
    assert_ne!(
        before[2],
        after[2],
        "{yaml}: editing {} must change the ingest key",
        file.display()
    );
    assert_eq!(after[3], "missing", "{yaml}: {after:?}");
}

#[test]
fn zju_mocap_yaml_ingests_the_fixture() {
    let sandbox = Sandbox::new();
    let data = sandbox.path().join("zju");
    let model = sandbox.path().join("smpl");
    write_fixture("zju", &data);
    write_fixture("smpl", &model);
    // Three cameras and four frames: train camera 0 on all frames, test cameras 1 and 2 on
    // frame 0 (every 30th).
    ingest_and_inspect(
        &sandbox,
        "zju_mocap.yaml",
        &[
            ("ZJU_MOCAP_ROOT", &data),
            ("SMPL_NEUTRAL_NPZ", &model.join("model.npz")),
        ],
        &[],
        4 + 2,
    );
    let model_npz = model.join("model.npz");
    let vars: [(&str, &Path); 2] = [("ZJU_MOCAP_ROOT", &data), ("SMPL_NEUTRAL_NPZ", &model_npz)];
    // The ingest ran, so it is cached until a file changes.
    for file in ["Camera_B1/000000.jpg", "annots.npy"] {
        let path = data.join("CoreView_377").join(file);
        edit_changes_ingest_key(&sandbox, "zju_mocap.yaml", &vars, &[], &path);
    }
}

/// A ZJU-MoCap sequence recorded by one camera has no camera to hold out: with the default
/// split (train camera 0, test cameras 1..) the pipeline, whose eval measures test images,
/// is refused when it loads, by `status` and by `run` before any stage runs, naming the
/// dataset's camera count and the split's fields. (It used to ingest and train, then fail
/// at eval.) With a temporal hold-out the same dataset is accepted.
#[test]
fn a_one_camera_dataset_is_refused_at_load_when_eval_needs_held_out_cameras() {
    let sandbox = Sandbox::new();
    let data = sandbox.path().join("zju");
    let model = sandbox.path().join("smpl");
    write_fixture("zju", &data);
    write_fixture("smpl", &model);
    // The sequence as Camera_B1 alone recorded it.
    let sequence = data.join("CoreView_377");
    std::fs::copy(
        data.join("variants/annots_one_camera.npy"),
        sequence.join("annots.npy"),
    )
    .unwrap();
    for camera in ["Camera_B2", "Camera_B3"] {
        std::fs::remove_dir_all(sequence.join(camera)).unwrap();
        std::fs::remove_dir_all(sequence.join("mask_cihp").join(camera)).unwrap();
    }
    let file = pipeline_file("zju_mocap.yaml");
    let model_npz = model.join("model.npz");
    let vars: [(&str, &Path); 2] = [("ZJU_MOCAP_ROOT", &data), ("SMPL_NEUTRAL_NPZ", &model_npz)];
    for verb in ["status", "run"] {
        let mut command = sandbox.command(&[verb, &file]);
        for (name, value) in vars {
            command.env(name, value);
        }
        let output = command.output().expect("run pipeline binary");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{verb} was accepted: {stderr}");
        for part in [
            "CoreView_377 has 1 camera and 4 frames",
            "no test images",
            "split.test_views []",
            "split.held_out_frames",
        ] {
            assert!(stderr.contains(part), "{verb}: no `{part}` in {stderr}");
        }
    }
    assert!(
        !sandbox.cache().join("ingest").exists(),
        "a stage ran before the refusal"
    );
    ok_with_env(
        &sandbox,
        &vars,
        &[
            "status",
            &file,
            "--set",
            "ingest.split.held_out_frames={start: 1, end: null, step: 2}",
        ],
    );
}

/// Two caches kept inside one dataset folder, used in turn: each is a pipeline cache (its
/// `CACHEDIR.TAG`), left out of the dataset's digest whichever cache a run uses, so every run
/// computes one ingest key and the later runs find it cached. (Each cache once left out only
/// itself, so every run saw the other's new entries and got a new key.)
#[test]
fn caches_inside_a_dataset_are_left_out_of_its_digest() {
    let sandbox = Sandbox::new();
    let data = sandbox.path().join("zju");
    let model = sandbox.path().join("smpl");
    write_fixture("zju", &data);
    write_fixture("smpl", &model);
    let sequence = data.join("CoreView_377");
    let caches = [sequence.join("cache_a"), sequence.join("cache_b")];
    let file = pipeline_file("zju_mocap.yaml");
    let run_in = |cache: &Path| -> (String, String) {
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_pipeline"))
            .current_dir(sandbox.path())
            .env_remove("SEQAVATAR_CACHE")
            .env("ZJU_MOCAP_ROOT", &data)
            .env("SMPL_NEUTRAL_NPZ", model.join("model.npz"))
            .arg("--cache")
            .arg(cache)
            .args(["run", &file, "--until", "ingest"])
            .output()
            .expect("run pipeline binary");
        let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
        assert!(
            output.status.success(),
            "{stdout}{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let row: Vec<String> = stdout
            .lines()
            .find(|line| line.starts_with("ingest "))
            .unwrap_or_else(|| panic!("no ingest row in {stdout}"))
            .split_whitespace()
            .map(str::to_owned)
            .collect();
        (row[2].clone(), row[3].clone())
    };
    let runs: Vec<(String, String)> = caches.iter().cycle().take(4).map(|c| run_in(c)).collect();
    for (run, (key, result)) in runs.iter().enumerate() {
        assert_eq!(
            key, &runs[0].0,
            "run {run} got another ingest key: {runs:?}"
        );
        let expected = if run < 2 { "ran" } else { "cached" };
        assert_eq!(result, expected, "run {run}: {runs:?}");
    }
    for cache in &caches {
        let tag = std::fs::read_to_string(cache.join("CACHEDIR.TAG")).unwrap();
        assert!(
            tag.starts_with("Signature: 8a477f597d28d172789f06886806bc55"),
            "{tag}"
        );
    }
}

#[test]
fn i3d_human_yaml_ingests_the_fixture() {
    let sandbox = Sandbox::new();
    let data = sandbox.path().join("i3d");
    let model = sandbox.path().join("smpl");
    write_fixture("i3d", &data);
    write_fixture("smpl", &model);
    ingest_and_inspect(
        &sandbox,
        "i3d_human.yaml",
        &[
            ("I3D_HUMAN_ROOT", &data),
            ("SMPL_NEUTRAL_NPZ", &model.join("model.npz")),
        ],
        &["ingest.dataset.sequence=ID2_1"],
        // ID2_1 (interval 3): train views 1 and 3, test view 2, each on frames 0, 3, 6.
        2 * 3 + 3,
    );
    edit_changes_ingest_key(
        &sandbox,
        "i3d_human.yaml",
        &[
            ("I3D_HUMAN_ROOT", &data),
            ("SMPL_NEUTRAL_NPZ", &model.join("model.npz")),
        ],
        &["ingest.dataset.sequence=ID2_1"],
        &data.join("ID2_1-train/masks/frame_000000_view_01.png"),
    );
}

#[test]
fn dna_rendering_yaml_ingests_the_fixture() {
    let sandbox = Sandbox::new();
    let data = sandbox.path().join("dna");
    write_fixture("dna", &data);
    ingest_and_inspect(
        &sandbox,
        "dna_rendering.yaml",
        &[
            ("DNA_RENDERING_ROOT", &data),
            ("SMPLX_NEUTRAL_NPZ", &data.join("smplx.npz")),
        ],
        &[],
        // Train cameras 0 and 2 on frames 0..2, test camera 48 on frame 0 (every 5th).
        2 * 3 + 1,
    );
}

/// The synthetic pipelines load (configs validated, keys derived) without running anything,
/// the history pipeline with its per-row evals and the authors' input scaling, the ablation
/// with its seeds.
#[test]
fn synthetic_pipelines_load() {
    let sandbox = Sandbox::new();
    for name in [
        "synthetic.yaml",
        "ablation_synthetic.yaml",
        "tradeoff_synthetic.yaml",
        "history_synthetic.yaml",
        "garment_synthetic.yaml",
    ] {
        let status = sandbox.ok(&["status", &pipeline_file(name)]);
        assert!(status.contains("missing"), "{name}: {status}");
    }
    let status = sandbox.ok(&["status", &pipeline_file("history_synthetic.yaml")]);
    for stage in ["motion_authors", "eval_b_pose", "eval_e_authors"] {
        assert!(status.contains(stage), "{stage}: {status}");
    }
    // The garment study: the oracle row on the oracle motion entry, the static control.
    let status = sandbox.ok(&["status", &pipeline_file("garment_synthetic.yaml")]);
    for stage in [
        "motion_oracle",
        "eval_oracle",
        "eval_static_b_pose",
        "eval_one_a",
    ] {
        assert!(status.contains(stage), "{stage}: {status}");
    }
    // The ablation: rows (a)-(e) and the oracle x 3 seeds, each evaluated.
    let status = sandbox.ok(&["status", &pipeline_file("ablation_synthetic.yaml")]);
    for stage in [
        "eval_a_none_s1",
        "eval_c_skeleton_s2",
        "eval_e_multiscale_s3",
        "motion_oracle",
        "eval_oracle_s2",
    ] {
        assert!(status.contains(stage), "{stage}: {status}");
    }
}

/// Every stage's cache key of the pipeline file `file`, by stage name (the keys of a fresh
/// local cache: nothing is run).
fn stage_keys(file: &Path) -> std::collections::BTreeMap<String, (String, String)> {
    let registry = seqavatar_registry::registry();
    let pipeline = seqavatar_engine::Pipeline::load(file, &registry, &[])
        .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    let cache = tempfile::tempdir().unwrap();
    let store = seqavatar_engine::LocalStore::open(cache.path()).unwrap();
    let keys = seqavatar_engine::compute_keys(&pipeline, &registry, &store).unwrap();
    pipeline
        .stages
        .iter()
        .map(|stage| {
            let key = keys[&stage.name].key.clone();
            (stage.name.clone(), (stage.kind.clone(), key))
        })
        .collect()
}

/// The sweeps written as `matrix:` stanzas expand to the runs that were written by hand (the
/// committed `tests/fixtures/pipelines/*_by_hand.yaml`), with the same cache keys, so no
/// cached entry is recomputed: the ablation with the same stage names, the trade-off study
/// with the same set of train and eval keys (its seeded rows got systematic names).
#[test]
fn matrix_sweeps_keep_the_cache_keys_of_the_hand_written_runs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let by_hand = |name: &str| root.join(format!("tests/fixtures/pipelines/{name}_by_hand.yaml"));

    let ablation = stage_keys(&root.join("pipelines/ablation_synthetic.yaml"));
    assert_eq!(ablation.len(), 4 + 2 * 18);
    assert_eq!(ablation, stage_keys(&by_hand("ablation_synthetic")));
    let ablation_text = std::fs::read_to_string(root.join("pipelines/ablation_synthetic.yaml"));
    assert!(ablation_text.unwrap().lines().count() < 60);

    let keys_by_kind = |keys: &std::collections::BTreeMap<String, (String, String)>| {
        let mut pairs: Vec<(String, String)> = keys.values().cloned().collect();
        pairs.sort();
        pairs
    };
    let tradeoff = stage_keys(&root.join("pipelines/tradeoff_synthetic.yaml"));
    let tradeoff_by_hand = stage_keys(&by_hand("tradeoff_synthetic"));
    assert_eq!(tradeoff.len(), 3 + 2 * 27);
    assert_eq!(keys_by_kind(&tradeoff), keys_by_kind(&tradeoff_by_hand));
    // The shared entries are the ablation's (its motion entry reaches further back).
    for stage in ["ingest", "fit"] {
        assert_eq!(tradeoff[stage], ablation[stage], "{stage}");
    }
}
