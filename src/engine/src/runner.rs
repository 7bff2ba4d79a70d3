//! The runner: computes keys in topological order, reuses verified entries, computes the
//! missing ones under the per-key lock, and publishes them. Also the [`StageContext`] that
//! stages see while they run.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::io::IsTerminal as _;
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime};

use anyhow::Context as _;
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::Registry;
use crate::entry::{
    EntryReader, EntryWriter, Manifest, ManifestExternalFile, ManifestInput, ReadLease,
};
use crate::key::{FileDigests, KeyMaterial, stage_key};
use crate::pipeline::{Pipeline, StageSpec};
use crate::store::{EntryId, EntryState, KeyLock, Staging, Store};

/// The file (in the store's local state folder) remembering external file digests.
const FILE_DIGEST_MEMO: &str = ".file-digests.json";
/// A log line starting with this prefix names the compute backend for the run summary.
pub const BACKEND_LOG_PREFIX: &str = "backend:";

/// Progress bars and log lines; plain stderr lines when stderr is not a terminal.
pub(crate) struct Progress {
    multi: MultiProgress,
    visible: bool,
}

impl Progress {
    pub(crate) fn new() -> Self {
        let visible = std::io::stderr().is_terminal();
        let target = if visible {
            ProgressDrawTarget::stderr()
        } else {
            ProgressDrawTarget::hidden()
        };
        Self {
            multi: MultiProgress::with_draw_target(target),
            visible,
        }
    }

    pub(crate) fn println(&self, message: &str) {
        if self.visible {
            // A failed terminal write is not worth aborting a stage for.
            let _ = self.multi.println(message);
        } else {
            eprintln!("{message}");
        }
    }

    fn spinner(&self, message: String) -> ProgressBar {
        let bar = self.multi.add(ProgressBar::new_spinner());
        bar.set_style(
            ProgressStyle::with_template("{spinner} {msg} [{elapsed}]")
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
        );
        bar.set_message(message);
        bar.enable_steady_tick(Duration::from_millis(120));
        bar
    }

    fn bar(&self, len: u64, message: String) -> ProgressBar {
        let bar = self.multi.add(ProgressBar::new(len));
        bar.set_style(
            ProgressStyle::with_template("  {msg} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        bar.set_message(message);
        bar
    }
}

/// What a running stage sees: its config, its inputs, its output and a work folder.
pub struct StageContext<'a> {
    stage_name: &'a str,
    key: &'a str,
    inputs: &'a [EntryReader],
    output: &'a EntryWriter,
    work_dir: &'a Path,
    progress: &'a Progress,
    log: Mutex<Vec<String>>,
    warnings: Mutex<Vec<String>>,
}

impl StageContext<'_> {
    /// The stage's name in the pipeline.
    pub fn stage_name(&self) -> &str {
        self.stage_name
    }

    /// The key of the entry being computed.
    pub fn key(&self) -> &str {
        self.key
    }

    /// The unique input of stage kind `kind`.
    pub fn input(&self, kind: &str) -> anyhow::Result<&EntryReader> {
        let mut matching = self.inputs.iter().filter(|input| input.kind() == kind);
        let first = matching.next().ok_or_else(|| {
            anyhow::anyhow!(
                "stage \"{}\" needs an input of kind \"{kind}\"; its inputs are: {}",
                self.stage_name,
                describe_inputs(self.inputs)
            )
        })?;
        anyhow::ensure!(
            matching.next().is_none(),
            "stage \"{}\" has several inputs of kind \"{kind}\" ({}); expected one",
            self.stage_name,
            describe_inputs(self.inputs)
        );
        Ok(first)
    }

    /// All inputs, in the order the pipeline lists them.
    pub fn inputs(&self) -> &[EntryReader] {
        self.inputs
    }

    /// Where the stage writes its arrays.
    pub fn output(&self) -> &EntryWriter {
        self.output
    }

    /// A folder that persists across interrupted runs of the same key (checkpoints); it is
    /// deleted after the entry is published.
    pub fn work_dir(&self) -> &Path {
        self.work_dir
    }

