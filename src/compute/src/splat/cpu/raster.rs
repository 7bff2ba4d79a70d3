//! Tile binning, front-to-back compositing and its backward pass, on the CPU.
//!
//! Work is split by rows of 16x16 tiles (a tile row is contiguous in the row-major image and
//! in the sorted intersection list, so every rayon task owns disjoint slices). Inside a tile
//! the loop runs over the tile's Gaussians, front to back, and for each over the pixels of
//! its screen box: per pixel this is exactly the contract's per-pixel loop, in the same order.

// Index loops mirror the matrix and per-channel formulas they implement.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::super::{ALPHA_THRESHOLD, MAX_ALPHA, MIN_TRANSMITTANCE, SplatError, TILE_SIZE};
use super::lanes::{BackwardTile, ForwardRows, ForwardTile, LanePath, TileList};
use super::project::{Splat2d, TileRect};
use super::tile::{PixelState, Slot, TileSlots, Upstream, box_in_tile, row_span};
use crate::scalar::Scalar;

const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;
const TS: usize = TILE_SIZE as usize;

/// Gaussian-tile intersections sorted by tile, then depth, then Gaussian index.
#[derive(Clone, Debug, Default)]
pub(super) struct Binning {
    /// `tiles + 1` offsets into `tile_gaussians`.
    pub tile_offsets: Vec<u32>,
    /// Each intersection's position in the depth order of the visible Gaussians (an index
    /// into `sorted` and into the splats permuted by [`sort_splats`]). Tiles walk increasing
    /// positions, so the permuted splats are read almost sequentially.
    pub tile_gaussians: Vec<u32>,
    /// Gaussian index of each depth-order position.
    pub sorted: Vec<u32>,
    /// `N + 1` offsets into `intersection_positions` (a Gaussian's intersections, its tiles
    /// row by row).
    pub gaussian_offsets: Vec<u32>,
    /// Position in `tile_gaussians` of each of a Gaussian's intersections.
    pub intersection_positions: Vec<u32>,
}

impl Binning {
    /// Tile `tile`'s entries of `tile_gaussians`.
    fn tile_range(&self, tile: usize) -> std::ops::Range<usize> {
        self.tile_offsets[tile] as usize..self.tile_offsets[tile + 1] as usize
    }
}

/// The pixel bounds `[x_start, x_end, y_start, y_end]` of tile column `tx` in the tile row
/// `rows` of a `width` wide image.
fn tile_bounds(tx: u32, width: u32, (y_start, y_end): (u32, u32)) -> [u32; 4] {
    let x_start = tx * TILE_SIZE;
    [x_start, (x_start + TILE_SIZE).min(width), y_start, y_end]
}

