//! Exact k-nearest-neighbour search in 3D on the CPU: a uniform grid searched in growing
//! shells, parallel over queries (rayon), and the brute-force reference it is tested against.
//! The project's one grid KNN: the motion stage's canonical template graph ([`knn_graph`]),
//! the avatar's nearest template vertices and training's AIAP neighbours all use it.
//!
//! Results are sorted by (squared distance, index), so ties resolve the same way in both
//! searches and on every run.

use rayon::prelude::*;
use std::sync::Mutex;

/// A uniform grid over reference points for repeated k-nearest queries.
pub struct KnnGrid {
    points: Vec<[f64; 3]>,
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// Start of each cell's run in `order` (length cells + 1).
    cell_start: Vec<usize>,
    /// Point indices sorted by cell.
    order: Vec<u32>,
    /// How far (per axis) a point may lie outside its cell's box through the rounding of
    /// [`Self::cell_coords`]: the cell skip test of [`Self::query`] grows the boxes by it.
    slack: f64,
    /// [`Self::query_all_tracked`]'s lists for the last query set it was given.
    tracked: Mutex<CandidateLists>,
}

impl KnnGrid {
    /// Builds the grid with about `points_per_cell` points per occupied cell. Non-finite
    /// points are never returned as neighbours.
    pub fn new(points: &[[f64; 3]], points_per_cell: f64) -> Self {
        let finite: Vec<&[f64; 3]> = points
            .iter()
            .filter(|p| p.iter().all(|v| v.is_finite()))
            .collect();
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &finite {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        if finite.is_empty() {
            lo = [0.0; 3];
            hi = [0.0; 3];
        }
        let extent: Vec<f64> = (0..3).map(|a| (hi[a] - lo[a]).max(1e-9)).collect();
        let volume = extent.iter().product::<f64>();
        let count = finite.len().max(1) as f64;
        let mut cell = (volume * points_per_cell / count).cbrt();
        // Flat clouds give a tiny volume: never let one axis need more than 256 cells.
        let max_extent = extent.iter().cloned().fold(0.0, f64::max);
        cell = cell.max(max_extent / 256.0).max(1e-9);
        let dims: [usize; 3] =
            std::array::from_fn(|a| ((extent[a] / cell).floor() as usize + 1).max(1));
        let cells = dims[0] * dims[1] * dims[2];
        let magnitude = lo.iter().chain(&hi).fold(0.0_f64, |m, v| m.max(v.abs()));
        let mut grid = Self {
            points: points.to_vec(),
            origin: lo,
            cell,
            dims,
            cell_start: vec![0; cells + 1],
            order: Vec::with_capacity(finite.len()),
            // Far above the rounding of `(p - origin) / cell` and of the box corners.
            slack: 1e-6 * cell + 1e-12 * magnitude,
            tracked: Mutex::default(),
        };
        let cell_of: Vec<Option<usize>> = points
            .iter()
            .map(|p| {
                p.iter()
                    .all(|v| v.is_finite())
                    .then(|| grid.flat(grid.cell_coords(p)))
            })
            .collect();
        for c in cell_of.iter().flatten() {
            grid.cell_start[c + 1] += 1;
        }
        for c in 0..cells {
            grid.cell_start[c + 1] += grid.cell_start[c];
        }
        let mut cursor = grid.cell_start.clone();
        grid.order = vec![0; grid.cell_start[cells]];
        for (i, c) in cell_of.iter().enumerate() {
            if let Some(c) = c {
                grid.order[cursor[*c]] = i as u32;
                cursor[*c] += 1;
            }
        }
        grid
    }

    fn cell_coords(&self, p: &[f64; 3]) -> [usize; 3] {
        std::array::from_fn(|a| {
            let v = ((p[a] - self.origin[a]) / self.cell).floor();
            if v.is_nan() || v < 0.0 {
                0
            } else {
                (v as usize).min(self.dims[a] - 1)
            }
        })
    }

    fn flat(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// The `k` nearest reference points of `query` (fewer when there are fewer points),
    /// nearest first.
    pub fn query(&self, query: &[f64; 3], k: usize) -> Vec<u32> {
        let mut best: Vec<(f64, u32)> = Vec::with_capacity(k + 1);
        if k == 0 || self.order.is_empty() || !query.iter().all(|v| v.is_finite()) {
            return Vec::new();
        }
        let centre = self.cell_coords(query);
        let max_radius = self.dims.iter().copied().max().unwrap_or(1);
        for radius in 0..=max_radius {
            let lo: [isize; 3] = std::array::from_fn(|a| centre[a] as isize - radius as isize);
            let hi: [isize; 3] = std::array::from_fn(|a| centre[a] as isize + radius as isize);
            for z in lo[2].max(0)..=hi[2].min(self.dims[2] as isize - 1) {
                for y in lo[1].max(0)..=hi[1].min(self.dims[1] as isize - 1) {
                    for x in lo[0].max(0)..=hi[0].min(self.dims[0] as isize - 1) {
                        let on_shell = [x, y, z]
                            .iter()
                            .zip(lo.iter().zip(hi.iter()))
                            .any(|(v, (l, h))| v == l || v == h);
                        if !on_shell {
                            continue;
                        }
                        // With k candidates, a cell whose box lies farther than the k-th
                        // cannot hold a better one (ties included: they are farther too).
                        if best.len() == k && self.box_distance2(query, [x, y, z]) > best[k - 1].0 {
                            continue;
                        }
                        let c = self.flat([x as usize, y as usize, z as usize]);
                        for &i in &self.order[self.cell_start[c]..self.cell_start[c + 1]] {
                            let d = dist2(query, &self.points[i as usize]);
                            insert_sorted(&mut best, (d, i), k);
                        }
                    }
                }
            }
            if best.len() == k {
                // Any point outside the searched cube is at least this far away.
                let mut clearance = f64::INFINITY;
                for a in 0..3 {
                    let cube_lo = self.origin[a] + lo[a] as f64 * self.cell;
                    let cube_hi = self.origin[a] + (hi[a] + 1) as f64 * self.cell;
                    // Cells beyond the grid hold nothing, so those sides never limit.
                    if lo[a] > 0 {
                        clearance = clearance.min(query[a] - cube_lo);
                    }
                    if hi[a] < self.dims[a] as isize - 1 {
                        clearance = clearance.min(cube_hi - query[a]);
                    }
                }
                if clearance.is_infinite()
                    || (clearance > 0.0 && best[k - 1].0 < clearance * clearance)
                {
                    break;
                }
            }
        }
        best.into_iter().map(|(_, i)| i).collect()
    }

    /// Squared distance from `query` to the box of cell `c` grown by [`Self::slack`]: no
    /// point of the cell is nearer.
    fn box_distance2(&self, query: &[f64; 3], c: [isize; 3]) -> f64 {
        let mut sum = 0.0;
        for a in 0..3 {
            let lo = self.origin[a] + c[a] as f64 * self.cell - self.slack;
            let hi = self.origin[a] + (c[a] + 1) as f64 * self.cell + self.slack;
            let gap = (lo - query[a]).max(query[a] - hi).max(0.0);
            sum += gap * gap;
        }
        sum
    }

    /// `k` nearest neighbours of every query, flattened `queries x k` (parallel).
    /// Panics if fewer than `k` finite reference points exist; see [`Self::reference_count`].
    pub fn query_all(&self, queries: &[[f64; 3]], k: usize) -> Vec<u32> {
        assert!(
            self.order.len() >= k,
            "k = {k} exceeds the {} reference points",
            self.order.len()
        );
        queries
            .par_iter()
            .flat_map_iter(|q| {
                let mut row = self.query(q, k);
                // A non-finite query gets the first reference point repeated: its result is
                // defined and it cannot index out of range.
                row.resize(k, self.order[0]);
                row
            })
            .collect()
    }

    /// [`Self::query_all`] for a query set that moves a little between calls (the
    /// canonical Gaussians, whose nearest template vertices training and rendering look up
    /// every frame): the same result, from candidate lists kept in the grid
    /// ([`CandidateLists`]) while no query has moved beyond their margin. The lists follow the
    /// last query set given; another set (or a call while another thread holds them) takes
    /// the full search, so any mix of callers gets exact results.
    pub fn query_all_tracked(&self, queries: &[[f64; 3]], k: usize) -> Vec<u32> {
        let Ok(mut lists) = self.tracked.try_lock() else {
            return self.query_all(queries, k);
        };
        lists.nearest(queries, Some(self), k, DEFAULT_MARGIN_FRACTION)
    }

    /// Full searches and calls of [`Self::query_all_tracked`] so far.
    pub fn tracked_searches(&self) -> (u64, u64) {
        self.tracked
            .lock()
            .map_or((0, 0), |lists| (lists.rebuilds, lists.calls))
    }

    /// Number of finite reference points.
    pub fn reference_count(&self) -> usize {
        self.order.len()
    }

    /// Every finite reference point within `radius` of `query` (distance <= radius), in no
    /// particular order; empty for a non-finite query or radius.
    pub fn within(&self, query: &[f64; 3], radius: f64) -> Vec<u32> {
        let mut found = Vec::new();
        if self.order.is_empty() || !query.iter().all(|v| v.is_finite()) || !radius.is_finite() {
            return found;
        }
        let radius = radius.max(0.0);
        // The cells whose (slack-grown) boxes can reach the ball; `cell_coords` clamps to
        // the grid, which holds every finite point.
        let lo = self.cell_coords(&std::array::from_fn(|a| query[a] - radius - self.slack));
        let hi = self.cell_coords(&std::array::from_fn(|a| query[a] + radius + self.slack));
        let limit = radius * radius;
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let c = self.flat([x, y, z]);
                    for &i in &self.order[self.cell_start[c]..self.cell_start[c + 1]] {
                        if dist2(query, &self.points[i as usize]) <= limit {
                            found.push(i);
                        }
                    }
                }
            }
        }
        found
    }
}

