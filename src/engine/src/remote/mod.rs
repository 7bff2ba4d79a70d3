//! The shared remote cache: entries in an S3-compatible bucket, fronted by a local folder
//! (read-through: a remote hit is downloaded, verified and installed locally; a local result
//! is published remotely).
//!
//! Remote layout under `s3://bucket/prefix/`:
//! - `<kind>/<key>/<upload>/...`: the files of one upload of an entry (a Zarr group), where
//!   `<upload>` is unique to the uploading process;
//! - `<kind>/<key>/.complete`: the completion marker, created with `If-None-Match: *` only
//!   after every file of the upload is stored; it names the upload. Readers follow only the
//!   marker, so a half-uploaded entry is never read and the first publisher wins even when two
//!   workers computed the same key;
//! - `.leases/<kind>/<key>`: the lease of a worker computing the key (see [`lease`]);
//! - `.readers/<kind>/<key>/<reader>` and `.readers/<kind>/<key>/.gc`: the read leases of
//!   the runs and commands reading the entry, and of a `gc` deleting it (see [`readers`]).

mod bucket;
mod lease;
mod readers;

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context as _;
use serde::{Deserialize, Serialize};
use zarrs::storage::ReadableListableStorage;

use bucket::Bucket;
pub use bucket::S3Url;
use lease::{Acquired, Lease, LeaseSettings, unique_name};

use crate::entry::{EntryReader, ReadLease};
use crate::local::{LocalStore, fsync_tree, remove_dir_if_present, write_completion_marker};
use crate::store::{
    COMPLETION_MARKER, EntryId, EntryState, KeyLock, Staging, Store, check_component,
};

/// Local folder (inside the local front) of downloads in progress.
const DOWNLOADS_DIR: &str = ".downloads";
/// Local folder (inside the local front) of entries computed here whose upload failed.
const PENDING_DIR: &str = ".pending-upload";
/// Remote folder of leases.
const LEASES_DIR: &str = ".leases";
/// Downloads older than this are leftovers of killed runs.
const STALE_DOWNLOAD: Duration = Duration::from_secs(3600);
/// Unpublished uploads older than this are leftovers that `gc` removes.
const STALE_UPLOAD: Duration = Duration::from_secs(3600);

/// The content of a remote completion marker.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct RemoteMarker {
    kind: String,
    key: String,
    /// The folder under `<kind>/<key>/` holding the published files.
    upload: String,
    files: usize,
    bytes: u64,
    published_at: String,
}

/// A cache in an S3-compatible bucket, fronted by a local folder.
pub struct RemoteStore {
    local: LocalStore,
    bucket: Arc<Bucket>,
    settings: LeaseSettings,
    /// Entries whose lock this process holds (their local lock file is ours).
    held: Arc<Mutex<BTreeSet<EntryId>>>,
}

/// The local lock and the remote lease of one key.
struct RemoteLock {
    id: EntryId,
    // Field order is drop order: the lease goes first, then the local lock.
    lease: Lease,
    _local: Box<dyn KeyLock>,
    held: Arc<Mutex<BTreeSet<EntryId>>>,
}

impl KeyLock for RemoteLock {
    fn id(&self) -> &EntryId {
        &self.id
    }
}

impl Drop for RemoteLock {
    fn drop(&mut self) {
        if let Some(reason) = self.lease.lost() {
            eprintln!(
                "warning: the lease of {} was lost while it was held ({reason}); another worker may have computed it too (the first published copy wins)",
                self.id
            );
        }
        self.held
            .lock()
            .expect("held set poisoned")
            .remove(&self.id);
    }
}

/// Proof, for [`LocalStore`] methods, that this process holds the lock of `id`.
struct HeldHere(EntryId);

impl KeyLock for HeldHere {
    fn id(&self) -> &EntryId {
        &self.0
    }
}

fn marker_object(id: &EntryId) -> String {
    format!("{}/{}/{COMPLETION_MARKER}", id.kind, id.key)
}

fn entry_folder(id: &EntryId) -> String {
    format!("{}/{}", id.kind, id.key)
}

fn lease_object(id: &EntryId) -> String {
    format!("{LEASES_DIR}/{}/{}", id.kind, id.key)
}

