//! The local store: a cache in a folder ([`LocalStore`]), used alone or as the local front of
//! the remote store. Staging always happens in a local directory; publishing makes an entry
//! visible by writing its completion marker last.

use std::fs::{self, File, OpenOptions};
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use zarrs::storage::ReadableListableStorage;

use crate::entry::ReadLease;
use crate::store::{
    COMPLETION_MARKER, EntryId, EntryState, KeyLock, Staging, Store, check_component,
};

/// The completion marker of the local entry folder `entry_dir`: the file `<key>.complete`
/// beside the folder, not inside it, so that the folder is a Zarr group holding only Zarr
/// nodes (zarr-python and xarray warn about any other object in a group). The publish
/// protocol is unchanged: the folder is renamed into place complete, the marker is written
/// after it and removed before it.
pub(crate) fn completion_marker(entry_dir: &Path) -> PathBuf {
    let mut name = entry_dir.file_name().unwrap_or_default().to_os_string();
    name.push(COMPLETION_MARKER);
    entry_dir.with_file_name(name)
}

/// Where entries published before the marker moved out of the folder keep it: inside.
/// Such entries stay readable (and are removed as usual); new ones never write it.
fn legacy_completion_marker(entry_dir: &Path) -> PathBuf {
    entry_dir.join(COMPLETION_MARKER)
}

/// Whether the local entry folder `entry_dir` is published (either marker exists).
pub(crate) fn is_published(entry_dir: &Path) -> bool {
    // A marker whose folder is gone (deleted by hand, or moved away by another tool) marks
    // nothing: the entry is missing and is computed again.
    entry_dir.is_dir()
        && (completion_marker(entry_dir).is_file() || legacy_completion_marker(entry_dir).is_file())
}

/// Writes the completion marker of `entry_dir` (already in place, complete) with `content`,
/// durably: the file is synced, then the folder that holds it.
pub(crate) fn write_completion_marker(entry_dir: &Path, content: &[u8]) -> anyhow::Result<()> {
    let marker = completion_marker(entry_dir);
    let mut file =
        File::create(&marker).with_context(|| format!("cannot create {}", marker.display()))?;
    file.write_all(content)
        .and_then(|()| file.sync_all())
        .with_context(|| format!("cannot write {}", marker.display()))?;
    if let Some(parent) = marker.parent() {
        fsync_dir(parent)?;
    }
    Ok(())
}

/// Removes the completion markers of `entry_dir` (first, so that a crash mid-way never
/// leaves a visible half-removed entry), durably.
fn remove_completion_markers(entry_dir: &Path) -> anyhow::Result<()> {
    for (marker, holder) in [
        (completion_marker(entry_dir), entry_dir.parent()),
        (legacy_completion_marker(entry_dir), Some(entry_dir)),
    ] {
        if marker.exists() {
            fs::remove_file(&marker)
                .with_context(|| format!("cannot remove {}", marker.display()))?;
            if let Some(holder) = holder {
                fsync_dir(holder)?;
            }
        }
    }
    Ok(())
}

/// The file that marks a cache root, in the Cache Directory Tagging format
/// (<https://bford.info/cachedir/>): backup tools that honour it skip the cache, and dataset
/// digests leave out any folder holding ours ([`is_pipeline_cache`]), whichever cache a run
/// uses.
pub(crate) const CACHE_TAG: &str = "CACHEDIR.TAG";
/// What the tag starts with, by the format.
const CACHE_TAG_SIGNATURE: &str = "Signature: 8a477f597d28d172789f06886806bc55\n";
/// The line after the signature that makes the tag a pipeline cache's.
const CACHE_TAG_OWNER: &str = "# This file marks a seqavatar pipeline cache";

/// Whether `dir` is the root of a pipeline cache: it holds our [`CACHE_TAG`] (a regular
/// file, read through the checked open of [`crate::files`]).
pub(crate) fn is_pipeline_cache(dir: &Path) -> bool {
    let tag = dir.join(CACHE_TAG);
    tag.is_file()
        && crate::files::read_regular_file_at_most(&tag, 4096, "a cache tag").is_ok_and(|bytes| {
            bytes.starts_with(format!("{CACHE_TAG_SIGNATURE}{CACHE_TAG_OWNER}").as_bytes())
        })
}