/// Sorts the visible Gaussians' tile intersections.
///
/// A global sort by `(f32 depth bits, index)` followed by a stable counting scatter into the
/// tiles gives each tile's list in the contract's order without sorting per tile. Depths are
/// at least the near plane (positive), so their `f32` bit patterns order like the values.
pub(super) fn bin<S: Scalar>(
    splats: &[Splat2d<S>],
    rects: &[TileRect],
    tiles: usize,
    tiles_x: u32,
) -> Result<Binning, SplatError> {
    let n = rects.len();
    let mut gaussian_offsets = Vec::with_capacity(n + 1);
    let mut total: u64 = 0;
    gaussian_offsets.push(0);
    for rect in rects {
        total += rect.area();
        if total > u64::from(u32::MAX) {
            return Err(SplatError::TooManyIntersections {
                count: total as usize,
            });
        }
        gaussian_offsets.push(total as u32);
    }
    let mut order: Vec<u64> = rects
        .par_iter()
        .zip(splats.par_iter())
        .enumerate()
        .filter(|(_, (rect, _))| rect.area() > 0)
        .map(|(index, (_, splat))| (u64::from(splat.depth.to_f32().to_bits()) << 32) | index as u64)
        .collect();
    order.par_sort_unstable();

    let sorted: Vec<u32> = order.iter().map(|key| (key & 0xffff_ffff) as u32).collect();
    drop(order);

    // The stable counting scatter, in parallel over chunks of the depth order: each chunk
    // counts its intersections per tile, and its cursor in a tile starts after those of the
    // earlier chunks, so every tile gets its entries in depth order as a serial scatter would.
    let chunk = sorted
        .len()
        .div_ceil(4 * rayon::current_num_threads())
        .max(4096);
    let mut cursors: Vec<Vec<u32>> = sorted
        .par_chunks(chunk)
        .map(|ranks| {
            let mut counts = vec![0_u32; tiles];
            for &g in ranks {
                let rect = rects[g as usize];
                for ty in rect.y0..rect.y1 {
                    let row = (ty * tiles_x) as usize;
                    for count in &mut counts[row + rect.x0 as usize..row + rect.x1 as usize] {
                        *count += 1;
                    }
                }
            }
            counts
        })
        .collect();
    let mut tile_offsets = vec![0_u32; tiles + 1];
    for t in 0..tiles {
        // Below `total`, which fits in `u32` (checked above).
        let mut running = tile_offsets[t];
        for counts in &mut cursors {
            let count = counts[t];
            counts[t] = running;
            running += count;
        }
        tile_offsets[t + 1] = running;
    }
    let mut tile_gaussians = vec![0_u32; total as usize];
    let mut intersection_positions = vec![0_u32; total as usize];
    {
        let tile_writer = DisjointWriter::new(&mut tile_gaussians);
        let position_writer = DisjointWriter::new(&mut intersection_positions);
        sorted
            .par_chunks(chunk)
            .zip(cursors.par_iter_mut())
            .enumerate()
            .for_each(|(k, (ranks, cursor))| {
                for (i, &g) in ranks.iter().enumerate() {
                    let rank = (k * chunk + i) as u32;
                    let rect = rects[g as usize];
                    let mut slot = gaussian_offsets[g as usize];
                    for ty in rect.y0..rect.y1 {
                        let row = (ty * tiles_x) as usize;
                        for tx in rect.x0..rect.x1 {
                            let tile = row + tx as usize;
                            let position = cursor[tile] as usize;
                            cursor[tile] += 1;
                            // SAFETY: positions are distinct: chunk `k`'s cursor in a tile
                            // runs over its own count of places after the earlier chunks'.
                            // Slots are distinct: each Gaussian is in one chunk, once, and
                            // owns `gaussian_offsets[g]..gaussian_offsets[g + 1]`.
                            unsafe {
                                tile_writer.write(position, rank);
                                position_writer.write(slot as usize, position as u32);
                            }
                            slot += 1;
                        }
                    }
                }
            });
    }
    Ok(Binning {
        tile_offsets,
        tile_gaussians,
        sorted,
        gaussian_offsets,
        intersection_positions,
    })
}

/// Writes into a slice from several threads at indices that are distinct by construction.
pub(super) struct DisjointWriter<'a, T> {
    start: *mut T,
    len: usize,
    _slice: std::marker::PhantomData<&'a mut [T]>,
}

// SAFETY: the writer only hands out writes of `T: Send` values to distinct indices (the
// contract of `write`), like splitting the slice into disjoint `&mut` parts.
unsafe impl<T: Send> Sync for DisjointWriter<'_, T> {}
// SAFETY: as for `Sync`: moving the writer to another thread moves only the right to make
// such writes; the borrowed slice outlives it (`'a`).
unsafe impl<T: Send> Send for DisjointWriter<'_, T> {}

impl<'a, T: Copy> DisjointWriter<'a, T> {
    pub fn new(slice: &'a mut [T]) -> Self {
        Self {
            start: slice.as_mut_ptr(),
            len: slice.len(),
            _slice: std::marker::PhantomData,
        }
    }

    /// Stores `value` at `index` (panics when out of bounds).
    ///
    /// # Safety
    /// While the writer lives, no other call (from any thread) may use the same `index`.
    #[inline(always)]
    pub unsafe fn write(&self, index: usize, value: T) {
        assert!(index < self.len, "index {index} of {}", self.len);
        // SAFETY: in bounds, and no other access to this element (the caller's contract).
        unsafe { self.start.add(index).write(value) }
    }
}

/// The visible splats in depth order (the order `Binning::tile_gaussians` refers to).
pub(super) fn sort_splats<S: Scalar>(splats: &[Splat2d<S>], binning: &Binning) -> Vec<Splat2d<S>> {
    binning
        .sorted
        .par_iter()
        .with_min_len(1024)
        .map(|&g| splats[g as usize])
        .collect()
}

