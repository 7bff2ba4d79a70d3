//! The commands behind the CLI: `run`, `status`, `inspect` and `gc`. They print to stdout and
//! return errors for the binary to report.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::entry::EntryReader;
use crate::local::{LocalStore, completion_marker, is_published};
use crate::open_store;
use crate::pipeline::Pipeline;
use crate::runner::{self, Outcome, RunOptions, StageReport};
use crate::store::{EntryId, EntryState, Store};
use crate::{PictureOptions, Registry};

/// Number of key characters shown in tables.
const KEY_PREFIX: usize = 12;

/// `pipeline run`.
pub fn run(
    registry: &Registry,
    file: &Path,
    sets: &[String],
    options: &RunOptions,
    cache: &Path,
) -> anyhow::Result<Vec<StageReport>> {
    let pipeline = Pipeline::load(file, registry, sets)?;
    let store = open_store(cache)?;
    let reports = runner::run(&pipeline, registry, store.as_ref(), options)?;
    print!("{}", summary_table(&reports));
    Ok(reports)
}

/// The run summary: stage, kind, key prefix, cached/ran, time (and backend when reported).
pub fn summary_table(reports: &[StageReport]) -> String {
    let with_backend = reports.iter().any(|report| report.backend.is_some());
    let mut rows = vec![{
        let mut header = vec!["stage", "kind", "key", "result", "time"];
        if with_backend {
            header.push("backend");
        }
        header.into_iter().map(String::from).collect::<Vec<_>>()
    }];
    for report in reports {
        let mut row = vec![
            report.name.clone(),
            report.kind.clone(),
            report.key[..KEY_PREFIX.min(report.key.len())].to_string(),
            report.outcome.to_string(),
            format_seconds(report.seconds),
        ];
        if with_backend {
            row.push(report.backend.clone().unwrap_or_else(|| "-".to_string()));
        }
        rows.push(row);
    }
    let ran = reports
        .iter()
        .filter(|report| report.outcome != Outcome::Cached)
        .count();
    let mut text = format_table(&rows);
    text.push_str(&format!(
        "{} stages: {ran} ran, {} cached\n",
        reports.len(),
        reports.len() - ran
    ));
    text
}

fn format_seconds(seconds: f64) -> String {
    if seconds < 60.0 {
        format!("{seconds:.2} s")
    } else {
        let minutes = (seconds / 60.0).floor();
        format!("{minutes:.0} min {:.0} s", seconds - minutes * 60.0)
    }
}

