//! What the generic per-pixel loops (`raster.rs`) and the eight-lane loops (`lanes.rs`) of a
//! tile share: the per-pixel state the forward pass leaves for the backward, the upstream
//! gradients, the gradient slots, and the splat's pixel span within a tile.

use super::project::Splat2d;
use crate::scalar::Scalar;

/// What the backward pass needs per pixel (`H x W` each).
pub(super) struct PixelState<S> {
    pub final_transmittance: Vec<S>,
    /// Number of entries of the pixel's tile list up to and including its last contributor.
    pub contributors: Vec<u32>,
}

/// Upstream gradients of one camera, already validated.
pub(super) struct Upstream<'a, S> {
    pub colour: &'a [S],
    pub alpha: Option<&'a [S]>,
    pub depth: Option<&'a [S]>,
}

/// Gradient of one intersection: `mean (2), conic (3), opacity, colour (3), depth`.
pub(super) type Slot<S> = [S; 10];

/// Where one tile's backward walk puts its list entries' gradients (entry `j` in slot `j`:
/// slots are in tile order, so each tile row's task writes its own contiguous part).
pub(super) struct TileSlots<'a, S> {
    pub slots: &'a mut [Slot<S>],
}

impl<S: Copy> TileSlots<'_, S> {
    #[inline(always)]
    pub fn put(&mut self, j: usize, gradient: Slot<S>) {
        self.slots[j] = gradient;
    }
}

/// The splat's pixel box intersected with a tile: `(x0, x1, y0, y1)`, possibly empty.
#[inline(always)]
pub(super) fn box_in_tile<S: Scalar>(splat: &Splat2d<S>, bounds: [u32; 4]) -> (u32, u32, u32, u32) {
    let [x_start, x_end, y_start, y_end] = bounds;
    let [x_lo, x_hi, y_lo, y_hi] = splat.pixel_box;
    (
        x_lo.max(x_start),
        x_hi.min(x_end),
        y_lo.max(y_start),
        y_hi.min(y_end),
    )
}

/// Columns `[lo, hi)` within `[x0, x1)` of the row at `dy = mean_y - row centre` where the
/// splat's power can reach `min_power`, with an eighth of a pixel of margin either side.
/// Columns outside would be skipped by `raster::splat_alpha` anyway, so this only saves work. The
/// margin only absorbs `f64` rounding of the bounds: the composited pixels already lie
/// strictly inside, since alpha `>= 1/255` needs a power `0.01` above `min_power`, far more
/// than the `f32` rounding of the power (the blur bounds the conic by `1/0.3`).
#[inline(always)]
pub(super) fn row_span<S: Scalar>(splat: &Splat2d<S>, dy: S, x0: u32, x1: u32) -> (u32, u32) {
    if x0 >= x1 {
        return (x0, x0);
    }
    let (lo, hi) = row_span_f64(&splat.row_span, dy.to_f64(), f64::from(x0), f64::from(x1));
    // Both lie in `[x0, x1]` (non-negative), so `as` is a floor.
    (lo as u32, hi as u32)
}

/// [`row_span`] on `f64` bounds `x0 < x1`, branch-free (so that a loop over rows
/// vectorises): `(lo, hi)` with `x0 <= lo <= hi <= x1`, still to be floored.
#[inline(always)]
pub(super) fn row_span_f64(constants: &[f64; 4], dy: f64, x0: f64, x1: f64) -> (f64, f64) {
    const MARGIN: f64 = 0.125;
    let [mean_x, slope, w0, w1] = *constants;
    let half_width_sq = w0 - dy * dy * w1;
    // False for NaN too (a degenerate conic): then the span is empty.
    let present = half_width_sq >= 0.0;
    let half_width = half_width_sq.max(0.0).sqrt();
    // Column `col` takes part when its centre `col + 0.5 = mean_x - dx` lies in
    // `centre -+ half_width`: `col` in `[centre - half_width - 0.5, centre + half_width - 0.5]`,
    // so `floor(hi)` is one past the last column. `max`/`min` (not `clamp`) also map a NaN
    // bound into `[x0, x1]`.
    let centre = mean_x - slope * dy;
    let lo = (centre - half_width - 0.5 - MARGIN).max(x0).min(x1);
    let hi = (centre + half_width + 0.5 + MARGIN).max(lo).min(x1);
    if present { (lo, hi) } else { (x0, x0) }
}
