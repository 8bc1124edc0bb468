//! The machine's thermal phase (warming up, steady, cooling, idle, cold, off) from its recent
//! spindle and NC-state history.
//!
//! The daemon receives spindle speeds and NC states as a stream, so the phase is a small state
//! machine fed one event at a time ([`PhaseTracker`]); the phase at any later instant is a pure
//! query of what it has seen ([`PhaseTracker::phase`]).
//!
//! What drives the thermal state is the spindle's heat outside measurement cycles. A cycle's own
//! spins are short and must not restart the warm-up clock, or every cycle run after a stop would
//! make the machine look freshly started and push the after-stop cycles out for ever.
//!
//! Events must come in time order. An event older than the last one taken is refused with
//! [`PhaseError::OutOfOrder`] and changes nothing: replaying it would rewrite a start or stop
//! time the caller may already have acted on. Events with equal times are taken in the order
//! given.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_core::recording::MachineStateKind;
use driftwatch_core::units::min_to_ns;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum PhaseError {
    #[error("phase config: {0}")]
    Config(&'static str),
    #[error("event at {t_ns} ns is older than the last one taken ({last_ns} ns); ignored")]
    OutOfOrder { t_ns: i64, last_ns: i64 },
    #[error("spindle speed at {t_ns} ns is not a finite number; ignored")]
    NotFinite { t_ns: i64 },
}

/// The machine's thermal phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum Phase {
    /// The NC is off.
    Off,
    /// Stopped (or never seen turning) for at least `cold_after_min`.
    Cold,
    /// Spindle turning outside measurement cycles for less than `warmup_min`.
    WarmUp,
    /// Spindle turning for `warmup_min` or longer.
    Steady,
    /// Spindle stopped less than `cooling_min` ago.
    Cooling,
    /// Stopped at least `cooling_min` but less than `cold_after_min` ago.
    Idle,
}

/// Thresholds of the phases.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PhaseConfig {
    /// Speed at or above which the spindle counts as turning, min^-1 (either sense of
    /// rotation). Default 100: below it the heat input is negligible and an NC's speed reading
    /// of a stopped spindle may jitter.
    pub spindle_on_rpm: f64,
    /// Time from a spindle start after which the machine counts as steady, min. Default 210,
    /// the patent's warm-up.
    pub warmup_min: f64,
    /// Time from a spindle stop during which the machine counts as cooling, min. Default 60.
    pub cooling_min: f64,
    /// Time from a spindle stop after which the machine counts as cold, min; at least
    /// `cooling_min`. Default 480.
    pub cold_after_min: f64,
}

impl Default for PhaseConfig {
    fn default() -> Self {
        PhaseConfig {
            spindle_on_rpm: 100.0,
            warmup_min: 210.0,
            cooling_min: 60.0,
            cold_after_min: 480.0,
        }
    }
}

impl PhaseConfig {
    pub fn validate(&self) -> Result<(), PhaseError> {
        if !driftwatch_core::units::positive(self.spindle_on_rpm) {
            return Err(PhaseError::Config("spindle_on_rpm must be > 0"));
        }
        if !driftwatch_core::units::positive(self.warmup_min) {
            return Err(PhaseError::Config("warmup_min must be > 0"));
        }
        if !driftwatch_core::units::positive(self.cooling_min) {
            return Err(PhaseError::Config("cooling_min must be > 0"));
        }
        if !self.cold_after_min.is_finite() || self.cold_after_min < self.cooling_min {
            return Err(PhaseError::Config("cold_after_min must be >= cooling_min"));
        }
        Ok(())
    }
}

/// The phase at one instant, with what it was derived from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct PhaseInfo {
    pub phase: Phase,
    /// When the event that drives this phase happened: the spindle start for `WarmUp` and
    /// `Steady`, the spindle stop for `Cooling`, `Idle` and `Cold`, the NC switching off for
    /// `Off`. `None` only for `Cold` when the spindle has never been seen turning, as nothing
    /// tells how long it has stood.
    pub since_ns: Option<i64>,
    /// When the phase will change by time alone if no further event comes (`WarmUp` to
    /// `Steady`, `Cooling` to `Idle`, `Idle` to `Cold`), so a caller can wake up for it.
    pub changes_at_ns: Option<i64>,
    /// The last spindle speed received, min^-1 (0 before any, and after the NC went off).
    pub spindle_rpm: f64,
    /// The NC state: the last one reported or, when none ever was, inferred as the recording
    /// contract says: `Measuring` inside a cycle the caller declared, `Cutting` whenever the
    /// spindle turns outside one, `Idle` otherwise.
    pub state: MachineStateKind,
    /// Whether `state` was reported by the NC rather than inferred.
    pub state_reported: bool,
    /// The machine is machining: state `Cutting` (reported or inferred).
    pub cutting: bool,
}