/// Candidate lists for queries that move a little between calls (a Verlet list): the one
/// mechanism behind [`MovingKnn`] (a point set among itself) and [`KnnGrid::query_all_tracked`]
/// (moving queries against fixed reference points).
///
/// A rebuild searches the grid and keeps, for each query `i`, every reference point within
/// `d_k(i) + reach x margin` of it, `d_k(i)` being its k-th neighbour's distance then. While
/// no query (and, for a set among itself, no reference point) has moved more than `margin`
/// from where it was at the rebuild, the current k nearest of `i` are among those candidates:
/// with fixed references its old k nearest are now within `d_k(i) + margin`, so every current
/// neighbour is, and was within `d_k(i) + 2 margin` of the old query (`reach` 2); when the
/// references move too, `d_k(i) + 2 margin` and `d_k(i) + 4 margin` (`reach` 4). Selecting
/// the k best candidates by (squared distance, index) then gives exactly what the full grid
/// search gives, ties included.
#[derive(Default)]
struct CandidateLists {
    k: usize,
    /// Query positions at the last rebuild.
    anchor: Vec<[f64; 3]>,
    margin: f64,
    /// Start of each query's run in `candidates` (length queries + 1).
    start: Vec<usize>,
    candidates: Vec<u32>,
    rebuilds: u64,
    calls: u64,
}

