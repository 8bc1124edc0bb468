//! Least squares, in one place: the workspace's linear fits and their covariances.
//!
//! * [`lsq`]: the workhorse. Minimises `chi2(beta) = |y - M beta|^2` for a design `M`
//!   (n x p) whose rows are already whitened (divided by their standard deviation, or
//!   multiplied by `sqrt(w)` for weights `w`: see [`weighted`]). The columns are scaled to
//!   unit norm first, `M = Ms D` with `D = diag(|m_j|)`, so that units do not decide the rank;
//!   then a Householder QR `Ms = Q R` and the SVD of the p x p triangle `R = U S V^T`.
//!   Singular values at or below `tol * s_max` are dropped (a truncated pseudo-inverse):
//!   `beta = D^-1 V S^+ U^T Q^T y`, `cov = D^-1 V S^+2 V^T D^-1`, which is `(M^T M)^-1` at
//!   full rank (below it, the pseudo-inverse taken in the scaled columns); the rank and the
//!   dropped directions (the *ties*: moving `beta` along one leaves the fit unchanged) are
//!   reported. QR first because the SVD of the long design itself would sweep every rotation
//!   across all n rows.
//! * [`weighted`]: the same with weights per row: `chi2 = sum_i w_i (y_i - m_i beta)^2`,
//!   `cov = (M^T W M)^-1`.
//! * [`constrained`]: the same under exact linear constraints `C beta = 0` (a gauge), by
//!   projecting the design onto the constraints' null space.
//! * [`ridge`] and [`least_squares`]: ridge regression on columns scaled to unit mean square,
//!   `(Xs^T Xs + lambda I) b = Xs^T y`, by Cholesky; the second with a vanishing ridge, so
//!   that a collinear design still gives a usable, if arbitrary, split of its gain where the
//!   truncated solve would report the tie.
//! * [`posterior`]: the Bayesian ridge with a prior precision per column and a weight per
//!   row, `A = Lambda + sum_i w_i x_i x_i^T`, `A beta = sum_i w_i y_i x_i`, by Cholesky.
//! * Subspace helpers built on the same factorisation: [`thin_svd`], [`basis`], [`scan`],
//!   [`beyond`], [`residual_of`], [`redundant_part`], [`hstack`].
//!
//! Pure: no I/O.

use nalgebra::{DMatrix, DVector};

/// Singular values at or below this fraction of the largest count as zero in [`lsq`]: far
/// above the rounding of the QR and SVD (about 1e-15), far below any design worth fitting.
pub const RANK_TOL: f64 = 1e-9;

/// Why a fit has no answer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LeastSquaresError {
    #[error("{rows} rows for {cols} unknowns: more rows than unknowns needed")]
    TooFewRows { rows: usize, cols: usize },
    #[error("{got} entries for a design of {rows} rows")]
    Length { rows: usize, got: usize },
    #[error("the normal equations are singular")]
    Singular,
    #[error("the solution is not finite")]
    NonFinite,
}

/// A least-squares fit on column-scaled designs (see the module documentation).
#[derive(Debug, Clone)]
pub struct Lsq {
    /// The minimum-norm (in the scaled columns) least-squares solution.
    pub beta: DVector<f64>,
    /// `(M^T M)^-1` at full rank (the pseudo-inverse in the scaled columns below it), in the
    /// parameters' own units: the covariance of `beta` for whitened rows.
    pub cov: DMatrix<f64>,
    /// `|y - M beta|^2`.
    pub chi2: f64,
    /// The number of singular values kept.
    pub rank: usize,
    /// The directions the design cannot see, in the parameters' own units: `M t ~ 0` for each
    /// (unit norm in the scaled columns, so comparable across units; `p - rank` of them), each
    /// signed so that the first of its largest components is positive.
    pub ties: Vec<DVector<f64>>,
}

/// Least squares with the default rank tolerance [`RANK_TOL`].
pub fn lsq(m: &DMatrix<f64>, y: &DVector<f64>) -> Lsq {
    lsq_with_tol(m, y, RANK_TOL)
}

