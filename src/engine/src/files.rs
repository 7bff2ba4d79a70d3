//! Reading and walking user-named files safely: only regular files stored on real file
//! systems are read or hashed. A device such as `/dev/zero`, a FIFO or a socket never ends or
//! blocks a read; a file of a kernel file system (`/proc`, `/sys`, cgroups, debugfs, ...)
//! reports a size (often 0) that says nothing of what it yields, and may block or never end
//! (`/proc/kmsg`, `/proc/self/pagemap`). So a file is opened without blocking
//! (`O_NONBLOCK`: opening a FIFO waits for a writer otherwise), the *opened handle* must be a
//! regular file on a file system that stores data, and no read goes past the size the file
//! declared when it was opened. A folder walk neither follows a symbolic link out of its
//! root nor goes deeper or wider than fixed caps.

use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context as _, bail};
use zarrs::filesystem::FilesystemStore;
use zarrs::storage::byte_range::ByteRangeIterator;
use zarrs::storage::{
    ListableStorageTraits, MaybeBytesIterator, ReadableListableStorage, ReadableStorageTraits,
    StorageError, StoreKey, StoreKeys, StoreKeysPrefixes, StorePrefix,
};

/// The deepest a folder walk goes below its root.
pub const MAX_WALK_DEPTH: usize = 64;
/// The most files one folder walk lists.
pub const MAX_WALK_FILES: usize = 1_000_000;

/// What a path that is neither a regular file nor a folder is, in words.
fn kind_of(file_type: &fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt as _;
        if file_type.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if file_type.is_char_device() {
            return "a character device";
        }
        if file_type.is_block_device() {
            return "a block device";
        }
        if file_type.is_socket() {
            return "a socket";
        }
    }
    if file_type.is_dir() {
        return "a folder";
    }
    "not a regular file"
}

/// Kernel file systems whose files are made up when read, by `statfs` type (the magic
/// numbers of `linux/magic.h`). `devtmpfs` reports the tmpfs type, which also holds real
/// files: its devices are refused by their file type instead.
#[cfg(target_os = "linux")]
const PSEUDO_FILE_SYSTEMS: &[(u64, &str)] = &[
    (0x9fa0, "proc"),
    (0x6265_6572, "sysfs"),
    (0x1cd1, "devpts"),
    (0x6462_6720, "debugfs"),
    (0x7472_6163, "tracefs"),
    (0x7363_6673, "securityfs"),
    (0x0027_e0eb, "cgroup"),
    (0x6367_7270, "cgroup2"),
    (0xcafe_4a11, "bpf"),
    (0x6165_676c, "pstore"),
    (0x6265_6570, "configfs"),
    (0xde5e_81e4, "efivarfs"),
    (0x4249_4e4d, "binfmt_misc"),
    (0x6573_5543, "fusectl"),
    (0x1980_0202, "mqueue"),
];

/// The name of the kernel file system `statfs` type `file_system` is, if it is one.
#[cfg(target_os = "linux")]
fn pseudo_file_system(stats: &libc::statfs) -> Option<&'static str> {
    // `f_type` is a signed or unsigned integer of 32 or 64 bits, by target: compare it as
    // the unsigned 32-bit magic number it holds.
    #[allow(clippy::unnecessary_cast)]
    let magic = (stats.f_type as u64) & 0xffff_ffff;
    PSEUDO_FILE_SYSTEMS
        .iter()
        .find(|(known, _)| *known == magic)
        .map(|(_, name)| *name)
}

/// The error for a file of the kernel file system `name`.
#[cfg(target_os = "linux")]
fn pseudo_file_error(path: &Path, name: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "{} lies on the kernel's {name} file system: its files are not stored data (their \
         size says nothing of what they yield, and reading may block or never end), so \
         only files on real file systems are read",
        path.display()
    )
}