impl CandidateLists {
    /// Whether the lists still hold every query's k nearest: same count, same `k`, no query
    /// moved beyond the margin.
    fn valid_for(&self, queries: &[[f64; 3]], k: usize) -> bool {
        self.anchor.len() == queries.len()
            && self.k == k
            && !self
                .anchor
                .par_iter()
                .zip(queries.par_iter())
                .any(|(a, q)| dist2(a, q) > self.margin * self.margin)
    }

    /// The k best candidates of every query, flattened `queries x k`.
    fn select(&self, queries: &[[f64; 3]], references: &[[f64; 3]], k: usize) -> Vec<u32> {
        queries
            .par_iter()
            .enumerate()
            .flat_map_iter(|(i, q)| {
                let mut best = Vec::with_capacity(k + 1);
                for &j in &self.candidates[self.start[i]..self.start[i + 1]] {
                    insert_sorted(&mut best, (dist2(q, &references[j as usize]), j), k);
                }
                best.into_iter().map(|(_, j)| j)
            })
            .collect()
    }

    /// The `k` nearest of every query, flattened `queries x k`: among `fixed`'s points, or
    /// with `None` among the queries themselves. From the lists while they are valid, else by
    /// a full search that rebuilds them; `k = 0` or a non-finite query takes the full search
    /// and forgets the lists.
    fn nearest(
        &mut self,
        queries: &[[f64; 3]],
        fixed: Option<&KnnGrid>,
        k: usize,
        margin_fraction: f64,
    ) -> Vec<u32> {
        self.calls += 1;
        // Checked first: a NaN displacement would pass `valid_for`'s comparison.
        let finite = queries.iter().all(|q| q.iter().all(|v| v.is_finite()));
        if k > 0 && finite && self.valid_for(queries, k) {
            let references = fixed.map_or(queries, |grid| grid.points.as_slice());
            return self.select(queries, references, k);
        }
        let own;
        let grid = match fixed {
            Some(grid) => grid,
            None => {
                own = KnnGrid::new(queries, 4.0);
                &own
            }
        };
        if k == 0 || !finite {
            self.anchor.clear();
            return grid.query_all(queries, k);
        }
        // Fixed references: a query's old neighbours are at most one margin farther now;
        // references that move too add another (see the type's comment).
        let reach = if fixed.is_some() { 2.0 } else { 4.0 };
        self.rebuild(grid, queries, k, margin_fraction, reach)
    }