/// Alpha of a splat at a pixel centre offset `d = mean - q`, or `None` when skipped.
/// Returns `(alpha, raw, gaussian)` with `raw = opacity * exp(power)` before the clamp.
#[inline(always)]
fn splat_alpha<S: Scalar>(splat: &Splat2d<S>, dx: S, dy: S, smooth: bool) -> Option<(S, S, S)> {
    let [a, b, c] = splat.conic;
    let half = S::from_f64(0.5);
    let power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy;
    if power > S::ZERO || power < splat.min_power {
        return None;
    }
    let gaussian = power.exp();
    let raw = splat.opacity * gaussian;
    let clamped = raw.min(S::from_f64(MAX_ALPHA));
    let threshold = S::from_f64(ALPHA_THRESHOLD);
    if clamped < threshold {
        return None;
    }
    let alpha = if smooth {
        clamped * smooth_step(clamped).0
    } else {
        clamped
    };
    Some((alpha, raw, gaussian))
}

/// The tests-only C1 cutoff: `s(u) = 3u^2 - 2u^3`, `u = clamp((alpha - t) / t, 0, 1)`,
/// `t = 1/255`. Returns `(s, ds/dalpha)`.
#[inline(always)]
pub(super) fn smooth_step<S: Scalar>(alpha: S) -> (S, S) {
    let threshold = S::from_f64(ALPHA_THRESHOLD);
    let u = ((alpha - threshold) / threshold).clamp(S::ZERO, S::ONE);
    let (two, three, six) = (S::from_f64(2.0), S::from_f64(3.0), S::from_f64(6.0));
    (
        u * u * (three - two * u),
        six * u * (S::ONE - u) / threshold,
    )
}

/// Per-camera outputs of the forward compositing (all `H x W`, colour `H x W x 3`).
pub(super) struct ForwardBuffers<S> {
    pub colour: Vec<S>,
    pub alpha: Vec<S>,
    pub depth: Vec<S>,
    pub pixels: PixelState<S>,
}

/// How one camera's tiles are composited: a `width x height` image over `background`, with
/// the smooth or the hard opacity cutoff.
#[derive(Clone, Copy, Debug)]
pub(super) struct Compositing<S> {
    pub width: u32,
    pub height: u32,
    pub background: [S; 3],
    pub smooth: bool,
}

/// Composites every tile front to back. `fast` holds `splats` itself when `S` is `f32`: then
/// the lane-parallel path of `lanes.rs` runs instead of the generic one.
pub(super) fn forward<S: Scalar>(
    splats: &[Splat2d<S>],
    fast: Option<LanePath<'_>>,
    binning: &Binning,
    Compositing {
        width,
        height,
        background,
        smooth,
    }: Compositing<S>,
) -> ForwardBuffers<S> {
    let (w, h) = (width as usize, height as usize);
    let tiles_x = width.div_ceil(TILE_SIZE);
    let mut out = ForwardBuffers {
        colour: vec![S::ZERO; w * h * 3],
        alpha: vec![S::ZERO; w * h],
        depth: vec![S::ZERO; w * h],
        pixels: PixelState {
            final_transmittance: vec![S::ZERO; w * h],
            contributors: vec![0; w * h],
        },
    };
    let rows = TS * w;
    out.colour
        .par_chunks_mut(rows * 3)
        .zip(out.alpha.par_chunks_mut(rows))
        .zip(out.depth.par_chunks_mut(rows))
        .zip(out.pixels.final_transmittance.par_chunks_mut(rows))
        .zip(out.pixels.contributors.par_chunks_mut(rows))
        .enumerate()
        .for_each(
            |(ty, ((((colour, alpha), depth), transmittance), contributors))| {
                let y_start = ty as u32 * TILE_SIZE;
                let y_end = (y_start + TILE_SIZE).min(height);
                if let Some(fast) = fast {
                    let mut tile = ForwardTile::new();
                    for tx in 0..tiles_x {
                        let range = binning.tile_range(ty * tiles_x as usize + tx as usize);
                        tile.composite(
                            fast,
                            TileList {
                                list: &binning.tile_gaussians[range],
                                bounds: tile_bounds(tx, width, (y_start, y_end)),
                            },
                            smooth,
                            background,
                            w,
                            ForwardRows {
                                colour: &mut *colour,
                                alpha: &mut *alpha,
                                depth: &mut *depth,
                                transmittance: &mut *transmittance,
                                contributors: &mut *contributors,
                            },
                        );
                    }
                    return;
                }
                let mut state = TileState::<S>::new();
                for tx in 0..tiles_x {
                    let range = binning.tile_range(ty * tiles_x as usize + tx as usize);
                    let bounds = tile_bounds(tx, width, (y_start, y_end));
                    let [x_start, x_end, ..] = bounds;
                    state.composite(splats, &binning.tile_gaussians[range], bounds, smooth);
                    for py in y_start..y_end {
                        for px in x_start..x_end {
                            let local = ((py - y_start) as usize) * TS + (px - x_start) as usize;
                            let out_index = (py - y_start) as usize * w + px as usize;
                            let t = state.transmittance[local];
                            for ch in 0..3 {
                                colour[3 * out_index + ch] =
                                    state.colour[local][ch] + t * background[ch];
                            }
                            alpha[out_index] = S::ONE - t;
                            depth[out_index] = state.depth[local];
                            transmittance[out_index] = t;
                            contributors[out_index] = state.contributors[local];
                        }
                    }
                }
            },
        );
    out
}

