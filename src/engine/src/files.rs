//! Reading and walking user-named files safely: only regular files are read or hashed (a
//! device such as `/dev/zero`, a FIFO or a socket never ends or blocks a read, so it is
//! refused from its metadata before it is opened), and a folder walk neither follows a
//! symbolic link out of its root nor goes deeper or wider than fixed caps.

use std::fs;
use std::io::Read as _;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};

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

/// The metadata of `path` (through symbolic links), or an error naming it when it is not a
/// regular file.
pub fn regular_file_metadata(path: &Path) -> anyhow::Result<fs::Metadata> {
    let metadata = fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    if !metadata.is_file() {
        bail!(
            "{} is {}: only regular files can be read",
            path.display(),
            kind_of(&metadata.file_type())
        );
    }
    Ok(metadata)
}

/// Opens a regular file for reading, refusing anything else before opening it (opening a
/// FIFO blocks) and checking the opened file again (it may have been replaced in between).
pub fn open_regular_file(path: &Path) -> anyhow::Result<fs::File> {
    regular_file_metadata(path)?;
    let file = fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let metadata = file
        .metadata()
        .with_context(|| format!("cannot read {}", path.display()))?;
    if !metadata.is_file() {
        bail!(
            "{} is {}: only regular files can be read",
            path.display(),
            kind_of(&metadata.file_type())
        );
    }
    Ok(file)
}

/// Reads a whole regular file (see [`open_regular_file`]), naming it in errors.
pub fn read_regular_file(path: &Path) -> anyhow::Result<Vec<u8>> {
    let mut file = open_regular_file(path)?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes)
        .with_context(|| format!("cannot read {}", path.display()))?;
    Ok(bytes)
}

/// The regular files under `root`, as sorted `/`-separated paths relative to it. Symbolic
/// links are followed only while they stay inside `root`; folders in `excluded` (canonical
/// paths, e.g. a cache kept inside the dataset) are skipped; anything that is neither a
/// regular file nor a folder is an error naming it, as are a walk deeper than
/// [`MAX_WALK_DEPTH`] and more than [`MAX_WALK_FILES`] files.
pub fn walk_regular_files(root: &Path, excluded: &[PathBuf]) -> anyhow::Result<Vec<String>> {
    let canonical_root =
        fs::canonicalize(root).with_context(|| format!("cannot resolve {}", root.display()))?;
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
        if excluded.contains(&canonical) {
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
    use std::time::{Duration, Instant};

    fn make_fifo(path: &Path) {
        let status = std::process::Command::new("mkfifo")
            .arg(path)
            .status()
            .expect("mkfifo runs");
        assert!(status.success());
    }

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