/// Left-aligned columns separated by two spaces.
fn format_table(rows: &[Vec<String>]) -> String {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let widths: Vec<usize> = (0..columns)
        .map(|column| {
            rows.iter()
                .filter_map(|row| row.get(column))
                .map(|cell| cell.chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut text = String::new();
    for row in rows {
        let mut line = String::new();
        for (column, cell) in row.iter().enumerate() {
            if column + 1 == row.len() {
                line.push_str(cell);
            } else {
                line.push_str(&format!("{cell:<width$}  ", width = widths[column]));
            }
        }
        text.push_str(line.trim_end());
        text.push('\n');
    }
    text
}

/// `pipeline status`: cached, partial (resumable) or missing for each stage, with its key.
/// With `verify`, cached entries are re-checked against their manifest digests and reported
/// `corrupt` (with the problems below the table) when they fail.
pub fn status(
    registry: &Registry,
    file: &Path,
    sets: &[String],
    verify: bool,
    cache: &Path,
) -> anyhow::Result<()> {
    let pipeline = Pipeline::load(file, registry, sets)?;
    let store = open_store(cache)?;
    let keys = runner::compute_keys(&pipeline, registry, store.as_ref())?;
    let mut rows = vec![["stage", "kind", "key", "state"].map(String::from).to_vec()];
    let mut problems = Vec::new();
    for &index in pipeline.order() {
        let stage = &pipeline.stages[index];
        let id = EntryId::new(&stage.kind, &keys[&stage.name].key);
        let state = match store.entry_state(&id)? {
            EntryState::Complete if verify => {
                let _lease = store.read_lease(&id)?;
                match runner::open_verified(store.as_ref(), &id) {
                    Ok(_) => "cached",
                    Err(problem) => {
                        problems.push(format!("{}: {id}: {problem}", stage.name));
                        "corrupt"
                    }
                }
            }
            EntryState::Complete => "cached",
            _ if store.has_resumable_work(&id) => "partial",
            _ => "missing",
        };
        rows.push(vec![
            stage.name.clone(),
            stage.kind.clone(),
            id.key.clone(),
            state.to_string(),
        ]);
    }
    print!("{}", format_table(&rows));
    for problem in &problems {
        println!("corrupt {problem}");
    }
    anyhow::ensure!(
        problems.is_empty(),
        "{} cached entries fail verification (the next run recomputes them)",
        problems.len()
    );
    Ok(())
}

/// What `pipeline inspect` should export.
#[derive(Debug, Clone, Default)]
pub struct InspectOptions {
    pub array: Option<String>,
    pub png: Option<PathBuf>,
    pub exr: Option<PathBuf>,
    pub picture: Option<String>,
    pub picture_options: Vec<String>,
    pub sets: Vec<String>,
}

/// Resolves `FILE:STAGE[:ARRAY]` or `CACHE_PATH[/ARRAY]` to the store holding an entry, the
/// entry and an optional array.
fn resolve_target(
    registry: &Registry,
    target: &str,
    sets: &[String],
    cache: &Path,
) -> anyhow::Result<(Box<dyn Store>, EntryId, Option<String>)> {
    let as_path = Path::new(target);
    if is_published(as_path) {
        let (store, id) = LocalStore::of_entry_folder(as_path)?;
        return Ok((Box::new(store), id, None));
    }
    if let (Some(parent), Some(name)) = (as_path.parent(), as_path.file_name())
        && is_published(parent)
    {
        let (store, id) = LocalStore::of_entry_folder(parent)?;
        return Ok((
            Box::new(store),
            id,
            Some(name.to_string_lossy().to_string()),
        ));
    }
    if as_path.is_dir() {
        anyhow::bail!(
            "{target}: not a published cache entry (no {} marker; the entry may be incomplete)",
            completion_marker(as_path).display()
        );
    }
    let split = [".yaml:", ".yml:"]
        .iter()
        .find_map(|suffix| target.find(suffix).map(|at| at + suffix.len() - 1));
    let Some(colon) = split else {
        anyhow::bail!("{target}: expected FILE.yaml:STAGE[:ARRAY] or the folder of a cache entry");
    };
    let file = Path::new(&target[..colon]);
    let rest = &target[colon + 1..];
    let (stage_name, array) = match rest.split_once(':') {
        Some((stage, array)) => (stage, Some(array.to_string())),
        None => (rest, None),
    };
    let pipeline = Pipeline::load(file, registry, sets)?;
    let stage = pipeline.stage(stage_name).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no stage named \"{stage_name}\" (stages: {})",
            file.display(),
            pipeline.stage_names().join(", ")
        )
    })?;
    let store = open_store(cache)?;
    let keys = runner::compute_keys(&pipeline, registry, store.as_ref())?;
    let id = EntryId::new(&stage.kind, &keys[&stage.name].key);
    anyhow::ensure!(
        store.entry_state(&id)? == EntryState::Complete,
        "stage \"{stage_name}\" ({id}) is not in the cache at {}; run `pipeline run {}` first",
        cache.display(),
        file.display()
    );
    Ok((store, id, array))
}

