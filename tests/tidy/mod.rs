//! Conventions the code keeps, checked on the sources.

use std::path::{Path, PathBuf};

/// Every `.rs` file under `dir` (recursively).
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let entries = std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for entry in entries {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|ext| ext == "rs") {
            out.push(path);
        }
    }
}

/// Whether a line picks a code path by the backend, as
/// `grep "match.*backend\|Backend::Cpu\|Backend::Gpu"` finds it.
fn names_the_backend(line: &str) -> bool {
    let matches_on_it = line
        .find("match")
        .is_some_and(|at| line[at..].contains("backend"));
    matches_on_it || line.contains("Backend::Cpu") || line.contains("Backend::Gpu")
}

/// The backend is chosen once (ARCHITECTURE.md, invariants): in the stage crates (sources,
/// tests, benches, examples) only `seqavatar_avatar::device::avatar_backend` looks at which
/// backend it is; everything else calls through the `AvatarBackend` it builds.
#[test]
fn the_backend_is_chosen_in_one_place() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    rust_files(&root.join("stages"), &mut files);
    assert!(files.len() > 50, "only {} files under stages/", files.len());
    let chooser = root.join("stages/avatar/src/device.rs");
    let mut elsewhere = Vec::new();
    let mut in_chooser = 0;
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for (number, line) in text.lines().enumerate() {
            if !names_the_backend(line) {
                continue;
            }
            if file == &chooser {
                in_chooser += 1;
            } else {
                elsewhere.push(format!("{}:{}: {line}", file.display(), number + 1));
            }
        }
    }
    assert!(
        elsewhere.is_empty(),
        "the backend is chosen in `avatar_backend` only, but:\n{}",
        elsewhere.join("\n")
    );
    assert!(
        in_chooser > 0,
        "`avatar_backend` no longer names the backends"
    );
}
