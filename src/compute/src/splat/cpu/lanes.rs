//! The `f32` speed path of tile compositing and its backward pass: eight pixels of a tile row
//! per step, written as fixed-width lane loops that LLVM vectorises (AVX2, or the same code
//! with AVX-512VL's 32 registers and masks, when the CPU has it, chosen at run time ([`Isa`]);
//! SSE2 otherwise, with bitwise-identical results).
//!
//! The per-pixel math is the contract's (`SPLATTING.md`) in the same operation order as the
//! generic path in `raster.rs`, with two differences that only change `f32` rounding: `exp`
//! is a polynomial ([`fast_exp`], within 2 ulp of `expf` on the range the rasteriser uses),
//! and the backward pass sums a Gaussian's per-pixel gradients per lane (its conic and mean
//! gradients as five moment sums, see [`LaneSums`]) before adding the lanes. Lanes whose
//! pixel does not take part are computed and then neutralised (alpha set to +0, masks), so a
//! Gaussian costs one step per 8-pixel group of its row spans; groups start at the span, not
//! at multiples of 8 ([`row_groups`]). The loops are bound by latency more than by
//! arithmetic: a splat's row spans (square roots) are computed for all rows at once, and the
//! control flow around a group is kept to straight-line code. `f64` runs never come here:
//! gradient checks keep the exact generic path.

// Index loops over lanes are what LLVM vectorises.
#![allow(clippy::needless_range_loop)]

use super::super::{ALPHA_THRESHOLD, MAX_ALPHA, MIN_TRANSMITTANCE, TILE_SIZE};
use super::project::Splat2d;
use super::tile::{PixelState, TileSlots, Upstream, box_in_tile, row_span_f64};
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

/// Binary [`Lanes`] methods, `name(a, b) => body;` for `fn name(self, other: Self) -> Self`
/// with `self` and `other` bound to `a` and `b`, each `#[inline(always)]`.
macro_rules! binary_lanes {
    ($($name:ident($a:ident, $b:ident) => $body:expr;)+) => {$(
        #[inline(always)]
        fn $name(self, other: Self) -> Self {
            let ($a, $b) = (self, other);
            $body
        }
    )+};
}

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
    /// Lanes read as `u32` bit patterns: the larger of `self` and `other`.
    fn max_u32(self, other: Self) -> Self;
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
    binary_lanes! {
        add(x, y) => x.map2(y, |a, b| a + b);
        sub(x, y) => x.map2(y, |a, b| a - b);
        mul(x, y) => x.map2(y, |a, b| a * b);
        div(x, y) => x.map2(y, |a, b| a / b);
        less(x, y) => x.mask(y, |a, b| a < b);
        less_equal(x, y) => x.mask(y, |a, b| a <= b);
        greater_equal(x, y) => x.mask(y, |a, b| a >= b);
        less_u32(x, y) => x.bitwise(y, |a, b| if a < b { u32::MAX } else { 0 });
        max_u32(x, y) => x.bitwise(y, u32::max);
        and(x, y) => x.bitwise(y, |a, b| a & b);
        or(x, y) => x.bitwise(y, |a, b| a | b);
        and_not(x, y) => x.bitwise(y, |a, b| a & !b);
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
    //! functions compiled with `#[target_feature(enable = "avx2,fma,...")]`, which are only
    //! called after [`super::isa`] found those features; these `#[inline(always)]` methods
    //! are inlined into them.
    #![allow(
        clippy::undocumented_unsafe_blocks,
        reason = "one SAFETY note above covers every intrinsic call of this module"
    )]

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
        binary_lanes! {
            add(a, b) => Self(unsafe { _mm256_add_ps(a.0, b.0) });
            sub(a, b) => Self(unsafe { _mm256_sub_ps(a.0, b.0) });
            mul(a, b) => Self(unsafe { _mm256_mul_ps(a.0, b.0) });
            div(a, b) => Self(unsafe { _mm256_div_ps(a.0, b.0) });
            less(a, b) => Self(unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(a.0, b.0) });
            less_equal(a, b) => Self(unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(a.0, b.0) });
            greater_equal(a, b) => Self(unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(a.0, b.0) });
            // Values below 2^31 compare the same signed.
            less_u32(a, b) => Self(unsafe {
                _mm256_castsi256_ps(_mm256_cmpgt_epi32(
                    _mm256_castps_si256(b.0),
                    _mm256_castps_si256(a.0),
                ))
            });
            max_u32(a, b) => Self(unsafe {
                _mm256_castsi256_ps(_mm256_max_epu32(
                    _mm256_castps_si256(a.0),
                    _mm256_castps_si256(b.0),
                ))
            });
            and(a, b) => Self(unsafe { _mm256_and_ps(a.0, b.0) });
            or(a, b) => Self(unsafe { _mm256_or_ps(a.0, b.0) });
            and_not(a, b) => Self(unsafe { _mm256_andnot_ps(b.0, a.0) });
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