    /// A full search of `grid`, whose result it returns, and new lists around it; the
    /// margin is `margin_fraction` x the mean k-th-neighbour distance.
    fn rebuild(
        &mut self,
        grid: &KnnGrid,
        queries: &[[f64; 3]],
        k: usize,
        margin_fraction: f64,
        reach: f64,
    ) -> Vec<u32> {
        self.rebuilds += 1;
        let nearest = grid.query_all(queries, k);
        let kth: Vec<f64> = nearest
            .par_chunks(k)
            .zip(queries.par_iter())
            .map(|(row, q)| dist2(q, &grid.points[row[k - 1] as usize]).sqrt())
            .collect();
        let mean = kth.iter().sum::<f64>() / kth.len().max(1) as f64;
        self.margin = margin_fraction * mean;
        let margin = self.margin;
        let lists: Vec<Vec<u32>> = queries
            .par_iter()
            .zip(kth.par_iter())
            // Grown by a relative 1e-9 so that rounding in the distances never drops a point
            // the argument above includes.
            .map(|(q, &d)| grid.within(q, (d + reach * margin) * (1.0 + 1e-9)))
            .collect();
        self.start.clear();
        self.start.push(0);
        self.candidates.clear();
        for list in &lists {
            self.candidates.extend_from_slice(list);
            self.start.push(self.candidates.len());
        }
        self.anchor.clear();
        self.anchor.extend_from_slice(queries);
        self.k = k;
        nearest
    }
}

/// The margin of [`MovingKnn::default`] and [`KnnGrid::query_all_tracked`], as a fraction of
/// the mean k-th-neighbour distance: larger keeps lists valid longer but makes them longer
/// (0.25: the demo's AIAP lists were rebuilt every 5 iterations).
pub const DEFAULT_MARGIN_FRACTION: f64 = 0.25;

/// Exact `k` nearest neighbours of a point set among itself, for a set that moves a little
/// between calls: training's AIAP neighbours, whose canonical Gaussians move by one Adam step
/// per iteration (a full grid search every iteration was 3% of a `fast` iteration). Every
/// call returns exactly what `KnnGrid::new(points, 4.0).query_all(points, k)` returns; the
/// grid is searched only when a point has moved beyond the margin since the last search
/// ([`CandidateLists`]), when the count or `k` changes, or when a point is not finite.
pub struct MovingKnn {
    margin_fraction: f64,
    lists: CandidateLists,
}

impl Default for MovingKnn {
    fn default() -> Self {
        Self::new(DEFAULT_MARGIN_FRACTION)
    }
}

impl MovingKnn {
    /// An empty list whose margin is `margin_fraction` x the mean k-th-neighbour distance.
    pub fn new(margin_fraction: f64) -> Self {
        Self {
            margin_fraction: margin_fraction.max(0.0),
            lists: CandidateLists::default(),
        }
    }

    /// Full searches so far (the first call always is one).
    pub fn rebuilds(&self) -> u64 {
        self.lists.rebuilds
    }

    pub fn calls(&self) -> u64 {
        self.lists.calls
    }

    /// The `k` nearest of every point among `points`, flattened `points x k`, nearest first
    /// (itself first unless an identical point has a smaller index). Panics as
    /// [`KnnGrid::query_all`] does when fewer than `k` points are finite.
    pub fn neighbours(&mut self, points: &[[f64; 3]], k: usize) -> Vec<u32> {
        self.lists.nearest(points, None, k, self.margin_fraction)
    }
}

