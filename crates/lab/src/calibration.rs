//! The displacement diagnosis judged on recordings whose truth is known: how often it
//! accepts a term on a null (false positives, [`crate::null_recordings`]), how often it finds an
//! effect injected at a known size (power), and whether any accepted term worsens the
//! held-out end of a real recording. The located term's power is measured on any recording
//! as it is ([`located_power`]): a drift that follows one temperature after an onset,
//! injected at several sizes into its real readings, against the same recording without it.
//!
//! Pure: plain data in and out, deterministic given the seeds.

use crate::null_recordings::{Null, null_recording, with_temperature_effect};
use driftwatch_diagnosis::displacement::{
    DisplacementDiagnosis, DisplacementError, DisplacementOptions, NotConfirmed,
    diagnose_displacements,
};
use driftwatch_thermal::model::{Event, ModelInput};

/// Grid of the temperature surrogates, ns (the diagnosis thins to 5 min).
pub const SURROGATE_STEP_NS: i64 = 300_000_000_000;
/// The slow noise of a readings null, um (the size of fl-thermal's residuals after one
/// spindle mode: 1-4 um).
pub const NULL_NOISE_UM: f64 = 2.0;

/// What the diagnosis accepted on one null recording that it should not have.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NullOutcome {
    pub null: &'static str,
    pub channel: String,
    pub seed: u64,
    /// The false terms: every accepted term on a readings null, every accepted temperature
    /// term on a temperature null (the spindle and the readings are real there, so a
    /// spindle term may be true).
    pub false_terms: Vec<String>,
}

/// The null of kind `null` made from `events` for `channel`, diagnosed with `opts`.
pub fn null_trial(
    events: &[Event],
    null: Null,
    channel: &str,
    seed: u64,
    opts: &DisplacementOptions,
) -> Result<NullOutcome, DisplacementError> {
    let ev = null_recording(
        events,
        null,
        channel,
        SURROGATE_STEP_NS,
        NULL_NOISE_UM,
        seed,
    );
    let d = diagnose_displacements(&ev, &[channel.to_string()], opts)?;
    let false_terms = d
        .channels
        .iter()
        .flat_map(|c| &c.accepted)
        .filter(|t| null.replaces_readings() || matches!(t.input, ModelInput::Temperature { .. }))
        .map(|t| t.term.clone())
        .collect();
    Ok(NullOutcome {
        null: null.as_str(),
        channel: channel.to_string(),
        seed,
        false_terms,
    })
}

/// Whether the diagnosis finds an effect of `sensor` of RMS `rms_um` injected into an AR-noise
/// null of `channel` (a term on that sensor accepted, at any lag).
pub fn power_trial(
    events: &[Event],
    channel: &str,
    sensor: &str,
    rms_um: f64,
    seed: u64,
    opts: &DisplacementOptions,
) -> Result<bool, DisplacementError> {
    let ev = null_recording(
        events,
        Null::ArNoise,
        channel,
        SURROGATE_STEP_NS,
        NULL_NOISE_UM,
        seed,
    );
    let ev = with_temperature_effect(&ev, channel, sensor, rms_um, None);
    let d = diagnose_displacements(&ev, &[channel.to_string()], opts)?;
    Ok(names_sensor(&d, sensor))
}

/// Whether an accepted term of the diagnosis is an input of `sensor`.
pub fn names_sensor(d: &DisplacementDiagnosis, sensor: &str) -> bool {
    d.channels
        .iter()
        .flat_map(|c| &c.accepted)
        .any(|t| matches!(&t.input, ModelInput::Temperature { sensor: s, .. } if s == sensor))
}

/// The accepted terms that worsen the held-out end: the final model's held-out RMS is
/// higher with the term than without it. `(channel, term, without, with)`.
pub fn worsening_terms(d: &DisplacementDiagnosis) -> Vec<(String, String, f64, f64)> {
    d.channels
        .iter()
        .flat_map(|c| {
            c.accepted
                .iter()
                .filter(|t| t.heldout_after_um > t.heldout_before_um + 1e-9)
                .map(|t| {
                    (
                        c.channel.clone(),
                        t.term.clone(),
                        t.heldout_before_um,
                        t.heldout_after_um,
                    )
                })
        })
        .collect()
}