/// The instruction sets the lane loops are compiled for, best first. All give bitwise
/// identical results.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Isa {
    /// The [`avx2::Avx2`] lanes compiled with AVX-512VL as well: the same 8-lane operations,
    /// but 32 vector registers (no reloading of constants) and mask registers (cheap masked
    /// stores and selects).
    Avx512,
    /// The [`avx2::Avx2`] lanes (AVX2, FMA in `exp`, POPCNT).
    Avx2,
    /// [`Portable`] lanes.
    Portable,
}

/// The best [`Isa`] this CPU runs, or a lesser one named by the environment variable
/// `SEQAVATAR_SPLAT_ISA` (`avx2` or `portable`; for comparing them in the bench). Decided
/// once per process.
pub(super) fn isa() -> Isa {
    static CHOSEN: std::sync::OnceLock<Isa> = std::sync::OnceLock::new();
    *CHOSEN.get_or_init(|| {
        let best = best_isa();
        match std::env::var("SEQAVATAR_SPLAT_ISA").as_deref() {
            Ok("portable") => Isa::Portable,
            Ok("avx2") if best != Isa::Portable => Isa::Avx2,
            _ => best,
        }
    })
}

/// The best [`Isa`] this CPU runs.
fn best_isa() -> Isa {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") && has!("fma") && has!("popcnt") {
            if has!("avx512f") && has!("avx512vl") {
                return Isa::Avx512;
            }
            return Isa::Avx2;
        }
    }
    Isa::Portable
}

/// Whether the AVX2 lanes can run here.
#[cfg(test)]
fn has_avx2() -> bool {
    best_isa() != Isa::Portable
}

/// Every [`Isa`] this CPU runs.
#[cfg(test)]
pub(super) fn available_isas() -> Vec<Isa> {
    [Isa::Avx512, Isa::Avx2, Isa::Portable]
        .into_iter()
        .filter(|&candidate| match best_isa() {
            Isa::Avx512 => true,
            Isa::Avx2 => candidate != Isa::Avx512,
            Isa::Portable => candidate == Isa::Portable,
        })
        .collect()
}

/// Calls the lane loop `$tile.$method::<V, ..>(args)` with the lanes of `$isa`: on x86-64
/// through a function compiled with that instruction set's features (the lane methods are
/// all `#[inline(always)]`, so they inline into it), elsewhere with [`Portable`] lanes. The
/// arguments are the caller's variables of those names.
macro_rules! on_isa {
    ($isa:expr, $tile:ident: $Tile:ty, $method:ident $(<$S:ident: $bound:path>)? (
        $($arg:ident: $ty:ty),* $(,)?
    )) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2,fma,popcnt")]
            fn avx2_lanes $(<$S: $bound>)? (tile: &mut $Tile, $($arg: $ty),*) {
                tile.$method::<avx2::Avx2 $(, $S)?>($($arg),*);
            }
            /// The same loop with AVX-512VL's registers and masks (see [`Isa::Avx512`]).
            #[target_feature(enable = "avx2,fma,popcnt,avx512f,avx512vl")]
            fn avx512_lanes $(<$S: $bound>)? (tile: &mut $Tile, $($arg: $ty),*) {
                tile.$method::<avx2::Avx2 $(, $S)?>($($arg),*);
            }
            match $isa {
                // SAFETY: the CPU has the features (`isa` found them).
                Isa::Avx512 => return unsafe { avx512_lanes($tile, $($arg),*) },
                // SAFETY: as above.
                Isa::Avx2 => return unsafe { avx2_lanes($tile, $($arg),*) },
                Isa::Portable => {}
            }
        }
        $tile.$method::<Portable $(, $S)?>($($arg),*);
    }};
}

