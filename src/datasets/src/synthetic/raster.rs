//! A software triangle rasterizer, independent of the Gaussian renderer: z-buffer, sample
//! points at pixel centres (continuous pixel convention), a top-left style tie rule so
//! triangles sharing an edge cover each sample once, and perspective-correct barycentric
//! coordinates.
//!
//! It writes a visibility buffer (nearest triangle and its perspective-correct barycentrics
//! per sample); shading is done afterwards by the caller.

use seqavatar_core::camera::Camera;
use seqavatar_core::glam::{DVec2, DVec3};

/// Triangles with a vertex closer than this to the camera plane (metres) are skipped: the
/// synthetic scene keeps every surface metres away from the cameras, so no clipping is needed.
pub const NEAR: f64 = 0.05;

/// No triangle covers the sample.
pub const EMPTY: u32 = u32::MAX;

/// What is visible at each sample of an image.
#[derive(Clone, Debug)]
pub struct VisibilityBuffer {
    pub width: usize,
    pub height: usize,
    /// Per sample, the visible triangle index or [`EMPTY`].
    pub triangle: Vec<u32>,
    /// Per sample, the perspective-correct barycentric weights of the triangle's vertices.
    pub barycentric: Vec<[f32; 3]>,
    /// Per sample, the camera-space depth of the visible surface (infinity where empty).
    pub depth: Vec<f32>,
}

/// A projected vertex: pixel position and camera depth.
#[derive(Clone, Copy, Debug)]
struct Projected {
    pixel: DVec2,
    depth: f64,
}

