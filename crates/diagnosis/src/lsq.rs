//! Linear least squares and subspace helpers shared by the cycle and displacement diagnoses:
//! solves on column-scaled designs (QR, then the SVD of the triangle), orthonormal bases, and
//! what a candidate adds to a fitted model.

use nalgebra::{DMatrix, DVector};

/// Least squares on whitened columns, by SVD with the columns scaled to unit norm.
pub struct Lsq {
    pub beta: DVector<f64>,
    /// `(M^T M)^+` in the unscaled columns.
    pub cov: DMatrix<f64>,
    pub chi2: f64,
    pub rank: usize,
}

pub fn lsq(m: &DMatrix<f64>, y: &DVector<f64>) -> Lsq {
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
    let tol = smax * 1e-9;
    let rank = svd.singular_values.iter().filter(|s| **s > tol).count();
    let p = m.ncols();
    let mut beta = DVector::zeros(p);
    let mut cov = DMatrix::zeros(p, p);
    if let (Some(uty), Some(vt)) = (uty, svd.v_t.as_ref()) {
        for (k, s) in svd.singular_values.iter().enumerate() {
            if *s <= tol {
                continue;
            }
            let uy = uty[k] / s;
            let v = vt.row(k).transpose();
            beta.axpy(uy, &v, 1.0);
            cov += &v * v.transpose() / (s * s);
        }
    }
    for i in 0..p {
        beta[i] /= norms[i];
        for j in 0..p {
            cov[(i, j)] /= norms[i] * norms[j];
        }
    }
    let r = y - m * &beta;
    Lsq {
        chi2: r.dot(&r),
        beta,
        cov,
        rank,
    }
}

/// The thin SVD of a tall matrix (U n x p, V^T p x p) by a Householder QR first and the SVD
/// of its p x p triangle: the same factors as the SVD of `m` itself, and several times
/// faster for the long designs of a diagnosis, whose SVD would sweep every rotation across
/// all n rows.
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
    let tol = svd.singular_values.max() * 1e-9;
    let keep: Vec<usize> = (0..svd.singular_values.len())
        .filter(|k| svd.singular_values[*k] > tol)
        .collect();
    match svd.u {
        Some(u) => u.select_columns(keep.iter()),
        None => DMatrix::zeros(m.nrows(), 0),
    }
}

/// What `x` adds to a model with orthonormal basis `q` and residual `e`: `(delta chi2,
/// 1 - R^2 of the weakest column)`.
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
    let b = x.tr_mul(e);
    let d = match a.clone().cholesky() {
        Some(c) => b.dot(&c.solve(&b)),
        None => 0.0,
    };
    (d.max(0.0), free)
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

pub fn residual_of(m: &DMatrix<f64>, y: &DVector<f64>) -> DVector<f64> {
    let f = lsq(m, y);
    y - m * f.beta
}

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
