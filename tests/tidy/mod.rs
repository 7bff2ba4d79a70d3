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

/// The backend factories: the only files that look at which backend a `Backend` is, each
/// when what it builds is built (ARCHITECTURE.md, invariants).
const BACKEND_FACTORIES: [&str; 3] = [
    // `avatar_backend`: the `AvatarBackend` of the host paths.
    "src/avatar/src/device.rs",
    // `frame_path`: a sequence rendered on the host or on the device.
    "src/avatar/src/sequence.rs",
    // `training_step`: the host or the device-resident training step.
    "stages/train/src/step/mod.rs",
];

/// The backend is chosen once (ARCHITECTURE.md, invariants): in the stage crates and the
/// libraries (sources, tests, benches, examples) only the [`BACKEND_FACTORIES`] look at which
/// backend it is, by matching on it (checked in stages/ and src/avatar/; the compute library
/// implements the backends) or by asking for its gpu (`.gpu()`, anywhere under stages/ and
/// src/); everything else calls through what they build.
#[test]
fn the_backend_is_chosen_in_one_place() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut matched = Vec::new();
    rust_files(&root.join("stages"), &mut matched);
    rust_files(&root.join("src/avatar"), &mut matched);
    let mut asked = Vec::new();
    rust_files(&root.join("stages"), &mut asked);
    rust_files(&root.join("src"), &mut asked);
    assert!(
        matched.len() > 50 && asked.len() > matched.len(),
        "only {} files under stages/ and src/avatar/, {} under stages/ and src/",
        matched.len(),
        asked.len()
    );
    let factories: Vec<_> = BACKEND_FACTORIES.iter().map(|f| root.join(f)).collect();
    let mut elsewhere = Vec::new();
    let mut in_factories = vec![0; factories.len()];
    for (files, looks) in [
        (&matched, names_the_backend as fn(&str) -> bool),
        (&asked, |line: &str| line.contains(".gpu()")),
    ] {
        for file in files {
            let text = std::fs::read_to_string(file).unwrap();
            for (number, line) in text.lines().enumerate() {
                if !looks(line) {
                    continue;
                }
                match factories.iter().position(|factory| factory == file) {
                    Some(factory) => in_factories[factory] += 1,
                    None => elsewhere.push(format!("{}:{}: {line}", file.display(), number + 1)),
                }
            }
        }
    }
    assert!(
        elsewhere.is_empty(),
        "the backend is chosen in {BACKEND_FACTORIES:?} only, but:\n{}",
        elsewhere.join("\n")
    );
    for (factory, count) in BACKEND_FACTORIES.iter().zip(in_factories) {
        assert!(count > 0, "{factory} no longer names the backends");
    }
}

/// The repository root.
fn repository_root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The `## Code map` section of ARCHITECTURE.md.
fn code_map(architecture: &str) -> &str {
    let start = architecture
        .find("\n## Code map")
        .expect("ARCHITECTURE.md has a `## Code map` section");
    let rest = &architecture[start + 1..];
    let end = rest[3..].find("\n## ").map_or(rest.len(), |at| at + 3);
    &rest[..end]
}

/// The workspace members listed in the root `Cargo.toml` (`members = [ "src/core", ... ]`).
fn workspace_members(manifest: &str) -> Vec<String> {
    let start = manifest
        .find("members = [")
        .expect("Cargo.toml lists the workspace members");
    let list = &manifest[start..];
    let list = &list[..list.find(']').expect("the members list is closed")];
    list.split('"')
        .skip(1)
        .step_by(2)
        .map(str::to_owned)
        .collect()
}

/// Top-level folders that are not ignored build or run outputs: every one not hidden, minus
/// the root-anchored names of `.gitignore` (`/target`, `/out/`; `/cache/*` keeps `cache`).
fn top_level_folders(root: &Path) -> Vec<String> {
    let ignore = std::fs::read_to_string(root.join(".gitignore")).unwrap_or_default();
    let ignored: Vec<&str> = ignore
        .lines()
        .filter_map(|line| line.trim().strip_prefix('/'))
        .map(|name| name.trim_end_matches('/'))
        .filter(|name| !name.contains(['/', '*']))
        .collect();
    let mut folders = Vec::new();
    for entry in std::fs::read_dir(root).unwrap() {
        let entry = entry.unwrap();
        let name = entry.file_name().to_string_lossy().into_owned();
        if entry.path().is_dir() && !name.starts_with('.') && !ignored.contains(&name.as_str()) {
            folders.push(name);
        }
    }
    folders.sort();
    folders
}