/// Edge function: twice the signed area of (a, b, p); positive on one side of a -> b.
fn edge(a: DVec2, b: DVec2, p: DVec2) -> f64 {
    (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
}

/// Tie rule for samples exactly on an edge: of the two directions of an edge, exactly one
/// owns it, so two triangles sharing an edge never both (nor neither) cover such a sample.
fn owns_edge(a: DVec2, b: DVec2) -> bool {
    let d = b - a;
    d.y > 0.0 || (d.y == 0.0 && d.x < 0.0)
}

/// Calls `visit(column, row, lambda)` for every sample centre `(column + 0.5, row + 0.5)`
/// inside the screen-space triangle, with its screen-space (affine) barycentrics.
pub fn scan_triangle(
    pixels: [DVec2; 3],
    width: usize,
    height: usize,
    mut visit: impl FnMut(usize, usize, [f64; 3]),
) {
    let [mut a, mut b, c] = pixels;
    let mut area = edge(a, b, c);
    let mut swapped = false;
    if area == 0.0 || !area.is_finite() {
        return;
    }
    if area < 0.0 {
        std::mem::swap(&mut a, &mut b);
        area = -area;
        swapped = true;
    }
    let lo = a.min(b).min(c);
    let hi = a.max(b).max(c);
    // Sample centres col + 0.5 within [lo, hi].
    let col0 = (lo.x - 0.5).ceil().max(0.0) as usize;
    let row0 = (lo.y - 0.5).ceil().max(0.0) as usize;
    let col1 = ((hi.x - 0.5).floor() + 1.0).clamp(0.0, width as f64) as usize;
    let row1 = ((hi.y - 0.5).floor() + 1.0).clamp(0.0, height as f64) as usize;
    let edges = [(b, c), (c, a), (a, b)];
    let owns = edges.map(|(p, q)| owns_edge(p, q));
    for row in row0..row1 {
        for col in col0..col1 {
            let p = DVec2::new(col as f64 + 0.5, row as f64 + 0.5);
            let mut lambda = [0.0; 3];
            let mut inside = true;
            for (k, &(p0, p1)) in edges.iter().enumerate() {
                let e = edge(p0, p1, p);
                if e < 0.0 || (e == 0.0 && !owns[k]) {
                    inside = false;
                    break;
                }
                lambda[k] = e / area;
            }
            if inside {
                if swapped {
                    lambda.swap(0, 1);
                }
                visit(col, row, lambda);
            }
        }
    }
}

/// Rasterizes `triangles` over world-space `positions` seen by `camera` (distortion is
/// ignored: synthetic cameras are ideal pinholes) into a `camera.width x camera.height`
/// visibility buffer.
pub fn rasterize(camera: &Camera, positions: &[DVec3], triangles: &[[u32; 3]]) -> VisibilityBuffer {
    let (width, height) = (camera.width as usize, camera.height as usize);
    let mut buffer = VisibilityBuffer {
        width,
        height,
        triangle: vec![EMPTY; width * height],
        barycentric: vec![[0.0; 3]; width * height],
        depth: vec![f32::INFINITY; width * height],
    };
    let intrinsics = camera.intrinsics;
    let projected: Vec<Option<Projected>> = positions
        .iter()
        .map(|&p| {
            let c = camera.world_to_camera(p);
            (c.z > NEAR).then(|| Projected {
                pixel: DVec2::new(
                    intrinsics.fx * c.x / c.z + intrinsics.cx,
                    intrinsics.fy * c.y / c.z + intrinsics.cy,
                ),
                depth: c.z,
            })
        })
        .collect();
    for (index, tri) in triangles.iter().enumerate() {
        let [Some(p0), Some(p1), Some(p2)] = tri.map(|v| projected[v as usize]) else {
            continue;
        };
        let inverse_depth = [1.0 / p0.depth, 1.0 / p1.depth, 1.0 / p2.depth];
        scan_triangle(
            [p0.pixel, p1.pixel, p2.pixel],
            width,
            height,
            |col, row, lambda| {
                // 1/z is affine in screen space; attributes over z are too.
                let w = [
                    lambda[0] * inverse_depth[0],
                    lambda[1] * inverse_depth[1],
                    lambda[2] * inverse_depth[2],
                ];
                let sum = w[0] + w[1] + w[2];
                let depth = 1.0 / sum;
                let sample = row * width + col;
                if (depth as f32) < buffer.depth[sample] {
                    buffer.depth[sample] = depth as f32;
                    buffer.triangle[sample] = index as u32;
                    buffer.barycentric[sample] = [
                        (w[0] / sum) as f32,
                        (w[1] / sum) as f32,
                        (w[2] / sum) as f32,
                    ];
                }
            },
        );
    }
    buffer
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::camera::Intrinsics;

    fn camera() -> Camera {
        Camera::look_at(
            64,
            48,
            Intrinsics {
                fx: 60.0,
                fy: 62.0,
                cx: 31.0,
                cy: 25.0,
            },
            DVec3::new(0.3, 0.2, -3.0),
            DVec3::ZERO,
            DVec3::Y,
        )
    }

    #[test]
    fn shared_edges_cover_each_sample_exactly_once() {
        // Two triangles splitting a square along a diagonal through sample centres.
        let square = [
            DVec2::new(2.5, 2.5),
            DVec2::new(12.5, 2.5),
            DVec2::new(12.5, 12.5),
            DVec2::new(2.5, 12.5),
        ];
        let mut count = vec![0u32; 16 * 16];
        for tri in [[0, 1, 2], [0, 2, 3]] {
            scan_triangle(tri.map(|i| square[i]), 16, 16, |c, r, lambda| {
                assert!((lambda.iter().sum::<f64>() - 1.0).abs() < 1e-12);
                count[r * 16 + c] += 1;
            });
        }
        for row in 0..16 {
            for col in 0..16 {
                let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
                // The square's left/top edges are owned, its right/bottom edges are not
                // (or the other way round): either way the interior is covered once.
                let strictly_inside = x > 2.5 && x < 12.5 && y > 2.5 && y < 12.5;
                let outside = !(2.5..=12.5).contains(&x) || !(2.5..=12.5).contains(&y);
                if strictly_inside {
                    assert_eq!(count[row * 16 + col], 1, "({col}, {row})");
                } else if outside {
                    assert_eq!(count[row * 16 + col], 0, "({col}, {row})");
                } else {
                    assert!(count[row * 16 + col] <= 1);
                }
            }
        }
        // Reversed winding covers the same samples.
        let mut a = Vec::new();
        let mut b = Vec::new();
        scan_triangle([square[0], square[1], square[2]], 16, 16, |c, r, _| {
            a.push((c, r))
        });
        scan_triangle([square[2], square[1], square[0]], 16, 16, |c, r, _| {
            b.push((c, r))
        });
        assert_eq!(a, b);
    }

    #[test]
    fn interpolation_is_perspective_correct() {
        // A tilted quad; every covered sample's interpolated world point must lie on the
        // pixel's viewing ray (closed form: ray-plane intersection).
        let cam = camera();
        let corners = [
            DVec3::new(-1.0, -0.8, -0.5),
            DVec3::new(1.0, -0.8, 1.5),
            DVec3::new(1.0, 0.8, 1.5),
            DVec3::new(-1.0, 0.8, -0.5),
        ];
        let triangles = [[0u32, 1, 2], [0, 2, 3]];
        let buffer = rasterize(&cam, &corners, &triangles);
        let normal = (corners[1] - corners[0])
            .cross(corners[3] - corners[0])
            .normalize();
        let mut covered = 0;
        for row in 0..buffer.height {
            for col in 0..buffer.width {
                let sample = row * buffer.width + col;
                let tri = buffer.triangle[sample];
                if tri == EMPTY {
                    continue;
                }
                covered += 1;
                let bary = buffer.barycentric[sample];
                let vertices = triangles[tri as usize].map(|v| corners[v as usize]);
                let interpolated: DVec3 = (0..3).map(|k| vertices[k] * bary[k] as f64).sum();
                // Ray through the sample centre.
                let intr = cam.intrinsics;
                let dir_cam = DVec3::new(
                    (col as f64 + 0.5 - intr.cx) / intr.fx,
                    (row as f64 + 0.5 - intr.cy) / intr.fy,
                    1.0,
                );
                let origin = cam.center();
                let dir = cam.rotation.transpose() * dir_cam;
                let t = (corners[0] - origin).dot(normal) / dir.dot(normal);
                let hit = origin + dir * t;
                assert!(
                    (interpolated - hit).length() < 1e-5,
                    "({col},{row}) {interpolated:?} vs {hit:?}"
                );
                let depth = cam.world_to_camera(hit).z;
                assert!((buffer.depth[sample] as f64 - depth).abs() < 1e-5);
            }
        }
        assert!(covered > 300, "covered {covered}");
        // An affine (not perspective-correct) interpolation would be off by millimetres.
    }

    #[test]
    fn z_buffer_keeps_the_nearest_surface() {
        let cam = camera();
        // Two parallel squares facing the camera; the nearer one is smaller.
        let far = 1.0;
        let near = -1.0;
        let positions = vec![
            DVec3::new(-1.0, -1.0, far),
            DVec3::new(1.0, -1.0, far),
            DVec3::new(1.0, 1.0, far),
            DVec3::new(-1.0, 1.0, far),
            DVec3::new(-0.3, -0.3, near),
            DVec3::new(0.3, -0.3, near),
            DVec3::new(0.3, 0.3, near),
            DVec3::new(-0.3, 0.3, near),
        ];
        // Near square drawn first, then the far one: the far must not overwrite it.
        let triangles = [[4u32, 5, 6], [4, 6, 7], [0, 1, 2], [0, 2, 3]];
        let buffer = rasterize(&cam, &positions, &triangles);
        let centre = cam.project(DVec3::new(0.0, 0.0, near)).unwrap();
        let sample = centre.y as usize * buffer.width + centre.x as usize;
        assert!(buffer.triangle[sample] < 2);
        let edge = cam.project(DVec3::new(0.8, 0.0, far)).unwrap();
        let sample = edge.y as usize * buffer.width + edge.x as usize;
        assert!(buffer.triangle[sample] >= 2);
        // Behind the camera: skipped, never NaN.
        let behind = [
            DVec3::new(0.0, 0.0, -5.0),
            DVec3::new(1.0, 0.0, -5.0),
            DVec3::new(0.0, 1.0, -5.0),
        ];
        let buffer = rasterize(&cam, &behind, &[[0, 1, 2]]);
        assert!(buffer.triangle.iter().all(|&t| t == EMPTY));
    }
}
