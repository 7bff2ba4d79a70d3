//! Shared helpers of the ingest tests: running the Python fixture writers and reading their
//! expectations.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// The repository's `tests/fixtures` folder.
pub fn fixtures_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures")
}

/// Runs `python3 tests/fixtures/<script> <args...>`; fails the test with an install hint when
/// Python or one of its packages is missing.
pub fn run_python(script: &str, args: &[&str]) {
    let script_path = fixtures_dir().join(script);
    let output = Command::new("python3")
        .arg(&script_path)
        .args(args)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "these tests write their fixtures with python3 ({e}); install Python 3 with \
                 `pip install numpy h5py pillow`"
            )
        });
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        if stderr.contains("ModuleNotFoundError") || stderr.contains("ImportError") {
            panic!(
                "the fixture writer {} needs numpy, h5py and pillow: `pip install numpy h5py \
                 pillow`\n{stderr}",
                script_path.display()
            );
        }
        panic!("fixture writer {} failed:\n{stderr}", script_path.display());
    }
}

/// Writes a dataset fixture (`zju`, `i3d`, `dna`, `smpl`, `smplx`) into a fresh temp dir.
pub fn dataset_fixture(kind: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("temp dir");
    run_python(
        "write_datasets.py",
        &[kind, dir.path().to_str().expect("utf-8 temp path")],
    );
    dir
}

pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn f64s(value: &serde_json::Value) -> Vec<f64> {
    match value {
        serde_json::Value::Array(items) => items.iter().flat_map(f64s).collect(),
        serde_json::Value::Number(n) => vec![n.as_f64().expect("number")],
        other => panic!("not numeric: {other}"),
    }
}

pub fn assert_close(actual: &[f64], expected: &[f64], tolerance: f64, what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        assert!(
            (a - e).abs() <= tolerance * (1.0 + e.abs()),
            "{what}[{i}]: {a} vs expected {e}"
        );
    }
}