/// The backquoted spans of a Markdown text.
fn code_spans(text: &str) -> Vec<&str> {
    text.split('`').skip(1).step_by(2).collect()
}

/// Whether a relative path exists, where `*` in its last component matches any run of
/// characters (`shaders/splat_*.wgsl`).
fn path_exists(root: &Path, path: &str) -> bool {
    let Some(star) = path.rfind('*') else {
        return root.join(path).exists();
    };
    let slash = path[..star].rfind('/').map_or(0, |at| at + 1);
    let (folder, pattern) = (&path[..slash], &path[slash..]);
    let (prefix, suffix) = pattern.split_once('*').unwrap();
    let Ok(entries) = std::fs::read_dir(root.join(folder)) else {
        return false;
    };
    entries.filter_map(Result::ok).any(|entry| {
        let name = entry.file_name().to_string_lossy().into_owned();
        name.len() >= prefix.len() + suffix.len()
            && name.starts_with(prefix)
            && name.ends_with(suffix)
    })
}

/// ARCHITECTURE.md stays true: its code map has an entry for every workspace crate and
/// every top-level folder, and every repository path it names (a code span starting with a
/// top-level folder, e.g. `src/avatar/src/device.rs`; `<placeholders>` are not paths)
/// exists.
#[test]
fn the_code_map_names_every_crate_and_folder_and_only_paths_that_exist() {
    let root = repository_root();
    let architecture = std::fs::read_to_string(root.join("ARCHITECTURE.md")).unwrap();
    let map = code_map(&architecture);
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();

    let members = workspace_members(&manifest);
    assert!(members.len() >= 9, "members: {members:?}");
    let mut missing: Vec<String> = members
        .iter()
        .filter(|member| !map.contains(&format!("### `{member}`")))
        .map(|member| format!("crate `{member}` (a `### `{member}`` entry)"))
        .collect();
    let folders = top_level_folders(root);
    for required in ["src", "stages", "shaders", "tests", "pipelines", "docs"] {
        assert!(folders.iter().any(|f| f == required), "{folders:?}");
    }
    missing.extend(
        folders
            .iter()
            .filter(|folder| !map.contains(&format!("### `{folder}/")))
            .map(|folder| format!("folder `{folder}/` (a `### `{folder}/`` entry)")),
    );
    assert!(
        missing.is_empty(),
        "ARCHITECTURE.md's code map lacks:\n{}",
        missing.join("\n")
    );

    let mut folders_and_hidden = folders.clone();
    folders_and_hidden.push(".ci".to_owned());
    let mut named = 0;
    let mut absent = Vec::new();
    for span in code_spans(&architecture) {
        let path = span.trim_end_matches(['.', ',', ';', ':']);
        let first = path.split('/').next().unwrap_or_default();
        if !path.contains('/')
            || path.contains(['<', ' ', '{'])
            || !folders_and_hidden.iter().any(|folder| folder == first)
        {
            continue;
        }
        named += 1;
        if !path_exists(root, path) {
            absent.push(path.to_owned());
        }
    }
    assert!(named > 20, "only {named} paths found in ARCHITECTURE.md");
    assert!(
        absent.is_empty(),
        "ARCHITECTURE.md names paths that do not exist:\n{}",
        absent.join("\n")
    );
}

/// Source comments cite the method notes at their place in the repository,
/// `docs/method.md`, and no source names an absolute path of a build machine.
#[test]
fn method_notes_are_cited_by_their_repository_path() {
    let root = repository_root();
    assert!(root.join("docs/method.md").is_file());
    let mut files = Vec::new();
    for folder in ["src", "stages", "tests", "fuzz"] {
        rust_files(&root.join(folder), &mut files);
    }
    assert!(files.len() > 100, "only {} files", files.len());
    // This file's own needles are not citations.
    let this_file = root.join("tests/tidy/mod.rs");
    let mut wrong = Vec::new();
    for file in files.iter().filter(|file| **file != this_file) {
        let text = std::fs::read_to_string(file).unwrap();
        for (number, line) in text.lines().enumerate() {
            // Spelled in two parts so that this file is no citation itself.
            let bare_citation = line
                .match_indices(concat!("method", ".md"))
                .any(|(at, _)| !line[..at].ends_with("docs/"));
            let absolute = ["/work/", "/home/", "/Users/"]
                .iter()
                .any(|prefix| line.contains(prefix));
            if bare_citation || absolute {
                wrong.push(format!("{}:{}: {line}", file.display(), number + 1));
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "cite `docs/method.md` and no absolute paths:\n{}",
        wrong.join("\n")
    );
}