/// Writes the [`CACHE_TAG`] of the cache at `root` where it is missing (atomically, as
/// another process may be reading it). Best effort: a read-only cache has none to write.
fn tag_cache_root(root: &Path) {
    let tag = root.join(CACHE_TAG);
    if tag.exists() {
        return;
    }
    let text = format!(
        "{CACHE_TAG_SIGNATURE}{CACHE_TAG_OWNER} (`pipeline --cache`): backup tools\n\
         # that honour CACHEDIR.TAG skip it, and dataset digests leave it out.\n\
         # For information about cache directory tags see https://bford.info/cachedir/\n"
    );
    let temporary = root.join(format!(".{CACHE_TAG}.{}", std::process::id()));
    if fs::write(&temporary, text).is_ok() && fs::rename(&temporary, &tag).is_err() {
        let _ = fs::remove_file(&temporary);
    }
}

const STAGING_DIR: &str = ".staging";
const LOCKS_DIR: &str = ".locks";
const TRASH_DIR: &str = ".trash";
/// Inside a staging area: the group being written, and the stage's resumable work folder.
const STAGING_OUTPUT: &str = "out";
const STAGING_WORK: &str = "work";

/// A cache in a local folder: `<root>/<kind>/<key>/` entries, `<root>/.staging/<kind>/<key>/`
/// staging areas, `<root>/.locks/<kind>/<key>.lock` lock files and `<key>.read` reader lock
/// files (shared `flock` by readers, exclusive by `gc`).
#[derive(Debug, Clone)]
pub struct LocalStore {
    root: PathBuf,
}

struct LocalLock {
    id: EntryId,
    _file: File,
}

impl KeyLock for LocalLock {
    fn id(&self) -> &EntryId {
        &self.id
    }
}

/// A locked reader lock file (`flock`, shared or exclusive).
struct LocalReadLease {
    _file: File,
}

impl ReadLease for LocalReadLease {}

/// What a read of a read-only cache holds instead of a lease: nothing, as no lock file can be
/// made there (a `gc` by someone who can write the cache would not see the reader).
struct Unleased;

impl ReadLease for Unleased {}

/// A cache that cannot be written here: a read-only file system, or folders this user may
/// not write (a published or shared cache). Reads go ahead without read leases; whatever
/// writes (computing, publishing, `gc`) fails with this error.
#[derive(Debug, thiserror::Error)]
#[error(
    "the cache {root} is read-only here ({reason}): it serves the entries it holds, but nothing \
     can be computed, published or removed in it"
)]
pub struct ReadOnlyCache {
    root: String,
    reason: std::io::Error,
}

/// Whether `error`, met making a file in the cache, says that the cache cannot be written.
fn is_read_only(error: &std::io::Error) -> bool {
    matches!(
        error.kind(),
        std::io::ErrorKind::ReadOnlyFilesystem | std::io::ErrorKind::PermissionDenied
    )
}

/// Says once per process that a read-only cache is read without leases.
fn note_unleased_reads(error: &ReadOnlyCache) {
    static NOTED: std::sync::Once = std::sync::Once::new();
    NOTED.call_once(|| {
        eprintln!(
            "note: the cache {} is read-only here ({}): reading it without read leases",
            error.root, error.reason
        );
    });
}

