//! Engine tests against the real binary: caching, keys, crash safety, concurrency,
//! corruption, malformed pipelines, inspect and gc. They use the built-in `test_arrays` kind.

use std::fs;
use std::path::Path;
use std::time::{Duration, Instant};

use crate::support::Sandbox;

/// A two-stage pipeline: `a` feeds `b`.
fn two_stages(a_config: &str, b_config: &str) -> String {
    format!(
        "stages:\n  - name: a\n    kind: test_arrays\n    config: {{{a_config}}}\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n    config: {{{b_config}}}\n"
    )
}

/// The summary table rows (stage, result) of `pipeline run` output.
fn results(stdout: &str) -> Vec<(String, String)> {
    stdout
        .lines()
        .skip(1)
        .filter(|line| !line.contains(" stages: "))
        .map(|line| {
            let cells: Vec<&str> = line.split_whitespace().collect();
            (cells[0].to_string(), cells[3].to_string())
        })
        .collect()
}

fn wait_for(what: &str, timeout: Duration, mut condition: impl FnMut() -> bool) {
    let start = Instant::now();
    while !condition() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn second_run_recomputes_nothing() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        &two_stages(
            "size: 8, count_file: count",
            "size: 8, seed: 3, count_file: count",
        ),
    );
    let first = sandbox.ok(&["run", "p.yaml"]);
    assert_eq!(
        results(&first),
        [("a".into(), "ran".into()), ("b".into(), "ran".into())]
    );
    assert!(first.contains("backend"), "{first}");
    assert_eq!(sandbox.count_lines("count"), 2);
    let second = sandbox.ok(&["run", "p.yaml"]);
    assert_eq!(
        results(&second),
        [("a".into(), "cached".into()), ("b".into(), "cached".into())]
    );
    assert!(second.contains("2 stages: 0 ran, 2 cached"), "{second}");
    assert_eq!(sandbox.count_lines("count"), 2);
    for (_, _, _, state) in sandbox.status("p.yaml") {
        assert_eq!(state, "cached");
    }
}

#[test]
fn keys_follow_config_upstream_and_not_key_order() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p1.yaml",
        &two_stages("size: 8, seed: 1", "size: 8, chunk: 2"),
    );
    sandbox.write(
        "p2.yaml",
        &two_stages("seed: 1, size: 8", "chunk: 2, size: 8"),
    );
    // Defaults written out explicitly give the same key.
    sandbox.write(
        "p3.yaml",
        &two_stages(
            "seed: 1, size: 8, sleep_ms: 0, steps: 1",
            "chunk: 2, size: 8",
        ),
    );
    sandbox.write(
        "p4.yaml",
        &two_stages("size: 8, seed: 2", "size: 8, chunk: 2"),
    );
    sandbox.write(
        "p5.yaml",
        &two_stages("size: 8, seed: 1", "size: 8, chunk: 4"),
    );
    let keys = |file: &str| (sandbox.key_of(file, "a"), sandbox.key_of(file, "b"));
    let (a1, b1) = keys("p1.yaml");
    assert_eq!(keys("p2.yaml"), (a1.clone(), b1.clone()));
    assert_eq!(keys("p3.yaml"), (a1.clone(), b1.clone()));
    // Changed upstream config: both keys change.
    let (a4, b4) = keys("p4.yaml");
    assert_ne!(a4, a1);
    assert_ne!(b4, b1);
    // Changed own config: only that key changes.
    let (a5, b5) = keys("p5.yaml");
    assert_eq!(a5, a1);
    assert_ne!(b5, b1);
    // --set changes the key like an edit of the file.
    let set_key = sandbox
        .ok(&["status", "p1.yaml", "--set", "a.seed=2"])
        .lines()
        .find(|line| line.starts_with("a "))
        .map(|line| line.split_whitespace().nth(2).unwrap().to_string())
        .unwrap();
    assert_eq!(set_key, a4);
}