/// Refuses `path` when `statfs` (the call `stat`, filling the buffer it is given, returning
/// 0 on success) says it lies on a kernel file system.
#[cfg(target_os = "linux")]
fn check_file_system(
    path: &Path,
    stat: impl FnOnce(*mut libc::statfs) -> libc::c_int,
) -> anyhow::Result<()> {
    let mut stats = std::mem::MaybeUninit::<libc::statfs>::uninit();
    if stat(stats.as_mut_ptr()) != 0 {
        return Err(std::io::Error::last_os_error())
            .with_context(|| format!("cannot read the file system of {}", path.display()));
    }
    // SAFETY: the call returned 0, so it filled `stats`.
    let stats = unsafe { stats.assume_init() };
    match pseudo_file_system(&stats) {
        Some(name) => Err(pseudo_file_error(path, name)),
        None => Ok(()),
    }
}

/// Refuses `path` when it lies on a kernel file system (by `statfs`; a no-op off Linux).
fn check_file_system_of_path(path: &Path) -> anyhow::Result<()> {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::ffi::OsStrExt as _;
        let c_path = std::ffi::CString::new(path.as_os_str().as_bytes())
            .with_context(|| format!("{} holds a NUL byte", path.display()))?;
        // SAFETY: `c_path` is a NUL-terminated string that outlives the call, and `stats`
        // points to writable memory of the size of `struct statfs`.
        check_file_system(path, |stats| unsafe {
            libc::statfs(c_path.as_ptr(), stats)
        })?;
    }
    #[cfg(not(target_os = "linux"))]
    let _ = path;
    Ok(())
}

/// Refuses the opened `file` (named `path` in errors) when it lies on a kernel file system.
fn check_file_system_of_handle(file: &fs::File, path: &Path) -> anyhow::Result<()> {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd as _;
        // SAFETY: the descriptor belongs to `file`, open for the whole call, and `stats`
        // points to writable memory of the size of `struct statfs`.
        check_file_system(path, |stats| unsafe {
            libc::fstatfs(file.as_raw_fd(), stats)
        })?;
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (file, path);
    Ok(())
}

fn refuse_unless_regular(path: &Path, metadata: &fs::Metadata) -> anyhow::Result<()> {
    if !metadata.is_file() {
        bail!(
            "{} is {}: only regular files can be read",
            path.display(),
            kind_of(&metadata.file_type())
        );
    }
    Ok(())
}

/// The metadata of `path` (through symbolic links), or an error naming it when it is not a
/// regular file or lies on a kernel file system (`/proc`, `/sys`, ...). Nothing is opened.
pub fn regular_file_metadata(path: &Path) -> anyhow::Result<fs::Metadata> {
    let metadata = fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    refuse_unless_regular(path, &metadata)?;
    check_file_system_of_path(path)?;
    Ok(metadata)
}

/// A regular file opened for reading by [`open_regular_file`]: reads end at the size it
/// declared when it was opened, and a file that holds more (a pseudo-file, or one written
/// while it is read) is an error naming it, found at most one byte past that size.
#[derive(Debug)]
pub struct RegularFile {
    file: fs::File,
    path: PathBuf,
    declared: u64,
    read: u64,
}

impl RegularFile {
    /// The size the file declared when it was opened: no read goes past it.
    pub fn declared_len(&self) -> u64 {
        self.declared
    }

    /// Reads the rest of the file (see [`Read::read_to_end`]), naming it in errors.
    pub fn read_all(mut self) -> anyhow::Result<Vec<u8>> {
        let remaining = self.declared.saturating_sub(self.read);
        // The declared size of a regular file is backed by storage, so this is no larger
        // than what the disk holds; the bound caps the up-front reservation all the same.
        let mut bytes = Vec::with_capacity(usize::try_from(remaining.min(1 << 30)).unwrap_or(0));
        self.read_to_end(&mut bytes)
            .with_context(|| format!("cannot read {}", self.path.display()))?;
        Ok(bytes)
    }
}

impl Read for RegularFile {
    fn read(&mut self, buffer: &mut [u8]) -> std::io::Result<usize> {
        // One byte more than what is left tells "ends where it said" from "holds more".
        let allowed = self.declared.saturating_sub(self.read).saturating_add(1);
        let length =
            usize::try_from(allowed).map_or(buffer.len(), |allowed| allowed.min(buffer.len()));
        let count = self.file.read(&mut buffer[..length])?;
        self.read += count as u64;
        if self.read > self.declared {
            return Err(std::io::Error::other(format!(
                "{} holds more than the {} bytes it declares (a pseudo-file, or a file written \
                 while it is read): refused",
                self.path.display(),
                self.declared
            )));
        }
        Ok(count)
    }
}

