//! The avatar's Gaussians as 3D Gaussian Splatting PLY clouds, for `pipeline export`: the
//! canonical (trained) Gaussians ([`canonical_cloud`]), one frame's posed Gaussians with each
//! world covariance as scales and a rotation ([`posed_cloud`], [`scale_rotation_of`]), and a
//! cloud back to what the splatting draws ([`cloud_to_world`]). The file format itself (the
//! writer and the strict reader of a plain cloud) is `seqavatar_formats::ply`,
//! re-exported here.

use seqavatar_compute::splat::covariance::covariance_from_scale_rotation;
use seqavatar_core::glam::{DMat3, DQuat, DVec3};
pub use seqavatar_formats::ply::{PlyError, SplatCloud, read_ply, write_ply};
use seqavatar_formats::ply::{check_degree, coefficient_count};

use crate::avatar::{AvatarGaussians, SH_STORED};
use crate::splatting::WorldGaussians;

/// The canonical (big-pose) Gaussians of an avatar, as stored: centres, log scales,
/// rotations, opacity logits, and the SH coefficients of the active degree `sh_degree`.
pub fn canonical_cloud(
    gaussians: &AvatarGaussians,
    sh_degree: u32,
) -> Result<SplatCloud, PlyError> {
    let n = gaussians.len();
    check_degree(sh_degree)?;
    check_lengths(gaussians)?;
    Ok(SplatCloud {
        xyz: narrow(&gaussians.xyz),
        sh: channel_major(&gaussians.sh, n, SH_STORED, sh_degree),
        sh_degree,
        opacity: narrow(&gaussians.opacity_logit),
        log_scale: narrow(&gaussians.log_scale),
        rotation: narrow(&gaussians.rotation),
    })
}

/// One frame's posed Gaussians: the world-space centres and covariances of `world` (what
/// the splatting draws), each covariance as scales and a rotation (its eigen
/// decomposition), with the opacity logits of `gaussians` (`world`'s opacities are
/// their sigmoids) and `world`'s SH coefficients.
pub fn posed_cloud(world: &WorldGaussians, opacity_logit: &[f64]) -> Result<SplatCloud, PlyError> {
    let n = world.opacities.len();
    check_degree(world.sh_degree)?;
    let k = coefficient_count(world.sh_degree);
    if world.means.len() != 3 * n
        || world.covariances.len() != 6 * n
        || world.sh.len() != 3 * k * n
        || opacity_logit.len() != n
    {
        return Err(PlyError::Input(format!(
            "posed Gaussians: {n} opacities need {} means, {} covariance entries, {} SH \
             coefficients and {n} logits; got {}, {}, {}, {}",
            3 * n,
            6 * n,
            3 * k * n,
            world.means.len(),
            world.covariances.len(),
            world.sh.len(),
            opacity_logit.len()
        )));
    }
    let mut log_scale = Vec::with_capacity(3 * n);
    let mut rotation = Vec::with_capacity(4 * n);
    for (i, c) in world.covariances.chunks_exact(6).enumerate() {
        let (scales, q) = scale_rotation_of(c).ok_or(PlyError::NotFinite {
            index: i,
            field: "covariance",
        })?;
        log_scale.extend(scales.map(|s| s.ln() as f32));
        rotation.extend(q.map(|v| v as f32));
    }
    Ok(SplatCloud {
        xyz: narrow(&world.means),
        sh: channel_major(&world.sh, n, k, world.sh_degree),
        sh_degree: world.sh_degree,
        opacity: narrow(opacity_logit),
        log_scale,
        rotation,
    })
}

/// The Gaussians as the splatting draws them: centres, covariances from scales and
/// rotations (`compute::splat::covariance`), sigmoid opacities, SH coefficient-major.
pub fn cloud_to_world(cloud: &SplatCloud) -> Result<WorldGaussians, PlyError> {
    let n = cloud.len();
    let k = coefficient_count(cloud.sh_degree);
    let scales: Vec<f64> = cloud
        .log_scale
        .iter()
        .map(|&s| f64::from(s).exp())
        .collect();
    let rotations: Vec<f64> = cloud.rotation.iter().map(|&q| f64::from(q)).collect();
    let covariances = covariance_from_scale_rotation(&scales, &rotations)
        .map_err(|e| PlyError::Input(format!("covariances: {e}")))?
        .covariances;
    let mut sh = Vec::with_capacity(3 * k * n);
    for i in 0..n {
        for coeff in 0..k {
            for c in 0..3 {
                sh.push(f64::from(cloud.sh[(i * 3 + c) * k + coeff]));
            }
        }
    }
    Ok(WorldGaussians {
        means: cloud.xyz.iter().map(|&v| f64::from(v)).collect(),
        covariances,
        opacities: cloud
            .opacity
            .iter()
            .map(|&l| 1.0 / (1.0 + (-f64::from(l)).exp()))
            .collect(),
        sh,
        sh_degree: cloud.sh_degree,
    })
}

