//! The train entry: the trained avatar (its arrays and attributes are read and written here,
//! [`AvatarGaussians`], [`AvatarAttributes`], for `seqavatar_avatar`'s `TrainedAvatar`, which
//! owns the model they describe), and the run's record.
//!
//! The avatar:
//! - `gaussian_xyz` f64 `(gaussian, xyz)`: canonical (big-pose) centres, metres.
//! - `gaussian_sh` f64 `(gaussian, coeff, rgb)`: 16 SH coefficients per channel (degree 3
//!   storage; the attribute `sh_degree` says how many are active).
//! - `gaussian_opacity` f64 `(gaussian)`: opacity logits (activated with a sigmoid).
//! - `gaussian_log_scale` f64 `(gaussian, xyz)`; `gaussian_rotation` f64 `(gaussian, wxyz)`.
//! - The body model arrays of the ingest schema (`body_model_*`), so that the entry renders
//!   on its own.
//! - `network.<name>` f64: network parameters by their stable names (when the motion context
//!   or the refiners use networks), the f32 values the networks train and render with.
//!
//! Attributes: `avatar` (the `AvatarConfig`), `sh_degree`, `scales` (raw temporal
//! scales fed to the networks, largest first), `sequence_length`, `background`,
//! `body_model_kind`, `extent`, `motion_joints` (with networks). The train stage adds its
//! own `config` (the resolved train config, which nothing here reads).
//!
//! The run: the attribute `config` (the resolved train config), and
//! - `loss_<name>` f64 `(iteration)` for `total`, `l1`, `mask_mse`, `dssim`, `lpips`
//!   (unweighted, 0 when the LPIPS loss is off), `aiap`, `psnr` (train PSNR inside the bound
//!   box) and `gaussians` (count after the iteration);
//! - `camera_K`, `camera_R`, `camera_t`, `camera_image_size`: the ingest entry's cameras
//!   (ingest resolution; training rescales them by `resolution_scale`);
//! - `test_psnr` f64 `(image)`: held-out PSNR per test image (docs/method.md protocol), with
//!   `test_image` u32 `(image)` the ingest image index;
//! - attributes `wall_seconds`, `iterations_per_second` (of the last session when resumed),
//!   `resumed_from`, `final_train_psnr` (mean over the last tenth of the iterations),
//!   `test_psnr_mean`, `backend`, `gaussians`;
//! - attributes `train_image_psnr_mean` (the held-out protocol's PSNR on up to
//!   64 training images spread over the training split, next to
//!   `test_psnr_mean`: the gap is memorisation), `train_image_psnr_images`, `input_rms`
//!   (`InputRms`: RMS of each non-rigid input block over the training
//!   frames) and `first_layer_norms` (a list of `BlockNorm`: first-layer
//!   weight norms per input block).
//!
//! [`PlannedTrain`]: what the entry will hold, as far as the stage's config determines it when
//! the pipeline loads.

use anyhow::Context as _;
use seqavatar_engine::{EntryReader, EntryWriter};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Coefficients stored per colour channel (degree 3).
pub const SH_STORED: usize = 16;

/// The per-Gaussian parameters of an avatar (flat, row-major): the `gaussian_*` arrays.
#[derive(Clone, Debug, PartialEq)]
pub struct AvatarGaussians {
    pub xyz: Vec<f64>,
    /// `N x 16 x 3`.
    pub sh: Vec<f64>,
    pub opacity_logit: Vec<f64>,
    pub log_scale: Vec<f64>,
    pub rotation: Vec<f64>,
}

/// The `gaussian_*` arrays in [`AvatarGaussians`]' field order: name, dimension names and the
/// extents after the `gaussian` axis.
const GAUSSIAN_ARRAYS: [(&str, &[&str], &[u64]); 5] = [
    ("gaussian_xyz", &["gaussian", "xyz"], &[3]),
    (
        "gaussian_sh",
        &["gaussian", "coeff", "rgb"],
        &[SH_STORED as u64, 3],
    ),
    ("gaussian_opacity", &["gaussian"], &[]),
    ("gaussian_log_scale", &["gaussian", "xyz"], &[3]),
    ("gaussian_rotation", &["gaussian", "wxyz"], &[4]),
];

impl AvatarGaussians {
    pub fn len(&self) -> usize {
        self.opacity_logit.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logit.is_empty()
    }

