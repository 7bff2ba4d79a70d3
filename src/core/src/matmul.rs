//! The one matrix product of the workspace: a safe, bounds-checked front of `gemm`.
//!
//! `gemm::gemm` takes raw pointers and strides, so every call is `unsafe` and its caller
//! must prove that every element it reads or writes lies inside live memory and that the
//! destination neither aliases the operands nor overlaps itself. [`matmul`] proves that
//! once, from slices and [`Layout`]s, and is the only `unsafe` gemm site: the dense layers
//! (`compute::nn::linear`), the LPIPS convolutions (`compute::lpips::cpu`) and the batched
//! pose blend shapes (`motion::pose`) all go through it.

pub use gemm::Parallelism;

mod sealed {
    /// The constants `matmul` passes to gemm, under names that cannot clash with the
    /// `ZERO`/`ONE` of a caller's own scalar trait.
    pub trait Sealed: Sized {
        const GEMM_ZERO: Self;
        const GEMM_ONE: Self;
    }
    impl Sealed for f32 {
        const GEMM_ZERO: Self = 0.0;
        const GEMM_ONE: Self = 1.0;
    }
    impl Sealed for f64 {
        const GEMM_ZERO: Self = 0.0;
        const GEMM_ONE: Self = 1.0;
    }
}

/// The real element types `gemm` multiplies: `f32` and `f64`.
pub trait MatmulScalar: Copy + Send + Sync + 'static + sealed::Sealed {}

impl MatmulScalar for f32 {}

impl MatmulScalar for f64 {}

/// Where a `rows x cols` matrix lies in a slice: element `(i, j)` is at
/// `offset + i * row_stride + j * col_stride`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    /// Index of element `(0, 0)`.
    pub offset: usize,
    pub rows: usize,
    pub cols: usize,
    /// Distance in elements between vertically adjacent elements.
    pub row_stride: usize,
    /// Distance in elements between horizontally adjacent elements.
    pub col_stride: usize,
}

impl Layout {
    /// A dense row-major `rows x cols` matrix at offset 0.
    pub fn row_major(rows: usize, cols: usize) -> Self {
        Layout::strided(rows, cols, cols, 1)
    }

    /// A `rows x cols` matrix with the given strides, at offset 0.
    pub fn strided(rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> Self {
        Layout {
            offset: 0,
            rows,
            cols,
            row_stride,
            col_stride,
        }
    }

    /// The same matrix starting at `offset`.
    pub fn at(self, offset: usize) -> Self {
        Layout { offset, ..self }
    }

    /// The index one past the last element, `None` for an empty matrix or on overflow.
    fn end(&self) -> Option<usize> {
        if self.rows == 0 || self.cols == 0 {
            return Some(0);
        }
        (self.rows - 1)
            .checked_mul(self.row_stride)?
            .checked_add((self.cols - 1).checked_mul(self.col_stride)?)?
            .checked_add(self.offset)?
            .checked_add(1)
    }

    /// Whether every element lies inside a slice of `len` elements.
    fn fits(&self, len: usize) -> bool {
        self.end().is_some_and(|end| end <= len)
    }

    /// Whether no two elements share an index (the dimensions of extent above 1, ordered by
    /// stride, nest without interleaving).
    fn is_injective(&self) -> bool {
        let mut dims: Vec<(usize, usize)> =
            [(self.rows, self.row_stride), (self.cols, self.col_stride)]
                .into_iter()
                .filter(|&(extent, _)| extent > 1)
                .collect();
        dims.sort_by_key(|&(_, stride)| stride);
        match dims.as_slice() {
            [] => true,
            [(_, stride)] => *stride >= 1,
            [(inner_extent, inner_stride), (_, outer_stride)] => {
                *inner_stride >= 1
                    && inner_stride
                        .checked_mul(*inner_extent)
                        .is_some_and(|span| *outer_stride >= span)
            }
            _ => unreachable!("a matrix has two dimensions"),
        }
    }
}

/// `gemm`'s own threads for a product of `multiply_adds` (`m n k`) when it is large enough
/// to pay for them (over 2^20) and rayon has more than one thread; otherwise none.
pub fn parallelism_for(multiply_adds: usize) -> Parallelism {
    let threads = rayon::current_num_threads();
    if threads > 1 && multiply_adds > 1 << 20 {
        Parallelism::Rayon(threads)
    } else {
        Parallelism::None
    }
}

fn stride(value: usize, operand: &str) -> isize {
    isize::try_from(value)
        .unwrap_or_else(|_| panic!("matmul: {operand} stride {value} exceeds isize"))
}

/// A read-only matrix: a slice and where the matrix lies in it.
#[derive(Clone, Copy, Debug)]
pub struct Matrix<'a, T> {
    pub data: &'a [T],
    /// Where the matrix lies in `data`.
    pub layout: Layout,
}

