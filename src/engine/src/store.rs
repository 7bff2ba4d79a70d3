//! Where entries live. [`Store`] is the seam between the engine and storage, implemented by
//! the local folder ([`crate::local::LocalStore`]) and the S3-compatible bucket
//! (`crate::remote::RemoteStore`); this module holds what they share.

use std::path::PathBuf;

use zarrs::storage::ReadableListableStorage;

use crate::entry::{EntryReader, ReadLease};

/// The suffix of the file whose presence makes an entry visible. In a local store the
/// marker of the entry folder `<kind>/<key>/` is the file `<kind>/<key>.complete` beside it
/// (see [`crate::local::completion_marker`]); in the remote store it is the object `<kind>/<key>/.complete`,
/// beside the uploads it names.
pub const COMPLETION_MARKER: &str = ".complete";

/// One entry: its stage kind and key.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct EntryId {
    pub kind: String,
    pub key: String,
}

impl EntryId {
    pub fn new(kind: &str, key: &str) -> Self {
        Self {
            kind: kind.to_string(),
            key: key.to_string(),
        }
    }
}

impl std::fmt::Display for EntryId {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(formatter, "{}/{}", self.kind, self.key)
    }
}

/// Whether an entry can be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntryState {
    /// Published: the completion marker exists.
    Complete,
    /// Present without a completion marker (a publish was interrupted); never used.
    Incomplete,
    Missing,
}

/// Exclusive right to compute one entry; released on drop. Locally a file lock, remotely a
/// lease object.
pub trait KeyLock: Send {
    fn id(&self) -> &EntryId;
}

/// Local directories where a stage computes its entry before publishing.
#[derive(Debug, Clone)]
pub struct Staging {
    /// The Zarr group being written (cleared when a run starts).
    pub output_dir: PathBuf,
    /// The stage's resumable work folder (kept across interrupted runs of the same key).
    pub work_dir: PathBuf,
}

/// Storage of cache entries. Methods that change an entry take the [`KeyLock`] as proof that
/// the caller holds it.
pub trait Store: Send + Sync {
    /// Human-readable location (a path or URL).
    fn describe(&self) -> String;
    /// Whether the entry is published.
    fn entry_state(&self, id: &EntryId) -> anyhow::Result<EntryState>;
    /// A zarrs storage rooted at the published entry, and a location for messages.
    fn reader_storage(&self, id: &EntryId) -> anyhow::Result<(ReadableListableStorage, String)>;
    /// Opens a published entry.
    fn open_entry(&self, id: &EntryId) -> anyhow::Result<EntryReader> {
        let (storage, location) = self.reader_storage(id)?;
        EntryReader::open(storage, &location)
    }
    /// Takes a shared read lease on an entry (waiting while `gc` is deleting it); the caller
    /// checks afterwards that the entry still exists.
    fn read_lease(&self, id: &EntryId) -> anyhow::Result<Box<dyn ReadLease>>;
    /// Takes the read lease exclusively if no reader holds it (for `gc`); `None` while some
    /// run reads the entry.
    fn try_exclusive_read_lease(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn ReadLease>>>;
    /// Takes the per-key lock, waiting for another holder; `on_wait` is called once before
    /// waiting.
    fn lock(&self, id: &EntryId, on_wait: &mut dyn FnMut()) -> anyhow::Result<Box<dyn KeyLock>>;
    /// Takes the per-key lock if nobody holds it.
    fn try_lock(&self, id: &EntryId) -> anyhow::Result<Option<Box<dyn KeyLock>>>;
    /// Prepares the staging area: an empty output directory and the kept work directory.
    fn begin_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<Staging>;
    /// Entries with a staging area (a run in progress, or the work folder of an interrupted
    /// one).
    fn staged(&self) -> anyhow::Result<Vec<EntryId>>;
    /// Deletes the staging area of an entry, work folder (checkpoints) included; returns the
    /// bytes freed.
    fn remove_staging(&self, lock: &dyn KeyLock) -> anyhow::Result<u64>;
    /// Whether a staging work directory with content exists (a resumable partial run).
    fn has_resumable_work(&self, id: &EntryId) -> bool;
    /// Makes the staged output the published entry and removes the staging area.
    fn publish(&self, lock: &dyn KeyLock, staging: &Staging) -> anyhow::Result<()>;
    /// Moves a published or incomplete entry aside (it will be recomputed); returns where.
    fn quarantine(&self, lock: &dyn KeyLock) -> anyhow::Result<String>;
    /// Every published entry.
    fn list(&self) -> anyhow::Result<Vec<EntryId>>;
    /// Stored bytes of an entry.
    fn entry_bytes(&self, id: &EntryId) -> u64;
    /// Deletes an entry; returns the bytes freed.
    fn remove(&self, lock: &dyn KeyLock) -> anyhow::Result<u64>;
    /// Removes leftovers of killed runs whose lock nobody holds (partial outputs, unpublished
    /// entries, quarantined entries); keeps work directories for resume. Returns one line per
    /// removal.
    fn clean_leftovers(&self) -> anyhow::Result<Vec<String>>;
    /// Deletes quarantined entries and unreferenced uploads; returns the bytes freed (or that
    /// would be, when `dry_run`).
    fn empty_trash(&self, dry_run: bool) -> anyhow::Result<u64>;
    /// A local directory for engine bookkeeping (file digest memo).
    fn local_state_dir(&self) -> PathBuf;
}

/// Checks that a kind or key is a plain folder name.
pub(crate) fn check_component(what: &str, value: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        !value.is_empty()
            && !value.starts_with('.')
            && value
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-'),
        "invalid {what} \"{value}\" for a cache folder name"
    );
    Ok(())
}
