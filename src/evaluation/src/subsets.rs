//! Scores of subsets of the test images, from what the ingest entry says about each frame:
//! the history frames (the garment's history-only displacement exceeds the threshold,
//! `history_frame`, history scene only) and the two protocols (held-out cameras on training
//! frames, the paper's; held-out frames, `frame_split` bit 2, never trained on).

use serde::{Deserialize, Serialize};

use seqavatar_engine::EntryReader;

use crate::scores::{ImageScore, MeanScores, mean_scores};

/// Bit of the ingest `frame_split` marking a held-out frame.
const HELD_OUT_FRAME: u8 = 4;

/// What the ingest entry says about one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameFlags {
    /// A history frame (`history_frame` = 1).
    pub history: bool,
    /// A held-out frame (`frame_split` bit 2): no training image uses it.
    pub held_out: bool,
}

/// Reads the per-frame flags of an ingest entry (all false where the entry records none).
pub fn frame_flags(ingest: &EntryReader) -> anyhow::Result<Vec<FrameFlags>> {
    // Both readers check their arrays against the frame axis.
    let split = seqavatar_schema::ingest::read_frame_split(ingest)?;
    let history = seqavatar_schema::ingest::read_garment_history(ingest)?;
    Ok(split
        .iter()
        .enumerate()
        .map(|(frame, &bits)| FrameFlags {
            history: history.as_ref().is_some_and(|h| h.frames[frame]),
            held_out: bits & HELD_OUT_FRAME != 0,
        })
        .collect())
}

/// Means over subsets of the scored images; a subset without images is `None`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SubsetScores {
    /// Images of history frames.
    pub history: Option<MeanScores>,
    /// Images of the other frames.
    pub not_history: Option<MeanScores>,
    /// The paper's protocol: held-out cameras on training frames.
    pub held_out_cameras: Option<MeanScores>,
    /// The temporal hold-out: frames never trained on (every view).
    pub held_out_frames: Option<MeanScores>,
    /// Held-out frames that are history frames.
    pub held_out_history_frames: Option<MeanScores>,
}

impl SubsetScores {
    /// Each subset with the name reports and logs give it.
    pub fn named(&self) -> [(&'static str, &Option<MeanScores>); 5] {
        [
            ("history frames", &self.history),
            ("other frames", &self.not_history),
            ("held-out cameras", &self.held_out_cameras),
            ("held-out frames", &self.held_out_frames),
            ("held-out history frames", &self.held_out_history_frames),
        ]
    }
}

/// Splits `scores` (one per scored image, whose frame is `frames[i]`) into the subsets.
pub fn subset_scores(
    flags: &[FrameFlags],
    frames: &[usize],
    scores: &[ImageScore],
) -> anyhow::Result<SubsetScores> {
    anyhow::ensure!(
        frames.len() == scores.len(),
        "{} frames for {} scores",
        frames.len(),
        scores.len()
    );
    let flag = |frame: usize| -> anyhow::Result<FrameFlags> {
        flags.get(frame).copied().ok_or_else(|| {
            anyhow::anyhow!(
                "frame {frame} is beyond the {} frames of the entry",
                flags.len()
            )
        })
    };
    let pick = |keep: &dyn Fn(FrameFlags) -> bool| -> anyhow::Result<Option<MeanScores>> {
        let mut chosen = Vec::new();
        for (&frame, score) in frames.iter().zip(scores) {
            if keep(flag(frame)?) {
                chosen.push(*score);
            }
        }
        Ok((!chosen.is_empty()).then(|| mean_scores(&chosen)))
    };
    Ok(SubsetScores {
        history: pick(&|f| f.history)?,
        not_history: pick(&|f| !f.history)?,
        held_out_cameras: pick(&|f| !f.held_out)?,
        held_out_frames: pick(&|f| f.held_out)?,
        held_out_history_frames: pick(&|f| f.held_out && f.history)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subsets_average_the_images_of_their_frames() {
        let flags = [
            FrameFlags::default(),
            FrameFlags {
                history: true,
                held_out: false,
            },
            FrameFlags {
                history: true,
                held_out: true,
            },
            FrameFlags {
                history: false,
                held_out: true,
            },
        ];
        let score = |psnr: f64| ImageScore {
            psnr,
            ssim: psnr / 100.0,
            lpips_vgg: None,
            lpips_alex: None,
            garment: None,
        };
        let frames = [0, 1, 2, 3, 1];
        let scores = [
            score(20.0),
            score(30.0),
            score(40.0),
            score(50.0),
            score(34.0),
        ];
        let subsets = subset_scores(&flags, &frames, &scores).unwrap();
        let history = subsets.history.unwrap();
        assert_eq!(history.images, 3);
        assert!((history.psnr - (30.0 + 40.0 + 34.0) / 3.0).abs() < 1e-12);
        assert!((history.ssim - (0.30 + 0.40 + 0.34) / 3.0).abs() < 1e-12);
        assert_eq!(subsets.not_history.unwrap().psnr, 35.0);
        assert_eq!(subsets.held_out_frames.unwrap().psnr, 45.0);
        assert_eq!(subsets.held_out_cameras.unwrap().psnr, 28.0);
        assert_eq!(subsets.held_out_history_frames.unwrap().psnr, 40.0);
        // No history frame: the subset is absent, not zero.
        let none = subset_scores(&flags[..1], &[0], &[score(25.0)]).unwrap();
        assert!(none.history.is_none() && none.held_out_frames.is_none());
        // A frame the entry does not have is an error.
        assert!(subset_scores(&flags, &[9], &[score(1.0)]).is_err());
    }
}
