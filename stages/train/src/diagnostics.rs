//! Does the non-rigid network use its inputs? Two diagnostics the train entry records (issue
//! 17, "diagnostics that show whether the context is used"):
//! - [`InputRms`]: the RMS of each input block the network is fed over the training frames
//!   (local pose; skeleton motion and vertex velocity per scale), so a block far below or
//!   above order 1 is visible;
//! - [`FirstLayerNorms`]: the Frobenius norm of the weights that read each input block in the
//!   block's first layer, and of the trunk's first-layer weights that read each encoder's
//!   features. A block whose weights stay at their initial size while others grow is not
//!   used. Norms are given with the number of input rows (`rms` = norm / sqrt(rows x out)),
//!   so blocks of different sizes compare.

use serde::{Deserialize, Serialize};

use seqavatar_avatar::avatar::{gather_frame_inputs, local_pose};
use seqavatar_avatar::config::AvatarConfig;
use seqavatar_avatar::model::{NetworkConfig, Networks};
use seqavatar_compute::nn::NnScalar;
use seqavatar_core::body::BodyParams;
use seqavatar_schema::motion::MotionTrack;

/// RMS of each input block of the non-rigid network over a set of frames. Blocks the motion
/// context does not feed are empty (`pose` is `None` without a non-rigid network).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InputRms {
    /// Raw scales of the per-scale blocks, largest first.
    pub scales: Vec<u32>,
    /// Local pose (axis-angle, radians, root excluded).
    pub pose: Option<f64>,
    /// Skeleton motion per scale, as fed (after the motion entry's input scaling).
    pub skeleton_motion: Vec<f64>,
    /// Template-vertex velocity per scale, as fed.
    pub vertex_velocity: Vec<f64>,
}

/// The RMS of each input block over `frames`, the inputs gathered exactly as training
/// gathers them (`scales` the raw scales fed, largest first).
pub fn input_rms(
    config: &AvatarConfig,
    scales: &[u32],
    motion: &MotionTrack,
    params: &[BodyParams],
    frames: &[usize],
) -> anyhow::Result<InputRms> {
    let context = config.motion_context;
    let mut rms = InputRms {
        scales: scales.to_vec(),
        ..InputRms::default()
    };
    if !context.has_non_rigid() || frames.is_empty() {
        return Ok(rms);
    }
    let slots = scales.len();
    let mut pose = (0.0, 0_usize);
    let mut skeleton = vec![(0.0, 0_usize); slots];
    let mut velocity = vec![(0.0, 0_usize); slots];
    for &frame in frames {
        let params = params.get(frame).ok_or_else(|| {
            anyhow::anyhow!(
                "frame {frame}: only {} frames of body parameters",
                params.len()
            )
        })?;
        for value in local_pose(params) {
            pose.0 += value * value;
            pose.1 += 1;
        }
        let inputs = gather_frame_inputs(config, scales, motion, params, frame)?;
        window_sums(
            &inputs.skeleton_motion,
            config.sequence_length,
            slots,
            &mut skeleton,
        )?;
        window_sums(
            &inputs.vertex_velocity,
            config.sequence_length,
            slots,
            &mut velocity,
        )?;
    }
    let root = |(sum, count): (f64, usize)| (sum / count.max(1) as f64).sqrt();
    rms.pose = Some(root(pose));
    if context.has_skeleton_motion() {
        rms.skeleton_motion = skeleton.into_iter().map(root).collect();
    }
    if context.has_velocity() {
        rms.vertex_velocity = velocity.into_iter().map(root).collect();
    }
    Ok(rms)
}

/// Adds the squares of an `(L, S, K, 3)` window to the per-scale sums (nothing for an empty
/// window).
fn window_sums(
    window: &[f32],
    length: usize,
    scales: usize,
    sums: &mut [(f64, usize)],
) -> anyhow::Result<()> {
    if window.is_empty() {
        return Ok(());
    }
    let slots = length * scales;
    anyhow::ensure!(
        slots > 0 && window.len().is_multiple_of(slots) && sums.len() == scales,
        "a motion window of {} values does not split into {length} frames x {scales} scales",
        window.len()
    );
    let slot = window.len() / slots;
    for (index, chunk) in window.chunks_exact(slot).enumerate() {
        let sum = &mut sums[index % scales];
        sum.0 += chunk.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>();
        sum.1 += chunk.len();
    }
    Ok(())
}