/// Least squares keeping the singular values above `tol * s_max` of the column-scaled design.
pub fn lsq_with_tol(m: &DMatrix<f64>, y: &DVector<f64>, tol: f64) -> Lsq {
    let norms: Vec<f64> = m
        .column_iter()
        .map(|c| {
            let n = c.norm();
            if n > 0.0 { n } else { 1.0 }
        })
        .collect();
    let mut ms = m.clone();
    for (j, n) in norms.iter().enumerate() {
        ms.column_mut(j).scale_mut(1.0 / n);
    }
    // U^T y without forming U: for a tall design, through the QR's Q^T y (see `thin_svd`).
    let (svd, uty) = if m.nrows() > m.ncols() {
        let qr = ms.qr();
        let mut qty = y.clone();
        qr.q_tr_mul(&mut qty);
        let svd = qr.r().svd(true, true);
        let uty = svd.u.as_ref().map(|ur| ur.tr_mul(&qty.rows(0, m.ncols())));
        (svd, uty)
    } else {
        let svd = ms.svd(true, true);
        let uty = svd.u.as_ref().map(|u| u.tr_mul(y));
        (svd, uty)
    };
    let smax = svd.singular_values.max();
    let tol = smax * tol;
    let rank = svd.singular_values.iter().filter(|s| **s > tol).count();
    let p = m.ncols();
    let mut beta = DVector::zeros(p);
    let mut cov = DMatrix::zeros(p, p);
    let mut ties = Vec::new();
    if let (Some(uty), Some(vt)) = (uty, svd.v_t.as_ref()) {
        for (k, s) in svd.singular_values.iter().enumerate() {
            let v = vt.row(k).transpose();
            if *s <= tol {
                ties.push(v);
                continue;
            }
            let uy = uty[k] / s;
            beta.axpy(uy, &v, 1.0);
            cov += &v * v.transpose() / (s * s);
        }
        // A wide design's thin SVD has only n right singular vectors: the other p - n
        // directions are all ties, the complement of the rows of V^T.
        if vt.nrows() < p {
            let rest = DMatrix::identity(p, p) - vt.tr_mul(vt);
            let svd = thin_svd(rest);
            if let Some(u) = svd.u {
                for (k, s) in svd.singular_values.iter().enumerate() {
                    // A projector's singular values are 1 (kept) or 0.
                    if *s > 0.5 {
                        ties.push(u.column(k).into_owned());
                    }
                }
            }
        }
    }
    for i in 0..p {
        beta[i] /= norms[i];
        for j in 0..p {
            cov[(i, j)] /= norms[i] * norms[j];
        }
    }
    for t in &mut ties {
        for (i, n) in norms.iter().enumerate() {
            t[i] /= n;
        }
        orient(t);
    }
    let r = y - m * &beta;
    Lsq {
        chi2: r.dot(&r),
        beta,
        cov,
        rank,
        ties,
    }
}

/// A tie and its negative are the same direction; the SVD's choice between them is an
/// accident of rounding. Fixed here: the first of its largest components (to 1e-6) positive.
fn orient(t: &mut DVector<f64>) {
    let big = t.amax();
    if let Some(first) = t.iter().find(|x| x.abs() >= (1.0 - 1e-6) * big)
        && *first < 0.0
    {
        t.neg_mut();
    }
}

/// Weighted least squares: `chi2 = sum_i w_i (y_i - m_i beta)^2`, `cov = (M^T W M)^+`. The
/// rows are scaled by `sqrt(w_i)` and solved by [`lsq`]; a weight must be finite and not
/// negative (a zero weight drops its row).
pub fn weighted(m: &DMatrix<f64>, y: &DVector<f64>, w: &[f64]) -> Result<Lsq, LeastSquaresError> {
    for got in [w.len(), y.len()] {
        if got != m.nrows() {
            return Err(LeastSquaresError::Length {
                rows: m.nrows(),
                got,
            });
        }
    }
    if w.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
        return Err(LeastSquaresError::NonFinite);
    }
    let mut mw = m.clone();
    let mut yw = y.clone();
    for (i, wi) in w.iter().enumerate() {
        let s = wi.sqrt();
        mw.row_mut(i).scale_mut(s);
        yw[i] *= s;
    }
    Ok(lsq(&mw, &yw))
}