/// Every file under `root` as a `/`-separated relative path, sorted.
fn relative_files(root: &Path) -> anyhow::Result<Vec<String>> {
    fn walk(root: &Path, dir: &Path, files: &mut Vec<String>) -> anyhow::Result<()> {
        for entry in fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
            let entry = entry.with_context(|| format!("cannot list {}", dir.display()))?;
            let path = entry.path();
            let file_type = entry
                .file_type()
                .with_context(|| format!("cannot stat {}", path.display()))?;
            if file_type.is_dir() {
                walk(root, &path, files)?;
            } else if file_type.is_file() {
                let relative = path.strip_prefix(root).unwrap_or(&path);
                let parts: Vec<String> = relative
                    .components()
                    .map(|part| part.as_os_str().to_string_lossy().to_string())
                    .collect();
                files.push(parts.join("/"));
            }
        }
        Ok(())
    }
    let mut files = Vec::new();
    walk(root, root, &mut files)?;
    files.sort();
    Ok(files)
}

fn remove_file_if_present(path: &Path) -> anyhow::Result<()> {
    match fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(error) => Err(error).with_context(|| format!("cannot remove {}", path.display())),
    }
}

/// Plain (not hidden) names in a local folder, sorted; nothing when it does not exist.
fn plain_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = fs::read_dir(dir)
        .map(|read| {
            read.filter_map(Result::ok)
                .filter_map(|entry| entry.file_name().into_string().ok())
                .filter(|name| !name.starts_with('.'))
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

impl RemoteStore {
    /// The cache at `url`, fronted by the local folder `local_root` (created if missing).
    /// Lease timing comes from `SEQAVATAR_LEASE_TIMEOUT_S`.
    pub fn open(url: &S3Url, local_root: &Path) -> anyhow::Result<Self> {
        let settings = LeaseSettings::from_env()?;
        Self::open_with(url, local_root, settings)
    }

    fn open_with(url: &S3Url, local_root: &Path, settings: LeaseSettings) -> anyhow::Result<Self> {
        Ok(Self {
            local: LocalStore::open(local_root)?,
            bucket: Arc::new(Bucket::open(url)?),
            settings,
            held: Arc::new(Mutex::new(BTreeSet::new())),
        })
    }

    pub fn local(&self) -> &LocalStore {
        &self.local
    }

    fn check_id(id: &EntryId) -> anyhow::Result<()> {
        check_component("stage kind", &id.kind)?;
        check_component("key", &id.key)
    }

    fn pending_path(&self, id: &EntryId) -> PathBuf {
        self.local
            .root()
            .join(PENDING_DIR)
            .join(&id.kind)
            .join(&id.key)
    }

    /// Reads and checks the remote completion marker of `id`; `None` when unpublished.
    fn remote_marker(&self, id: &EntryId) -> anyhow::Result<Option<(RemoteMarker, Vec<u8>)>> {
        let object = marker_object(id);
        let Some((bytes, _)) = self.bucket.get(&object)? else {
            return Ok(None);
        };
        let marker: RemoteMarker = serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "{}: malformed completion marker",
                self.bucket.describe(&object)
            )
        })?;
        anyhow::ensure!(
            marker.kind == id.kind && marker.key == id.key,
            "{}: the completion marker names {}/{}",
            self.bucket.describe(&object),
            marker.kind,
            marker.key
        );
        check_component("upload", &marker.upload).with_context(|| {
            format!(
                "{}: field \"upload\" of the completion marker",
                self.bucket.describe(&object)
            )
        })?;
        Ok(Some((marker, bytes)))
    }

    /// Downloads the published remote entry, verifies every file against its manifest and
    /// installs it in the local front (appearing at once, with its completion marker).
    fn download(&self, id: &EntryId) -> anyhow::Result<()> {
        let (marker, marker_bytes) = self.remote_marker(id)?.ok_or_else(|| {
            anyhow::anyhow!("entry {id} is not published in {}", self.bucket.url())
        })?;
        let data = format!("{}/{}", entry_folder(id), marker.upload);
        let location = self.bucket.describe(&data);
        let names: Vec<String> = self
            .bucket
            .list_tree(&data)?
            .into_iter()
            .map(|object| object.name)
            .collect();
        anyhow::ensure!(
            !names.is_empty(),
            "{location}: the completion marker names this upload but it holds no files"
        );
        for name in &names {
            anyhow::ensure!(
                name.split('/')
                    .all(|part| !part.is_empty() && part != "." && part != ".."),
                "{location}: invalid object name \"{name}\""
            );
        }
        let temp = self
            .local
            .root()
            .join(DOWNLOADS_DIR)
            .join(&id.kind)
            .join(format!("{}.{}", id.key, unique_name()));
        fs::create_dir_all(&temp).with_context(|| format!("cannot create {}", temp.display()))?;
        let result = (|| -> anyhow::Result<()> {
            let bytes = self.bucket.download_files(&data, &names, &temp)?;
            let storage: ReadableListableStorage = crate::files::entry_storage(&temp)?;
            let reader = EntryReader::open(storage, &location)?;
            anyhow::ensure!(
                reader.kind() == id.kind && reader.key() == id.key,
                "{location}: the manifest names {}/{}, expected {id}",
                reader.kind(),
                reader.key()
            );
            let problems = reader.verify();
            anyhow::ensure!(
                problems.is_empty(),
                "remote entry {location} is corrupt: {}",
                problems.join("; ")
            );
            fsync_tree(&temp)?;
            self.install(id, &temp, &marker_bytes)?;
            eprintln!(
                "downloaded {id} from {location} ({} files, {bytes} bytes)",
                names.len()
            );
            Ok(())
        })();
        if result.is_err() {
            let _ = remove_dir_if_present(&temp);
        }
        result
    }

    /// Renames a complete downloaded folder into place, then writes its local completion
    /// marker (`marker`: the remote marker's bytes), as a local publish does.
    fn install(&self, id: &EntryId, folder: &Path, marker: &[u8]) -> anyhow::Result<()> {
        let target = self.local.entry_dir(id);
        if let Some(parent) = target.parent() {
            fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        if fs::rename(folder, &target).is_ok() {
            return write_completion_marker(&target, marker);
        }
        if self.local.entry_state(id)? == EntryState::Complete {
            remove_dir_if_present(folder)?; // Another run installed it first.
            return Ok(());
        }
        // An unpublished leftover occupies the place: move it aside under the lock.
        let held_here = self.held.lock().expect("held set poisoned").contains(id);
        let local_lock: Box<dyn KeyLock> = if held_here {
            Box::new(HeldHere(id.clone()))
        } else {
            self.local.try_lock(id)?.ok_or_else(|| {
                anyhow::anyhow!(
                    "cannot install {id}: another run is writing {}",
                    target.display()
                )
            })?
        };
        if self.local.entry_state(id)? != EntryState::Missing {
            self.local.quarantine(local_lock.as_ref())?;
        }
        fs::rename(folder, &target)
            .with_context(|| format!("cannot move {} to {}", folder.display(), target.display()))?;
        write_completion_marker(&target, marker)
    }

    /// Uploads the files of the local folder `source` (its completion marker excepted) as a
    /// new upload of `id`, then creates the remote completion marker. Returns false when
    /// another worker published the entry first (our upload is then deleted).
    fn upload(&self, id: &EntryId, source: &Path) -> anyhow::Result<bool> {
        let names: Vec<String> = relative_files(source)?
            .into_iter()
            .filter(|name| name != COMPLETION_MARKER)
            .collect();
        let upload = unique_name();
        let data = format!("{}/{upload}", entry_folder(id));
        let bytes = self.bucket.upload_files(source, &names, &data)?;
        let marker = RemoteMarker {
            kind: id.kind.clone(),
            key: id.key.clone(),
            upload,
            files: names.len(),
            bytes,
            published_at: crate::timefmt::rfc3339(std::time::SystemTime::now()),
        };
        let body = serde_json::to_vec(&marker).context("cannot serialize the marker")?;
        if self.bucket.put_create(&marker_object(id), body)?.is_some() {
            return Ok(true);
        }
        self.bucket.delete_tree(&data)?;
        Ok(false)
    }

    /// Publishes remotely the local entries whose upload failed in an earlier run.
    fn retry_pending_uploads(&self) -> anyhow::Result<Vec<String>> {
        let mut lines = Vec::new();
        let root = self.local.root().join(PENDING_DIR);
        for kind in plain_names(&root) {
            for key in plain_names(&root.join(&kind)) {
                let id = EntryId::new(&kind, &key);
                if Self::check_id(&id).is_err() {
                    continue;
                }
                let pending = self.pending_path(&id);
                if self.local.entry_state(&id)? != EntryState::Complete
                    || self.bucket.head(&marker_object(&id))?.is_some()
                {
                    remove_file_if_present(&pending)?;
                    continue;
                }
                // No lease needed: the marker is created only if absent, in a folder of
                // its own; the local lock keeps a local gc from removing the entry meanwhile.
                let Some(lock) = self.local.try_lock(&id)? else {
                    continue; // Another local run is on it.
                };
                let published = self.upload(&id, &self.local.entry_dir(&id))?;
                remove_file_if_present(&pending)?;
                drop(lock);
                lines.push(if published {
                    format!("pending upload: published {id} to {}", self.bucket.url())
                } else {
                    format!("pending upload: {id} was published by another worker meanwhile")
                });
            }
        }
        Ok(lines)
    }

    /// The lock of `id` made of its remote `lease` and `local` lock, recorded as held here.
    fn held_lock(&self, id: &EntryId, lease: Lease, local: Box<dyn KeyLock>) -> Box<dyn KeyLock> {
        self.held
            .lock()
            .expect("held set poisoned")
            .insert(id.clone());
        Box::new(RemoteLock {
            id: id.clone(),
            lease,
            _local: local,
            held: self.held.clone(),
        })
    }

    /// Every `<kind>/<key>` folder of the bucket with valid names, published or not.
    fn remote_folders(&self) -> anyhow::Result<Vec<EntryId>> {
        let mut ids = Vec::new();
        let (kinds, _) = self.bucket.list_folder("")?;
        for kind in kinds.into_iter().filter(|kind| !kind.starts_with('.')) {
            let (keys, _) = self.bucket.list_folder(&kind)?;
            for key in keys {
                let id = EntryId::new(&kind, &key);
                if Self::check_id(&id).is_ok() {
                    ids.push(id);
                }
            }
        }
        Ok(ids)
    }

    /// Every entry with a remote completion marker.
    fn remote_entries(&self) -> anyhow::Result<Vec<EntryId>> {
        let mut ids = Vec::new();
        for id in self.remote_folders()? {
            if self.bucket.head(&marker_object(&id))?.is_some() {
                ids.push(id);
            }
        }
        Ok(ids)
    }

    /// Removes remote uploads that no completion marker names (failed or losing uploads)
    /// once they are older than [`STALE_UPLOAD`] (younger ones may still be in progress);
    /// returns the bytes freed (or that would be, when `dry_run`).
    fn remove_remote_orphans(&self, dry_run: bool) -> anyhow::Result<u64> {
        let mut freed = 0;
        for id in self.remote_folders()? {
            let kept = self.remote_marker(&id)?.map(|(marker, _)| marker.upload);
            let mut orphans = BTreeSet::new();
            for object in self.bucket.list_tree(&entry_folder(&id))? {
                let upload = object.name.split('/').next().unwrap_or_default();
                if object.name != COMPLETION_MARKER
                    && Some(upload) != kept.as_deref()
                    && upload_is_stale(upload)
                {
                    freed += object.size;
                    orphans.insert(upload.to_string());
                }
            }
            if !dry_run {
                for upload in orphans {
                    self.bucket
                        .delete_tree(&format!("{}/{upload}", entry_folder(&id)))?;
                }
            }
        }
        Ok(freed)
    }
}