/// The size of the weights reading one input block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlockNorm {
    /// Which block, e.g. `skeleton_motion@6` or `trunk<-pose_features`.
    pub block: String,
    /// The layer whose weight rows read it.
    pub layer: String,
    /// Input rows of the layer that read the block.
    pub rows: usize,
    /// Frobenius norm of those rows.
    pub norm: f64,
    /// `norm / sqrt(rows x outputs)`: the RMS weight, comparable across blocks.
    pub rms: f64,
}

/// First-layer weight norms per input block of the non-rigid network (empty without one).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FirstLayerNorms {
    pub blocks: Vec<BlockNorm>,
}

/// Rows `rows` of an `in x out` row-major weight, as a [`BlockNorm`].
fn rows_norm<S: NnScalar>(
    block: String,
    layer: &str,
    weight: &[S],
    outputs: usize,
    rows: &[usize],
) -> BlockNorm {
    let mut sum = 0.0;
    for &row in rows {
        sum += weight[row * outputs..(row + 1) * outputs]
            .iter()
            .map(|v| v.to_f64().powi(2))
            .sum::<f64>();
    }
    let norm = sum.sqrt();
    BlockNorm {
        block,
        layer: layer.to_owned(),
        rows: rows.len(),
        norm,
        rms: norm / ((rows.len() * outputs).max(1) as f64).sqrt(),
    }
}