    /// A progress bar shown under the stage's line.
    pub fn progress_bar(&self, len: u64, message: &str) -> ProgressBar {
        self.progress
            .bar(len, format!("{}: {message}", self.stage_name))
    }

    /// Prints a line and records it in the manifest `log`. A line `backend: NAME` names the
    /// compute backend in the run summary.
    pub fn log(&self, message: &str) {
        self.progress
            .println(&format!("[{}] {message}", self.stage_name));
        self.log
            .lock()
            .expect("log poisoned")
            .push(message.to_string());
    }

    /// Prints a warning and records it in the manifest `warnings`.
    pub fn warn(&self, message: &str) {
        self.progress
            .println(&format!("[{}] warning: {message}", self.stage_name));
        self.warnings
            .lock()
            .expect("warnings poisoned")
            .push(message.to_string());
    }
}

fn describe_inputs(inputs: &[EntryReader]) -> String {
    if inputs.is_empty() {
        return "none".to_string();
    }
    inputs
        .iter()
        .map(|input| format!("{} ({})", input.stage_name(), input.kind()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The key of one stage and the external file digests that went into it.
#[derive(Debug, Clone)]
pub struct StageKey {
    pub key: String,
    pub external_files: Vec<ManifestExternalFile>,
}

/// Checks that every external file still has the digest its stage's key was computed from;
/// the error names the first that changed.
fn external_files_unchanged(
    store: &dyn Store,
    files: &[ManifestExternalFile],
) -> Result<(), String> {
    if files.is_empty() {
        return Ok(());
    }
    let mut digests = FileDigests::load(&store.local_state_dir().join(FILE_DIGEST_MEMO));
    digests.exclude(&store.local_state_dir());
    for file in files {
        match digests.digest(Path::new(&file.path)) {
            Ok(digest) if digest == file.digest => {}
            Ok(_) => {
                return Err(format!(
                    "external input {} changed while the stage ran",
                    file.path
                ));
            }
            Err(error) => {
                return Err(format!(
                    "external input {} cannot be read again after the stage ({error:#})",
                    file.path
                ));
            }
        }
    }
    // Best effort: the memo only saves hashing next time.
    let _ = digests.save();
    Ok(())
}

/// Computes the keys of the stages at `indices` (and, needed for them, their ancestors).
pub fn compute_keys(
    pipeline: &Pipeline,
    registry: &Registry,
    store: &dyn Store,
) -> anyhow::Result<BTreeMap<String, StageKey>> {
    let mut digests = FileDigests::load(&store.local_state_dir().join(FILE_DIGEST_MEMO));
    digests.exclude(&store.local_state_dir());
    let mut keys: BTreeMap<String, StageKey> = BTreeMap::new();
    for &index in pipeline.order() {
        let stage = &pipeline.stages[index];
        let kind = registry
            .get(&stage.kind)
            .ok_or_else(|| anyhow::anyhow!("unknown stage kind \"{}\"", stage.kind))?;
        let files = kind
            .external_files(&stage.typed)
            .with_context(|| format!("stage \"{}\": cannot list its external files", stage.name))?;
        let mut external_files = Vec::with_capacity(files.len());
        for file in files {
            let digest = digests
                .digest(&file)
                .with_context(|| format!("stage \"{}\"", stage.name))?;
            external_files.push(ManifestExternalFile {
                path: file.display().to_string(),
                digest,
            });
        }
        let input_keys: Vec<String> = stage
            .inputs
            .iter()
            .map(|input| keys[input].key.clone())
            .collect();
        let external_digests: Vec<String> = external_files
            .iter()
            .map(|file| file.digest.clone())
            .collect();
        let key = stage_key(&KeyMaterial {
            kind: &stage.kind,
            version: kind.version(),
            config: &stage.config,
            input_keys: &input_keys,
            external_digests: &external_digests,
        });
        keys.insert(
            stage.name.clone(),
            StageKey {
                key,
                external_files,
            },
        );
    }
    // The memo is an optimisation; failing to save it must not fail the run.
    let _ = digests.save();
    Ok(keys)
}

/// Options of `pipeline run`.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Run only this stage and its ancestors.
    pub until: Option<String>,
    /// Recompute these stages even when cached.
    pub force: Vec<String>,
}

/// How a stage's entry was obtained.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    Cached,
    Ran,
    /// Recomputed because `--force` or a corrupt entry.
    Recomputed(String),
}

impl std::fmt::Display for Outcome {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Outcome::Cached => write!(formatter, "cached"),
            Outcome::Ran => write!(formatter, "ran"),
            Outcome::Recomputed(reason) => write!(formatter, "ran ({reason})"),
        }
    }
}

