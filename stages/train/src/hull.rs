//! Gaussians where the images show a person but the body template has no surface: a loose
//! skirt, a coat's hem, hair. The body template's vertices are where training starts
//! (docs/method.md, "Init"); a skirt's Gaussians then have to travel from the thighs to the
//! hem, 10-20 cm, through the photometric loss alone. `hull_init` carves the visual hull of
//! a few training frames from their masks, keeps its outer surface where it is farther than
//! `min_distance` from the posed template, maps those points to the canonical space through
//! the inverse of the skinning at their nearest template vertex, and gives them the colour
//! the unoccluded training views see there.

use rayon::prelude::*;
use seqavatar_core::body::BodyParams;
use seqavatar_core::glam::{DAffine3, DVec3};
use serde::{Deserialize, Serialize};

use seqavatar_avatar::rig::{BodyRig, rows_to_affine};
use seqavatar_core::camera::Camera;
use seqavatar_knn::KnnGrid;

use crate::data::TrainingData;

/// The most voxels one frame's hull may have (16.8 M cells, 17 MB of occupancy).
pub const MAX_HULL_CELLS: usize = 1 << 24;

/// The `hull_init` train config: where to add Gaussians from the masks' visual hull (every
/// field has a default: `hull_init: {}` is the measured setting of docs/results.md).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HullInit {
    /// Training frames carved, spread evenly over the sequence.
    pub frames: usize,
    /// Voxel edge, metres.
    pub voxel: f64,
    /// Hull points closer than this (metres) to the posed template add nothing: the
    /// template's own Gaussians are there.
    pub min_distance: f64,
    /// The most Gaussians added (an even subset of the hull points beyond that).
    pub max_gaussians: usize,
}

impl Default for HullInit {
    fn default() -> Self {
        Self {
            frames: 4,
            voxel: 0.015,
            min_distance: 0.03,
            max_gaussians: 3000,
        }
    }
}

/// Largest [`HullInit::frames`].
pub const MAX_HULL_FRAMES: usize = 64;

impl HullInit {
    /// `(field, message)` of the first invalid field.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let bad = |field: &str, message: String| Err((format!("hull_init.{field}"), message));
        if !(1..=MAX_HULL_FRAMES).contains(&self.frames) {
            return bad(
                "frames",
                format!("must be in 1..={MAX_HULL_FRAMES}, got {}", self.frames),
            );
        }
        if !(self.voxel.is_finite() && (1e-3..=0.1).contains(&self.voxel)) {
            return bad(
                "voxel",
                format!("must be in [0.001, 0.1] m, got {}", self.voxel),
            );
        }
        if !(self.min_distance.is_finite() && (0.0..=0.5).contains(&self.min_distance)) {
            return bad(
                "min_distance",
                format!("must be in [0, 0.5] m, got {}", self.min_distance),
            );
        }
        Ok(())
    }
}

/// Canonical centres (`N x 3`) and colours in `[0, 1]` (`N x 3`) of the added Gaussians, and
/// the colour the images show at each template vertex (`None` where no view saw it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HullPoints {
    pub centres: Vec<f64>,
    pub colours: Vec<f64>,
    pub template_colours: Vec<Option<[f64; 3]>>,
}

/// How deep inside the hull (metres) a point may lie and still be seen: the visual hull of a
/// few views is centimetres wider than the body it wraps.
const SURFACE_DEPTH: f64 = 0.05;

/// Room left around the posed template's bounding box for what it does not cover.
const MARGIN: f64 = 0.3;

/// One frame's skinning at the template vertices: `y = A (B^-1 (x - b) + o) + a`.
struct VertexSkinning {
    /// Blended target transforms per vertex.
    target: Vec<DAffine3>,
    /// Blended canonical transforms per vertex.
    canonical: Vec<DAffine3>,
    /// Rest-space offsets per vertex.
    offsets: Vec<DVec3>,
}

