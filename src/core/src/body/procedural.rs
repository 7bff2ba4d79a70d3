//! The built-in procedural body: SMPL's 24-joint tree and joint order, a closed surface of a
//! few thousand vertices around the bones, smooth skinning weights, a joint regressor and two
//! shape parameters (height, girth). It needs no licensed file.
//!
//! Construction:
//! - The body is the zero level set of a smooth union of tapered capsules ("parts"), one or
//!   more per joint, in SMPL's rest frame (y up, x towards the body's left, z forward, the
//!   pelvis joint at the origin, arms out in a T-pose).
//! - The surface is extracted with surface nets on a regular grid (one vertex per grid cell
//!   the surface crosses, one quad per crossed grid edge), which is closed by construction,
//!   then each vertex is moved onto the level set by Newton steps.
//! - Skinning weights are a soft-min over the parts' distances (temperature
//!   [`SKIN_TEMPERATURE`]), the largest four kept and renormalised.
//! - The joint regressor, for each joint, is the minimum-norm affine combination of its
//!   nearest surface vertices that reproduces the designed joint position exactly.
//! - Shape: beta 0 scales the whole body about the pelvis by 8 % per unit (height); beta 1
//!   pushes every vertex away from the axis of its own part by 15 % of its distance (girth).

use glam::DVec3;

use super::SMPL_PARENTS;
use super::model::{BodyModel, BodyModelArrays};

/// Grid spacing of the surface extraction (metres); 0.02 gives about 4500 vertices.
pub const DEFAULT_GRID_SPACING: f64 = 0.02;
/// Width (metres) of the soft-min that turns part distances into skinning weights.
pub const SKIN_TEMPERATURE: f64 = 0.012;
/// Blend radius (metres) of the smooth union between parts.
const BLEND_RADIUS: f64 = 0.02;
/// Surface vertices per joint in the regressor.
const REGRESSOR_NEIGHBOURS: usize = 24;
/// Relative scale change per unit of beta 0.
pub const HEIGHT_PER_BETA: f64 = 0.08;
/// Relative radius change per unit of beta 1.
pub const GIRTH_PER_BETA: f64 = 0.15;

/// Rest positions of SMPL's 24 joints for the procedural body (metres).
pub const JOINTS: [[f64; 3]; 24] = [
    [0.0, 0.0, 0.0],       // pelvis
    [0.09, -0.08, 0.0],    // left hip
    [-0.09, -0.08, 0.0],   // right hip
    [0.0, 0.11, -0.01],    // spine1
    [0.10, -0.50, 0.0],    // left knee
    [-0.10, -0.50, 0.0],   // right knee
    [0.0, 0.24, -0.01],    // spine2
    [0.10, -0.89, -0.02],  // left ankle
    [-0.10, -0.89, -0.02], // right ankle
    [0.0, 0.33, 0.0],      // spine3
    [0.11, -0.94, 0.09],   // left foot
    [-0.11, -0.94, 0.09],  // right foot
    [0.0, 0.47, -0.01],    // neck
    [0.07, 0.42, 0.0],     // left collar
    [-0.07, 0.42, 0.0],    // right collar
    [0.0, 0.58, 0.02],     // head
    [0.18, 0.44, -0.01],   // left shoulder
    [-0.18, 0.44, -0.01],  // right shoulder
    [0.44, 0.44, -0.02],   // left elbow
    [-0.44, 0.44, -0.02],  // right elbow
    [0.68, 0.44, -0.02],   // left wrist
    [-0.68, 0.44, -0.02],  // right wrist
    [0.76, 0.44, -0.02],   // left hand
    [-0.76, 0.44, -0.02],  // right hand
];

/// A tapered capsule: the segment `a -> b` with radius varying linearly from `ra` to `rb`,
/// skinned to `joint`.
#[derive(Clone, Copy, Debug)]
pub struct Part {
    pub a: DVec3,
    pub b: DVec3,
    pub ra: f64,
    pub rb: f64,
    pub joint: usize,
}