/// Least squares under exact homogeneous constraints: minimise `|y - M beta|^2` subject to
/// `C beta = 0` (a gauge: the parameters the data cannot place, fixed by convention).
///
/// With `P = I - Q Q^T` the projector onto the null space of `C` (`Q` an orthonormal basis of
/// the rows of `C`), `beta = P z` for the [`lsq`] solution `z` of the design `M P`, and
/// `cov = P (P M^T M P)^+ P = N (N^T M^T M N)^-1 N^T` for any basis `N` of that null space:
/// what very heavy constraint rows tend to, without their weight's rounding. The rank counts
/// the constrained directions as determined (a unique solution has rank p); the ties are the
/// directions neither the data nor the constraints fix.
pub fn constrained(m: &DMatrix<f64>, y: &DVector<f64>, c: &DMatrix<f64>) -> Lsq {
    let p = m.ncols();
    let q = basis(&c.transpose());
    let proj = DMatrix::identity(p, p) - &q * q.transpose();
    let f = lsq(&(m * &proj), y);
    let beta = &proj * &f.beta;
    let cov = &proj * &f.cov * &proj;
    // The fit's ties are the rows of C plus the real ties; the projector removes the former.
    let ties = if f.ties.is_empty() {
        Vec::new()
    } else {
        let scale = f.ties.iter().map(|t| t.norm()).fold(0.0, f64::max);
        let projected =
            DMatrix::from_columns(&f.ties.iter().map(|t| &proj * t).collect::<Vec<_>>());
        let svd = thin_svd(projected);
        match svd.u {
            Some(u) => (0..svd.singular_values.len())
                .filter(|&k| svd.singular_values[k] > 1e-6 * scale)
                .map(|k| {
                    let mut t = u.column(k).into_owned();
                    orient(&mut t);
                    t
                })
                .collect(),
            None => Vec::new(),
        }
    };
    let r = y - m * &beta;
    Lsq {
        chi2: r.dot(&r),
        beta,
        cov,
        rank: p - ties.len(),
        ties,
    }
}

/// Ridge regression on columns scaled to unit mean square (`Xs = X D^-1`,
/// `D = diag(sqrt(|x_j|^2 / n))`): `(Xs^T Xs + lambda I) b = Xs^T y`, `beta = D^-1 b`, by
/// Cholesky. The scaling makes one `lambda` mean the same for every column whatever its unit.
pub fn ridge(
    x: &DMatrix<f64>,
    y: &DVector<f64>,
    lambda: f64,
) -> Result<DVector<f64>, LeastSquaresError> {
    let (n, p) = x.shape();
    if y.len() != n {
        return Err(LeastSquaresError::Length {
            rows: n,
            got: y.len(),
        });
    }
    let scale: Vec<f64> = (0..p)
        .map(|j| {
            let c = x.column(j);
            (c.norm_squared() / n as f64).sqrt().max(1e-12)
        })
        .collect();
    let xs = DMatrix::from_fn(n, p, |i, j| x[(i, j)] / scale[j]);
    let mut a = xs.transpose() * &xs;
    for j in 0..p {
        a[(j, j)] += lambda;
    }
    let b = xs.transpose() * y;
    let sol = a.cholesky().ok_or(LeastSquaresError::Singular)?.solve(&b);
    let out = DVector::from_fn(p, |j, _| sol[j] / scale[j]);
    if out.iter().all(|v| v.is_finite()) {
        Ok(out)
    } else {
        Err(LeastSquaresError::NonFinite)
    }
}

/// Least squares with a vanishing ridge, `lambda = 1e-9 n` in [`ridge`] (only so that a
/// collinear design still solves): the solver of the thermal families, the grey box's gains
/// and the learning across runs, where a collinear input must still give a usable, if
/// arbitrary, split of its gain ([`lsq`] would truncate and report the tie instead). Needs
/// more rows than columns.
pub fn least_squares(
    x: &DMatrix<f64>,
    y: &DVector<f64>,
) -> Result<DVector<f64>, LeastSquaresError> {
    let (n, p) = x.shape();
    if n <= p || p == 0 {
        return Err(LeastSquaresError::TooFewRows { rows: n, cols: p });
    }
    ridge(x, y, 1e-9 * n as f64)
}

