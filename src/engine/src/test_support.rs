//! Helpers for tests of code that must refuse pseudo-files instead of blocking on them
//! (used by this crate's tests and by the stages' tests).

use std::path::Path;
use std::time::Duration;

/// Makes a FIFO (named pipe) at `path` with `mkfifo`.
pub fn make_fifo(path: &Path) {
    let status = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .expect("mkfifo runs");
    assert!(status.success(), "mkfifo {}", path.display());
}

/// Runs `work` on a thread and panics if it has not returned within `seconds`: a read that
/// blocks (on a FIFO, say) fails the test instead of hanging it.
pub fn finishes_within<T: Send + 'static>(
    seconds: u64,
    work: impl FnOnce() -> T + Send + 'static,
) -> T {
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = sender.send(work());
    });
    receiver
        .recv_timeout(Duration::from_secs(seconds))
        .unwrap_or_else(|_| panic!("the call blocked for more than {seconds} s"))
}