impl LocalStore {
    /// A store rooted at `root` (created if missing).
    pub fn open(root: &Path) -> anyhow::Result<Self> {
        crate::files::require_utf8_path(root)?;
        fs::create_dir_all(root)
            .with_context(|| format!("cannot create cache folder {}", root.display()))?;
        tag_cache_root(root);
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    /// The store and the entry of an entry folder `<root>/<kind>/<key>` named by a user (the
    /// folder form of `render --avatar` and of `inspect`), so that it is read as any entry of
    /// its cache is: under its read lease. Unlike [`LocalStore::open`], it makes and tags
    /// nothing: the folder may lie anywhere.
    pub fn of_entry_folder(folder: &Path) -> anyhow::Result<(Self, EntryId)> {
        let canonical = folder
            .canonicalize()
            .with_context(|| format!("cannot resolve {}", folder.display()))?;
        fn name(path: Option<&Path>) -> Option<&str> {
            path.and_then(Path::file_name)
                .and_then(|name| name.to_str())
        }
        let (Some(key), Some(kind), Some(root)) = (
            name(Some(&canonical)),
            name(canonical.parent()),
            canonical.parent().and_then(Path::parent),
        ) else {
            anyhow::bail!(
                "{}: expected a cache entry folder <cache>/<kind>/<key>",
                folder.display()
            );
        };
        crate::files::require_utf8_path(root)?;
        let store = Self {
            root: root.to_path_buf(),
        };
        Ok((store, EntryId::new(kind, key)))
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The published entry folder.
    pub fn entry_dir(&self, id: &EntryId) -> PathBuf {
        self.root.join(&id.kind).join(&id.key)
    }

    fn staging_dir(&self, id: &EntryId) -> PathBuf {
        self.root.join(STAGING_DIR).join(&id.kind).join(&id.key)
    }

    /// The lock file `<key>.lock` of an entry, or with `extension` `read` its reader lock file.
    fn lock_path(&self, id: &EntryId, extension: &str) -> PathBuf {
        self.root
            .join(LOCKS_DIR)
            .join(&id.kind)
            .join(format!("{}.{extension}", id.key))
    }

    /// Opens (making it if needed) the lock file [`LocalStore::lock_path`] and returns it with
    /// its path; a cache that cannot be written here is a [`ReadOnlyCache`] error.
    fn open_lock_file(&self, id: &EntryId, extension: &str) -> anyhow::Result<(File, PathBuf)> {
        let path = self.lock_path(id, extension);
        check_component("stage kind", &id.kind)?;
        check_component("key", &id.key)?;
        let read_only = |reason: std::io::Error| ReadOnlyCache {
            root: self.root.display().to_string(),
            reason,
        };
        if let Some(parent) = path.parent() {
            match fs::create_dir_all(parent) {
                Err(error) if is_read_only(&error) => return Err(read_only(error).into()),
                result => result.with_context(|| format!("cannot create {}", parent.display()))?,
            }
        }
        let file = match OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
        {
            Err(error) if is_read_only(&error) => return Err(read_only(error).into()),
            result => {
                result.with_context(|| format!("cannot open lock file {}", path.display()))?
            }
        };
        Ok((file, path))
    }

    fn trash_destination(&self, id: &EntryId) -> PathBuf {
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .as_nanos();
        self.root.join(TRASH_DIR).join(&id.kind).join(format!(
            "{}.{stamp}.{}",
            id.key,
            std::process::id()
        ))
    }

    /// The `<kind>/<key>` folders under `dir`, as entry ids, sorted.
    fn ids_under(dir: &Path) -> Vec<EntryId> {
        let mut ids = Vec::new();
        for kind in Self::plain_subdirs(dir) {
            for key in Self::plain_subdirs(&dir.join(&kind)) {
                ids.push(EntryId::new(&kind, &key));
            }
        }
        ids
    }

    /// Sub-folders of `dir` that are plain names (kinds or keys), sorted.
    fn plain_subdirs(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = match fs::read_dir(dir) {
            Ok(read) => read
                .filter_map(Result::ok)
                .filter(|entry| entry.file_type().map(|t| t.is_dir()).unwrap_or(false))
                .filter_map(|entry| entry.file_name().into_string().ok())
                .filter(|name| !name.starts_with('.'))
                .collect(),
            Err(_) => vec![],
        };
        names.sort();
        names
    }
}

impl Store for LocalStore {
    fn describe(&self) -> String {
        self.root.display().to_string()
    }

    fn entry_state(&self, id: &EntryId) -> anyhow::Result<EntryState> {
        let dir = self.entry_dir(id);
        if is_published(&dir) {
            Ok(EntryState::Complete)
        } else if dir.exists() {
            Ok(EntryState::Incomplete)
        } else {
            Ok(EntryState::Missing)
        }
    }

    fn reader_storage(&self, id: &EntryId) -> anyhow::Result<(ReadableListableStorage, String)> {
        let dir = self.entry_dir(id);
        anyhow::ensure!(
            is_published(&dir),
            "entry {} is not published in {}",
            id,
            self.root.display()
        );
        let storage = crate::files::entry_storage(&dir)
            .with_context(|| format!("cannot open entry {}", dir.display()))?;
        Ok((storage, dir.display().to_string()))
    }

    fn read_lease(&self, id: &EntryId) -> anyhow::Result<Box<dyn ReadLease>> {
        let (file, path) = match self.open_lock_file(id, "read") {
            Ok(opened) => opened,
            Err(error) => match error.downcast::<ReadOnlyCache>() {
                Ok(read_only) => {
                    note_unleased_reads(&read_only);
                    return Ok(Box::new(Unleased));
                }
                Err(error) => return Err(error),
            },
        };
        file.lock_shared()
            .with_context(|| format!("cannot lock {} (shared)", path.display()))?;
        Ok(Box::new(LocalReadLease { _file: file }))
    }

    fn try_exclusive_read_lease(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn ReadLease>>> {
        let (file, path) = self.open_lock_file(id, "read")?;
        Ok(try_lock_file(&file, &path)?
            .then(|| Box::new(LocalReadLease { _file: file }) as Box<dyn ReadLease>))
    }

    fn lock(&self, id: &EntryId, on_wait: &mut dyn FnMut()) -> anyhow::Result<Box<dyn KeyLock>> {
        let (file, path) = self.open_lock_file(id, "lock")?;
        if !try_lock_file(&file, &path)? {
            on_wait();
            file.lock()
                .with_context(|| format!("cannot lock {}", path.display()))?;
        }
        Ok(Box::new(LocalLock {
            id: id.clone(),
            _file: file,
        }))
    }

    fn try_lock(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn KeyLock>>> {
        let (file, path) = self.open_lock_file(id, "lock")?;
        Ok(try_lock_file(&file, &path)?.then(|| {
            Box::new(LocalLock {
                id: id.clone(),
                _file: file,
            }) as Box<dyn KeyLock>
        }))
    }

    fn begin_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<Staging> {
        let staging_dir = self.staging_dir(lock.id());
        let output_dir = staging_dir.join(STAGING_OUTPUT);
        let work_dir = staging_dir.join(STAGING_WORK);
        if output_dir.exists() {
            fs::remove_dir_all(&output_dir).with_context(|| {
                format!("cannot clear a partial output {}", output_dir.display())
            })?;
        }
        fs::create_dir_all(&output_dir)
            .with_context(|| format!("cannot create {}", output_dir.display()))?;
        fs::create_dir_all(&work_dir)
            .with_context(|| format!("cannot create {}", work_dir.display()))?;
        Ok(Staging {
            output_dir,
            work_dir,
        })
    }

    fn staged(&self) -> anyhow::Result<Vec<EntryId>> {
        Ok(Self::ids_under(&self.root.join(STAGING_DIR)))
    }

    fn remove_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<u64> {
        let dir = self.staging_dir(lock.id());
        let bytes = tree_bytes(&dir);
        remove_dir_if_present(&dir)?;
        Ok(bytes)
    }

    fn has_resumable_work(&self, id: &EntryId) -> bool {
        let work_dir = self.staging_dir(id).join(STAGING_WORK);
        fs::read_dir(work_dir)
            .map(|mut read| read.next().is_some())
            .unwrap_or(false)
    }

    fn publish(&self, lock: &dyn KeyLock, staging: &Staging) -> anyhow::Result<()> {
        let id = lock.id();
        fsync_tree(&staging.output_dir)?;
        let target = self.entry_dir(id);
        if target.exists() {
            // Unpublished (no marker) or forced: never used, safe to move aside under the lock.
            self.quarantine(lock)?;
        }
        let kind_dir = self.root.join(&id.kind);
        fs::create_dir_all(&kind_dir)
            .with_context(|| format!("cannot create {}", kind_dir.display()))?;
        fs::rename(&staging.output_dir, &target).with_context(|| {
            format!(
                "cannot move {} to {}",
                staging.output_dir.display(),
                target.display()
            )
        })?;
        fsync_dir(&kind_dir)?;
        let marker = format!(
            "{{\"kind\":\"{}\",\"key\":\"{}\",\"published_at\":\"{}\"}}\n",
            id.kind,
            id.key,
            crate::timefmt::rfc3339(std::time::SystemTime::now())
        );
        write_completion_marker(&target, marker.as_bytes())?;
        let staging_dir = self.staging_dir(id);
        fs::remove_dir_all(&staging_dir)
            .with_context(|| format!("cannot remove {}", staging_dir.display()))?;
        Ok(())
    }

    fn quarantine(&self, lock: &dyn KeyLock) -> anyhow::Result<String> {
        let id = lock.id();
        let source = self.entry_dir(id);
        let destination = self.trash_destination(id);
        if let Some(parent) = destination.parent() {
            fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        // Remove the marker first so that a crash mid-way never leaves a visible bad entry.
        remove_completion_markers(&source)?;
        if !source.exists() {
            return Ok(format!("nowhere ({} was already gone)", source.display()));
        }
        fs::rename(&source, &destination).with_context(|| {
            format!(
                "cannot move {} to {}",
                source.display(),
                destination.display()
            )
        })?;
        Ok(destination.display().to_string())
    }

    fn list(&self) -> anyhow::Result<Vec<EntryId>> {
        let mut ids = Vec::new();
        for id in Self::ids_under(&self.root) {
            if self.entry_state(&id)? == EntryState::Complete {
                ids.push(id);
            }
        }
        Ok(ids)
    }

    fn entry_bytes(&self, id: &EntryId) -> u64 {
        tree_bytes(&self.entry_dir(id))
    }

    fn remove(&self, lock: &dyn KeyLock) -> anyhow::Result<u64> {
        let dir = self.entry_dir(lock.id());
        let bytes = tree_bytes(&dir);
        remove_completion_markers(&dir)?;
        fs::remove_dir_all(&dir).with_context(|| format!("cannot remove {}", dir.display()))?;
        Ok(bytes)
    }

    fn clean_leftovers(&self) -> anyhow::Result<Vec<String>> {
        match self.clean_leftovers_writable() {
            // Nothing can be cleaned in a read-only cache, and nothing there needs it to be
            // read.
            Err(error) if error.is::<ReadOnlyCache>() => Ok(Vec::new()),
            result => result,
        }
    }

    fn empty_trash(&self, dry_run: bool) -> anyhow::Result<u64> {
        empty_trash(self, dry_run)
    }

    fn local_state_dir(&self) -> PathBuf {
        self.root.clone()
    }
}

impl LocalStore {
    /// [`Store::clean_leftovers`], failing with [`ReadOnlyCache`] in a read-only cache.
    fn clean_leftovers_writable(&self) -> anyhow::Result<Vec<String>> {
        let mut removed = Vec::new();
        for id in Self::ids_under(&self.root.join(STAGING_DIR)) {
            let Some(lock) = self.try_lock(&id)? else {
                continue; // A live run owns it.
            };
            let staging_dir = self.staging_dir(&id);
            if remove_dir_if_present(&staging_dir.join(STAGING_OUTPUT))? {
                removed.push(format!("partial output of {id} (killed run)"));
            }
            if !self.has_resumable_work(&id) {
                remove_dir_if_present(&staging_dir)?;
            }
            drop(lock);
        }
        for id in Self::ids_under(&self.root) {
            if self.entry_state(&id)? != EntryState::Incomplete {
                continue;
            }
            if let Some(lock) = self.try_lock(&id)?
                && self.entry_state(&id)? == EntryState::Incomplete
            {
                remove_dir_if_present(&self.entry_dir(&id))?;
                removed.push(format!("unpublished entry {id} (interrupted publish)"));
                drop(lock);
            }
        }
        Ok(removed)
    }
}

/// Takes the exclusive `flock` of the lock file `file` (named `path` in errors) without
/// waiting; `false` when another process holds it.
fn try_lock_file(file: &File, path: &Path) -> anyhow::Result<bool> {
    match file.try_lock() {
        Ok(()) => Ok(true),
        Err(fs::TryLockError::WouldBlock) => Ok(false),
        Err(fs::TryLockError::Error(error)) => {
            Err(error).with_context(|| format!("cannot lock {}", path.display()))
        }
    }
}

/// Removes the quarantined entries; returns the bytes freed.
pub(crate) fn empty_trash(store: &LocalStore, dry_run: bool) -> anyhow::Result<u64> {
    let trash = store.root().join(TRASH_DIR);
    let bytes = tree_bytes(&trash);
    if !dry_run && trash.exists() {
        fs::remove_dir_all(&trash).with_context(|| format!("cannot remove {}", trash.display()))?;
    }
    Ok(bytes)
}

/// Removes a folder tree; a folder that is already gone (another run cleaned it) is fine.
/// Returns whether something was removed.
pub(crate) fn remove_dir_if_present(dir: &Path) -> anyhow::Result<bool> {
    match fs::remove_dir_all(dir) {
        Ok(()) => Ok(true),
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(error) => Err(error).with_context(|| format!("cannot remove {}", dir.display())),
    }
}

/// Total size of the files under `path`.
pub(crate) fn tree_bytes(path: &Path) -> u64 {
    let Ok(metadata) = fs::symlink_metadata(path) else {
        return 0;
    };
    if metadata.is_file() {
        return metadata.len();
    }
    if !metadata.is_dir() {
        return 0;
    }
    fs::read_dir(path)
        .map(|read| {
            read.filter_map(Result::ok)
                .map(|entry| tree_bytes(&entry.path()))
                .sum()
        })
        .unwrap_or(0)
}

/// fsyncs every file and directory under `root` (and `root` itself).
pub(crate) fn fsync_tree(root: &Path) -> anyhow::Result<()> {
    for entry in fs::read_dir(root).with_context(|| format!("cannot list {}", root.display()))? {
        let entry = entry.with_context(|| format!("cannot list {}", root.display()))?;
        let path = entry.path();
        let file_type = entry
            .file_type()
            .with_context(|| format!("cannot stat {}", path.display()))?;
        if file_type.is_dir() {
            fsync_tree(&path)?;
        } else if file_type.is_file() {
            File::open(&path)
                .and_then(|file| file.sync_all())
                .with_context(|| format!("cannot fsync {}", path.display()))?;
        }
    }
    fsync_dir(root)
}

fn fsync_dir(dir: &Path) -> anyhow::Result<()> {
    File::open(dir)
        .and_then(|file| file.sync_all())
        .with_context(|| format!("cannot fsync folder {}", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_store() -> (tempfile::TempDir, LocalStore) {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        (dir, store)
    }

    /// A cache path that is not UTF-8 is refused when the cache opens, named (shown lossily),
    /// not later by zarrs as "base path … is not valid".
    #[cfg(unix)]
    #[test]
    fn a_cache_path_that_is_not_utf8_is_named() {
        use std::os::unix::ffi::OsStrExt as _;
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join(std::ffi::OsStr::from_bytes(b"cache-\xff"));
        let error = format!("{:#}", LocalStore::open(&cache).unwrap_err());
        assert!(
            error.contains("cache-\u{fffd} is not valid UTF-8"),
            "{error}"
        );
        assert!(!cache.exists());
    }

    #[test]
    fn lock_is_exclusive_until_dropped() {
        let (_dir, store) = temp_store();
        let id = EntryId::new("test_arrays", "abc");
        let held = store.try_lock(&id).unwrap().expect("free lock");
        assert!(store.try_lock(&id).unwrap().is_none());
        drop(held);
        assert!(store.try_lock(&id).unwrap().is_some());
    }

    #[test]
    fn publish_makes_entry_visible_and_clears_staging() {
        let (_dir, store) = temp_store();
        let id = EntryId::new("test_arrays", "k1");
        let lock = store.try_lock(&id).unwrap().unwrap();
        let staging = store.begin_staging(lock.as_ref()).unwrap();
        fs::write(staging.output_dir.join("zarr.json"), b"{}").unwrap();
        fs::write(staging.work_dir.join("checkpoint"), b"1").unwrap();
        assert!(store.has_resumable_work(&id));
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
        store.publish(lock.as_ref(), &staging).unwrap();
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Complete);
        assert!(!store.has_resumable_work(&id));
        assert_eq!(store.list().unwrap(), vec![id.clone()]);
        // The marker sits beside the group, which holds only what the stage wrote.
        let entry = store.entry_dir(&id);
        assert!(entry.with_file_name("k1.complete").is_file());
        let names: Vec<_> = fs::read_dir(&entry)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["zarr.json"]);
        assert!(store.remove(lock.as_ref()).unwrap() > 0);
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
        assert!(!entry.with_file_name("k1.complete").exists());
    }

    /// Entries published with the marker inside the folder (before it moved beside it) stay
    /// visible and readable, and are removed and quarantined like new ones.
    #[test]
    fn entries_with_the_marker_inside_stay_published() {
        let (_dir, store) = temp_store();
        for (key, quarantine) in [("old1", false), ("old2", true)] {
            let id = EntryId::new("test_arrays", key);
            let entry = store.entry_dir(&id);
            fs::create_dir_all(&entry).unwrap();
            fs::write(entry.join("zarr.json"), b"{}").unwrap();
            fs::write(entry.join(COMPLETION_MARKER), b"{}").unwrap();
            assert_eq!(store.entry_state(&id).unwrap(), EntryState::Complete);
            assert!(store.reader_storage(&id).is_ok());
            let lock = store.try_lock(&id).unwrap().unwrap();
            if quarantine {
                store.quarantine(lock.as_ref()).unwrap();
            } else {
                store.remove(lock.as_ref()).unwrap();
            }
            assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
        }
    }

    /// A marker whose folder is gone (deleted by hand, or moved away by an older version of
    /// the tool) marks nothing: the entry is missing, and quarantining it removes the marker
    /// instead of failing on the absent folder.
    #[test]
    fn a_marker_without_its_folder_is_not_published() {
        let (_dir, store) = temp_store();
        let id = EntryId::new("test_arrays", "k4");
        let lock = store.try_lock(&id).unwrap().unwrap();
        let staging = store.begin_staging(lock.as_ref()).unwrap();
        fs::write(staging.output_dir.join("zarr.json"), b"{}").unwrap();
        store.publish(lock.as_ref(), &staging).unwrap();
        let entry = store.entry_dir(&id);
        fs::remove_dir_all(&entry).unwrap();
        assert!(entry.with_file_name("k4.complete").is_file());
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
        assert!(store.reader_storage(&id).is_err());
        store.quarantine(lock.as_ref()).unwrap();
        assert!(!entry.with_file_name("k4.complete").exists());
    }

    /// A crash after the folder was renamed into place but before its marker was written
    /// leaves an entry that is never read and is cleaned up.
    #[test]
    fn a_folder_without_its_marker_is_not_published() {
        let (_dir, store) = temp_store();
        let id = EntryId::new("test_arrays", "k3");
        let entry = store.entry_dir(&id);
        fs::create_dir_all(&entry).unwrap();
        fs::write(entry.join("zarr.json"), b"{}").unwrap();
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Incomplete);
        assert!(store.reader_storage(&id).is_err());
        assert_eq!(store.clean_leftovers().unwrap().len(), 1);
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
    }

    #[test]
    fn leftovers_lose_output_but_keep_work() {
        let (_dir, store) = temp_store();
        let id = EntryId::new("test_arrays", "k2");
        let lock = store.try_lock(&id).unwrap().unwrap();
        let staging = store.begin_staging(lock.as_ref()).unwrap();
        fs::write(staging.output_dir.join("partial"), b"x").unwrap();
        fs::write(staging.work_dir.join("checkpoint"), b"1").unwrap();
        // While the lock is held, nothing is a leftover.
        assert!(store.clean_leftovers().unwrap().is_empty());
        drop(lock);
        let removed = store.clean_leftovers().unwrap();
        assert_eq!(removed.len(), 1, "{removed:?}");
        assert!(!staging.output_dir.exists());
        assert!(staging.work_dir.join("checkpoint").exists());
        // An entry folder without its marker is never visible and gets cleaned.
        fs::create_dir_all(store.entry_dir(&id)).unwrap();
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Incomplete);
        assert_eq!(store.clean_leftovers().unwrap().len(), 1);
        assert_eq!(store.entry_state(&id).unwrap(), EntryState::Missing);
    }

    /// Every store root is tagged as a cache when it opens; an entry folder named by a user
    /// resolves to its store and entry without making or tagging anything, wherever it lies.
    #[test]
    fn caches_are_tagged_and_entry_folders_are_read_in_place() {
        let (dir, store) = temp_store();
        assert!(is_pipeline_cache(dir.path()));
        let id = EntryId::new("test_arrays", "k5");
        let lock = store.try_lock(&id).unwrap().unwrap();
        let staging = store.begin_staging(lock.as_ref()).unwrap();
        fs::write(staging.output_dir.join("zarr.json"), b"{}").unwrap();
        store.publish(lock.as_ref(), &staging).unwrap();
        fs::remove_file(dir.path().join(CACHE_TAG)).unwrap();
        let (found, found_id) = LocalStore::of_entry_folder(&store.entry_dir(&id)).unwrap();
        assert_eq!(found_id, id);
        assert_eq!(found.root(), fs::canonicalize(dir.path()).unwrap());
        assert!(!dir.path().join(CACHE_TAG).exists());
        // A tag of another tool does not make a folder a pipeline cache.
        fs::write(dir.path().join(CACHE_TAG), CACHE_TAG_SIGNATURE).unwrap();
        assert!(!is_pipeline_cache(dir.path()));
    }

    #[test]
    fn rejects_path_like_components() {
        let (_dir, store) = temp_store();
        assert!(store.try_lock(&EntryId::new("../x", "k")).is_err());
        assert!(store.try_lock(&EntryId::new("kind", ".hidden")).is_err());
    }
}
