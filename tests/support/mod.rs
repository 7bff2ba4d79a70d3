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

/// Every stage kind, as the `pipeline` binary registers them, for tests that run pipelines in
/// process.
pub fn registry() -> Registry {
    seqavatar_registry::registry()
}
