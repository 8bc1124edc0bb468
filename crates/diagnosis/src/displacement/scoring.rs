//! What a column adds to a model, as regression with autoregressive errors (feasible GLS):
//! the forward selection, its surrogate bar and the located term all score a candidate here.
//!
//! The AR noise model is estimated from the residual of the model WITH the candidate, and
//! both likelihoods (with and without it) are taken on the rows whitened by that one noise
//! model: the noise is what the model leaves once the term is in, as in any GLS test of a
//! coefficient. Estimated without the candidate, the noise model is fitted to a residual that
//! still holds the drift the candidate would explain: a slow drift makes it near a random
//! walk, and whitening with a random walk differences the drift away, so the very term that
//! explains it scores nothing (docs/physics.md 4.6.2, "The noise model"). The bar every score
//! must clear is made the same way, the AR model re-estimated with each surrogate column, so
//! what a persistent residual lets a chance column reach is in the bar.

use super::{Design, ar_by_bic, ar1};
use driftwatch_core::least_squares::lsq;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

/// Where the noise model a column is scored with comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NoiseModel {
    /// From the residual of the model without the candidate, for both likelihoods (the rule
    /// before; a slow drift the candidate would explain whitens to nothing).
    WithoutCandidate,
    /// From the residual of the model with it, for both likelihoods (a GLS test of the
    /// coefficient).
    WithCandidate,
    /// Each model with the noise model of its own residual (the likelihood ratio profiled
    /// over the noise), the AR orders counted as parameters.
    Profile,
}

/// A column's score against one model: its delta-BIC and the AR coefficients it was whitened
/// with (the t statistic of the term is taken with the same ones).
pub(super) struct Scored {
    pub delta_bic: f64,
    pub phi: Vec<f64>,
}

/// One model on the training rows, to score columns added to it.
pub(super) struct ColumnScorer<'a> {
    design: &'a Design<'a>,
    /// The model's and the readings' training rows.
    mt: DMatrix<f64>,
    yt: DVector<f64>,
    /// The AR model of the model's own residual, and the model's whitened SSE with it.
    phi0: Vec<f64>,
    sse0: f64,
    noise: NoiseModel,
    n_w: f64,
}

impl<'a> ColumnScorer<'a> {
    /// The model `m` (every row) of `design`, its noise estimated as `noise` says.
    pub fn new(design: &'a Design<'a>, m: &DMatrix<f64>, noise: NoiseModel) -> Self {
        let mt = m.select_rows(design.train.iter());
        let yt = design.y.select_rows(design.train.iter());
        let start = design.ar_max.max(1);
        let (phi0, sse0) = gls(design, &mt, &yt, start);
        ColumnScorer {
            n_w: (design.train.len() - start) as f64,
            design,
            mt,
            yt,
            phi0,
            sse0,
            noise,
        }
    }

    /// The delta-BIC (`N ln(SSE0 / SSE1) - k ln N` on the whitened training rows) of column
    /// `x`, given on the training rows, with `extra` more parameters (a located onset, a lag)
    /// charged `ln N` each. None when the column adds nothing the model does not span.
    pub fn score(&self, x: &[f64], extra: usize) -> Option<Scored> {
        let p = self.mt.ncols();
        let start = self.design.ar_max.max(1);
        let mut full = self.mt.clone().insert_column(p, 0.0);
        full.column_mut(p).copy_from_slice(x);
        let k = (1 + extra) as f64;
        let (sse0, sse1, phi, k) = match self.noise {
            NoiseModel::WithoutCandidate => {
                let (_, sse1) = whitened_sse(&full, &self.yt, &self.phi0, start)?;
                (self.sse0, sse1, self.phi0.clone(), k)
            }
            NoiseModel::WithCandidate => {
                let phi = ols_ar(self.design, &full, &self.yt)?;
                let (fw, sse1) = whitened_sse(&full, &self.yt, &phi, start)?;
                let yw = whiten_vec(&self.yt, &phi, start);
                let sse0 = lsq(&fw.columns(0, p).into_owned(), &yw).chi2;
                (sse0, sse1, phi, k)
            }
            NoiseModel::Profile => {
                let phi = ols_ar(self.design, &full, &self.yt)?;
                let (_, sse1) = whitened_sse(&full, &self.yt, &phi, start)?;
                // Each model with its own noise model: the AR orders count as parameters.
                let orders = phi.len() as f64 - self.phi0.len() as f64;
                (self.sse0, sse1, phi, k + orders)
            }
        };
        let delta_bic = self.n_w * (sse0 / sse1.max(1e-300)).ln() - k * self.n_w.ln();
        Some(Scored { delta_bic, phi })
    }