/// A past event a tracker is brought back with after a restart: the stored spindle samples
/// and the stored cycles' starts and ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PastEvent {
    Spindle { t_ns: i64, rpm: f64 },
    Cycle { t_ns: i64, active: bool },
}

impl PastEvent {
    fn t_ns(&self) -> i64 {
        match self {
            PastEvent::Spindle { t_ns, .. } | PastEvent::Cycle { t_ns, .. } => *t_ns,
        }
    }
}

/// The thermal phase as a state machine fed event by event.
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseTracker {
    cfg: PhaseConfig,
    last_event_ns: Option<i64>,
    rpm: f64,
    /// The last NC state reported and since when it has held.
    state: Option<(MachineStateKind, i64)>,
    /// A measurement cycle declared by the caller ([`PhaseTracker::on_cycle`]).
    cycle_active: bool,
    /// Start of the spindle run in progress, if the spindle turns outside a cycle.
    run_start_ns: Option<i64>,
    last_stop_ns: Option<i64>,
}

impl PhaseTracker {
    pub fn new(cfg: PhaseConfig) -> Result<Self, PhaseError> {
        cfg.validate()?;
        Ok(PhaseTracker {
            cfg,
            last_event_ns: None,
            rpm: 0.0,
            state: None,
            cycle_active: false,
            run_start_ns: None,
            last_stop_ns: None,
        })
    }

    pub fn config(&self) -> &PhaseConfig {
        &self.cfg
    }

    /// Take the past events up to `now_ns`, in time order (at one instant a cycle's start
    /// before the spindle sample it spins, its end after the sample that stops its spin): a
    /// restarted service knows how long ago the spindle started or stopped instead of calling
    /// the machine cold.
    pub fn replay(&mut self, mut events: Vec<PastEvent>, now_ns: i64) {
        events.retain(|e| e.t_ns() <= now_ns);
        events.sort_by_key(|e| {
            let rank = match e {
                PastEvent::Cycle { active: true, .. } => 0,
                PastEvent::Spindle { .. } => 1,
                PastEvent::Cycle { active: false, .. } => 2,
            };
            (e.t_ns(), rank)
        });
        for e in events {
            // A non-finite or out-of-order stored value is passed over, as a live one is.
            let _ = match e {
                PastEvent::Spindle { t_ns, rpm } => self.on_spindle(t_ns, rpm),
                PastEvent::Cycle { t_ns, active } => self.on_cycle(t_ns, active),
            };
        }
    }

    /// A spindle speed (min^-1; the sign is the sense of rotation and is ignored).
    pub fn on_spindle(&mut self, t_ns: i64, rpm: f64) -> Result<(), PhaseError> {
        if !rpm.is_finite() {
            return Err(PhaseError::NotFinite { t_ns });
        }
        self.accept(t_ns)?;
        self.rpm = rpm;
        self.update(t_ns);
        Ok(())
    }

    /// An NC state from `/machine/state`. Repeating the current state keeps its start time.
    pub fn on_state(&mut self, t_ns: i64, state: MachineStateKind) -> Result<(), PhaseError> {
        self.accept(t_ns)?;
        if state == MachineStateKind::Off {
            // An NC that is off turns nothing, and it will not report the spindle stopping.
            self.rpm = 0.0;
        }
        if self.state.map(|(s, _)| s) != Some(state) {
            self.state = Some((state, t_ns));
        }
        self.update(t_ns);
        Ok(())
    }

    /// A measurement cycle begins (`active`) or ends, as known to the caller (the daemon that
    /// runs it, or the cycle's detections in a recording). Needed for NCs that do not report
    /// `Measuring`: without it, a cycle's spin would count as a spindle start.
    pub fn on_cycle(&mut self, t_ns: i64, active: bool) -> Result<(), PhaseError> {
        self.accept(t_ns)?;
        self.cycle_active = active;
        self.update(t_ns);
        Ok(())
    }

    fn accept(&mut self, t_ns: i64) -> Result<(), PhaseError> {
        if let Some(last_ns) = self.last_event_ns
            && t_ns < last_ns
        {
            return Err(PhaseError::OutOfOrder { t_ns, last_ns });
        }
        self.last_event_ns = Some(t_ns);
        Ok(())
    }

    fn turning(&self) -> bool {
        self.rpm.abs() >= self.cfg.spindle_on_rpm
    }

    fn measuring(&self) -> bool {
        self.cycle_active || self.state.map(|(s, _)| s) == Some(MachineStateKind::Measuring)
    }