/// One row of the run summary.
#[derive(Debug, Clone)]
pub struct StageReport {
    pub name: String,
    pub kind: String,
    pub key: String,
    pub outcome: Outcome,
    pub seconds: f64,
    pub backend: Option<String>,
}

/// The stages selected by `until` (that stage and its ancestors), in topological order.
pub fn selected_stages<'p>(
    pipeline: &'p Pipeline,
    until: Option<&str>,
) -> anyhow::Result<Vec<&'p StageSpec>> {
    let wanted: Option<BTreeSet<String>> = match until {
        None => None,
        Some(name) => {
            anyhow::ensure!(
                pipeline.stage(name).is_some(),
                "--until {name}: no stage named \"{name}\" in {} (stages: {})",
                pipeline.file.display(),
                pipeline.stage_names().join(", ")
            );
            Some(pipeline.ancestors_and_self(name))
        }
    };
    Ok(pipeline
        .order()
        .iter()
        .map(|&index| &pipeline.stages[index])
        .filter(|stage| wanted.as_ref().is_none_or(|set| set.contains(&stage.name)))
        .collect())
}

/// Opens a published entry and checks every file against its manifest.
pub fn open_verified(store: &dyn Store, id: &EntryId) -> Result<EntryReader, String> {
    let reader = store.open_entry(id).map_err(|error| format!("{error:#}"))?;
    let problems = entry_problems(&reader, id, None);
    if problems.is_empty() {
        Ok(reader)
    } else {
        Err(problems.join("; "))
    }
}

/// What in `reader`, opened as the entry `id`, does not match its manifest: the entry it
/// names, the group metadata, and the files of every array (of the array `only`, when
/// given). The one check behind `run`'s reuse, `status --verify`, `inspect` and every
/// reader outside a run.
pub fn entry_problems(reader: &EntryReader, id: &EntryId, only: Option<&str>) -> Vec<String> {
    if reader.kind() != id.kind || reader.key() != id.key {
        return vec![format!(
            "manifest names {}/{}, expected {id}",
            reader.kind(),
            reader.key()
        )];
    }
    match only {
        None => reader.verify(),
        Some(name) => [reader.verify_metadata(), reader.verify_array(name)].concat(),
    }
}

/// Opens a published entry for a command that reads it outside a run (`render`, `export`,
/// `report`): takes the read lease `gc` respects (held as long as the returned reader or a
/// clone of it lives) and verifies the entry as `run` does, so a tampered or damaged entry
/// is refused rather than used.
pub fn open_leased_verified(store: &dyn Store, id: &EntryId) -> anyhow::Result<EntryReader> {
    let lease = store.read_lease(id)?;
    let reader = open_verified(store, id).map_err(|problems| {
        anyhow::anyhow!(
            "entry {id} is corrupt ({problems}); `pipeline run` on its pipeline recomputes it"
        )
    })?;
    Ok(reader.holding(lease))
}

/// Runs the pipeline: reuses verified entries and computes the missing ones.
pub fn run(
    pipeline: &Pipeline,
    registry: &Registry,
    store: &dyn Store,
    options: &RunOptions,
) -> anyhow::Result<Vec<StageReport>> {
    for name in &options.force {
        anyhow::ensure!(
            pipeline.stage(name).is_some(),
            "--force {name}: no stage named \"{name}\" in {} (stages: {})",
            pipeline.file.display(),
            pipeline.stage_names().join(", ")
        );
    }
    let progress = Progress::new();
    for line in store.clean_leftovers()? {
        progress.println(&format!("cleaned up {line}"));
    }
    let keys = compute_keys(pipeline, registry, store)?;
    let stages = selected_stages(pipeline, options.until.as_deref())?;
    let mut run = Run {
        registry,
        store,
        options,
        progress: &progress,
        reports: Vec::new(),
        leases: Vec::new(),
        readers: HashMap::new(),
    };
    for stage in stages {
        run.stage(stage, &keys[&stage.name])?;
    }
    Ok(run.reports)
}

