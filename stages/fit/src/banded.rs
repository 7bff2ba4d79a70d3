//! Symmetric positive definite banded linear systems: assembly and Cholesky solve.
//!
//! The normal equations of a temporal least-squares problem are banded: a residual that
//! couples frames `t - 1`, `t` and `t + 1` (with `block` unknowns per frame) couples unknowns
//! at most `3 * block - 1` apart. Cholesky of an `n x n` matrix of half-bandwidth `p` costs `O(n p^2)`, so a whole
//! sequence is solved in time linear in its length.

/// Why a banded system could not be solved.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BandedError {
    #[error("matrix is not positive definite (pivot {pivot:e} at row {row})")]
    NotPositiveDefinite { row: usize, pivot: f64 },
}

/// Dot product with four partial sums (bounds-check free, pipelines well).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut partial = [0.0; 4];
    let (a4, b4) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = a4
        .remainder()
        .iter()
        .zip(b4.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in a4.zip(b4) {
        for c in 0..4 {
            partial[c] += x[c] * y[c];
        }
    }
    (partial[0] + partial[1]) + (partial[2] + partial[3]) + tail
}

/// A symmetric matrix stored by its lower band: entry `(i, j)` with `j <= i <= j + p`.
#[derive(Clone, Debug)]
pub struct BandedMatrix {
    n: usize,
    half_bandwidth: usize,
    /// Row `i` holds `(i, i - d)` at position `i * (p + 1) + d` for `d` in `0..=p`.
    band: Vec<f64>,
}

impl BandedMatrix {
    /// A zero `n x n` matrix with half-bandwidth `half_bandwidth`.
    pub fn zeros(n: usize, half_bandwidth: usize) -> Self {
        Self {
            n,
            half_bandwidth,
            band: vec![0.0; n * (half_bandwidth + 1)],
        }
    }

    pub fn size(&self) -> usize {
        self.n
    }

    /// Adds `value` to entries `(i, j)` and `(j, i)` (once when `i == j`).
    ///
    /// Panics when `|i - j|` exceeds the bandwidth: that is a bug in the assembly.
    pub fn add(&mut self, i: usize, j: usize, value: f64) {
        let (row, col) = if i >= j { (i, j) } else { (j, i) };
        let d = row - col;
        assert!(
            d <= self.half_bandwidth,
            "entry ({i}, {j}) outside half-bandwidth {}",
            self.half_bandwidth
        );
        self.band[row * (self.half_bandwidth + 1) + d] += value;
    }

    /// Entry `(i, j)` (zero outside the band).
    pub fn get(&self, i: usize, j: usize) -> f64 {
        let (row, col) = if i >= j { (i, j) } else { (j, i) };
        let d = row - col;
        if d > self.half_bandwidth {
            0.0
        } else {
            self.band[row * (self.half_bandwidth + 1) + d]
        }
    }

    /// Solves `A x = b` by banded Cholesky (`A = L L^T`), consuming a copy of the band.
    pub fn solve(&self, rhs: &[f64]) -> Result<Vec<f64>, BandedError> {
        assert_eq!(rhs.len(), self.n, "right-hand side length");
        let p = self.half_bandwidth;
        let stride = p + 1;
        let mut l = self.band.clone();
        // l[i * stride + (i - j)] = L(i, j).
        for i in 0..self.n {
            let first = i.saturating_sub(p);
            for j in first..=i {
                let k_first = first.max(j.saturating_sub(p));
                // sum_k L(i, k) L(j, k) over k in k_first..j: both rows store the run
                // k = j - 1, j - 2, ..., k_first contiguously (`L(r, k)` at `r - k`).
                let run = j - k_first;
                let row_i = &l[i * stride + (i - j + 1)..i * stride + (i - j + 1) + run];
                let row_j = &l[j * stride + 1..j * stride + 1 + run];
                let sum = l[i * stride + (i - j)] - dot(row_i, row_j);
                if i == j {
                    if !(sum > 0.0 && sum.is_finite()) {
                        return Err(BandedError::NotPositiveDefinite { row: i, pivot: sum });
                    }
                    l[i * stride] = sum.sqrt();
                } else {
                    l[i * stride + (i - j)] = sum / l[j * stride];
                }
            }
        }
        // Forward substitution: L y = b.
        let mut x = rhs.to_vec();
        for i in 0..self.n {
            let mut sum = x[i];
            for k in i.saturating_sub(p)..i {
                sum -= l[i * stride + (i - k)] * x[k];
            }
            x[i] = sum / l[i * stride];
        }
        // Back substitution: L^T x = y.
        for i in (0..self.n).rev() {
            let mut sum = x[i];
            for k in i + 1..(i + p + 1).min(self.n) {
                sum -= l[k * stride + (k - i)] * x[k];
            }
            x[i] = sum / l[i * stride];
        }
        Ok(x)
    }
}

#[cfg(test)]
mod tests {
    // Dense reference linear algebra reads best with explicit indices.
    #![allow(clippy::needless_range_loop)]

    use super::*;

    /// Dense Gaussian elimination with partial pivoting, as an independent check.
    fn dense_solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
        let n = b.len();
        for c in 0..n {
            let pivot = (c..n)
                .max_by(|&i, &j| a[i][c].abs().partial_cmp(&a[j][c].abs()).unwrap())
                .unwrap();
            a.swap(c, pivot);
            b.swap(c, pivot);
            for r in c + 1..n {
                let f = a[r][c] / a[c][c];
                for k in c..n {
                    a[r][k] -= f * a[c][k];
                }
                b[r] -= f * b[c];
            }
        }
        let mut x = vec![0.0; n];
        for r in (0..n).rev() {
            let s: f64 = (r + 1..n).map(|k| a[r][k] * x[k]).sum();
            x[r] = (b[r] - s) / a[r][r];
        }
        x
    }

    #[test]
    fn matches_dense_elimination() {
        for (n, p) in [(1, 0), (5, 1), (17, 4), (30, 8), (6, 10)] {
            // A = B^T B + I with B banded is SPD with the same kind of band.
            let mut m = BandedMatrix::zeros(n, p);
            let mut dense = vec![vec![0.0; n]; n];
            let mut seed = 1.0_f64;
            for i in 0..n {
                for j in i.saturating_sub(p)..=i {
                    seed = (seed * 7.31 + 0.17).fract();
                    let v = if i == j {
                        n as f64 + 1.0 + seed
                    } else {
                        seed - 0.5
                    };
                    m.add(i, j, v);
                    dense[i][j] += v;
                    if i != j {
                        dense[j][i] += v;
                    }
                }
            }
            let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
            let x = m.solve(&b).unwrap();
            let expected = dense_solve(dense, b);
            for (a, e) in x.iter().zip(&expected) {
                assert!((a - e).abs() < 1e-10, "n={n} p={p}: {a} vs {e}");
            }
        }
    }

    #[test]
    fn rejects_indefinite_matrices() {
        let mut m = BandedMatrix::zeros(2, 1);
        m.add(0, 0, 1.0);
        m.add(1, 0, 2.0);
        m.add(1, 1, 1.0);
        assert!(matches!(
            m.solve(&[1.0, 1.0]),
            Err(BandedError::NotPositiveDefinite { row: 1, .. })
        ));
        let nan = BandedMatrix {
            n: 1,
            half_bandwidth: 0,
            band: vec![f64::NAN],
        };
        assert!(nan.solve(&[1.0]).is_err());
    }
}