    /// Writes the `gaussian_*` arrays, one chunk each.
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        let n = self.len() as u64;
        let fields = [
            &self.xyz,
            &self.sh,
            &self.opacity_logit,
            &self.log_scale,
            &self.rotation,
        ];
        for ((name, dims, row), values) in GAUSSIAN_ARRAYS.iter().zip(fields) {
            let shape: Vec<u64> = [n].iter().chain(*row).copied().collect();
            let chunk: Vec<u64> = [n.max(1)].iter().chain(*row).copied().collect();
            out.write_array(name, dims, &shape, &chunk, values)?;
        }
        Ok(())
    }

    /// Reads the `gaussian_*` arrays: one count of Gaussians, the shapes above, finite
    /// values; errors name the entry and the array.
    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        // The count of Gaussians; `gaussian_xyz`'s shape is checked with the others.
        let n = entry.shape("gaussian_xyz")?.first().copied().unwrap_or(0);
        let [xyz, sh, opacity_logit, log_scale, rotation] =
            GAUSSIAN_ARRAYS.map(|(name, _, row)| -> anyhow::Result<Vec<f64>> {
                let array = entry.read::<f64>(name)?;
                let expected: Vec<usize> = [n].iter().chain(row).map(|&d| d as usize).collect();
                anyhow::ensure!(
                    array.shape == expected,
                    "entry {location}: array `{name}` has shape {:?}, expected {expected:?}",
                    array.shape
                );
                if let Some(bad) = array.data.iter().position(|v| !v.is_finite()) {
                    anyhow::bail!(
                        "entry {location}: array `{name}` has a non-finite value at {bad}"
                    );
                }
                Ok(array.data)
            });
        Ok(Self {
            xyz: xyz?,
            sh: sh?,
            opacity_logit: opacity_logit?,
            log_scale: log_scale?,
            rotation: rotation?,
        })
    }
}

/// The array of the network parameter `name` (`network.<name>`).
fn network_array(name: &str) -> String {
    format!("network.{name}")
}

/// Writes the network parameter `name`, `(output)` or `(input, output)`, one chunk.
pub fn write_network_parameter(
    out: &EntryWriter,
    name: &str,
    shape: &[usize],
    values: &[f64],
) -> anyhow::Result<()> {
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let dims: &[&str] = if shape.len() == 2 {
        &["input", "output"]
    } else {
        &["output"]
    };
    let chunk: Vec<u64> = shape.iter().map(|&d| d.max(1)).collect();
    out.write_array(&network_array(name), dims, &shape, &chunk, values)
}

/// The values of the network parameter `name`; `None` where the entry has no readable such
/// array (the network loader names the missing parameter).
pub fn read_network_parameter(entry: &EntryReader, name: &str) -> Option<Vec<f64>> {
    entry.read::<f64>(&network_array(name)).ok().map(|a| a.data)
}

/// The avatar's attributes of a train entry; `C` is the avatar's config (`seqavatar_avatar`'s
/// `AvatarConfig`, attribute `avatar`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AvatarAttributes<C> {
    pub avatar: C,
    /// Active SH degree, 0..=3.
    pub sh_degree: u32,
    /// Raw temporal scales fed to the networks, largest first.
    pub scales: Vec<u32>,
    pub sequence_length: usize,
    pub background: [f64; 3],
    pub body_model_kind: String,
    pub extent: f64,
    /// With networks only: the joints of the skeleton-motion input.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_joints: Option<usize>,
}

impl<C: Serialize> AvatarAttributes<C> {
    /// Sets each field as an attribute.
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        let serde_json::Value::Object(attributes) = serde_json::to_value(self)? else {
            anyhow::bail!("the avatar's attributes are not a mapping");
        };
        attributes
            .into_iter()
            .try_for_each(|(key, value)| out.set_attribute(&key, value))
    }
}

impl<C: DeserializeOwned> AvatarAttributes<C> {
    /// Reads the attributes; errors name the entry and the attribute.
    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let attributes = serde_json::Value::Object(entry.attributes().clone());
        let read: Self = serde_json::from_value(attributes)
            .with_context(|| format!("entry {location}: the avatar's attributes"))?;
        anyhow::ensure!(
            read.sh_degree <= 3,
            "entry {location}: attribute `sh_degree` is not 0..=3"
        );
        Ok(read)
    }
}

/// The plan of a train entry (the stage's `planned` hook).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlannedTrain {
    /// The avatar's motion context, as named in the train config (`motion_context`).
    pub motion_context: String,
    /// Whether rendering the avatar reads the motion entry (skeleton-motion context).
    pub renders_from_motion_entry: bool,
}

impl PlannedTrain {
    /// The plan of a train input as a downstream stage's load-time check sees it.
    pub fn of(input: &seqavatar_engine::StageInput<'_>) -> Result<Self, String> {
        crate::ingest::planned_of(input)
    }
}
