//! The displacement diagnosis judged on recordings whose truth is known: how often it
//! accepts a term on a null (false positives, [`crate::surrogates`]), how often it finds an
//! effect injected at a known size (power), and whether any accepted term worsens the
//! held-out end of a real recording.
//!
//! Pure: plain data in and out, deterministic given the seeds.

use crate::displacement::{
    DisplacementDiagnosis, DisplacementError, DisplacementOptions, diagnose_displacements,
};
use crate::surrogates::{Null, null_recording, with_temperature_effect};
use driftwatch_core::thermal_model::{Event, ModelInput};

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