/// Per-pixel compositing state of one tile.
struct TileState<S> {
    transmittance: [S; TILE_PIXELS],
    colour: [[S; 3]; TILE_PIXELS],
    depth: [S; TILE_PIXELS],
    contributors: [u32; TILE_PIXELS],
    done: [bool; TILE_PIXELS],
}

impl<S: Scalar> TileState<S> {
    fn new() -> Box<Self> {
        Box::new(Self {
            transmittance: [S::ONE; TILE_PIXELS],
            colour: [[S::ZERO; 3]; TILE_PIXELS],
            depth: [S::ZERO; TILE_PIXELS],
            contributors: [0; TILE_PIXELS],
            done: [false; TILE_PIXELS],
        })
    }

    /// `bounds = [x_start, x_end, y_start, y_end]` in pixels.
    fn composite(&mut self, splats: &[Splat2d<S>], list: &[u32], bounds: [u32; 4], smooth: bool) {
        let [x_start, x_end, y_start, y_end] = bounds;
        self.transmittance.fill(S::ONE);
        self.colour.fill([S::ZERO; 3]);
        self.depth.fill(S::ZERO);
        self.contributors.fill(0);
        self.done.fill(false);
        let mut active = ((x_end - x_start) * (y_end - y_start)) as usize;
        let t_min = S::from_f64(MIN_TRANSMITTANCE);
        let half = S::from_f64(0.5);
        for (j, &g) in list.iter().enumerate() {
            if active == 0 {
                break;
            }
            let splat = &splats[g as usize];
            let (x0, x1, y0, y1) = box_in_tile(splat, bounds);
            for py in y0..y1 {
                let dy = splat.mean[1] - (S::from_u32(py) + half);
                let row = (py - y_start) as usize * TS;
                let (span_lo, span_hi) = row_span(splat, dy, x0, x1);
                for px in span_lo..span_hi {
                    let local = row + (px - x_start) as usize;
                    if self.done[local] {
                        continue;
                    }
                    let dx = splat.mean[0] - (S::from_u32(px) + half);
                    let Some((alpha, _, _)) = splat_alpha(splat, dx, dy, smooth) else {
                        continue;
                    };
                    let t = self.transmittance[local];
                    let t_next = t * (S::ONE - alpha);
                    if t_next <= t_min {
                        self.done[local] = true;
                        active -= 1;
                        continue;
                    }
                    let weight = alpha * t;
                    let c = &mut self.colour[local];
                    for ch in 0..3 {
                        c[ch] += weight * splat.colour[ch];
                    }
                    self.depth[local] += weight * splat.depth;
                    self.transmittance[local] = t_next;
                    self.contributors[local] = j as u32 + 1;
                }
            }
        }
    }
}

