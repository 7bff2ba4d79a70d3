//! Projection of one Gaussian into one camera (EWA splatting with a guard band, SH colour,
//! opacity-aware screen extent) and its backward pass, generic over the scalar type.

// Index loops mirror the matrix and per-channel formulas they implement.
#![allow(clippy::needless_range_loop)]

use seqavatar_core::camera::Camera;

use super::super::sh::{sh_basis, sh_colour_unclamped};
use super::super::{
    ALPHA_THRESHOLD, BLUR_VARIANCE, FAR_PLANE, GUARD_BAND, GaussianSet, MAX_EXTENT_SIGMAS,
    NEAR_PLANE, TILE_SIZE,
};
use crate::scalar::Scalar;

type Mat3<S> = [[S; 3]; 3];

/// One camera's constants in the working precision.
#[derive(Clone, Debug)]
pub(super) struct CameraParams<S> {
    /// World-to-camera rotation, row-major.
    pub rotation: Mat3<S>,
    pub translation: [S; 3],
    /// Camera centre in world coordinates (origin of the SH view directions).
    pub centre: [S; 3],
    pub fx: S,
    pub fy: S,
    pub cx: S,
    pub cy: S,
    /// Guard band limits of `x/z` and `y/z`: `[-neg, pos]`.
    pub lim_x: [S; 2],
    pub lim_y: [S; 2],
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
}

impl<S: Scalar> CameraParams<S> {
    pub fn new(camera: &Camera) -> Self {
        let intr = camera.intrinsics;
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let lim = |size: f64, c: f64, f: f64| {
            [
                S::from_f64(c / f + GUARD_BAND * size / (2.0 * f)),
                S::from_f64((size - c) / f + GUARD_BAND * size / (2.0 * f)),
            ]
        };
        let r = camera.rotation;
        let centre = camera.center();
        Self {
            // glam is column-major: row i, column j is `col(j)[i]`.
            rotation: std::array::from_fn(|i| std::array::from_fn(|j| S::from_f64(r.col(j)[i]))),
            translation: camera.translation.to_array().map(S::from_f64),
            centre: centre.to_array().map(S::from_f64),
            fx: S::from_f64(intr.fx),
            fy: S::from_f64(intr.fy),
            cx: S::from_f64(intr.cx),
            cy: S::from_f64(intr.cy),
            lim_x: lim(w, intr.cx, intr.fx),
            lim_y: lim(h, intr.cy, intr.fy),
            width: camera.width,
            height: camera.height,
            tiles_x: camera.width.div_ceil(TILE_SIZE),
            tiles_y: camera.height.div_ceil(TILE_SIZE),
        }
    }
}

/// A projected Gaussian: everything compositing needs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Splat2d<S> {
    /// Continuous pixel coordinates.
    pub mean: [S; 2],
    /// Inverse 2D covariance `(A, B, C)` = `[[A, B], [B, C]]`.
    pub conic: [S; 3],
    pub opacity: S,
    pub colour: [S; 3],
    /// Camera-space `z` (metres).
    pub depth: S,
    /// `ln(1 / (255 opacity)) - 0.01`: a power below this gives an alpha below `1/255` by a
    /// 1% margin, far beyond rounding, so the rasteriser skips the `exp` with the same result.
    pub min_power: S,
    /// Pixels `[x_lo, x_hi) x [y_lo, y_hi)` of the screen box `mean -+ radius` grown by one
    /// pixel (so rounding cannot drop a pixel the contract composites), clipped to the image.
    pub pixel_box: [u32; 4],
    /// `[mean_x, -B/A, -2 min_power / A, det(conic) / A^2]` in f64: on the row at
    /// `dy = mean_y - row centre`, `power >= min_power` exactly for
    /// `dx in -B/A dy -+ sqrt(-2 min_power / A - dy^2 det / A^2)`.
    pub row_span: [f64; 4],
}

/// Tiles `[x0, x1) x [y0, y1)` a Gaussian's screen box touches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct TileRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl TileRect {
    pub fn area(&self) -> u64 {
        u64::from(self.x1 - self.x0) * u64::from(self.y1 - self.y0)
    }
}