fn dist2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

fn insert_sorted(best: &mut Vec<(f64, u32)>, item: (f64, u32), k: usize) {
    if best.len() == k && !less(item, best[k - 1]) {
        return;
    }
    let pos = best.partition_point(|&b| less(b, item));
    best.insert(pos, item);
    best.truncate(k);
}

fn less(a: (f64, u32), b: (f64, u32)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// Brute-force reference: `k` nearest of each query, flattened, same ordering rules.
pub fn knn_brute_force(points: &[[f64; 3]], queries: &[[f64; 3]], k: usize) -> Vec<u32> {
    queries
        .par_iter()
        .flat_map_iter(|q| {
            let mut best = Vec::with_capacity(k + 1);
            for (i, p) in points.iter().enumerate() {
                if p.iter().all(|v| v.is_finite()) {
                    insert_sorted(&mut best, (dist2(q, p), i as u32), k);
                }
            }
            best.into_iter().map(|(_, i)| i)
        })
        .collect()
}

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

/// The exact `k`-nearest-neighbour graph of `points` among themselves (the canonical
/// template's vertex graph). Each point's list starts with the point itself (distance 0)
/// unless an identical point has a smaller index, because training gathers the velocities of
/// the `tau` template vertices nearest to a Gaussian, and Gaussians start on the template
/// vertices. Distances are computed in f64 and rounded to f32.
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
    let wide: Vec<[f64; 3]> = points.iter().map(|p| p.map(f64::from)).collect();
    let indices = KnnGrid::new(&wide, 2.0 * k as f64).query_all(&wide, k);
    let distances = indices
        .par_chunks(k)
        .zip(wide.par_iter())
        .flat_map_iter(|(row, p)| {
            row.iter()
                .map(|&j| dist2(p, &wide[j as usize]).sqrt() as f32)
        })
        .collect();
    Ok(KnnGraph {
        k,
        indices,
        distances,
    })
}