#[test]
fn killed_run_leaves_no_entry_and_next_run_resumes() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        "stages:\n  - name: slow\n    kind: test_arrays\n    config: {sleep_ms: 3000, steps: 30, count_file: count}\n",
    );
    let mut child = sandbox.spawn(&["run", "p.yaml"]);
    let staging = sandbox.cache().join(".staging").join("test_arrays");
    wait_for("a recorded step", Duration::from_secs(60), || {
        fs::read_dir(&staging)
            .into_iter()
            .flatten()
            .flatten()
            .any(|entry| entry.path().join("work").join("steps_done").exists())
    });
    child.kill().expect("kill the run");
    let status = child.wait().expect("wait for the killed run");
    assert!(!status.success());
    // Nothing visible: the key is not cached, but the work folder makes it resumable.
    assert_eq!(sandbox.state_of("p.yaml", "slow"), "partial");
    let key = sandbox.key_of("p.yaml", "slow");
    assert!(
        !sandbox
            .cache()
            .join("test_arrays")
            .join(format!("{key}.complete"))
            .exists()
    );
    let output = sandbox.run(&["run", "p.yaml"]);
    assert!(output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("resuming at step"), "{stderr}");
    assert!(stderr.contains("cleaned up partial output"), "{stderr}");
    assert_eq!(sandbox.state_of("p.yaml", "slow"), "cached");
    assert_eq!(sandbox.count_lines("count"), 2);
    // Publishing removed the staging area.
    assert!(
        !sandbox
            .cache()
            .join(".staging/test_arrays")
            .join(&key)
            .exists()
    );
    assert_eq!(results(&sandbox.ok(&["run", "p.yaml"]))[0].1, "cached");
}

#[test]
fn concurrent_runs_compute_each_stage_once() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        &two_stages(
            "sleep_ms: 800, count_file: count",
            "sleep_ms: 300, seed: 5, count_file: count",
        ),
    );
    let first = sandbox.spawn(&["run", "p.yaml"]);
    let second = sandbox.spawn(&["run", "p.yaml"]);
    let outputs = [
        first.wait_with_output().unwrap(),
        second.wait_with_output().unwrap(),
    ];
    let mut ran = 0;
    for output in &outputs {
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        ran += results(&String::from_utf8_lossy(&output.stdout))
            .iter()
            .filter(|(_, result)| result == "ran")
            .count();
    }
    assert_eq!(sandbox.count_lines("count"), 2, "each stage computed once");
    assert_eq!(ran, 2);
}

#[test]
fn corrupted_chunk_is_reported_and_recomputed() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        &two_stages("count_file: count", "count_file: count"),
    );
    sandbox.ok(&["run", "p.yaml"]);
    let key = sandbox.key_of("p.yaml", "a");
    let chunk = sandbox
        .cache()
        .join("test_arrays")
        .join(&key)
        .join("values/c/1");
    let mut bytes = fs::read(&chunk).expect("chunk file");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x5a;
    fs::write(&chunk, bytes).unwrap();
    let output = sandbox.run(&["run", "p.yaml"]);
    assert!(output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("array \"values\": file values/c/1 does not match its digest"),
        "{stderr}"
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert_eq!(
        results(&stdout),
        [("a".into(), "ran".into()), ("b".into(), "cached".into())]
    );
    assert_eq!(sandbox.count_lines("count"), 3);
    // A deleted chunk is caught the same way.
    fs::remove_file(&chunk).unwrap();
    let stderr = sandbox.run(&["run", "p.yaml"]).stderr;
    assert!(String::from_utf8_lossy(&stderr).contains("file values/c/1 is missing"));
    assert_eq!(results(&sandbox.ok(&["run", "p.yaml"]))[0].1, "cached");
    assert_eq!(sandbox.count_lines("count"), 4);
}

