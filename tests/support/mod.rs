//! Shared helpers of the integration tests: a temporary folder with its own cache in which
//! the real `pipeline` binary runs.

#![allow(dead_code)]

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

use seqavatar_engine::Registry;

/// A temporary folder with a cache and pipeline files.
pub struct Sandbox {
    dir: tempfile::TempDir,
}

impl Sandbox {
    pub fn new() -> Self {
        Self {
            dir: tempfile::tempdir().expect("temporary folder"),
        }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    pub fn cache(&self) -> PathBuf {
        self.path().join("cache")
    }

    pub fn write(&self, name: &str, text: &str) -> PathBuf {
        let path = self.path().join(name);
        fs::write(&path, text).expect("write pipeline");
        path
    }

    pub fn command(&self, args: &[&str]) -> Command {
        let mut command = Command::new(env!("CARGO_BIN_EXE_pipeline"));
        command
            .current_dir(self.path())
            .env_remove("SEQAVATAR_CACHE")
            .arg("--cache")
            .arg(self.cache())
            .args(args);
        command
    }

    pub fn run(&self, args: &[&str]) -> Output {
        self.command(args).output().expect("run pipeline binary")
    }

    pub fn ok(&self, args: &[&str]) -> String {
        let output = self.run(args);
        assert!(
            output.status.success(),
            "pipeline {args:?} failed:\nstdout:\n{}\nstderr:\n{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stdout).into_owned()
    }

    pub fn fails(&self, args: &[&str]) -> String {
        let output = self.run(args);
        assert!(
            !output.status.success(),
            "pipeline {args:?} should fail; stdout:\n{}",
            String::from_utf8_lossy(&output.stdout)
        );
        String::from_utf8_lossy(&output.stderr).into_owned()
    }

    pub fn spawn(&self, args: &[&str]) -> Child {
        self.command(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn pipeline binary")
    }

    /// (stage, kind, key, state) rows of `pipeline status`.
    pub fn status(&self, file: &str) -> Vec<(String, String, String, String)> {
        self.ok(&["status", file])
            .lines()
            .skip(1)
            .map(|line| {
                let cells: Vec<&str> = line.split_whitespace().collect();
                assert_eq!(cells.len(), 4, "status line {line:?}");
                (
                    cells[0].to_string(),
                    cells[1].to_string(),
                    cells[2].to_string(),
                    cells[3].to_string(),
                )
            })
            .collect()
    }

    pub fn key_of(&self, file: &str, stage: &str) -> String {
        self.status(file)
            .into_iter()
            .find(|row| row.0 == stage)
            .unwrap_or_else(|| panic!("no stage {stage}"))
            .2
    }

    pub fn state_of(&self, file: &str, stage: &str) -> String {
        self.status(file)
            .into_iter()
            .find(|row| row.0 == stage)
            .unwrap_or_else(|| panic!("no stage {stage}"))
            .3
    }

    pub fn count_lines(&self, name: &str) -> usize {
        fs::read_to_string(self.path().join(name))
            .map(|text| text.lines().count())
            .unwrap_or(0)
    }
}

/// The sandbox's cache made read-only for the commands of [`ReadOnlyCache::command`], as a
/// published or shared cache is: its permissions stripped (`chmod -R a-w`) and, where that
/// does not stop writes (as root), each command run in a private mount namespace with the
/// cache bind-mounted read-only (`unshare`). Permissions come back on drop.
pub struct ReadOnlyCache<'s> {
    sandbox: &'s Sandbox,
    bind_mount: bool,
}

/// The shell step that bind-mounts `$1` read-only, then runs the rest of the arguments.
const READ_ONLY_MOUNT: &str =
    r#"mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && shift && exec "$@""#;

impl<'s> ReadOnlyCache<'s> {
    /// `None`, saying why, where neither way can make the cache read-only; a failure instead
    /// when `CI` is set.
    pub fn new(sandbox: &'s Sandbox) -> Option<Self> {
        let chmod = |mode: &str| {
            let status = Command::new("chmod")
                .args(["-R", mode])
                .arg(sandbox.cache())
                .status()
                .expect("run chmod");
            assert!(status.success(), "chmod -R {mode} failed");
        };
        chmod("a-w");
        let probe = sandbox.cache().join("write-probe");
        if fs::write(&probe, b"").is_err() {
            return Some(Self {
                sandbox,
                bind_mount: false,
            });
        }
        fs::remove_file(&probe).expect("remove the write probe");
        let mounted = Command::new("unshare")
            .args(["-rm", "sh", "-c", READ_ONLY_MOUNT, "sh"])
            .arg(sandbox.cache())
            .arg("true")
            .output()
            .is_ok_and(|output| output.status.success());
        if mounted {
            return Some(Self {
                sandbox,
                bind_mount: true,
            });
        }
        chmod("u+w");
        let why = "permissions do not stop this user's writes (root) and `unshare -rm` cannot \
                   bind-mount the cache read-only here";
        // CI must run the read-only tests, not pass them by skipping (as the browser test).
        assert!(std::env::var_os("CI").is_none(), "CI is set, but {why}");
        eprintln!("skipped: {why}");
        None
    }

    /// `pipeline ARGS` on the read-only cache.
    pub fn command(&self, args: &[&str]) -> Command {
        let sandbox = self.sandbox;
        if !self.bind_mount {
            return sandbox.command(args);
        }
        let mut command = Command::new("unshare");
        command
            .current_dir(sandbox.path())
            .env_remove("SEQAVATAR_CACHE")
            .args(["-rm", "sh", "-c", READ_ONLY_MOUNT, "sh"])
            .arg(sandbox.cache())
            .arg(env!("CARGO_BIN_EXE_pipeline"))
            .arg("--cache")
            .arg(sandbox.cache())
            .args(args);
        command
    }

    /// Runs `pipeline ARGS` on the read-only cache; its stdout and stderr.
    pub fn run(&self, args: &[&str]) -> (bool, String, String) {
        let output = self.command(args).output().expect("run pipeline binary");
        (
            output.status.success(),
            String::from_utf8_lossy(&output.stdout).into_owned(),
            String::from_utf8_lossy(&output.stderr).into_owned(),
        )
    }

    /// Like [`Sandbox::ok`], on the read-only cache; returns stdout and stderr.
    pub fn ok(&self, args: &[&str]) -> (String, String) {
        let (success, stdout, stderr) = self.run(args);
        assert!(
            success,
            "pipeline {args:?} failed on the read-only cache:\nstdout:\n{stdout}\nstderr:\n{stderr}"
        );
        (stdout, stderr)
    }
}

impl Drop for ReadOnlyCache<'_> {
    fn drop(&mut self) {
        let _ = Command::new("chmod")
            .args(["-R", "u+w"])
            .arg(self.sandbox.cache())
            .status();
    }
}

/// Waits until `child` has written `path`; a child that ends first fails the test, showing
/// its stderr.
pub fn wait_for_file(child: &mut Child, path: &Path) {
    let started = std::time::Instant::now();
    while !path.exists() {
        if let Some(status) = child.try_wait().expect("poll the child") {
            let mut stderr = String::new();
            if let Some(mut pipe) = child.stderr.take() {
                let _ = std::io::Read::read_to_string(&mut pipe, &mut stderr);
            }
            panic!(
                "ended ({status}) before writing {}:\n{stderr}",
                path.display()
            );
        }
        assert!(
            started.elapsed().as_secs() < 300,
            "{} was never written",
            path.display()
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Asserts that `gc` (its stdout `report`) skipped every entry of `ids` (`kind/key`) as read
/// by a running pipeline, and that the reader `child` outlived it (else the test proves
/// nothing).
pub fn assert_gc_skipped(report: &str, ids: &[String], child: &mut Child) {
    assert!(
        child.try_wait().expect("poll the child").is_none(),
        "the reader ended before gc did: the test proves nothing\n{report}"
    );
    for id in ids {
        assert!(
            report.contains(&format!("skipped {id}: a running pipeline reads it")),
            "gc did not skip {id}:\n{report}"
        );
    }
}

/// Every stage kind, as the `pipeline` binary registers them, for tests that run pipelines in
/// process.
pub fn registry() -> Registry {
    seqavatar_registry::registry()
}