    fn update(&mut self, t_ns: i64) {
        let turning = self.turning();
        match self.run_start_ns {
            // A run that enters a measurement cycle with the spindle still turning goes on
            // heating the machine: only the spindle stopping ends it.
            Some(_) if !turning => {
                self.run_start_ns = None;
                self.last_stop_ns = Some(t_ns);
            }
            // A spin begun inside a cycle that goes on after it starts a run when the cycle
            // ends; one that ends inside the cycle never does.
            None if turning && !self.measuring() => self.run_start_ns = Some(t_ns),
            _ => {}
        }
    }

    /// The phase at `now_ns` (normally at or after the last event; an earlier instant is read
    /// against the same history, so elapsed times below zero count as just begun).
    pub fn phase(&self, now_ns: i64) -> PhaseInfo {
        let turning = self.turning();
        let (state, state_reported) = match self.state {
            Some((s, _)) => (s, true),
            None if self.cycle_active => (MachineStateKind::Measuring, false),
            None if turning => (MachineStateKind::Cutting, false),
            None => (MachineStateKind::Idle, false),
        };
        let (phase, since_ns, changes_at_ns) = match (self.state, self.run_start_ns) {
            (Some((MachineStateKind::Off, off_ns)), _) => (Phase::Off, Some(off_ns), None),
            (_, Some(start)) => {
                let steady_at = start.saturating_add(min_to_ns(self.cfg.warmup_min));
                if now_ns < steady_at {
                    (Phase::WarmUp, Some(start), Some(steady_at))
                } else {
                    (Phase::Steady, Some(start), None)
                }
            }
            (_, None) => match self.last_stop_ns {
                Some(stop) => {
                    let idle_at = stop.saturating_add(min_to_ns(self.cfg.cooling_min));
                    let cold_at = stop.saturating_add(min_to_ns(self.cfg.cold_after_min));
                    if now_ns < idle_at {
                        (Phase::Cooling, Some(stop), Some(idle_at))
                    } else if now_ns < cold_at {
                        (Phase::Idle, Some(stop), Some(cold_at))
                    } else {
                        (Phase::Cold, Some(stop), None)
                    }
                }
                None => (Phase::Cold, None, None),
            },
        };
        PhaseInfo {
            phase,
            since_ns,
            changes_at_ns,
            spindle_rpm: self.rpm,
            state,
            state_reported,
            cutting: state == MachineStateKind::Cutting,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use MachineStateKind::{Alarm, Cutting, Idle, Measuring, Off};

    const T0: i64 = 1_772_431_200_000_000_000; // 2026-03-02T06:00:00Z

    fn at(min: f64) -> i64 {
        T0 + min_to_ns(min)
    }

    fn tracker() -> PhaseTracker {
        PhaseTracker::new(PhaseConfig::default()).unwrap()
    }

    #[test]
    fn warm_up_turns_steady_at_warmup_min() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_spindle(at(10.0), 20000.0).unwrap();
        let p = tr.phase(at(10.0 + 209.5));
        assert_eq!(p.phase, Phase::WarmUp);
        assert_eq!(p.since_ns, Some(at(10.0)));
        assert_eq!(p.changes_at_ns, Some(at(220.0)));
        assert_eq!(p.state, Idle);
        assert!(!p.cutting, "spinning in Idle is warm-up, not cutting");
        let p = tr.phase(at(220.0));
        assert_eq!(p.phase, Phase::Steady);
        assert_eq!(p.since_ns, Some(at(10.0)));
        assert_eq!(p.changes_at_ns, None);
    }

    #[test]
    fn a_slow_spindle_is_not_turning() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_spindle(at(1.0), 99.0).unwrap();
        assert_eq!(tr.phase(at(2.0)).phase, Phase::Cold);
        // Reverse rotation heats just the same.
        tr.on_spindle(at(3.0), -100.0).unwrap();
        assert_eq!(tr.phase(at(4.0)).phase, Phase::WarmUp);
        assert_eq!(tr.phase(at(4.0)).since_ns, Some(at(3.0)));
    }