#[test]
fn malformed_pipelines_are_rejected_before_running() {
    let sandbox = Sandbox::new();
    let cases: &[(&str, &str)] = &[
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      count_file: count\n      sizee: 3\n",
            "bad.yaml:6: stage \"a\": config key \"sizee\": unknown field `sizee`",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config: {count_file: count, size: [1]}\n",
            "bad.yaml:4: stage \"a\": config key \"size\": invalid type",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config: {count_file: count}\n  - name: b\n    kind: tset_arrays\n",
            "bad.yaml:6: stage \"b\": unknown stage kind \"tset_arrays\"",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config: {count_file: count}\n    inputs: [c]\n",
            "bad.yaml:5: stage \"a\": input \"c\" is not a stage of this pipeline",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config: {count_file: count}\n    inputs: [b]\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n",
            "the inputs form a cycle",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    colour: red\n",
            "bad.yaml:4: stage \"a\": unknown key \"colour\"",
        ),
        (
            "stages:\n  - name: a\n    kind: test_arrays\n    config: {count_file: \"${SEQAVATAR_SURELY_UNSET_VAR}\"}\n",
            "environment variable SEQAVATAR_SURELY_UNSET_VAR is not set",
        ),
        (
            "stages:\n  - name: a\n    kind: [test_arrays\n",
            "bad.yaml:",
        ),
    ];
    for (text, expected) in cases {
        sandbox.write("bad.yaml", text);
        let stderr = sandbox.fails(&["run", "bad.yaml"]);
        assert!(
            stderr.contains(expected),
            "expected {expected:?} in {stderr:?}"
        );
        assert_eq!(sandbox.count_lines("count"), 0, "nothing may run");
    }
    sandbox.write("good.yaml", &two_stages("count_file: count", ""));
    let stderr = sandbox.fails(&["run", "good.yaml", "--set", "a.chunk=zero"]);
    assert!(stderr.contains("config key \"chunk\""), "{stderr}");
    let stderr = sandbox.fails(&["run", "good.yaml", "--until", "zz"]);
    assert!(
        stderr.contains("--until zz: no stage named \"zz\""),
        "{stderr}"
    );
    assert_eq!(sandbox.count_lines("count"), 0);
}

#[test]
fn until_force_and_failures() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        &two_stages("count_file: count", "count_file: count"),
    );
    let until = sandbox.ok(&["run", "p.yaml", "--until", "a"]);
    assert_eq!(results(&until), [("a".into(), "ran".into())]);
    assert_eq!(sandbox.state_of("p.yaml", "b"), "missing");
    let forced = sandbox.ok(&["run", "p.yaml", "--force", "a"]);
    assert_eq!(
        results(&forced),
        [("a".into(), "ran".into()), ("b".into(), "ran".into())]
    );
    assert!(forced.contains("forced"), "{forced}");
    assert_eq!(sandbox.count_lines("count"), 3);
    // A failing stage reports itself and publishes nothing.
    sandbox.write(
        "fail.yaml",
        "stages:\n  - name: f\n    kind: test_arrays\n    config: {steps: 3, fail_at: 2}\n",
    );
    let stderr = sandbox.fails(&["run", "fail.yaml"]);
    assert!(
        stderr.contains("stage \"f\" (kind test_arrays") && stderr.contains("failing at step 2"),
        "{stderr}"
    );
    assert_eq!(sandbox.state_of("fail.yaml", "f"), "partial");
}