/// Whether an upload folder is older than [`STALE_UPLOAD`]; its name ends with its creation
/// time in nanoseconds since the epoch (see [`unique_name`]).
fn upload_is_stale(upload: &str) -> bool {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default()
        .as_nanos();
    match upload
        .rsplit('-')
        .next()
        .and_then(|text| text.parse::<u128>().ok())
    {
        Some(created) => now.saturating_sub(created) > STALE_UPLOAD.as_nanos(),
        None => true,
    }
}

impl Store for RemoteStore {
    fn describe(&self) -> String {
        format!(
            "{} (local copy in {})",
            self.bucket.url(),
            self.local.root().display()
        )
    }

    fn entry_state(&self, id: &EntryId) -> anyhow::Result<EntryState> {
        Self::check_id(id)?;
        let local = self.local.entry_state(id)?;
        if local == EntryState::Complete || self.bucket.head(&marker_object(id))?.is_some() {
            Ok(EntryState::Complete)
        } else {
            Ok(local)
        }
    }

    fn reader_storage(&self, id: &EntryId) -> anyhow::Result<(ReadableListableStorage, String)> {
        Self::check_id(id)?;
        if self.local.entry_state(id)? != EntryState::Complete {
            self.download(id)?;
        }
        self.local.reader_storage(id)
    }