    #[test]
    fn stop_then_cooling_idle_cold() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Cutting).unwrap();
        tr.on_spindle(at(0.0), 12000.0).unwrap();
        tr.on_spindle(at(100.0), 0.0).unwrap();
        tr.on_state(at(100.0), Idle).unwrap();
        let phase_at = |m: f64| tr.phase(at(m));
        assert_eq!(phase_at(100.0).phase, Phase::Cooling);
        assert_eq!(phase_at(159.9).phase, Phase::Cooling);
        assert_eq!(phase_at(159.9).changes_at_ns, Some(at(160.0)));
        assert_eq!(phase_at(160.0).phase, Phase::Idle);
        assert_eq!(phase_at(579.9).phase, Phase::Idle);
        assert_eq!(phase_at(579.9).changes_at_ns, Some(at(580.0)));
        assert_eq!(phase_at(580.0).phase, Phase::Cold);
        for m in [100.0, 160.0, 580.0, 5000.0] {
            assert_eq!(phase_at(m).since_ns, Some(at(100.0)), "at {m} min");
        }
    }

    #[test]
    fn never_turned_is_cold_without_a_since() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        let p = tr.phase(at(1.0));
        assert_eq!(
            (p.phase, p.since_ns, p.changes_at_ns),
            (Phase::Cold, None, None)
        );
    }

    #[test]
    fn measurement_spins_during_cooling_keep_the_stop_time() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_spindle(at(0.0), 20000.0).unwrap();
        tr.on_spindle(at(210.0), 0.0).unwrap();
        for (start, end) in [(225.0, 226.0), (240.0, 241.0)] {
            tr.on_state(at(start), Measuring).unwrap();
            tr.on_spindle(at(start), 20000.0).unwrap();
            let p = tr.phase(at(start + 0.5));
            assert_eq!(p.phase, Phase::Cooling);
            assert_eq!(p.since_ns, Some(at(210.0)));
            assert_eq!(
                (p.state, p.spindle_rpm, p.cutting),
                (Measuring, 20000.0, false)
            );
            tr.on_spindle(at(end), 0.0).unwrap();
            tr.on_state(at(end), Idle).unwrap();
        }
        let p = tr.phase(at(260.0));
        assert_eq!(p.phase, Phase::Cooling);
        assert_eq!(p.since_ns, Some(at(210.0)));
        assert_eq!(tr.phase(at(270.0)).phase, Phase::Idle);
    }

    #[test]
    fn a_run_goes_on_through_a_cycle_at_speed() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_spindle(at(0.0), 20000.0).unwrap();
        tr.on_state(at(30.0), Measuring).unwrap();
        tr.on_state(at(31.0), Idle).unwrap();
        assert_eq!(tr.phase(at(40.0)).since_ns, Some(at(0.0)));
        assert_eq!(tr.phase(at(210.0)).phase, Phase::Steady);
        // The spindle stopping inside a cycle is a stop all the same.
        tr.on_state(at(300.0), Measuring).unwrap();
        tr.on_spindle(at(300.5), 0.0).unwrap();
        tr.on_state(at(301.0), Idle).unwrap();
        let p = tr.phase(at(310.0));
        assert_eq!((p.phase, p.since_ns), (Phase::Cooling, Some(at(300.5))));
    }

    #[test]
    fn a_spin_begun_in_a_cycle_and_kept_after_starts_a_run_when_the_cycle_ends() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_state(at(5.0), Measuring).unwrap();
        tr.on_spindle(at(5.0), 20000.0).unwrap();
        assert_eq!(tr.phase(at(5.5)).phase, Phase::Cold);
        tr.on_state(at(6.0), Cutting).unwrap();
        let p = tr.phase(at(7.0));
        assert_eq!(
            (p.phase, p.since_ns, p.cutting),
            (Phase::WarmUp, Some(at(6.0)), true)
        );
    }

    #[test]
    fn without_reported_state_a_turning_spindle_is_cutting() {
        let mut tr = tracker();
        tr.on_spindle(at(0.0), 0.0).unwrap();
        let p = tr.phase(at(0.0));
        assert_eq!((p.state, p.state_reported, p.cutting), (Idle, false, false));
        tr.on_spindle(at(1.0), 8000.0).unwrap();
        let p = tr.phase(at(2.0));
        assert_eq!(
            (p.state, p.state_reported, p.cutting),
            (Cutting, false, true)
        );
        assert_eq!((p.phase, p.since_ns), (Phase::WarmUp, Some(at(1.0))));
        tr.on_spindle(at(50.0), 0.0).unwrap();
        let p = tr.phase(at(51.0));
        assert_eq!((p.state, p.cutting, p.phase), (Idle, false, Phase::Cooling));
        // A cycle the caller declares is no spindle start and no cutting.
        tr.on_cycle(at(65.0), true).unwrap();
        tr.on_spindle(at(65.0), 20000.0).unwrap();
        let p = tr.phase(at(65.5));
        assert_eq!((p.state, p.cutting), (Measuring, false));
        assert_eq!((p.phase, p.since_ns), (Phase::Cooling, Some(at(50.0))));
        tr.on_spindle(at(66.0), 0.0).unwrap();
        tr.on_cycle(at(66.0), false).unwrap();
        let p = tr.phase(at(70.0));
        assert_eq!(
            (p.phase, p.since_ns, p.state),
            (Phase::Cooling, Some(at(50.0)), Idle)
        );
    }

    #[test]
    fn a_reported_state_is_taken_as_is() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Alarm).unwrap();
        tr.on_spindle(at(0.0), 5000.0).unwrap();
        let p = tr.phase(at(1.0));
        assert_eq!((p.state, p.state_reported, p.cutting), (Alarm, true, false));
        assert_eq!(p.phase, Phase::WarmUp);
    }

    #[test]
    fn off_ends_a_run_and_the_stop_time_survives_it() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Cutting).unwrap();
        tr.on_spindle(at(0.0), 12000.0).unwrap();
        tr.on_state(at(30.0), Off).unwrap();
        let p = tr.phase(at(40.0));
        assert_eq!(
            (p.phase, p.since_ns, p.spindle_rpm),
            (Phase::Off, Some(at(30.0)), 0.0)
        );
        // Repeated reports of the same state keep its start time.
        tr.on_state(at(45.0), Off).unwrap();
        assert_eq!(tr.phase(at(46.0)).since_ns, Some(at(30.0)));
        tr.on_state(at(50.0), Idle).unwrap();
        let p = tr.phase(at(50.0));
        assert_eq!((p.phase, p.since_ns), (Phase::Cooling, Some(at(30.0))));
        assert_eq!(tr.phase(at(90.0)).phase, Phase::Idle);
    }

    #[test]
    fn out_of_order_and_non_finite_events_are_refused_and_change_nothing() {
        let mut tr = tracker();
        tr.on_state(at(0.0), Idle).unwrap();
        tr.on_spindle(at(10.0), 20000.0).unwrap();
        let before = tr.clone();
        assert_eq!(
            tr.on_spindle(at(5.0), 0.0),
            Err(PhaseError::OutOfOrder {
                t_ns: at(5.0),
                last_ns: at(10.0)
            })
        );
        assert!(matches!(
            tr.on_state(at(9.0), Cutting),
            Err(PhaseError::OutOfOrder { .. })
        ));
        assert!(matches!(
            tr.on_cycle(at(9.0), true),
            Err(PhaseError::OutOfOrder { .. })
        ));
        assert_eq!(
            tr.on_spindle(at(11.0), f64::NAN),
            Err(PhaseError::NotFinite { t_ns: at(11.0) })
        );
        assert_eq!(tr, before);
        // Equal times are in order.
        tr.on_spindle(at(10.0), 0.0).unwrap();
        assert_eq!(tr.phase(at(10.0)).phase, Phase::Cooling);
    }

    #[test]
    fn config_defaults_validation_and_unknown_keys() {
        let cfg: PhaseConfig = toml::from_str("").unwrap();
        assert_eq!(cfg, PhaseConfig::default());
        assert_eq!(cfg.warmup_min, 210.0);
        let cfg: PhaseConfig = toml::from_str("cooling_min = 30").unwrap();
        assert_eq!((cfg.cooling_min, cfg.cold_after_min), (30.0, 480.0));
        assert!(toml::from_str::<PhaseConfig>("warmup_mins = 30").is_err());
        for bad in [
            PhaseConfig {
                spindle_on_rpm: 0.0,
                ..Default::default()
            },
            PhaseConfig {
                warmup_min: f64::NAN,
                ..Default::default()
            },
            PhaseConfig {
                cooling_min: -1.0,
                ..Default::default()
            },
            PhaseConfig {
                cold_after_min: 59.0,
                ..Default::default()
            },
        ] {
            assert!(matches!(
                PhaseTracker::new(bad.clone()),
                Err(PhaseError::Config(_))
            ));
        }
        // Idle may be skipped altogether.
        let cfg = PhaseConfig {
            cold_after_min: 60.0,
            ..Default::default()
        };
        let mut tr = PhaseTracker::new(cfg).unwrap();
        tr.on_spindle(at(0.0), 1000.0).unwrap();
        tr.on_spindle(at(1.0), 0.0).unwrap();
        assert_eq!(tr.phase(at(61.0)).phase, Phase::Cold);
    }

    #[test]
    fn phase_serialises_in_snake_case() {
        assert_eq!(
            serde_json::to_string(&Phase::WarmUp).unwrap(),
            "\"warm_up\""
        );
        assert_eq!(
            serde_json::from_str::<Phase>("\"cooling\"").unwrap(),
            Phase::Cooling
        );
    }
}