/// What the steps of one run share.
struct Run<'r> {
    registry: &'r Registry,
    store: &'r dyn Store,
    options: &'r RunOptions,
    progress: &'r Progress,
    reports: Vec<StageReport>,
    /// Shared read leases on every entry this run uses, held until it returns: `gc` skips
    /// entries that a run reads.
    leases: Vec<Box<dyn ReadLease>>,
    /// The entry of each stage done so far, by stage name.
    readers: HashMap<String, EntryReader>,
}

/// One stage of a run, as its steps see it.
struct StageJob<'j> {
    stage: &'j StageSpec,
    kind: &'j dyn crate::erased::ErasedStage,
    stage_key: &'j StageKey,
    id: EntryId,
    forced: bool,
    started: Instant,
}

impl StageJob<'_> {
    /// The summary row of this stage.
    fn report(&self, outcome: Outcome, log: &[String]) -> StageReport {
        StageReport {
            name: self.stage.name.clone(),
            kind: self.stage.kind.clone(),
            key: self.stage_key.key.clone(),
            outcome,
            seconds: self.started.elapsed().as_secs_f64(),
            backend: backend_of(log),
        }
    }
}

impl Run<'_> {
    /// Reuses the stage's verified entry, or computes and publishes it under the key's lock.
    fn stage(&mut self, stage: &StageSpec, stage_key: &StageKey) -> anyhow::Result<()> {
        let (store, progress) = (self.store, self.progress);
        let kind = self
            .registry
            .get(&stage.kind)
            .ok_or_else(|| anyhow::anyhow!("unknown stage kind \"{}\"", stage.kind))?;
        let forced = self.options.force.contains(&stage.name);
        let job = StageJob {
            stage,
            kind,
            stage_key,
            id: EntryId::new(&stage.kind, &stage_key.key),
            forced,
            started: Instant::now(),
        };
        let id = &job.id;
        let mut recompute_reason: Option<String> = forced.then(|| "forced".to_string());

        self.leases.push(store.read_lease(id)?);
        if !forced && store.entry_state(id)? == EntryState::Complete {
            match open_verified(store, id) {
                Ok(reader) => {
                    self.reuse(&job, reader);
                    return Ok(());
                }
                Err(problems) => {
                    progress.println(&format!(
                        "[{}] cached entry {id} is corrupt ({problems}); recomputing",
                        stage.name
                    ));
                    recompute_reason = Some("corrupt entry".to_string());
                }
            }
        }

        let lock = store
            .lock(id, &mut || {
                progress.println(&format!(
                    "[{}] waiting for another run computing {id}",
                    stage.name
                ));
            })
            .with_context(|| format!("stage \"{}\" ({id}) must be computed", stage.name))?;
        // Another run may have published it while we waited.
        if !forced && store.entry_state(id)? == EntryState::Complete {
            match open_verified(store, id) {
                Ok(reader) => {
                    self.reuse(&job, reader);
                    return Ok(());
                }
                Err(problems) => {
                    let moved = store.quarantine(lock.as_ref())?;
                    progress.println(&format!(
                        "[{}] entry {id} is corrupt ({problems}); moved to {moved}",
                        stage.name
                    ));
                    recompute_reason = Some("corrupt entry".to_string());
                }
            }
        } else if store.entry_state(id)? != EntryState::Missing {
            store.quarantine(lock.as_ref())?;
        }
        self.compute(&job, lock, recompute_reason)
    }

    /// Records a verified published entry as the stage's result.
    fn reuse(&mut self, job: &StageJob<'_>, reader: EntryReader) {
        self.reports
            .push(job.report(Outcome::Cached, &reader.manifest().log));
        self.readers.insert(job.stage.name.clone(), reader);
    }

    /// Runs the stage kind into a fresh staging area, checks what it read did not change, and
    /// publishes the entry.
    fn compute(
        &mut self,
        job: &StageJob<'_>,
        lock: Box<dyn KeyLock>,
        recompute_reason: Option<String>,
    ) -> anyhow::Result<()> {
        let (store, progress) = (self.store, self.progress);
        let StageJob {
            stage,
            stage_key,
            ref id,
            forced,
            ..
        } = *job;
        let inputs: Vec<EntryReader> = stage
            .inputs
            .iter()
            .map(|input| self.readers[input].clone())
            .collect();
        if forced && store.has_resumable_work(id) {
            // `--force` starts over: the work folder (checkpoints) of an earlier run goes too.
            store.remove_staging(lock.as_ref())?;
            progress.println(&format!(
                "[{}] forced: removed the work folder of an earlier run",
                stage.name
            ));
        }
        let staging = store.begin_staging(lock.as_ref())?;
        let writer = EntryWriter::create(&staging.output_dir)?;
        let started_at = SystemTime::now();
        let (log, warnings) = match self.run_kind(job, &inputs, &writer, &staging) {
            Ok(log_and_warnings) => log_and_warnings,
            Err(error) => {
                // A stage that failed (rather than a run that was killed) discards its partial
                // output now, so the next run has nothing to clean up and report as a killed
                // run; the work folder stays for resume.
                drop(writer);
                if let Err(e) = std::fs::remove_dir_all(&staging.output_dir) {
                    progress.println(&format!(
                        "cannot remove the partial output {}: {e}",
                        staging.output_dir.display()
                    ));
                }
                return Err(error.context(format!(
                    "stage \"{}\" (kind {}, key {}) failed",
                    stage.name,
                    stage.kind,
                    &stage_key.key[..12]
                )));
            }
        };
        check_reads_unchanged(store, job, &inputs, &staging)?;
        let mut manifest = manifest_of(job, &inputs, started_at, log, warnings);
        writer
            .finish(&mut manifest)
            .with_context(|| format!("stage \"{}\": cannot finish its entry", stage.name))?;
        drop(writer);
        crate::entry::validate_staged(
            &staging.output_dir,
            &format!("stage \"{}\" ({id})", stage.name),
        )
        .with_context(|| {
            format!(
                "stage \"{}\": its entry cannot be read back, nothing was published",
                stage.name
            )
        })?;
        store
            .publish(lock.as_ref(), &staging)
            .with_context(|| format!("stage \"{}\": cannot publish {id}", stage.name))?;
        drop(lock);
        let reader = store.open_entry(id)?;
        let outcome = match recompute_reason {
            Some(reason) => Outcome::Recomputed(reason),
            None => Outcome::Ran,
        };
        self.reports.push(job.report(outcome, &manifest.log));
        self.readers.insert(stage.name.clone(), reader);
        Ok(())
    }

    /// Runs the stage kind (a panic is its error) behind a spinner; returns its log and
    /// warnings.
    fn run_kind(
        &self,
        job: &StageJob<'_>,
        inputs: &[EntryReader],
        writer: &EntryWriter,
        staging: &Staging,
    ) -> anyhow::Result<(Vec<String>, Vec<String>)> {
        let StageJob {
            stage,
            kind,
            stage_key,
            ..
        } = *job;
        let resumed = self.store.has_resumable_work(&job.id);
        let spinner = self.progress.spinner(format!(
            "{} ({}, {})",
            stage.name,
            stage.kind,
            &stage_key.key[..12]
        ));
        let mut context = StageContext {
            stage_name: &stage.name,
            key: &stage_key.key,
            inputs,
            output: writer,
            work_dir: &staging.work_dir,
            progress: self.progress,
            log: Mutex::new(Vec::new()),
            warnings: Mutex::new(Vec::new()),
        };
        if resumed {
            context.log("resuming from the work folder of an interrupted run");
        }
        let result =
            std::panic::catch_unwind(AssertUnwindSafe(|| kind.run(&stage.typed, &mut context)))
                .unwrap_or_else(|panic| {
                    let text = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_else(|| "unknown panic".to_string());
                    Err(anyhow::anyhow!("panicked: {text}"))
                });
        spinner.finish_and_clear();
        result?;
        let log = context.log.into_inner().expect("log poisoned");
        let warnings = context.warnings.into_inner().expect("warnings poisoned");
        Ok((log, warnings))
    }
}

