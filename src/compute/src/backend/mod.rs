//! Device selection (`auto | cpu | gpu`) and the wgpu context shared by every gpu operation.
//!
//! `auto` picks a hardware GPU adapter when there is one and falls back to `cpu`; a software
//! adapter (Mesa lavapipe) is never chosen for real work, only when a caller asks for it
//! explicitly with [`AdapterChoice::AllowSoftware`] (the gpu tests do).

mod context;
mod kernel;
pub mod primitives;
pub mod shaders;
pub mod test_support;
mod timer;

pub use context::{
    AdapterChoice, GpuBuffer, GpuContext, KernelSource, PendingDownload, TensorCores, Transfers,
    split_workgroups,
};
pub use kernel::{Kernel, PreparedDispatch, Record, Workgroups};
pub use timer::PhaseTimer;

use std::fmt;
use std::str::FromStr;
use std::sync::Arc;

/// Why a backend or a gpu resource could not be provided.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    #[error("unknown device {given:?}: expected one of auto, cpu, gpu")]
    UnknownDevice { given: String },
    #[error("no suitable GPU adapter found ({wanted})")]
    NoAdapter { wanted: &'static str },
    #[error("could not open the GPU device on adapter {adapter:?}: {message}")]
    DeviceRequest { adapter: String, message: String },
    #[error("GPU buffer of {bytes} bytes for {what} exceeds the adapter limit of {limit} bytes")]
    BufferTooLarge {
        what: String,
        bytes: u64,
        limit: u64,
    },
    #[error("GPU work failed: {message}")]
    Gpu { message: String },
    #[error("shader {name} failed to compile: {message}")]
    Shader { name: String, message: String },
}

/// The `device:` setting of a configuration (the train and eval configs hold it directly,
/// spelled `auto`, `cpu` or `gpu`; any other name is rejected with the choices) and of the
/// `--device` option. [`Backend::select`] resolves it once.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceChoice {
    /// A hardware GPU when there is one, else `cpu`.
    #[default]
    Auto,
    /// Plain Rust on the CPU.
    Cpu,
    /// A hardware GPU; an error when there is none.
    Gpu,
}

impl FromStr for DeviceChoice {
    type Err = BackendError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text {
            "auto" => Ok(Self::Auto),
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            other => Err(BackendError::UnknownDevice {
                given: other.to_owned(),
            }),
        }
    }
}

impl fmt::Display for DeviceChoice {
    fn fmt(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
        formatter.write_str(match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
        })
    }
}

/// The backend an operation runs on. Cheap to clone: the gpu context is shared.
#[derive(Clone, Debug)]
pub enum Backend {
    Cpu,
    Gpu(Arc<GpuContext>),
}

impl Backend {
    /// Resolves a `device:` setting. `Auto` never fails: without a hardware adapter it is `Cpu`.
    pub fn select(choice: DeviceChoice) -> Result<Self, BackendError> {
        Self::select_adapter(choice, AdapterChoice::Hardware)
    }

    /// [`Backend::select`] with the gpu taken as `adapter` allows: benches pass
    /// [`AdapterChoice::AllowSoftware`] to time the software adapter (Mesa lavapipe).
    pub fn select_adapter(
        choice: DeviceChoice,
        adapter: AdapterChoice,
    ) -> Result<Self, BackendError> {
        match choice {
            DeviceChoice::Cpu => Ok(Self::Cpu),
            DeviceChoice::Gpu => Ok(Self::Gpu(Arc::new(GpuContext::new(adapter)?))),
            DeviceChoice::Auto => match GpuContext::new(adapter) {
                Ok(context) => Ok(Self::Gpu(Arc::new(context))),
                Err(_) => Ok(Self::Cpu),
            },
        }
    }

    /// One line for run summaries: which backend ran, and on which adapter.
    pub fn describe(&self) -> String {
        match self {
            Self::Cpu => format!("cpu ({} threads)", rayon::current_num_threads()),
            Self::Gpu(context) => format!("gpu ({})", context.describe()),
        }
    }

    /// Host-device traffic through this backend so far (none on `cpu`).
    pub fn transfers(&self) -> Transfers {
        match self {
            Self::Cpu => Transfers::default(),
            Self::Gpu(context) => context.transfers(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_choice_parses_and_rejects_unknown_names() {
        for (text, choice) in [
            ("auto", DeviceChoice::Auto),
            ("cpu", DeviceChoice::Cpu),
            ("gpu", DeviceChoice::Gpu),
        ] {
            assert_eq!(text.parse::<DeviceChoice>().unwrap(), choice);
            assert_eq!(choice.to_string(), text);
        }
        let error = "cuda".parse::<DeviceChoice>().unwrap_err();
        assert!(error.to_string().contains("\"cuda\""), "{error}");
    }

    /// Configs spell the choice as the former config enum did (`auto`, `cpu`, `gpu`: the
    /// same canonical JSON, so the same cache keys), and an unknown name is an error that
    /// names it and the choices.
    #[test]
    fn device_choice_serialises_as_configs_spell_it() {
        for (choice, text) in [
            (DeviceChoice::Auto, "auto"),
            (DeviceChoice::Cpu, "cpu"),
            (DeviceChoice::Gpu, "gpu"),
        ] {
            let json = serde_json::to_string(&choice).unwrap();
            assert_eq!(json, format!("\"{text}\""));
            assert_eq!(serde_json::from_str::<DeviceChoice>(&json).unwrap(), choice);
        }
        for bad in ["cuda", "GPU", ""] {
            let error = serde_json::from_value::<DeviceChoice>(serde_json::json!(bad))
                .unwrap_err()
                .to_string();
            for part in [&format!("`{bad}`"), "auto", "cpu", "gpu"] {
                assert!(error.contains(part), "{bad:?}: `{error}` lacks {part}");
            }
        }
    }

    #[test]
    fn auto_never_picks_a_software_adapter() {
        let backend = Backend::select(DeviceChoice::Auto).unwrap();
        if let Backend::Gpu(context) = &backend {
            assert_ne!(context.info().device_type, wgpu::DeviceType::Cpu);
        }
        assert!(!backend.describe().is_empty());
        assert_eq!(
            Backend::select(DeviceChoice::Cpu).unwrap().describe(),
            format!("cpu ({} threads)", rayon::current_num_threads())
        );
    }

    #[test]
    fn the_gpu_test_context_describes_its_adapter() {
        let Some(context) = test_support::gpu_test_context() else {
            return;
        };
        let text = Backend::Gpu(context.clone()).describe();
        assert!(text.contains(&context.info().name), "{text}");
    }
}
