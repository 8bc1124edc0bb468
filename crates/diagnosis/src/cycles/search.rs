//! The search of [`super::diagnose`] (docs/physics.md 4.6.1) as an object: the rows left after
//! the outlier screen, the held-out blocks, the whitened baseline and library, and one method
//! per phase (baseline, locate, candidates, thresholds, forward selection and pruning, the
//! periodic discrepancy, coincidences, the final fit with each term's ambiguity group, the
//! channels, what stays unexplained).

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};

use driftwatch_thermal::model::Event;

use super::{
    Accepted, Alternative, ChannelFigures, DiagnoseOptions, FitFigures, GroupMember, Mismatch,
    NotIdentifiable, Outlier, Parameter, PeriodicResidual, Refused, Threshold, Unexplained,
    baseline_matrix, blocks, group_means, heldout_prediction, heldout_sse, locate, model_input,
    periodic_scan, screen_outliers, step_candidates,
};
use crate::effects::{Candidate, Drivers};
use crate::rows::Rows;
use crate::stepwise::{Rules, Scoring, Verdict, stepwise};
use driftwatch_core::least_squares::{
    Lsq, basis, beyond, hstack, inverse_form, lsq, residual_of, scan,
};

/// `rows` without the readings that are outliers against a robust baseline
/// ([`screen_outliers`]), and those readings.
pub(super) fn without_outliers(
    rows: &Rows,
    spindle: &[Event],
    opts: &DiagnoseOptions,
) -> (Rows, Vec<Outlier>) {
    let mut rows = rows.clone();
    let mut outliers = Vec::new();
    let flagged = screen_outliers(
        &rows,
        spindle,
        &opts.model,
        opts.sigma_um,
        opts.outlier_sigma,
    );
    let mut keep = Vec::with_capacity(rows.rows.len());
    let mut next = flagged.iter().peekable();
    for (i, r) in rows.rows.iter().enumerate() {
        match next.peek() {
            Some((j, e)) if *j == i => {
                outliers.push(Outlier {
                    t_ns: r.t_ns,
                    cycle: r.cycle,
                    step: r.step.clone(),
                    residual_um: *e,
                });
                next.next();
            }
            _ => keep.push(r.clone()),
        }
    }
    rows.rows = keep;
    (rows, outliers)
}

/// A fit's figures, its residuals and its prediction of every row from the training blocks
/// (whitened).
pub(super) struct Fit {
    pub figures: FitFigures,
    pub resid: DVector<f64>,
    pub pred: DVector<f64>,
}

/// What forward selection and pruning chose over one baseline: the chosen candidates, the
/// refused ones, and for each taken one the held-out blocks it improved.
pub(super) struct Selection {
    pub chosen: Vec<usize>,
    pub refused: Vec<Refused>,
    pub blocks_better: BTreeMap<usize, usize>,
}

/// Terms that coincide in time with an earlier accepted effect.
#[derive(Default)]
pub(super) struct Coincidences {
    /// Kept: the term's index and the earlier effect as a member of its group.
    pub coincident: BTreeMap<usize, GroupMember>,
    /// Dropped: the earlier effect's index and the term as a member of its group.
    pub folded: Vec<(usize, GroupMember)>,
}

/// The final model: the effective baseline (the baseline, with the periodic discrepancy when
/// one was found), the chosen terms and their joint fit.
pub(super) struct Final {
    pub base_eff: DMatrix<f64>,
    pub chosen: Vec<usize>,
    pub blocks_better: BTreeMap<usize, usize>,
    pub coincidences: Coincidences,
    pub m: DMatrix<f64>,
    pub fit: Fit,
    pub f: Lsq,
    /// `max(chi2/dof, 1)`: the covariance's scale.
    pub scale: f64,
}

/// One accepted term in the final fit.
struct TermFit {
    k: usize,
    b: DVector<f64>,
    cov: DMatrix<f64>,
    /// Its footprint on every row, um.
    foot: DVector<f64>,
    /// The final model without it.
    mrest: DMatrix<f64>,
    dbic: f64,
    t: f64,
    ho_before: f64,
    ho_after: f64,
}

/// What another explanation of an accepted term is measured against: the model without the
/// term (orthonormal basis `qr`, chi2 and residual) and the term's footprint beyond it (`v`).
struct Rival<'o> {
    opts: &'o DiagnoseOptions,
    qr: DMatrix<f64>,
    chi2_rest: f64,
    e_rest: DVector<f64>,
    full_chi2: f64,
    v: DVector<f64>,
    vv: f64,
    /// The term's parameters, profiled ones counted.
    k_term: f64,
}

impl Rival<'_> {
    /// Columns `x` (with `profiled` located parameters) as an explanation of the term.
    fn alt(&self, x: &DMatrix<f64>, profiled: usize) -> Option<Alternative> {
        let bs = beyond(&self.qr, x, self.opts.structural_tol)?;
        let dv = bs.tr_mul(&self.v).norm_squared();
        let miss = (self.vv - dv).max(0.0);
        let data = self.chi2_rest - bs.tr_mul(&self.e_rest).norm_squared() - self.full_chi2;
        // Two per parameter beyond the term's (Akaike's charge: does it predict the data
        // as well, not would BIC pick it).
        let extra = ((bs.ncols() + profiled) as f64 - self.k_term).max(0.0) * 2.0;
        let bar = self.opts.min_delta_bic;
        let inseparable = miss < 1e-3 * self.vv;
        let comparable = inseparable || miss.min(data) + extra < bar;
        Some(Alternative {
            cos: (dv / self.vv).sqrt(),
            miss,
            data,
            parameters: bs.ncols() + profiled,
            comparable,
            // What is left grows with the square of the amplitude: the factor that brings the
            // expected misfit to the bar.
            splits_at: (comparable && !inseparable)
                .then(|| ((bar - extra).max(0.0) / miss).sqrt().max(1.0)),
        })
    }

    /// Whether an alternative belongs in the group: close in footprint or comparable.
    fn close(&self, a: &Alternative) -> bool {
        a.cos > self.opts.ambiguity_cos || a.comparable
    }

    /// An alternative as a member of the term's group.
    fn member(&self, effect: &str, term: String, a: &Alternative, why: &str) -> GroupMember {
        GroupMember {
            effect: effect.into(),
            term,
            cos: a.cos,
            delta_chi2: a.data,
            footprint_left_chi2: a.miss,
            parameters: a.parameters,
            comparable: a.comparable,
            splits_at: a.splits_at,
            reason: format!(
                "{why}: cos {:.3} with its footprint, which it carries but for chi2 {:.1}; the data fit {} by chi2 {:.1} with it in place of the term ({} parameter{}){}",
                a.cos,
                a.miss,
                if a.data >= 0.0 { "worse" } else { "better" },
                a.data.abs(),
                a.parameters,
                if a.parameters == 1 { "" } else { "s" },
                if a.comparable {
                    if a.miss < 1e-3 * self.vv {
                        ": the plan cannot tell them apart"
                    } else {
                        ": it explains the data comparably"
                    }
                } else {
                    ""
                }
            ),
        }
    }
}

/// How an accepted term is named: whether it is, its group, the accepted term it coincides
/// with, and how to split them.
struct Naming {
    named: bool,
    named_at: Option<f64>,
    group: Vec<GroupMember>,
    coincides: Option<GroupMember>,
    split_by: Vec<String>,
}