/// `pipeline inspect`: prints an entry (or one array of it) under the read lease `gc`
/// respects, and checks what it prints against the manifest: the attributes and the arrays
/// shown (every array when `--picture` draws from the entry). On a mismatch it still prints
/// what it could read, then fails with "UNVERIFIED" and writes no picture.
pub fn inspect(
    registry: &Registry,
    target: &str,
    options: &InspectOptions,
    cache: &Path,
) -> anyhow::Result<()> {
    let (store, id, target_array) = resolve_target(registry, target, &options.sets, cache)?;
    let _lease = store.read_lease(&id)?;
    let entry = store.open_entry(&id)?;
    let array = options.array.clone().or(target_array);
    if let Some(name) = &array {
        anyhow::ensure!(
            entry.has_array(name),
            "{}: no array \"{name}\" (arrays: {})",
            entry.location(),
            entry.array_names().join(", ")
        );
    }
    let checked = if options.picture.is_some() {
        None
    } else {
        array.as_deref()
    };
    let problems = runner::entry_problems(&entry, &id, checked);
    let description = describe_entry(&entry, array.as_deref(), registry);
    if !problems.is_empty() {
        let unreadable = match &description {
            Ok(text) => {
                print!("{text}");
                String::new()
            }
            Err(error) => format!("; reading it: {error:#}"),
        };
        anyhow::bail!(
            "UNVERIFIED: entry {id} ({}) does not match its manifest ({}){unreadable}; what it \
             holds may be damaged or tampered with (`pipeline run` on its pipeline recomputes it)",
            entry.location(),
            problems.join("; ")
        );
    }
    print!("{}", description?);
    let picture_options = PictureOptions::parse(&options.picture_options)?;
    if let Some(picture) = &options.picture {
        let kind = registry.get(entry.kind()).ok_or_else(|| {
            anyhow::anyhow!(
                "stage kind \"{}\" is not known to this binary",
                entry.kind()
            )
        })?;
        let out = options
            .png
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("--picture needs --png OUT"))?;
        let image = kind.draw_picture(&entry, picture, &picture_options)?;
        image
            .save(out)
            .with_context(|| format!("cannot write {}", out.display()))?;
        println!(
            "wrote {} ({}x{})",
            out.display(),
            image.width(),
            image.height()
        );
    } else if let Some(out) = &options.png {
        let name = image_array_name(&entry, array.as_deref())?;
        let image = crate::picture::array_png(&entry, &name, &picture_options)?;
        image
            .save(out)
            .with_context(|| format!("cannot write {}", out.display()))?;
        println!(
            "wrote {} ({}x{}) from array \"{name}\"",
            out.display(),
            image.width(),
            image.height()
        );
    }
    if let Some(out) = &options.exr {
        let name = image_array_name(&entry, array.as_deref())?;
        let (width, height, channels) =
            crate::picture::array_exr(&entry, &name, &picture_options, out)?;
        println!(
            "wrote {} ({width}x{height}, {channels} channel(s)) from array \"{name}\"",
            out.display()
        );
    }
    Ok(())
}

fn image_array_name(entry: &EntryReader, array: Option<&str>) -> anyhow::Result<String> {
    match array {
        Some(name) => Ok(name.to_string()),
        None => anyhow::bail!(
            "--png/--exr need an array: add it to the target or pass --array (arrays: {})",
            entry.array_names().join(", ")
        ),
    }
}

/// The provenance and array table of an entry.
fn describe_entry(
    entry: &EntryReader,
    only: Option<&str>,
    registry: &Registry,
) -> anyhow::Result<String> {
    let manifest = entry.manifest();
    let mut text = String::new();
    text.push_str(&format!("entry     {}\n", entry.location()));
    text.push_str(&format!(
        "stage     {} (kind {}, version {})\n",
        manifest.stage_name, manifest.kind, manifest.version
    ));
    text.push_str(&format!("key       {}\n", manifest.key));
    text.push_str(&format!(
        "computed  {} .. {} ({}) by seqavatar {}\n",
        manifest.started_at,
        manifest.finished_at,
        format_seconds(manifest.wall_time_s),
        manifest.tool_version
    ));
    for input in &manifest.inputs {
        text.push_str(&format!(
            "input     {} ({} {})\n",
            input.stage_name,
            input.kind,
            &input.key[..KEY_PREFIX.min(input.key.len())]
        ));
    }
    for file in &manifest.external_files {
        text.push_str(&format!(
            "file      {} ({})\n",
            file.path,
            &file.digest[..KEY_PREFIX.min(file.digest.len())]
        ));
    }
    text.push_str(&format!(
        "config    {}\n",
        serde_json::to_string(&manifest.config).unwrap_or_default()
    ));
    for (key, value) in entry.attributes() {
        let shown = shorten(&value.to_string(), 200);
        text.push_str(&format!("attribute {key} = {shown}\n"));
    }
    for line in &manifest.log {
        text.push_str(&format!("log       {line}\n"));
    }
    for line in &manifest.warnings {
        text.push_str(&format!("warning   {line}\n"));
    }
    if let Some(kind) = registry.get(&manifest.kind) {
        for picture in kind.pictures() {
            text.push_str(&format!(
                "picture   {}: {}\n",
                picture.name, picture.description
            ));
        }
    }
    let header = [
        "array", "dtype", "shape", "chunks", "dims", "stored", "min", "max", "mean", "nan",
    ];
    let mut rows = vec![header.map(String::from).to_vec()];
    for (name, record) in &manifest.arrays {
        if only.is_some_and(|wanted| wanted != name) {
            continue;
        }
        let stats = array_stats(entry, name)?;
        rows.push(vec![
            name.clone(),
            record.dtype.clone(),
            format!("{:?}", record.shape),
            format!("{:?}", record.chunk_shape),
            record.dimension_names.join(","),
            format_bytes(entry.stored_bytes(name)),
            stats.text(stats.min),
            stats.text(stats.max),
            stats.mean_text(),
            stats.nan.to_string(),
        ]);
    }
    text.push_str(&format_table(&rows));
    if let Some(name) = only {
        for key in ["units", "description"] {
            if let Some(value) = entry.array_attribute(name, key) {
                text.push_str(&format!("{name}.{key} = {value}\n"));
            }
        }
    }
    Ok(text)
}