impl Part {
    /// Closest point of the axis to `p` and the parameter along it.
    fn closest(&self, p: DVec3) -> (DVec3, f64) {
        let ab = self.b - self.a;
        let t = ((p - self.a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
        (self.a + ab * t, t)
    }

    /// Signed distance-like value (exact for an untapered capsule).
    pub fn distance(&self, p: DVec3) -> f64 {
        let (c, t) = self.closest(p);
        (p - c).length() - (self.ra + (self.rb - self.ra) * t)
    }
}

fn part(a: [f64; 3], b: [f64; 3], ra: f64, rb: f64, joint: usize) -> Part {
    Part {
        a: DVec3::from_array(a),
        b: DVec3::from_array(b),
        ra,
        rb,
        joint,
    }
}

/// The capsules of the procedural body. Torso pieces are horizontal capsules, which give the
/// torso a wide, shallow cross-section.
pub fn parts() -> Vec<Part> {
    let j = |i: usize| JOINTS[i];
    let mut parts = vec![
        part([-0.075, -0.04, 0.0], [0.075, -0.04, 0.0], 0.115, 0.115, 0),
        part([-0.07, 0.11, -0.01], [0.07, 0.11, -0.01], 0.10, 0.10, 3),
        part([-0.08, 0.23, -0.005], [0.08, 0.23, -0.005], 0.105, 0.105, 6),
        part([-0.085, 0.34, 0.0], [0.085, 0.34, 0.0], 0.105, 0.105, 9),
        part([0.0, 0.43, -0.01], [0.0, 0.55, 0.0], 0.05, 0.05, 12),
        part([0.0, 0.63, 0.02], [0.0, 0.68, 0.02], 0.095, 0.09, 15),
    ];
    for side in [0usize, 1] {
        let s = if side == 0 { 1.0 } else { -1.0 };
        let k = |left: usize| left + side;
        parts.extend([
            part([0.03 * s, 0.42, 0.0], j(k(16)), 0.06, 0.055, k(13)),
            part(j(k(16)), j(k(18)), 0.052, 0.042, k(16)),
            part(j(k(18)), j(k(20)), 0.04, 0.032, k(18)),
            part(j(k(20)), j(k(22)), 0.033, 0.03, k(20)),
            part(j(k(22)), [0.84 * s, 0.44, -0.02], 0.028, 0.022, k(22)),
            part(j(k(1)), j(k(4)), 0.085, 0.055, k(1)),
            part(j(k(4)), j(k(7)), 0.052, 0.04, k(4)),
            part(j(k(7)), j(k(10)), 0.038, 0.035, k(7)),
            part(j(k(10)), [0.115 * s, -0.945, 0.16], 0.032, 0.028, k(10)),
        ]);
    }
    parts
}

/// Polynomial smooth minimum with blend radius `k`.
fn smooth_min(a: f64, b: f64, k: f64) -> f64 {
    let h = (k - (a - b).abs()).max(0.0) / k;
    a.min(b) - h * h * k * 0.25
}

/// The body's implicit function: negative inside.
fn body_field(parts: &[Part], p: DVec3) -> f64 {
    parts
        .iter()
        .map(|part| part.distance(p))
        .fold(f64::INFINITY, |acc, d| {
            if acc.is_infinite() {
                d
            } else {
                smooth_min(acc, d, BLEND_RADIUS)
            }
        })
}

fn field_gradient(parts: &[Part], p: DVec3) -> DVec3 {
    let h = 1e-5;
    DVec3::new(
        body_field(parts, p + DVec3::X * h) - body_field(parts, p - DVec3::X * h),
        body_field(parts, p + DVec3::Y * h) - body_field(parts, p - DVec3::Y * h),
        body_field(parts, p + DVec3::Z * h) - body_field(parts, p - DVec3::Z * h),
    ) / (2.0 * h)
}

/// A closed triangle mesh of the zero level set of `field` inside `[lo, hi]`, by surface
/// nets with spacing `h`. The box must contain the whole surface with a margin.
fn surface_nets(
    field: &dyn Fn(DVec3) -> f64,
    lo: DVec3,
    hi: DVec3,
    h: f64,
) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let n = ((hi - lo) / h).ceil().as_uvec3() + 1;
    let (nx, ny, nz) = (n.x as usize, n.y as usize, n.z as usize);
    let point = |i: usize, j: usize, k: usize| lo + DVec3::new(i as f64, j as f64, k as f64) * h;
    let index = |i: usize, j: usize, k: usize| (k * ny + j) * nx + i;
    let values: Vec<f64> = (0..nx * ny * nz)
        .map(|flat| {
            let (i, j, k) = (flat % nx, (flat / nx) % ny, flat / (nx * ny));
            field(point(i, j, k))
        })
        .collect();
    // One vertex per cell (min corner (i, j, k)) that the surface crosses.
    let mut cell_vertex = vec![u32::MAX; (nx - 1) * (ny - 1) * (nz - 1)];
    let cell_index = |i: usize, j: usize, k: usize| (k * (ny - 1) + j) * (nx - 1) + i;
    let mut vertices = Vec::new();
    const CORNERS: [[usize; 3]; 8] = [
        [0, 0, 0],
        [1, 0, 0],
        [0, 1, 0],
        [1, 1, 0],
        [0, 0, 1],
        [1, 0, 1],
        [0, 1, 1],
        [1, 1, 1],
    ];
    const EDGES: [[usize; 2]; 12] = [
        [0, 1],
        [2, 3],
        [4, 5],
        [6, 7],
        [0, 2],
        [1, 3],
        [4, 6],
        [5, 7],
        [0, 4],
        [1, 5],
        [2, 6],
        [3, 7],
    ];
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let corner_values = CORNERS.map(|[a, b, c]| values[index(i + a, j + b, k + c)]);
                let inside = corner_values.iter().filter(|v| **v < 0.0).count();
                if inside == 0 || inside == 8 {
                    continue;
                }
                let mut sum = DVec3::ZERO;
                let mut count = 0.0;
                for [e0, e1] in EDGES {
                    let (v0, v1) = (corner_values[e0], corner_values[e1]);
                    if (v0 < 0.0) != (v1 < 0.0) {
                        let t = v0 / (v0 - v1);
                        let p0 = DVec3::from_array(CORNERS[e0].map(|c| c as f64));
                        let p1 = DVec3::from_array(CORNERS[e1].map(|c| c as f64));
                        sum += p0 + (p1 - p0) * t;
                        count += 1.0;
                    }
                }
                cell_vertex[cell_index(i, j, k)] = vertices.len() as u32;
                vertices.push(point(i, j, k) + sum / count * h);
            }
        }
    }
    // One quad per crossed grid edge, oriented so the normal points from inside to outside.
    let mut faces = Vec::new();
    let mut quad = |cells: [u32; 4], outward_positive: bool| {
        let [a, b, c, d] = if outward_positive {
            cells
        } else {
            [cells[3], cells[2], cells[1], cells[0]]
        };
        // Split along the shorter diagonal.
        let (pa, pb, pc, pd) = (
            vertices[a as usize],
            vertices[b as usize],
            vertices[c as usize],
            vertices[d as usize],
        );
        if (pa - pc).length_squared() <= (pb - pd).length_squared() {
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        } else {
            faces.push([a, b, d]);
            faces.push([b, c, d]);
        }
    };
    for k in 1..nz - 1 {
        for j in 1..ny - 1 {
            for i in 1..nx - 1 {
                let v0 = values[index(i, j, k)] < 0.0;
                // x edge (i,j,k)->(i+1,j,k): cells around it counter-clockwise seen from +x.
                if i + 1 < nx && (values[index(i + 1, j, k)] < 0.0) != v0 {
                    let cells = [
                        cell_vertex[cell_index(i, j - 1, k - 1)],
                        cell_vertex[cell_index(i, j, k - 1)],
                        cell_vertex[cell_index(i, j, k)],
                        cell_vertex[cell_index(i, j - 1, k)],
                    ];
                    quad(cells, v0);
                }
                if j + 1 < ny && (values[index(i, j + 1, k)] < 0.0) != v0 {
                    let cells = [
                        cell_vertex[cell_index(i - 1, j, k - 1)],
                        cell_vertex[cell_index(i - 1, j, k)],
                        cell_vertex[cell_index(i, j, k)],
                        cell_vertex[cell_index(i, j, k - 1)],
                    ];
                    quad(cells, v0);
                }
                if k + 1 < nz && (values[index(i, j, k + 1)] < 0.0) != v0 {
                    let cells = [
                        cell_vertex[cell_index(i - 1, j - 1, k)],
                        cell_vertex[cell_index(i, j - 1, k)],
                        cell_vertex[cell_index(i, j, k)],
                        cell_vertex[cell_index(i - 1, j, k)],
                    ];
                    quad(cells, v0);
                }
            }
        }
    }
    (vertices, faces)
}