/// A posterior under a Gaussian prior: its mean and precision matrix.
#[derive(Debug, Clone)]
pub struct Posterior {
    pub mean: DVector<f64>,
    pub precision: DMatrix<f64>,
}

impl Posterior {
    /// The posterior covariance, `A^-1`.
    pub fn covariance(&self) -> Result<DMatrix<f64>, LeastSquaresError> {
        self.precision
            .clone()
            .try_inverse()
            .ok_or(LeastSquaresError::Singular)
    }
}

/// The Bayesian ridge: rows `(x_i, y_i, w_i)` and a zero-mean prior of precision `lambda_j`
/// per column give the precision `A = diag(lambda) + sum_i w_i x_i x_i^T` and the mean
/// `A^-1 sum_i w_i y_i x_i` (Cholesky; `A` symmetrised against rounding first).
pub fn posterior<'a>(
    rows: impl IntoIterator<Item = (&'a DVector<f64>, f64, f64)>,
    lambda: &[f64],
) -> Result<Posterior, LeastSquaresError> {
    let rows: Vec<_> = rows.into_iter().collect();
    // One prior gives one answer.
    let mut one = posteriors(&rows, &[lambda]);
    one.pop().unwrap_or(Err(LeastSquaresError::Singular))
}

/// [`posterior`] of the same rows under each prior of `lambdas` (a ridge's grid), bit for bit
/// as each would be alone: the prior enters `A` only on its diagonal, so the products off the
/// diagonal and `sum_i w_i y_i x_i` are summed once, and only the diagonal again for each
/// prior, from its precision and in the rows' order, as the rank-one updates (`ger`) sum it.
pub fn posteriors(
    rows: &[(&DVector<f64>, f64, f64)],
    lambdas: &[&[f64]],
) -> Vec<Result<Posterior, LeastSquaresError>> {
    let n = lambdas.first().map_or(0, |l| l.len());
    let length = |got: usize| LeastSquaresError::Length { rows: n, got };
    if let Some(&(x, _, _)) = rows.iter().find(|(x, _, _)| x.len() != n) {
        return vec![Err(length(x.len())); lambdas.len()];
    }
    let mut off = DMatrix::zeros(n, n);
    let mut b = DVector::zeros(n);
    for &(x, y, w) in rows {
        off.ger(w, x, x, 1.0);
        b.axpy(w * y, x, 1.0);
    }
    lambdas
        .iter()
        .map(|lambda| {
            if lambda.len() != n {
                return Err(length(lambda.len()));
            }
            let mut a = off.clone();
            for (j, l) in lambda.iter().enumerate() {
                // `ger`'s sum for this entry: a += (w x_j) x_j, row after row.
                a[(j, j)] = rows.iter().fold(*l, |d, &(x, _, w)| w * x[j] * x[j] + d);
            }
            let a = (a.clone() + a.transpose()) * 0.5;
            let chol = a.clone().cholesky().ok_or(LeastSquaresError::Singular)?;
            Ok(Posterior {
                mean: chol.solve(&b),
                precision: a,
            })
        })
        .collect()
}

/// The thin SVD of a tall matrix (U n x p, V^T p x p) by a Householder QR first and the SVD
/// of its p x p triangle: the same factors as the SVD of `m` itself, and several times
/// faster for long designs, whose SVD would sweep every rotation across all n rows.
pub fn thin_svd(m: DMatrix<f64>) -> nalgebra::SVD<f64, nalgebra::Dyn, nalgebra::Dyn> {
    let (n, p) = m.shape();
    if n <= p {
        return m.svd(true, true);
    }
    let qr = m.qr();
    let svd = qr.r().svd(true, true);
    let u = svd.u.as_ref().map(|ur| qr.q() * ur);
    nalgebra::SVD {
        u,
        v_t: svd.v_t,
        singular_values: svd.singular_values,
    }
}