/// Opens a regular file for reading, checked on the opened handle: opened with
/// `O_NONBLOCK` (a FIFO does not wait for a writer) and `O_NOCTTY`, then refused unless the
/// handle is a regular file on a real file system (not `/proc`, `/sys`, ...). Reads of the
/// result stop at the size declared now ([`RegularFile`]).
pub fn open_regular_file(path: &Path) -> anyhow::Result<RegularFile> {
    // Checked by path first, for a clear message where opening alone would fail otherwise
    // (`/proc/kmsg` is not readable by users) and to open nothing that is not a file.
    regular_file_metadata(path)?;
    let mut options = fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt as _;
        // O_NONBLOCK changes nothing for regular files; it keeps a FIFO or device swapped
        // in after the check above from blocking the open.
        options.custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY);
    }
    let file = options
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    // The path may have been replaced in between: the opened handle is what counts.
    let metadata = file
        .metadata()
        .with_context(|| format!("cannot read {}", path.display()))?;
    refuse_unless_regular(path, &metadata)?;
    check_file_system_of_handle(&file, path)?;
    Ok(RegularFile {
        file,
        path: path.to_path_buf(),
        declared: metadata.len(),
        read: 0,
    })
}

/// Reads a whole regular file (see [`open_regular_file`]), naming it in errors.
pub fn read_regular_file(path: &Path) -> anyhow::Result<Vec<u8>> {
    open_regular_file(path)?.read_all()
}

/// Reads a whole regular file of at most `max_bytes` bytes, naming it (and `what` it is) in
/// errors; a larger file is refused from its declared size, before anything is read.
pub fn read_regular_file_at_most(
    path: &Path,
    max_bytes: u64,
    what: &str,
) -> anyhow::Result<Vec<u8>> {
    let file = open_regular_file(path)?;
    if file.declared_len() > max_bytes {
        bail!(
            "{} is {} bytes: {what} may be at most {max_bytes} bytes",
            path.display(),
            file.declared_len()
        );
    }
    file.read_all()
}

/// Refuses a cache folder whose path is not UTF-8, naming it (shown lossily): zarrs names
/// files by text and refuses such a path with only "base path … is not valid".
pub fn require_utf8_path(dir: &Path) -> anyhow::Result<()> {
    if dir.to_str().is_none() {
        bail!(
            "{} is not valid UTF-8: the cache and its entries must lie under a path in UTF-8 \
             (the Zarr store names files by text); move or rename the folder",
            dir.display()
        );
    }
    Ok(())
}

/// A zarrs store over the local folder `dir` (see [`require_utf8_path`]).
pub fn filesystem_store(dir: &Path) -> anyhow::Result<FilesystemStore> {
    require_utf8_path(dir)?;
    FilesystemStore::new(dir).with_context(|| format!("cannot open {}", dir.display()))
}

/// The storage an entry folder of the cache is read through: a zarrs [`FilesystemStore`]
/// whose every read is checked first, so that a chunk or metadata file replaced by a FIFO,
/// a device or a link into `/proc` is an error naming it, not a read that blocks or never
/// ends. (zarrs opens the file itself, so the check is of the path just before; it guards
/// against a damaged or tampered cache, not a racing writer.)
pub fn entry_storage(dir: &Path) -> anyhow::Result<ReadableListableStorage> {
    Ok(Arc::new(CheckedFilesystemStore {
        inner: filesystem_store(dir)?,
    }))
}

/// See [`entry_storage`].
#[derive(Debug)]
struct CheckedFilesystemStore {
    inner: FilesystemStore,
}