#[test]
fn inspect_prints_arrays_and_exports_pictures() {
    let sandbox = Sandbox::new();
    sandbox.write(
        "p.yaml",
        &two_stages("size: 6, chunk: 4", "size: 6, seed: 1"),
    );
    sandbox.ok(&["run", "p.yaml"]);
    let text = sandbox.ok(&["inspect", "p.yaml:b"]);
    for expected in [
        "kind test_arrays",
        "values",
        "float64",
        "[6]",
        "uint8",
        "[6, 6, 3]",
        "input     a",
        "attribute sum",
    ] {
        assert!(text.contains(expected), "{expected:?} missing in\n{text}");
    }
    // b's values are 1 + i + i for i in 0..6: min 1, max 11, mean 6.
    let values_line = text
        .lines()
        .find(|line| line.starts_with("values "))
        .unwrap();
    assert!(
        values_line.contains("1.000000  11.000000  6.000000  0"),
        "{values_line}"
    );
    let key = sandbox.key_of("p.yaml", "b");
    let folder = sandbox.cache().join("test_arrays").join(&key);
    let by_path = sandbox.ok(&["inspect", folder.join("values").to_str().unwrap()]);
    assert!(by_path.contains("units = \"counts\""), "{by_path}");
    sandbox.ok(&["inspect", "p.yaml:b:image", "--png", "image.png"]);
    let png = image_size(&sandbox.path().join("image.png"));
    assert_eq!(png, (6, 6));
    sandbox.ok(&[
        "inspect",
        "p.yaml:b",
        "--picture",
        "values",
        "--opt",
        "height=10",
        "--png",
        "bars.png",
    ]);
    assert_eq!(image_size(&sandbox.path().join("bars.png")), (6, 10));
    sandbox.ok(&["inspect", "p.yaml:b:image", "--exr", "image.exr"]);
    let exr = fs::read(sandbox.path().join("image.exr")).unwrap();
    assert_eq!(&exr[..4], &[0x76, 0x2f, 0x31, 0x01], "OpenEXR magic");
    let stderr = sandbox.fails(&["inspect", "p.yaml:b:values", "--png", "v.png"]);
    assert!(stderr.contains("not image-like"), "{stderr}");
    let stderr = sandbox.fails(&["inspect", "p.yaml:b:nothing"]);
    assert!(stderr.contains("no array \"nothing\""), "{stderr}");
    // An unknown picture names the ones the stage kind draws (from its `pictures()`).
    let stderr = sandbox.fails(&["inspect", "p.yaml:b", "--picture", "bars", "--png", "x.png"]);
    assert!(
        stderr.contains("no picture named \"bars\" (it has: values)"),
        "{stderr}"
    );
}

/// Width and height from a PNG header.
fn image_size(path: &Path) -> (u32, u32) {
    let bytes = fs::read(path).expect("png file");
    assert_eq!(&bytes[1..4], b"PNG");
    let width = u32::from_be_bytes(bytes[16..20].try_into().unwrap());
    let height = u32::from_be_bytes(bytes[20..24].try_into().unwrap());
    (width, height)
}

#[test]
fn gc_keeps_only_listed_pipelines() {
    let sandbox = Sandbox::new();
    sandbox.write("keep.yaml", &two_stages("seed: 1", ""));
    sandbox.write("drop.yaml", &two_stages("seed: 2", ""));
    sandbox.ok(&["run", "keep.yaml"]);
    sandbox.ok(&["run", "drop.yaml"]);
    let dry = sandbox.ok(&["gc", "--keep", "keep.yaml", "--dry-run"]);
    assert_eq!(dry.matches("would remove test_arrays/").count(), 2, "{dry}");
    assert_eq!(sandbox.state_of("drop.yaml", "a"), "cached");
    let removed = sandbox.ok(&["gc", "--keep", "keep.yaml"]);
    assert_eq!(
        removed.matches("removed test_arrays/").count(),
        2,
        "{removed}"
    );
    assert_eq!(sandbox.state_of("drop.yaml", "a"), "missing");
    assert_eq!(sandbox.state_of("drop.yaml", "b"), "missing");
    assert_eq!(sandbox.state_of("keep.yaml", "a"), "cached");
    assert_eq!(sandbox.state_of("keep.yaml", "b"), "cached");
}