/// The search over one recording.
pub(super) struct Search<'a> {
    opts: &'a DiagnoseOptions,
    pub sigma: f64,
    pub rows: Rows,
    pub n: usize,
    pub drivers: Drivers,
    pub times: Vec<i64>,
    pub blocks: Vec<(i64, i64)>,
    /// Each row's block.
    pub block_of: Vec<usize>,
    /// The rows outside and inside the last block.
    train_last: Vec<usize>,
    test_last: Vec<usize>,
    /// The baseline design and the readings, whitened.
    pub base: DMatrix<f64>,
    y: DVector<f64>,
    ln_n: f64,
    /// The library (with the located steps), its whitened columns, which candidates the
    /// baseline cannot tell from itself, their relative energy beyond the baseline, and which
    /// are searched.
    cands: Vec<Candidate>,
    xs: Vec<DMatrix<f64>>,
    structural: Vec<bool>,
    free_of: Vec<f64>,
    allowed: Vec<bool>,
}

impl<'a> Search<'a> {
    /// The held-out blocks and the whitened baseline of `rows` (already screened).
    pub fn new(
        rows: Rows,
        spindle: &[Event],
        temperatures: &[Event],
        opts: &'a DiagnoseOptions,
    ) -> Search<'a> {
        let sigma = opts.sigma_um;
        let n = rows.rows.len();
        let drivers = Drivers::new(&rows, spindle, temperatures, &opts.model);
        let times: Vec<i64> = rows.rows.iter().map(|r| r.t_ns).collect();
        let blocks = blocks(&times);
        let block_of: Vec<usize> = times
            .iter()
            .map(|t| {
                blocks
                    .iter()
                    .position(|(a, b)| t >= a && t < b)
                    .unwrap_or(blocks.len() - 1)
            })
            .collect();
        let nb = blocks.len();
        let (train_last, test_last) = (0..n).partition(|i| block_of[*i] != nb - 1);
        // The baseline design, whitened.
        let base = baseline_matrix(&rows, &drivers.spindle, sigma);
        let y = DVector::from_iterator(n, rows.rows.iter().map(|r| r.deviation_um / sigma));
        Search {
            opts,
            sigma,
            rows,
            n,
            drivers,
            times,
            blocks,
            block_of,
            train_last,
            test_last,
            base,
            y,
            ln_n: (n as f64).ln(),
            cands: Vec::new(),
            xs: Vec::new(),
            structural: Vec::new(),
            free_of: Vec::new(),
            allowed: Vec::new(),
        }
    }

    /// The rows outside and inside block `b`.
    fn split(&self, b: usize) -> (Vec<usize>, Vec<usize>) {
        (0..self.n).partition(|i| self.block_of[*i] != b)
    }

    /// Model `m`'s figures, residuals and held-out prediction.
    pub fn figures(&self, m: &DMatrix<f64>) -> Fit {
        let (n, y, sigma) = (self.n, &self.y, self.sigma);
        let f = lsq(m, y);
        let r = y - m * &f.beta;
        let dof = n.saturating_sub(f.rank).max(1);
        let pred = heldout_prediction(m, y, &self.train_last);
        let rms = |idx: &[usize], v: &DVector<f64>| {
            (idx.iter().map(|i| v[*i].powi(2)).sum::<f64>() / idx.len().max(1) as f64).sqrt()
                * sigma
        };
        let ho = y - &pred;
        let (train_um, heldout_um) = (rms(&self.train_last, &r), rms(&self.test_last, &ho));
        Fit {
            figures: FitFigures {
                parameters: f.rank,
                chi2_dof: f.chi2 / dof as f64,
                dof,
                rms_train_um: train_um,
                rms_heldout_um: heldout_um,
                heldout_extrapolates: heldout_um > 5.0 * train_um && heldout_um > 5.0 * sigma,
            },
            resid: r,
            pred,
        }
    }

    /// Where the residuals `resid_um` are systematic: [`locate`], and the rows grouped by
    /// their phase `phase`, feed and spindle speed.
    pub fn locate(&self, resid_um: &[f64], phase: &[&'static str]) -> Vec<Mismatch> {
        let (rows, sigma) = (&self.rows, self.sigma);
        let mut located = locate(rows, resid_um, sigma, 4.0);
        group_means(
            "phase",
            phase.iter().map(|p| p.to_string()),
            resid_um,
            sigma,
            4.0,
            &mut located,
        );
        group_means(
            "feed",
            rows.rows
                .iter()
                .map(|r| format!("{} mm/min", r.feed_mm_min)),
            resid_um,
            sigma,
            4.0,
            &mut located,
        );
        group_means(
            "spindle speed",
            rows.rows
                .iter()
                .map(|r| format!("{} min^-1", r.spindle_rpm)),
            resid_um,
            sigma,
            4.0,
            &mut located,
        );
        located.sort_by(|a, b| b.t.abs().total_cmp(&a.t.abs()));
        located
    }

    /// The library, whitened: the effects' candidates, the missing spins' when the log lacks
    /// them, and the steps located against the baseline (orthonormal basis `q0`, residual
    /// `base_resid`).
    pub fn candidates(&mut self, q0: &DMatrix<f64>, base_resid: &DVector<f64>) {
        let (n, sigma) = (self.n, self.sigma);
        let mut cands: Vec<Candidate> =
            crate::effects::candidates(&self.rows, &self.drivers, self.opts.model.n_ref_rpm);
        if !self.drivers.missing_spins.is_empty() {
            cands.push(self.missing_spins());
        }
        // Steps at a time located by likelihood (a change at an unknown time), one candidate
        // per signature that can jump, at its best time against the baseline.
        cands.extend(step_candidates(&self.rows, q0, base_resid, sigma));
        self.xs = cands
            .iter()
            .map(|c| DMatrix::from_fn(n, c.columns.len(), |i, j| c.columns[j][i] / sigma))
            .collect();
        self.cands = cands;
    }

    /// The switch to a spindle log with the cycles' spins: the baseline's own response to the
    /// heat the log lacks, scaled by one parameter.
    fn missing_spins(&self) -> Candidate {
        let (rows, drivers) = (&self.rows, &self.drivers);
        let basis_len = 1 + drivers.spindle.len();
        let f = lsq(&self.base, &self.y);
        let col: Vec<f64> = (0..self.n)
            .map(|i| {
                let r = &rows.rows[i];
                (0..rows.params.len())
                    .map(|j| {
                        r.sensitivity[j]
                            * drivers
                                .missing_spins
                                .iter()
                                .enumerate()
                                .map(|(b, g)| f.beta[j * basis_len + 1 + b] * g[i])
                                .sum::<f64>()
                    })
                    .sum()
            })
            .collect();
        Candidate {
            effect: "measurement_heating",
            term: "baseline response x cycle spins missing from the spindle log".into(),
            unit: "1".into(),
            columns: vec![col],
            signature: "all".into(),
            shape_kind: crate::effects::ShapeKind::MissingSpins,
            shape: drivers.missing_spins.clone(),
            profiled: 0,
            step_ns: None,
        }
    }

    /// What the baseline cannot tell apart from each candidate (its relative energy beyond
    /// the baseline), and the strongest candidate drivers of the baseline's residuals (as t).
    pub fn screen(&mut self, q0: &DMatrix<f64>, base_resid: &DVector<f64>) -> Vec<(String, f64)> {
        self.structural = vec![false; self.cands.len()];
        self.free_of = vec![0.0; self.cands.len()];
        let mut drivers_t = Vec::new();
        for (i, x) in self.xs.iter().enumerate() {
            let (d, free) = scan(q0, base_resid, x);
            self.free_of[i] = free;
            self.structural[i] = free < self.opts.structural_tol || x.norm() == 0.0;
            if !self.structural[i] {
                let c = &self.cands[i];
                drivers_t.push((format!("{}: {}", c.effect, c.term), d.sqrt()));
            }
        }
        drivers_t.sort_by(|a, b| b.1.total_cmp(&a.1));
        drivers_t.truncate(10);
        drivers_t
    }

    /// The detection threshold of each one-parameter candidate.
    pub fn thresholds(&self) -> Vec<Threshold> {
        let opts = self.opts;
        // sigma sqrt((10 + ln n) / (n ms (1 - R^2))) with the columns already in sigma units;
        // where |t| >= min_t binds harder (small n), its bar instead.
        let bar = (opts.min_delta_bic + (self.n as f64).ln()).max(opts.min_t * opts.min_t);
        self.cands
            .iter()
            .zip(&self.xs)
            .zip(&self.free_of)
            .filter(|((c, x), free)| c.columns.len() == 1 && x.norm() > 0.0 && **free > 0.0)
            .map(|((c, x), free)| Threshold {
                effect: c.effect,
                term: c.term.clone(),
                unit: c.unit.clone(),
                amplitude: (bar / (x.norm_squared() * free)).sqrt(),
            })
            .collect()
    }

    /// Which candidates are searched: not structural, and slow terms only on two days or
    /// more. Returns those not tested for want of two days.
    pub fn allow(&mut self) -> Vec<String> {
        let two_days = self.drivers.span_h >= 48.0;
        let mut not_tested = Vec::new();
        let structural = &self.structural;
        self.allowed = self
            .cands
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let slow = crate::effects::effect(c.effect).is_some_and(|e| e.slow)
                    || c.term.contains("Fourier");
                if slow && !two_days && !structural[i] {
                    not_tested.push(format!("{}: {}", c.effect, c.term));
                }
                !structural[i] && (two_days || !slow)
            })
            .collect();
        not_tested
    }

    /// The effects none of whose (testable, non-step) candidates has `practical_tol` of its
    /// energy beyond the baseline.
    pub fn not_identifiable(&self) -> Vec<NotIdentifiable> {
        let (cands, opts) = (&self.cands, self.opts);
        let mut out = Vec::new();
        for e in crate::effects::EFFECTS {
            // Only what this recording can test (slow terms need two days).
            // A step is a change, not a level: whether the level is identifiable is asked of
            // the other shapes.
            let mut of: Vec<usize> = (0..cands.len())
                .filter(|i| {
                    cands[*i].effect == e.id
                        && cands[*i].shape_kind != crate::effects::ShapeKind::Step
                        && (self.allowed[*i] || self.structural[*i])
                })
                .collect();
            if of.is_empty() || of.iter().any(|i| self.free_of[*i] >= opts.practical_tol) {
                continue;
            }
            // Describe it by its strongest signature.
            of.sort_by(|a, b| self.xs[*b].norm().total_cmp(&self.xs[*a].norm()));
            let most_free = of.iter().map(|i| self.free_of[*i]).fold(0.0, f64::max);
            let (sn, best, best_cos) = self.confounding(&cands[of[0]]);
            let reason = if sn == 0.0 {
                "no reading of this plan is sensitive to it".to_string()
            } else if most_free >= opts.structural_tol {
                format!(
                    "in practice: at most {:.1} % of any of its time shapes lies outside the baseline; its signature is {best} (cos {best_cos:.3})",
                    100.0 * most_free
                )
            } else {
                format!(
                    "every time shape of it lies in the baseline: per unit, its signature is {best} (cos {best_cos:.3})"
                )
            };
            out.push(NotIdentifiable {
                effect: e.id.into(),
                label: e.label.into(),
                confounded_with: best,
                cos: best_cos,
                reason,
                split_by: crate::effects::advice(e, &self.rows),
            });
        }
        out
    }

    /// The combination of design parameters that makes up candidate `c`'s signature: the
    /// signature's norm, the combination in words and its |cos| with the signature.
    fn confounding(&self, c: &Candidate) -> (f64, String, f64) {
        let rows = &self.rows;
        let s: Vec<f64> = rows
            .signature(&c.signature)
            .map(|j| rows.rows.iter().map(|r| r.signature[j]).collect())
            .or_else(|| {
                rows.param(&c.signature)
                    .map(|j| rows.rows.iter().map(|r| r.sensitivity[j]).collect())
            })
            .unwrap_or_default();
        let sn = s.iter().map(|v| v * v).sum::<f64>().sqrt();
        let (mut best, mut best_cos) = (String::new(), 0.0);
        if sn > 0.0 {
            let a = DMatrix::from_fn(rows.rows.len(), rows.params.len(), |i, j| {
                rows.rows[i].sensitivity[j]
            });
            let f = lsq(&a, &DVector::from_column_slice(&s));
            let fitted = &a * &f.beta;
            best_cos = (fitted.dot(&DVector::from_column_slice(&s))
                / (fitted.norm() * sn).max(1e-300))
            .abs();
            let mut parts: Vec<(f64, String)> = rows
                .params
                .iter()
                .enumerate()
                .map(|(j, name)| (f.beta[j] * a.column(j).norm() / sn, name.clone()))
                .filter(|(w, _)| w.abs() > 0.1)
                .collect();
            parts.sort_by(|x, y| y.0.abs().total_cmp(&x.0.abs()));
            best = parts
                .iter()
                .map(|(_, n)| {
                    let j = rows.param(n).unwrap_or(0);
                    format!("{:+.3} {n}", f.beta[j])
                })
                .collect::<Vec<_>>()
                .join(" ");
        }
        (sn, best, best_cos)
    }

    /// A candidate's BIC penalty: its columns and its profiled (located) parameters.
    fn k_of(&self, i: usize) -> f64 {
        (self.xs[i].ncols() + self.cands[i].profiled) as f64 * self.ln_n
    }

    /// `base` with the columns of the candidates `chosen`.
    fn model_with(&self, base: &DMatrix<f64>, chosen: &[usize]) -> DMatrix<f64> {
        let cols: Vec<&DMatrix<f64>> = chosen.iter().map(|i| &self.xs[*i]).collect();
        hstack(base, &cols)
    }

    /// Forward selection and backward pruning over `base` (the baseline, or the baseline with
    /// a periodic discrepancy the library has no shape for).
    pub fn select(&self, base: &DMatrix<f64>) -> Selection {
        let mut scoring = CycleScoring {
            s: self,
            base,
            m: DMatrix::zeros(0, 0),
            refused: Vec::new(),
            blocks_better: BTreeMap::new(),
        };
        let rules = Rules {
            max_terms: self.opts.max_terms,
            tries: 5,
            min_worth: self.opts.min_delta_bic,
        };
        let chosen = stepwise(&mut scoring, &rules);
        Selection {
            chosen,
            refused: scoring.refused,
            blocks_better: scoring.blocks_better,
        }
    }

    /// A periodic residual at a period the library has no shape for, after selection `sel`:
    /// modelled as a discrepancy (so that no library term is forced into its shape), then the
    /// search again. The effective baseline, the selection over it, and the finding with its
    /// number of columns.
    pub fn periodic(
        &self,
        sel: Selection,
    ) -> (DMatrix<f64>, Selection, Option<(PeriodicResidual, usize)>) {
        let m = self.model_with(&self.base, &sel.chosen);
        match periodic_scan(&self.rows, &m, &self.y, self.sigma, self.opts) {
            Some((found, block)) => {
                let base_eff = hstack(&self.base, &[&block]);
                let sel = self.select(&base_eff);
                (base_eff, sel, Some((found, block.ncols())))
            }
            None => (self.base.clone(), sel, None),
        }
    }

    /// A signature class (or the design parameters) times a time shape, whitened.
    fn class_times(&self, names: &[String], shape: &[Vec<f64>]) -> DMatrix<f64> {
        let cols: Vec<Vec<f64>> = names
            .iter()
            .filter_map(|nm| crate::effects::signature_column(&self.rows, nm))
            .collect();
        DMatrix::from_fn(self.n, cols.len() * shape.len(), |i, c| {
            let (j, g) = (c / shape.len(), c % shape.len());
            cols[j][i] * shape[g][i] / self.sigma
        })
    }

    /// Terms that coincide in time with an earlier accepted effect (their footprint, beyond
    /// the baseline, lies within what the design parameters do in that effect's time shape)
    /// must be justified on held-out data (delta-chi2 summed over the blocks, each predicted
    /// from the others, of min_delta_bic or more); then they are kept but not named, else
    /// they are folded into that effect's group (and dropped from `chosen`).
    pub fn coincidences(&self, base_eff: &DMatrix<f64>, chosen: &mut Vec<usize>) -> Coincidences {
        let (xs, y, opts) = (&self.xs, &self.y, self.opts);
        let mut out = Coincidences::default();
        let qb = basis(base_eff);
        let p0 = base_eff.ncols();
        let mut pos = 1;
        while pos < chosen.len() {
            let ti = chosen[pos];
            let m = self.model_with(base_eff, chosen);
            let f = lsq(&m, y);
            let off = p0 + chosen[..pos].iter().map(|j| xs[*j].ncols()).sum::<usize>();
            let ft = &xs[ti] * f.beta.rows(off, xs[ti].ncols());
            let v = &ft - &qb * qb.tr_mul(&ft);
            let vv = v.norm_squared();
            let Some((ei, cos)) = self.coinciding(&qb, &chosen[..pos], ti, &v, vv) else {
                pos += 1;
                continue;
            };
            let without: Vec<usize> = chosen.iter().copied().filter(|j| *j != ti).collect();
            let mo = self.model_with(base_eff, &without);
            let ho: f64 = (0..self.blocks.len())
                .map(|blk| {
                    let (tr, te) = self.split(blk);
                    heldout_sse(&mo, y, &tr, &te) - heldout_sse(&m, y, &tr, &te)
                })
                .sum();
            let dchi = lsq(&mo, y).chi2 - f.chi2;
            if ho < opts.min_delta_bic {
                // Not a rival to its name: the data do not justify it on its own.
                out.folded.push((
                    ei,
                    self.coincident_member(
                        ti,
                        (cos, dchi, vv),
                        false,
                        format!(
                            "coincides in time with it (cos {cos:.2} with the design parameters in its time shape) and the held-out blocks gain only delta-chi2 {ho:.1} from it (under {}): not accepted on its own",
                            opts.min_delta_bic
                        ),
                    ),
                ));
                chosen.remove(pos);
            } else {
                out.coincident.insert(
                    ti,
                    self.coincident_member(
                        ei,
                        (cos, dchi, vv),
                        true,
                        format!(
                            "it coincides in time with this accepted term (cos {cos:.2} with the design parameters in its time shape); kept because the held-out blocks gain delta-chi2 {ho:.1} from it, but it may be more of that effect"
                        ),
                    ),
                );
                pos += 1;
            }
        }
        out
    }

    /// The first of the earlier terms `earlier` of another effect whose time shape, with the
    /// design parameters in it, holds term `ti`'s footprint `v` beyond the baseline (basis
    /// `qb`, `vv = |v|^2`) to |cos| over `ambiguity_cos`, with that cos.
    fn coinciding(
        &self,
        qb: &DMatrix<f64>,
        earlier: &[usize],
        ti: usize,
        v: &DVector<f64>,
        vv: f64,
    ) -> Option<(usize, f64)> {
        let (cands, xs) = (&self.cands, &self.xs);
        for &ei in earlier {
            if cands[ei].effect == cands[ti].effect || vv == 0.0 {
                continue;
            }
            let xe = hstack(
                &self.class_times(&self.rows.params, &cands[ei].shape),
                &[&xs[ei]],
            );
            let Some(be) = beyond(qb, &xe, self.opts.structural_tol) else {
                continue;
            };
            let cos = (be.tr_mul(v).norm_squared() / vv).sqrt();
            if cos > self.opts.ambiguity_cos
                || same_cause(cands[ei].shape_kind, cands[ti].shape_kind)
            {
                return Some((ei, cos));
            }
        }
        None
    }

    /// Candidate `c` as a member of another's group, with `(cos, delta-chi2, |v|^2)`.
    fn coincident_member(
        &self,
        c: usize,
        (cos, dchi, vv): (f64, f64, f64),
        comparable: bool,
        reason: String,
    ) -> GroupMember {
        GroupMember {
            effect: self.cands[c].effect.into(),
            term: self.cands[c].term.clone(),
            cos,
            delta_chi2: dchi,
            footprint_left_chi2: (1.0 - cos * cos).max(0.0) * vv,
            parameters: self.xs[c].ncols() + self.cands[c].profiled,
            comparable,
            splits_at: None,
            reason,
        }
    }

    /// The final fit of `chosen` over `base_eff`.
    pub fn final_fit(
        &self,
        base_eff: DMatrix<f64>,
        chosen: Vec<usize>,
        blocks_better: BTreeMap<usize, usize>,
        coincidences: Coincidences,
    ) -> Final {
        let m = self.model_with(&base_eff, &chosen);
        let fit = self.figures(&m);
        let f = lsq(&m, &self.y);
        let dof = self.n.saturating_sub(f.rank).max(1);
        let scale = (f.chi2 / dof as f64).max(1.0);
        Final {
            base_eff,
            chosen,
            blocks_better,
            coincidences,
            m,
            fit,
            f,
            scale,
        }
    }

    /// Each chosen term's figures, ambiguity group and statement, and its footprint
    /// `(term, [row])`, um.
    pub fn accepted(
        &self,
        fin: &Final,
        sensors: &[String],
    ) -> (Vec<Accepted>, Vec<(String, Vec<f64>)>) {
        let mut accepted = Vec::new();
        let mut footprints = Vec::new();
        let mut off = fin.base_eff.ncols();
        for pos in 0..fin.chosen.len() {
            let i = fin.chosen[pos];
            let tf = self.term_fit(fin, pos, off);
            off += tf.k;
            let c = &self.cands[i];
            let naming = self.naming(fin, i, &tf);
            let names: Vec<String> = if tf.k == 1 {
                vec![c.term.clone()]
            } else {
                (0..tf.k)
                    .map(|j| format!("{} [{}]", c.term, if j == 0 { "cos" } else { "sin" }))
                    .collect()
            };
            let parameters: Vec<Parameter> = names
                .into_iter()
                .enumerate()
                .map(|(j, name)| Parameter {
                    name,
                    unit: c.unit.clone(),
                    value: tf.b[j],
                    sigma: tf.cov[(j, j)].max(0.0).sqrt(),
                })
                .collect();
            let amplitude = (tf.foot.norm_squared() / self.n as f64).sqrt();
            let peak = tf.foot.amax();
            let statement = self.statement(c, &tf, &parameters, &naming);
            let improved = fin.blocks_better.get(&i).copied().unwrap_or(0);
            footprints.push((
                c.term.clone(),
                tf.foot.iter().copied().collect::<Vec<f64>>(),
            ));
            accepted.push(Accepted {
                effect: c.effect.into(),
                label: crate::effects::effect(c.effect)
                    .map_or(c.effect, |e| e.label)
                    .into(),
                term: c.term.clone(),
                parameters,
                amplitude_rms_um: amplitude,
                peak_um: peak,
                t: tf.t,
                delta_bic: tf.dbic,
                heldout_rms_before_um: tf.ho_before,
                heldout_rms_after_um: tf.ho_after,
                blocks_improved: improved,
                blocks: self.blocks.len(),
                named: naming.named,
                named_at: naming.named_at,
                step_ns: c.step_ns,
                ambiguity_group: naming.group,
                split_by: naming.split_by.join("; "),
                statement,
                model_input: model_input(
                    &c.signature,
                    c.term.split_once(" x ").map_or("", |x| x.1),
                    &self.rows.locations,
                    sensors,
                ),
            });
        }
        (accepted, footprints)
    }

    /// The term at `pos` of the final model, its columns from `off`: value, covariance,
    /// footprint, delta-BIC, t and held-out RMS on the last block without and with it.
    fn term_fit(&self, fin: &Final, pos: usize, off: usize) -> TermFit {
        let (y, sigma) = (&self.y, self.sigma);
        let i = fin.chosen[pos];
        let k = self.xs[i].ncols();
        let b = fin.f.beta.rows(off, k).into_owned();
        let cov = fin.f.cov.view((off, off), (k, k)).into_owned() * fin.scale;
        let foot = &self.xs[i] * &b * sigma;
        let rest: Vec<usize> = fin
            .chosen
            .iter()
            .enumerate()
            .filter(|(p, _)| *p != pos)
            .map(|(_, j)| *j)
            .collect();
        let mrest = self.model_with(&fin.base_eff, &rest);
        let dbic = lsq(&mrest, y).chi2 - fin.f.chi2 - self.k_of(i);
        let t = inverse_form(cov.clone(), &b).map_or(0.0, f64::sqrt);
        let (ho_before, ho_after) = {
            let sse = |m: &DMatrix<f64>| heldout_sse(m, y, &self.train_last, &self.test_last);
            let rms = |s: f64| (s / self.test_last.len().max(1) as f64).sqrt() * sigma;
            (rms(sse(&mrest)), rms(sse(&fin.m)))
        };
        TermFit {
            k,
            b,
            cov,
            foot,
            mrest,
            dbic,
            t,
            ho_before,
            ho_after,
        }
    }

    /// Term `i`'s ambiguity group, whether it is named, and how to split it from the rest.
    fn naming(&self, fin: &Final, i: usize, tf: &TermFit) -> Naming {
        let c = &self.cands[i];
        let rival = self.rival(fin, i, tf);
        let mut group = if rival.vv > 0.0 {
            self.ambiguity_group(&fin.chosen, i, &rival)
        } else {
            Vec::new()
        };
        for (ei, m) in &fin.coincidences.folded {
            if *ei == i {
                group.push(m.clone());
            }
        }
        let coincides = fin.coincidences.coincident.get(&i).cloned();
        if let Some(m) = &coincides {
            group.push(m.clone());
        }
        let rivals: Vec<&GroupMember> = group
            .iter()
            .filter(|g| g.effect != c.effect && g.comparable)
            .collect();
        let named = coincides.is_none() && rivals.is_empty();
        let named_at = if named || coincides.is_some() {
            None
        } else {
            rivals
                .iter()
                .map(|g| g.splits_at)
                .try_fold(1.0_f64, |m, f| f.map(|f| m.max(f)))
        };
        group.sort_by(|a, b| {
            b.comparable
                .cmp(&a.comparable)
                .then(b.cos.total_cmp(&a.cos))
        });
        let mut split_by: Vec<String> = Vec::new();
        for g in group.iter().map(|g| g.effect.as_str()).chain([c.effect]) {
            if let Some(s) =
                crate::effects::effect(g).map(|e| crate::effects::advice(e, &self.rows))
                && !split_by.contains(&s)
            {
                split_by.push(s);
            }
        }
        Naming {
            named,
            named_at,
            group,
            coincides,
            split_by,
        }
    }

    /// What alternatives to term `i` of the final model are measured against.
    fn rival(&self, fin: &Final, i: usize, tf: &TermFit) -> Rival<'a> {
        let qr = basis(&tf.mrest);
        let chi2_rest = lsq(&tf.mrest, &self.y).chi2;
        let e_rest = residual_of(&tf.mrest, &self.y);
        let v = {
            let f = &self.xs[i] * &tf.b;
            &f - &qr * qr.tr_mul(&f)
        };
        let vv = v.norm_squared();
        Rival {
            opts: self.opts,
            qr,
            chi2_rest,
            e_rest,
            full_chi2: fin.f.chi2,
            v,
            vv,
            k_term: (tf.k + self.cands[i].profiled) as f64,
        }
    }

    /// Ambiguity: other explanations of term `i`'s footprint beyond the rest: each other
    /// candidate; each signature class in the same time shape (jointly); the classes of other
    /// effects together (a combination, up to 24 columns); the pose-shaped effects'
    /// candidates together. An alternative explains it comparably when it carries the
    /// footprint but for a relative 1e-3 (the plan cannot tell them apart, whatever the
    /// data), or when it fits as well: the lesser of what it leaves of the footprint and how
    /// much worse it fits the data, plus 2 per parameter it has beyond the term's, under
    /// min_delta_bic. Such an alternative of another effect and the term is not named.
    fn ambiguity_group(&self, chosen: &[usize], i: usize, rival: &Rival) -> Vec<GroupMember> {
        let c = &self.cands[i];
        let mut group: Vec<GroupMember> = Vec::new();
        let mut constant_alone: BTreeMap<usize, bool> = BTreeMap::new();
        for (j, x) in self.xs.iter().enumerate() {
            if j == i || chosen.contains(&j) || self.structural[j] || !self.allowed[j] {
                continue;
            }
            let Some(a) = rival.alt(x, self.cands[j].profiled) else {
                continue;
            };
            if rival.close(&a) {
                group.push(rival.member(
                    self.cands[j].effect,
                    self.cands[j].term.clone(),
                    &a,
                    "another candidate",
                ));
            }
            // A signature whose static value the baseline does not hold (a squareness) never
            // follows a temperature from zero: the candidate with its own constant beside it,
            // one parameter more, is the fair rival of a term whose constant the baseline
            // holds (a location error following the same temperature).
            if a.comparable {
                continue;
            }
            // (Only where the constant alone does not already explain the term: then the
            // pair says nothing the constant does not.)
            if let Some(k) = self.constant_sibling(j)
                && k != i
                && !chosen.contains(&k)
                && !*constant_alone.entry(k).or_insert_with(|| {
                    rival
                        .alt(&self.xs[k], self.cands[k].profiled)
                        .is_some_and(|a| a.comparable)
                })
                && let Some(a2) = rival.alt(
                    &hstack(x, &[&self.xs[k]]),
                    self.cands[j].profiled + self.cands[k].profiled,
                )
                && a2.comparable
            {
                group.push(rival.member(
                    self.cands[j].effect,
                    format!("{} with {}", self.cands[j].term, self.cands[k].term),
                    &a2,
                    "another candidate with its static part",
                ));
            }
        }
        let mut others: Vec<(&'static str, Vec<String>, DMatrix<f64>)> = Vec::new();
        for (cls, names) in crate::effects::signature_classes(&self.rows) {
            let Some(effect) = crate::effects::class_effect(cls, c.shape_kind) else {
                continue;
            };
            if effect == c.effect {
                continue;
            }
            let x = self.class_times(&names, &c.shape);
            if let Some(a) = rival.alt(&x, c.profiled)
                && rival.close(&a)
            {
                group.push(rival.member(
                    effect,
                    format!("{} x the same time shape", names.join(", ")),
                    &a,
                    &format!("{} in the same time shape", names.join(", ")),
                ));
            }
            others.push((effect, names, x));
        }
        let alone = group.iter().any(|g| g.effect != c.effect && g.comparable);
        let union_cols: usize = others.iter().map(|o| o.2.ncols()).sum();
        if !alone && others.len() > 1 && union_cols <= 24 {
            self.combination(&others, c.profiled, rival, &mut group);
        }
        self.pose_shaped(c, rival, &mut group);
        group
    }

    /// The searched constant-shape candidate of candidate `j`'s signature, when `j` has
    /// another shape: its static part where the baseline does not hold it.
    fn constant_sibling(&self, j: usize) -> Option<usize> {
        let c = &self.cands[j];
        if c.shape_kind == crate::effects::ShapeKind::Constant || c.columns.len() != 1 {
            return None;
        }
        (0..self.cands.len()).find(|&k| {
            let o = &self.cands[k];
            k != j
                && o.signature == c.signature
                && o.shape_kind == crate::effects::ShapeKind::Constant
                && self.allowed[k]
                && !self.structural[k]
        })
    }

    /// The other effects' classes in the term's time shape together (`others`): when they
    /// explain it comparably, each class that makes up over a fifth of the combination.
    fn combination(
        &self,
        others: &[(&'static str, Vec<String>, DMatrix<f64>)],
        profiled: usize,
        rival: &Rival,
        group: &mut Vec<GroupMember>,
    ) {
        let refs: Vec<&DMatrix<f64>> = others.iter().map(|o| &o.2).collect();
        let xu = hstack(&DMatrix::zeros(self.n, 0), &refs);
        let Some(a) = rival.alt(&xu, profiled) else {
            return;
        };
        if !a.comparable {
            return;
        }
        // Which classes make up the combination: their share of the footprint.
        let qr = &rival.qr;
        let xt = &xu - qr * qr.tr_mul(&xu);
        let fit = lsq(&xt, &rival.v);
        let all: Vec<String> = others.iter().flat_map(|o| o.1.clone()).collect();
        let mut col = 0;
        for (effect, names, x) in others {
            let kc = x.ncols();
            let part = xt.columns(col, kc) * fit.beta.rows(col, kc);
            col += kc;
            let share = part.norm() / rival.vv.sqrt();
            if share > 0.2 {
                group.push(rival.member(
                    effect,
                    format!("{} x the same time shape, in combination", names.join(", ")),
                    &a,
                    &format!(
                        "a combination of {} in the same time shape, {} {:.0} % of it",
                        all.join(", "),
                        names.join(", "),
                        100.0 * share
                    ),
                ));
            }
        }
    }

    /// The pose-shaped effects' searched candidates together, for a term of another effect.
    fn pose_shaped(&self, c: &Candidate, rival: &Rival, group: &mut Vec<GroupMember>) {
        for eff in ["c_indexing", "rotary_backlash"] {
            if eff == c.effect {
                continue;
            }
            let of: Vec<usize> = (0..self.cands.len())
                .filter(|j| self.cands[*j].effect == eff && self.allowed[*j])
                .collect();
            let x = hstack(
                &DMatrix::zeros(self.n, 0),
                &of.iter().map(|j| &self.xs[*j]).collect::<Vec<_>>(),
            );
            if of.len() < 2 || x.ncols() > 6 {
                continue;
            }
            if let Some(a) = rival.alt(&x, 0)
                && rival.close(&a)
            {
                group.push(rival.member(
                    eff,
                    "all its shapes together".into(),
                    &a,
                    "its shapes together",
                ));
            }
        }
    }

    /// What accepted term `c` is and what it did, in words.
    fn statement(
        &self,
        c: &Candidate,
        tf: &TermFit,
        parameters: &[Parameter],
        naming: &Naming,
    ) -> String {
        let (named, group) = (naming.named, &naming.group);
        let e = crate::effects::effect(c.effect);
        let amplitude = (tf.foot.norm_squared() / self.n as f64).sqrt();
        let peak = tf.foot.amax();
        let mut other_effects: Vec<&str> = Vec::new();
        for g in group {
            if g.effect != c.effect && !other_effects.contains(&g.effect.as_str()) {
                other_effects.push(g.effect.as_str());
            }
        }
        let label_of =
            |id: &str| crate::effects::effect(id).map_or(id.to_string(), |e| e.label.to_string());
        let head = if named {
            e.map_or(c.effect.to_string(), |e| e.label.to_string())
        } else {
            let mut alts: Vec<String> = vec![label_of(c.effect)];
            for g in group {
                let l = label_of(&g.effect);
                if (g.comparable
                    || naming
                        .coincides
                        .as_ref()
                        .is_some_and(|m| m.effect == g.effect))
                    && !alts.contains(&l)
                {
                    alts.push(l);
                }
            }
            format!("Not named, one of: {}", alts.join(" OR "))
        };
        let split_by = &naming.split_by;
        format!(
            "{}: {} = {} ({}); it moves the readings by {:.2} um RMS, {:.2} um at most, against a reading noise of {:.2} um; held-out RMS {:.3} -> {:.3} um.{}{}",
            head,
            c.term,
            parameters
                .iter()
                .map(|p| format!("{:.3} +- {:.3} {}", p.value, p.sigma, p.unit))
                .collect::<Vec<_>>()
                .join(", "),
            e.map_or("", |e| e.physics),
            amplitude,
            peak,
            self.sigma,
            tf.ho_before,
            tf.ho_after,
            if other_effects.is_empty() {
                String::new()
            } else if named {
                format!(
                    " Footprints like it: {}, but none fits the data as well; to split them further: {}.",
                    other_effects.join(", "),
                    split_by.join("; ")
                )
            } else {
                format!(
                    " The plan cannot tell it from {}; to split them: {}.{}",
                    other_effects.join(", "),
                    split_by.join("; "),
                    match (naming.named_at, &naming.coincides) {
                        (Some(f), _) if f > 1.05 => format!(
                            " If it is the cause, it would be named at about {f:.1} times this amplitude on this plan."
                        ),
                        (Some(_), _) => " If it is the cause, most recordings of this amplitude would name it; on this one the noise leaves a rival as good.".to_string(),
                        (None, None) => " No amplitude names it on this plan.".to_string(),
                        (None, Some(_)) => String::new(),
                    }
                )
            },
            if c.shape_kind == crate::effects::ShapeKind::Fourier {
                " Its time shape is a daily pair because no logged temperature explains it as well: log the temperature that drives it (the hall's air, most often) to name its driver."
            } else {
                ""
            }
        )
    }

    /// Per channel (step of the cycle), before (`baseline`) and after (`fin`).
    pub fn channels(&self, baseline: &Fit, fin: &Final) -> Vec<ChannelFigures> {
        let (n, rows, y, sigma) = (self.n, &self.rows, &self.y, self.sigma);
        let nb = self.blocks.len();
        let frac = (n.saturating_sub(fin.f.rank)) as f64 / n as f64;
        let frac0 = (n.saturating_sub(lsq(&self.base, y).rank)) as f64 / n as f64;
        let ho_b = y - &baseline.pred;
        let ho_f = y - &fin.fit.pred;
        let (base_resid, fin_resid) = (&baseline.resid, &fin.fit.resid);
        let mut channels = Vec::new();
        for s in &self.steps() {
            let idx: Vec<usize> = (0..n).filter(|i| &rows.rows[*i].step == s).collect();
            let tr: Vec<usize> = idx
                .iter()
                .copied()
                .filter(|i| self.block_of[*i] != nb - 1)
                .collect();
            let te: Vec<usize> = idx
                .iter()
                .copied()
                .filter(|i| self.block_of[*i] == nb - 1)
                .collect();
            let ms = |v: &DVector<f64>, ix: &[usize]| {
                ix.iter().map(|i| v[*i].powi(2)).sum::<f64>() / ix.len().max(1) as f64
            };
            let mut by_time = idx.clone();
            by_time.sort_by_key(|i| rows.rows[*i].t_ns);
            let series: Vec<f64> = by_time.iter().map(|i| fin_resid[*i] * sigma).collect();
            channels.push(ChannelFigures {
                channel: s.clone(),
                n: idx.len(),
                ljung_box_p_after: driftwatch_core::stats::ljung_box(&series, 10)
                    .map(|lb| lb.p_value),
                chi2_dof_before: ms(base_resid, &idx) / frac0.max(1e-9),
                chi2_dof_after: ms(fin_resid, &idx) / frac.max(1e-9),
                rms_train_before_um: ms(base_resid, &tr).sqrt() * sigma,
                rms_train_after_um: ms(fin_resid, &tr).sqrt() * sigma,
                rms_heldout_before_um: ms(&ho_b, &te).sqrt() * sigma,
                rms_heldout_after_um: ms(&ho_f, &te).sqrt() * sigma,
            });
        }
        channels
    }

    /// The steps of the cycle (channels), sorted.
    fn steps(&self) -> Vec<String> {
        let mut steps: Vec<String> = self.rows.rows.iter().map(|r| r.step.clone()).collect();
        steps.sort();
        steps.dedup();
        steps
    }

    /// The periodic discrepancy `found` (`kb` columns after the baseline's), sized in the
    /// final fit: its amplitude, the design parameters that carry it and its statement.
    pub fn size_periodic(
        &self,
        fin: &Final,
        mut found: PeriodicResidual,
        kb: usize,
    ) -> PeriodicResidual {
        let (n, sigma, rows) = (self.n, self.sigma, &self.rows);
        let pb = rows.params.len();
        let at = self.base.ncols();
        let bb = fin.f.beta.rows(at, kb).into_owned();
        let cv = fin.f.cov.view((at, at), (kb, kb)).into_owned() * fin.scale;
        let block = fin.base_eff.columns(at, kb).into_owned();
        let foot = &block * &bb * sigma;
        found.amplitude_rms_um = (foot.norm_squared() / n as f64).sqrt();
        found.peak_um = foot.amax();
        let mut carried: Vec<Parameter> = (0..pb)
            .map(|j| {
                let (c, s_) = (bb[j], bb[j + pb]);
                let a = c.hypot(s_);
                let var = if a > 0.0 {
                    (c * c * cv[(j, j)]
                        + 2.0 * c * s_ * cv[(j, j + pb)]
                        + s_ * s_ * cv[(j + pb, j + pb)])
                        / (a * a)
                } else {
                    cv[(j, j)]
                };
                Parameter {
                    name: rows.params[j].clone(),
                    unit: crate::effects::signature_unit(&rows.params[j]).into(),
                    value: a,
                    sigma: var.max(0.0).sqrt(),
                }
            })
            .filter(|p| p.value >= 3.0 * p.sigma)
            .collect();
        carried.sort_by(|a, b| {
            (b.value / b.sigma.max(1e-300)).total_cmp(&(a.value / a.sigma.max(1e-300)))
        });
        found.statement = periodic_statement(&found, &carried);
        found.carried_by = carried;
        found
    }

    /// What stays structured after the final fit `fin`: the worst channel by Ljung-Box, where
    /// and when the residuals are systematic, and the discrepancy (with the periodic one).
    pub fn unexplained(
        &self,
        fin: &Final,
        phase: &[&'static str],
        periodic: Option<PeriodicResidual>,
        channels: &[ChannelFigures],
    ) -> Vec<Unexplained> {
        let (n, rows, sigma) = (self.n, &self.rows, self.sigma);
        let fin_um: Vec<f64> = fin.fit.resid.iter().map(|v| v * sigma).collect();
        let serial = SerialCorrelation::of(channels);
        let final_fig = &fin.fit.figures;
        if !(final_fig.chi2_dof > 1.2 || serial.p_channels < UNEXPLAINED_P || periodic.is_some()) {
            return Vec::new();
        }
        let mut where_ = locate(rows, &fin_um, sigma, 4.0);
        group_means(
            "phase",
            phase.iter().map(|p| p.to_string()),
            &fin_um,
            sigma,
            4.0,
            &mut where_,
        );
        where_.sort_by(|a, b| b.t.abs().total_cmp(&a.t.abs()));
        where_.truncate(8);
        let mut per_cycle: BTreeMap<i64, (i64, f64, usize)> = BTreeMap::new();
        for (r, e) in rows.rows.iter().zip(&fin_um) {
            let c = per_cycle.entry(r.cycle).or_insert((r.t_ns, 0.0, 0));
            c.1 += e;
            c.2 += 1;
        }
        let mut when: Vec<(i64, f64)> = per_cycle
            .values()
            .map(|(t, s, k)| (*t, s / *k as f64))
            .collect();
        when.sort_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
        when.truncate(5);
        let ms = fin_um.iter().map(|v| v * v).sum::<f64>() / n as f64;
        vec![Unexplained {
            chi2_dof: final_fig.chi2_dof,
            ljung_box_p: serial.p,
            ljung_box_p_channels: serial.p_channels,
            channels_tested: serial.tested,
            channel: serial.channel,
            located: where_,
            when,
            discrepancy_um: match &periodic {
                Some(p) => p
                    .amplitude_rms_um
                    .hypot((ms - sigma * sigma).max(0.0).sqrt()),
                None => (ms - sigma * sigma).max(0.0).sqrt(),
            },
            periodic,
        }]
    }
}

/// Whether two time shapes share their cause whatever their footprints' overlap: the tilt duty
/// and the cycles' spins missing from the log both follow the cycle schedule (a cycle tilts B
/// and spins the spindle), so a tilt term beside an accepted measurement-heating term may be
/// more of the cycles' unlogged heat; it stays only if the held-out blocks justify it.
fn same_cause(a: crate::effects::ShapeKind, b: crate::effects::ShapeKind) -> bool {
    use crate::effects::ShapeKind::{MissingSpins, Tilt};
    matches!((a, b), (MissingSpins, Tilt) | (Tilt, MissingSpins))
}

/// The false-flag rate of the "unexplained" serial-correlation test on a clean recording: over
/// all its channels together, not per channel (a recording has about 18; tested each at this
/// level, one clean recording in fifty would be flagged).
pub const UNEXPLAINED_P: f64 = 1e-3;

/// Serial correlation left in the final residuals, over the channels.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialCorrelation {
    /// The smallest Ljung-Box p of a channel, and that channel.
    pub p: f64,
    pub channel: String,
    /// Channels with enough readings to test.
    pub tested: usize,
    /// The smallest p judged over every channel tested ([`sidak`]).
    pub p_channels: f64,
}

impl SerialCorrelation {
    pub fn of(channels: &[ChannelFigures]) -> Self {
        let tested: Vec<(f64, &str)> = channels
            .iter()
            .filter_map(|c| Some((c.ljung_box_p_after?, c.channel.as_str())))
            .collect();
        let (p, channel) = tested
            .iter()
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or((1.0, String::new()), |(p, c)| (*p, c.to_string()));
        SerialCorrelation {
            p,
            channel,
            tested: tested.len(),
            p_channels: sidak(p, tested.len()),
        }
    }
}

/// The probability that the smallest of `m` independent p-values is at most `p_min` when
/// nothing is there (Sidak): the family-wise p of the most serially correlated channel.
fn sidak(p_min: f64, m: usize) -> f64 {
    if m == 0 {
        return 1.0;
    }
    // 1 - (1 - p)^m without losing a small p to rounding.
    -(m as f64 * (-p_min.clamp(0.0, 1.0)).ln_1p()).exp_m1()
}

/// The periodic discrepancy in words, carried by `carried`.
fn periodic_statement(found: &PeriodicResidual, carried: &[Parameter]) -> String {
    format!(
        "A periodic residual with a period of {:.1} min{} moves the readings by {:.2} um RMS ({:.2} um at most; delta-BIC {:.0}), carried by {}. No effect of the library has this time shape (its periodic shapes are the 24-h and 12-h pairs): it is modelled as a discrepancy so that no library term is forced into it, and left unexplained. Log what cycles at this period (coolant or chiller, hydraulics) to name it.",
        found.period_min,
        if found.aliases_min.is_empty() {
            String::new()
        } else {
            format!(
                " (or {} min: at this cycle cadence the data cannot tell them apart)",
                found
                    .aliases_min
                    .iter()
                    .map(|p| format!("{p:.1}"))
                    .collect::<Vec<_>>()
                    .join(" or ")
            )
        },
        found.amplitude_rms_um,
        found.peak_um,
        found.delta_bic,
        if carried.is_empty() {
            "no single design parameter".to_string()
        } else {
            carried
                .iter()
                .map(|p| format!("{} ({:.2} +- {:.2} {})", p.name, p.value, p.sigma, p.unit))
                .collect::<Vec<_>>()
                .join(", ")
        }
    )
}

/// The cycle search's scoring for [`stepwise`] over one baseline: a candidate ranks by
/// delta-BIC (its columns and profiled parameters charged `ln N` each) and is taken when its
/// |t|, its footprint and its held-out blocks pass; a chosen term is worth its delta-BIC.
struct CycleScoring<'s, 'a> {
    s: &'s Search<'a>,
    base: &'s DMatrix<f64>,
    /// The model of the current forward step.
    m: DMatrix<f64>,
    refused: Vec<Refused>,
    blocks_better: BTreeMap<usize, usize>,
}

impl Scoring for CycleScoring<'_, '_> {
    fn rank(&mut self, chosen: &[usize]) -> Vec<(usize, f64)> {
        let s = self.s;
        self.m = s.model_with(self.base, chosen);
        let q = basis(&self.m);
        let e = residual_of(&self.m, &s.y);
        let mut ranked: Vec<(usize, f64)> = (0..s.cands.len())
            .filter(|i| s.allowed[*i] && !chosen.contains(i))
            .map(|i| {
                let (d, _) = scan(&q, &e, &s.xs[i]);
                (i, d - s.k_of(i))
            })
            .filter(|(_, b)| *b >= s.opts.min_delta_bic)
            .collect();
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
        ranked
    }

    fn judge(&mut self, chosen: &[usize], i: usize, dbic: f64) -> Verdict {
        let (s, opts) = (self.s, self.s.opts);
        let (y, xs, cands) = (&s.y, &s.xs, &s.cands);
        let mut with = chosen.to_vec();
        with.push(i);
        let mw = s.model_with(self.base, &with);
        let f = lsq(&mw, y);
        let dof = s.n.saturating_sub(f.rank).max(1);
        let scale = (f.chi2 / dof as f64).max(1.0);
        let k = xs[i].ncols();
        let off = mw.ncols() - k;
        let b = f.beta.rows(off, k).into_owned();
        let c = f.cov.view((off, off), (k, k)).into_owned() * scale;
        let t = inverse_form(c.clone(), &b).map_or(0.0, f64::sqrt);
        let foot = &xs[i] * &b * s.sigma;
        let peak = foot.amax();
        let max_um = crate::effects::effect(cands[i].effect).map_or(f64::INFINITY, |e| e.max_um);
        let nb = s.blocks.len();
        let mut improved = 0;
        for blk in 0..nb {
            let (tr, te) = s.split(blk);
            if heldout_sse(&mw, y, &tr, &te) < heldout_sse(&self.m, y, &tr, &te) {
                improved += 1;
            }
        }
        let need = (opts.min_blocks_improved * nb as f64 - 1e-9).ceil() as usize;
        let reason = if t < opts.min_t {
            Some(format!("|t| {t:.1} < {}", opts.min_t))
        } else if peak > max_um {
            Some(format!(
                "footprint {peak:.1} um beyond the plausible {max_um} um"
            ))
        } else if improved < need {
            Some(format!(
                "held-out fit better in {improved} of {nb} blocks (needs {need})"
            ))
        } else {
            None
        };
        let Some(reason) = reason else {
            self.blocks_better.insert(i, improved);
            return Verdict::Take;
        };
        if !self
            .refused
            .iter()
            .any(|r| r.term == cands[i].term && r.effect == cands[i].effect)
        {
            self.refused.push(Refused {
                effect: cands[i].effect.into(),
                term: cands[i].term.clone(),
                delta_bic: dbic,
                t,
                reason,
            });
        }
        Verdict::Refuse
    }

    fn worth(&mut self, chosen: &[usize]) -> Vec<f64> {
        let s = self.s;
        let full = lsq(&s.model_with(self.base, chosen), &s.y).chi2;
        chosen
            .iter()
            .enumerate()
            .map(|(pos, i)| {
                let mut without = chosen.to_vec();
                without.remove(pos);
                let d = lsq(&s.model_with(self.base, &without), &s.y).chi2 - full;
                d - s.k_of(*i)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::sidak;

    /// The smallest of 18 channels' p-values at 0.00085 is no rare event over the 18 (about
    /// 1.5 %); one channel's p is its own; a p far below rounding keeps its size.
    #[test]
    fn the_smallest_p_is_judged_over_every_channel_tested() {
        assert!((sidak(0.00085, 18) - 0.01519).abs() < 1e-4);
        assert!((sidak(0.00085, 1) - 0.00085).abs() < 1e-15);
        assert!((sidak(1e-20, 18) / 18e-20 - 1.0).abs() < 1e-9);
        assert_eq!(sidak(0.3, 0), 1.0);
        assert!((sidak(1.0, 5) - 1.0).abs() < 1e-15);
    }
}