/// Points of an `N x 3` flat slice as arrays.
pub fn as_points(flat: &[f64]) -> Vec<[f64; 3]> {
    flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rng::SplitMix64 as Rng;

    fn check(points: &[[f64; 3]], queries: &[[f64; 3]], k: usize, per_cell: f64) {
        let grid = KnnGrid::new(points, per_cell);
        let fast = grid.query_all(queries, k);
        let slow = knn_brute_force(points, queries, k);
        assert_eq!(fast, slow);
    }

    #[test]
    fn grid_matches_brute_force_on_clouds() {
        let mut rng = Rng::new(7);
        // A body-like anisotropic cloud, queries inside and far outside.
        let points: Vec<[f64; 3]> = (0..3000)
            .map(|_| {
                [
                    rng.uniform(-0.3, 0.3),
                    rng.uniform(-0.9, 0.9),
                    rng.uniform(-0.1, 0.1),
                ]
            })
            .collect();
        let mut queries: Vec<[f64; 3]> = (0..500)
            .map(|_| {
                [
                    rng.uniform(-0.4, 0.4),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-0.2, 0.2),
                ]
            })
            .collect();
        queries.push([5.0, -7.0, 3.0]);
        queries.extend_from_slice(&points[..20]);
        for (k, per_cell) in [(1, 2.0), (5, 2.0), (8, 0.5), (8, 20.0)] {
            check(&points, &queries, k, per_cell);
        }
        // Self query: the point itself comes first.
        let grid = KnnGrid::new(&points, 2.0);
        assert_eq!(grid.query(&points[17], 5)[0], 17);
    }

    #[test]
    fn degenerate_clouds() {
        // All points equal (ties broken by index), a flat plane, and a line.
        let same = vec![[1.0, 2.0, 3.0]; 10];
        check(&same, &[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], 4, 2.0);
        let mut rng = Rng::new(1);
        let plane: Vec<[f64; 3]> = (0..400)
            .map(|_| [rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0), 0.0])
            .collect();
        check(&plane, &plane[..50], 5, 2.0);
        let line: Vec<[f64; 3]> = (0..100).map(|i| [i as f64 * 0.01, 0.0, 0.0]).collect();
        check(&line, &[[0.5, 0.3, 0.0], [-1.0, 0.0, 0.0]], 6, 1.0);
        // Non-finite points are skipped, non-finite queries give a defined row.
        let mut with_nan = line.clone();
        with_nan[3] = [f64::NAN, 0.0, 0.0];
        let grid = KnnGrid::new(&with_nan, 2.0);
        let row = grid.query(&[0.03, 0.0, 0.0], 2);
        assert!(!row.contains(&3));
        assert_eq!(grid.query_all(&[[f64::NAN, 0.0, 0.0]], 2).len(), 2);
        assert_eq!(grid.reference_count(), 99);
    }

    #[test]
    fn within_finds_exactly_the_points_in_the_ball() {
        let wide: Vec<[f64; 3]> = shell_points(900).iter().map(|p| p.map(f64::from)).collect();
        let grid = KnnGrid::new(&wide, 4.0);
        for (q, radius) in [
            (wide[5], 0.05),
            (wide[9], 0.0),
            ([0.0, 0.0, 0.0], 0.25),
            ([3.0, 0.0, 0.0], 2.5),
            ([0.1, 0.2, -0.1], 10.0),
        ] {
            let mut found = grid.within(&q, radius);
            found.sort_unstable();
            let expected: Vec<u32> = (0..wide.len() as u32)
                .filter(|&i| dist2(&q, &wide[i as usize]) <= radius * radius)
                .collect();
            assert_eq!(found, expected, "query {q:?} radius {radius}");
        }
        assert!(grid.within(&[f64::NAN, 0.0, 0.0], 1.0).is_empty());
        assert!(grid.within(&[0.0; 3], f64::INFINITY).is_empty());
    }

    #[test]
    fn moving_knn_is_the_full_search_while_points_drift_jump_and_vanish() {
        let mut rng = Rng::new(5);
        let mut points: Vec<[f64; 3]> = shell_points(1500)
            .iter()
            .map(|p| p.map(f64::from))
            .collect();
        let mut moving = MovingKnn::default();
        let steps = 60;
        for step in 0..steps {
            // Adam-sized drift: a few per cent of the ~2 cm spacing per step, every point.
            for p in points.iter_mut() {
                for v in p.iter_mut() {
                    *v += rng.uniform(-4e-4, 4e-4);
                }
            }
            if step == 20 {
                // A few points jump far (beyond any margin): the list must notice.
                for p in points.iter_mut().take(7) {
                    p[1] += 0.3;
                }
            }
            if step == 40 {
                // Densification-like renumbering: fewer points, others in their slots.
                points.truncate(1200);
                points.swap(3, 900);
            }
            let k = if step == 50 { 3 } else { 5 };
            let expected = KnnGrid::new(&points, 4.0).query_all(&points, k);
            assert_eq!(moving.neighbours(&points, k), expected, "step {step}");
        }
        assert_eq!(
            knn_brute_force(&points, &points, 5),
            moving.neighbours(&points, 5)
        );
        // The lists were reused most of the time, and rebuilt at least at the first call, the
        // jump, the new count and the new k.
        assert!(moving.rebuilds() >= 4, "{} rebuilds", moving.rebuilds());
        assert!(
            moving.rebuilds() * 3 < moving.calls(),
            "{} rebuilds in {} calls",
            moving.rebuilds(),
            moving.calls()
        );
    }

    #[test]
    fn tracked_queries_are_the_full_search_while_they_drift() {
        let template: Vec<[f64; 3]> = shell_points(2000)
            .iter()
            .map(|p| p.map(f64::from))
            .collect();
        let grid = KnnGrid::new(&template, 4.0);
        let mut rng = Rng::new(9);
        // Gaussians near the template, drifting; a second query set interleaved now and then
        // (another caller of the same grid) must not disturb either's results.
        let mut gaussians: Vec<[f64; 3]> = template[..1700]
            .iter()
            .map(|p| p.map(|v| v + rng.uniform(-0.01, 0.01)))
            .collect();
        let other: Vec<[f64; 3]> = template[300..400].to_vec();
        for step in 0..40 {
            for g in gaussians.iter_mut() {
                for v in g.iter_mut() {
                    *v += rng.uniform(-5e-4, 5e-4);
                }
            }
            if step == 15 {
                gaussians[42] = [0.5, 0.5, 0.5];
            }
            let k = if step == 30 { 1 } else { 4 };
            assert_eq!(
                grid.query_all_tracked(&gaussians, k),
                grid.query_all(&gaussians, k),
                "step {step}"
            );
            if step % 10 == 9 {
                assert_eq!(grid.query_all_tracked(&other, 3), grid.query_all(&other, 3));
            }
        }
        assert_eq!(
            grid.query_all_tracked(&gaussians, 4),
            knn_brute_force(&template, &gaussians, 4)
        );
        let (searches, calls) = grid.tracked_searches();
        assert_eq!(calls, 45);
        // First call, the jump, k = 1 and back, and two rebuilds per interleaved set.
        assert!(searches >= 5, "{searches} searches");
        assert!(searches * 3 < calls, "{searches} searches in {calls} calls");
        // Non-finite queries take the full search and get its defined rows.
        let bad = vec![[f64::NAN, 0.0, 0.0], template[0]];
        assert_eq!(grid.query_all_tracked(&bad, 2), grid.query_all(&bad, 2));
    }

    #[test]
    fn moving_knn_keeps_ties_and_handles_degenerate_sets() {
        // A lattice has many equal distances; shifting it keeps them equal (exactly, with a
        // power-of-two step) and the order by index must match the full search.
        let lattice: Vec<[f64; 3]> = (0..6 * 6 * 6)
            .map(|i| {
                [
                    (i % 6) as f64 * 0.25,
                    (i / 6 % 6) as f64 * 0.25,
                    (i / 36) as f64 * 0.25,
                ]
            })
            .collect();
        let mut moving = MovingKnn::default();
        for step in 0..5 {
            let shifted: Vec<[f64; 3]> = lattice
                .iter()
                .map(|p| p.map(|v| v + step as f64 * 0.0078125))
                .collect();
            assert_eq!(
                moving.neighbours(&shifted, 7),
                knn_brute_force(&shifted, &shifted, 7),
                "step {step}"
            );
        }
        assert_eq!(moving.rebuilds(), 1);
        // Coincident points (margin 0): reused while nothing moves.
        let same = vec![[1.0, 2.0, 3.0]; 10];
        let mut moving = MovingKnn::default();
        for _ in 0..3 {
            assert_eq!(
                moving.neighbours(&same, 4),
                knn_brute_force(&same, &same, 4)
            );
        }
        assert_eq!(moving.rebuilds(), 1);
        // A non-finite point takes the full search, whose rows are defined.
        let mut with_nan = lattice.clone();
        with_nan[4] = [f64::NAN, 0.0, 0.0];
        assert_eq!(
            moving.neighbours(&with_nan, 3),
            KnnGrid::new(&with_nan, 4.0).query_all(&with_nan, 3)
        );
    }

    /// Deterministic pseudo-random points on a shell like a body surface.
    fn shell_points(n: usize) -> Vec<[f32; 3]> {
        let mut rng = Rng::new(11);
        (0..n)
            .map(|_| {
                let v = [0, 1, 2].map(|_| rng.uniform(-1.0, 1.0));
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
    fn graph_matches_brute_force_self_first() {
        let points = shell_points(700);
        let wide: Vec<[f64; 3]> = points.iter().map(|p| p.map(f64::from)).collect();
        for k in [1, 6, 8] {
            let graph = knn_graph(&points, k).unwrap();
            assert_eq!(graph.indices, knn_brute_force(&wide, &wide, k), "k={k}");
            for i in 0..points.len() {
                assert_eq!(graph.indices[i * k], i as u32, "self first");
                assert_eq!(graph.distances[i * k], 0.0);
                for n in 0..k {
                    let j = graph.indices[i * k + n] as usize;
                    let d = dist2(&wide[i], &wide[j]).sqrt() as f32;
                    assert_eq!(graph.distances[i * k + n], d);
                }
            }
        }
    }

    #[test]
    fn graph_errors_and_degenerate_sets() {
        // All points on a line, duplicates included.
        let points: Vec<[f32; 3]> = (0..50).map(|i| [(i / 2) as f32 * 0.01, 0.0, 0.0]).collect();
        let wide: Vec<[f64; 3]> = points.iter().map(|p| p.map(f64::from)).collect();
        let graph = knn_graph(&points, 3).unwrap();
        assert_eq!(graph.indices, knn_brute_force(&wide, &wide, 3));
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