/// An orthonormal basis of the column space of `m` (columns scaled first).
pub fn basis(m: &DMatrix<f64>) -> DMatrix<f64> {
    let mut ms = m.clone();
    for mut c in ms.column_iter_mut() {
        let n = c.norm();
        if n > 0.0 {
            c.scale_mut(1.0 / n);
        }
    }
    let svd = thin_svd(ms);
    let tol = svd.singular_values.max() * RANK_TOL;
    let keep: Vec<usize> = (0..svd.singular_values.len())
        .filter(|k| svd.singular_values[*k] > tol)
        .collect();
    match svd.u {
        Some(u) => u.select_columns(keep.iter()),
        None => DMatrix::zeros(m.nrows(), 0),
    }
}

/// What `x` adds to a model with orthonormal basis `q` and residual `e`: `(delta chi2,
/// 1 - R^2 of the weakest column)`, with `delta chi2 = b^T A^-1 b`, `A = X^T (I - Q Q^T) X`,
/// `b = X^T e` (Cholesky; a column already in the model gives 0).
pub fn scan(q: &DMatrix<f64>, e: &DVector<f64>, x: &DMatrix<f64>) -> (f64, f64) {
    let qx = q.tr_mul(x);
    let a = x.tr_mul(x) - qx.tr_mul(&qx);
    let mut free = f64::INFINITY;
    for j in 0..x.ncols() {
        let xx = x.column(j).norm_squared();
        free = free.min(if xx > 0.0 { a[(j, j)] / xx } else { 0.0 });
    }
    if free < 1e-12 {
        return (0.0, free.max(0.0));
    }
    let d = inverse_form(a, &x.tr_mul(e)).unwrap_or(0.0);
    (d.max(0.0), free)
}

/// `b^T A^-1 b` for a symmetric positive definite `A` (by Cholesky), `None` when `A` is not:
/// the sum of squares a fit explains (`A = X^T X`, `b = X^T y`), or a Wald statistic squared
/// (`A` an estimate's covariance, `b` the estimate).
pub fn inverse_form(a: DMatrix<f64>, b: &DVector<f64>) -> Option<f64> {
    a.cholesky().map(|c| b.dot(&c.solve(b)))
}

/// An orthonormal basis of what the columns of `x` add to the orthonormal basis `q`:
/// columns with less than `tol` of their energy outside `q` (or none) are dropped, collinear
/// ones are fine. `None` when nothing is left.
pub fn beyond(q: &DMatrix<f64>, x: &DMatrix<f64>, tol: f64) -> Option<DMatrix<f64>> {
    let xt = x - q * q.tr_mul(x);
    let keep: Vec<usize> = (0..x.ncols())
        .filter(|j| {
            let e = x.column(*j).norm_squared();
            e > 0.0 && xt.column(*j).norm_squared() >= tol * e
        })
        .collect();
    if keep.is_empty() {
        return None;
    }
    let b = basis(&xt.select_columns(keep.iter()));
    (b.ncols() > 0).then_some(b)
}

/// `y - M beta` for the [`lsq`] fit.
pub fn residual_of(m: &DMatrix<f64>, y: &DVector<f64>) -> DVector<f64> {
    let f = lsq(m, y);
    y - m * f.beta
}

/// The components of `v` in the left null space of the tall `m` (n x p): the last `n - p`
/// entries of `Q^T v` for the full Householder QR `m = Q R`. For the residual of a fit they
/// are what no parameter can absorb (the redundancy), and their squares sum to its chi-square.
pub fn redundant_part(m: &DMatrix<f64>, v: &DVector<f64>) -> DVector<f64> {
    let (n, p) = m.shape();
    if n <= p {
        return DVector::zeros(0);
    }
    let qr = m.clone().qr();
    let mut qtv = v.clone();
    qr.q_tr_mul(&mut qtv);
    qtv.rows(p, n - p).into_owned()
}