/// Walks every tile back to front and writes each intersection's gradient into its slot.
pub(super) fn backward<S: Scalar>(
    splats: &[Splat2d<S>],
    fast: Option<LanePath<'_>>,
    binning: &Binning,
    buffers: &PixelState<S>,
    upstream: &Upstream<'_, S>,
    Compositing {
        width,
        height,
        background,
        smooth,
    }: Compositing<S>,
) -> Vec<Slot<S>> {
    let w = width as usize;
    let tiles_x = width.div_ceil(TILE_SIZE);
    let tiles_y = height.div_ceil(TILE_SIZE);
    let mut slots = vec![[S::ZERO; 10]; binning.tile_gaussians.len()];
    // Split the slots by tile row so each task owns its rows' intersections.
    let mut row_slots: Vec<(usize, &mut [Slot<S>])> = Vec::with_capacity(tiles_y as usize);
    let mut rest: &mut [Slot<S>] = &mut slots;
    for ty in 0..tiles_y {
        let start = binning.tile_offsets[(ty * tiles_x) as usize] as usize;
        let end = binning.tile_offsets[((ty + 1) * tiles_x) as usize] as usize;
        let (head, tail) = rest.split_at_mut(end - start);
        row_slots.push((ty as usize, head));
        rest = tail;
    }
    row_slots.into_par_iter().for_each(|(ty, row_slots)| {
        let row_base = binning.tile_offsets[ty * tiles_x as usize] as usize;
        let y_start = ty as u32 * TILE_SIZE;
        let y_end = (y_start + TILE_SIZE).min(height);
        if let Some(fast) = fast {
            let mut tile = BackwardTile::new();
            for tx in 0..tiles_x {
                let range = binning.tile_range(ty * tiles_x as usize + tx as usize);
                let (begin, end) = (range.start, range.end);
                let bounds = tile_bounds(tx, width, (y_start, y_end));
                let count = tile.load(buffers, upstream, bounds, w, background);
                tile.walk(
                    fast,
                    TileList {
                        list: &binning.tile_gaussians[begin..end],
                        bounds,
                    },
                    count,
                    &mut TileSlots {
                        slots: &mut row_slots[begin - row_base..end - row_base],
                    },
                    smooth,
                    upstream,
                );
            }
            return;
        }
        let mut state = BackwardState::<S>::new();
        for tx in 0..tiles_x {
            let range = binning.tile_range(ty * tiles_x as usize + tx as usize);
            let (begin, end) = (range.start, range.end);
            let bounds = tile_bounds(tx, width, (y_start, y_end));
            state.load(buffers, upstream, bounds, w, background);
            state.walk(
                splats,
                &binning.tile_gaussians[range],
                &mut TileSlots {
                    slots: &mut row_slots[begin - row_base..end - row_base],
                },
                bounds,
                smooth,
            );
        }
    });
    slots
}

/// Per-pixel state of the backward walk over one tile.
struct BackwardState<S> {
    /// Transmittance after the Gaussian being visited (divided back one step at a time).
    transmittance: [S; TILE_PIXELS],
    final_transmittance: [S; TILE_PIXELS],
    /// `sum_{j > i} c_j alpha_j T_j + T_final background`, per channel.
    colour_behind: [[S; 3]; TILE_PIXELS],
    /// `sum_{j > i} z_j alpha_j T_j`.
    depth_behind: [S; TILE_PIXELS],
    contributors: [u32; TILE_PIXELS],
    d_colour: [[S; 3]; TILE_PIXELS],
    d_alpha: [S; TILE_PIXELS],
    d_depth: [S; TILE_PIXELS],
    max_contributors: u32,
}

impl<S: Scalar> BackwardState<S> {
    fn new() -> Box<Self> {
        Box::new(Self {
            transmittance: [S::ONE; TILE_PIXELS],
            final_transmittance: [S::ONE; TILE_PIXELS],
            colour_behind: [[S::ZERO; 3]; TILE_PIXELS],
            depth_behind: [S::ZERO; TILE_PIXELS],
            contributors: [0; TILE_PIXELS],
            d_colour: [[S::ZERO; 3]; TILE_PIXELS],
            d_alpha: [S::ZERO; TILE_PIXELS],
            d_depth: [S::ZERO; TILE_PIXELS],
            max_contributors: 0,
        })
    }

