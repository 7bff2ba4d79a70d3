//! Exact k-nearest-neighbour graph of a point set on a uniform grid.
//!
//! Used for the canonical template's vertex graph. Each point's list starts with the point
//! itself (distance 0), because training gathers the velocities of the `tau` template
//! vertices nearest to a Gaussian, and Gaussians start on the template vertices.
//! Ties are broken by the smaller index, so the graph is deterministic.

use rayon::prelude::*;

/// Neighbour indices and Euclidean distances, `(n_points, k)` each, row-major, nearest first.
#[derive(Clone, Debug, PartialEq)]
pub struct KnnGraph {
    pub k: usize,
    pub indices: Vec<u32>,
    pub distances: Vec<f32>,
}

/// Why a KNN graph could not be built.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum KnnError {
    #[error("k = {k} neighbours asked for but only {points} points exist")]
    TooFewPoints { k: usize, points: usize },
    #[error("k must be at least 1")]
    ZeroK,
    #[error("point {index} is not finite")]
    NotFinite { index: usize },
}

struct Grid {
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// Start of each cell's run in `order`; `starts[n_cells]` is the end.
    starts: Vec<usize>,
    order: Vec<u32>,
}

impl Grid {
    fn new(points: &[[f32; 3]], k: usize) -> Self {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in points {
            for c in 0..3 {
                lo[c] = lo[c].min(f64::from(p[c]));
                hi[c] = hi[c].max(f64::from(p[c]));
            }
        }
        let extent: Vec<f64> = (0..3).map(|c| (hi[c] - lo[c]).max(1e-9)).collect();
        let volume = extent[0] * extent[1] * extent[2];
        // About 2k points per occupied cell for a surface-like set; the cube root rule is a
        // starting point, capped so the grid stays small.
        let target_cells = (points.len() as f64 / (2.0 * k as f64)).clamp(1.0, 1.0e6);
        let mut cell = (volume / target_cells).cbrt();
        let max_extent = extent.iter().cloned().fold(0.0, f64::max);
        cell = cell.max(max_extent / 128.0).max(1e-9);
        // extent / cell <= 128, so every point lies inside its own cell (no clamping).
        let dims = [0, 1, 2].map(|c| (extent[c] / cell).floor() as usize + 1);
        let n_cells = dims[0] * dims[1] * dims[2];
        let mut grid = Self {
            origin: lo,
            cell,
            dims,
            starts: vec![0; n_cells + 1],
            order: vec![0; points.len()],
        };
        let cell_of: Vec<usize> = points.iter().map(|p| grid.cell_index(p)).collect();
        for &c in &cell_of {
            grid.starts[c + 1] += 1;
        }
        for c in 0..n_cells {
            grid.starts[c + 1] += grid.starts[c];
        }
        let mut fill = grid.starts.clone();
        for (i, &c) in cell_of.iter().enumerate() {
            grid.order[fill[c]] = i as u32;
            fill[c] += 1;
        }
        grid
    }

    fn coords(&self, p: &[f32; 3]) -> [usize; 3] {
        [0, 1, 2].map(|c| {
            let x = ((f64::from(p[c]) - self.origin[c]) / self.cell).floor();
            (x.max(0.0) as usize).min(self.dims[c] - 1)
        })
    }

    fn cell_index(&self, p: &[f32; 3]) -> usize {
        let [x, y, z] = self.coords(p);
        (z * self.dims[1] + y) * self.dims[0] + x
    }
}

/// Builds the exact `k`-nearest-neighbour graph (self included) of `points`.
pub fn knn_graph(points: &[[f32; 3]], k: usize) -> Result<KnnGraph, KnnError> {
    if k == 0 {
        return Err(KnnError::ZeroK);
    }
    if points.len() < k {
        return Err(KnnError::TooFewPoints {
            k,
            points: points.len(),
        });
    }
    if let Some(index) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(KnnError::NotFinite { index });
    }
    let grid = Grid::new(points, k);
    let rows: Vec<(Vec<u32>, Vec<f32>)> = (0..points.len())
        .into_par_iter()
        .map(|i| query(&grid, points, i, k))
        .collect();
    let mut indices = Vec::with_capacity(points.len() * k);
    let mut distances = Vec::with_capacity(points.len() * k);
    for (idx, dist) in rows {
        indices.extend(idx);
        distances.extend(dist);
    }
    Ok(KnnGraph {
        k,
        indices,
        distances,
    })
}