/// The manifest of a stage's new entry (digests filled in by `EntryWriter::finish`).
fn manifest_of(
    job: &StageJob<'_>,
    inputs: &[EntryReader],
    started_at: SystemTime,
    log: Vec<String>,
    warnings: Vec<String>,
) -> Manifest {
    let StageJob {
        stage,
        kind,
        stage_key,
        started,
        ..
    } = *job;
    let finished_at = SystemTime::now();
    Manifest {
        kind: stage.kind.clone(),
        version: kind.version(),
        stage_name: stage.name.clone(),
        key: stage_key.key.clone(),
        config: stage.config.clone(),
        inputs: inputs
            .iter()
            .map(|input| ManifestInput {
                stage_name: input.stage_name().to_string(),
                kind: input.kind().to_string(),
                key: input.key().to_string(),
            })
            .collect(),
        external_files: stage_key.external_files.clone(),
        tool_version: crate::TOOL_VERSION.to_string(),
        // Filled in by `finish`, with the array digests.
        metadata_digest: String::new(),
        arrays: BTreeMap::new(),
        wall_time_s: started.elapsed().as_secs_f64(),
        started_at: crate::timefmt::rfc3339(started_at),
        finished_at: crate::timefmt::rfc3339(finished_at),
        log,
        warnings,
    }
}

