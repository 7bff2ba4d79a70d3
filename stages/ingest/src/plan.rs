//! The ingest plan: which views, frames and images a split selects, and the frame axis
//! (`past_frames` steps before the first used frame, clamped at the sequence start).

use anyhow::bail;

use seqavatar_datasets::Split;

/// What the stage will ingest: resolved from a reader's default split and the overrides.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IngestPlan {
    /// Dataset camera indices written as the `view` axis, sorted.
    pub views: Vec<usize>,
    /// Dataset frame-list indices written as the `frame` axis: an arithmetic sequence with
    /// step `frame_interval` that reaches `past_frames` steps before the first used frame.
    pub frames: Vec<usize>,
    pub frame_interval: usize,
    /// Per frame of `frames`: bit 0 = a training image uses it, bit 1 = a test image does,
    /// bit 2 = a held-out frame (never trained on; every view has a test image there).
    pub frame_split: Vec<u8>,
    /// Images to write: (position in `views`, position in `frames`, split 0 train / 1 test):
    /// training images, then test images, each by view then frame, then the held-out
    /// frames' images (test) by view then frame.
    pub images: Vec<(usize, usize, u8)>,
}

impl IngestPlan {
    /// Resolves the split against a dataset with `num_cameras` cameras and `num_frames`
    /// frames. Errors name the config field at fault.
    pub fn new(
        split: &Split,
        num_cameras: usize,
        num_frames: usize,
        past_frames: usize,
    ) -> anyhow::Result<Self> {
        let SplitFrames {
            train: train_frames,
            test: test_frames,
            held_out,
            first,
            last,
        } = SplitFrames::resolve(split, num_cameras, num_frames)?;
        let interval = split.frame_interval;
        let start = first - (first / interval).min(past_frames) * interval;
        let frames: Vec<usize> = (start..=last).step_by(interval).collect();
        let position = |f: usize| (f - start) / interval;
        let mut frame_split = vec![0u8; frames.len()];
        for (list, bits) in [(&train_frames, 1u8), (&test_frames, 2), (&held_out, 2 | 4)] {
            for &f in list {
                frame_split[position(f)] |= bits;
            }
        }
        let mut views: Vec<usize> = split
            .train_views
            .iter()
            .chain(&split.test_views)
            .copied()
            .collect();
        views.sort_unstable();
        views.dedup();
        let view_position = |v: usize| views.binary_search(&v).expect("view comes from the split");
        let mut images = Vec::new();
        for (view_list, frame_list, image_split) in [
            (&split.train_views, &train_frames, 0u8),
            (&split.test_views, &test_frames, 1),
            (&views, &held_out, 1),
        ] {
            for &v in view_list {
                for &f in frame_list {
                    images.push((view_position(v), position(f), image_split));
                }
            }
        }
        // The same (view, frame) in both splits is stored once, as training data.
        let mut seen = std::collections::HashSet::new();
        images.retain(|&(v, f, _)| seen.insert((v, f)));
        Ok(Self {
            views,
            frames,
            frame_interval: interval,
            frame_split,
            images,
        })
    }
}

/// How many images a split yields, by split.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageCounts {
    pub train: usize,
    pub test: usize,
}

impl ImageCounts {
    /// The images [`IngestPlan::new`] would list for the same arguments, counted without
    /// listing them (time and memory linear in the frames, whatever the cameras): the
    /// pipeline's load-time checks use it on configs of up to 10^8 images. Errors as
    /// [`IngestPlan::new`].
    pub fn of(split: &Split, num_cameras: usize, num_frames: usize) -> anyhow::Result<Self> {
        let frames = SplitFrames::resolve(split, num_cameras, num_frames)?;
        let set = |list: &[usize]| {
            let mut member = vec![false; num_frames];
            for &f in list {
                member[f] = true;
            }
            member
        };
        let (trained, tested, held) =
            (set(&frames.train), set(&frames.test), set(&frames.held_out));
        // A view's test images: its test frames (if a test view) and the held-out frames,
        // less its training frames (if a training view; stored once, as training images).
        let test_only = |is_train: bool, is_test: bool| {
            (0..num_frames)
                .filter(|&f| (is_test && tested[f]) || held[f])
                .filter(|&f| !(is_train && trained[f]))
                .count()
        };
        let train_views: std::collections::BTreeSet<usize> =
            split.train_views.iter().copied().collect();
        let test_views: std::collections::BTreeSet<usize> =
            split.test_views.iter().copied().collect();
        let both = train_views.intersection(&test_views).count();
        let train_only = train_views.len() - both;
        let test_view_only = test_views.len() - both;
        let train = train_views.len() * frames.train.len();
        let test = both * test_only(true, true)
            + train_only * test_only(true, false)
            + test_view_only * test_only(false, true);
        Ok(Self { train, test })
    }
}

