//! The thermal base of a recording without a spindle log (docs/physics.md 4.6.2, "Thermal
//! base"). With a spindle log the baseline's spindle mode models the warm-up; without one the
//! baseline is the offset alone and its residual is the whole warm-up, so slow that the AR
//! noise model of that residual is near a random walk (lag-1 autocorrelation 0.999 on a 78-h
//! spindle test). The forward selection scores a candidate with the noise model of the model
//! without it, and whitening with a random walk differences every slow candidate away: no
//! temperature could carry the warm-up, and every later departure was sought in the misfit
//! of the warm-up. The base is therefore the forward selection's first step over the logged
//! temperatures and their lags, scored as the located term is (each model with the noise
//! model of its own residual), against the same surrogate bar, |t|, rolling origins and
//! footprint. Like the spindle mode it stands for, it is part of the baseline the whole search
//! then runs on again. The held-out veto judges the base with what was found on it: the search
//! on the base is kept when its final model is no worse on the held-out end than the search on
//! the offset alone; otherwise the base and its located terms are reported beside the final
//! model with their figures. (Exempt from the veto, a base of one temperature replaced better
//! terms: on fl-thermal without its spindle log ch3's held-out RMS rose 5.79 -> 10.07 um.)

use super::{
    Design, DisplacementOptions, LocatedTerm, RefusedTerm, Scope, Search, Selection, Term, search,
    select,
};
use serde::Serialize;

/// Mixed into the surrogates' seed of the base's selection.
const SEED_TAG: u64 = 0x0074_6865_726d_616c;

/// The thermal base of a channel and what the search on it gave.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ThermalBase {
    /// The base's term (effect `missing_temperature`); when kept, its held-out figures are
    /// those of the final model without it and with it, as every accepted term's.
    pub term: Term,
    /// Held-out RMS, um: the offset alone, the offset with the base, the model the search
    /// made on the base (its located terms in when accepted), and the model the search made
    /// on the offset alone.
    pub offset_heldout_um: f64,
    pub base_heldout_um: f64,
    pub searched_heldout_um: f64,
    pub offset_searched_heldout_um: f64,
    /// Kept: the search on the base is the channel's diagnosis. Otherwise the held-out veto
    /// dropped the base with what was found on it (the model on it is worse on the held-out
    /// end than the one on the offset alone), and its located terms are reported here.
    pub kept: bool,
    pub located_term: Option<LocatedTerm>,
    pub late_term: Option<LocatedTerm>,
    pub statement: String,
}

/// The base's candidate (its index) and term.
struct Found {
    k: usize,
    term: Term,
}

/// The thermal base on the baseline `base_cols` (the offset alone), and the refusals of its
/// search (each reason marked as the base's).
fn find(
    design: &Design,
    base_cols: &[Vec<f64>],
    channel: &str,
    opts: &DisplacementOptions,
) -> (Option<Found>, Vec<RefusedTerm>) {
    let scope = Scope {
        noise: opts.located_noise,
        only: Some("missing_temperature"),
        max_terms: 1,
        seed_tag: SEED_TAG,
    };
    let Selection {
        chosen,
        mut accepted,
        mut refused,
        ..
    } = select(design, base_cols, None, channel, opts, scope);
    for r in &mut refused {
        r.reason = format!("as the thermal base: {}", r.reason);
    }
    let found = chosen
        .first()
        .zip(accepted.pop())
        .map(|(&k, term)| Found { k, term });
    (found, refused)
}

/// The search on a thermal base, when one passes: `run` (the search on the offset alone)
/// becomes the search on the base when the model that makes is no worse on the held-out end
/// (the held-out veto applied to the base with what was found on it); otherwise `run` stays
/// and the base is reported with its located terms. The base's refusals join `run`'s.
pub(super) fn settle(
    design: &Design,
    base_cols: &[Vec<f64>],
    run: &mut Search,
    span: (&[f64], &[(String, Vec<f64>)]),
    channel: &str,
    opts: &DisplacementOptions,
) -> Option<ThermalBase> {
    let (found, refused) = find(design, base_cols, channel, opts);
    let Some(Found { k, mut term }) = found else {
        run.sel.refused.splice(0..0, refused);
        return None;
    };
    let cols: Vec<Vec<f64>> = base_cols
        .iter()
        .cloned()
        .chain([design.cands[k].x.clone()])
        .collect();
    let held = |chosen: &[usize], cols: &[Vec<f64>]| {
        design.fit(&design.matrix(chosen, cols)).1.rms_heldout_um
    };
    let (offset_heldout_um, base_heldout_um) = (held(&[], base_cols), held(&[], &cols));
    let on = search(design, &cols, (Some(k), true), span, channel, opts);
    let offset_searched_heldout_um = run.final_fit.rms_heldout_um;
    let searched_heldout_um = on.final_fit.rms_heldout_um;
    let kept = !opts.heldout_veto || searched_heldout_um <= offset_searched_heldout_um;
    if kept {
        let without: Vec<Vec<f64>> = on
            .final_cols
            .iter()
            .enumerate()
            .filter(|(i, _)| *i != base_cols.len())
            .map(|(_, c)| c.clone())
            .collect();
        term.heldout_before_um = held(&on.sel.chosen, &without);
        term.heldout_after_um = searched_heldout_um;
    }
    let mut base = ThermalBase {
        term,
        offset_heldout_um,
        base_heldout_um,
        searched_heldout_um,
        offset_searched_heldout_um,
        kept,
        located_term: None,
        late_term: None,
        statement: String::new(),
    };
    base.statement = statement(channel, &base);
    if kept {
        base.term.statement = base.statement.clone();
        *run = on;
    } else {
        base.located_term = on.located_term;
        base.late_term = on.late_term;
    }
    run.sel.refused.splice(0..0, refused);
    Some(base)
}

fn statement(channel: &str, b: &ThermalBase) -> String {
    let t = &b.term;
    let verdict = if b.kept {
        format!(
            "the search ran on it: held-out RMS {:.2} um with what it found, against {:.2} um on the offset alone",
            b.searched_heldout_um, b.offset_searched_heldout_um
        )
    } else {
        format!(
            "the search ran on it (its located terms follow, marked so), but the model it made there is worse on the held-out end ({:.2} um) than the one on the offset alone ({:.2} um): vetoed, the final model is the offset's. Without a spindle log the offset's level, the training span's mean, can lie nearer the held-out readings than the warm-up's end does; a recording with the spindle speed logged, or a held-out end after the drifts the base leaves are modelled, would judge the base",
            b.searched_heldout_um, b.offset_searched_heldout_um
        )
    };
    format!(
        "{channel}: thermal base (no spindle log, and the forward selection took no term: a temperature carries the warm-up): {} at {:.3} ± {:.3} {} (delta-BIC {:.1}, each model whitened with its own noise model, t {:.1}, better predictions from {} rolling origins); held-out RMS {:.2} um with the offset alone, {:.2} um with it; {verdict}",
        t.term,
        t.value,
        t.sigma,
        t.unit,
        t.delta_bic,
        t.t,
        t.blocks_improved,
        b.offset_heldout_um,
        b.base_heldout_um
    )
}