/// Why a Gaussian did not reach the rasteriser.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Cull {
    NonFiniteInput,
    NonFiniteProjection,
    Depth,
    Covariance,
    Opacity,
    Offscreen,
}

/// The symmetric 3x3 matrix of an upper triangle `(xx, xy, xz, yy, yz, zz)`.
fn symmetric<S: Scalar>(u: &[S]) -> Mat3<S> {
    [[u[0], u[1], u[2]], [u[1], u[3], u[4]], [u[2], u[4], u[5]]]
}

fn mat_vec<S: Scalar>(m: &Mat3<S>, v: [S; 3]) -> [S; 3] {
    std::array::from_fn(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

fn mat_t_vec<S: Scalar>(m: &Mat3<S>, v: [S; 3]) -> [S; 3] {
    std::array::from_fn(|i| m[0][i] * v[0] + m[1][i] * v[1] + m[2][i] * v[2])
}

fn mat_mul<S: Scalar>(a: &Mat3<S>, b: &Mat3<S>) -> Mat3<S> {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j])
    })
}

fn transpose<S: Scalar>(m: &Mat3<S>) -> Mat3<S> {
    std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
}

/// Intermediate values of the projection shared by forward and backward.
struct Geometry<S> {
    p: [S; 3],
    /// Camera-space covariance `R Sigma R^T`.
    cov_cam: Mat3<S>,
    /// Clamped `x/z`, `y/z` and whether each clamp was inactive.
    u: S,
    v: S,
    u_free: bool,
    v_free: bool,
    /// The two rows of the EWA Jacobian (`J[0][1] = J[1][0] = 0`).
    j: [[S; 3]; 2],
    /// Projected covariance `(a, b, c)`, blur included.
    cov_2d: [S; 3],
}