/// `text` cut to at most `limit` characters (never inside a multibyte character), with
/// `...` when something was cut.
fn shorten(text: &str, limit: usize) -> String {
    match text.char_indices().nth(limit) {
        Some((cut, _)) => format!("{}...", &text[..cut]),
        None => text.to_string(),
    }
}

/// Running min / max / mean / NaN count.
#[derive(Debug, Clone, Copy, Default)]
struct Stats {
    min: f64,
    max: f64,
    sum: f64,
    finite: u64,
    nan: u64,
}

impl Stats {
    fn add(&mut self, value: f64) {
        if value.is_nan() {
            self.nan += 1;
            return;
        }
        if self.finite == 0 {
            self.min = value;
            self.max = value;
        } else {
            self.min = self.min.min(value);
            self.max = self.max.max(value);
        }
        self.sum += value;
        self.finite += 1;
    }

    /// `value` (the minimum, maximum or mean), or `-` where no value was finite.
    fn text(&self, value: f64) -> String {
        if self.finite == 0 {
            "-".into()
        } else {
            format!("{value:.6}")
        }
    }

    fn mean_text(&self) -> String {
        self.text(self.sum / self.finite as f64)
    }
}

/// Statistics of an array, read in blocks along the first axis to bound memory.
fn array_stats(entry: &EntryReader, name: &str) -> anyhow::Result<Stats> {
    let shape = entry.shape(name)?;
    let mut stats = Stats::default();
    if shape.is_empty() {
        for value in entry.read_region_f64(name, &[], &[])? {
            stats.add(value);
        }
        return Ok(stats);
    }
    let inner: u64 = shape[1..].iter().product::<u64>().max(1);
    let rows_per_block = (16_000_000 / inner).max(1);
    let mut row = 0u64;
    while row < shape[0] {
        let rows = rows_per_block.min(shape[0] - row);
        let mut start = vec![0u64; shape.len()];
        start[0] = row;
        let mut block_shape = shape.clone();
        block_shape[0] = rows;
        for value in entry.read_region_f64(name, &start, &block_shape)? {
            stats.add(value);
        }
        row += rows;
    }
    Ok(stats)
}

fn format_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// What `pipeline gc` did (or would do, in a dry run).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GcReport {
    /// Entries removed.
    pub removed: Vec<EntryId>,
    /// Cached entries that a `--keep` pipeline references.
    pub kept: usize,
    /// Unreferenced entries left alone because a running pipeline computes or reads them.
    pub skipped: Vec<EntryId>,
    /// Work folders (checkpoints) of unreferenced runs removed.
    pub work_folders: Vec<EntryId>,
    pub freed: u64,
}