/// The norms of the non-rigid network's first-layer weights per input block: local pose
/// (`pose_encoder.0`), skeleton motion per scale (`seq_pose_encoder.frame`, rows
/// `|S| x joints x 3` scale-major), vertex velocity per scale (`seq_xyz_encoder.velocity`,
/// rows `tau x |S| x 3`), and the trunk's first layer per feature block (position encoding,
/// velocity features, pose features, skeleton-motion features). `scales` names the slots.
pub fn first_layer_norms<S: NnScalar>(
    networks: &Networks<S>,
    scales: &[u32],
) -> anyhow::Result<FirstLayerNorms> {
    let config: &NetworkConfig = networks.config();
    let mut blocks = Vec::new();
    if !networks.has_non_rigid() {
        return Ok(FirstLayerNorms { blocks });
    }
    let params = networks.parameters();
    let weight = |layer: &str| -> anyhow::Result<(&[S], usize, usize)> {
        let name = format!("non_rigid.{layer}.weight");
        let param = params
            .iter()
            .find(|param| param.name == name)
            .ok_or_else(|| anyhow::anyhow!("the non-rigid network has no parameter {name}"))?;
        Ok((param.values, param.shape[0], param.shape[1]))
    };
    let scale_name = |slot: usize| {
        scales
            .get(slot)
            .map_or_else(|| format!("slot{slot}"), |s| s.to_string())
    };
    let n_scales = config.n_scales;
    let (w, rows, out) = weight("pose_encoder.0")?;
    blocks.push(rows_norm(
        "pose".into(),
        "pose_encoder.0",
        w,
        out,
        &(0..rows).collect::<Vec<_>>(),
    ));
    if config.motion_context.has_skeleton_motion() {
        let (w, rows, out) = weight("seq_pose_encoder.frame")?;
        let per_scale = rows / n_scales.max(1);
        for slot in 0..n_scales {
            blocks.push(rows_norm(
                format!("skeleton_motion@{}", scale_name(slot)),
                "seq_pose_encoder.frame",
                w,
                out,
                &(slot * per_scale..(slot + 1) * per_scale).collect::<Vec<_>>(),
            ));
        }
    }
    if config.motion_context.has_velocity() {
        let (w, rows, out) = weight("seq_xyz_encoder.velocity")?;
        for slot in 0..n_scales {
            // Rows `tau x |S| x 3`: neighbour k, slot s, axis c is row (k |S| + s) 3 + c.
            let picked: Vec<usize> = (0..rows)
                .filter(|row| (row / 3) % n_scales == slot)
                .collect();
            blocks.push(rows_norm(
                format!("vertex_velocity@{}", scale_name(slot)),
                "seq_xyz_encoder.velocity",
                w,
                out,
                &picked,
            ));
        }
    }
    // The trunk reads the per-Gaussian rows (position encoding, velocity features), then the
    // per-frame rows (pose features, skeleton-motion features).
    let widths = &config.widths;
    let mut parts = vec![("position_encoding", widths.encoding_width())];
    if config.motion_context.has_velocity() {
        parts.push(("velocity_features", widths.seq_xyz));
    }
    parts.push(("pose_features", widths.pose_encoder));
    if config.motion_context.has_skeleton_motion() {
        parts.push(("skeleton_motion_features", widths.seq_pose));
    }
    let (w, rows, out) = weight("trunk.0")?;
    let total: usize = parts.iter().map(|(_, width)| width).sum();
    anyhow::ensure!(
        total == rows,
        "the non-rigid trunk's first layer reads {rows} inputs, the blocks {total}"
    );
    let mut start = 0;
    for (name, width) in parts {
        blocks.push(rows_norm(
            format!("trunk<-{name}"),
            "trunk.0",
            w,
            out,
            &(start..start + width).collect::<Vec<_>>(),
        ));
        start += width;
    }
    Ok(FirstLayerNorms { blocks })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{MotionContext, Preset, TrainConfig};
    use seqavatar_avatar::model::Widths;
    use seqavatar_core::glam::DVec3;
    use seqavatar_schema::motion::FrameAxis;

    /// A track whose every value at scale slot 0 is `a` and at slot 1 is `b` (any window then
    /// has RMS |a| and |b| per scale, whatever frames it gathers).
    fn track(frames: usize, joints: usize, vertices: usize, a: f32, b: f32) -> MotionTrack {
        let fill = |count: usize| -> Vec<f32> {
            (0..frames)
                .flat_map(|_| [vec![a; count * 3], vec![b; count * 3]].concat())
                .collect()
        };
        MotionTrack {
            num_frames: frames,
            num_joints: joints,
            garment_rows: 0,
            num_vertices: vertices,
            scales: vec![2, 1],
            scale_steps: vec![2, 1],
            skeleton_motion: fill(joints),
            vertex_velocity: fill(vertices),
            axis: FrameAxis::FROM_START,
        }
    }

    fn params(value: f64) -> BodyParams {
        BodyParams {
            pose: vec![DVec3::splat(9.0), DVec3::splat(value), DVec3::splat(-value)],
            betas: Vec::new(),
            expression: Vec::new(),
            world_rotation: DVec3::ZERO,
            world_translation: DVec3::ZERO,
        }
    }

    fn avatar(context: MotionContext) -> AvatarConfig {
        let mut config = TrainConfig::preset(Preset::Fast);
        config.motion_context = context;
        config.avatar()
    }

    #[test]
    fn input_rms_per_block_and_scale() {
        let motion = track(6, 2, 3, 2.0, -0.5);
        let poses: Vec<BodyParams> = (0..6).map(|_| params(0.3)).collect();
        let rms = input_rms(
            &avatar(MotionContext::Multiscale),
            &[2, 1],
            &motion,
            &poses,
            &[1, 4, 5],
        )
        .unwrap();
        // The root joint (9.0) is not part of the local pose.
        assert!((rms.pose.unwrap() - 0.3).abs() < 1e-12, "{rms:?}");
        assert_eq!(rms.scales, [2, 1]);
        for (got, want) in rms.skeleton_motion.iter().zip([2.0, 0.5]) {
            assert!((got - want).abs() < 1e-6, "{rms:?}");
        }
        for (got, want) in rms.vertex_velocity.iter().zip([2.0, 0.5]) {
            assert!((got - want).abs() < 1e-6, "{rms:?}");
        }
        // Blocks the context does not feed are absent; no network, nothing at all.
        let pose_only =
            input_rms(&avatar(MotionContext::Pose), &[2, 1], &motion, &poses, &[1]).unwrap();
        assert!(pose_only.skeleton_motion.is_empty() && pose_only.vertex_velocity.is_empty());
        assert!(pose_only.pose.is_some());
        let none = input_rms(&avatar(MotionContext::None), &[2, 1], &motion, &poses, &[1]).unwrap();
        assert_eq!(none.pose, None);
        // A frame without body parameters is an error, not a panic.
        assert!(input_rms(&avatar(MotionContext::Pose), &[2, 1], &motion, &poses, &[9]).is_err());
    }

    #[test]
    fn window_sums_split_frames_and_scales() {
        // L = 2, S = 2, K x 3 = 2 values per slot: slots alternate scale 0, scale 1.
        let window = [1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0];
        let mut sums = vec![(0.0, 0); 2];
        window_sums(&window, 2, 2, &mut sums).unwrap();
        assert_eq!(
            sums,
            [(1.0 + 1.0 + 9.0 + 9.0, 4), (4.0 + 4.0 + 16.0 + 16.0, 4)]
        );
        assert!(window_sums(&window[..7], 2, 2, &mut sums).is_err());
    }

    fn small_networks(context: MotionContext) -> Networks<f64> {
        let config = NetworkConfig {
            motion_context: context,
            trunk_width: 7,
            trunk_depth: 2,
            skinning_joints: 3,
            motion_joints: 4,
            tau: 2,
            sequence_length: 2,
            n_scales: if context.is_multiscale() { 2 } else { 1 },
            pose_refiner: false,
            lbs_offsets: false,
            widths: Widths {
                encoding_frequencies: 2,
                pose_encoder: 5,
                seq_pose_frame: 3,
                seq_pose: 4,
                seq_xyz_velocity: 5,
                seq_xyz_position: 3,
                seq_xyz_frame: 4,
                seq_xyz_hidden: 6,
                seq_xyz: 5,
                pose_refiner_hidden: 6,
                lbs_hidden: 5,
            },
        };
        Networks::new(&config, 3).unwrap()
    }

    #[test]
    fn first_layer_norms_read_the_rows_of_each_block() {
        let mut networks = small_networks(MotionContext::Multiscale);
        // Velocity weights: row (k |S| + s) 3 + c gets the value s + 1 (k over tau = 2
        // neighbours, c over 3 axes), every other weight 1.
        for param in networks.parameters_mut() {
            let out = param.shape.get(1).copied().unwrap_or(0);
            if param.name == "non_rigid.seq_xyz_encoder.velocity.weight" {
                for k in 0..2 {
                    for s in 0..2 {
                        for c in 0..3 {
                            let row = (k * 2 + s) * 3 + c;
                            param.values[row * out..(row + 1) * out].fill((s + 1) as f64);
                        }
                    }
                }
            } else {
                param.values.fill(1.0);
            }
        }
        let norms = first_layer_norms(&networks, &[6, 3]).unwrap();
        let get = |name: &str| {
            norms
                .blocks
                .iter()
                .find(|b| b.block == name)
                .unwrap_or_else(|| panic!("no block {name} in {norms:?}"))
                .clone()
        };
        // Pose: 3 (J - 1) = 6 rows x 5 outputs of ones.
        assert!((get("pose").norm - 30f64.sqrt()).abs() < 1e-12);
        // Skeleton motion: 4 joints x 3 = 12 rows per scale x 3 outputs.
        let skeleton = get("skeleton_motion@3");
        assert_eq!(skeleton.rows, 12);
        assert!((skeleton.norm - 36f64.sqrt()).abs() < 1e-12);
        assert!((skeleton.rms - 1.0).abs() < 1e-12);
        // Velocity: 6 rows per scale x 5 outputs, value 1 at scale 6 and 2 at scale 3.
        assert!((get("vertex_velocity@6").norm - 30f64.sqrt()).abs() < 1e-12);
        assert!((get("vertex_velocity@3").norm - (4.0 * 30f64).sqrt()).abs() < 1e-12);
        assert!((get("vertex_velocity@3").rms - 2.0).abs() < 1e-12);
        // Trunk: 15 encoding rows, 5 velocity-feature rows, 5 pose rows, 4 skeleton rows,
        // 7 outputs.
        assert_eq!(get("trunk<-position_encoding").rows, 15);
        assert!((get("trunk<-velocity_features").norm - 35f64.sqrt()).abs() < 1e-12);
        assert!((get("trunk<-skeleton_motion_features").norm - 28f64.sqrt()).abs() < 1e-12);
        // Without velocity the velocity blocks are absent; without a non-rigid network there
        // is nothing.
        let skeleton_only =
            first_layer_norms(&small_networks(MotionContext::Skeleton), &[6, 3]).unwrap();
        assert!(
            skeleton_only
                .blocks
                .iter()
                .all(|b| !b.block.contains("velocity"))
        );
        assert!(
            skeleton_only
                .blocks
                .iter()
                .any(|b| b.block == "trunk<-pose_features")
        );
        let none = first_layer_norms(&small_networks(MotionContext::None), &[6, 3]).unwrap();
        assert!(none.blocks.is_empty());
    }
}