/// The splats in depth order as `f32` and the instruction set to composite them with.
#[derive(Clone, Copy)]
pub(super) struct LanePath<'a> {
    pub splats: &'a [Splat2d<f32>],
    pub isa: Isa,
}

/// `SKIP_MASKS[k]`: the first `k` lanes set (all-ones bits), the others zero.
const SKIP_MASKS: [[f32; LANES]; LANES + 1] = {
    let mut masks = [[0.0_f32; LANES]; LANES + 1];
    let mut k = 0;
    while k <= LANES {
        let mut l = 0;
        while l < k {
            masks[k][l] = f32::from_bits(u32::MAX);
            l += 1;
        }
        k += 1;
    }
    masks
};

// A tile row is covered by at most two groups.
const _: () = assert!(TS <= 2 * LANES && TS >= LANES);

/// The 8-pixel groups that cover tile-local columns `[lo, hi)` of a tile row
/// (`lo < hi <= 16`), as `(first column, lanes to skip)`, and how many there are (the first
/// `count` entries): one group starting at `lo` (moved left to fit in the row), and when the
/// span is wider than 8, a second one ending at `hi` whose first `skip` lanes the first group
/// already covered. Groups start anywhere, not at multiples of 8, so a span of up to 8
/// columns costs one group wherever it lies. Lanes of the first group outside `[lo, hi)` are
/// harmless: the per-pixel contract decides whether they are composited, exactly as for any
/// other pixel. (A fixed array rather than an iterator: the chained iterator's state machine
/// cost about a third of a group's instructions. Not a closure either: closures do not
/// inherit the loops' `target_feature`s, so the lane intrinsics would not inline into them.)
#[inline(always)]
fn row_groups(lo: usize, hi: usize) -> ([(usize, usize); 2], usize) {
    debug_assert!(lo < hi && hi <= TS);
    let first = lo.min(TS - LANES);
    // Meaningful only when there is a second group (then `hi > first + 8 >= 8`).
    let second_start = hi.max(LANES) - LANES;
    let second = (second_start, (first + LANES).saturating_sub(second_start));
    ([(first, 0), second], 1 + usize::from(hi > first + LANES))
}

/// The tile rows a splat's box covers, and on each its tile-local column span `[lo, hi)`
/// (the span of `tile::row_span`, moved to the tile's first column). Spans are computed
/// per row on demand ([`Self::row`]), so rows the loops skip (finished in the forward pass,
/// past their last contributor in the backward pass) cost nothing.
struct TileSpans {
    rows: std::ops::Range<usize>,
    /// `Splat2d::row_span` with the mean moved to the tile's first column.
    constants: [f64; 4],
    /// The box's tile-local columns.
    lo_x: f64,
    hi_x: f64,
    mean_y: f32,
    y_start: u32,
}

impl TileSpans {
    #[inline(always)]
    fn new(splat: &Splat2d<f32>, bounds: [u32; 4]) -> Self {
        let [x_start, _, y_start, _] = bounds;
        let (x0, x1, y0, y1) = box_in_tile(splat, bounds);
        // Exact: the mean is an `f32` and the tile start a small integer.
        let mut constants = splat.row_span;
        constants[0] -= f64::from(x_start);
        let rows = if x0 >= x1 || y0 >= y1 {
            0..0
        } else {
            (y0 - y_start) as usize..((y1 - y_start) as usize).min(TS)
        };
        Self {
            rows,
            constants,
            lo_x: f64::from(x0.saturating_sub(x_start)),
            hi_x: f64::from(x1.saturating_sub(x_start)),
            mean_y: splat.mean[1],
            y_start,
        }
    }