/// Refuses to publish when what the stage read changed while it ran; the partial output goes
/// as for a failed stage.
fn check_reads_unchanged(
    store: &dyn Store,
    job: &StageJob<'_>,
    inputs: &[EntryReader],
    staging: &Staging,
) -> anyhow::Result<()> {
    let stage = job.stage;
    // Inputs that changed while the stage read them (a chunk deleted or rewritten) must
    // not produce a published entry.
    for input in inputs {
        let problems = input.verify();
        if !problems.is_empty() {
            let _ = std::fs::remove_dir_all(&staging.output_dir);
            anyhow::bail!(
                "stage \"{}\": input {} ({}) changed while the stage ran, nothing was published: {}",
                stage.name,
                input.stage_name(),
                input.location(),
                problems.join("; ")
            );
        }
    }
    // External files (dataset files) edited while the stage read them: hashed again now
    // (the memo re-hashes any file whose size, times or inode changed), so an entry is
    // never published under the key of what the files were before.
    if let Err(problem) = external_files_unchanged(store, &job.stage_key.external_files) {
        let _ = std::fs::remove_dir_all(&staging.output_dir);
        anyhow::bail!(
            "stage \"{}\": {problem}; nothing was published (run it again once the \
             files are stable)",
            stage.name
        );
    }
    Ok(())
}

