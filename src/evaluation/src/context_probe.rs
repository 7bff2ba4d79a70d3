//! Does the avatar use its motion context? Eval renders the test images again with the
//! per-frame motion-history inputs (skeleton motion and vertex velocities, the arrays gathered
//! from the motion entry and fed to the avatar) replaced, and reports the PSNR change per
//! subset:
//! - [`ContextProbe::Zeroed`]: the history inputs set to zero (the body pose is kept);
//! - [`ContextProbe::FromFrame`]: frame `i` gets frame `(i + offset) mod n`'s history inputs,
//!   its own pose (a plausible context from another moment of the same sequence).
//!
//! The replacement happens on the inputs, outside the avatar's networks
//! ([`seqavatar_avatar::sequence::History`]: gathered on the host on `cpu`, on the device on
//! the `gpu`), so the probes apply to every backend and network implementation alike. Avatars whose motion context has no
//! history inputs (`none`, `pose`) are not probed: their renders could not change.

use serde::{Deserialize, Serialize};

use crate::scores::{ImageScore, MeanScores};
use crate::subsets::SubsetScores;

/// How the motion-history inputs of a frame are replaced.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum ContextProbe {
    /// Skeleton motion and vertex velocities set to zero.
    Zeroed,
    /// Frame `i` gets the history inputs of frame `(i + offset) mod frames` (counted from the
    /// first frame whose motion window the sequence holds, see [`ContextProbe::donor`]).
    FromFrame { offset: usize },
}

impl ContextProbe {
    /// A short name for logs and tables.
    pub fn describe(self) -> String {
        match self {
            ContextProbe::Zeroed => "context zeroed".to_owned(),
            ContextProbe::FromFrame { offset } => {
                format!("context from frame i + {offset} (mod n)")
            }
        }
    }

    /// The frame whose history inputs frame `frame` gets, `None` for
    /// [`ContextProbe::Zeroed`]. Donors are drawn from `first..frames`, the frames whose
    /// motion windows the sequence holds (`first` is 0 when it starts its recording):
    /// `first + (frame - first + offset) mod (frames - first)`.
    pub fn donor(self, frame: usize, first: usize, frames: usize) -> Option<usize> {
        match self {
            ContextProbe::Zeroed => None,
            ContextProbe::FromFrame { offset } => {
                let first = first.min(frame);
                let span = frames.saturating_sub(first).max(1);
                Some(first + (frame - first + offset) % span)
            }
        }
    }
}

/// The scores of one probe and their change against the unprobed renders of the same images.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProbeResult {
    pub probe: ContextProbe,
    /// Means over all scored images with the probe.
    pub means: MeanScores,
    /// Subset means with the probe.
    pub subsets: SubsetScores,
    /// Probe PSNR minus the unprobed PSNR (dB, same images): all images and each subset
    /// (`None` where the subset is empty). Negative: the probe hurts, the context is used.
    pub psnr_change: PsnrChange,
}

/// PSNR changes per subset (dB).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PsnrChange {
    pub all: f64,
    pub history: Option<f64>,
    pub not_history: Option<f64>,
    pub held_out_cameras: Option<f64>,
    pub held_out_frames: Option<f64>,
    pub held_out_history_frames: Option<f64>,
    /// The same changes of the garment region's PSNR, where the images have one (absent in
    /// summaries written before eval version 11).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub garment: Option<Box<PsnrChange>>,
}

impl PsnrChange {
    /// The change of every subset from the probed and unprobed means, on the whole image and
    /// on the garment region.
    pub fn between(
        probed: &MeanScores,
        probed_subsets: &SubsetScores,
        base: &MeanScores,
        base_subsets: &SubsetScores,
    ) -> Self {
        let garment = |m: &MeanScores| m.garment.as_ref().and_then(|g| g.psnr);
        let mut change = Self::of(probed, probed_subsets, base, base_subsets, |m| Some(m.psnr))
            .unwrap_or_default();
        change.garment =
            Self::of(probed, probed_subsets, base, base_subsets, garment).map(Box::new);
        change
    }