/// The weighted sum of row-major 3 x 4 joint transforms, as the skinning blends them.
fn blend(joints: &[[f64; 12]], weights: &[f64]) -> DAffine3 {
    let mut sum = [0.0; 12];
    for (w, rows) in weights.iter().zip(joints) {
        for e in 0..12 {
            sum[e] += w * rows[e];
        }
    }
    rows_to_affine(&sum)
}

impl VertexSkinning {
    /// The skinning of frame `params` at every template vertex, with the rig's (possibly
    /// diffused) template weights, as training skins a Gaussian with zero weight offsets.
    fn new(rig: &BodyRig, params: &BodyParams) -> anyhow::Result<Self> {
        let pose = rig.pose(params)?;
        let joints = rig.joint_count();
        let weights: Vec<&[f64]> = rig.template_weights.chunks_exact(joints).collect();
        let normalised = |w: &[f64]| -> Vec<f64> {
            // softmax(log(w + eps)) as the skinning takes it.
            let eps = seqavatar_avatar::skinning::WEIGHT_LOG_EPS;
            let total: f64 = w.iter().map(|v| v + eps).sum();
            w.iter().map(|v| (v + eps) / total).collect()
        };
        let (target, canonical): (Vec<_>, Vec<_>) = weights
            .par_iter()
            .map(|w| {
                let w = normalised(w);
                (
                    blend(&pose.target_joints, &w),
                    blend(&rig.canonical_joints, &w),
                )
            })
            .unzip();
        let offsets = pose
            .vertex_offsets
            .chunks_exact(3)
            .map(|o| DVec3::new(o[0], o[1], o[2]))
            .collect();
        Ok(Self {
            target,
            canonical,
            offsets,
        })
    }

    /// A canonical point skinned with vertex `v`'s transforms.
    fn forward(&self, v: usize, canonical: DVec3) -> DVec3 {
        let (a, b) = (self.target[v], self.canonical[v]);
        a.matrix3 * (b.matrix3.inverse() * (canonical - b.translation) + self.offsets[v])
            + a.translation
    }

    /// The canonical point that vertex `v`'s transforms skin to `world`.
    fn inverse(&self, v: usize, world: DVec3) -> DVec3 {
        let (a, b) = (self.target[v], self.canonical[v]);
        b.matrix3 * (a.matrix3.inverse() * (world - a.translation) - self.offsets[v])
            + b.translation
    }
}

/// A voxel grid over a box.
struct Grid {
    origin: DVec3,
    voxel: f64,
    dims: [usize; 3],
}

impl Grid {
    fn cells(&self) -> usize {
        self.dims.iter().product()
    }

    fn centre(&self, cell: usize) -> DVec3 {
        let [nx, ny, _] = self.dims;
        let (x, y, z) = (cell % nx, (cell / nx) % ny, cell / (nx * ny));
        self.origin + (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * self.voxel
    }

    fn cell_of(&self, point: DVec3) -> Option<usize> {
        let local = (point - self.origin) / self.voxel;
        let [nx, ny, nz] = self.dims;
        if local.min_element() < 0.0 {
            return None;
        }
        let (x, y, z) = (local.x as usize, local.y as usize, local.z as usize);
        (x < nx && y < ny && z < nz).then_some(x + nx * (y + ny * z))
    }

    /// Whether `cell` has a 6-neighbour outside `occupied` (or lies on the grid's border).
    fn on_surface(&self, occupied: &[bool], cell: usize) -> bool {
        let [nx, ny, nz] = self.dims;
        let (x, y, z) = (cell % nx, (cell / nx) % ny, cell / (nx * ny));
        if x == 0 || y == 0 || z == 0 || x + 1 == nx || y + 1 == ny || z + 1 == nz {
            return true;
        }
        [1, nx, nx * ny]
            .iter()
            .any(|&step| !occupied[cell - step] || !occupied[cell + step])
    }
}

/// One view of a frame: its camera, image and mask at the training resolution.
pub struct HullView<'a> {
    pub camera: &'a Camera,
    /// `H x W x 3` bytes.
    pub rgb: &'a [u8],
    /// `H x W` bytes, 255 = foreground.
    pub mask: &'a [u8],
}

