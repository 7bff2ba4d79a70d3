//! How gpu tests get a context: the software adapter is allowed, a missing adapter skips the
//! test with a printed reason, except under CI (`CI` set) where it is a failure.
//!
//! `SEQAVATAR_GPU_TESTS=0` skips gpu tests on purpose (a machine without any Vulkan driver).

use std::sync::{Arc, OnceLock};

use super::{AdapterChoice, Backend, GpuContext};

/// The shared gpu context for tests, or `None` (after printing why) when the test should be
/// skipped. Panics when `CI` is set and no adapter exists, so CI never passes vacuously.
pub fn gpu_test_context() -> Option<Arc<GpuContext>> {
    if std::env::var("SEQAVATAR_GPU_TESTS").is_ok_and(|value| value == "0") {
        eprintln!("skipped: SEQAVATAR_GPU_TESTS=0");
        return None;
    }
    static CONTEXT: OnceLock<Result<Arc<GpuContext>, String>> = OnceLock::new();
    let context = CONTEXT.get_or_init(|| {
        GpuContext::new(AdapterChoice::AllowSoftware)
            .map(Arc::new)
            .map_err(|error| error.to_string())
    });
    match context {
        Ok(context) => Some(context.clone()),
        Err(error) if std::env::var_os("CI").is_some() => {
            panic!(
                "CI is set but no Vulkan adapter was found ({error}); install mesa-vulkan-drivers or set SEQAVATAR_GPU_TESTS=0"
            )
        }
        Err(error) => {
            eprintln!("skipped: no Vulkan adapter ({error})");
            None
        }
    }
}

/// The gpu backend on the shared test context ([`gpu_test_context`]), or `None` under the
/// same rules.
pub fn gpu_test_backend() -> Option<Backend> {
    gpu_test_context().map(Backend::Gpu)
}

/// A context of its own, not shared with other tests, under the same rules as
/// [`gpu_test_context`].
fn own_context() -> Option<GpuContext> {
    gpu_test_context()?;
    match GpuContext::new(AdapterChoice::AllowSoftware) {
        Ok(context) => Some(context),
        Err(error) => panic!("a second gpu context could not be opened: {error}"),
    }
}

/// A separate context whose dispatches go 2D beyond `limit` workgroups per dimension, or
/// `None` under the same rules as [`gpu_test_context`].
pub fn gpu_test_context_with_dispatch_limit(limit: u32) -> Option<Arc<GpuContext>> {
    own_context().map(|context| Arc::new(context.with_dispatch_limit(limit)))
}

/// A context of its own (not shared with other tests), or `None` under the same rules as
/// [`gpu_test_context`]: for tests that count the context's host-device traffic
/// ([`GpuContext::transfers`]) while other tests run in parallel.
pub fn gpu_test_context_alone() -> Option<Arc<GpuContext>> {
    own_context().map(Arc::new)
}

/// The gpu backend on a context of its own ([`gpu_test_context_alone`]).
pub fn gpu_test_backend_alone() -> Option<Backend> {
    gpu_test_context_alone().map(Backend::Gpu)
}