    /// The highest over `k` replicates of the best score that phase-randomised copies of
    /// `cols` (each given on the training rows) reach: what the best of these candidates
    /// reaches by chance against this model, its noise model estimated as the real ones'.
    /// (A copy made on every reading and cut to the training rows would carry a trend across
    /// the training span as a real candidate does, where one made on the training rows is
    /// circular; tried, it raised fl-thermal's bars several-fold and changed the calibrated
    /// selection: not adopted, see docs/physics.md 4.6.2.)
    pub fn surrogate_bar(&self, cols: &[Vec<f64>], k: usize, rng: &mut impl rand::Rng) -> f64 {
        let mut bar = f64::NEG_INFINITY;
        for _ in 0..k {
            for x in cols {
                let xs = crate::surrogates::phase_randomised(x, rng);
                if let Some(s) = self.score(&xs, 0) {
                    bar = bar.max(s.delta_bic);
                }
            }
        }
        bar
    }
}

/// The AR coefficients of the OLS residual of `m` (training rows) on `y`; none when `m` is
/// rank-deficient.
fn ols_ar(design: &Design, m: &DMatrix<f64>, y: &DVector<f64>) -> Option<Vec<f64>> {
    let f = lsq(m, y);
    if f.rank < m.ncols() {
        return None;
    }
    let e: Vec<f64> = (y - m * &f.beta).iter().copied().collect();
    Some(design.ar_of(&e))
}

/// A model's noise model and whitened SSE, the AR model from its own OLS residual.
fn gls(design: &Design, m: &DMatrix<f64>, y: &DVector<f64>, start: usize) -> (Vec<f64>, f64) {
    let f = lsq(m, y);
    let e: Vec<f64> = (y - m * &f.beta).iter().copied().collect();
    let phi = design.ar_of(&e);
    let sse = lsq(&whiten_rows(m, &phi, start), &whiten_vec(y, &phi, start)).chi2;
    (phi, sse)
}

/// `m` and `y` whitened with `phi`, and the SSE of the fit: none when `m` is
/// rank-deficient once whitened.
fn whitened_sse(
    m: &DMatrix<f64>,
    y: &DVector<f64>,
    phi: &[f64],
    start: usize,
) -> Option<(DMatrix<f64>, f64)> {
    let mw = whiten_rows(m, phi, start);
    let f = lsq(&mw, &whiten_vec(y, phi, start));
    (f.rank == m.ncols()).then_some((mw, f.chi2))
}

fn whiten_vec(y: &DVector<f64>, phi: &[f64], start: usize) -> DVector<f64> {
    whiten_rows(
        &DMatrix::from_column_slice(y.len(), 1, y.as_slice()),
        phi,
        start,
    )
    .column(0)
    .into_owned()
}

impl Design<'_> {
    /// The AR coefficients of a residual `e` (the order by BIC up to `ar_max`, or AR(1)).
    pub(super) fn ar_of(&self, e: &[f64]) -> Vec<f64> {
        if self.ar_max <= 1 {
            vec![ar1(e)]
        } else {
            ar_by_bic(e, self.ar_max)
        }
    }
}

/// Rows `start..` of `v` whitened by AR coefficients `phi` (each row less the weighted rows
/// before it): every order whitens the same rows, so that the scores compare.
fn whiten_rows(v: &DMatrix<f64>, phi: &[f64], start: usize) -> DMatrix<f64> {
    let n = v.nrows();
    DMatrix::from_fn(n.saturating_sub(start), v.ncols(), |r, j| {
        let k = r + start;
        v[(k, j)]
            - phi
                .iter()
                .enumerate()
                .map(|(l, p)| p * v[(k - 1 - l, j)])
                .sum::<f64>()
    })
}