impl CheckedFilesystemStore {
    /// Whether `key` exists as a regular file on a real file system; an error naming the
    /// file when it exists as anything else.
    fn check(&self, key: &StoreKey) -> Result<bool, StorageError> {
        let path = self.inner.key_to_fspath(key);
        let metadata = match fs::metadata(&path) {
            Ok(metadata) => metadata,
            Err(error) if error.kind() == std::io::ErrorKind::NotFound => return Ok(false),
            Err(error) => {
                return Err(StorageError::Other(format!(
                    "cannot read {}: {error}",
                    path.display()
                )));
            }
        };
        refuse_unless_regular(&path, &metadata)
            .and_then(|()| check_file_system_of_path(&path))
            .map_err(|error| StorageError::Other(format!("{error:#}")))?;
        Ok(true)
    }
}

impl ReadableStorageTraits for CheckedFilesystemStore {
    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        if !self.check(key)? {
            return Ok(None);
        }
        self.inner.get_partial_many(key, byte_ranges)
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        if !self.check(key)? {
            return Ok(None);
        }
        self.inner.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.inner.supports_get_partial()
    }
}

impl ListableStorageTraits for CheckedFilesystemStore {
    fn list(&self) -> Result<StoreKeys, StorageError> {
        self.inner.list()
    }

    fn list_prefix(&self, prefix: &StorePrefix) -> Result<StoreKeys, StorageError> {
        self.inner.list_prefix(prefix)
    }

    fn list_dir(&self, prefix: &StorePrefix) -> Result<StoreKeysPrefixes, StorageError> {
        self.inner.list_dir(prefix)
    }

    fn size_prefix(&self, prefix: &StorePrefix) -> Result<u64, StorageError> {
        self.inner.size_prefix(prefix)
    }
}

/// The regular files under `root`, as sorted `/`-separated paths relative to it. Symbolic
/// links are followed only while they stay inside `root`; folders in `excluded` (canonical
/// paths, e.g. the cache in use kept inside the dataset) and every pipeline cache (a folder
/// holding the cache tag, [`crate::local::is_pipeline_cache`]) are skipped; anything that is
/// neither a regular file nor a folder is an error naming it, as are a walk deeper than
/// [`MAX_WALK_DEPTH`] and more than [`MAX_WALK_FILES`] files.
pub fn walk_regular_files(root: &Path, excluded: &[PathBuf]) -> anyhow::Result<Vec<String>> {
    let canonical_root =
        fs::canonicalize(root).with_context(|| format!("cannot resolve {}", root.display()))?;
    check_file_system_of_path(&canonical_root)?;
    let mut files = Vec::new();
    walk(&canonical_root, root, root, 0, excluded, &mut files)?;
    files.sort();
    Ok(files)
}

