//! The `f32` speed path of tile compositing and its backward pass: eight pixels of a tile row
//! per step, written as fixed-width lane loops that LLVM vectorises (AVX2 when the CPU has
//! it, chosen at run time; SSE2 otherwise, with bitwise-identical results).
//!
//! The per-pixel math is the contract's (`SPLATTING.md`) in the same operation order as the
//! generic path in `raster.rs`, with two differences that only change `f32` rounding: `exp`
//! is a polynomial ([`fast_exp`], within 2 ulp of `expf` on the range the rasteriser uses),
//! and the backward pass sums a Gaussian's per-pixel gradients per lane before adding the
//! lanes. Lanes whose pixel does not take part are computed and discarded by selects, so a
//! Gaussian costs one step per 8-pixel group its row spans touch. `f64` runs never come here:
//! gradient checks keep the exact generic path.

// Index loops over lanes are what LLVM vectorises.
#![allow(clippy::needless_range_loop)]

use super::super::{ALPHA_THRESHOLD, MAX_ALPHA, MIN_TRANSMITTANCE, TILE_SIZE};
use super::project::Splat2d;
use super::raster::{PixelState, Slot, Upstream, box_in_tile, row_span};
use crate::scalar::Scalar;

/// Pixels per step (one AVX2 register of `f32`).
const LANES: usize = 8;
const TS: usize = TILE_SIZE as usize;
const TILE_PIXELS: usize = TS * TS;
/// Pixel-centre offsets of the lanes from the group's first column.
const LANE_CENTRES: [f32; LANES] = [0.5, 1.5, 2.5, 3.5, 4.5, 5.5, 6.5, 7.5];
/// How many list entries ahead a tile loop prefetches splats.
const PREFETCH_DISTANCE: usize = 8;
const THRESHOLD: f32 = ALPHA_THRESHOLD as f32;
const ALPHA_MAX: f32 = MAX_ALPHA as f32;
const T_MIN: f32 = MIN_TRANSMITTANCE as f32;

/// `e^x` in `f32` for `x` in `[-87, 0]` (the rasteriser needs `[ln(1/255) - 0.01, 0]`):
/// Cephes `expf`, range reduction by `n = round(x / ln 2)` with a two-part `ln 2`, a degree-6
/// polynomial (Horner steps fused, `f32::mul_add`), and `2^n` built in the exponent bits. Branch-free so that it vectorises; an
/// argument outside the range gives an unspecified value (never a panic), which the callers
/// discard.
#[inline(always)]
pub(super) fn fast_exp(x: f32) -> f32 {
    let shifted = x * std::f32::consts::LOG2_E + EXP_SHIFTER;
    let n = shifted - EXP_SHIFTER;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = EXP_POLY[0];
    for &c in &EXP_POLY[1..] {
        p = p.mul_add(r, c);
    }
    let y = (p * r).mul_add(r, r) + 1.0;
    // `shifted` has the bits `0x4b40_0000 + n`; `2^n` has `(n + 127) << 23`.
    let scale = f32::from_bits(shifted.to_bits().wrapping_add(EXP_BIAS).wrapping_shl(23));
    y * scale
}

/// 1.5 * 2^23: adding it rounds to an integer (round to nearest even) and leaves that
/// integer in the low mantissa bits.
const EXP_SHIFTER: f32 = 12_582_912.0;
/// `127 - bits(EXP_SHIFTER)`, wrapping: turns `bits(n + EXP_SHIFTER)` into the biased
/// exponent of `2^n`.
const EXP_BIAS: u32 = 127_u32.wrapping_sub(0x4b40_0000);
/// `ln 2` split so that `n * LN2_HI` is exact for the `n` that occur.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Cephes `expf` polynomial, highest degree first: `e^r ~ 1 + r + r^2 p(r)`.
const EXP_POLY: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

/// Eight `f32` lanes and the operations the compositing loops need. A mask is a value whose
/// lanes are all-ones or all-zero bit patterns; selects and logic act on bits, so a mask can
/// also carry `u32` values (contributor counts) through [`Lanes::select`] unchanged.
///
/// The two implementations compute every lane with the same IEEE operations in the same
/// order (fused multiply-adds in `exp` in both, nowhere else), so they agree bit for bit.
trait Lanes: Copy {
    fn splat(value: f32) -> Self;
    fn load(values: &[f32; LANES]) -> Self;
    fn store(self, out: &mut [f32; LANES]);
    fn add(self, other: Self) -> Self;
    fn sub(self, other: Self) -> Self;
    fn mul(self, other: Self) -> Self;
    fn div(self, other: Self) -> Self;
    fn less(self, other: Self) -> Self;
    fn less_equal(self, other: Self) -> Self;
    fn greater_equal(self, other: Self) -> Self;
    /// Lanes read as `u32` bit patterns below `2^31`: `self < other`.
    fn less_u32(self, other: Self) -> Self;
    fn and(self, other: Self) -> Self;
    fn or(self, other: Self) -> Self;
    /// `self & !other`.
    fn and_not(self, other: Self) -> Self;
    /// `mask ? a : b` per lane.
    fn select(mask: Self, a: Self, b: Self) -> Self;
    /// Bit `l` set when lane `l` of a mask is set.
    fn mask_bits(self) -> u32;
    /// [`fast_exp`] per lane.
    fn exp(self) -> Self;
    /// Hints that `value` will be read soon (a no-op where there is no such instruction).
    fn prefetch<T>(value: &T);
}

