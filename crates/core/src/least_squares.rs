//! Least squares with a vanishing ridge on column-scaled designs: the solver of the thermal
//! families, the grey box's gains and the learning across runs. Pure.

use nalgebra::{DMatrix, DVector};

/// Least squares with a vanishing ridge (only so that a collinear design still solves),
/// on columns scaled to unit mean square. `None` when the design has no more rows than
/// columns. (`driftwatch_diagnosis::lsq` truncates the SVD instead, and reports the rank: here a
/// collinear input must still give a usable, if arbitrary, split of its gain.)
pub fn least_squares(x: &DMatrix<f64>, y: &DVector<f64>) -> Option<DVector<f64>> {
    let (n, p) = x.shape();
    if n <= p || p == 0 {
        return None;
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
        a[(j, j)] += 1e-9 * n as f64;
    }
    let b = xs.transpose() * y;
    let sol = a.cholesky()?.solve(&b);
    let out = DVector::from_fn(p, |j, _| sol[j] / scale[j]);
    out.iter().all(|v| v.is_finite()).then_some(out)
}