impl HullView<'_> {
    /// The pixel index `point` falls on, `None` behind the camera or outside the image.
    fn pixel(&self, point: DVec3) -> Option<usize> {
        let p = self.camera.project(point)?;
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        (p.x >= 0.0 && p.y >= 0.0 && p.x < w && p.y < h)
            .then(|| p.y as usize * self.camera.width as usize + p.x as usize)
    }
}

/// The visual hull of `views` over `grid`: a cell is occupied when at least two views see
/// its centre and every view that sees it has it inside the mask.
fn carve(grid: &Grid, views: &[HullView<'_>]) -> Vec<bool> {
    (0..grid.cells())
        .into_par_iter()
        .map(|cell| {
            let centre = grid.centre(cell);
            let mut seen = 0;
            for view in views {
                if let Some(pixel) = view.pixel(centre) {
                    if view.mask[pixel] < 128 {
                        return false;
                    }
                    seen += 1;
                }
            }
            seen >= 2
        })
        .collect()
}

/// The mean colour of `point` over the views whose line of sight leaves the hull within
/// `SURFACE_DEPTH` and does not enter it again, and whether there was such a view; over every
/// view that sees it when none does (grey when no view sees it).
fn colour(
    grid: &Grid,
    occupied: &[bool],
    views: &[HullView<'_>],
    point: DVec3,
) -> ([f64; 3], bool) {
    let mut sums = [[0.0; 3], [0.0; 3]];
    let mut counts = [0usize; 2];
    for view in views {
        let Some(pixel) = view.pixel(point) else {
            continue;
        };
        let towards = view.camera.center() - point;
        let distance = towards.length();
        let step = towards / distance * grid.voxel;
        // A template vertex lies inside the hull's padding and a hull point on its surface:
        // the ray may cross `SURFACE_DEPTH` of occupied cells before it leaves; more, or
        // any occupied cell after that, hides the point.
        let (mut occluded, mut left) = (false, false);
        let (mut probe, mut travelled) = (point, 0.0);
        loop {
            probe += step;
            travelled += grid.voxel;
            let Some(cell) = grid.cell_of(probe).filter(|_| travelled < distance) else {
                break;
            };
            if !occupied[cell] {
                left = true;
            } else if left || travelled > SURFACE_DEPTH {
                occluded = true;
                break;
            }
        }
        let slot = usize::from(occluded);
        for c in 0..3 {
            sums[slot][c] += f64::from(view.rgb[3 * pixel + c]) / 255.0;
        }
        counts[slot] += 1;
    }
    match counts {
        [0, 0] => ([0.5; 3], false),
        [0, n] => (sums[1].map(|s| s / n as f64), false),
        [n, _] => (sums[0].map(|s| s / n as f64), true),
    }
}

/// What one frame's hull gives: hull points in the canonical space with their colours, and
/// the colour each template vertex shows (with whether a view saw it unoccluded).
struct FrameHull {
    points: Vec<([f64; 3], [f64; 3])>,
    template_colours: Vec<([f64; 3], bool)>,
}

/// Hull points of one frame in the canonical space, with their colours.
fn frame_points(
    rig: &BodyRig,
    params: &BodyParams,
    views: &[HullView<'_>],
    init: &HullInit,
) -> anyhow::Result<FrameHull> {
    let skinning = VertexSkinning::new(rig, params)?;
    let posed: Vec<[f64; 3]> = rig
        .canonical_vertices
        .chunks_exact(3)
        .enumerate()
        .map(|(v, c)| skinning.forward(v, DVec3::new(c[0], c[1], c[2])).to_array())
        .collect();
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in &posed {
        lo = lo.min(DVec3::from(*p));
        hi = hi.max(DVec3::from(*p));
    }
    let origin = lo - MARGIN;
    let size = hi - lo + 2.0 * MARGIN;
    let dims = (size / init.voxel)
        .ceil()
        .to_array()
        .map(|d| d.max(1.0) as usize);
    let grid = Grid {
        origin,
        voxel: init.voxel,
        dims,
    };
    anyhow::ensure!(
        dims.iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .is_some_and(|n| n <= MAX_HULL_CELLS),
        "train config field `hull_init.voxel`: {} m gives {dims:?} voxels over the body's box \
         ({:.2} x {:.2} x {:.2} m), over the cap of {MAX_HULL_CELLS}: raise it",
        init.voxel,
        size.x,
        size.y,
        size.z
    );
    let occupied = carve(&grid, views);
    let template = KnnGrid::new(&posed, 4.0);
    let surface: Vec<usize> = (0..grid.cells())
        .into_par_iter()
        .filter(|&cell| occupied[cell] && grid.on_surface(&occupied, cell))
        .collect();
    let points = surface
        .par_iter()
        .filter_map(|&cell| {
            let centre = grid.centre(cell);
            let v = template.query(&centre.to_array(), 1)[0] as usize;
            let distance = (centre - DVec3::from(posed[v])).length();
            // A blended transform near singular (weights split between opposed joint
            // rotations) maps a point to no finite canonical position: it adds nothing.
            let canonical = skinning.inverse(v, centre);
            (distance > init.min_distance && canonical.is_finite()).then(|| {
                (
                    canonical.to_array(),
                    colour(&grid, &occupied, views, centre).0,
                )
            })
        })
        .collect();
    let template_colours = posed
        .par_iter()
        .map(|p| colour(&grid, &occupied, views, DVec3::from(*p)))
        .collect();
    Ok(FrameHull {
        points,
        template_colours,
    })
}

/// The Gaussians `init` adds, and the template Gaussians' colours: hull points of
/// `init.frames` training frames spread over the sequence, merged on a canonical grid of the
/// same voxel (the first point of a cell kept), then an even subset of at most
/// `init.max_gaussians`; each template vertex's colour is its mean over the frames where a
/// view saw it unoccluded (`None` where none did).
pub fn hull_gaussians(data: &TrainingData, init: &HullInit) -> anyhow::Result<HullPoints> {
    let vertices = data.rig.vertex_count();
    let mut frames: Vec<usize> = data
        .images
        .iter()
        .filter(|image| image.split == 0)
        .map(|image| image.frame)
        .collect();
    frames.sort_unstable();
    frames.dedup();
    let count = init.frames.min(frames.len());
    let chosen: Vec<usize> = (0..count)
        .map(|k| frames[k * frames.len() / count])
        .collect();
    let mut merged: std::collections::BTreeMap<[i64; 3], ([f64; 3], [f64; 3])> =
        std::collections::BTreeMap::new();
    let mut template_sums = vec![([0.0; 3], 0usize); vertices];
    for &frame in &chosen {
        let views: Vec<HullView<'_>> = data
            .images
            .iter()
            .filter(|image| image.split == 0 && image.frame == frame)
            .map(|image| HullView {
                camera: &data.cameras[image.view],
                rgb: &image.rgb,
                mask: &image.mask,
            })
            .collect();
        let hull = frame_points(&data.rig, &data.params[frame], &views, init)?;
        for (centre, colour) in hull.points {
            let key = centre.map(|c| (c / init.voxel).floor() as i64);
            merged.entry(key).or_insert((centre, colour));
        }
        for ((sum, n), (colour, seen)) in template_sums.iter_mut().zip(hull.template_colours) {
            if seen {
                for c in 0..3 {
                    sum[c] += colour[c];
                }
                *n += 1;
            }
        }
    }
    let points: Vec<([f64; 3], [f64; 3])> = merged.into_values().collect();
    let keep = points.len().min(init.max_gaussians);
    let mut out = HullPoints {
        template_colours: template_sums
            .into_iter()
            .map(|(sum, n)| (n > 0).then(|| sum.map(|s| s / n as f64)))
            .collect(),
        ..HullPoints::default()
    };
    for k in 0..keep {
        let (centre, colour) = points[k * points.len() / keep];
        out.centres.extend(centre);
        out.colours.extend(colour);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::camera::Intrinsics;

    const RADIUS: f64 = 0.3;
    const DISTANCE: f64 = 2.0;
    const SIZE: u32 = 96;

    /// Cameras on the six axes at `DISTANCE` from the origin, looking at it.
    fn axis_cameras() -> Vec<Camera> {
        let f = 120.0;
        let intrinsics = Intrinsics {
            fx: f,
            fy: f,
            cx: f64::from(SIZE) / 2.0,
            cy: f64::from(SIZE) / 2.0,
        };
        [
            DVec3::X,
            -DVec3::X,
            DVec3::Y,
            -DVec3::Y,
            DVec3::Z,
            -DVec3::Z,
        ]
        .iter()
        .map(|&axis| {
            let up = if axis.y.abs() > 0.5 {
                DVec3::Z
            } else {
                DVec3::Y
            };
            Camera::look_at(SIZE, SIZE, intrinsics, axis * DISTANCE, DVec3::ZERO, up)
        })
        .collect()
    }

    /// The mask of a sphere of `RADIUS` at the origin: the pixels whose ray through the
    /// pixel's centre passes within `RADIUS` of it. Each camera's image is one flat colour.
    fn sphere_views(cameras: &[Camera]) -> Vec<(Vec<u8>, Vec<u8>)> {
        cameras
            .iter()
            .enumerate()
            .map(|(k, camera)| {
                let Intrinsics { fx, fy, cx, cy } = camera.intrinsics;
                let mut mask = vec![0u8; (SIZE * SIZE) as usize];
                for row in 0..SIZE as usize {
                    for col in 0..SIZE as usize {
                        let ray_camera = DVec3::new(
                            (col as f64 + 0.5 - cx) / fx,
                            (row as f64 + 0.5 - cy) / fy,
                            1.0,
                        );
                        let ray = (camera.rotation.transpose() * ray_camera).normalize();
                        let eye = camera.center();
                        let closest = eye - ray * eye.dot(ray);
                        if closest.length() < RADIUS {
                            mask[row * SIZE as usize + col] = 255;
                        }
                    }
                }
                let rgb = [40 * k as u8, 255 - 40 * k as u8, 7].repeat((SIZE * SIZE) as usize);
                (rgb, mask)
            })
            .collect()
    }

    fn hull_views<'a>(
        cameras: &'a [Camera],
        images: &'a [(Vec<u8>, Vec<u8>)],
    ) -> Vec<HullView<'a>> {
        cameras
            .iter()
            .zip(images)
            .map(|(camera, (rgb, mask))| HullView { camera, rgb, mask })
            .collect()
    }

    fn grid() -> Grid {
        let voxel = 0.02;
        Grid {
            origin: DVec3::splat(-0.5),
            voxel,
            dims: [50; 3],
        }
    }

    /// The hull of a sphere seen from the six axes is the intersection of the six cones
    /// tangent to it (half-angle `asin(R / D)` about each camera's axis): every cell centre
    /// clearly inside all cones is kept, every one clearly outside one is carved, and the
    /// sphere itself is always inside.
    #[test]
    fn carving_a_sphere_gives_the_intersection_of_its_tangent_cones() {
        let cameras = axis_cameras();
        let images = sphere_views(&cameras);
        let views = hull_views(&cameras, &images);
        let grid = grid();
        let occupied = carve(&grid, &views);
        let half_angle = (RADIUS / DISTANCE).asin();
        // Two pixels of slack: the masks sample the silhouette at pixel centres.
        let slack = 2.0 / 120.0;
        let (mut inside, mut outside) = (0, 0);
        for cell in 0..grid.cells() {
            let p = grid.centre(cell);
            let margin = cameras
                .iter()
                .map(|camera| {
                    let axis = (-camera.center()).normalize();
                    let angle = (p - camera.center()).normalize().dot(axis).acos();
                    half_angle - angle
                })
                .fold(f64::INFINITY, f64::min);
            if margin > slack {
                assert!(occupied[cell], "cell at {p} is inside every cone");
                inside += 1;
            } else if margin < -slack {
                assert!(!occupied[cell], "cell at {p} is outside a cone");
                outside += 1;
            }
            if p.length() < RADIUS - grid.voxel {
                assert!(occupied[cell], "cell at {p} is inside the sphere");
            }
        }
        assert!(inside > 1000 && outside > 1000, "{inside} / {outside}");
    }

    /// A point on the sphere facing the +x camera takes its colour from the cameras that see
    /// it, never from the -x camera, whose view of it the sphere blocks.
    #[test]
    fn colours_come_from_the_views_that_see_the_point() {
        let cameras = axis_cameras();
        let images = sphere_views(&cameras);
        let views = hull_views(&cameras, &images);
        let grid = grid();
        let occupied = carve(&grid, &views);
        let point = DVec3::new(RADIUS - 0.01, 0.0, 0.0);
        let (seen_colour, seen) = colour(&grid, &occupied, &views, point);
        assert!(seen);
        // Camera k's image is (40 k, 255 - 40 k, 7) / 255: +x is camera 0, -x camera 1.
        let own = [0.0, 1.0, 7.0 / 255.0];
        assert!(
            (0..3).all(|c| (seen_colour[c] - own[c]).abs() < 1e-12),
            "{seen_colour:?}: only the +x camera sees the point head-on"
        );
        // The sphere's centre is deeper than `SURFACE_DEPTH` for every view.
        let (_, seen) = colour(&grid, &occupied, &views, DVec3::ZERO);
        assert!(!seen);
    }

    /// The per-vertex skinning is the training's skinning (`skin_forward` with zero weight
    /// offsets at that vertex) on a posed, moved and turned procedural body with diffused
    /// weights, and `inverse` undoes it.
    #[test]
    fn vertex_skinning_is_the_training_skinning_and_inverts() {
        use seqavatar_avatar::skinning::{GaussianParams, skin_forward};
        let mut rig =
            BodyRig::new(seqavatar_core::body::procedural::procedural_body(0.05)).unwrap();
        rig.smooth_template_weights(0.1);
        let mut params = rig.model.zero_params();
        for (j, rotation) in params.pose.iter_mut().enumerate() {
            *rotation = DVec3::new(0.1 * (j as f64).sin(), 0.2, -0.05 * j as f64 / 10.0);
        }
        params.world_rotation = DVec3::new(0.3, -1.2, 0.4);
        params.world_translation = DVec3::new(1.5, -0.2, 3.0);
        let skinning = VertexSkinning::new(&rig, &params).unwrap();
        let pose = rig.pose(&params).unwrap();
        let frame = rig.frame(&pose, 1e-5, 0.5);
        let vertices = rig.vertex_count();
        for v in (0..vertices).step_by(vertices / 37) {
            let c = &rig.canonical_vertices[3 * v..3 * v + 3];
            let canonical = DVec3::new(c[0] + 0.03, c[1] - 0.02, c[2] + 0.05);
            let expected = skin_forward(
                &frame,
                &GaussianParams {
                    positions: &canonical.to_array(),
                    log_scales: &[-4.0; 3],
                    d_scales: &[0.0; 3],
                    rotations: &[1.0, 0.0, 0.0, 0.0],
                    d_rotations: &[1.0, 0.0, 0.0, 0.0],
                    weight_offsets: None,
                    nearest: &[v as u32],
                },
            )
            .positions;
            let world = skinning.forward(v, canonical);
            assert!(
                (world - DVec3::from_slice(&expected)).length() < 1e-12,
                "vertex {v}: {world} against {expected:?}"
            );
            assert!((skinning.inverse(v, world) - canonical).length() < 1e-12);
        }
    }
}