/// The portable implementation (plain arrays; the compiler uses SSE2 where it can).
#[derive(Clone, Copy)]
struct Portable([f32; LANES]);

impl Portable {
    #[inline(always)]
    fn map2(self, other: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        Self(std::array::from_fn(|l| f(self.0[l], other.0[l])))
    }

    #[inline(always)]
    fn mask(self, other: Self, f: impl Fn(f32, f32) -> bool) -> Self {
        Self(std::array::from_fn(|l| {
            f32::from_bits(if f(self.0[l], other.0[l]) {
                u32::MAX
            } else {
                0
            })
        }))
    }

    #[inline(always)]
    fn bitwise(self, other: Self, f: impl Fn(u32, u32) -> u32) -> Self {
        Self(std::array::from_fn(|l| {
            f32::from_bits(f(self.0[l].to_bits(), other.0[l].to_bits()))
        }))
    }
}

impl Lanes for Portable {
    #[inline(always)]
    fn splat(value: f32) -> Self {
        Self([value; LANES])
    }
    #[inline(always)]
    fn load(values: &[f32; LANES]) -> Self {
        Self(*values)
    }
    #[inline(always)]
    fn store(self, out: &mut [f32; LANES]) {
        *out = self.0;
    }
    #[inline(always)]
    fn add(self, other: Self) -> Self {
        self.map2(other, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, other: Self) -> Self {
        self.map2(other, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, other: Self) -> Self {
        self.map2(other, |a, b| a * b)
    }
    #[inline(always)]
    fn div(self, other: Self) -> Self {
        self.map2(other, |a, b| a / b)
    }
    #[inline(always)]
    fn less(self, other: Self) -> Self {
        self.mask(other, |a, b| a < b)
    }
    #[inline(always)]
    fn less_equal(self, other: Self) -> Self {
        self.mask(other, |a, b| a <= b)
    }
    #[inline(always)]
    fn greater_equal(self, other: Self) -> Self {
        self.mask(other, |a, b| a >= b)
    }
    #[inline(always)]
    fn less_u32(self, other: Self) -> Self {
        self.bitwise(other, |a, b| if a < b { u32::MAX } else { 0 })
    }
    #[inline(always)]
    fn and(self, other: Self) -> Self {
        self.bitwise(other, |a, b| a & b)
    }
    #[inline(always)]
    fn or(self, other: Self) -> Self {
        self.bitwise(other, |a, b| a | b)
    }
    #[inline(always)]
    fn and_not(self, other: Self) -> Self {
        self.bitwise(other, |a, b| a & !b)
    }
    #[inline(always)]
    fn select(mask: Self, a: Self, b: Self) -> Self {
        Self(std::array::from_fn(|l| {
            let m = mask.0[l].to_bits();
            f32::from_bits((a.0[l].to_bits() & m) | (b.0[l].to_bits() & !m))
        }))
    }
    #[inline(always)]
    fn mask_bits(self) -> u32 {
        (0..LANES).fold(0, |bits, l| bits | ((self.0[l].to_bits() >> 31) << l))
    }
    #[inline(always)]
    fn exp(self) -> Self {
        Self(self.0.map(fast_exp))
    }
    #[inline(always)]
    fn prefetch<T>(_value: &T) {}
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! [`Lanes`] on AVX2 registers.
    //!
    //! SAFETY (for every `unsafe` block below): [`Avx2`] values are only created inside
    //! functions compiled with `#[target_feature(enable = "avx2,fma")]`, which are only
    //! called after [`super::has_avx2`]; these `#[inline(always)]` methods are inlined
    //! into them.

    use std::arch::x86_64::*;

    use super::{LANES, Lanes};

    #[derive(Clone, Copy)]
    pub(super) struct Avx2(__m256);

    impl Lanes for Avx2 {
        #[inline(always)]
        fn splat(value: f32) -> Self {
            Self(unsafe { _mm256_set1_ps(value) })
        }
        #[inline(always)]
        fn load(values: &[f32; LANES]) -> Self {
            Self(unsafe { _mm256_loadu_ps(values.as_ptr()) })
        }
        #[inline(always)]
        fn store(self, out: &mut [f32; LANES]) {
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn add(self, other: Self) -> Self {
            Self(unsafe { _mm256_add_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn sub(self, other: Self) -> Self {
            Self(unsafe { _mm256_sub_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn mul(self, other: Self) -> Self {
            Self(unsafe { _mm256_mul_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn div(self, other: Self) -> Self {
            Self(unsafe { _mm256_div_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn less(self, other: Self) -> Self {
            Self(unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(self.0, other.0) })
        }
        #[inline(always)]
        fn less_equal(self, other: Self) -> Self {
            Self(unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(self.0, other.0) })
        }
        #[inline(always)]
        fn greater_equal(self, other: Self) -> Self {
            Self(unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(self.0, other.0) })
        }
        #[inline(always)]
        fn less_u32(self, other: Self) -> Self {
            // Values below 2^31 compare the same signed.
            Self(unsafe {
                _mm256_castsi256_ps(_mm256_cmpgt_epi32(
                    _mm256_castps_si256(other.0),
                    _mm256_castps_si256(self.0),
                ))
            })
        }
        #[inline(always)]
        fn and(self, other: Self) -> Self {
            Self(unsafe { _mm256_and_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn or(self, other: Self) -> Self {
            Self(unsafe { _mm256_or_ps(self.0, other.0) })
        }
        #[inline(always)]
        fn and_not(self, other: Self) -> Self {
            Self(unsafe { _mm256_andnot_ps(other.0, self.0) })
        }
        #[inline(always)]
        fn select(mask: Self, a: Self, b: Self) -> Self {
            Self(unsafe { _mm256_blendv_ps(b.0, a.0, mask.0) })
        }
        #[inline(always)]
        fn mask_bits(self) -> u32 {
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        fn exp(self) -> Self {
            // `super::fast_exp`, operation for operation.
            let x = self;
            let shifted = x
                .mul(Self::splat(std::f32::consts::LOG2_E))
                .add(Self::splat(super::EXP_SHIFTER));
            let n = shifted.sub(Self::splat(super::EXP_SHIFTER));
            let r = x
                .sub(n.mul(Self::splat(super::LN2_HI)))
                .sub(n.mul(Self::splat(super::LN2_LO)));
            let mut p = Self::splat(super::EXP_POLY[0]);
            for &c in &super::EXP_POLY[1..] {
                p = Self(unsafe { _mm256_fmadd_ps(p.0, r.0, _mm256_set1_ps(c)) });
            }
            let y = Self(unsafe { _mm256_fmadd_ps(p.mul(r).0, r.0, r.0) }).add(Self::splat(1.0));
            let scale = unsafe {
                _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
                    _mm256_castps_si256(shifted.0),
                    _mm256_set1_epi32(super::EXP_BIAS as i32),
                )))
            };
            y.mul(Self(scale))
        }
        #[inline(always)]
        fn prefetch<T>(value: &T) {
            let address = (value as *const T).cast::<i8>();
            unsafe { _mm_prefetch::<_MM_HINT_T0>(address) };
            if size_of::<T>() > 64 {
                unsafe { _mm_prefetch::<_MM_HINT_T0>(address.wrapping_add(64)) };
            }
        }
    }
}

/// Whether the AVX2 lanes (which also use FMA in `exp`) can run here (cached by the standard
/// library).
#[inline(always)]
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `f32` lanes of `values[base..base + 8]`.
#[inline(always)]
fn lanes_of<T>(values: &mut [T], base: usize) -> &mut [T; LANES] {
    (&mut values[base..base + LANES]).try_into().unwrap()
}

/// Per-lane pixel-centre offsets `d = mean - q` and the splat's alpha: returns
/// `(dx, composited, gaussian, raw, clamped)` with `composited` the mask of lanes the contract
/// composites (power in range, alpha at least `1/255`).
#[inline(always)]
fn lane_alpha<V: Lanes>(splat: &Splat2d<f32>, column: f32, dy: f32) -> (V, V, V, V, V) {
    let [a, b, c] = splat.conic;
    let dx = V::splat(splat.mean[0]).sub(V::splat(column).add(V::load(&LANE_CENTRES)));
    let dyv = V::splat(dy);
    // power = -0.5 (a dx dx + c dy dy) - b dx dy, in the generic path's order.
    let quad = V::splat(a).mul(dx).mul(dx).add(V::splat(c * dy * dy));
    let power = V::splat(-0.5).mul(quad).sub(V::splat(b).mul(dx).mul(dyv));
    let in_range = power
        .less_equal(V::splat(0.0))
        .and(power.greater_equal(V::splat(splat.min_power)));
    let gaussian = power.exp();
    let raw = V::splat(splat.opacity).mul(gaussian);
    let max = V::splat(ALPHA_MAX);
    let clamped = V::select(raw.less(max), raw, max);
    let composited = in_range.and(clamped.greater_equal(V::splat(THRESHOLD)));
    (dx, composited, gaussian, raw, clamped)
}

/// The tests-only C1 cutoff of `raster::smooth_step` per lane: `(s, ds/dalpha)`.
#[inline(always)]
fn lane_smooth_step<V: Lanes>(alpha: V) -> (V, V) {
    let threshold = V::splat(THRESHOLD);
    let u = alpha.sub(threshold).div(threshold);
    let zero = V::splat(0.0);
    let one = V::splat(1.0);
    let u = V::select(zero.less(u), u, zero);
    let u = V::select(u.less(one), u, one);
    (
        u.mul(u).mul(V::splat(3.0).sub(V::splat(2.0).mul(u))),
        V::splat(6.0).mul(u).mul(one.sub(u)).div(threshold),
    )
}

/// Per-pixel compositing state of one tile, one array per quantity.
pub(super) struct ForwardTile {
    transmittance: [f32; TILE_PIXELS],
    colour: [[f32; TILE_PIXELS]; 3],
    depth: [f32; TILE_PIXELS],
    /// `u32` contributor counts stored as `f32` bit patterns (moved by selects only).
    contributors: [f32; TILE_PIXELS],
    /// All-ones bits once the pixel has stopped (or lies outside the image), else zero.
    done: [f32; TILE_PIXELS],
    /// Pixels of each tile row still compositing (rows with none are skipped).
    row_active: [u32; TS],
}

impl ForwardTile {
    pub fn new() -> Box<Self> {
        Box::new(Self {
            transmittance: [1.0; TILE_PIXELS],
            colour: [[0.0; TILE_PIXELS]; 3],
            depth: [0.0; TILE_PIXELS],
            contributors: [0.0; TILE_PIXELS],
            done: [0.0; TILE_PIXELS],
            row_active: [0; TS],
        })
    }

    /// Composites one tile (`bounds = [x_start, x_end, y_start, y_end]`) and writes its
    /// pixels into the tile row's output slices (`width` pixels per image row).
    #[allow(clippy::too_many_arguments)]
    pub fn composite<S: Scalar>(
        &mut self,
        splats: &[Splat2d<f32>],
        list: &[u32],
        bounds: [u32; 4],
        smooth: bool,
        background: [S; 3],
        width: usize,
        out: ForwardRows<'_, S>,
    ) {
        if smooth {
            self.run::<true>(splats, list, bounds);
        } else {
            self.run::<false>(splats, list, bounds);
        }
        let [x_start, x_end, y_start, y_end] = bounds;
        for py in y_start..y_end {
            for px in x_start..x_end {
                let local = (py - y_start) as usize * TS + (px - x_start) as usize;
                let index = (py - y_start) as usize * width + px as usize;
                let t = S::from_f64(f64::from(self.transmittance[local]));
                for ch in 0..3 {
                    out.colour[3 * index + ch] =
                        S::from_f64(f64::from(self.colour[ch][local])) + t * background[ch];
                }
                out.alpha[index] = S::ONE - t;
                out.depth[index] = S::from_f64(f64::from(self.depth[local]));
                out.transmittance[index] = t;
                out.contributors[index] = self.contributors[local].to_bits();
            }
        }
    }

    fn run<const SMOOTH: bool>(&mut self, splats: &[Splat2d<f32>], list: &[u32], bounds: [u32; 4]) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            /// The lane loop compiled for AVX2 (the methods it calls are all inlined).
            #[target_feature(enable = "avx2,fma")]
            fn run_avx2(
                tile: &mut ForwardTile,
                splats: &[Splat2d<f32>],
                list: &[u32],
                bounds: [u32; 4],
                smooth: bool,
            ) {
                tile.run_lanes::<avx2::Avx2>(splats, list, bounds, smooth);
            }
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { run_avx2(self, splats, list, bounds, SMOOTH) };
            return;
        }
        self.run_lanes::<Portable>(splats, list, bounds, SMOOTH);
    }

    #[inline(always)]
    fn run_lanes<V: Lanes>(
        &mut self,
        splats: &[Splat2d<f32>],
        list: &[u32],
        bounds: [u32; 4],
        smooth: bool,
    ) {
        let [x_start, x_end, y_start, y_end] = bounds;
        self.transmittance.fill(1.0);
        for channel in &mut self.colour {
            channel.fill(0.0);
        }
        self.depth.fill(0.0);
        self.contributors.fill(0.0);
        // Pixels outside the image start done, so partial tiles need no other mask.
        let (w, h) = ((x_end - x_start) as usize, (y_end - y_start) as usize);
        for (local, done) in self.done.iter_mut().enumerate() {
            let outside = local % TS >= w || local / TS >= h;
            *done = f32::from_bits(if outside { u32::MAX } else { 0 });
        }
        for (row, active) in self.row_active.iter_mut().enumerate() {
            *active = if row < h { w as u32 } else { 0 };
        }
        let mut active = (w * h) as u32;
        for (j, &g) in list.iter().enumerate() {
            if active == 0 {
                break;
            }
            // The list jumps through the splats (they are in depth order, tiles in space):
            // fetch a few entries ahead so the cache misses overlap.
            if let Some(&ahead) = list.get(j + PREFETCH_DISTANCE) {
                V::prefetch(&splats[ahead as usize]);
            }
            let splat = &splats[g as usize];
            let (x0, x1, y0, y1) = box_in_tile(splat, bounds);
            for py in y0..y1 {
                let row_index = (py - y_start) as usize;
                if self.row_active[row_index] == 0 {
                    continue;
                }
                let dy = splat.mean[1] - (py as f32 + 0.5);
                let (lo, hi) = row_span(splat, dy, x0, x1);
                if lo >= hi {
                    continue;
                }
                let row = row_index * TS;
                let (g0, g1) = (
                    (lo - x_start) as usize / LANES,
                    ((hi - x_start) as usize).div_ceil(LANES),
                );
                for group in g0..g1 {
                    let column = (x_start as usize + group * LANES) as f32;
                    let base = row + group * LANES;
                    let stops = if smooth {
                        self.group::<V, true>(base, splat, column, dy, j as u32 + 1)
                    } else {
                        self.group::<V, false>(base, splat, column, dy, j as u32 + 1)
                    };
                    self.row_active[row_index] -= stops;
                    active -= stops;
                }
            }
        }
    }

    /// One Gaussian over the 8 pixels from `base` (tile-local) whose first column is
    /// `column`. Returns how many pixels stopped.
    #[inline(always)]
    fn group<V: Lanes, const SMOOTH: bool>(
        &mut self,
        base: usize,
        splat: &Splat2d<f32>,
        column: f32,
        dy: f32,
        rank: u32,
    ) -> u32 {
        let done_lanes = lanes_of(&mut self.done, base);
        let done = V::load(done_lanes);
        if done.mask_bits() == (1 << LANES) - 1 {
            return 0;
        }
        let (_, composited, _, _, clamped) = lane_alpha::<V>(splat, column, dy);
        let valid = composited.and_not(done);
        if valid.mask_bits() == 0 {
            return 0;
        }
        let alpha = if SMOOTH {
            clamped.mul(lane_smooth_step(clamped).0)
        } else {
            clamped
        };
        let t_lanes = lanes_of(&mut self.transmittance, base);
        let t = V::load(t_lanes);
        let t_next = t.mul(V::splat(1.0).sub(alpha));
        let stop = valid.and(t_next.less_equal(V::splat(T_MIN)));
        let take = valid.and_not(stop);
        let weight = alpha.mul(t);
        V::select(take, t_next, t).store(t_lanes);
        for ch in 0..3 {
            let lanes = lanes_of(&mut self.colour[ch], base);
            let value = V::load(lanes);
            V::select(
                take,
                value.add(weight.mul(V::splat(splat.colour[ch]))),
                value,
            )
            .store(lanes);
        }
        let depth_lanes = lanes_of(&mut self.depth, base);
        let depth = V::load(depth_lanes);
        V::select(take, depth.add(weight.mul(V::splat(splat.depth))), depth).store(depth_lanes);
        let contributor_lanes = lanes_of(&mut self.contributors, base);
        let contributors = V::load(contributor_lanes);
        V::select(take, V::splat(f32::from_bits(rank)), contributors).store(contributor_lanes);
        done.or(stop).store(done_lanes);
        stop.mask_bits().count_ones()
    }
}

/// One tile row's output slices of the forward pass (`16 x width` pixels).
pub(super) struct ForwardRows<'a, S> {
    pub colour: &'a mut [S],
    pub alpha: &'a mut [S],
    pub depth: &'a mut [S],
    pub transmittance: &'a mut [S],
    pub contributors: &'a mut [u32],
}

/// Per-pixel state of the backward walk over one tile, one array per quantity.
pub(super) struct BackwardTile {
    /// Transmittance after the Gaussian being visited (divided back one step at a time).
    transmittance: [f32; TILE_PIXELS],
    final_transmittance: [f32; TILE_PIXELS],
    /// `sum_{j > i} c_j alpha_j T_j + T_final background`, per channel.
    colour_behind: [[f32; TILE_PIXELS]; 3],
    /// `sum_{j > i} z_j alpha_j T_j`.
    depth_behind: [f32; TILE_PIXELS],
    /// `u32` contributor counts as `f32` bit patterns; 0 for pixels outside the image.
    contributors: [f32; TILE_PIXELS],
    d_colour: [[f32; TILE_PIXELS]; 3],
    d_alpha: [f32; TILE_PIXELS],
    d_depth: [f32; TILE_PIXELS],
    /// Largest contributor count of each tile row (a list entry at or past it is skipped).
    row_contributors: [u32; TS],
}

/// Per-lane partial sums of one Gaussian's gradient (the layout of [`Slot`]).
type LaneGradient<V> = [V; 10];

impl BackwardTile {
    pub fn new() -> Box<Self> {
        Box::new(Self {
            transmittance: [1.0; TILE_PIXELS],
            final_transmittance: [1.0; TILE_PIXELS],
            colour_behind: [[0.0; TILE_PIXELS]; 3],
            depth_behind: [0.0; TILE_PIXELS],
            contributors: [0.0; TILE_PIXELS],
            d_colour: [[0.0; TILE_PIXELS]; 3],
            d_alpha: [0.0; TILE_PIXELS],
            d_depth: [0.0; TILE_PIXELS],
            row_contributors: [0; TS],
        })
    }

    /// Loads one tile's pixels; returns the largest contributor count.
    pub fn load<S: Scalar>(
        &mut self,
        buffers: &PixelState<S>,
        upstream: &Upstream<'_, S>,
        bounds: [u32; 4],
        width: usize,
        background: [S; 3],
    ) -> u32 {
        let [x_start, x_end, y_start, y_end] = bounds;
        let background = background.map(|b| b.to_f32());
        self.contributors.fill(0.0);
        self.row_contributors.fill(0);
        let mut max_contributors = 0;
        for py in y_start..y_end {
            for px in x_start..x_end {
                let local = (py - y_start) as usize * TS + (px - x_start) as usize;
                let index = py as usize * width + px as usize;
                let t = buffers.final_transmittance[index].to_f32();
                self.transmittance[local] = t;
                self.final_transmittance[local] = t;
                for ch in 0..3 {
                    self.colour_behind[ch][local] = t * background[ch];
                    self.d_colour[ch][local] = upstream.colour[3 * index + ch].to_f32();
                }
                self.depth_behind[local] = 0.0;
                let count = buffers.contributors[index];
                self.contributors[local] = f32::from_bits(count);
                max_contributors = max_contributors.max(count);
                let row = &mut self.row_contributors[(py - y_start) as usize];
                *row = (*row).max(count);
                self.d_alpha[local] = upstream.alpha.map_or(0.0, |a| a[index].to_f32());
                self.d_depth[local] = upstream.depth.map_or(0.0, |d| d[index].to_f32());
            }
        }
        max_contributors
    }

    /// Walks the tile's first `count` list entries back to front, writing each one's
    /// gradient into `slots`.
    pub fn walk<S: Scalar>(
        &mut self,
        splats: &[Splat2d<f32>],
        list: &[u32],
        count: u32,
        slots: &mut [Slot<S>],
        bounds: [u32; 4],
        smooth: bool,
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            /// The lane loop compiled for AVX2 (the methods it calls are all inlined).
            #[target_feature(enable = "avx2,fma")]
            fn walk_avx2<S: Scalar>(
                tile: &mut BackwardTile,
                splats: &[Splat2d<f32>],
                list: &[u32],
                count: u32,
                slots: &mut [Slot<S>],
                bounds: [u32; 4],
                smooth: bool,
            ) {
                tile.walk_lanes::<avx2::Avx2, S>(splats, list, count, slots, bounds, smooth);
            }
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { walk_avx2(self, splats, list, count, slots, bounds, smooth) };
            return;
        }
        self.walk_lanes::<Portable, S>(splats, list, count, slots, bounds, smooth);
    }

    #[inline(always)]
    fn walk_lanes<V: Lanes, S: Scalar>(
        &mut self,
        splats: &[Splat2d<f32>],
        list: &[u32],
        count: u32,
        slots: &mut [Slot<S>],
        bounds: [u32; 4],
        smooth: bool,
    ) {
        let [x_start, _, y_start, _] = bounds;
        for j in (0..count as usize).rev() {
            if let Some(ahead) = j.checked_sub(PREFETCH_DISTANCE) {
                V::prefetch(&splats[list[ahead] as usize]);
            }
            let splat = &splats[list[j] as usize];
            let (x0, x1, y0, y1) = box_in_tile(splat, bounds);
            let mut acc: LaneGradient<V> = [V::splat(0.0); 10];
            for py in y0..y1 {
                let row_index = (py - y_start) as usize;
                if j as u32 >= self.row_contributors[row_index] {
                    continue;
                }
                let dy = splat.mean[1] - (py as f32 + 0.5);
                let (lo, hi) = row_span(splat, dy, x0, x1);
                if lo >= hi {
                    continue;
                }
                let row = row_index * TS;
                let (g0, g1) = (
                    (lo - x_start) as usize / LANES,
                    ((hi - x_start) as usize).div_ceil(LANES),
                );
                for group in g0..g1 {
                    let column = (x_start as usize + group * LANES) as f32;
                    let base = row + group * LANES;
                    if smooth {
                        self.group::<V, true>(base, splat, column, dy, j as u32, &mut acc);
                    } else {
                        self.group::<V, false>(base, splat, column, dy, j as u32, &mut acc);
                    }
                }
            }
            slots[j] = std::array::from_fn(|k| {
                let mut lanes = [0.0; LANES];
                acc[k].store(&mut lanes);
                let sum = ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5]))
                    + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7]));
                S::from_f64(f64::from(sum))
            });
        }
    }

    /// Backward of one Gaussian (list entry `j`) over the 8 pixels from `base` whose first
    /// column is `column`, accumulating its gradient per lane.
    #[inline(always)]
    fn group<V: Lanes, const SMOOTH: bool>(
        &mut self,
        base: usize,
        splat: &Splat2d<f32>,
        column: f32,
        dy: f32,
        j: u32,
        acc: &mut LaneGradient<V>,
    ) {
        let (dx, composited, gaussian, raw, clamped) = lane_alpha::<V>(splat, column, dy);
        let contributors = V::load(lanes_of(&mut self.contributors, base));
        let valid = composited.and(V::splat(f32::from_bits(j)).less_u32(contributors));
        if valid.mask_bits() == 0 {
            return;
        }
        let zero = V::splat(0.0);
        let (s, ds) = if SMOOTH {
            lane_smooth_step(clamped)
        } else {
            (V::splat(1.0), zero)
        };
        let alpha = if SMOOTH { clamped.mul(s) } else { clamped };
        let inv_one_minus = V::splat(1.0).div(V::splat(1.0).sub(alpha));
        let t_lanes = lanes_of(&mut self.transmittance, base);
        let t_after = V::load(t_lanes);
        let t = t_after.mul(inv_one_minus);
        let weight = alpha.mul(t);
        V::select(valid, t, t_after).store(t_lanes);
        let mut d_alpha = zero;
        for ch in 0..3 {
            let dc = V::load(lanes_of(&mut self.d_colour[ch], base));
            acc[6 + ch] = acc[6 + ch].add(V::select(valid, weight.mul(dc), zero));
            let behind_lanes = lanes_of(&mut self.colour_behind[ch], base);
            let behind = V::load(behind_lanes);
            let colour = V::splat(splat.colour[ch]);
            d_alpha = d_alpha.add(dc.mul(colour.mul(t).sub(behind.mul(inv_one_minus))));
            V::select(valid, behind.add(weight.mul(colour)), behind).store(behind_lanes);
        }
        let d_alpha_up = V::load(lanes_of(&mut self.d_alpha, base));
        let t_final = V::load(lanes_of(&mut self.final_transmittance, base));
        d_alpha = d_alpha.add(d_alpha_up.mul(t_final).mul(inv_one_minus));
        let dd = V::load(lanes_of(&mut self.d_depth, base));
        let depth_lanes = lanes_of(&mut self.depth_behind, base);
        let depth_behind = V::load(depth_lanes);
        let depth = V::splat(splat.depth);
        d_alpha = d_alpha.add(dd.mul(depth.mul(t).sub(depth_behind.mul(inv_one_minus))));
        acc[9] = acc[9].add(V::select(valid, weight.mul(dd), zero));
        V::select(valid, depth_behind.add(weight.mul(depth)), depth_behind).store(depth_lanes);

        // Through the smooth cutoff (tests only) and the 0.99 clamp.
        let d_raw = if SMOOTH {
            d_alpha.mul(s.add(clamped.mul(ds)))
        } else {
            d_alpha
        };
        let passes = valid.and(raw.less(V::splat(ALPHA_MAX)));
        let d_power = V::select(passes, d_raw.mul(raw), zero);
        acc[5] = acc[5].add(V::select(passes, d_raw.mul(gaussian), zero));
        let [ca, cb, cc] = splat.conic;
        let dyv = V::splat(dy);
        let half = V::splat(0.5);
        acc[2] = acc[2].sub(half.mul(dx).mul(dx).mul(d_power));
        acc[3] = acc[3].sub(dx.mul(dyv).mul(d_power));
        acc[4] = acc[4].sub(half.mul(dyv).mul(dyv).mul(d_power));
        acc[0] = acc[0].sub(V::splat(ca).mul(dx).add(V::splat(cb).mul(dyv)).mul(d_power));
        acc[1] = acc[1].sub(V::splat(cb).mul(dx).add(V::splat(cc).mul(dyv)).mul(d_power));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_exp_is_within_two_ulp_of_exp_on_the_rasteriser_range() {
        // Every 97th f32 in [-10, 0], the ends and the points where n changes.
        let mut x = -10.0_f32;
        let mut worst = 0.0_f64;
        while x <= 0.0 {
            let exact = f64::from(x).exp();
            let got = f64::from(fast_exp(x));
            let ulp = f64::from(f32::EPSILON) * exact;
            worst = worst.max((got - exact).abs() / ulp);
            x = f32::from_bits(x.to_bits() - 97);
            if x.to_bits() < 97 {
                break;
            }
        }
        for k in 0..15 {
            let x = -(k as f32) * std::f32::consts::LN_2 * 0.5;
            let exact = f64::from(x).exp();
            let got = f64::from(fast_exp(x));
            worst = worst.max((got - exact).abs() / (f64::from(f32::EPSILON) * exact));
        }
        assert!(worst <= 2.0, "worst error {worst} ulp");
        assert_eq!(fast_exp(0.0), 1.0);
        assert_eq!(fast_exp(-0.0), 1.0);
        // The deep end of the range stays accurate and normal.
        let deep = fast_exp(-87.0);
        assert!((f64::from(deep) / (-87.0_f64).exp() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn out_of_range_arguments_do_not_panic() {
        for x in [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e30,
            -1e30,
            100.0,
        ] {
            std::hint::black_box(fast_exp(x));
        }
    }

    #[test]
    fn smooth_step_matches_the_generic_one() {
        for k in 0..=200 {
            let alpha = k as f32 / 100.0 * THRESHOLD + 0.5 * THRESHOLD;
            let (s, ds) = lane_smooth_step(Portable::splat(alpha));
            let (s_ref, ds_ref) = super::super::raster::smooth_step(alpha);
            assert!(
                (s.0[3] - s_ref).abs() <= 1e-6,
                "{alpha}: {} vs {s_ref}",
                s.0[3]
            );
            assert!((ds.0[5] - ds_ref).abs() <= 1e-6 * ds_ref.abs().max(1.0));
        }
    }

    /// Values that exercise every branch of the lane operations: the exp range and beyond,
    /// signed zeros, infinities, NaN, near-threshold alphas.
    fn awkward_values() -> Vec<f32> {
        let mut values = vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.5,
            0.99,
            THRESHOLD,
            -87.0,
            -100.0,
            100.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e-30,
            -1e30,
            T_MIN,
        ];
        let mut x = 0.123_f32;
        for _ in 0..200 {
            x = (x * 3.7 + 0.31).fract();
            values.push(-12.0 * x);
            values.push(x);
        }
        values
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_lanes_agree_bit_for_bit_with_portable_lanes() {
        if !has_avx2() {
            return;
        }
        fn run<V: Lanes>(a: &[f32; LANES], b: &[f32; LANES]) -> Vec<[u32; LANES]> {
            let (x, y) = (V::load(a), V::load(b));
            let ops = [
                x.add(y),
                x.sub(y),
                x.mul(y),
                x.div(y),
                x.less(y),
                x.less_equal(y),
                x.greater_equal(y),
                x.less_u32(y),
                x.and(y),
                x.or(y),
                x.and_not(y),
                V::select(x.less(y), x, y),
                x.exp(),
                lane_smooth_step(x).0,
                lane_smooth_step(x).1,
            ];
            ops.iter()
                .map(|v| {
                    let mut out = [0.0; LANES];
                    v.store(&mut out);
                    out.map(f32::to_bits)
                })
                .chain([[x.less(y).mask_bits(); LANES]])
                .collect()
        }
        #[target_feature(enable = "avx2,fma")]
        fn run_avx2(a: &[f32; LANES], b: &[f32; LANES]) -> Vec<[u32; LANES]> {
            run::<avx2::Avx2>(a, b)
        }
        let values = awkward_values();
        for (k, chunk) in values.windows(2 * LANES).enumerate().step_by(3) {
            let mut a: [f32; LANES] = chunk[..LANES].try_into().unwrap();
            let mut b: [f32; LANES] = chunk[LANES..].try_into().unwrap();
            if k % 2 == 0 {
                // `less_u32` is defined for bit patterns below 2^31.
                a = a.map(f32::abs);
                b = b.map(f32::abs);
            }
            // SAFETY: AVX2 is available (checked above).
            let fast = unsafe { run_avx2(&a, &b) };
            let portable = run::<Portable>(&a, &b);
            for (op, (f, p)) in fast.iter().zip(&portable).enumerate() {
                // less_u32 (op 7) only for non-negative patterns.
                if op == 7 && k % 2 == 1 {
                    continue;
                }
                assert_eq!(f, p, "op {op}: {a:?} {b:?}");
            }
        }
    }
}