    fn load(
        &mut self,
        buffers: &PixelState<S>,
        upstream: &Upstream<'_, S>,
        bounds: [u32; 4],
        width: usize,
        background: [S; 3],
    ) {
        let [x_start, x_end, y_start, y_end] = bounds;
        self.max_contributors = 0;
        for py in y_start..y_end {
            for px in x_start..x_end {
                let local = (py - y_start) as usize * TS + (px - x_start) as usize;
                let index = py as usize * width + px as usize;
                let t = buffers.final_transmittance[index];
                self.transmittance[local] = t;
                self.final_transmittance[local] = t;
                self.colour_behind[local] = background.map(|b| t * b);
                self.depth_behind[local] = S::ZERO;
                self.contributors[local] = buffers.contributors[index];
                self.max_contributors = self.max_contributors.max(buffers.contributors[index]);
                self.d_colour[local] = std::array::from_fn(|ch| upstream.colour[3 * index + ch]);
                self.d_alpha[local] = upstream.alpha.map_or(S::ZERO, |a| a[index]);
                self.d_depth[local] = upstream.depth.map_or(S::ZERO, |d| d[index]);
            }
        }
    }

    fn walk(
        &mut self,
        splats: &[Splat2d<S>],
        list: &[u32],
        slots: &mut TileSlots<'_, S>,
        bounds: [u32; 4],
        smooth: bool,
    ) {
        let [x_start, _, y_start, _] = bounds;
        let half = S::from_f64(0.5);
        let max_alpha = S::from_f64(MAX_ALPHA);
        let zero = S::ZERO;
        for j in (0..self.max_contributors as usize).rev() {
            let splat = &splats[list[j] as usize];
            let (x0, x1, y0, y1) = box_in_tile(splat, bounds);
            let [ca, cb, cc] = splat.conic;
            let mut grad = [zero; 10];
            for py in y0..y1 {
                let dy = splat.mean[1] - (S::from_u32(py) + half);
                let row = (py - y_start) as usize * TS;
                let (span_lo, span_hi) = row_span(splat, dy, x0, x1);
                for px in span_lo..span_hi {
                    let local = row + (px - x_start) as usize;
                    if j as u32 >= self.contributors[local] {
                        continue;
                    }
                    let dx = splat.mean[0] - (S::from_u32(px) + half);
                    let Some((alpha, raw, gaussian)) = splat_alpha(splat, dx, dy, smooth) else {
                        continue;
                    };
                    let one_minus = S::ONE - alpha;
                    let inv_one_minus = S::ONE / one_minus;
                    let t = self.transmittance[local] * inv_one_minus;
                    let weight = alpha * t;
                    let dc = self.d_colour[local];
                    let behind = self.colour_behind[local];
                    let mut d_alpha = zero;
                    for ch in 0..3 {
                        grad[6 + ch] += weight * dc[ch];
                        d_alpha += dc[ch] * (splat.colour[ch] * t - behind[ch] * inv_one_minus);
                    }
                    d_alpha +=
                        self.d_alpha[local] * self.final_transmittance[local] * inv_one_minus;
                    let dd = self.d_depth[local];
                    d_alpha += dd * (splat.depth * t - self.depth_behind[local] * inv_one_minus);
                    grad[9] += weight * dd;
                    for ch in 0..3 {
                        self.colour_behind[local][ch] += weight * splat.colour[ch];
                    }
                    self.depth_behind[local] += weight * splat.depth;
                    self.transmittance[local] = t;

                    // Through the smooth cutoff (tests only) and the 0.99 clamp.
                    let d_raw = if smooth {
                        let clamped = raw.min(max_alpha);
                        let (s, ds) = smooth_step(clamped);
                        d_alpha * (s + clamped * ds)
                    } else {
                        d_alpha
                    };
                    if raw >= max_alpha {
                        continue;
                    }
                    grad[5] += d_raw * gaussian;
                    let d_power = d_raw * raw;
                    grad[2] -= half * dx * dx * d_power;
                    grad[3] -= dx * dy * d_power;
                    grad[4] -= half * dy * dy * d_power;
                    grad[0] -= (ca * dx + cb * dy) * d_power;
                    grad[1] -= (cb * dx + cc * dy) * d_power;
                }
            }
            slots.put(j, grad);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::scene::SplitMix64;

    #[test]
    fn parallel_binning_matches_a_per_tile_sort() {
        // Enough Gaussians for several scatter chunks, with equal depths (ties by index),
        // empty rectangles and rectangles at the grid's edges.
        let mut rng = SplitMix64::new(9);
        let (tiles_x, tiles_y) = (13_u32, 7_u32);
        let n = 20_000;
        let mut splats = vec![Splat2d::<f32>::default(); n];
        let mut rects = vec![TileRect::default(); n];
        for (splat, rect) in splats.iter_mut().zip(&mut rects) {
            splat.depth = (1.0 + (rng.next_f64() * 50.0).floor() * 0.25) as f32;
            if rng.next_f64() < 0.1 {
                continue;
            }
            let x0 = (rng.next_f64() * f64::from(tiles_x)) as u32;
            let y0 = (rng.next_f64() * f64::from(tiles_y)) as u32;
            *rect = TileRect {
                x0,
                y0,
                x1: (x0 + 1 + (rng.next_f64() * 4.0) as u32).min(tiles_x),
                y1: (y0 + 1 + (rng.next_f64() * 3.0) as u32).min(tiles_y),
            };
        }
        let tiles = (tiles_x * tiles_y) as usize;
        let binning = bin(&splats, &rects, tiles, tiles_x).unwrap();
        let mut seen = vec![false; binning.tile_gaussians.len()];
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                let tile = (ty * tiles_x + tx) as usize;
                let mut expected: Vec<(u32, usize)> = (0..n)
                    .filter(|&g| {
                        let r = rects[g];
                        (r.x0..r.x1).contains(&tx) && (r.y0..r.y1).contains(&ty)
                    })
                    .map(|g| (splats[g].depth.to_bits(), g))
                    .collect();
                expected.sort_unstable();
                let range =
                    binning.tile_offsets[tile] as usize..binning.tile_offsets[tile + 1] as usize;
                let got: Vec<usize> = binning.tile_gaussians[range.clone()]
                    .iter()
                    .map(|&rank| binning.sorted[rank as usize] as usize)
                    .collect();
                let expected: Vec<usize> = expected.into_iter().map(|(_, g)| g).collect();
                assert_eq!(got, expected, "tile ({tx}, {ty})");
                for (position, &g) in range.zip(&got) {
                    // The slot is this Gaussian's, at this tile's place in its row-by-row order.
                    let r = rects[g];
                    let k = (ty - r.y0) * (r.x1 - r.x0) + (tx - r.x0);
                    let slot = (binning.gaussian_offsets[g] + k) as usize;
                    assert_eq!(binning.intersection_positions[slot] as usize, position);
                    assert!(!seen[slot]);
                    seen[slot] = true;
                }
            }
        }
        assert!(seen.iter().all(|&s| s));
    }