    /// `(dy, lo, hi)` of tile row `r` (one of [`Self::rows`]): `dy = mean_y - row centre` as
    /// the lanes use it, and the span, empty when `lo >= hi`.
    #[inline(always)]
    fn row(&self, r: usize) -> (f32, i32, i32) {
        let dy = self.mean_y - ((self.y_start + r as u32) as f32 + 0.5);
        let (lo, hi) = row_span_f64(&self.constants, f64::from(dy), self.lo_x, self.hi_x);
        // In `[0, 16]`, so the conversions are floors.
        (dy, lo as i32, hi as i32)
    }

    /// [`Self::row`] of all 16 tile rows at once, those outside [`Self::rows`] included
    /// (meaningless there): a fixed-length branch-free loop that vectorises, and whose
    /// square roots overlap instead of each delaying its row's groups (the loops are bound
    /// by latency, not throughput).
    #[inline(always)]
    fn all_rows(&self) -> RowSpans {
        let mut spans = RowSpans {
            dy: [0.0; TS],
            lo: [0; TS],
            hi: [0; TS],
        };
        for r in 0..TS {
            let (dy, lo, hi) = self.row(r);
            spans.dy[r] = dy;
            spans.lo[r] = lo;
            spans.hi[r] = hi;
        }
        spans
    }
}

