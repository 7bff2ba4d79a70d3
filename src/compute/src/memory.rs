//! How the process's allocator treats the large, short-lived buffers of training.
//!
//! A training iteration allocates and frees the same buffers every time (activations of
//! 5860 x 64..512 floats, image gradients, per-Gaussian arrays: 0.1-15 MB each). glibc's
//! malloc hands blocks above its mmap threshold straight to the kernel and gives freed heap
//! tops back (`brk`/`munmap`), so each iteration page-faults and the kernel zeroes the same
//! memory again: on the `fast` preset that was 15-20% of an iteration's wall time (page faults,
//! `clear_page`, `munmap` in `perf`), most of it in the backward phase.
//! [`retain_freed_memory`] raises both thresholds, so freed blocks are kept and reused; the
//! process keeps its peak footprint instead of returning it between iterations.
//!
//! Other platforms (and musl) keep their allocator's defaults: the call does nothing there.

/// Largest mmap threshold glibc accepts through `mallopt` on 64-bit targets (half its 64 MiB
/// per-thread heap): blocks above this are still mapped and unmapped per allocation.
pub const MMAP_THRESHOLD_BYTES: i32 = 32 << 20;

/// What [`retain_freed_memory`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AllocatorTuning {
    /// glibc accepted both settings.
    Applied,
    /// glibc rejected one of them (the defaults stay in force for it).
    Rejected,
    /// Not glibc: nothing was changed.
    Unsupported,
}

/// Keeps freed memory of up to [`MMAP_THRESHOLD_BYTES`] per block in the process for reuse
/// instead of returning it to the kernel (glibc `M_MMAP_THRESHOLD` and `M_TRIM_THRESHOLD`).
/// Call it once at program start, before worker threads allocate; calling it again is
/// harmless.
pub fn retain_freed_memory() -> AllocatorTuning {
    imp::retain_freed_memory()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
mod imp {
    use super::{AllocatorTuning, MMAP_THRESHOLD_BYTES};
    use std::ffi::c_int;

    // From glibc's <malloc.h>.
    const M_TRIM_THRESHOLD: c_int = -1;
    const M_MMAP_THRESHOLD: c_int = -3;

    unsafe extern "C" {
        fn mallopt(param: c_int, value: c_int) -> c_int;
    }

    pub(super) fn retain_freed_memory() -> AllocatorTuning {
        // SAFETY: `mallopt` takes two integers, touches only malloc's own parameters (under
        // its lock) and is declared with glibc's signature; both parameters are documented
        // glibc options and the values are in their accepted ranges.
        let mmap = unsafe { mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) };
        // Trim only when more than 1 GiB is free at the heap top.
        // SAFETY: as above.
        let trim = unsafe { mallopt(M_TRIM_THRESHOLD, 1 << 30) };
        if mmap == 1 && trim == 1 {
            AllocatorTuning::Applied
        } else {
            AllocatorTuning::Rejected
        }
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
mod imp {
    use super::AllocatorTuning;

    pub(super) fn retain_freed_memory() -> AllocatorTuning {
        AllocatorTuning::Unsupported
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_accepts_the_settings() {
        let expected = if cfg!(all(target_os = "linux", target_env = "gnu")) {
            AllocatorTuning::Applied
        } else {
            AllocatorTuning::Unsupported
        };
        assert_eq!(retain_freed_memory(), expected);
        // A second call (another binary's start-up in the same process) is accepted too.
        assert_eq!(retain_freed_memory(), expected);
    }
}