/// What the diagnosis made of a drift injected into a real recording: `rms_um` of `sensor`'s
/// change since `onset_h` added to `channel` (none at size 0: the recording as it is).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LocatedOutcome {
    pub channel: String,
    pub sensor: String,
    pub onset_h: f64,
    pub rms_um: f64,
    /// The located term's sensor, onset and verdict (none: nothing was located).
    pub located_sensor: Option<String>,
    pub located_onset_h: Option<f64>,
    pub located_accepted: bool,
    pub reason: Option<NotConfirmed>,
    /// The rule the located term failed, if any.
    pub rule: Option<String>,
    /// The located term names `sensor`, whatever its verdict.
    pub found: bool,
    /// Found and modelled: a term on `sensor` is accepted (the located one, or one of the
    /// forward selection) that the recording without the injection does not have.
    pub modelled: bool,
    /// A located term accepted on another sensor than the injected one (at size 0: any
    /// accepted located term, a term the recording itself gives).
    pub false_term: Option<String>,
    /// The channel's held-out RMS with the final model, um.
    pub heldout_um: f64,
    /// The located term's held-out RMS without it and with it, um.
    pub located_heldout_um: Option<(f64, f64)>,
}

/// The accepted terms of `d`'s first channel on `sensor`: the located term's, or a
/// temperature input's.
fn accepts_sensor(d: &DisplacementDiagnosis, sensor: &str) -> bool {
    d.channels.first().is_some_and(|c| {
        c.located_term
            .iter()
            .chain(&c.late_term)
            .any(|l| l.accepted && l.sensor == sensor)
            || c.accepted.iter().any(
                |t| matches!(&t.input, ModelInput::Temperature { sensor: s, .. } if s == sensor),
            )
    })
}

/// The located term's power on a real recording: for each of `sizes` (um RMS; 0 gives the
/// recording as it is), a drift of `sensor`'s change since `onset_ns` (0 before it) added
/// to `channel`'s readings ([`with_temperature_effect`]), diagnosed on that channel alone
/// with `opts`. An outcome is modelled when a term on `sensor` is accepted that the
/// recording without the injection does not have; a false term is a located term accepted
/// on another sensor (at size 0, any).
pub fn located_power(
    events: &[Event],
    channel: &str,
    sensor: &str,
    onset_ns: i64,
    sizes: &[f64],
    opts: &DisplacementOptions,
) -> Result<Vec<LocatedOutcome>, DisplacementError> {
    let channels = [channel.to_string()];
    let t0 = events
        .iter()
        .find(|e| matches!(e, Event::Observation { channel: c, .. } if c == channel))
        .map_or(0, Event::t_ns);
    let clean = diagnose_displacements(events, &channels, opts)?;
    let had = accepts_sensor(&clean, sensor);
    let mut out = Vec::with_capacity(sizes.len());
    for &rms_um in sizes {
        let d = if rms_um > 0.0 {
            let ev = with_temperature_effect(events, channel, sensor, rms_um, Some(onset_ns));
            diagnose_displacements(&ev, &channels, opts)?
        } else {
            clean.clone()
        };
        let Some(c) = d.channels.first() else {
            continue;
        };
        let l = c.located_term.as_ref();
        // The later departure's term counts as the located one does: accepted on the null
        // or on another sensor, it is a false term.
        let false_term = l
            .into_iter()
            .chain(c.late_term.as_ref())
            .find(|l| l.accepted && (rms_um == 0.0 || l.sensor != sensor))
            .map(|l| l.term.clone());
        out.push(LocatedOutcome {
            channel: channel.to_string(),
            sensor: sensor.to_string(),
            onset_h: driftwatch_core::units::ns_to_h(onset_ns - t0),
            rms_um,
            located_sensor: l.map(|l| l.sensor.clone()),
            located_onset_h: l.and_then(|l| l.onset_h),
            located_accepted: l.is_some_and(|l| l.accepted),
            reason: l.and_then(|l| l.reason),
            rule: l.and_then(|l| l.rule.clone()),
            found: l.is_some_and(|l| l.sensor == sensor),
            modelled: rms_um > 0.0 && !had && accepts_sensor(&d, sensor),
            false_term,
            heldout_um: c.final_fit.rms_heldout_um,
            located_heldout_um: l.map(|l| (l.heldout_before_um, l.heldout_after_um)),
        });
    }
    Ok(out)
}