fn check_lengths(g: &AvatarGaussians) -> Result<(), PlyError> {
    let n = g.len();
    if g.xyz.len() != 3 * n
        || g.sh.len() != 3 * SH_STORED * n
        || g.log_scale.len() != 3 * n
        || g.rotation.len() != 4 * n
    {
        return Err(PlyError::Input(format!(
            "avatar Gaussians: {n} opacities but {} centre, {} SH, {} scale and {} rotation values",
            g.xyz.len(),
            g.sh.len(),
            g.log_scale.len(),
            g.rotation.len()
        )));
    }
    Ok(())
}

fn narrow(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&v| v as f32).collect()
}

/// `N x stored x 3` (coefficient-major, rgb inner) to `N x 3 x K` for degree `degree`.
fn channel_major(sh: &[f64], n: usize, stored: usize, degree: u32) -> Vec<f32> {
    let k = coefficient_count(degree);
    let mut out = Vec::with_capacity(3 * k * n);
    for i in 0..n {
        for c in 0..3 {
            for coeff in 0..k {
                out.push(sh[(i * stored + coeff) * 3 + c] as f32);
            }
        }
    }
    out
}

/// Scales (standard deviations) and a unit `wxyz` rotation with `R diag(s^2) R^T = sigma`,
/// from the upper triangle `xx xy xz yy yz zz` of a symmetric covariance (cyclic Jacobi
/// rotations to machine precision; eigenvalues at or below zero become the smallest positive
/// f32 scale's square). `None` for a non-finite covariance.
pub fn scale_rotation_of(upper: &[f64]) -> Option<([f64; 3], [f64; 4])> {
    if upper.len() != 6 || !upper.iter().all(|v| v.is_finite()) {
        return None;
    }
    let mut a = [
        [upper[0], upper[1], upper[2]],
        [upper[1], upper[3], upper[4]],
        [upper[2], upper[4], upper[5]],
    ];
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..64 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let diag = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= f64::EPSILON * 1e-3 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            // The rotation that zeroes a[p][q] (Golub & Van Loan, symmetric Schur).
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let floor = f64::from(f32::MIN_POSITIVE);
    let scales = [0, 1, 2].map(|i| a[i][i].max(floor * floor).sqrt());
    // Columns of `v` are the eigenvectors; make it a proper rotation.
    let mut m = DMat3::from_cols(
        DVec3::new(v[0][0], v[1][0], v[2][0]),
        DVec3::new(v[0][1], v[1][1], v[2][1]),
        DVec3::new(v[0][2], v[1][2], v[2][2]),
    );
    if m.determinant() < 0.0 {
        m.z_axis = -m.z_axis;
    }
    let q = DQuat::from_mat3(&m).normalize();
    Some((scales, [q.w, q.x, q.y, q.z]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rng::SplitMix64 as Rng;

    /// Scale and rotation of a covariance reproduce it (`R diag(s^2) R^T`), against the
    /// compute crate's covariance of known scales and rotations.
    #[test]
    fn eigen_decomposition_reproduces_covariances() {
        let mut rng = Rng::new(4);
        let mut cases: Vec<([f64; 3], [f64; 4])> = (0..200)
            .map(|_| {
                (
                    [0, 1, 2].map(|_| rng.uniform(-6.0, -1.0).exp()),
                    [0, 1, 2, 3].map(|_| rng.uniform(-1.0, 1.0)),
                )
            })
            .collect();
        // Repeated eigenvalues and an axis-aligned Gaussian.
        cases.push(([0.1, 0.1, 0.1], [0.3, 0.1, -0.4, 0.8]));
        cases.push(([0.2, 0.05, 0.05], [1.0, 0.0, 0.0, 0.0]));
        for (scales, q) in cases {
            let sigma = covariance_from_scale_rotation(&scales, &q)
                .unwrap()
                .covariances;
            let (s2, q2) = scale_rotation_of(&sigma).unwrap();
            let back = covariance_from_scale_rotation(&s2, &q2)
                .unwrap()
                .covariances;
            let size = sigma.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (a, b) in sigma.iter().zip(&back) {
                assert!((a - b).abs() <= 1e-12 * size, "{sigma:?} vs {back:?}");
            }
            let mut want = scales;
            let mut got = s2;
            want.sort_by(f64::total_cmp);
            got.sort_by(f64::total_cmp);
            for (a, b) in want.iter().zip(&got) {
                assert!((a - b).abs() <= 1e-9 * a, "{want:?} vs {got:?}");
            }
        }
        assert!(scale_rotation_of(&[f64::NAN, 0.0, 0.0, 1.0, 0.0, 1.0]).is_none());
    }

    /// A posed frame of an avatar with every per-frame network (pose refiner, non-rigid
    /// offsets, LBS offsets), written and read back, splats to the avatar's own render within
    /// 1e-3 RMS (f32 file values); the canonical file holds the trained columns.
    #[test]
    fn a_posed_frame_re_renders_to_the_avatar_render() {
        use crate::avatar::{FrameInputs, TrainedAvatar};
        use crate::config::{AvatarConfig, MotionContext};
        use crate::model::{NetworkConfig, Networks};
        use crate::rig::BodyRig;
        use seqavatar_compute::backend::{Backend, DeviceChoice};
        use seqavatar_compute::splat::RasterOptions;
        use seqavatar_core::body::procedural::procedural_body;
        use seqavatar_core::camera::{Camera, Intrinsics};

        let mut rng = Rng::new(6);
        let model = procedural_body(0.05);
        let rig = BodyRig::new(model.clone()).unwrap();
        let config = AvatarConfig {
            motion_context: MotionContext::Pose,
            trunk_width: 16,
            trunk_depth: 2,
            ..AvatarConfig::for_tests()
        };
        let j = rig.joint_count();
        let net_config = NetworkConfig::from_avatar(&config, j, j, 1).unwrap();
        let mut networks = Networks::<f32>::new(&net_config, 2).unwrap();
        for param in networks.parameters_mut() {
            if param.name.starts_with("non_rigid.heads")
                || param.name.starts_with("lbs_offsets.4")
                || param.name.starts_with("pose_refiner.2")
            {
                for x in param.values.iter_mut() {
                    *x = rng.uniform(-0.05, 0.05) as f32;
                }
            }
        }
        let n = 300;
        let v = rig.vertex_count();
        let gaussians = AvatarGaussians {
            xyz: (0..n)
                .flat_map(|i| {
                    let k = 3 * ((i * 53) % v);
                    rig.canonical_vertices[k..k + 3].to_vec()
                })
                .collect(),
            sh: (0..n * 48).map(|_| rng.uniform(-0.5, 0.5)).collect(),
            opacity_logit: (0..n).map(|_| rng.uniform(0.0, 3.0)).collect(),
            log_scale: (0..3 * n).map(|_| rng.uniform(-3.5, -2.5)).collect(),
            rotation: (0..4 * n).map(|_| rng.uniform(-1.0, 1.0)).collect(),
        };
        let mut avatar = TrainedAvatar::new(config, rig, gaussians, 2, vec![1], Some(networks));
        avatar.background = [0.2, 0.3, 0.4];
        let mut params = model.zero_params();
        params.pose[1] = DVec3::new(0.4, 0.0, 0.1);
        params.pose[17] = DVec3::new(0.0, 0.3, -0.7);
        params.world_translation = DVec3::new(0.05, 0.1, 0.0);
        let inputs = FrameInputs {
            params,
            skeleton_motion: Vec::new(),
            vertex_velocity: Vec::new(),
        };
        let camera = Camera::look_at(
            48,
            64,
            Intrinsics {
                fx: 60.0,
                fy: 60.0,
                cx: 24.0,
                cy: 32.0,
            },
            DVec3::new(0.0, 0.0, 2.4),
            DVec3::ZERO,
            DVec3::new(0.0, 1.0, 0.0),
        );
        let device = avatar
            .backend(Backend::select(DeviceChoice::Cpu).unwrap())
            .unwrap();
        let rendered = avatar.render(&inputs, &camera, &device).unwrap();
        let deformed = avatar.deform(&inputs, &device).unwrap();
        let cloud = posed_cloud(&deformed.world, &avatar.gaussians.opacity_logit).unwrap();
        let back = read_ply(&write_ply(&cloud).unwrap()).unwrap();
        let world = cloud_to_world(&back).unwrap();
        let options = RasterOptions {
            background: avatar.background,
            smooth_cutoff: false,
        };
        let replayed = device
            .splat_forward(&world, std::slice::from_ref(&camera), &options)
            .unwrap()
            .images
            .swap_remove(0);
        let squared: f64 = rendered
            .colour
            .iter()
            .zip(&replayed.colour)
            .map(|(a, b)| (a - b).powi(2))
            .sum();
        let rms = (squared / rendered.colour.len() as f64).sqrt();
        let covered = rendered.alpha.iter().filter(|&&a| a > 0.5).count();
        eprintln!("re-rendered posed PLY: RMS {rms:.2e}, {covered} covered pixels");
        assert!(covered > 100, "the avatar covers {covered} pixels");
        assert!(rms <= 1e-3, "RMS {rms}");
        // The posed centres are the deformed ones, not the canonical ones.
        let moved = back
            .xyz
            .iter()
            .zip(&avatar.gaussians.xyz)
            .map(|(&a, &b)| (f64::from(a) - b).abs())
            .fold(0.0, f64::max);
        assert!(moved > 0.05, "posed centres moved by {moved} only");
        // The canonical file: the trained columns at f32 precision.
        let canonical =
            read_ply(&write_ply(&canonical_cloud(&avatar.gaussians, 2).unwrap()).unwrap()).unwrap();
        assert_eq!(canonical.len(), n);
        for (a, b) in canonical.xyz.iter().zip(&avatar.gaussians.xyz) {
            assert_eq!(*a, *b as f32);
        }
        for (a, b) in canonical
            .opacity
            .iter()
            .zip(&avatar.gaussians.opacity_logit)
        {
            assert_eq!(*a, *b as f32);
        }
        // SH: coefficient 3 (degree 1) of blue of Gaussian 7 is `f_rest_{2 * 15 + 2}`.
        assert_eq!(
            canonical.sh[(7 * 3 + 2) * 16 + 3],
            avatar.gaussians.sh[(7 * SH_STORED + 3) * 3 + 2] as f32
        );
    }
}