#[test]
fn gc_skips_entries_a_running_pipeline_reads_until_it_dies() {
    let sandbox = Sandbox::new();
    sandbox.write("p.yaml", &two_stages("", "sleep_ms: 60000, steps: 600"));
    // Keys derive from configs, so they are known before anything runs.
    let a = sandbox.key_of("p.yaml", "a");
    let b = sandbox.key_of("p.yaml", "b");
    let mut child = sandbox.spawn(&["run", "p.yaml"]);
    // Wait for a step of b itself: a (one step) writes the same `work/steps_done` in its own
    // staging folder before it is published, and gc must see a published.
    let b_steps = sandbox
        .cache()
        .join(".staging")
        .join("test_arrays")
        .join(&b)
        .join("work")
        .join("steps_done");
    wait_for("a step of b", Duration::from_secs(60), || b_steps.exists());
    // b is running with a as its input: gc (keeping nothing) must leave a alone.
    let report = sandbox.ok(&["gc"]);
    assert!(
        report.contains(&format!(
            "skipped test_arrays/{a}: a running pipeline reads it"
        )),
        "{report}"
    );
    assert!(report.contains("skipped 1 in use"), "{report}");
    assert_eq!(sandbox.state_of("p.yaml", "a"), "cached");
    // A killed reader leaves no lock behind; its orphaned work folder goes too.
    child.kill().expect("kill the run");
    child.wait().expect("wait for the killed run");
    let report = sandbox.ok(&["gc"]);
    assert!(
        report.contains(&format!("removed test_arrays/{a}")),
        "{report}"
    );
    assert!(
        report.contains(&format!("removed the work folder of test_arrays/{b}")),
        "{report}"
    );
    assert_eq!(sandbox.state_of("p.yaml", "a"), "missing");
    assert_eq!(sandbox.state_of("p.yaml", "b"), "missing");
}

#[test]
fn edited_attributes_and_missing_chunks_are_never_served() {
    let sandbox = Sandbox::new();
    sandbox.write("p.yaml", &two_stages("", ""));
    sandbox.ok(&["run", "p.yaml"]);
    let key = sandbox.key_of("p.yaml", "a");
    let folder = sandbox.cache().join("test_arrays").join(&key);
    let folder_arg = folder.to_str().expect("utf-8 temp path").to_string();
    let verified = sandbox.ok(&["status", "--verify", "p.yaml"]);
    assert_eq!(verified.matches(" cached").count(), 2, "{verified}");

    // A deleted chunk: inspect names the entry and the array instead of printing zeros.
    let chunk = folder.join("values/c/1");
    let bytes = fs::read(&chunk).unwrap();
    fs::remove_file(&chunk).unwrap();
    let error = sandbox.fails(&["inspect", &folder_arg]);
    assert!(
        error.contains(&format!("entry a ({folder_arg})"))
            && error.contains(
                "array \"values\": chunk file values/c/1 is listed in the manifest but missing from the store"
            ),
        "{error}"
    );
    let error = sandbox.fails(&["status", "--verify", "p.yaml"]);
    assert!(
        error.contains("cached entries fail verification"),
        "{error}"
    );
    fs::write(&chunk, bytes).unwrap();
    sandbox.ok(&["inspect", &folder_arg]);

    // An edited stage attribute in the group zarr.json.
    let group = folder.join("zarr.json");
    let mut document: serde_json::Value =
        serde_json::from_slice(&fs::read(&group).unwrap()).unwrap();
    assert_eq!(document["attributes"]["sum"], serde_json::json!(120.0));
    document["attributes"]["sum"] = serde_json::json!(121.0);
    fs::write(&group, serde_json::to_vec_pretty(&document).unwrap()).unwrap();
    let output = sandbox.run(&["status", "--verify", "p.yaml"]);
    assert!(!output.status.success());
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains("corrupt a: ")
            && stdout.contains("zarr.json (group attributes) does not match its digest"),
        "{stdout}"
    );
    // The next run recomputes it; b (same key, computed from the right data) stays cached.
    let rerun = results(&sandbox.ok(&["run", "p.yaml"]));
    assert_eq!(rerun[0], ("a".to_string(), "ran".to_string()));
    assert_eq!(rerun[1], ("b".to_string(), "cached".to_string()));
    sandbox.ok(&["status", "--verify", "p.yaml"]);
}