/// A matrix to write: a unique slice and where the matrix lies in it.
#[derive(Debug)]
pub struct MatrixMut<'a, T> {
    pub data: &'a mut [T],
    /// Where the matrix lies in `data`.
    pub layout: Layout,
}

impl<'a, T> Matrix<'a, T> {
    /// The matrix at `layout` in `data`.
    pub fn new(data: &'a [T], layout: Layout) -> Self {
        Matrix { data, layout }
    }
}

impl<'a, T> MatrixMut<'a, T> {
    /// The matrix at `layout` in `data`.
    pub fn new(data: &'a mut [T], layout: Layout) -> Self {
        MatrixMut { data, layout }
    }
}

/// `dst = lhs rhs`, or `dst += lhs rhs` when `accumulate`.
///
/// # Panics
///
/// On inconsistent shapes (`lhs` is `m x k`, `rhs` `k x n`, `dst` `m x n`), on a layout
/// reaching past its slice, and on a destination layout that maps two elements to one index.
/// Callers validate user inputs before, so a panic here is a broken internal invariant.
pub fn matmul<T: MatmulScalar>(
    dst: MatrixMut<'_, T>,
    lhs: Matrix<'_, T>,
    rhs: Matrix<'_, T>,
    accumulate: bool,
    parallelism: Parallelism,
) {
    let MatrixMut {
        data: dst,
        layout: dst_layout,
    } = dst;
    let Matrix {
        data: lhs,
        layout: lhs_layout,
    } = lhs;
    let Matrix {
        data: rhs,
        layout: rhs_layout,
    } = rhs;
    let (m, n, k) = (dst_layout.rows, dst_layout.cols, lhs_layout.cols);
    assert!(
        lhs_layout.rows == m && rhs_layout.rows == k && rhs_layout.cols == n,
        "matmul: shapes do not chain: dst {m}x{n}, lhs {}x{}, rhs {}x{}",
        lhs_layout.rows,
        lhs_layout.cols,
        rhs_layout.rows,
        rhs_layout.cols
    );
    assert!(
        dst_layout.fits(dst.len()),
        "matmul: dst layout {dst_layout:?} exceeds its {} elements",
        dst.len()
    );
    assert!(
        lhs_layout.fits(lhs.len()),
        "matmul: lhs layout {lhs_layout:?} exceeds its {} elements",
        lhs.len()
    );
    assert!(
        rhs_layout.fits(rhs.len()),
        "matmul: rhs layout {rhs_layout:?} exceeds its {} elements",
        rhs.len()
    );
    assert!(
        dst_layout.is_injective(),
        "matmul: dst layout {dst_layout:?} maps several elements to one index"
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        // An empty sum: gemm is not asked to handle it.
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    dst[dst_layout.offset
                        + i * dst_layout.row_stride
                        + j * dst_layout.col_stride] = T::GEMM_ZERO;
                }
            }
        }
        return;
    }
    // SAFETY: the assertions above keep every element gemm reads (`lhs`, `rhs`, and `dst`
    // when accumulating) or writes (`dst`) inside its slice, with strides that fit `isize`.
    // `dst` is a unique borrow, so it aliases neither shared operand, and its layout is
    // injective, so no two (possibly parallel) writes land on one element.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr().add(dst_layout.offset),
            stride(dst_layout.col_stride, "dst column"),
            stride(dst_layout.row_stride, "dst row"),
            accumulate,
            lhs.as_ptr().add(lhs_layout.offset),
            stride(lhs_layout.col_stride, "lhs column"),
            stride(lhs_layout.row_stride, "lhs row"),
            rhs.as_ptr().add(rhs_layout.offset),
            stride(rhs_layout.col_stride, "rhs column"),
            stride(rhs_layout.row_stride, "rhs row"),
            T::GEMM_ONE,
            T::GEMM_ONE,
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn random(rng: &mut SplitMix64, len: usize) -> Vec<f64> {
        (0..len).map(|_| rng.next_f64() * 2.0 - 1.0).collect()
    }

    fn get(data: &[f64], layout: Layout, i: usize, j: usize) -> f64 {
        data[layout.offset + i * layout.row_stride + j * layout.col_stride]
    }

    /// The triple loop, in f64, with the same layouts.
    fn naive(
        dst: &mut [f64],
        dst_layout: Layout,
        lhs: &[f64],
        lhs_layout: Layout,
        rhs: &[f64],
        rhs_layout: Layout,
        accumulate: bool,
    ) {
        for i in 0..dst_layout.rows {
            for j in 0..dst_layout.cols {
                let sum: f64 = (0..lhs_layout.cols)
                    .map(|p| get(lhs, lhs_layout, i, p) * get(rhs, rhs_layout, p, j))
                    .sum();
                let index =
                    dst_layout.offset + i * dst_layout.row_stride + j * dst_layout.col_stride;
                dst[index] = if accumulate { dst[index] + sum } else { sum };
            }
        }
    }

    #[test]
    fn matches_the_triple_loop_for_strided_offset_and_transposed_operands() {
        let mut rng = SplitMix64::new(3);
        for &(m, n, k) in &[(1, 1, 1), (5, 7, 3), (17, 1, 9), (1, 13, 4), (33, 29, 65)] {
            for accumulate in [false, true] {
                for parallelism in [Parallelism::None, Parallelism::Rayon(2)] {
                    // lhs stored transposed with a padded stride, rhs row-major at an offset,
                    // dst column-major with padding between columns.
                    let lhs_layout = Layout::strided(m, k, 1, m + 2).at(1);
                    let rhs_layout = Layout::row_major(k, n).at(5);
                    let dst_layout = Layout::strided(m, n, 1, m + 3).at(2);
                    let lhs = random(&mut rng, 1 + (m + 2) * k);
                    let rhs = random(&mut rng, 5 + k * n);
                    let start = random(&mut rng, 2 + (m + 3) * n);
                    let mut expected = start.clone();
                    naive(
                        &mut expected,
                        dst_layout,
                        &lhs,
                        lhs_layout,
                        &rhs,
                        rhs_layout,
                        accumulate,
                    );
                    let mut dst = start.clone();
                    matmul(
                        MatrixMut::new(&mut dst, dst_layout),
                        Matrix::new(&lhs, lhs_layout),
                        Matrix::new(&rhs, rhs_layout),
                        accumulate,
                        parallelism,
                    );
                    for (index, (got, want)) in dst.iter().zip(&expected).enumerate() {
                        assert!(
                            (got - want).abs() <= 1e-12 * (1.0 + want.abs()),
                            "{m}x{n}x{k} accumulate={accumulate} [{index}]: {got} vs {want}"
                        );
                    }
                    // The padding between the destination's columns is untouched.
                    assert_eq!(dst[0], start[0]);
                    assert_eq!(dst[2 + m], start[2 + m]);
                }
            }
        }
    }

    #[test]
    fn f32_matches_f64() {
        let mut rng = SplitMix64::new(9);
        let (m, n, k) = (6, 10, 70);
        let lhs = random(&mut rng, m * k);
        let rhs = random(&mut rng, k * n);
        let mut expected = vec![0.0; m * n];
        let (a, b, c) = (
            Layout::row_major(m, k),
            Layout::row_major(k, n),
            Layout::row_major(m, n),
        );
        naive(&mut expected, c, &lhs, a, &rhs, b, false);
        let to_f32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let mut dst = vec![f32::NAN; m * n];
        let (lhs, rhs) = (to_f32(&lhs), to_f32(&rhs));
        matmul(
            MatrixMut::new(&mut dst, c),
            Matrix::new(&lhs, a),
            Matrix::new(&rhs, b),
            false,
            Parallelism::None,
        );
        for (got, want) in dst.iter().zip(&expected) {
            assert!((*got as f64 - want).abs() < 1e-4, "{got} vs {want}");
        }
    }

    #[test]
    fn an_empty_inner_dimension_zeroes_or_keeps_the_destination() {
        let layout = Layout::strided(2, 3, 4, 1);
        let mut dst = vec![7.0f64; 8];
        matmul(
            MatrixMut::new(&mut dst, layout),
            Matrix::new(&[], Layout::row_major(2, 0)),
            Matrix::new(&[], Layout::row_major(0, 3)),
            true,
            Parallelism::None,
        );
        assert_eq!(dst, vec![7.0; 8]);
        matmul(
            MatrixMut::new(&mut dst, layout),
            Matrix::new(&[], Layout::row_major(2, 0)),
            Matrix::new(&[], Layout::row_major(0, 3)),
            false,
            Parallelism::None,
        );
        assert_eq!(dst, vec![0.0, 0.0, 0.0, 7.0, 0.0, 0.0, 0.0, 7.0]);
    }

    #[test]
    fn an_empty_destination_touches_nothing() {
        let mut dst: Vec<f32> = Vec::new();
        matmul(
            MatrixMut::new(&mut dst, Layout::row_major(0, 3)),
            Matrix::new(&[], Layout::row_major(0, 2)),
            Matrix::new(&[1.0; 6], Layout::row_major(2, 3)),
            false,
            Parallelism::None,
        );
    }

    #[test]
    #[should_panic(expected = "rhs layout")]
    fn rejects_an_operand_past_its_slice() {
        let mut dst = vec![0.0f32; 4];
        let rhs = vec![1.0f32; 3];
        matmul(
            MatrixMut::new(&mut dst, Layout::row_major(2, 2)),
            Matrix::new(&[1.0; 4], Layout::row_major(2, 2)),
            Matrix::new(&rhs, Layout::row_major(2, 2)),
            false,
            Parallelism::None,
        );
    }

    #[test]
    #[should_panic(expected = "maps several elements")]
    fn rejects_an_overlapping_destination() {
        let mut dst = vec![0.0f32; 4];
        matmul(
            MatrixMut::new(&mut dst, Layout::strided(2, 2, 1, 1)),
            Matrix::new(&[1.0; 4], Layout::row_major(2, 2)),
            Matrix::new(&[1.0; 4], Layout::row_major(2, 2)),
            false,
            Parallelism::None,
        );
    }

    #[test]
    #[should_panic(expected = "do not chain")]
    fn rejects_shapes_that_do_not_chain() {
        let mut dst = vec![0.0f32; 4];
        matmul(
            MatrixMut::new(&mut dst, Layout::row_major(2, 2)),
            Matrix::new(&[1.0; 6], Layout::row_major(2, 3)),
            Matrix::new(&[1.0; 4], Layout::row_major(2, 2)),
            false,
            Parallelism::None,
        );
    }

    #[test]
    fn injectivity_and_bounds_of_layouts() {
        assert!(Layout::row_major(3, 4).is_injective());
        assert!(Layout::strided(3, 4, 1, 3).is_injective());
        assert!(!Layout::strided(3, 4, 2, 1).is_injective());
        assert!(Layout::strided(1, 4, 0, 1).is_injective());
        assert!(!Layout::strided(3, 1, 0, 1).is_injective());
        assert!(Layout::row_major(3, 4).fits(12));
        assert!(!Layout::row_major(3, 4).at(1).fits(12));
        assert!(!Layout::strided(2, 2, usize::MAX, 1).fits(usize::MAX));
        assert!(Layout::row_major(0, 4).fits(0));
    }
}