    fn read_lease(&self, id: &EntryId) -> anyhow::Result<Box<dyn ReadLease>> {
        Self::check_id(id)?;
        let local = self.local.read_lease(id)?;
        readers::read_lease(&self.bucket, self.settings, id, local)
    }

    fn try_exclusive_read_lease(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn ReadLease>>> {
        Self::check_id(id)?;
        let Some(local) = self.local.try_exclusive_read_lease(id)? else {
            return Ok(None);
        };
        readers::try_exclusive_read_lease(&self.bucket, self.settings, id, local)
    }

    fn lock(&self, id: &EntryId, on_wait: &mut dyn FnMut()) -> anyhow::Result<Box<dyn KeyLock>> {
        Self::check_id(id)?;
        let mut waited = false;
        let mut notify_once = || {
            if !waited {
                waited = true;
                on_wait();
            }
        };
        let local = self.local.lock(id, &mut notify_once)?;
        let lease = Lease::acquire(
            &self.bucket,
            &lease_object(id),
            self.settings,
            true,
            &mut notify_once,
        )?
        .ok_or_else(|| anyhow::anyhow!("lease of {id} not obtained"))?;
        if let Acquired::TakenOver(previous) = lease.acquired() {
            eprintln!(
                "took over the lease of {id} from {previous}, which stopped renewing it for {:.1} s",
                self.settings.timeout.as_secs_f64()
            );
        }
        Ok(self.held_lock(id, lease, local))
    }

    fn try_lock(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn KeyLock>>> {
        Self::check_id(id)?;
        let Some(local) = self.local.try_lock(id)? else {
            return Ok(None);
        };
        let Some(lease) = Lease::acquire(
            &self.bucket,
            &lease_object(id),
            self.settings,
            false,
            &mut || {},
        )?
        else {
            return Ok(None);
        };
        Ok(Some(self.held_lock(id, lease, local)))
    }

    fn begin_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<Staging> {
        self.local.begin_staging(lock)
    }

    fn staged(&self) -> anyhow::Result<Vec<EntryId>> {
        self.local.staged()
    }

    fn remove_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<u64> {
        self.local.remove_staging(lock)
    }

    fn has_resumable_work(&self, id: &EntryId) -> bool {
        self.local.has_resumable_work(id)
    }

    fn publish(&self, lock: &dyn KeyLock, staging: &Staging) -> anyhow::Result<()> {
        let id = lock.id();
        // Upload first (the local publish moves the staged folder), but keep the result
        // locally even when the upload fails: it is valid, only not shared yet.
        let uploaded = self.upload(id, &staging.output_dir);
        self.local.publish(lock, staging)?;
        match uploaded {
            Ok(true) => Ok(()),
            Ok(false) => {
                eprintln!(
                    "another worker published {id} to {} first; its copy is kept there",
                    self.bucket.url()
                );
                Ok(())
            }
            Err(error) => {
                let pending = self.pending_path(id);
                if let Some(parent) = pending.parent() {
                    let _ = fs::create_dir_all(parent);
                }
                let _ = fs::write(&pending, b"");
                Err(error.context(format!(
                    "{id} is stored locally in {} but could not be published to {}; the next run with this cache retries the upload",
                    self.local.entry_dir(id).display(),
                    self.bucket.url()
                )))
            }
        }
    }

    fn quarantine(&self, lock: &dyn KeyLock) -> anyhow::Result<String> {
        let id = lock.id();
        // The marker goes first so that no reader ever sees a half-deleted entry.
        self.bucket.delete(&marker_object(id))?;
        self.bucket.delete_tree(&entry_folder(id))?;
        let mut location = format!("{} (deleted)", self.bucket.describe(&entry_folder(id)));
        if self.local.entry_state(id)? != EntryState::Missing {
            location.push_str(&format!("; local copy {}", self.local.quarantine(lock)?));
        }
        Ok(location)
    }

    fn list(&self) -> anyhow::Result<Vec<EntryId>> {
        let mut ids: BTreeSet<EntryId> = self.local.list()?.into_iter().collect();
        ids.extend(self.remote_entries()?);
        Ok(ids.into_iter().collect())
    }

    fn entry_bytes(&self, id: &EntryId) -> u64 {
        if self.local.entry_state(id).ok() == Some(EntryState::Complete) {
            return self.local.entry_bytes(id);
        }
        self.bucket
            .list_tree(&entry_folder(id))
            .map(|objects| objects.iter().map(|object| object.size).sum())
            .unwrap_or(0)
    }

    fn remove(&self, lock: &dyn KeyLock) -> anyhow::Result<u64> {
        let id = lock.id();
        self.bucket.delete(&marker_object(id))?;
        let mut bytes = self.bucket.delete_tree(&entry_folder(id))?;
        if self.local.entry_state(id)? != EntryState::Missing {
            bytes += self.local.remove(lock)?;
        }
        Ok(bytes)
    }

    fn clean_leftovers(&self) -> anyhow::Result<Vec<String>> {
        let mut lines = self.local.clean_leftovers()?;
        let downloads = self.local.root().join(DOWNLOADS_DIR);
        for kind in plain_names(&downloads) {
            for name in plain_names(&downloads.join(&kind)) {
                let folder = downloads.join(&kind).join(&name);
                let stale = fs::metadata(&folder)
                    .and_then(|metadata| metadata.modified())
                    .ok()
                    .and_then(|modified| modified.elapsed().ok())
                    .is_some_and(|age| age > STALE_DOWNLOAD);
                if stale && remove_dir_if_present(&folder)? {
                    lines.push(format!("interrupted download {kind}/{name}"));
                }
            }
        }
        lines.extend(self.retry_pending_uploads()?);
        for name in readers::remove_expired(&self.bucket, self.settings)? {
            lines.push(format!(
                "expired read lease {}",
                self.bucket.describe(&name)
            ));
        }
        Ok(lines)
    }

    fn empty_trash(&self, dry_run: bool) -> anyhow::Result<u64> {
        Ok(self.local.empty_trash(dry_run)? + self.remove_remote_orphans(dry_run)?)
    }

    fn local_state_dir(&self) -> PathBuf {
        self.local.local_state_dir()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_files_are_slash_separated_and_sorted() {
        let dir = tempfile::tempdir().unwrap();
        fs::create_dir_all(dir.path().join("values/c")).unwrap();
        fs::write(dir.path().join("zarr.json"), b"{}").unwrap();
        fs::write(dir.path().join("values/c/1"), b"x").unwrap();
        fs::write(dir.path().join("values/c/0"), b"x").unwrap();
        fs::write(dir.path().join(COMPLETION_MARKER), b"").unwrap();
        assert_eq!(
            relative_files(dir.path()).unwrap(),
            [COMPLETION_MARKER, "values/c/0", "values/c/1", "zarr.json"]
        );
    }

    #[test]
    fn only_old_or_unnamed_uploads_are_stale() {
        let fresh = unique_name();
        assert!(!upload_is_stale(&fresh));
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos()
            - 2 * STALE_UPLOAD.as_nanos();
        assert!(upload_is_stale(&format!("node7-42-{nanos}")));
        assert!(upload_is_stale("garbage"));
        // A creation time in the future (clock skew) is not stale.
        assert!(!upload_is_stale(&format!("h-1-{}", u128::MAX / 2)));
    }

    #[test]
    fn object_names_follow_the_layout() {
        let id = EntryId::new("motion", "abc123");
        assert_eq!(marker_object(&id), "motion/abc123/.complete");
        assert_eq!(entry_folder(&id), "motion/abc123");
        assert_eq!(lease_object(&id), ".leases/motion/abc123");
        assert!(RemoteStore::check_id(&EntryId::new("motion", "../x")).is_err());
    }
}