/// `[a | cols...]`.
pub fn hstack(a: &DMatrix<f64>, cols: &[&DMatrix<f64>]) -> DMatrix<f64> {
    let extra: usize = cols.iter().map(|c| c.ncols()).sum();
    let mut m = DMatrix::zeros(a.nrows(), a.ncols() + extra);
    m.columns_mut(0, a.ncols()).copy_from(a);
    let mut j = a.ncols();
    for c in cols {
        m.columns_mut(j, c.ncols()).copy_from(c);
        j += c.ncols();
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * (1.0 + b.abs())
    }

    /// A straight line through weighted points: the weighted normal equations solved by hand.
    #[test]
    fn weighted_line_fit_matches_the_closed_form() {
        let t = [0.0, 1.0, 2.0, 3.0, 4.0];
        let y = [1.1, 2.9, 5.2, 6.8, 9.3];
        let w = [1.0, 4.0, 1.0, 0.25, 2.0];
        let m = DMatrix::from_fn(5, 2, |i, j| if j == 0 { 1.0 } else { t[i] });
        let f = weighted(&m, &DVector::from_column_slice(&y), &w).unwrap();
        // Closed form: [S St; St Stt] [a b]^T = [Sy Sty].
        let (mut s, mut st, mut stt, mut sy, mut sty) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..5 {
            s += w[i];
            st += w[i] * t[i];
            stt += w[i] * t[i] * t[i];
            sy += w[i] * y[i];
            sty += w[i] * t[i] * y[i];
        }
        let det = s * stt - st * st;
        let a = (stt * sy - st * sty) / det;
        let b = (s * sty - st * sy) / det;
        assert!(close(f.beta[0], a, 1e-12), "{} vs {a}", f.beta[0]);
        assert!(close(f.beta[1], b, 1e-12), "{} vs {b}", f.beta[1]);
        let chi2: f64 = (0..5).map(|i| w[i] * (y[i] - a - b * t[i]).powi(2)).sum();
        assert!(close(f.chi2, chi2, 1e-10));
        assert_eq!(f.rank, 2);
        assert!(f.ties.is_empty());
    }

    /// A noise-free design returns its generating parameters exactly.
    #[test]
    fn exact_data_give_the_true_parameters() {
        let m = DMatrix::from_fn(7, 3, |i, j| ((i * 3 + j * 5) % 7) as f64 + (j as f64) * 0.5);
        let truth = DVector::from_vec(vec![2.0, -1.5, 0.25]);
        let f = lsq(&m, &(&m * &truth));
        assert!((f.beta - truth).amax() < 1e-12);
        assert!(f.chi2 < 1e-20);
    }

    /// The covariance is `(J^T W J)^-1`, inverted here by the 2 x 2 formula.
    #[test]
    fn covariance_is_the_inverse_information() {
        let j = DMatrix::from_row_slice(4, 2, &[1.0, 0.0, 1.0, 1.0, 1.0, 2.0, 1.0, 5.0]);
        let w = [2.0, 1.0, 0.5, 3.0];
        let f = weighted(&j, &DVector::zeros(4), &w).unwrap();
        let (mut a, mut b, mut d) = (0.0, 0.0, 0.0);
        for (i, wi) in w.iter().enumerate() {
            a += wi * j[(i, 0)] * j[(i, 0)];
            b += wi * j[(i, 0)] * j[(i, 1)];
            d += wi * j[(i, 1)] * j[(i, 1)];
        }
        let det = a * d - b * b;
        let inv = DMatrix::from_row_slice(2, 2, &[d / det, -b / det, -b / det, a / det]);
        for (got, want) in f.cov.iter().zip(inv.iter()) {
            assert!(close(*got, *want, 1e-12), "{} vs {inv}", f.cov);
        }
    }

    /// Two identical columns: rank p - 1, and the tie is their difference.
    #[test]
    fn identical_columns_lower_the_rank_and_name_the_tie() {
        let m = DMatrix::from_fn(6, 3, |i, j| match j {
            0 => 1.0,
            _ => i as f64,
        });
        let y = DVector::from_fn(6, |i, _| 1.0 + 2.0 * i as f64);
        let f = lsq(&m, &y);
        assert_eq!(f.rank, 2);
        assert_eq!(f.ties.len(), 1);
        let t = &f.ties[0];
        let big = t.amax();
        assert!(t[0].abs() < 1e-9 * big, "{t}");
        assert!(close(t[1] / t[2], -1.0, 1e-9), "{t}");
        // Signed by convention: the first of the largest components positive.
        assert!(t[1] > 0.0, "{t}");
        // The fit is still exact, the gain split evenly (minimum norm).
        assert!(f.chi2 < 1e-20);
        assert!(close(f.beta[1], 1.0, 1e-9) && close(f.beta[2], 1.0, 1e-9));
    }

    /// A wide design: its ties include the directions the thin SVD does not return.
    #[test]
    fn wide_design_reports_every_tie() {
        let m = DMatrix::from_row_slice(2, 4, &[1.0, 2.0, 0.0, 1.0, 0.0, 1.0, 1.0, 3.0]);
        let f = lsq(&m, &DVector::from_vec(vec![1.0, 2.0]));
        assert_eq!(f.rank, 2);
        assert_eq!(f.ties.len(), 2);
        for t in &f.ties {
            assert!((&m * t).amax() < 1e-12 * t.amax());
        }
    }

    /// Columns of 1e-6 and 1e6 solve to the parameters of the same problem in sensible units:
    /// the scaling, not the unit, decides the rank and the rounding.
    #[test]
    fn column_scaling_makes_units_irrelevant() {
        let n = 20;
        let t = |i: usize| i as f64 / (n - 1) as f64;
        let unit = DMatrix::from_fn(n, 3, |i, j| t(i).powi(j as i32));
        let truth = DVector::from_vec(vec![0.5, -2.0, 3.0]);
        let y = DVector::from_fn(n, |i, _| {
            (&unit * &truth)[i] + 1e-3 * (i as f64 * 1.7).sin()
        });
        let s = [1e-6, 1.0, 1e6];
        let bad = DMatrix::from_fn(n, 3, |i, j| unit[(i, j)] * s[j]);
        let good = lsq(&unit, &y);
        let scaled = lsq(&bad, &y);
        assert_eq!(scaled.rank, 3);
        for j in 0..3 {
            assert!(close(scaled.beta[j] * s[j], good.beta[j], 1e-10), "{j}");
            for k in 0..3 {
                assert!(close(
                    scaled.cov[(j, k)] * s[j] * s[k],
                    good.cov[(j, k)],
                    1e-9
                ));
            }
        }
        assert!(close(scaled.chi2, good.chi2, 1e-9));
    }

    /// Ridge on an orthogonal design: each scaled coefficient shrinks by `c / (c + lambda)`.
    #[test]
    fn ridge_shrinks_as_the_closed_form_says() {
        // Columns orthogonal, mean square 1 and 4 (scaled to 1 by the ridge).
        let x = DMatrix::from_row_slice(4, 2, &[1.0, 2.0, 1.0, -2.0, 1.0, 2.0, 1.0, -2.0]);
        let y = DVector::from_vec(vec![3.0, -1.0, 3.0, -1.0]);
        // Least squares: beta = (1, 1). Scaled columns have |xs_j|^2 = 4, so the ridge
        // solution is b_j = 4 / (4 + lambda) times the unpenalised scaled coefficient.
        let lambda = 2.0;
        let b = ridge(&x, &y, lambda).unwrap();
        let shrink = 4.0 / (4.0 + lambda);
        assert!(close(b[0], shrink, 1e-12), "{b}");
        assert!(close(b[1], shrink, 1e-12), "{b}");
        // The vanishing ridge is least squares.
        let v = least_squares(&x, &y).unwrap();
        assert!((v - DVector::from_vec(vec![1.0, 1.0])).amax() < 1e-8);
        assert_eq!(
            least_squares(&x.rows(0, 2).into_owned(), &y.rows(0, 2).into_owned()),
            Err(LeastSquaresError::TooFewRows { rows: 2, cols: 2 })
        );
    }

    /// The posterior of one parameter: precision `lambda + sum w x^2`, mean `sum w x y / A`.
    #[test]
    fn posterior_of_one_parameter() {
        let rows = [DVector::from_vec(vec![1.0]), DVector::from_vec(vec![2.0])];
        let (y, w) = ([1.0, 3.0], [1.0, 0.5]);
        let p = posterior(
            rows.iter().zip(y).zip(w).map(|((x, y), w)| (x, y, w)),
            &[0.5],
        )
        .unwrap();
        let a = 0.5 + 1.0 + 0.5 * 4.0;
        assert!(close(p.precision[(0, 0)], a, 1e-15));
        assert!(close(p.mean[0], (1.0 + 0.5 * 2.0 * 3.0) / a, 1e-15));
        assert!(close(p.covariance().unwrap()[(0, 0)], 1.0 / a, 1e-15));
    }

    /// Several priors on the same rows give, bit for bit, what each gives alone summed from
    /// its own diagonal (the rank-one updates of the textbook sum, as `posterior` was), and a
    /// row of the wrong length is refused under every prior.
    #[test]
    fn posteriors_of_a_grid_are_each_prior_alone_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let n = 5;
        let rows: Vec<(DVector<f64>, f64, f64)> = (0..40)
            .map(|_| {
                let x = DVector::from_fn(n, |_, _| rng.random_range(-3.0..3.0));
                (x, rng.random_range(-50.0..50.0), rng.random_range(0.1..4.0))
            })
            .collect();
        let rows: Vec<(&DVector<f64>, f64, f64)> =
            rows.iter().map(|(x, y, w)| (x, *y, *w)).collect();
        let grid: Vec<Vec<f64>> = [0.0, 1e-3, 0.7, 100.0]
            .iter()
            .map(|k| (0..n).map(|j| 1e-6 + k * (j as f64 + 0.5)).collect())
            .collect();
        let lambdas: Vec<&[f64]> = grid.iter().map(Vec::as_slice).collect();
        let all = posteriors(&rows, &lambdas);
        for (lambda, got) in lambdas.iter().zip(&all) {
            let mut a = DMatrix::from_diagonal(&DVector::from_column_slice(lambda));
            let mut b = DVector::zeros(n);
            for &(x, y, w) in &rows {
                a.ger(w, x, x, 1.0);
                b.axpy(w * y, x, 1.0);
            }
            let a = (a.clone() + a.transpose()) * 0.5;
            let mean = a.clone().cholesky().unwrap().solve(&b);
            let got = got.as_ref().unwrap();
            assert_eq!(got.precision, a);
            assert_eq!(got.mean, mean);
            assert_eq!(posterior(rows.iter().copied(), lambda).unwrap().mean, mean);
        }
        let short = DVector::from_vec(vec![1.0; n - 1]);
        let bad = [rows[0], (&short, 1.0, 1.0)];
        let refused = posteriors(&bad, &lambdas);
        assert_eq!(refused.len(), lambdas.len());
        for r in refused {
            assert_eq!(
                r.err(),
                Some(LeastSquaresError::Length {
                    rows: n,
                    got: n - 1
                })
            );
        }
    }

    /// A gauge as an exact constraint: two offsets only their difference is seen, the sum
    /// fixed at zero by convention.
    #[test]
    fn constraints_fix_the_gauge_exactly() {
        // y_i = a - b: only a - b is seen.
        let m = DMatrix::from_fn(3, 2, |_, j| if j == 0 { 1.0 } else { -1.0 });
        let y = DVector::from_vec(vec![1.9, 2.0, 2.1]);
        let c = DMatrix::from_row_slice(1, 2, &[1.0, 1.0]);
        let f = constrained(&m, &y, &c);
        assert_eq!(f.rank, 2);
        assert!(f.ties.is_empty());
        assert!(close(f.beta[0], 1.0, 1e-12) && close(f.beta[1], -1.0, 1e-12));
        // var(a - b) = 1/3 and a = -b: var(a) = 1/12, cov(a, b) = -1/12.
        assert!(close(f.cov[(0, 0)], 1.0 / 12.0, 1e-12));
        assert!(close(f.cov[(0, 1)], -1.0 / 12.0, 1e-12));
        // Without the constraint the same design has a tie along (1, 1).
        let free = lsq(&m, &y);
        assert_eq!(free.rank, 1);
        assert!(close(free.ties[0][0] / free.ties[0][1], 1.0, 1e-12));
    }

    /// The redundant part of a residual carries all of its chi-square.
    #[test]
    fn redundancy_carries_the_chi_square() {
        let m = DMatrix::from_fn(6, 2, |i, j| (i as f64).powi(j as i32));
        let y = DVector::from_vec(vec![0.1, 0.9, 2.2, 2.8, 4.1, 5.0]);
        let f = lsq(&m, &y);
        let r = &y - &m * &f.beta;
        let red = redundant_part(&m, &r);
        assert_eq!(red.len(), 4);
        assert!(close(red.norm_squared(), f.chi2, 1e-12));
    }
}