/// Minimum-norm affine weights `w` (sum 1) with `sum w_i p_i = target`, closest to uniform.
fn affine_weights(points: &[DVec3], target: DVec3) -> Vec<f64> {
    let n = points.len() as f64;
    let uniform = 1.0 / n;
    // A = [p_i; 1] (4 x n). w = u + A^T (A A^T)^-1 (b - A u).
    let mut aat = [[0.0f64; 4]; 4];
    let rows = |p: DVec3| [p.x, p.y, p.z, 1.0];
    for &p in points {
        let r = rows(p);
        for a in 0..4 {
            for b in 0..4 {
                aat[a][b] += r[a] * r[b];
            }
        }
    }
    let mean: DVec3 = points.iter().copied().sum::<DVec3>() * uniform;
    let residual = [target.x - mean.x, target.y - mean.y, target.z - mean.z, 0.0];
    let lambda = solve4(aat, residual);
    points
        .iter()
        .map(|&p| {
            let r = rows(p);
            uniform + (0..4).map(|a| r[a] * lambda[a]).sum::<f64>()
        })
        .collect()
}

/// Solves a symmetric positive definite 4x4 system by Gaussian elimination with pivoting.
// Index loops mirror the textbook elimination; iterators would obscure it.
#[allow(clippy::needless_range_loop)]
fn solve4(mut a: [[f64; 4]; 4], mut b: [f64; 4]) -> [f64; 4] {
    for col in 0..4 {
        let pivot = (col..4)
            .max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))
            .expect("non-empty range");
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..4 {
            let f = a[row][col] / a[col][col];
            for c in col..4 {
                a[row][c] -= f * a[col][c];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; 4];
    for row in (0..4).rev() {
        let s: f64 = (row + 1..4).map(|c| a[row][c] * x[c]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

/// Builds the procedural body with grid spacing `grid_spacing` (metres; use
/// [`DEFAULT_GRID_SPACING`]). Smaller spacing gives more vertices (about
/// `4500 * (0.02 / spacing)^2`).
pub fn procedural_body(grid_spacing: f64) -> BodyModel {
    assert!(
        (0.005..=0.05).contains(&grid_spacing),
        "grid spacing {grid_spacing} m outside 0.005..0.05"
    );
    let parts = parts();
    let field = |p: DVec3| body_field(&parts, p);
    let (mut vertices, faces) = surface_nets(
        &field,
        DVec3::new(-0.95, -1.05, -0.2),
        DVec3::new(0.95, 0.85, 0.25),
        grid_spacing,
    );
    // Newton steps onto the level set.
    for v in vertices.iter_mut() {
        for _ in 0..3 {
            let g = field_gradient(&parts, *v);
            let g2 = g.length_squared();
            if g2 > 1e-12 {
                *v -= g * (field(*v) / g2);
            }
        }
    }
    let num_vertices = vertices.len();
    let num_joints = JOINTS.len();

    // Skinning weights: soft-min of part distances, four largest kept.
    let mut weights = vec![0.0; num_vertices * num_joints];
    let mut dominant_part = vec![0usize; num_vertices];
    for (v, &p) in vertices.iter().enumerate() {
        let distances: Vec<f64> = parts.iter().map(|part| part.distance(p)).collect();
        let (best, &d_min) = distances
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))
            .expect("parts are not empty");
        dominant_part[v] = best;
        let mut per_joint = vec![0.0; num_joints];
        for (part, d) in parts.iter().zip(&distances) {
            per_joint[part.joint] += (-(d - d_min) / SKIN_TEMPERATURE).exp();
        }
        let mut order: Vec<usize> = (0..num_joints).collect();
        order.sort_by(|&a, &b| per_joint[b].total_cmp(&per_joint[a]));
        let kept = &order[..4];
        let total: f64 = kept.iter().map(|&j| per_joint[j]).sum();
        for &j in kept {
            weights[v * num_joints + j] = per_joint[j] / total;
        }
    }

    // Joint regressor: affine combination of the nearest vertices.
    let mut joint_regressor = vec![0.0; num_joints * num_vertices];
    for (j, joint) in JOINTS.iter().enumerate() {
        let target = DVec3::from_array(*joint);
        let mut nearest: Vec<usize> = (0..num_vertices).collect();
        nearest.select_nth_unstable_by(REGRESSOR_NEIGHBOURS, |&a, &b| {
            (vertices[a] - target)
                .length_squared()
                .total_cmp(&(vertices[b] - target).length_squared())
        });
        nearest.truncate(REGRESSOR_NEIGHBOURS);
        let points: Vec<DVec3> = nearest.iter().map(|&v| vertices[v]).collect();
        for (&v, w) in nearest.iter().zip(affine_weights(&points, target)) {
            joint_regressor[j * num_vertices + v] = w;
        }
    }

    // Shape blend shapes: height (uniform scale about the pelvis) and girth (radial).
    let num_betas = 2;
    let mut shape_dirs = vec![0.0; num_vertices * 3 * num_betas];
    for (v, &p) in vertices.iter().enumerate() {
        let (axis_point, _) = parts[dominant_part[v]].closest(p);
        let height = p * HEIGHT_PER_BETA;
        let girth = (p - axis_point) * GIRTH_PER_BETA;
        for c in 0..3 {
            shape_dirs[(v * 3 + c) * num_betas] = height[c];
            shape_dirs[(v * 3 + c) * num_betas + 1] = girth[c];
        }
    }

    let arrays = BodyModelArrays {
        template: vertices.iter().map(|v| v.to_array()).collect(),
        faces,
        parents: SMPL_PARENTS
            .iter()
            .map(|p| p.map_or(-1, |p| p as i64))
            .collect(),
        weights,
        joint_regressor,
        shape_dirs,
        num_betas,
        expression_dirs: Vec::new(),
        num_expression: 0,
        pose_dirs: Vec::new(),
    };
    BodyModel::new(arrays).expect("the procedural body is valid by construction")
}