/// `inspect` checks what it prints against the manifest, under the read lease `gc`
/// respects: a chunk swapped for another entry's (valid zstd and CRC, other values) or an
/// edited attribute is still shown, but flagged "UNVERIFIED" on stderr with a failing exit
/// status; an array of the same entry that is intact prints as usual.
#[test]
fn inspect_verifies_what_it_prints() {
    let sandbox = Sandbox::new();
    sandbox.write("p.yaml", &two_stages("seed: 1", ""));
    sandbox.write("q.yaml", &two_stages("seed: 2", ""));
    sandbox.ok(&["run", "p.yaml"]);
    sandbox.ok(&["run", "q.yaml"]);
    let folder = |file: &str| {
        sandbox
            .cache()
            .join("test_arrays")
            .join(sandbox.key_of(file, "a"))
    };
    let (entry, other) = (folder("p.yaml"), folder("q.yaml"));

    // Read under its lease: the reader lock file is made again when it is gone.
    let locks = sandbox.cache().join(".locks");
    fs::remove_dir_all(&locks).unwrap();
    let sound = sandbox.ok(&["inspect", "p.yaml:a"]);
    let key = sandbox.key_of("p.yaml", "a");
    assert!(
        locks
            .join("test_arrays")
            .join(format!("{key}.read"))
            .is_file()
    );

    let chunk = entry.join("values/c/0");
    let original = fs::read(&chunk).unwrap();
    fs::copy(other.join("values/c/0"), &chunk).unwrap();
    let values_arg = entry.join("values").display().to_string();
    for target in ["p.yaml:a", "p.yaml:a:values", values_arg.as_str()] {
        let output = sandbox.run(&["inspect", target]);
        let (stdout, stderr) = (
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr),
        );
        assert!(!output.status.success(), "{target}: {stdout}");
        assert!(
            stderr.contains("UNVERIFIED")
                && stderr.contains(&format!("test_arrays/{key}"))
                && stderr.contains("values/c/0 does not match its digest"),
            "{target}: {stderr}"
        );
        // What it read is still shown, for the diagnosis: the swapped values.
        let values_line = stdout
            .lines()
            .find(|line| line.starts_with("values "))
            .unwrap();
        assert!(!sound.contains(values_line), "{values_line}");
    }
    sandbox.ok(&["inspect", "p.yaml:a:image"]);
    fs::write(&chunk, &original).unwrap();
    assert_eq!(sandbox.ok(&["inspect", "p.yaml:a"]), sound);

    // An edited attribute.
    let group = entry.join("zarr.json");
    let mut document: serde_json::Value =
        serde_json::from_slice(&fs::read(&group).unwrap()).unwrap();
    document["attributes"]["sum"] = serde_json::json!(1e6);
    fs::write(&group, serde_json::to_vec_pretty(&document).unwrap()).unwrap();
    for target in ["p.yaml:a", "p.yaml:a:image"] {
        let stderr = sandbox.fails(&["inspect", target]);
        assert!(
            stderr.contains("UNVERIFIED") && stderr.contains("zarr.json (group attributes)"),
            "{target}: {stderr}"
        );
    }
}