    #[test]
    fn row_spans_hold_every_pixel_the_contract_composites() {
        let mut rng = SplitMix64::new(5);
        for _ in 0..300 {
            // A random 2D covariance (blur included) and opacity.
            let (sx, sy) = (rng.uniform(0.1, 30.0), rng.uniform(0.1, 30.0));
            let angle = rng.uniform(0.0, std::f64::consts::PI);
            let (cos, sin) = (angle.cos(), angle.sin());
            let a = cos * cos * sx * sx + sin * sin * sy * sy + 0.3;
            let b = cos * sin * (sx * sx - sy * sy);
            let c = sin * sin * sx * sx + cos * cos * sy * sy + 0.3;
            let det = a * c - b * b;
            let opacity = rng.uniform(ALPHA_THRESHOLD, 1.0) as f32;
            let mean = [
                rng.uniform(-5.0, 70.0) as f32,
                rng.uniform(-5.0, 70.0) as f32,
            ];
            let conic = [(c / det) as f32, (-b / det) as f32, (a / det) as f32];
            let min_power = (ALPHA_THRESHOLD as f32 / opacity).ln() - 0.01;
            let splat = Splat2d::<f32> {
                mean,
                conic,
                opacity,
                colour: [0.5; 3],
                depth: 1.0,
                min_power,
                pixel_box: [0, 64, 0, 64],
                row_span: super::super::project::row_span_constants(mean[0], conic, min_power),
            };
            for py in 0..64_u32 {
                let dy = splat.mean[1] - (py as f32 + 0.5);
                let (lo, hi) = row_span(&splat, dy, 0, 64);
                for px in 0..64_u32 {
                    let dx = splat.mean[0] - (px as f32 + 0.5);
                    if splat_alpha(&splat, dx, dy, false).is_some() {
                        assert!(
                            (lo..hi).contains(&px),
                            "pixel ({px}, {py}) outside span {lo}..{hi}"
                        );
                    }
                }
            }
        }
    }
}