/// [`TileSpans::row`] of every tile row, one array per quantity.
struct RowSpans {
    dy: [f32; TS],
    lo: [i32; TS],
    hi: [i32; TS],
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

/// One tile's work: its `bounds = [x_start, x_end, y_start, y_end]` and its depth-sorted
/// list of Gaussians.
#[derive(Clone, Copy, Debug)]
pub(super) struct TileList<'a> {
    pub list: &'a [u32],
    pub bounds: [u32; 4],
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
    pub fn composite<S: Scalar>(
        &mut self,
        lanes: LanePath<'_>,
        TileList { list, bounds }: TileList<'_>,
        smooth: bool,
        background: [S; 3],
        width: usize,
        out: ForwardRows<'_, S>,
    ) {
        if smooth {
            self.run::<true>(lanes, list, bounds);
        } else {
            self.run::<false>(lanes, list, bounds);
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

    fn run<const SMOOTH: bool>(&mut self, lanes: LanePath<'_>, list: &[u32], bounds: [u32; 4]) {
        let (splats, smooth) = (lanes.splats, SMOOTH);
        on_isa!(lanes.isa, self: ForwardTile, run_lanes(
            splats: &[Splat2d<f32>],
            list: &[u32],
            bounds: [u32; 4],
            smooth: bool,
        ));
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
            let spans = TileSpans::new(splat, bounds);
            let rows = spans.all_rows();
            for r in spans.rows.clone() {
                let (dy, lo, hi) = (rows.dy[r], rows.lo[r], rows.hi[r]);
                if self.row_active[r] == 0 || lo >= hi {
                    continue;
                }
                let row = r * TS;
                let (groups, count) = row_groups(lo as usize, hi as usize);
                for &(start, skip) in &groups[..count] {
                    let column = (x_start as usize + start) as f32;
                    let base = row + start;
                    let stops = if smooth {
                        self.group::<V, true>(base, splat, column, dy, skip, j as u32 + 1)
                    } else {
                        self.group::<V, false>(base, splat, column, dy, skip, j as u32 + 1)
                    };
                    self.row_active[r] -= stops;
                    active -= stops;
                }
            }
        }
    }

    /// One Gaussian over the 8 pixels from `base` (tile-local) whose first column is
    /// `column`, except the first `skip` lanes (see [`row_groups`]). Returns how many pixels
    /// stopped.
    #[inline(always)]
    fn group<V: Lanes, const SMOOTH: bool>(
        &mut self,
        base: usize,
        splat: &Splat2d<f32>,
        column: f32,
        dy: f32,
        skip: usize,
        rank: u32,
    ) -> u32 {
        let done_lanes = lanes_of(&mut self.done, base);
        let done = V::load(done_lanes).or(V::load(&SKIP_MASKS[skip]));
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
        let one = V::splat(1.0);
        let t_next = t.mul(one.sub(alpha));
        let stop = valid.and(t_next.less_equal(V::splat(T_MIN)));
        let take = valid.and_not(stop);
        // Zero (+0) in lanes that do not take this Gaussian: adding it leaves their colour and
        // depth (finite, non-negative) bit for bit unchanged, and `t (1 - 0)` is `t`, so the
        // stores need no select (a select of the loaded value compiles to an AVX2 masked
        // store, which AMD CPUs microcode).
        let alpha = take.and(alpha);
        let weight = alpha.mul(t);
        t.mul(one.sub(alpha)).store(t_lanes);
        for ch in 0..3 {
            let lanes = lanes_of(&mut self.colour[ch], base);
            let value = V::load(lanes);
            value
                .add(weight.mul(V::splat(splat.colour[ch])))
                .store(lanes);
        }
        let depth_lanes = lanes_of(&mut self.depth, base);
        let depth = V::load(depth_lanes);
        depth
            .add(weight.mul(V::splat(splat.depth)))
            .store(depth_lanes);
        // Ranks grow along the list, so a taking lane's new rank is the larger one.
        let contributor_lanes = lanes_of(&mut self.contributors, base);
        let contributors = V::load(contributor_lanes);
        take.and(V::splat(f32::from_bits(rank)))
            .max_u32(contributors)
            .store(contributor_lanes);
        V::load(done_lanes).or(stop).store(done_lanes);
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
    /// gradient into `slots`. `upstream` must be the one [`Self::load`] read.
    pub fn walk<S: Scalar>(
        &mut self,
        lanes: LanePath<'_>,
        TileList { list, bounds }: TileList<'_>,
        count: u32,
        slots: &mut TileSlots<'_, S>,
        smooth: bool,
        upstream: &Upstream<'_, S>,
    ) {
        let variant = Variant {
            smooth,
            alpha: upstream.alpha.is_some(),
            depth: upstream.depth.is_some(),
        };
        let args = (lanes.splats, list, count, slots, bounds);
        on_isa!(lanes.isa, self: BackwardTile, walk_variant<S: Scalar>(
            args: WalkArgs<'_, '_, S>,
            variant: Variant,
        ));
    }

    /// [`Self::walk_lanes`] compiled for the variant (each drops the work it does not need).
    #[inline(always)]
    fn walk_variant<V: Lanes, S: Scalar>(&mut self, args: WalkArgs<'_, '_, S>, variant: Variant) {
        match (variant.smooth, variant.alpha, variant.depth) {
            (false, false, false) => self.walk_lanes::<V, S, false, false, false>(args),
            (false, true, false) => self.walk_lanes::<V, S, false, true, false>(args),
            (false, false, true) => self.walk_lanes::<V, S, false, false, true>(args),
            (false, true, true) => self.walk_lanes::<V, S, false, true, true>(args),
            (true, false, false) => self.walk_lanes::<V, S, true, false, false>(args),
            (true, true, false) => self.walk_lanes::<V, S, true, true, false>(args),
            (true, false, true) => self.walk_lanes::<V, S, true, false, true>(args),
            (true, true, true) => self.walk_lanes::<V, S, true, true, true>(args),
        }
    }

    /// The walk for the smooth cutoff (`SMOOTH`, tests only) and upstream alpha (`ALPHA`)
    /// and depth (`DEPTH`) gradients present or not.
    #[inline(always)]
    fn walk_lanes<V: Lanes, S: Scalar, const SMOOTH: bool, const ALPHA: bool, const DEPTH: bool>(
        &mut self,
        (splats, list, count, slots, bounds): WalkArgs<'_, '_, S>,
    ) {
        let x_start = bounds[0];
        for j in (0..count as usize).rev() {
            if let Some(ahead) = j.checked_sub(PREFETCH_DISTANCE) {
                V::prefetch(&splats[list[ahead] as usize]);
            }
            let splat = &splats[list[j] as usize];
            let spans = TileSpans::new(splat, bounds);
            let mut acc: LaneSums<V> = [V::splat(0.0); 10];
            let rows = spans.all_rows();
            for r in spans.rows.clone() {
                let (dy, lo, hi) = (rows.dy[r], rows.lo[r], rows.hi[r]);
                if j as u32 >= self.row_contributors[r] || lo >= hi {
                    continue;
                }
                let row = r * TS;
                let (groups, count) = row_groups(lo as usize, hi as usize);
                for &(start, skip) in &groups[..count] {
                    let column = (x_start as usize + start) as f32;
                    self.group::<V, SMOOTH, ALPHA, DEPTH>(
                        row + start,
                        splat,
                        (column, dy),
                        skip,
                        j as u32,
                        &mut acc,
                    );
                }
            }
            let sum = |k: usize| {
                let mut lanes = [0.0; LANES];
                acc[k].store(&mut lanes);
                lanes.iter().map(|&v| f64::from(v)).sum::<f64>()
            };
            // See [`LaneSums`]: the power's gradient is `opacity q`.
            let opacity = f64::from(splat.opacity);
            let [ca, cb, cc] = splat.conic.map(f64::from);
            let (sx, sy) = (opacity * sum(SUM_QX), opacity * sum(SUM_QY));
            let grad: [f64; 10] = [
                -(ca * sx + cb * sy),
                -(cb * sx + cc * sy),
                -0.5 * opacity * sum(SUM_QXX),
                -opacity * sum(SUM_QXY),
                -0.5 * opacity * sum(SUM_QYY),
                sum(SUM_Q),
                sum(SUM_COLOUR),
                sum(SUM_COLOUR + 1),
                sum(SUM_COLOUR + 2),
                sum(SUM_DEPTH),
            ];
            slots.put(j, grad.map(S::from_f64));
        }
    }

    /// Backward of one Gaussian (list entry `j`) over the 8 pixels from `base` whose first
    /// pixel is at `(column, dy)`, except the first `skip` lanes (see [`row_groups`]), adding to its
    /// per-lane sums.
    #[inline(always)]
    fn group<V: Lanes, const SMOOTH: bool, const ALPHA: bool, const DEPTH: bool>(
        &mut self,
        base: usize,
        splat: &Splat2d<f32>,
        (column, dy): (f32, f32),
        skip: usize,
        j: u32,
        acc: &mut LaneSums<V>,
    ) {
        let contributors = V::load(lanes_of(&mut self.contributors, base));
        let taking_part = V::splat(f32::from_bits(j))
            .less_u32(contributors)
            .and_not(V::load(&SKIP_MASKS[skip]));
        if taking_part.mask_bits() == 0 {
            return;
        }
        let (dx, composited, gaussian, raw, clamped) = lane_alpha::<V>(splat, column, dy);
        let valid = composited.and(taking_part);
        if valid.mask_bits() == 0 {
            return;
        }
        let zero = V::splat(0.0);
        let one = V::splat(1.0);
        let (s, ds) = if SMOOTH {
            lane_smooth_step(clamped)
        } else {
            (one, zero)
        };
        // Zero (+0) in the lanes that do not take part: there `1 / (1 - alpha)` is exactly 1
        // and the weight is 0, so the transmittance and the sums behind keep their bits and
        // the stores need no select. Upstream gradients are finite (checked), so the
        // gradient sums get zeros from those lanes.
        let alpha = valid.and(if SMOOTH { clamped.mul(s) } else { clamped });
        let inv_one_minus = one.div(one.sub(alpha));
        let t_lanes = lanes_of(&mut self.transmittance, base);
        let t = V::load(t_lanes).mul(inv_one_minus);
        t.store(t_lanes);
        let weight = alpha.mul(t);
        let mut d_alpha = zero;
        for ch in 0..3 {
            let dc = V::load(lanes_of(&mut self.d_colour[ch], base));
            acc[SUM_COLOUR + ch] = acc[SUM_COLOUR + ch].add(weight.mul(dc));
            let behind_lanes = lanes_of(&mut self.colour_behind[ch], base);
            let behind = V::load(behind_lanes);
            let colour = V::splat(splat.colour[ch]);
            d_alpha = d_alpha.add(dc.mul(colour.mul(t).sub(behind.mul(inv_one_minus))));
            behind.add(weight.mul(colour)).store(behind_lanes);
        }
        if ALPHA {
            let d_alpha_up = V::load(lanes_of(&mut self.d_alpha, base));
            let t_final = V::load(lanes_of(&mut self.final_transmittance, base));
            d_alpha = d_alpha.add(d_alpha_up.mul(t_final).mul(inv_one_minus));
        }
        if DEPTH {
            let dd = V::load(lanes_of(&mut self.d_depth, base));
            let depth_lanes = lanes_of(&mut self.depth_behind, base);
            let depth_behind = V::load(depth_lanes);
            let depth = V::splat(splat.depth);
            d_alpha = d_alpha.add(dd.mul(depth.mul(t).sub(depth_behind.mul(inv_one_minus))));
            acc[SUM_DEPTH] = acc[SUM_DEPTH].add(weight.mul(dd));
            depth_behind.add(weight.mul(depth)).store(depth_lanes);
        }

        // Through the smooth cutoff (tests only) and the 0.99 clamp.
        let d_raw = if SMOOTH {
            d_alpha.mul(s.add(clamped.mul(ds)))
        } else {
            d_alpha
        };
        let passes = valid.and(raw.less(V::splat(ALPHA_MAX)));
        let q = passes.and(d_raw.mul(gaussian));
        acc[SUM_Q] = acc[SUM_Q].add(q);
        let dyv = V::splat(dy);
        let qx = q.mul(dx);
        let qy = q.mul(dyv);
        acc[SUM_QX] = acc[SUM_QX].add(qx);
        acc[SUM_QY] = acc[SUM_QY].add(qy);
        acc[SUM_QXX] = acc[SUM_QXX].add(qx.mul(dx));
        acc[SUM_QXY] = acc[SUM_QXY].add(qx.mul(dyv));
        acc[SUM_QYY] = acc[SUM_QYY].add(qy.mul(dyv));
    }
}

/// The backward walk's splats, tile list, entry count, gradient slots and tile bounds.
type WalkArgs<'a, 'b, S> = (
    &'a [Splat2d<f32>],
    &'a [u32],
    u32,
    &'a mut TileSlots<'b, S>,
    [u32; 4],
);

/// Which specialisation of the backward walk runs.
#[derive(Clone, Copy)]
struct Variant {
    smooth: bool,
    alpha: bool,
    depth: bool,
}

/// Per-lane partial sums of one Gaussian's gradient over a tile. With `q = dL/draw *
/// exp(power)` per pixel (the opacity gradient), the power's gradient is `opacity q` and the
/// conic and mean gradients are linear in `q dx`, `q dy`, `q dx^2`, `q dx dy`, `q dy^2`
/// (`d = mean - pixel centre`): `dL/dconic = -opacity (sum q dx^2 / 2, sum q dx dy,
/// sum q dy^2 / 2)`, `dL/dmean = -opacity conic (sum q dx, sum q dy)`. Summing those five
/// and scaling once per Gaussian costs fewer operations per pixel than the per-pixel form.
type LaneSums<V> = [V; 10];
const SUM_QX: usize = 0;
const SUM_QY: usize = 1;
const SUM_QXX: usize = 2;
const SUM_QXY: usize = 3;
const SUM_QYY: usize = 4;
const SUM_Q: usize = 5;
const SUM_COLOUR: usize = 6;
const SUM_DEPTH: usize = 9;

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
    fn row_groups_cover_every_span_column_exactly_once_inside_the_row() {
        for lo in 0..TS {
            for hi in lo + 1..=TS {
                let mut covered = [0; TS];
                let (groups, count) = row_groups(lo, hi);
                for &(start, skip) in &groups[..count] {
                    assert!(start + LANES <= TS, "{lo}..{hi}: group at {start}");
                    assert!(skip < LANES);
                    for column in start + skip..start + LANES {
                        covered[column] += 1;
                    }
                }
                for (column, &count) in covered.iter().enumerate() {
                    let expected = usize::from((lo..hi).contains(&column));
                    // Columns outside the span may be visited once (the contract decides).
                    assert!(
                        count == expected || (expected == 0 && count == 1),
                        "{lo}..{hi}: column {column} visited {count} times"
                    );
                }
                assert!(count <= (hi - lo).div_ceil(LANES).max(1));
            }
        }
    }

    #[test]
    fn tile_spans_are_the_row_spans_of_the_box_rows() {
        use super::super::tile::row_span;
        let mut rng = crate::splat::scene::SplitMix64::new(11);
        for _ in 0..500 {
            let mean = [
                rng.uniform(-20.0, 60.0) as f32,
                rng.uniform(-20.0, 60.0) as f32,
            ];
            let (sx, sy) = (rng.uniform(0.6, 12.0), rng.uniform(0.6, 12.0));
            let b = rng.uniform(-0.9, 0.9) * sx * sy;
            let (a, c) = (sx * sx, sy * sy);
            let det = a * c - b * b;
            let conic = [(c / det) as f32, (-b / det) as f32, (a / det) as f32];
            let opacity = rng.uniform(0.01, 1.0) as f32;
            let min_power = (THRESHOLD / opacity).ln() - 0.01;
            let radius = [3.33 * sx, 3.33 * sy];
            let range = |m: f32, r: f64| {
                let lo = (f64::from(m) - r - 1.0).floor().clamp(0.0, 48.0) as u32;
                let hi = (f64::from(m) + r + 1.0).ceil().clamp(0.0, 48.0) as u32;
                (lo, hi)
            };
            let ((x_lo, x_hi), (y_lo, y_hi)) =
                (range(mean[0], radius[0]), range(mean[1], radius[1]));
            let splat = Splat2d::<f32> {
                mean,
                conic,
                opacity,
                colour: [0.5; 3],
                depth: 1.0,
                min_power,
                pixel_box: [x_lo, x_hi, y_lo, y_hi],
                row_span: super::super::project::row_span_constants(mean[0], conic, min_power),
            };
            for (tx, ty) in [(0, 0), (16, 16), (32, 16), (32, 32)] {
                // The last tile column is partial (image 44 wide).
                let bounds = [tx, (tx + 16).min(44), ty, ty + 16];
                let spans = TileSpans::new(&splat, bounds);
                let (x0, x1, y0, y1) = box_in_tile(&splat, bounds);
                if x0 >= x1 || y0 >= y1 {
                    assert!(spans.rows.is_empty());
                    continue;
                }
                assert_eq!(spans.rows, (y0 - ty) as usize..(y1 - ty) as usize);
                for py in y0..y1 {
                    let r = (py - ty) as usize;
                    let (lo, hi) = row_span(&splat, mean[1] - (py as f32 + 0.5), x0, x1);
                    let (lo, hi) = (lo - tx, hi - tx);
                    let (dy, span_lo, span_hi) = spans.row(r);
                    let all = spans.all_rows();
                    assert_eq!((all.dy[r], all.lo[r], all.hi[r]), (dy, span_lo, span_hi));
                    assert_eq!(dy, mean[1] - (py as f32 + 0.5));
                    if lo < hi {
                        assert_eq!((span_lo, span_hi), (lo as i32, hi as i32));
                    } else {
                        assert!(span_lo >= span_hi);
                    }
                }
            }
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
                x.max_u32(y),
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
        #[target_feature(enable = "avx2,fma,popcnt")]
        fn run_avx2(a: &[f32; LANES], b: &[f32; LANES]) -> Vec<[u32; LANES]> {
            run::<avx2::Avx2>(a, b)
        }
        #[target_feature(enable = "avx2,fma,popcnt,avx512f,avx512vl")]
        fn run_avx512(a: &[f32; LANES], b: &[f32; LANES]) -> Vec<[u32; LANES]> {
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
            let portable = run::<Portable>(&a, &b);
            // SAFETY: AVX2 is available (checked above).
            let mut fast = vec![("avx2", unsafe { run_avx2(&a, &b) })];
            if best_isa() == Isa::Avx512 {
                // SAFETY: AVX-512VL is available (checked just above).
                fast.push(("avx512", unsafe { run_avx512(&a, &b) }));
            }
            for (isa, fast) in fast {
                for (op, (f, p)) in fast.iter().zip(&portable).enumerate() {
                    // less_u32 (op 7) only for non-negative patterns.
                    if op == 7 && k % 2 == 1 {
                        continue;
                    }
                    assert_eq!(f, p, "{isa} op {op}: {a:?} {b:?}");
                }
            }
        }
    }
}