/// `pipeline gc`: removes entries that none of `keep` references and that no running
/// pipeline reads, and the work folders (checkpoints) of unreferenced interrupted runs.
pub fn gc(
    registry: &Registry,
    keep: &[PathBuf],
    sets: &[String],
    dry_run: bool,
    cache: &Path,
) -> anyhow::Result<GcReport> {
    let store = open_store(cache)?;
    let mut referenced: BTreeSet<EntryId> = BTreeSet::new();
    for file in keep {
        let pipeline = Pipeline::load(file, registry, sets)?;
        let keys = runner::compute_keys(&pipeline, registry, store.as_ref())?;
        for stage in &pipeline.stages {
            referenced.insert(EntryId::new(&stage.kind, &keys[&stage.name].key));
        }
    }
    let verb = if dry_run { "would remove" } else { "removed" };
    let mut report = GcReport::default();
    // A dry run of a cache that cannot be written here takes no locks (it could make no lock
    // file) and says what a gc that can write it would remove.
    let unlocked_dry_run =
        |error: &anyhow::Error| dry_run && error.is::<crate::local::ReadOnlyCache>();
    for id in store.list()? {
        if referenced.contains(&id) {
            report.kept += 1;
            continue;
        }
        let lock = match store.try_lock(&id) {
            Err(error) if unlocked_dry_run(&error) => None,
            result => {
                let Some(lock) = result? else {
                    println!("skipped {id}: a running pipeline is computing it");
                    report.skipped.push(id);
                    continue;
                };
                // Exclusive against the shared leases of runs reading the entry; held while
                // deleting so that a run starting to read it waits, then finds it gone.
                let Some(readers) = store.try_exclusive_read_lease(&id)? else {
                    println!("skipped {id}: a running pipeline reads it");
                    report.skipped.push(id);
                    continue;
                };
                Some((lock, readers))
            }
        };
        let bytes = match &lock {
            Some((lock, _readers)) if !dry_run => store.remove(lock.as_ref())?,
            _ => store.entry_bytes(&id),
        };
        println!("{verb} {id} ({})", format_bytes(bytes));
        report.freed += bytes;
        report.removed.push(id);
    }
    for id in store.staged()? {
        if referenced.contains(&id) {
            continue; // Its work folder resumes a run of a kept pipeline.
        }
        let lock = match store.try_lock(&id) {
            Err(error) if unlocked_dry_run(&error) => None,
            result => match result? {
                Some(lock) => Some(lock),
                None => continue, // A live run owns it.
            },
        };
        match &lock {
            Some(lock) if !dry_run => {
                let bytes = store.remove_staging(lock.as_ref())?;
                println!("{verb} the work folder of {id} ({})", format_bytes(bytes));
                report.freed += bytes;
            }
            _ => println!("{verb} the work folder of {id}"),
        }
        report.work_folders.push(id);
    }
    if !dry_run {
        for line in store.clean_leftovers()? {
            println!("{verb} {line}");
        }
    }
    let trash = store.empty_trash(dry_run)?;
    if trash > 0 {
        println!("{verb} quarantined entries ({})", format_bytes(trash));
        report.freed += trash;
    }
    println!(
        "{verb} {} entries, {} freed; kept {} referenced entries; skipped {} in use",
        report.removed.len(),
        format_bytes(report.freed),
        report.kept,
        report.skipped.len()
    );
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_aligns_columns() {
        let rows = vec![
            vec!["a".to_string(), "long".to_string(), "x".to_string()],
            vec!["longer".to_string(), "b".to_string(), "y".to_string()],
        ];
        assert_eq!(format_table(&rows), "a       long  x\nlonger  b     y\n");
    }

    #[test]
    fn shorten_never_cuts_a_character() {
        assert_eq!(shorten("abc", 3), "abc");
        assert_eq!(shorten("abcd", 3), "abc...");
        // 'é' is two bytes: a byte-based cut at 3 would split it.
        assert_eq!(shorten("aaé€x", 3), "aaé...");
        assert_eq!(shorten("ééé", 3), "ééé");
    }

    #[test]
    fn inspect_shows_long_multibyte_attributes() {
        let dir = tempfile::tempdir().unwrap();
        let writer = crate::entry::EntryWriter::create(dir.path()).unwrap();
        writer
            .write_array::<u8>("a", &["i"], &[1], &[1], &[7])
            .unwrap();
        // 199 ASCII bytes then multibyte characters: byte 200 falls inside one.
        let value = format!("{}{}", "x".repeat(198), "é".repeat(50));
        writer
            .set_attribute("note", serde_json::json!(value))
            .unwrap();
        writer
            .finish(&mut crate::entry::Manifest {
                kind: "k".into(),
                version: 1,
                stage_name: "s".into(),
                key: "key".into(),
                config: serde_json::json!({}),
                inputs: vec![],
                external_files: vec![],
                tool_version: "0".into(),
                metadata_digest: String::new(),
                arrays: Default::default(),
                wall_time_s: 0.0,
                started_at: String::new(),
                finished_at: String::new(),
                log: vec![],
                warnings: vec![],
            })
            .unwrap();
        let storage = crate::files::entry_storage(dir.path()).unwrap();
        let entry = EntryReader::open(storage, "entry").unwrap();
        let text = describe_entry(&entry, None, &Registry::new()).unwrap();
        assert!(text.contains("attribute note = \"xxx"), "{text}");
        assert!(text.contains("é..."), "{text}");
    }

    fn write_pipeline(dir: &Path, name: &str, seed: i64) -> PathBuf {
        let file = dir.join(name);
        std::fs::write(
            &file,
            format!("stages:\n  - name: a\n    kind: test_arrays\n    config: {{seed: {seed}}}\n"),
        )
        .unwrap();
        file
    }

    #[test]
    fn gc_respects_readers_and_reports_what_it_keeps() {
        use crate::local::LocalStore;
        use crate::store::Store as _;
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("cache");
        let registry = Registry::new();
        let kept_file = write_pipeline(dir.path(), "kept.yaml", 1);
        let other_file = write_pipeline(dir.path(), "other.yaml", 2);
        run(&registry, &kept_file, &[], &RunOptions::default(), &cache).unwrap();
        let other = run(&registry, &other_file, &[], &RunOptions::default(), &cache).unwrap();
        let other_id = EntryId::new("test_arrays", &other[0].key);
        let store = LocalStore::open(&cache).unwrap();
        // The work folder of an interrupted run nobody keeps.
        let orphan = EntryId::new("test_arrays", "0123abcd");
        let staging = {
            let lock = store.try_lock(&orphan).unwrap().unwrap();
            let staging = store.begin_staging(lock.as_ref()).unwrap();
            std::fs::write(staging.work_dir.join("checkpoint"), b"1234").unwrap();
            staging
        };

        // A run reading `other` holds a shared lease: gc leaves it.
        let lease = store.read_lease(&other_id).unwrap();
        let report = gc(
            &registry,
            std::slice::from_ref(&kept_file),
            &[],
            false,
            &cache,
        )
        .unwrap();
        assert_eq!(report.kept, 1, "{report:?}");
        assert!(report.removed.is_empty(), "{report:?}");
        assert_eq!(report.skipped, std::slice::from_ref(&other_id));
        assert_eq!(report.work_folders, std::slice::from_ref(&orphan));
        assert!(!staging.work_dir.exists());
        assert_eq!(store.entry_state(&other_id).unwrap(), EntryState::Complete);

        // Once the reader is gone (a dead process releases its lock too), gc removes it.
        drop(lease);
        let report = gc(&registry, &[kept_file], &[], false, &cache).unwrap();
        assert_eq!((report.kept, report.removed.len()), (1, 1), "{report:?}");
        assert_eq!(report.removed, std::slice::from_ref(&other_id));
        assert_eq!(store.entry_state(&other_id).unwrap(), EntryState::Missing);
    }

    /// `gc --keep FILE --set ...` keeps the entries `run FILE --set ...` made.
    #[test]
    fn gc_keeps_the_entries_of_a_pipeline_run_with_overrides() {
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("cache");
        let registry = Registry::new();
        let file = write_pipeline(dir.path(), "p.yaml", 1);
        let sets = vec!["a.seed=7".to_string()];
        let made = run(&registry, &file, &sets, &RunOptions::default(), &cache).unwrap();
        let id = EntryId::new("test_arrays", &made[0].key);
        let report = gc(&registry, std::slice::from_ref(&file), &sets, false, &cache).unwrap();
        assert_eq!((report.kept, report.removed.len()), (1, 0), "{report:?}");
        // Without the overrides the entry is not the pipeline's and goes.
        let report = gc(&registry, std::slice::from_ref(&file), &[], false, &cache).unwrap();
        assert_eq!(report.removed, [id]);
    }

    /// What `render`, `export` and `report` open: refused when tampered (an edited group
    /// attribute, a chunk re-encoded validly with other values), and under the read lease
    /// `gc` respects while the reader lives.
    #[test]
    fn leased_verified_readers_refuse_tampering_and_keep_gc_away() {
        use crate::local::LocalStore;
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("cache");
        let registry = Registry::new();
        let file = write_pipeline(dir.path(), "p.yaml", 1);
        let other = write_pipeline(dir.path(), "other.yaml", 2);
        let made = run(&registry, &file, &[], &RunOptions::default(), &cache).unwrap();
        let id = EntryId::new("test_arrays", &made[0].key);
        let store = LocalStore::open(&cache).unwrap();

        // The lease lives as long as any clone of the reader: gc skips the entry below.
        let reader = crate::open_leased_verified(&store, &id).unwrap();
        let copy = reader.clone();
        drop(reader);
        let report = gc(&registry, std::slice::from_ref(&other), &[], true, &cache).unwrap();
        assert_eq!(report.skipped, std::slice::from_ref(&id), "{report:?}");
        drop(copy);
        // A test in another thread that spawns a process shares the lease file's open file
        // description (and so its `flock`) from the fork until the child's exec closes it:
        // the lease may outlive the reader by that instant, never longer.
        let mut report = gc(&registry, std::slice::from_ref(&other), &[], true, &cache).unwrap();
        for _ in 0..100 {
            if report.skipped.is_empty() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
            report = gc(&registry, std::slice::from_ref(&other), &[], true, &cache).unwrap();
        }
        assert!(report.skipped.is_empty(), "{report:?}");

        let entry = store.entry_dir(&id);
        // A chunk re-encoded with valid zstd and CRC-32C but other values.
        let chunk = entry.join("values/c/0");
        let original_chunk = std::fs::read(&chunk).unwrap();
        {
            let storage =
                std::sync::Arc::new(zarrs::filesystem::FilesystemStore::new(&entry).unwrap());
            let array = zarrs::array::Array::open(storage, "/values").unwrap();
            let mut values: Vec<f64> = array.retrieve_chunk(&[0]).unwrap();
            values[0] += 3.0;
            array.store_chunk(&[0], &values).unwrap();
        }
        let error = crate::open_leased_verified(&store, &id)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("corrupt") && error.contains("values/c/0"),
            "{error}"
        );
        std::fs::write(&chunk, original_chunk).unwrap();
        crate::open_leased_verified(&store, &id).unwrap();

        // An edited attribute in the group's zarr.json.
        let group = entry.join("zarr.json");
        let mut metadata: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&group).unwrap()).unwrap();
        metadata["attributes"]["background"] = serde_json::json!([1.0, 1.0, 1.0]);
        std::fs::write(&group, serde_json::to_vec(&metadata).unwrap()).unwrap();
        let error = crate::open_leased_verified(&store, &id)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("corrupt") && error.contains("zarr.json"),
            "{error}"
        );
    }

    #[test]
    fn byte_sizes_are_readable() {
        assert_eq!(format_bytes(12), "12 B");
        assert_eq!(format_bytes(2048), "2.0 KiB");
        assert_eq!(format_bytes(5 * 1024 * 1024 * 1024), "5.0 GiB");
    }

    #[test]
    fn stats_skip_nan_and_handle_empty() {
        let mut stats = Stats::default();
        assert_eq!(stats.mean_text(), "-");
        for value in [1.0, f64::NAN, -3.0, 5.0] {
            stats.add(value);
        }
        assert_eq!(
            (stats.min, stats.max, stats.nan, stats.finite),
            (-3.0, 5.0, 1, 3)
        );
        assert_eq!(stats.mean_text(), "1.000000");
    }
}