/// The frames of a split, checked against the dataset: what [`IngestPlan::new`] and
/// [`ImageCounts::of`] share.
struct SplitFrames {
    /// Training frames (without the held-out ones); empty without training views.
    train: Vec<usize>,
    /// Test frames of the test views; empty without test views.
    test: Vec<usize>,
    held_out: Vec<usize>,
    /// The first and last frame used.
    first: usize,
    last: usize,
}

impl SplitFrames {
    /// Errors name the config field at fault.
    fn resolve(split: &Split, num_cameras: usize, num_frames: usize) -> anyhow::Result<Self> {
        let interval = split.frame_interval;
        if interval == 0 {
            bail!("split.frame_interval must be at least 1");
        }
        for (field, views) in [
            ("split.train_views", &split.train_views),
            ("split.test_views", &split.test_views),
        ] {
            if let Some(bad) = views.iter().find(|&&v| v >= num_cameras) {
                bail!(
                    "{field} names view {bad} but the dataset has {num_cameras} cameras (0..{num_cameras})"
                );
            }
        }
        if split.train_views.is_empty() && split.test_views.is_empty() {
            bail!("split.train_views and split.test_views are both empty");
        }
        let held_out = match &split.held_out_frames {
            Some(range) => range.indices(num_frames, "split.held_out_frames")?,
            None => Vec::new(),
        };
        let train_frames: Vec<usize> = if split.train_views.is_empty() {
            Vec::new()
        } else {
            let all = split
                .train_frames
                .indices(num_frames, "split.train_frames")?;
            let kept: Vec<usize> = all.into_iter().filter(|f| !held_out.contains(f)).collect();
            if kept.is_empty() {
                bail!("split.held_out_frames leaves no frame of split.train_frames to train on");
            }
            kept
        };
        let test_frames = if split.test_views.is_empty() {
            Vec::new()
        } else {
            split.test_frames.indices(num_frames, "split.test_frames")?
        };
        let used: Vec<usize> = train_frames
            .iter()
            .chain(&test_frames)
            .chain(&held_out)
            .copied()
            .collect();
        let first = *used.iter().min().expect("at least one split is non-empty");
        let last = *used.iter().max().expect("at least one split is non-empty");
        if let Some(bad) = used
            .iter()
            .find(|&&f| !(f - first).is_multiple_of(interval))
        {
            bail!(
                "frame {bad} is not on the frame axis {first} + k * {interval}: the split's frame steps must be multiples of split.frame_interval"
            );
        }
        Ok(Self {
            train: train_frames,
            test: test_frames,
            held_out,
            first,
            last,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_datasets::FrameRange;

    /// Every frame.
    fn all() -> FrameRange {
        FrameRange {
            start: 0,
            end: None,
            step: 1,
        }
    }

    fn split(
        train: &[usize],
        test: &[usize],
        train_frames: FrameRange,
        test_frames: FrameRange,
        interval: usize,
    ) -> Split {
        Split {
            train_views: train.to_vec(),
            test_views: test.to_vec(),
            train_frames,
            test_frames,
            frame_interval: interval,
            held_out_frames: None,
        }
    }

    #[test]
    fn zju_style_split_ingests_only_used_images_and_past_frames() {
        // Train view 0 on frames 10..20; test views 1, 2 every 5th frame from 10.
        let s = split(
            &[0],
            &[2, 1],
            FrameRange {
                start: 10,
                end: Some(20),
                step: 1,
            },
            FrameRange {
                start: 10,
                end: Some(20),
                step: 5,
            },
            1,
        );
        let plan = IngestPlan::new(&s, 4, 100, 3).unwrap();
        assert_eq!(plan.views, vec![0, 1, 2]);
        assert_eq!(plan.frames, (7..20).collect::<Vec<_>>());
        assert_eq!(plan.frame_split[..3], [0, 0, 0]);
        assert_eq!(plan.frame_split[3], 3);
        assert_eq!(plan.frame_split[4], 1);
        assert_eq!(plan.images.len(), 10 + 2 * 2);
        assert!(plan.images.contains(&(2, 8, 1)));
        // Past frames clamp at the start of the sequence.
        let plan = IngestPlan::new(&s, 4, 100, 50).unwrap();
        assert_eq!(plan.frames[0], 0);
    }

    #[test]
    fn interval_and_errors() {
        let s = split(
            &[0],
            &[],
            FrameRange {
                start: 4,
                end: None,
                step: 3,
            },
            all(),
            3,
        );
        let plan = IngestPlan::new(&s, 1, 12, 1).unwrap();
        assert_eq!(plan.frames, vec![1, 4, 7, 10]);
        let bad = split(
            &[0],
            &[],
            FrameRange {
                start: 4,
                end: None,
                step: 2,
            },
            all(),
            3,
        );
        let err = IngestPlan::new(&bad, 1, 12, 1).unwrap_err().to_string();
        assert!(err.contains("frame_interval"), "{err}");
        let bad = split(&[5], &[], all(), all(), 1);
        let err = IngestPlan::new(&bad, 2, 12, 0).unwrap_err().to_string();
        assert!(err.contains("split.train_views"), "{err}");
        let bad = split(
            &[0],
            &[],
            FrameRange {
                start: 0,
                end: Some(40),
                step: 1,
            },
            all(),
            1,
        );
        let err = IngestPlan::new(&bad, 2, 12, 0).unwrap_err().to_string();
        assert!(err.contains("split.train_frames.end"), "{err}");
    }

    #[test]
    fn held_out_frames_are_never_trained_on_and_tested_from_every_view() {
        let mut s = split(
            &[0, 2],
            &[1],
            all(),
            FrameRange {
                start: 0,
                end: None,
                step: 2,
            },
            1,
        );
        s.held_out_frames = Some(FrameRange {
            start: 3,
            end: None,
            step: 4,
        });
        let plan = IngestPlan::new(&s, 3, 12, 0).unwrap();
        let held = [3, 7, 11];
        for &(view, frame, split) in &plan.images {
            if held.contains(&frame) {
                assert_eq!(split, 1, "held-out frame {frame} trained on in view {view}");
            }
        }
        for &f in &held {
            assert_eq!(plan.frame_split[f], 2 | 4);
            // Every view (training views too) has a test image of every held-out frame.
            for view in 0..3 {
                assert!(plan.images.contains(&(view, f, 1)), "view {view} frame {f}");
            }
        }
        // Training: 2 views x 9 frames; paper test: view 1 on 6 even frames; temporal: the
        // other two views (view 1's odd held-out frames are new too) -> 3 x 3 held-out.
        assert_eq!(plan.images.iter().filter(|i| i.2 == 0).count(), 18);
        assert_eq!(plan.images.len(), 18 + 6 + 9);
        assert_eq!(plan.frame_split[2], 3);
        // Holding out every training frame is an error naming the field.
        s.held_out_frames = Some(all());
        let err = IngestPlan::new(&s, 3, 12, 0).unwrap_err().to_string();
        assert!(err.contains("split.held_out_frames"), "{err}");
    }

    /// [`ImageCounts::of`] counts exactly the images [`IngestPlan::new`] lists, by split, on
    /// splits with overlapping, duplicated and empty views, frame steps, intervals and
    /// hold-outs; and it counts the largest synthetic scene the ranges allow (1024 cameras x
    /// 100000 frames) at once, where listing would take gigabytes.
    #[test]
    fn image_counts_match_the_listed_plan() {
        let range = |start: usize, end: Option<usize>, step: usize| FrameRange { start, end, step };
        let views: [(&[usize], &[usize]); 6] = [
            (&[0, 2, 3], &[1]),
            (&[0, 1], &[1]),
            (&[0, 1, 1], &[1, 2, 2]),
            (&[], &[0, 1]),
            (&[0], &[]),
            (&[0, 1, 2, 3], &[0, 1, 2, 3]),
        ];
        let mut checked = 0;
        for (train, test) in views {
            for (train_frames, test_frames) in [
                (all(), range(0, None, 2)),
                (range(2, Some(10), 2), range(0, None, 4)),
                (range(0, Some(6), 1), range(4, Some(12), 1)),
            ] {
                for held_out in [None, Some(range(3, None, 4)), Some(range(1, Some(2), 1))] {
                    for interval in [1, 2] {
                        let mut s = split(
                            train,
                            test,
                            train_frames.clone(),
                            test_frames.clone(),
                            interval,
                        );
                        s.held_out_frames = held_out.clone();
                        let listed = IngestPlan::new(&s, 4, 12, 2);
                        let counted = ImageCounts::of(&s, 4, 12);
                        match (listed, counted) {
                            (Ok(plan), Ok(counts)) => {
                                let by =
                                    |split: u8| plan.images.iter().filter(|i| i.2 == split).count();
                                assert_eq!((counts.train, counts.test), (by(0), by(1)), "{s:?}");
                                checked += 1;
                            }
                            (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string()),
                            (a, b) => panic!("{s:?}: listed {a:?}, counted {b:?}"),
                        }
                    }
                }
            }
        }
        assert!(checked > 50, "{checked}");
        let started = std::time::Instant::now();
        let s = split(
            &(0..1024).filter(|v| v % 4 != 1).collect::<Vec<_>>(),
            &(1..1024).step_by(4).collect::<Vec<_>>(),
            all(),
            range(0, None, 2),
            1,
        );
        let counts = ImageCounts::of(&s, 1024, 100_000).unwrap();
        assert_eq!(
            counts,
            ImageCounts {
                train: 768 * 100_000,
                test: 256 * 50_000
            }
        );
        assert!(started.elapsed() < std::time::Duration::from_secs(1));
    }
}