    /// The changes of the figure `pick` reads; `None` where the means over all images lack it.
    fn of(
        probed: &MeanScores,
        probed_subsets: &SubsetScores,
        base: &MeanScores,
        base_subsets: &SubsetScores,
        pick: impl Fn(&MeanScores) -> Option<f64>,
    ) -> Option<Self> {
        let delta = |p: &Option<MeanScores>, b: &Option<MeanScores>| {
            Some(pick(p.as_ref()?)? - pick(b.as_ref()?)?)
        };
        Some(PsnrChange {
            all: pick(probed)? - pick(base)?,
            history: delta(&probed_subsets.history, &base_subsets.history),
            not_history: delta(&probed_subsets.not_history, &base_subsets.not_history),
            held_out_cameras: delta(
                &probed_subsets.held_out_cameras,
                &base_subsets.held_out_cameras,
            ),
            held_out_frames: delta(
                &probed_subsets.held_out_frames,
                &base_subsets.held_out_frames,
            ),
            held_out_history_frames: delta(
                &probed_subsets.held_out_history_frames,
                &base_subsets.held_out_history_frames,
            ),
            garment: None,
        })
    }
}

/// Builds a [`ProbeResult`] from the probe's per-image scores and the unprobed means.
pub fn probe_result(
    probe: ContextProbe,
    scores: &[ImageScore],
    subsets: SubsetScores,
    base: &MeanScores,
    base_subsets: &SubsetScores,
) -> ProbeResult {
    let means = crate::scores::mean_scores(scores);
    let psnr_change = PsnrChange::between(&means, &subsets, base, base_subsets);
    ProbeResult {
        probe,
        means,
        subsets,
        psnr_change,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::glam::DVec3;

    /// The garment region's changes come from the region's means, subset by subset, beside
    /// the whole image's; without a region in both runs there are none.
    #[test]
    fn psnr_changes_cover_the_garment_region() {
        use crate::region::RegionMeans;
        let means = |psnr: f64, garment: Option<f64>| MeanScores {
            images: 4,
            psnr,
            ssim: 0.9,
            lpips_vgg: None,
            lpips_alex: None,
            garment: garment.map(|g| RegionMeans {
                images: 4,
                empty_images: 0,
                psnr: Some(g),
                ssim: Some(0.5),
                lpips_vgg: None,
                lpips_alex: None,
            }),
        };
        let subsets = |history: MeanScores| SubsetScores {
            history: Some(history),
            ..SubsetScores::default()
        };
        let (base, probed) = (means(30.0, Some(16.0)), means(29.0, Some(14.5)));
        let change = PsnrChange::between(
            &probed,
            &subsets(means(28.0, Some(14.0))),
            &base,
            &subsets(means(29.5, Some(16.5))),
        );
        assert_eq!((change.all, change.history), (-1.0, Some(-1.5)));
        let garment = change.garment.expect("both runs have the region");
        assert_eq!((garment.all, garment.history), (-1.5, Some(-2.5)));
        assert_eq!((garment.not_history, garment.garment), (None, None));
        let without = PsnrChange::between(
            &means(29.0, None),
            &SubsetScores::default(),
            &base,
            &SubsetScores::default(),
        );
        assert_eq!((without.all, without.garment), (-1.0, None));
    }

    #[test]
    fn donors_are_drawn_from_the_frames_with_a_whole_window() {
        let probe = ContextProbe::FromFrame { offset: 5 };
        assert_eq!(probe.donor(0, 0, 8), Some(5));
        assert_eq!(probe.donor(6, 0, 8), Some(3));
        // Frames 0..4 cannot be drawn: donors stay in 4..8.
        assert_eq!(probe.donor(6, 4, 8), Some(7));
        assert_eq!(probe.donor(7, 4, 8), Some(4));
        assert_eq!(ContextProbe::Zeroed.donor(3, 0, 8), None);
    }

    /// An avatar with skeleton motion and velocity inputs (multiscale, non-trivial heads) on
    /// a track whose frames differ only in their motion values (every pose is the rest pose):
    /// zeroing must change the render and equal a frame whose track values are zero; the
    /// context of frame `i + k` must render exactly as frame `i + k` itself. On `cpu` (the
    /// inputs replaced on the host) and on the gpu (on the device).
    #[test]
    fn probes_change_what_the_avatar_renders() {
        use seqavatar_compute::backend::{Backend, DeviceChoice};
        probes_change_what_the_avatar_renders_on(Backend::select(DeviceChoice::Cpu).unwrap());
        if let Some(gpu) = seqavatar_compute::backend::test_support::gpu_test_backend() {
            probes_change_what_the_avatar_renders_on(gpu);
        }
    }

    fn probes_change_what_the_avatar_renders_on(backend: seqavatar_compute::backend::Backend) {
        use crate::avatar_render::AvatarRenderer;
        use crate::evaluate::ViewRenderer;
        use seqavatar_avatar::config::MotionContext;
        use seqavatar_avatar::test_support::{TestAvatar, small_config, uniform_track};
        use seqavatar_core::camera::{Camera, Intrinsics};

        let frames = 4;
        let avatar = TestAvatar {
            gaussians: 200,
            seed: 11,
            ..TestAvatar::new(small_config(MotionContext::Multiscale))
        }
        .build();
        let model = avatar.rig.model.clone();
        // Frame f's motion values are all f (frame 0: zero), at both scales.
        let track = uniform_track(&avatar, frames, |f| f as f32);
        let mut renderer = AvatarRenderer::new(
            avatar,
            vec![model.zero_params(); frames],
            Some(track),
            backend,
            "test".into(),
        )
        .unwrap();
        let camera = Camera::look_at(
            32,
            40,
            Intrinsics {
                fx: 40.0,
                fy: 40.0,
                cx: 16.0,
                cy: 20.0,
            },
            DVec3::new(0.0, 0.0, 2.5),
            DVec3::ZERO,
            DVec3::new(0.0, 1.0, 0.0),
        );
        // Frame 0's window clamps at frame 0 (all zero); frame 3's is not zero.
        let own = renderer.render(3, &camera).unwrap();
        let zero_frame = renderer.render(0, &camera).unwrap();
        let frame_one = renderer.render(1, &camera).unwrap();
        let differs = |a: &seqavatar_compute::image::ImageF32,
                       b: &seqavatar_compute::image::ImageF32| {
            a.data
                .iter()
                .zip(&b.data)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0_f32, f32::max)
        };
        assert!(
            differs(&own, &zero_frame) > 1e-3,
            "the context changes nothing"
        );
        assert!(renderer.set_context_probe(Some(ContextProbe::Zeroed)));
        let zeroed = renderer.render(3, &camera).unwrap();
        assert!(differs(&zeroed, &own) > 1e-3, "zeroing changed nothing");
        assert_eq!(differs(&zeroed, &zero_frame), 0.0);
        assert!(renderer.set_context_probe(Some(ContextProbe::FromFrame { offset: 2 })));
        // Frame 3 gets frame (3 + 2) mod 4 = 1's context.
        let shifted = renderer.render(3, &camera).unwrap();
        assert_eq!(differs(&shifted, &frame_one), 0.0);
        assert!(differs(&shifted, &own) > 1e-3);
        assert!(renderer.set_context_probe(None));
        assert_eq!(differs(&renderer.render(3, &camera).unwrap(), &own), 0.0);
    }

    #[test]
    fn psnr_change_is_probed_minus_unprobed_per_subset() {
        let mean = |psnr: f64| MeanScores {
            images: 2,
            psnr,
            ssim: 0.9,
            lpips_vgg: None,
            lpips_alex: None,
            garment: None,
        };
        let base = SubsetScores {
            history: Some(mean(30.0)),
            not_history: Some(mean(32.0)),
            ..SubsetScores::default()
        };
        let probed = SubsetScores {
            history: Some(mean(28.5)),
            not_history: Some(mean(32.0)),
            ..SubsetScores::default()
        };
        let change = PsnrChange::between(&mean(31.0), &probed, &mean(31.5), &base);
        assert_eq!(change.all, -0.5);
        assert_eq!(change.history, Some(-1.5));
        assert_eq!(change.not_history, Some(0.0));
        assert_eq!(change.held_out_frames, None);
    }
}