fn geometry<S: Scalar>(
    cam: &CameraParams<S>,
    mean: [S; 3],
    cov: &[S],
) -> Result<Geometry<S>, Cull> {
    let m = mat_vec(&cam.rotation, mean);
    let p = [
        m[0] + cam.translation[0],
        m[1] + cam.translation[1],
        m[2] + cam.translation[2],
    ];
    let z = p[2];
    if !z.is_finite() || !p[0].is_finite() || !p[1].is_finite() {
        return Err(Cull::NonFiniteProjection);
    }
    if !(z >= S::from_f64(NEAR_PLANE) && z <= S::from_f64(FAR_PLANE)) {
        return Err(Cull::Depth);
    }
    let sigma = symmetric(cov);
    let cov_cam = mat_mul(&mat_mul(&cam.rotation, &sigma), &transpose(&cam.rotation));
    let inv_z = S::ONE / z;
    let (x_over_z, y_over_z) = (p[0] * inv_z, p[1] * inv_z);
    let u = x_over_z.clamp(-cam.lim_x[0], cam.lim_x[1]);
    let v = y_over_z.clamp(-cam.lim_y[0], cam.lim_y[1]);
    let u_free = x_over_z >= -cam.lim_x[0] && x_over_z <= cam.lim_x[1];
    let v_free = y_over_z >= -cam.lim_y[0] && y_over_z <= cam.lim_y[1];
    let j = [
        [cam.fx * inv_z, S::ZERO, -cam.fx * u * inv_z],
        [S::ZERO, cam.fy * inv_z, -cam.fy * v * inv_z],
    ];
    let jw0 = mat_t_vec(&cov_cam, j[0]);
    let jw1 = mat_t_vec(&cov_cam, j[1]);
    let blur = S::from_f64(BLUR_VARIANCE);
    let dot = |a: [S; 3], b: [S; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cov_2d = [dot(jw0, j[0]) + blur, dot(jw0, j[1]), dot(jw1, j[1]) + blur];
    Ok(Geometry {
        p,
        cov_cam,
        u,
        v,
        u_free,
        v_free,
        j,
        cov_2d,
    })
}

fn unit_view_direction<S: Scalar>(cam: &CameraParams<S>, mean: [S; 3]) -> ([S; 3], S) {
    let v = [
        mean[0] - cam.centre[0],
        mean[1] - cam.centre[1],
        mean[2] - cam.centre[2],
    ];
    let length = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    // The near plane keeps the mean at least 1 cm from the centre, so `length > 0`.
    let inv = S::ONE / length;
    ([v[0] * inv, v[1] * inv, v[2] * inv], length)
}

fn read3<S: Scalar>(values: &[S], index: usize) -> [S; 3] {
    [
        values[3 * index],
        values[3 * index + 1],
        values[3 * index + 2],
    ]
}

/// Projects Gaussian `index`; the tile rectangle is non-empty for a visible Gaussian.
pub(super) fn project<S: Scalar>(
    cam: &CameraParams<S>,
    gaussians: &GaussianSet<'_, S>,
    index: usize,
) -> Result<(Splat2d<S>, TileRect), Cull> {
    let k = gaussians.sh_coefficients();
    let mean = read3(gaussians.means, index);
    let cov = &gaussians.covariances[6 * index..6 * index + 6];
    let opacity = gaussians.opacities[index];
    let sh = &gaussians.sh[3 * k * index..3 * k * (index + 1)];
    let finite = mean.iter().chain(cov).chain(sh).all(|v| v.is_finite()) && opacity.is_finite();
    if !finite {
        return Err(Cull::NonFiniteInput);
    }
    let geo = geometry(cam, mean, cov)?;
    let [a, b, c] = geo.cov_2d;
    let det = a * c - b * b;
    if !(a.is_finite() && c.is_finite() && det.is_finite()) {
        return Err(Cull::NonFiniteProjection);
    }
    if !(a > S::ZERO && c > S::ZERO && det > S::ZERO) {
        return Err(Cull::Covariance);
    }
    let inv_det = S::ONE / det;
    let conic = [c * inv_det, -b * inv_det, a * inv_det];
    let inv_z = S::ONE / geo.p[2];
    let mean_2d = [
        cam.fx * geo.p[0] * inv_z + cam.cx,
        cam.fy * geo.p[1] * inv_z + cam.cy,
    ];
    if !conic.iter().chain(&mean_2d).all(|v| v.is_finite()) {
        return Err(Cull::NonFiniteProjection);
    }
    let threshold = S::from_f64(ALPHA_THRESHOLD);
    if opacity < threshold {
        return Err(Cull::Opacity);
    }
    let extent = (S::from_f64(2.0) * (S::from_f64(255.0) * opacity).ln())
        .max(S::ZERO)
        .sqrt()
        .min(S::from_f64(MAX_EXTENT_SIGMAS));
    let radius = [(extent * a.sqrt()).ceil(), (extent * c.sqrt()).ceil()];
    if !(radius[0] > S::ZERO && radius[1] > S::ZERO) {
        return Err(Cull::Offscreen);
    }
    let rect = tile_rect(cam, mean_2d, radius);
    if rect.x0 >= rect.x1 || rect.y0 >= rect.y1 {
        return Err(Cull::Offscreen);
    }
    let min_power = (threshold / opacity).ln() - S::from_f64(0.01);
    let (dir, _) = unit_view_direction(cam, mean);
    let basis = sh_basis(dir, gaussians.sh_degree, None);
    let colour = sh_colour_unclamped(sh, &basis).map(|v| v.max(S::ZERO));
    if !colour.iter().all(|v| v.is_finite()) {
        return Err(Cull::NonFiniteProjection);
    }
    Ok((
        Splat2d {
            mean: mean_2d,
            conic,
            opacity,
            colour,
            depth: geo.p[2],
            min_power,
            pixel_box: pixel_box(cam, mean_2d, radius),
            row_span: row_span_constants(mean_2d[0], conic, min_power),
        },
        rect,
    ))
}

/// See [`Splat2d::pixel_box`].
fn pixel_box<S: Scalar>(cam: &CameraParams<S>, mean: [S; 2], radius: [S; 2]) -> [u32; 4] {
    let range = |m: S, r: S, size: u32| {
        let (m, r) = (m.to_f64(), r.to_f64());
        let lo = (m - r - 1.0).floor().clamp(0.0, f64::from(size)) as u32;
        let hi = (m + r + 1.0).ceil().clamp(0.0, f64::from(size)) as u32;
        (lo, hi)
    };
    let (x_lo, x_hi) = range(mean[0], radius[0], cam.width);
    let (y_lo, y_hi) = range(mean[1], radius[1], cam.height);
    [x_lo, x_hi, y_lo, y_hi]
}

/// See [`Splat2d::row_span`].
pub(super) fn row_span_constants<S: Scalar>(mean_x: S, conic: [S; 3], min_power: S) -> [f64; 4] {
    let [a, b, c] = conic.map(|v| v.to_f64());
    let det = a * c - b * b;
    [
        mean_x.to_f64(),
        -b / a,
        -2.0 * min_power.to_f64() / a,
        det / (a * a),
    ]
}

/// `[floor((m - r) / 16), ceil((m + r) / 16))` per axis, clamped to the tile grid.
fn tile_rect<S: Scalar>(cam: &CameraParams<S>, mean: [S; 2], radius: [S; 2]) -> TileRect {
    let tile = f64::from(TILE_SIZE);
    let range = |m: S, r: S, tiles: u32| {
        let (m, r) = (m.to_f64(), r.to_f64());
        // `as` saturates, so huge boxes are clamped rather than wrapped.
        let lo = ((m - r) / tile).floor().clamp(0.0, f64::from(tiles)) as u32;
        let hi = ((m + r) / tile).ceil().clamp(0.0, f64::from(tiles)) as u32;
        (lo, hi)
    };
    let (x0, x1) = range(mean[0], radius[0], cam.tiles_x);
    let (y0, y1) = range(mean[1], radius[1], cam.tiles_y);
    TileRect { x0, y0, x1, y1 }
}

/// Gradient of the loss with respect to one camera's projected quantities of one Gaussian.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Splat2dGradient<S> {
    pub mean: [S; 2],
    pub conic: [S; 3],
    pub opacity: S,
    pub colour: [S; 3],
    pub depth: S,
}