/// The backend named by a `backend: NAME` log line, if any.
pub fn backend_of(log: &[String]) -> Option<String> {
    log.iter().rev().find_map(|line| {
        line.strip_prefix(BACKEND_LOG_PREFIX)
            .map(|rest| rest.trim().to_string())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::StageKind;
    use crate::builtin::TestArrays;
    use crate::config::ConfigError;
    use crate::local::LocalStore;
    use std::path::PathBuf;

    /// `test_arrays` with another implementation version.
    struct Bumped;

    impl StageKind for Bumped {
        type Config = <TestArrays as StageKind>::Config;
        fn kind(&self) -> &'static str {
            "test_arrays"
        }
        fn version(&self) -> u32 {
            TestArrays.version() + 1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            TestArrays.input_kinds()
        }
        fn resolve_config(&self, raw: &serde_json::Value) -> Result<Self::Config, ConfigError> {
            TestArrays.resolve_config(raw)
        }
        fn run(&self, config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            TestArrays.run(config, ctx)
        }
    }

    /// Reads its input, then deletes one of the input's chunks (as a careless `rm` or a `gc`
    /// without reader locks would) before writing its own array.
    struct Vandal;

    impl StageKind for Vandal {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "vandal"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &["test_arrays"]
        }
        fn run(&self, _config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            let input = ctx.input("test_arrays")?;
            let values = input.read::<f64>("values")?;
            std::fs::remove_file(Path::new(input.location()).join("values/c/0"))?;
            ctx.output()
                .write_array::<f64>("copy", &["index"], &[16], &[16], &values.data)
        }
    }

    #[test]
    fn inputs_changed_during_a_stage_are_not_published() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let mut registry = Registry::new();
        registry.add(Box::new(Vandal));
        let text = "stages:\n  - name: a\n    kind: test_arrays\n  - name: v\n    kind: vandal\n    inputs: [a]\n";
        let pipeline = Pipeline::parse(text, Path::new("p.yaml"), &registry, &[]).unwrap();
        let error = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap_err();
        let message = format!("{error:#}");
        assert!(
            message.contains("input a (")
                && message.contains("changed while the stage ran, nothing was published")
                && message.contains("values/c/0 is missing"),
            "{message}"
        );
        let keys = compute_keys(&pipeline, &registry, &store).unwrap();
        let vandal = EntryId::new("vandal", &keys["v"].key);
        assert_eq!(store.entry_state(&vandal).unwrap(), EntryState::Missing);
        // The damaged input is found and recomputed by the next run; the chunk is deleted
        // again, so the stage fails again rather than publishing.
        let error = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap_err();
        assert!(format!("{error:#}").contains("changed while the stage ran"));
    }

    /// Depends on the external file named by its config, and appends to it while it runs
    /// (a dataset edited during ingest).
    struct Editor;

    impl StageKind for Editor {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "editor"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &[]
        }
        fn external_files(&self, config: &serde_json::Value) -> anyhow::Result<Vec<PathBuf>> {
            Ok(vec![PathBuf::from(config["file"].as_str().unwrap())])
        }
        fn run(&self, config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            let path = PathBuf::from(config["file"].as_str().unwrap());
            let before = std::fs::read(&path)?;
            std::fs::write(&path, [before.as_slice(), b" edited"].concat())?;
            ctx.output()
                .write_array::<f64>("length", &["one"], &[1], &[1], &[before.len() as f64])
        }
    }

    #[test]
    fn an_external_file_edited_during_a_stage_is_not_published() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(&dir.path().join("cache")).unwrap();
        let data = dir.path().join("dataset.txt");
        std::fs::write(&data, b"frames").unwrap();
        let mut registry = Registry::new();
        registry.add(Box::new(Editor));
        let text = format!(
            "stages:\n  - name: e\n    kind: editor\n    config: {{file: {}}}\n",
            data.display()
        );
        let pipeline = Pipeline::parse(&text, Path::new("p.yaml"), &registry, &[]).unwrap();
        let keys = compute_keys(&pipeline, &registry, &store).unwrap();
        let error = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap_err();
        let message = format!("{error:#}");
        assert!(
            message.contains("dataset.txt changed while the stage ran")
                && message.contains("nothing was published"),
            "{message}"
        );
        let entry = EntryId::new("editor", &keys["e"].key);
        assert_eq!(store.entry_state(&entry).unwrap(), EntryState::Missing);
    }

    /// Counts its attempts in its work folder, then fails.
    struct Flaky;

    impl StageKind for Flaky {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "flaky"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &[]
        }
        fn run(&self, _config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            let path = ctx.work_dir().join("attempts");
            let attempts = std::fs::read_to_string(&path).unwrap_or_default() + "x";
            std::fs::write(&path, &attempts)?;
            anyhow::bail!("failed after {} attempts", attempts.len())
        }
    }

    #[test]
    fn force_starts_over_without_the_work_folder() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let mut registry = Registry::new();
        registry.add(Box::new(Flaky));
        let text = "stages:\n  - name: f\n    kind: flaky\n";
        let pipeline = Pipeline::parse(text, Path::new("p.yaml"), &registry, &[]).unwrap();
        let attempt = |force: bool| {
            let options = RunOptions {
                until: None,
                force: if force { vec!["f".to_string()] } else { vec![] },
            };
            format!(
                "{:#}",
                run(&pipeline, &registry, &store, &options).unwrap_err()
            )
        };
        assert!(attempt(false).contains("failed after 1 attempts"));
        // The work folder is kept for a resume...
        assert!(attempt(false).contains("failed after 2 attempts"));
        // ...and `--force` deletes it.
        let forced = attempt(true);
        assert!(forced.contains("failed after 1 attempts"), "{forced}");
    }

    const TEXT: &str = "stages:\n  - name: a\n    kind: test_arrays\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n";

    fn keys(registry: &Registry, store: &LocalStore) -> (String, String) {
        let pipeline = Pipeline::parse(TEXT, Path::new("p.yaml"), registry, &[]).unwrap();
        let keys = compute_keys(&pipeline, registry, store).unwrap();
        (keys["a"].key.clone(), keys["b"].key.clone())
    }

    #[test]
    fn stage_version_changes_every_downstream_key() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let original = keys(&Registry::new(), &store);
        let mut bumped_registry = Registry::new();
        bumped_registry.add(Box::new(Bumped));
        let bumped = keys(&bumped_registry, &store);
        assert_ne!(original.0, bumped.0);
        assert_ne!(original.1, bumped.1);
        assert_eq!(original, keys(&Registry::new(), &store));
    }

    #[test]
    fn run_publishes_then_reuses() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let registry = Registry::new();
        let pipeline = Pipeline::parse(TEXT, Path::new("p.yaml"), &registry, &[]).unwrap();
        let first = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
        assert!(first.iter().all(|report| report.outcome == Outcome::Ran));
        assert_eq!(first[0].backend.as_deref(), Some("cpu"));
        let second = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
        assert!(
            second
                .iter()
                .all(|report| report.outcome == Outcome::Cached)
        );
        let b = store
            .open_entry(&EntryId::new("test_arrays", &second[1].key))
            .unwrap();
        // b = (i) + (i) for the default size 16.
        let values = b.read::<f64>("values").unwrap();
        assert_eq!(
            values.data,
            (0..16).map(|i| 2.0 * f64::from(i)).collect::<Vec<_>>()
        );
        assert_eq!(b.manifest().inputs[0].key, second[0].key);
        assert_eq!(b.manifest().log, ["backend: cpu"]);
        assert!(b.manifest().started_at.ends_with('Z'));
    }

    /// A stage that fails leaves no partial output for the next run to report as a killed
    /// run's, and keeps its work folder, so the next run resumes.
    #[test]
    fn a_failed_stage_leaves_no_killed_run_leftovers() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let registry = Registry::new();
        let text = "stages:\n  - {name: a, kind: test_arrays, config: {steps: 4, fail_at: 2}}\n";
        let pipeline = Pipeline::parse(text, Path::new("p.yaml"), &registry, &[]).unwrap();
        let error = run(&pipeline, &registry, &store, &RunOptions::default()).unwrap_err();
        assert!(format!("{error:#}").contains("fail_at"), "{error:#}");
        let key = &compute_keys(&pipeline, &registry, &store).unwrap()["a"].key;
        let id = EntryId::new("test_arrays", key);
        assert!(store.has_resumable_work(&id), "the work folder stays");
        assert_eq!(store.clean_leftovers().unwrap(), Vec::<String>::new());
        // A killed run (its partial output still there) is still reported as one.
        let lock = store.try_lock(&id).unwrap().unwrap();
        let staging = store.begin_staging(lock.as_ref()).unwrap();
        std::fs::write(staging.output_dir.join("chunk"), b"partial").unwrap();
        drop(lock);
        let cleaned = store.clean_leftovers().unwrap();
        assert_eq!(cleaned.len(), 1, "{cleaned:?}");
        assert!(cleaned[0].contains("(killed run)"), "{cleaned:?}");
    }
}