/// A read-only cache (permissions stripped, or a read-only bind mount where the tests run as
/// root) serves what it holds: a fully cached `run`, `status --verify`, `inspect` and
/// `gc --dry-run` work without making a lock file, saying once that they read without
/// leases; a run that must compute, and `gc`, fail with one message naming the cache.
#[test]
fn a_read_only_cache_serves_reads() {
    let sandbox = Sandbox::new();
    sandbox.write("p.yaml", &two_stages("", ""));
    sandbox.write("q.yaml", &two_stages("seed: 9", ""));
    sandbox.ok(&["run", "p.yaml"]);
    let locks = sandbox.cache().join(".locks");
    fs::remove_dir_all(&locks).unwrap();
    let Some(cache) = crate::support::ReadOnlyCache::new(&sandbox) else {
        return;
    };
    let cache_text = sandbox.cache().display().to_string();
    let note = format!("the cache {cache_text} is read-only here");
    let (stdout, stderr) = cache.ok(&["run", "p.yaml"]);
    assert!(stdout.contains("2 stages: 0 ran, 2 cached"), "{stdout}");
    assert_eq!(stderr.matches(&note).count(), 1, "said once: {stderr}");
    assert!(stderr.contains("without read leases"), "{stderr}");
    let (stdout, stderr) = cache.ok(&["status", "--verify", "p.yaml"]);
    assert_eq!(stdout.matches(" cached").count(), 2, "{stdout}");
    assert_eq!(stderr.matches(&note).count(), 1, "{stderr}");
    let (stdout, _) = cache.ok(&["inspect", "p.yaml:b"]);
    assert!(stdout.contains("kind test_arrays"), "{stdout}");
    // A dry run of gc says what a gc that can write the cache would remove.
    let (stdout, _) = cache.ok(&["gc", "--dry-run"]);
    assert_eq!(
        stdout.matches("would remove test_arrays/").count(),
        2,
        "{stdout}"
    );
    for args in [&["run", "q.yaml"][..], &["gc"]] {
        let (success, _, stderr) = cache.run(args);
        assert!(!success, "{args:?} wrote to a read-only cache");
        assert!(
            stderr.contains(&note) && stderr.contains("nothing can be computed"),
            "{args:?}: {stderr}"
        );
    }
    assert!(!locks.exists(), "lock files were made in a read-only cache");
    drop(cache);
    // Writable again, the same cache computes.
    sandbox.ok(&["run", "q.yaml"]);
}

/// Every file under `dir` (recursively), relative to `root`, with `/` separators.
fn files_under(root: &Path, dir: &Path, out: &mut Vec<String>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files_under(root, &path, out);
        } else {
            let relative = path.strip_prefix(root).unwrap();
            out.push(relative.to_string_lossy().replace('\\', "/"));
        }
    }
}

/// A published entry folder is a Zarr v3 group that holds only Zarr nodes, so zarr-python
/// and xarray open it without warnings: every file is a node's `zarr.json` or a chunk under
/// an array's `c/` folder. Its completion marker is the file `<key>.complete` beside it.
#[test]
fn published_entries_hold_only_zarr_nodes() {
    let sandbox = Sandbox::new();
    sandbox.write("p.yaml", &two_stages("size: 8", "size: 8, seed: 3"));
    sandbox.ok(&["run", "p.yaml"]);
    for stage in ["a", "b"] {
        let key = sandbox.key_of("p.yaml", stage);
        let kind_dir = sandbox.cache().join("test_arrays");
        let entry = kind_dir.join(&key);
        assert!(
            kind_dir.join(format!("{key}.complete")).is_file(),
            "{stage}"
        );
        let mut files = Vec::new();
        files_under(&entry, &entry, &mut files);
        assert!(files.contains(&"zarr.json".to_string()), "{files:?}");
        let strays: Vec<&String> = files
            .iter()
            .filter(|file| {
                let is_metadata = file.rsplit('/').next() == Some("zarr.json");
                let is_chunk = file.split('/').rev().skip(1).any(|part| part == "c");
                !(is_metadata || is_chunk)
            })
            .collect();
        assert!(strays.is_empty(), "{stage}: not Zarr nodes: {strays:?}");
    }
    // `inspect` takes the entry folder itself.
    let folder = sandbox
        .cache()
        .join("test_arrays")
        .join(sandbox.key_of("p.yaml", "a"));
    sandbox.ok(&["inspect", folder.to_str().unwrap()]);
}