/// Gradients of one Gaussian's inputs from one camera.
pub(super) struct InputGradient<S> {
    pub mean: [S; 3],
    pub covariance: [S; 6],
    pub opacity: S,
    /// `K x 3`, first `3K` entries used.
    pub sh: [S; 48],
}

/// Backward of [`project`] for a visible Gaussian.
pub(super) fn project_backward<S: Scalar>(
    cam: &CameraParams<S>,
    gaussians: &GaussianSet<'_, S>,
    index: usize,
    grad: &Splat2dGradient<S>,
) -> Option<InputGradient<S>> {
    let zero = S::ZERO;
    let k = gaussians.sh_coefficients();
    let mean = read3(gaussians.means, index);
    let cov = &gaussians.covariances[6 * index..6 * index + 6];
    let sh = &gaussians.sh[3 * k * index..3 * k * (index + 1)];
    // Only Gaussians the forward pass found visible come here, so this succeeds unless the
    // caller changed the Gaussians between the passes; then there is no gradient to give.
    let Ok(geo) = geometry(cam, mean, cov) else {
        return None;
    };
    let [x, y, z] = geo.p;
    let inv_z = S::ONE / z;
    let inv_z2 = inv_z * inv_z;
    let mut dp = [zero; 3];

    // mean_2d = (fx x / z + cx, fy y / z + cy); depth = z.
    dp[0] += grad.mean[0] * cam.fx * inv_z;
    dp[1] += grad.mean[1] * cam.fy * inv_z;
    dp[2] -= (grad.mean[0] * cam.fx * x + grad.mean[1] * cam.fy * y) * inv_z2;
    dp[2] += grad.depth;

    // conic = inverse(cov_2d): d cov_2d = -Q G Q with G the symmetric gradient of Q.
    let [a, b, c] = geo.cov_2d;
    let inv_det = S::ONE / (a * c - b * b);
    let q = [[c * inv_det, -b * inv_det], [-b * inv_det, a * inv_det]];
    let half = S::from_f64(0.5);
    let g = [
        [grad.conic[0], half * grad.conic[1]],
        [half * grad.conic[1], grad.conic[2]],
    ];
    let mut qg = [[zero; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            qg[i][j] = q[i][0] * g[0][j] + q[i][1] * g[1][j];
        }
    }
    // `ds` is the gradient with respect to the (symmetric) entries of cov_2d.
    let mut ds = [[zero; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            ds[i][j] = -(qg[i][0] * q[0][j] + qg[i][1] * q[1][j]);
        }
    }

    // cov_2d = J W J^T: dW = J^T dS J, dJ = 2 dS J W.
    let jm = geo.j;
    let mut dw = [[zero; 3]; 3];
    for (i, row) in dw.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let mut acc = zero;
            for r in 0..2 {
                for s in 0..2 {
                    acc += jm[r][i] * ds[r][s] * jm[s][j];
                }
            }
            *v = acc;
        }
    }
    let w = geo.cov_cam;
    let two = S::from_f64(2.0);
    let mut dj = [[zero; 3]; 2];
    for (r, row) in dj.iter_mut().enumerate() {
        for (col, v) in row.iter_mut().enumerate() {
            let mut acc = zero;
            for s in 0..2 {
                for m in 0..3 {
                    acc += ds[r][s] * jm[s][m] * w[m][col];
                }
            }
            *v = two * acc;
        }
    }
    // J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] with u = clamp(x/z), v = clamp(y/z).
    dp[2] -= dj[0][0] * cam.fx * inv_z2 + dj[1][1] * cam.fy * inv_z2;
    dp[2] += dj[0][2] * cam.fx * geo.u * inv_z2 + dj[1][2] * cam.fy * geo.v * inv_z2;
    let du = -dj[0][2] * cam.fx * inv_z;
    let dv = -dj[1][2] * cam.fy * inv_z;
    if geo.u_free {
        dp[0] += du * inv_z;
        dp[2] -= du * x * inv_z2;
    }
    if geo.v_free {
        dp[1] += dv * inv_z;
        dp[2] -= dv * y * inv_z2;
    }

    // W = R Sigma R^T: dSigma = R^T dW R, folded onto the upper triangle.
    let rot = &cam.rotation;
    let dsigma = mat_mul(&mat_mul(&transpose(rot), &dw), rot);
    let covariance = [
        dsigma[0][0],
        dsigma[0][1] + dsigma[1][0],
        dsigma[0][2] + dsigma[2][0],
        dsigma[1][1],
        dsigma[1][2] + dsigma[2][1],
        dsigma[2][2],
    ];

    // p = R mean + t.
    let mut d_mean = mat_t_vec(rot, dp);

    // Colour = max(0, sum_k sh_k Y_k(dir) + 0.5) with dir = (mean - centre) / |mean - centre|.
    let (dir, length) = unit_view_direction(cam, mean);
    let mut basis_grad = [[zero; 3]; 16];
    let basis = sh_basis(dir, gaussians.sh_degree, Some(&mut basis_grad));
    let unclamped = sh_colour_unclamped(sh, &basis);
    let d_colour: [S; 3] = std::array::from_fn(|ch| {
        if unclamped[ch] > zero {
            grad.colour[ch]
        } else {
            zero
        }
    });
    let mut d_sh = [zero; 48];
    let mut d_dir = [zero; 3];
    for kk in 0..k {
        let mut weight = zero;
        for ch in 0..3 {
            d_sh[3 * kk + ch] = basis[kk] * d_colour[ch];
            weight += sh[3 * kk + ch] * d_colour[ch];
        }
        for axis in 0..3 {
            d_dir[axis] += weight * basis_grad[kk][axis];
        }
    }
    let radial = d_dir[0] * dir[0] + d_dir[1] * dir[1] + d_dir[2] * dir[2];
    let inv_length = S::ONE / length;
    for axis in 0..3 {
        d_mean[axis] += (d_dir[axis] - dir[axis] * radial) * inv_length;
    }

    Some(InputGradient {
        mean: d_mean,
        covariance,
        opacity: grad.opacity,
        sh: d_sh,
    })
}