fn walk(
    canonical_root: &Path,
    root: &Path,
    dir: &Path,
    depth: usize,
    excluded: &[PathBuf],
    files: &mut Vec<String>,
) -> anyhow::Result<()> {
    if depth > MAX_WALK_DEPTH {
        bail!(
            "{} lies more than {MAX_WALK_DEPTH} folders deep below {} (a link loop?)",
            dir.display(),
            root.display()
        );
    }
    for entry in fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let entry = entry.with_context(|| format!("cannot list {}", dir.display()))?;
        let path = entry.path();
        let mut file_type = entry
            .file_type()
            .with_context(|| format!("cannot read {}", path.display()))?;
        let canonical = fs::canonicalize(&path)
            .with_context(|| format!("cannot resolve {}", path.display()))?;
        if file_type.is_symlink() {
            if !canonical.starts_with(canonical_root) {
                bail!(
                    "{} is a symbolic link to {}, outside {}: links are not followed out \
                     of a dataset folder (copy or move the target inside it)",
                    path.display(),
                    canonical.display(),
                    root.display()
                );
            }
            file_type = fs::metadata(&path)
                .with_context(|| format!("cannot read {}", path.display()))?
                .file_type();
        }
        if excluded.contains(&canonical)
            || (file_type.is_dir() && crate::local::is_pipeline_cache(&path))
        {
            continue;
        }
        if file_type.is_dir() {
            walk(canonical_root, root, &path, depth + 1, excluded, files)?;
        } else if file_type.is_file() {
            if files.len() >= MAX_WALK_FILES {
                bail!("{} holds more than {MAX_WALK_FILES} files", root.display());
            }
            let relative = path.strip_prefix(root).unwrap_or(&path);
            files.push(relative.to_string_lossy().replace('\\', "/"));
        } else {
            bail!(
                "{} is {}: only regular files and folders can be read",
                path.display(),
                kind_of(&file_type)
            );
        }
    }
    Ok(())
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;
    use crate::test_support::{finishes_within, make_fifo};
    use std::time::{Duration, Instant};

    #[test]
    fn devices_and_fifos_are_refused_quickly() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        make_fifo(&fifo);
        for path in [Path::new("/dev/zero"), fifo.as_path()] {
            let start = Instant::now();
            let error = read_regular_file(path).unwrap_err().to_string();
            assert!(start.elapsed() < Duration::from_secs(1), "{error}");
            assert!(error.contains("only regular files"), "{error}");
            assert!(error.contains(&path.display().to_string()), "{error}");
        }
        let error = read_regular_file(dir.path()).unwrap_err().to_string();
        assert!(error.contains("a folder"), "{error}");
        std::fs::write(dir.path().join("file"), b"abc").unwrap();
        assert_eq!(read_regular_file(&dir.path().join("file")).unwrap(), b"abc");
    }

    /// Files of `/proc` look regular, declare size 0 and yield data (or block, or never end):
    /// refused from their file system, by path and without reading, in milliseconds.
    #[cfg(target_os = "linux")]
    #[test]
    fn kernel_pseudo_files_are_refused_quickly() {
        for name in ["/proc/self/status", "/proc/self/pagemap", "/proc/kmsg"] {
            let path = Path::new(name);
            if name != "/proc/kmsg" {
                // The case the issue reports: a "regular" file of size 0 that has data.
                let metadata = fs::metadata(path).unwrap();
                assert!(metadata.is_file() && metadata.len() == 0, "{name}");
            }
            let error = finishes_within(2, move || {
                let start = Instant::now();
                let error = read_regular_file(Path::new(name)).unwrap_err();
                (format!("{error:#}"), start.elapsed())
            });
            assert!(
                error.1 < Duration::from_millis(500),
                "{name}: {:?}",
                error.1
            );
            assert!(error.0.contains(name), "{}", error.0);
            assert!(error.0.contains("kernel's proc file system"), "{}", error.0);
            let error = regular_file_metadata(path).unwrap_err().to_string();
            assert!(error.contains("proc file system"), "{error}");
        }
        // A sysfs file, where the machine has one.
        let sys = Path::new("/sys/kernel/mm/transparent_hugepage/enabled");
        if sys.is_file() {
            let error = format!("{:#}", read_regular_file(sys).unwrap_err());
            assert!(error.contains("sysfs"), "{error}");
        }
        // A walk of a proc folder stops at its root.
        let error = walk_regular_files(Path::new("/proc/self"), &[])
            .unwrap_err()
            .to_string();
        assert!(error.contains("proc file system"), "{error}");
    }

    /// A FIFO is refused without waiting for a writer.
    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        make_fifo(&fifo);
        let error = finishes_within(2, move || {
            format!("{:#}", read_regular_file(&fifo).unwrap_err())
        });
        assert!(error.contains("a FIFO (named pipe)"), "{error}");
        assert!(error.contains("pipe"), "{error}");
    }

    /// No read goes past the size a file declared when it was opened: one that holds more
    /// by the time it is read is refused, naming it.
    #[test]
    fn reads_stop_at_the_declared_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("growing");
        fs::write(&path, b"abc").unwrap();
        let opened = open_regular_file(&path).unwrap();
        assert_eq!(opened.declared_len(), 3);
        fs::write(&path, b"abcdefgh").unwrap();
        let error = format!("{:#}", opened.read_all().unwrap_err());
        assert!(
            error.contains("holds more than the 3 bytes it declares"),
            "{error}"
        );
        assert!(error.contains("growing"), "{error}");
        // An empty file that stays empty reads as empty.
        fs::write(&path, b"").unwrap();
        assert!(read_regular_file(&path).unwrap().is_empty());
        // The size cap refuses from the declared size, naming the file and what it is.
        fs::write(&path, b"abcdefgh").unwrap();
        let error = read_regular_file_at_most(&path, 4, "a pipeline file")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("8 bytes: a pipeline file may be at most 4 bytes"),
            "{error}"
        );
        assert_eq!(
            read_regular_file_at_most(&path, 8, "x").unwrap(),
            b"abcdefgh"
        );
    }

    /// The cache's own files are read through zarrs: a chunk or metadata file replaced by a
    /// FIFO is an error naming it, not a read that waits for a writer forever.
    #[test]
    fn entry_storage_refuses_a_fifo_in_place_of_a_chunk() {
        use zarrs::storage::ReadableStorageTraits as _;
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("zarr.json"), b"{}").unwrap();
        make_fifo(&dir.path().join("c"));
        let root = dir.path().to_path_buf();
        let (present, fifo, missing) = finishes_within(2, move || {
            let storage = entry_storage(&root).unwrap();
            let present = storage.get(&StoreKey::new("zarr.json").unwrap());
            let fifo = storage.get(&StoreKey::new("c").unwrap());
            let missing = storage.get(&StoreKey::new("absent").unwrap());
            (present, fifo.map(|_| ()), missing)
        });
        assert_eq!(present.unwrap().unwrap().as_ref(), b"{}");
        let error = fifo.unwrap_err().to_string();
        assert!(error.contains("a FIFO (named pipe)"), "{error}");
        assert!(missing.unwrap().is_none());
    }

    /// zarrs cannot take a path that is not UTF-8: the error names it (shown lossily)
    /// instead of "base path … is not valid".
    #[test]
    fn a_non_utf8_store_path_is_named() {
        use std::os::unix::ffi::OsStrExt as _;
        let dir = tempfile::tempdir().unwrap();
        let odd = dir.path().join(std::ffi::OsStr::from_bytes(b"cache-\xff"));
        let Err(error) = entry_storage(&odd) else {
            panic!("a path that is not UTF-8 was accepted");
        };
        let error = format!("{error:#}");
        assert!(error.contains("cache-\u{fffd}"), "{error}");
        assert!(error.contains("is not valid UTF-8"), "{error}");
    }

    #[test]
    fn walks_refuse_fifos_links_out_and_skip_excluded_folders() {
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret"), b"x").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("a/b")).unwrap();
        std::fs::write(root.join("a/b/one"), b"1").unwrap();
        std::fs::write(root.join("two"), b"2").unwrap();
        std::os::unix::fs::symlink(root.join("two"), root.join("a/link_in")).unwrap();
        std::fs::create_dir(root.join("cache")).unwrap();
        std::fs::write(root.join("cache/entry"), b"3").unwrap();
        let cache = std::fs::canonicalize(root.join("cache")).unwrap();
        assert_eq!(
            walk_regular_files(root, std::slice::from_ref(&cache)).unwrap(),
            ["a/b/one", "a/link_in", "two"]
        );
        assert_eq!(walk_regular_files(root, &[]).unwrap().len(), 4);

        std::os::unix::fs::symlink(outside.path(), root.join("out")).unwrap();
        let error = walk_regular_files(root, &[]).unwrap_err().to_string();
        assert!(error.contains("outside"), "{error}");
        std::fs::remove_file(root.join("out")).unwrap();

        // A link back to an ancestor loops until the depth cap.
        std::os::unix::fs::symlink(root.join("a"), root.join("a/b/loop")).unwrap();
        let error = walk_regular_files(root, &[]).unwrap_err().to_string();
        assert!(error.contains("folders deep"), "{error}");
        std::fs::remove_file(root.join("a/b/loop")).unwrap();

        make_fifo(&root.join("a/pipe"));
        let start = Instant::now();
        let error = walk_regular_files(root, &[]).unwrap_err().to_string();
        assert!(start.elapsed() < Duration::from_secs(1));
        assert!(error.contains("FIFO"), "{error}");
    }

    #[test]
    fn walking_dev_does_not_follow_links_into_proc() {
        let start = Instant::now();
        let error = walk_regular_files(Path::new("/dev"), &[])
            .unwrap_err()
            .to_string();
        assert!(start.elapsed() < Duration::from_secs(1), "{error}");
    }
}