fn squared_distance(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    (0..3)
        .map(|c| {
            let d = f64::from(a[c]) - f64::from(b[c]);
            d * d
        })
        .sum()
}

/// Searches shells of cells of growing Chebyshev radius around the query's cell until the
/// k-th best distance is closer than anything an unvisited cell could hold.
fn query(grid: &Grid, points: &[[f32; 3]], i: usize, k: usize) -> (Vec<u32>, Vec<f32>) {
    let p = &points[i];
    let centre = grid.coords(p);
    // Sorted best list of (squared distance, index).
    let mut best: Vec<(f64, u32)> = Vec::with_capacity(k + 1);
    let max_radius = grid.dims.iter().copied().max().unwrap_or(1);
    for radius in 0..=max_radius {
        let lo = centre.map(|c| c as isize - radius as isize);
        let hi = centre.map(|c| c as isize + radius as isize);
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let on_shell = [x, y, z]
                        .iter()
                        .zip(lo.iter().zip(&hi))
                        .any(|(&v, (&l, &h))| v == l || v == h);
                    if !on_shell {
                        continue;
                    }
                    if x < 0 || y < 0 || z < 0 {
                        continue;
                    }
                    let (x, y, z) = (x as usize, y as usize, z as usize);
                    if x >= grid.dims[0] || y >= grid.dims[1] || z >= grid.dims[2] {
                        continue;
                    }
                    let cell = (z * grid.dims[1] + y) * grid.dims[0] + x;
                    for &j in &grid.order[grid.starts[cell]..grid.starts[cell + 1]] {
                        let d = squared_distance(p, &points[j as usize]);
                        let candidate = (d, j);
                        if best.len() == k && candidate >= best[k - 1] {
                            continue;
                        }
                        let at = best.partition_point(|b| *b < candidate);
                        best.insert(at, candidate);
                        best.truncate(k);
                    }
                }
            }
        }
        // Everything outside the visited cube is at least `radius * cell` away from `p`
        // (p lies inside the centre cell).
        if best.len() == k {
            let reach = radius as f64 * grid.cell;
            if best[k - 1].0 <= reach * reach {
                break;
            }
        }
    }
    (
        best.iter().map(|b| b.1).collect(),
        best.iter().map(|b| b.0.sqrt() as f32).collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute_force(points: &[[f32; 3]], k: usize) -> Vec<u32> {
        let mut out = Vec::new();
        for p in points {
            let mut all: Vec<(f64, u32)> = points
                .iter()
                .enumerate()
                .map(|(j, q)| (squared_distance(p, q), j as u32))
                .collect();
            all.sort_by(|a, b| a.partial_cmp(b).unwrap());
            out.extend(all[..k].iter().map(|x| x.1));
        }
        out
    }

    /// Deterministic pseudo-random points (a 64-bit LCG), on a shell like a body surface.
    fn shell_points(n: usize) -> Vec<[f32; 3]> {
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        (0..n)
            .map(|_| {
                let v = [next(), next(), next()];
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
                [
                    (v[0] / n * 0.3) as f32,
                    (v[1] / n * 0.9) as f32,
                    (v[2] / n * 0.2) as f32,
                ]
            })
            .collect()
    }

    #[test]
    fn matches_brute_force() {
        let points = shell_points(700);
        for k in [1, 6, 8] {
            let graph = knn_graph(&points, k).unwrap();
            assert_eq!(graph.indices, brute_force(&points, k), "k={k}");
            for i in 0..points.len() {
                assert_eq!(graph.indices[i * k], i as u32, "self first");
                assert_eq!(graph.distances[i * k], 0.0);
            }
        }
    }

    #[test]
    fn degenerate_sets() {
        // All points on a line, duplicates included.
        let points: Vec<[f32; 3]> = (0..50).map(|i| [(i / 2) as f32 * 0.01, 0.0, 0.0]).collect();
        let graph = knn_graph(&points, 3).unwrap();
        assert_eq!(graph.indices, brute_force(&points, 3));
        assert_eq!(
            knn_graph(&points[..2], 3),
            Err(KnnError::TooFewPoints { k: 3, points: 2 })
        );
        assert_eq!(knn_graph(&points, 0), Err(KnnError::ZeroK));
        let mut bad = points.clone();
        bad[7][1] = f32::NAN;
        assert_eq!(knn_graph(&bad, 2), Err(KnnError::NotFinite { index: 7 }));
        let single = knn_graph(&[[1.0, 2.0, 3.0]], 1).unwrap();
        assert_eq!(single.indices, vec![0]);
    }
}
