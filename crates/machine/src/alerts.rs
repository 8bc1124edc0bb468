//! Alerts for one machine, over the stream of cycle results: a location error too far from its
//! reference, drifting too fast, cycles rejected in a row, or readings that disagree with each
//! other. Each rule has at most one open alert, which is raised, updated when its value moves
//! materially, possibly acknowledged, and resolved.
//!
//! Pure: every time is passed in (ns since the Unix epoch) and the whole memory of the engine is
//! [`AlertState`], plain data the daemon persists and hands back on restart.
//!
//! Rules are TOML, e.g.
//!
//! ```toml
//! [[rules]]
//! kind = "threshold"   # |value - reference| of one error
//! error = "EZ0B"
//! limit = 30.0         # raises above this, um (urad for EA.., EB.., EC..)
//! clear = 25.0         # resolves only below this
//! # reference = 0.0    # default: the first validated value of the error
//!
//! [[rules]]
//! kind = "rate"        # drift between the last two validated values
//! error = "EZ0B"
//! limit_per_min = 3.0
//! clear_per_min = 2.0
//!
//! [[rules]]
//! kind = "rejected_in_a_row"
//! count = 3
//!
//! [[rules]]
//! kind = "chi2"        # chi2/dof of a validated cycle
//! factor = 4.0
//!
//! [[rules]]
//! kind = "clock_skew"  # the NC's events refused for their time stamps
//! clear_after_min = 10.0
//!
//! [[rules]]
//! kind = "verification" # a reference instrument disagrees with the tool setter
//! critical_z = 4.0      # critical beyond this |z|
//! ```

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_core::recording::{CycleResultMsg, ResultStatus};

/// An open alert's value must move by more than this fraction of its rule's limit before an
/// `Updated` event is worth a notification; smaller moves are cycle-to-cycle noise.
const UPDATE_FRACTION: f64 = 0.1;

/// A threshold or rate exceeded by more than this multiple of its limit is critical.
const CRITICAL_FACTOR: f64 = 1.5;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum AlertError {
    #[error("alert rule {rule}: {message}")]
    InvalidRule { rule: String, message: String },
    #[error("alert rule {0} is configured more than once; each rule may appear once")]
    DuplicateRule(String),
    #[error("alert rules are not valid TOML: {0}")]
    Parse(String),
    #[error("no open alert with id {0}")]
    UnknownAlert(u64),
    #[error("an acknowledgement must name who gives it")]
    AnonymousAck,
}

/// One alert rule. Location errors are named as in the machine description (EX0B, EZ0B, ...);
/// values are in um, or urad for the angular errors (names starting EA, EB or EC).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Rule {
    /// `|value - reference|` of one error above `limit` raises; the alert resolves only once it
    /// falls below `clear` (`0 < clear < limit`), so a value hovering near the limit does not
    /// flap. Critical above 1.5 x `limit`.
    Threshold {
        error: String,
        limit: f64,
        clear: f64,
        /// The reference state. Default (absent): the first validated value of the error the
        /// engine sees, i.e. the machine as it was when monitoring began.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reference: Option<f64>,
    },
    /// Drift rate between the last two validated values of one error, per minute, in absolute
    /// value: above `limit_per_min` raises, below `clear_per_min` resolves. Critical above
    /// 1.5 x `limit_per_min`.
    Rate {
        error: String,
        limit_per_min: f64,
        clear_per_min: f64,
    },
    /// `count` (at least 1) consecutive rejected cycles raise; the next validated cycle
    /// resolves. Always a warning.
    RejectedInARow { count: u32 },
    /// A validated cycle whose chi2/dof exceeds `factor` raises: its redundant readings disagree
    /// more than their noise explains (an outlier the solver absorbed, a wrong sigma, a model
    /// gap). The next validated cycle at or under `factor` resolves. Always a warning.
    Chi2 { factor: f64 },
    /// The machine link refused events stamped too far from the service clock (an NC clock
    /// set to local time, or not synchronised): raised at the first refusal, resolved after
    /// `clear_after_min` minutes without one. Its value is the largest skew seen, in s
    /// (positive: ahead of the service clock). Always a warning.
    ClockSkew { clear_after_min: f64 },
    /// A verification against a reference instrument (an R-test result posted to
    /// `/verifications`) in which any error differs from the tool setter's by more than k
    /// combined standard uncertainties (`verification.k`) raises; the next verification with
    /// every error within them resolves. Its value is the largest |z|; critical above
    /// `critical_z` (> 0).
    Verification { critical_z: f64 },
}

impl Rule {
    /// The rule's name in alerts, e.g. `threshold:EZ0B`, `rate:EZ0B`, `rejected_in_a_row`,
    /// `chi2`.
    pub fn name(&self) -> String {
        match self {
            Rule::Threshold { error, .. } => format!("threshold:{error}"),
            Rule::Rate { error, .. } => format!("rate:{error}"),
            Rule::RejectedInARow { .. } => "rejected_in_a_row".into(),
            Rule::Chi2 { .. } => "chi2".into(),
            Rule::ClockSkew { .. } => "clock_skew".into(),
            Rule::Verification { .. } => "verification".into(),
        }
    }

    /// The location error the rule watches, if any.
    pub fn error(&self) -> Option<&str> {
        match self {
            Rule::Threshold { error, .. } | Rule::Rate { error, .. } => Some(error),
            Rule::RejectedInARow { .. }
            | Rule::Chi2 { .. }
            | Rule::ClockSkew { .. }
            | Rule::Verification { .. } => None,
        }
    }

    fn validate(&self) -> Result<(), AlertError> {
        let invalid = |message: String| {
            Err(AlertError::InvalidRule {
                rule: self.name(),
                message,
            })
        };
        if let Some(error) = self.error()
            && (error.is_empty() || error.trim() != error)
        {
            // A stray space would make the rule silently watch nothing.
            return invalid(format!(
                "'{error}' is not an error name (no blanks around it)"
            ));
        }
        match self {
            Rule::Threshold {
                limit,
                clear,
                reference,
                ..
            } => {
                if !(driftwatch_core::units::positive(*clear)
                    && driftwatch_core::units::positive(*limit)
                    && clear < limit)
                {
                    return invalid(format!(
                        "needs 0 < clear < limit, got clear {clear}, limit {limit}"
                    ));
                }
                if reference.is_some_and(|r| !r.is_finite()) {
                    return invalid("reference must be a finite number".into());
                }
            }
            Rule::Rate {
                limit_per_min,
                clear_per_min,
                ..
            } => {
                if !(driftwatch_core::units::positive(*clear_per_min)
                    && driftwatch_core::units::positive(*limit_per_min)
                    && clear_per_min < limit_per_min)
                {
                    return invalid(format!(
                        "needs 0 < clear_per_min < limit_per_min, got clear_per_min \
                         {clear_per_min}, limit_per_min {limit_per_min}"
                    ));
                }
            }
            Rule::RejectedInARow { count } => {
                if *count < 1 {
                    return invalid("count must be at least 1".into());
                }
            }
            Rule::Chi2 { factor } => {
                if !driftwatch_core::units::positive(*factor) {
                    return invalid(format!("factor must be > 0, got {factor}"));
                }
            }
            Rule::ClockSkew { clear_after_min } => {
                if !driftwatch_core::units::positive(*clear_after_min) {
                    return invalid(format!(
                        "clear_after_min must be > 0, got {clear_after_min}"
                    ));
                }
            }
            Rule::Verification { critical_z } => {
                if !(driftwatch_core::units::positive(*critical_z) && critical_z.is_finite()) {
                    return invalid(format!("critical_z must be > 0, got {critical_z}"));
                }
            }
        }
        Ok(())
    }
}

/// The shipped rule set: EZ0B and EX0B 30 um from their reference (clear at 25 um), EZ0B
/// drifting 3 um/min (clear at 2 um/min), 3 cycles rejected in a row, chi2/dof over 4, events
/// refused for their time stamps (clear after 10 min without one), a verification against a
/// reference instrument that exceeds (critical beyond |z| 4).
pub fn default_rules() -> Vec<Rule> {
    vec![
        Rule::Threshold {
            error: "EZ0B".into(),
            limit: 30.0,
            clear: 25.0,
            reference: None,
        },
        Rule::Threshold {
            error: "EX0B".into(),
            limit: 30.0,
            clear: 25.0,
            reference: None,
        },
        Rule::Rate {
            error: "EZ0B".into(),
            limit_per_min: 3.0,
            clear_per_min: 2.0,
        },
        Rule::RejectedInARow { count: 3 },
        Rule::Chi2 { factor: 4.0 },
        Rule::ClockSkew {
            clear_after_min: 10.0,
        },
        Rule::Verification { critical_z: 4.0 },
    ]
}

/// Checks every rule and that no rule appears twice (two rules with one name would share, and
/// fight over, one open alert).
pub fn validate_rules(rules: &[Rule]) -> Result<(), AlertError> {
    let mut seen = BTreeSet::new();
    for rule in rules {
        rule.validate()?;
        if !seen.insert(rule.name()) {
            return Err(AlertError::DuplicateRule(rule.name()));
        }
    }
    Ok(())
}

/// The alert section of a configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AlertConfig {
    /// The rules, evaluated in this order. Default (key absent): [`default_rules`];
    /// `rules = []` switches alerts off.
    #[serde(default = "default_rules")]
    pub rules: Vec<Rule>,
}

impl Default for AlertConfig {
    fn default() -> Self {
        AlertConfig {
            rules: default_rules(),
        }
    }
}

impl AlertConfig {
    /// Parses and validates a TOML text with `[[rules]]` tables.
    pub fn from_toml(text: &str) -> Result<Self, AlertError> {
        let cfg: AlertConfig =
            toml::from_str(text).map_err(|e| AlertError::Parse(e.message().to_string()))?;
        validate_rules(&cfg.rules)?;
        Ok(cfg)
    }
}

/// What the engine is told.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Input {
    Cycle(CycleInput),
    Clock(ClockInput),
    Verification(VerificationInput),
}

/// A verification against a reference instrument, as the rules see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VerificationInput {
    /// The reference time, ns since the Unix epoch.
    pub t_ns: i64,
    /// The latest setter cycle it compared with.
    pub cycle: i64,
    pub exceeds: bool,
    /// The largest |z| of its errors.
    pub worst_abs_z: f64,
    /// Its coverage factor.
    pub k: f64,
    /// What it found, in words.
    pub summary: String,
}

impl From<&crate::verification::Verification> for VerificationInput {
    fn from(v: &crate::verification::Verification) -> Self {
        VerificationInput {
            t_ns: v.t_ns,
            cycle: v.latest_cycle(),
            exceeds: v.exceeds_any,
            worst_abs_z: v.worst_z.abs(),
            k: v.k,
            summary: v.summary(),
        }
    }
}

/// What the machine link refused for its time stamps since the last look (`refused` may be
/// 0: the look itself lets an open alert resolve).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClockInput {
    /// The service clock, ns since the Unix epoch.
    pub t_ns: i64,
    pub refused: u64,
    /// The largest skew among them, s (positive: ahead of the service clock).
    pub worst_skew_s: f64,
}

/// The outcome of one measurement cycle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CycleInput {
    /// The cycle's reference time, ns since the Unix epoch.
    pub t_ns: i64,
    pub cycle: i64,
    /// Validated (`status: ok`).
    pub ok: bool,
    /// Identified errors, um and urad; empty for a rejected cycle.
    #[serde(default)]
    pub errors: BTreeMap<String, f64>,
    #[serde(default)]
    pub chi2: Option<f64>,
    #[serde(default)]
    pub dof: Option<usize>,
    /// Why the cycle was rejected.
    #[serde(default)]
    pub reason: Option<String>,
}

impl From<&CycleResultMsg> for CycleInput {
    fn from(m: &CycleResultMsg) -> Self {
        CycleInput {
            t_ns: m.t_ns,
            cycle: m.cycle,
            ok: m.status == ResultStatus::Ok,
            errors: m.errors.clone().unwrap_or_default(),
            chi2: m.chi2,
            dof: m.dof,
            reason: m.reason.clone(),
        }
    }
}

impl From<&CycleResultMsg> for Input {
    fn from(m: &CycleResultMsg) -> Self {
        Input::Cycle(m.into())
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum Severity {
    Warning,
    Critical,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    Raised,
    /// The open alert's value moved by more than 10 % of its limit since it was last
    /// reported, or its severity changed.
    Updated,
    Resolved,
}

/// A change in an alert, for notification and the alert log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlertEvent {
    /// Stable over the alert's life: its Raised, Updated and Resolved events share it.
    pub id: u64,
    pub rule: String,
    pub kind: EventKind,
    /// When the engine decided, ns since the Unix epoch.
    pub t_ns: i64,
    /// The cycle that caused the event.
    pub cycle: i64,
    pub severity: Severity,
    pub message: String,
    /// What the rule compares with its limit: deviation from the reference (um, urad), drift
    /// rate (per min), rejected cycles in a row, chi2/dof.
    pub value: f64,
    pub acknowledged: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Acknowledgement {
    pub by: String,
    pub t_ns: i64,
}

/// An open alert.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Alert {
    pub id: u64,
    pub rule: String,
    pub severity: Severity,
    pub raised_t_ns: i64,
    pub raised_cycle: i64,
    /// The latest value and its description.
    pub value: f64,
    pub message: String,
    pub last_cycle: i64,
    /// The value in the last Raised or Updated event: updates are measured from it, not from the
    /// previous cycle, so that a slow creep is still reported.
    pub reported_value: f64,
    pub acknowledged: Option<Acknowledgement>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Sample {
    t_ns: i64,
    value: f64,
}

/// Everything the engine remembers; the daemon persists it (serde) and restores it with
/// [`AlertEngine::restore`]. Unknown fields are ignored and missing ones take their empty
/// value, so a state written by another version still loads.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AlertState {
    /// The last alert id given out (0: none yet); ids are never reused.
    last_id: u64,
    /// Time of the last cycle evaluated.
    last_t_ns: Option<i64>,
    /// First validated value of each error.
    references: BTreeMap<String, f64>,
    /// Last validated value of each error.
    last_values: BTreeMap<String, Sample>,
    rejected_in_a_row: u32,
    /// Service time of the last event refused for its time stamp.
    last_clock_refusal_ns: Option<i64>,
    /// Reference time of the last verification evaluated.
    last_verification_t_ns: Option<i64>,
    /// Open alerts by rule name.
    open: BTreeMap<String, Alert>,
}

/// The rule name of the machine loop's health alert ([`AlertEngine::loop_fault`]): built in,
/// never configured.
pub const LOOP_FAULT_RULE: &str = "loop_fault";

/// What the alert log holds of a machine at start-up, for [`AlertEngine::resume`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LoggedAlerts {
    /// Alerts raised and never resolved: id, rule, severity.
    pub open: Vec<(u64, String, Severity)>,
    /// The highest alert id in the log (0: none).
    pub max_id: u64,
}

/// What one rule makes of one cycle.
struct Observation {
    value: f64,
    limit: f64,
    raise: bool,
    resolve: bool,
    severity: Severity,
    message: String,
}

/// The alert engine of one machine.
#[derive(Debug, Clone)]
pub struct AlertEngine {
    rules: Vec<Rule>,
    state: Tracked,
}

/// The engine's state and a count of the times it was handed out to be changed. The machine
/// core keeps a copy to store after every change; it compares the whole state again only when
/// the count moved, instead of after every input (most inputs change nothing of it). Every
/// change goes through [`Tracked::edit`]: reading is all the rest of the engine can do.
#[derive(Debug, Clone, Default)]
struct Tracked {
    state: AlertState,
    edits: u64,
}

impl Tracked {
    fn edit(&mut self) -> &mut AlertState {
        self.edits += 1;
        &mut self.state
    }
}

impl std::ops::Deref for Tracked {
    type Target = AlertState;
    fn deref(&self) -> &AlertState {
        &self.state
    }
}

impl AlertEngine {
    pub fn new(rules: Vec<Rule>) -> Result<Self, AlertError> {
        validate_rules(&rules)?;
        Ok(AlertEngine {
            rules,
            state: Tracked::default(),
        })
    }

    /// Continues from a persisted state, possibly under changed rules. An open alert whose rule
    /// is no longer configured could never resolve, so it is resolved here and its event
    /// returned.
    pub fn restore(
        rules: Vec<Rule>,
        mut state: AlertState,
        now: i64,
    ) -> Result<(Self, Vec<AlertEvent>), AlertError> {
        validate_rules(&rules)?;
        let mut names: BTreeSet<String> = rules.iter().map(Rule::name).collect();
        names.insert(LOOP_FAULT_RULE.to_string());
        let orphans: Vec<String> = state
            .open
            .keys()
            .filter(|n| !names.contains(*n))
            .cloned()
            .collect();
        let mut events = Vec::new();
        for name in orphans {
            if let Some(a) = state.open.remove(&name) {
                let message = format!("rule {name} is no longer configured");
                events.push(event(&a, EventKind::Resolved, now, a.last_cycle, message));
            }
        }
        // A hand-edited or truncated state must not hand out an id still in use.
        let max_open = state.open.values().map(|a| a.id).max().unwrap_or(0);
        state.last_id = state.last_id.max(max_open);
        let state = Tracked { state, edits: 0 };
        Ok((AlertEngine { rules, state }, events))
    }

    /// Continues after a restart from the kept state (none: the store kept none) and the
    /// alert log: ids go on above every id the log holds, and an alert the log shows open
    /// that the kept state does not (its state was not kept before the stop) is resolved with
    /// an event saying so, so that no alert stays open in the log without a resolved event.
    pub fn resume(
        rules: Vec<Rule>,
        state: Option<AlertState>,
        logged: &LoggedAlerts,
        now: i64,
    ) -> Result<(Self, Vec<AlertEvent>), AlertError> {
        let (mut engine, mut events) = Self::restore(rules, state.unwrap_or_default(), now)?;
        let st = engine.state.edit();
        st.last_id = st.last_id.max(logged.max_id);
        for (id, rule, severity) in &logged.open {
            let held = engine.state.open.values().any(|a| a.id == *id);
            if held || events.iter().any(|e| e.id == *id) {
                continue;
            }
            events.push(AlertEvent {
                id: *id,
                rule: rule.clone(),
                kind: EventKind::Resolved,
                t_ns: now,
                cycle: 0,
                severity: *severity,
                message: "resolved at restart: the service stopped before it kept this \
                          alert's state, so its rule starts again from the next cycle"
                    .into(),
                value: f64::NAN,
                acknowledged: false,
            });
        }
        Ok((engine, events))
    }

    pub fn rules(&self) -> &[Rule] {
        &self.rules
    }

    /// The state to persist.
    pub fn state(&self) -> &AlertState {
        &self.state
    }

    /// How many times the state was handed out to be changed: while it stands still, the
    /// state is the same as when it was last read.
    pub fn edits(&self) -> u64 {
        self.state.edits
    }

    /// The errors the rules watch, for checking against the machine's error names: a rule on a
    /// name the machine does not report never fires.
    pub fn watched_errors(&self) -> BTreeSet<&str> {
        self.rules.iter().filter_map(Rule::error).collect()
    }

    /// The reference a threshold on `error` measures from: the configured one, else the first
    /// validated value seen.
    pub fn reference(&self, error: &str) -> Option<f64> {
        self.rules
            .iter()
            .find_map(|r| match r {
                Rule::Threshold {
                    error: e,
                    reference: Some(v),
                    ..
                } if e == error => Some(*v),
                _ => None,
            })
            .or_else(|| self.state.references.get(error).copied())
    }

    /// Open alerts, oldest first.
    pub fn open_alerts(&self) -> Vec<&Alert> {
        let mut v: Vec<&Alert> = self.state.open.values().collect();
        v.sort_by_key(|a| a.id);
        v
    }

    pub fn alert(&self, id: u64) -> Option<&Alert> {
        self.state.open.values().find(|a| a.id == id)
    }

    /// Acknowledges an open alert. It stays open and resolves by its rule as before; a second
    /// acknowledgement keeps the first (who saw it first is what matters) and changes nothing.
    /// Returns whether this one acknowledged it.
    pub fn ack(&mut self, id: u64, by: &str, now: i64) -> Result<bool, AlertError> {
        if by.trim().is_empty() {
            return Err(AlertError::AnonymousAck);
        }
        let alert = self
            .state
            .edit()
            .open
            .values_mut()
            .find(|a| a.id == id)
            .ok_or(AlertError::UnknownAlert(id))?;
        if alert.acknowledged.is_some() {
            return Ok(false);
        }
        alert.acknowledged = Some(Acknowledgement {
            by: by.to_string(),
            t_ns: now,
        });
        Ok(true)
    }

    /// Applies every rule to one input, in rule order. A cycle not later than the last one
    /// evaluated is ignored (no events, no change): a daemon that replays its last cycle after
    /// a restart must not count a rejection twice or see a drift over zero minutes.
    /// The machine loop's own health, a rule every machine has: while its steps fail (its
    /// store or recorder refuses writes) an alert is open, critical, with the failure's
    /// message; it resolves when a step succeeds again. `value` counts the failed steps.
    pub fn loop_fault(
        &mut self,
        failing: bool,
        failed_steps: u64,
        message: &str,
        now: i64,
    ) -> Vec<AlertEvent> {
        let mut events = Vec::new();
        let obs = Observation {
            value: failed_steps as f64,
            limit: f64::INFINITY,
            raise: failing,
            resolve: !failing,
            severity: Severity::Critical,
            message: message.to_string(),
        };
        let cycle = self
            .state
            .open
            .values()
            .map(|a| a.last_cycle)
            .max()
            .unwrap_or(0);
        self.apply(LOOP_FAULT_RULE.to_string(), obs, cycle, now, &mut events);
        events
    }

    pub fn evaluate(&mut self, input: &Input, now: i64) -> Vec<AlertEvent> {
        match input {
            Input::Cycle(c) => self.evaluate_cycle(c, now),
            Input::Clock(c) => self.evaluate_clock(c, now),
            Input::Verification(v) => self.evaluate_verification(v, now),
        }
    }

    /// A verification older (by its reference time) than the last one evaluated changes
    /// nothing: it says nothing about the machine as it is now, so it must not resolve (nor
    /// raise) an alert about a newer one.
    fn evaluate_verification(&mut self, v: &VerificationInput, now: i64) -> Vec<AlertEvent> {
        if self
            .state
            .last_verification_t_ns
            .is_some_and(|t| v.t_ns < t)
        {
            return Vec::new();
        }
        self.state.edit().last_verification_t_ns = Some(v.t_ns);
        let mut events = Vec::new();
        for i in 0..self.rules.len() {
            let Rule::Verification { critical_z } = self.rules[i] else {
                continue;
            };
            let name = self.rules[i].name();
            let severity = if v.worst_abs_z > critical_z {
                Severity::Critical
            } else {
                Severity::Warning
            };
            let obs = Observation {
                value: v.worst_abs_z,
                limit: v.k,
                raise: v.exceeds,
                resolve: !v.exceeds,
                severity,
                message: v.summary.clone(),
            };
            self.apply(name, obs, v.cycle, now, &mut events);
        }
        events
    }

    fn evaluate_clock(&mut self, c: &ClockInput, now: i64) -> Vec<AlertEvent> {
        let mut events = Vec::new();
        if c.refused > 0 {
            self.state.edit().last_clock_refusal_ns = Some(c.t_ns);
        }
        for i in 0..self.rules.len() {
            let Rule::ClockSkew { clear_after_min } = self.rules[i] else {
                continue;
            };
            let name = self.rules[i].name();
            let obs = if c.refused > 0 {
                let worst = match self.state.open.get(&name) {
                    Some(a) if a.value.abs() > c.worst_skew_s.abs() => a.value,
                    _ => c.worst_skew_s,
                };
                Observation {
                    value: worst,
                    // Only a change of severity (never) would update: one alert per episode.
                    limit: f64::INFINITY,
                    raise: true,
                    resolve: false,
                    severity: Severity::Warning,
                    message: format!(
                        "{} event(s) refused for their time stamps, up to {:.0} s {} the service \
                         clock: is the NC's clock set to local time, or not synchronised?",
                        c.refused,
                        worst.abs(),
                        if worst > 0.0 { "ahead of" } else { "behind" }
                    ),
                }
            } else {
                let quiet = self.state.last_clock_refusal_ns.is_none_or(|t| {
                    (c.t_ns - t) as f64
                        >= clear_after_min * driftwatch_core::units::NS_PER_MIN as f64
                });
                // Nothing open, nothing to resolve: no message to write (this runs at every
                // step of every loop).
                if !quiet || !self.state.open.contains_key(&name) {
                    continue;
                }
                Observation {
                    value: 0.0,
                    limit: f64::INFINITY,
                    raise: false,
                    resolve: true,
                    severity: Severity::Warning,
                    message: format!(
                        "no event refused for its time stamp in {clear_after_min} min"
                    ),
                }
            };
            // Not from a cycle: cycle 0.
            self.apply(name, obs, 0, now, &mut events);
        }
        events
    }

    fn evaluate_cycle(&mut self, c: &CycleInput, now: i64) -> Vec<AlertEvent> {
        if self.state.last_t_ns.is_some_and(|t| c.t_ns <= t) {
            return Vec::new();
        }
        self.state.edit().last_t_ns = Some(c.t_ns);
        // A non-finite value is no measurement; rules treat it as absent.
        let values: BTreeMap<&str, f64> = if c.ok {
            c.errors
                .iter()
                .filter(|(_, v)| v.is_finite())
                .map(|(k, v)| (k.as_str(), *v))
                .collect()
        } else {
            BTreeMap::new()
        };
        let st = self.state.edit();
        for (k, v) in &values {
            st.references.entry(k.to_string()).or_insert(*v);
        }
        let rejected_before = st.rejected_in_a_row;
        st.rejected_in_a_row = if c.ok { 0 } else { rejected_before + 1 };

        let mut events = Vec::new();
        for i in 0..self.rules.len() {
            let rule = &self.rules[i];
            let obs = match rule {
                Rule::Threshold {
                    error,
                    limit,
                    clear,
                    ..
                } => values.get(error.as_str()).and_then(|v| {
                    let reference = self.reference(error)?;
                    Some(threshold(error, *v, reference, *limit, *clear))
                }),
                Rule::Rate {
                    error,
                    limit_per_min,
                    clear_per_min,
                } => values.get(error.as_str()).and_then(|v| {
                    let prev = self.state.last_values.get(error)?;
                    let cur = Sample {
                        t_ns: c.t_ns,
                        value: *v,
                    };
                    Some(rate(error, *prev, cur, *limit_per_min, *clear_per_min))
                }),
                Rule::RejectedInARow { count } => Some(rejected(
                    c,
                    self.state.rejected_in_a_row,
                    rejected_before,
                    *count,
                )),
                Rule::Chi2 { factor } => chi2(c, *factor),
                Rule::ClockSkew { .. } | Rule::Verification { .. } => None,
            };
            if let Some(obs) = obs {
                let name = rule.name();
                self.apply(name, obs, c.cycle, now, &mut events);
            }
        }
        for (k, v) in values {
            self.state.edit().last_values.insert(
                k.to_string(),
                Sample {
                    t_ns: c.t_ns,
                    value: v,
                },
            );
        }
        events
    }

    fn apply(
        &mut self,
        rule: String,
        obs: Observation,
        cycle: i64,
        now: i64,
        events: &mut Vec<AlertEvent>,
    ) {
        let st = self.state.edit();
        match st.open.get_mut(&rule) {
            None if obs.raise => {
                st.last_id += 1;
                let a = Alert {
                    id: st.last_id,
                    rule: rule.clone(),
                    severity: obs.severity,
                    raised_t_ns: now,
                    raised_cycle: cycle,
                    value: obs.value,
                    message: obs.message,
                    last_cycle: cycle,
                    reported_value: obs.value,
                    acknowledged: None,
                };
                events.push(event(&a, EventKind::Raised, now, cycle, a.message.clone()));
                st.open.insert(rule, a);
            }
            None => {}
            Some(_) if obs.resolve => {
                if let Some(mut a) = st.open.remove(&rule) {
                    // The event keeps the alert's severity so it reaches whoever got the alert.
                    a.value = obs.value;
                    events.push(event(&a, EventKind::Resolved, now, cycle, obs.message));
                }
            }
            Some(a) => {
                let escalated = a.severity != obs.severity;
                a.value = obs.value;
                a.severity = obs.severity;
                a.message = obs.message;
                a.last_cycle = cycle;
                if escalated || (obs.value - a.reported_value).abs() > UPDATE_FRACTION * obs.limit {
                    a.reported_value = obs.value;
                    events.push(event(a, EventKind::Updated, now, cycle, a.message.clone()));
                }
            }
        }
    }
}

fn event(a: &Alert, kind: EventKind, t_ns: i64, cycle: i64, message: String) -> AlertEvent {
    AlertEvent {
        id: a.id,
        rule: a.rule.clone(),
        kind,
        t_ns,
        cycle,
        severity: a.severity,
        message,
        value: a.value,
        acknowledged: a.acknowledged.is_some(),
    }
}

/// The unit of an error as its ISO 230-7 name says (`EA0C`: urad, `EX0B`: um); um for a
/// name that is not a location error name.
fn unit(error: &str) -> &'static str {
    driftwatch_core::error_name::ErrorName::parse(error).map_or("um", |e| e.unit())
}

fn severity(value: f64, limit: f64) -> Severity {
    if value > CRITICAL_FACTOR * limit {
        Severity::Critical
    } else {
        Severity::Warning
    }
}

fn threshold(error: &str, v: f64, reference: f64, limit: f64, clear: f64) -> Observation {
    let u = unit(error);
    let dev = (v - reference).abs();
    let (raise, resolve) = (dev > limit, dev < clear);
    let head = format!("{error} is {dev:.1} {u} from its reference {reference:.1} {u}");
    let message = if raise {
        format!("{head}, over the {limit} {u} limit")
    } else if resolve {
        format!("{head}, back under the {clear} {u} clear level")
    } else {
        format!("{head}, under the {limit} {u} limit but not yet under the {clear} {u} clear level")
    };
    Observation {
        value: dev,
        limit,
        raise,
        resolve,
        severity: severity(dev, limit),
        message,
    }
}

fn rate(error: &str, prev: Sample, now: Sample, limit: f64, clear: f64) -> Observation {
    let u = unit(error);
    // Accepted cycles are strictly later than every earlier one, so dt > 0.
    let dt_min = (now.t_ns - prev.t_ns) as f64 / driftwatch_core::units::NS_PER_MIN as f64;
    let r = (now.value - prev.value) / dt_min;
    let value = r.abs();
    let (raise, resolve) = (value > limit, value < clear);
    let verb = if r >= 0.0 { "rises" } else { "falls" };
    let head = format!(
        "{error} {verb} at {value:.2} {u}/min ({:.1} to {:.1} {u} over {dt_min:.1} min)",
        prev.value, now.value
    );
    let message = if raise {
        format!("{head}, over the {limit} {u}/min limit")
    } else if resolve {
        format!("{head}, back under the {clear} {u}/min clear level")
    } else {
        format!(
            "{head}, under the {limit} {u}/min limit but not yet under the {clear} {u}/min \
             clear level"
        )
    };
    Observation {
        value,
        limit,
        raise,
        resolve,
        severity: severity(value, limit),
        message,
    }
}

fn rejected(c: &CycleInput, in_a_row: u32, before: u32, count: u32) -> Observation {
    let plural = |n: u32| if n == 1 { "cycle" } else { "cycles" };
    let message = if c.ok {
        format!(
            "cycle {} validated after {before} rejected {} in a row",
            c.cycle,
            plural(before)
        )
    } else {
        let reason = c.reason.as_deref().unwrap_or("no reason given");
        format!(
            "{in_a_row} {} in a row rejected (limit {count}); cycle {}: {reason}",
            plural(in_a_row),
            c.cycle
        )
    };
    Observation {
        value: f64::from(in_a_row),
        limit: f64::from(count),
        raise: in_a_row >= count,
        resolve: c.ok,
        severity: Severity::Warning,
        message,
    }
}

fn chi2(c: &CycleInput, factor: f64) -> Option<Observation> {
    // Only a validated cycle with redundancy says anything about consistency; a rejected one
    // leaves an open alert as it is.
    if !c.ok {
        return None;
    }
    let (chi2, dof) = (c.chi2?, c.dof?);
    if dof == 0 || !chi2.is_finite() {
        return None;
    }
    let r = chi2 / dof as f64;
    let raise = r > factor;
    let message = if raise {
        format!(
            "cycle {}: chi2/dof is {r:.2} ({chi2:.1} over {dof} degrees of freedom), over the \
             factor {factor}: the readings disagree with each other more than their noise explains",
            c.cycle
        )
    } else {
        format!(
            "cycle {}: chi2/dof is {r:.2}, back at or under the factor {factor}",
            c.cycle
        )
    };
    Some(Observation {
        value: r,
        limit: factor,
        raise,
        resolve: !raise,
        severity: Severity::Warning,
        message,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;
    const T0: i64 = 1_700_000_000_000_000_000;

    fn ok(cycle: i64, errors: &[(&str, f64)]) -> Input {
        Input::Cycle(CycleInput {
            t_ns: T0 + cycle * 15 * MIN,
            cycle,
            ok: true,
            errors: errors.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            chi2: Some(8.0),
            dof: Some(8),
            reason: None,
        })
    }

    fn with_chi2(cycle: i64, chi2: f64, dof: usize) -> Input {
        let Input::Cycle(mut c) = ok(cycle, &[]) else {
            unreachable!()
        };
        c.chi2 = Some(chi2);
        c.dof = Some(dof);
        Input::Cycle(c)
    }

    fn rejected_cycle(cycle: i64) -> Input {
        Input::Cycle(CycleInput {
            t_ns: T0 + cycle * 15 * MIN,
            cycle,
            ok: false,
            errors: BTreeMap::new(),
            chi2: None,
            dof: None,
            reason: Some("step c0_x+: no_trip".into()),
        })
    }

    fn engine(rules: Vec<Rule>) -> AlertEngine {
        AlertEngine::new(rules).unwrap()
    }

    fn ez0b_threshold() -> Rule {
        Rule::Threshold {
            error: "EZ0B".into(),
            limit: 30.0,
            clear: 25.0,
            reference: None,
        }
    }

    /// Feeds EZ0B values, one cycle each, and returns the event kinds per cycle.
    fn feed_ez0b(e: &mut AlertEngine, first: i64, values: &[f64]) -> Vec<Vec<EventKind>> {
        values
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let cycle = first + i as i64;
                let ev = e.evaluate(&ok(cycle, &[("EZ0B", *v)]), T0 + cycle * 15 * MIN + 1);
                ev.iter().map(|x| x.kind).collect()
            })
            .collect()
    }

    #[test]
    fn threshold_raises_updates_only_on_material_change_and_resolves_below_clear() {
        let mut e = engine(vec![ez0b_threshold()]);
        // The first value is the reference: 0 um.
        assert!(e.evaluate(&ok(0, &[("EZ0B", 0.0)]), T0).is_empty());
        assert!(e.evaluate(&ok(1, &[("EZ0B", 29.0)]), T0 + 1).is_empty());

        let ev = e.evaluate(&ok(2, &[("EZ0B", 34.2)]), T0 + 2);
        assert_eq!(ev.len(), 1);
        let raised = &ev[0];
        assert_eq!(raised.kind, EventKind::Raised);
        assert_eq!(raised.rule, "threshold:EZ0B");
        assert_eq!(raised.severity, Severity::Warning);
        assert_eq!(raised.cycle, 2);
        assert_eq!(raised.t_ns, T0 + 2);
        assert!((raised.value - 34.2).abs() < 1e-12);
        assert_eq!(
            raised.message,
            "EZ0B is 34.2 um from its reference 0.0 um, over the 30 um limit"
        );
        let id = raised.id;

        // 2.5 um from the last reported 34.2 is within 10 % of 30 um: no event ...
        assert!(e.evaluate(&ok(3, &[("EZ0B", 36.7)]), T0 + 3).is_empty());
        // ... but the creep is measured from the reported value, not the previous cycle.
        let ev = e.evaluate(&ok(4, &[("EZ0B", 37.5)]), T0 + 4);
        assert_eq!(ev.len(), 1);
        assert_eq!((ev[0].kind, ev[0].id), (EventKind::Updated, id));
        assert!((ev[0].value - 37.5).abs() < 1e-12);
        assert_eq!(e.open_alerts()[0].reported_value, 37.5);

        // Under the limit but not under the clear level: still open.
        let ev = e.evaluate(&ok(5, &[("EZ0B", 26.0)]), T0 + 5);
        assert_eq!(ev[0].kind, EventKind::Updated);
        assert!(
            ev[0]
                .message
                .contains("not yet under the 25 um clear level")
        );
        assert_eq!(e.open_alerts().len(), 1);

        let ev = e.evaluate(&ok(6, &[("EZ0B", 24.0)]), T0 + 6);
        assert_eq!(ev.len(), 1);
        assert_eq!((ev[0].kind, ev[0].id), (EventKind::Resolved, id));
        assert_eq!(
            ev[0].message,
            "EZ0B is 24.0 um from its reference 0.0 um, back under the 25 um clear level"
        );
        assert!(e.open_alerts().is_empty());

        // A new excursion is a new alert with a new id.
        let ev = e.evaluate(&ok(7, &[("EZ0B", -31.0)]), T0 + 7);
        assert_eq!(ev[0].kind, EventKind::Raised);
        assert_ne!(ev[0].id, id);
    }

    #[test]
    fn threshold_hysteresis_does_not_flap_between_clear_and_limit() {
        // Never raised: hovering under the limit raises nothing.
        let mut e = engine(vec![ez0b_threshold()]);
        let kinds = feed_ez0b(&mut e, 0, &[0.0, 26.0, 29.9, 26.0, 29.9, 24.0, 29.9]);
        assert!(kinds.iter().all(Vec::is_empty));

        // Raised once: hovering between clear and limit neither resolves nor re-raises, and
        // moves within 3 um (10 % of the limit) of the reported 30.5 um are not even updates.
        let mut e = engine(vec![ez0b_threshold()]);
        let kinds = feed_ez0b(&mut e, 0, &[0.0, 30.5, 28.0, 29.9, 28.0, 30.4, 27.6, 24.9]);
        let all: Vec<EventKind> = kinds.into_iter().flatten().collect();
        assert_eq!(all, vec![EventKind::Raised, EventKind::Resolved]);

        // Wider swings inside the band are updates of the one alert, never a new one.
        let mut e = engine(vec![ez0b_threshold()]);
        let kinds = feed_ez0b(&mut e, 0, &[0.0, 30.5, 25.5, 29.9, 25.5, 29.9, 24.9]);
        let all: Vec<EventKind> = kinds.into_iter().flatten().collect();
        use EventKind::{Raised, Resolved, Updated};
        assert_eq!(
            all,
            vec![Raised, Updated, Updated, Updated, Updated, Resolved]
        );
    }

    #[test]
    fn threshold_is_critical_beyond_one_and_a_half_limits_and_escalation_is_an_update() {
        let mut e = engine(vec![ez0b_threshold()]);
        feed_ez0b(&mut e, 0, &[0.0]);
        let ev = e.evaluate(&ok(1, &[("EZ0B", 44.0)]), T0 + 1);
        assert_eq!(ev[0].severity, Severity::Warning);
        // 1.5 um more is under the 3 um update step, but it crosses 45 um: critical now.
        let ev = e.evaluate(&ok(2, &[("EZ0B", 45.5)]), T0 + 2);
        assert_eq!(ev.len(), 1);
        assert_eq!(ev[0].kind, EventKind::Updated);
        assert_eq!(ev[0].severity, Severity::Critical);
        assert_eq!(e.open_alerts()[0].severity, Severity::Critical);
        // Straight to critical on the first cycle over.
        let mut e = engine(vec![ez0b_threshold()]);
        feed_ez0b(&mut e, 0, &[10.0]);
        let ev = e.evaluate(&ok(1, &[("EZ0B", -40.0)]), T0 + 1);
        assert_eq!(
            (ev[0].kind, ev[0].severity),
            (EventKind::Raised, Severity::Critical)
        );
        assert!((ev[0].value - 50.0).abs() < 1e-12);
    }

    #[test]
    fn threshold_uses_a_configured_reference_and_angular_units() {
        let mut e = engine(vec![Rule::Threshold {
            error: "EA0C".into(),
            limit: 50.0,
            clear: 40.0,
            reference: Some(100.0),
        }]);
        let ev = e.evaluate(&ok(0, &[("EA0C", 160.0)]), T0);
        assert_eq!(ev.len(), 1);
        assert_eq!(
            ev[0].message,
            "EA0C is 60.0 urad from its reference 100.0 urad, over the 50 urad limit"
        );
        assert_eq!(e.reference("EA0C"), Some(100.0));
    }

    #[test]
    fn rejected_and_missing_values_leave_thresholds_alone() {
        let mut e = engine(vec![ez0b_threshold()]);
        feed_ez0b(&mut e, 0, &[0.0, 40.0]);
        // A rejected cycle and a cycle without EZ0B neither resolve nor update.
        assert!(e.evaluate(&rejected_cycle(2), T0 + 2).is_empty());
        assert!(e.evaluate(&ok(3, &[("EX0B", 1.0)]), T0 + 3).is_empty());
        assert!(e.evaluate(&ok(4, &[("EZ0B", f64::NAN)]), T0 + 4).is_empty());
        assert_eq!(e.open_alerts().len(), 1);
        assert_eq!(e.open_alerts()[0].value, 40.0);
        // A NaN is not taken as the reference either.
        let mut e = engine(vec![ez0b_threshold()]);
        feed_ez0b(&mut e, 0, &[f64::NAN, 5.0]);
        assert_eq!(e.reference("EZ0B"), Some(5.0));
    }

    #[test]
    fn rate_alert_over_the_last_two_validated_values() {
        let mut e = engine(vec![Rule::Rate {
            error: "EZ0B".into(),
            limit_per_min: 3.0,
            clear_per_min: 2.0,
        }]);
        // 15 min between cycles: 45 um in one interval is 3 um/min exactly, not over.
        let kinds = feed_ez0b(&mut e, 0, &[0.0, 45.0]);
        assert!(kinds.iter().all(Vec::is_empty));
        let ev = e.evaluate(&ok(2, &[("EZ0B", 105.0)]), T0 + 2);
        assert_eq!(ev.len(), 1);
        assert_eq!(ev[0].kind, EventKind::Raised);
        assert_eq!(ev[0].rule, "rate:EZ0B");
        assert!((ev[0].value - 4.0).abs() < 1e-12);
        assert_eq!(
            ev[0].message,
            "EZ0B rises at 4.00 um/min (45.0 to 105.0 um over 15.0 min), over the 3 um/min limit"
        );
        // A rejected cycle in between: the rate spans the 30 min to the last validated value.
        assert!(e.evaluate(&rejected_cycle(3), T0 + 3).is_empty());
        let ev = e.evaluate(&ok(4, &[("EZ0B", 30.0)]), T0 + 4);
        assert!(ev[0].message.starts_with("EZ0B falls at 2.50 um/min"));
        assert!((ev[0].value - 2.5).abs() < 1e-12);
        assert_eq!(ev[0].kind, EventKind::Updated);
        // Exactly at the clear level it stays open; under it, it resolves.
        let ev = e.evaluate(&ok(5, &[("EZ0B", 0.0)]), T0 + 5);
        assert_eq!((ev[0].kind, ev[0].value), (EventKind::Updated, 2.0));
        assert!(
            ev[0]
                .message
                .contains("not yet under the 2 um/min clear level")
        );
        let ev = e.evaluate(&ok(6, &[("EZ0B", 15.0)]), T0 + 6);
        assert_eq!(ev[0].kind, EventKind::Resolved);
        assert!((ev[0].value - 1.0).abs() < 1e-12);
    }

    #[test]
    fn rejected_in_a_row_raises_at_count_and_an_ok_cycle_resolves() {
        let mut e = engine(vec![Rule::RejectedInARow { count: 3 }]);
        assert!(e.evaluate(&rejected_cycle(0), T0).is_empty());
        assert!(e.evaluate(&rejected_cycle(1), T0 + 1).is_empty());
        // An ok cycle resets the count.
        assert!(e.evaluate(&ok(2, &[]), T0 + 2).is_empty());
        assert!(e.evaluate(&rejected_cycle(3), T0 + 3).is_empty());
        assert!(e.evaluate(&rejected_cycle(4), T0 + 4).is_empty());
        let ev = e.evaluate(&rejected_cycle(5), T0 + 5);
        assert_eq!(ev.len(), 1);
        assert_eq!(ev[0].kind, EventKind::Raised);
        assert_eq!(ev[0].rule, "rejected_in_a_row");
        assert_eq!(ev[0].value, 3.0);
        assert_eq!(
            ev[0].message,
            "3 cycles in a row rejected (limit 3); cycle 5: step c0_x+: no_trip"
        );
        let id = ev[0].id;
        let ev = e.evaluate(&rejected_cycle(6), T0 + 6);
        assert_eq!((ev[0].kind, ev[0].value), (EventKind::Updated, 4.0));
        let ev = e.evaluate(&ok(7, &[]), T0 + 7);
        assert_eq!((ev[0].kind, ev[0].id), (EventKind::Resolved, id));
        assert_eq!(
            ev[0].message,
            "cycle 7 validated after 4 rejected cycles in a row"
        );
    }

    #[test]
    fn chi2_raises_on_a_validated_cycle_over_the_factor_and_resolves_on_the_next_under() {
        let mut e = engine(vec![Rule::Chi2 { factor: 4.0 }]);
        assert!(e.evaluate(&with_chi2(0, 32.0, 8), T0).is_empty());
        let ev = e.evaluate(&with_chi2(1, 50.4, 8), T0 + 1);
        assert_eq!(ev.len(), 1);
        assert_eq!(
            (ev[0].kind, ev[0].rule.as_str()),
            (EventKind::Raised, "chi2")
        );
        assert!((ev[0].value - 6.3).abs() < 1e-12);
        assert!(
            ev[0]
                .message
                .starts_with("cycle 1: chi2/dof is 6.30 (50.4 over 8")
        );
        // A rejected cycle and a cycle without redundancy say nothing: still open.
        assert!(e.evaluate(&rejected_cycle(2), T0 + 2).is_empty());
        assert!(e.evaluate(&with_chi2(3, 0.0, 0), T0 + 3).is_empty());
        assert_eq!(e.open_alerts().len(), 1);
        let ev = e.evaluate(&with_chi2(4, 9.0, 8), T0 + 4);
        assert_eq!(ev[0].kind, EventKind::Resolved);
    }

    #[test]
    fn ack_of_an_unknown_id_is_an_error_and_acknowledged_alerts_still_resolve() {
        let mut e = engine(vec![ez0b_threshold()]);
        assert_eq!(e.ack(1, "ops", T0), Err(AlertError::UnknownAlert(1)));
        feed_ez0b(&mut e, 0, &[0.0, 35.0]);
        let id = e.open_alerts()[0].id;
        assert_eq!(
            e.ack(id + 1, "ops", T0),
            Err(AlertError::UnknownAlert(id + 1))
        );
        assert_eq!(e.ack(id, " ", T0), Err(AlertError::AnonymousAck));
        assert_eq!(e.ack(id, "ops", T0 + 5), Ok(true));
        assert_eq!(e.ack(id, "later", T0 + 6), Ok(false));
        let ack = e.alert(id).unwrap().acknowledged.clone().unwrap();
        assert_eq!((ack.by.as_str(), ack.t_ns), ("ops", T0 + 5));
        let ev = e.evaluate(&ok(2, &[("EZ0B", 10.0)]), T0 + 7);
        assert_eq!(
            (ev[0].kind, ev[0].acknowledged),
            (EventKind::Resolved, true)
        );
        // Once resolved, the id is no longer open.
        assert_eq!(e.ack(id, "ops", T0 + 8), Err(AlertError::UnknownAlert(id)));
    }

    #[test]
    fn a_replayed_or_older_cycle_is_ignored() {
        let mut e = engine(vec![Rule::RejectedInARow { count: 2 }]);
        assert!(e.evaluate(&rejected_cycle(0), T0).is_empty());
        let before = e.state().clone();
        assert!(e.evaluate(&rejected_cycle(0), T0 + 1).is_empty());
        assert_eq!(e.state(), &before);
        assert_eq!(e.evaluate(&rejected_cycle(1), T0 + 2).len(), 1);
    }

    #[test]
    fn state_survives_persistence_and_a_removed_rule_resolves_its_alert() {
        let mut e = engine(default_rules());
        let ev = e.evaluate(&ok(0, &[("EZ0B", 0.0), ("EX0B", 0.0)]), T0);
        assert!(ev.is_empty());
        let ev = e.evaluate(&ok(1, &[("EZ0B", 31.0), ("EX0B", 40.0)]), T0 + 1);
        let rules: Vec<&str> = ev.iter().map(|x| x.rule.as_str()).collect();
        assert_eq!(rules, ["threshold:EZ0B", "threshold:EX0B"]);
        e.ack(ev[0].id, "ops", T0 + 2).unwrap();

        let json = serde_json::to_string(e.state()).unwrap();
        let state: AlertState = serde_json::from_str(&json).unwrap();
        assert_eq!(&state, e.state());
        let (mut r, ev) = AlertEngine::restore(default_rules(), state.clone(), T0 + 3).unwrap();
        assert!(ev.is_empty());
        assert_eq!(r.open_alerts(), e.open_alerts());
        // References and ids carry over: 24 um from the reference 0 resolves, and the next
        // alert gets a fresh id.
        let ev = r.evaluate(&ok(2, &[("EZ0B", 24.0), ("EX0B", 40.0)]), T0 + 4);
        assert_eq!(ev.len(), 1);
        assert_eq!(
            (ev[0].kind, ev[0].acknowledged),
            (EventKind::Resolved, true)
        );
        let ev = r.evaluate(&ok(3, &[("EZ0B", 40.0), ("EX0B", 40.0)]), T0 + 5);
        assert_eq!(ev[0].id, 3);

        // Restored without the EX0B rule: its alert can never resolve, so it resolves now.
        let rules: Vec<Rule> = default_rules()
            .into_iter()
            .filter(|r| r.name() != "threshold:EX0B")
            .collect();
        let (r, ev) = AlertEngine::restore(rules, state, T0 + 9).unwrap();
        assert_eq!(ev.len(), 1);
        assert_eq!(ev[0].kind, EventKind::Resolved);
        assert_eq!(ev[0].rule, "threshold:EX0B");
        assert_eq!(ev[0].t_ns, T0 + 9);
        assert_eq!(ev[0].message, "rule threshold:EX0B is no longer configured");
        assert_eq!(r.open_alerts().len(), 1);
    }

    #[test]
    fn new_refuses_invalid_and_duplicate_rules() {
        let bad = [
            Rule::Threshold {
                error: "EZ0B".into(),
                limit: 25.0,
                clear: 25.0,
                reference: None,
            },
            Rule::Threshold {
                error: "EZ0B".into(),
                limit: 30.0,
                clear: 0.0,
                reference: None,
            },
            Rule::Threshold {
                error: "EZ0B ".into(),
                limit: 30.0,
                clear: 25.0,
                reference: None,
            },
            Rule::Threshold {
                error: "EZ0B".into(),
                limit: 30.0,
                clear: 25.0,
                reference: Some(f64::NAN),
            },
            Rule::Rate {
                error: "EZ0B".into(),
                limit_per_min: f64::NAN,
                clear_per_min: 2.0,
            },
            Rule::Rate {
                error: "EZ0B".into(),
                limit_per_min: 2.0,
                clear_per_min: 3.0,
            },
            Rule::RejectedInARow { count: 0 },
            Rule::Chi2 { factor: -1.0 },
            Rule::Verification { critical_z: 0.0 },
            Rule::Verification {
                critical_z: f64::NAN,
            },
        ];
        for rule in bad {
            let err = AlertEngine::new(vec![rule.clone()]).unwrap_err();
            assert!(
                matches!(&err, AlertError::InvalidRule { rule: r, .. } if *r == rule.name()),
                "{rule:?}: {err}"
            );
        }
        let err = AlertEngine::new(vec![ez0b_threshold(), ez0b_threshold()]).unwrap_err();
        assert_eq!(err, AlertError::DuplicateRule("threshold:EZ0B".into()));
    }

    const DEFAULT_TOML: &str = r#"
        [[rules]]
        kind = "threshold"
        error = "EZ0B"
        limit = 30
        clear = 25

        [[rules]]
        kind = "threshold"
        error = "EX0B"
        limit = 30.0
        clear = 25.0

        [[rules]]
        kind = "rate"
        error = "EZ0B"
        limit_per_min = 3.0
        clear_per_min = 2.0

        [[rules]]
        kind = "rejected_in_a_row"
        count = 3

        [[rules]]
        kind = "chi2"
        factor = 4.0

        [[rules]]
        kind = "clock_skew"
        clear_after_min = 10

        [[rules]]
        kind = "verification"
        critical_z = 4
    "#;

    #[test]
    fn default_rules_parse_from_toml() {
        let cfg = AlertConfig::from_toml(DEFAULT_TOML).unwrap();
        assert_eq!(cfg.rules, default_rules());
        // What we write reads back the same, and an absent key means the defaults.
        let text = toml::to_string(&AlertConfig::default()).unwrap();
        assert_eq!(
            AlertConfig::from_toml(&text).unwrap().rules,
            default_rules()
        );
        assert_eq!(AlertConfig::from_toml("").unwrap().rules, default_rules());
        assert!(
            AlertConfig::from_toml("rules = []")
                .unwrap()
                .rules
                .is_empty()
        );
        let with_ref = "[[rules]]\nkind = \"threshold\"\nerror = \"EY0C\"\nlimit = 10\n\
                        clear = 8\nreference = -3.5\n";
        assert_eq!(
            AlertConfig::from_toml(with_ref).unwrap().rules[0],
            Rule::Threshold {
                error: "EY0C".into(),
                limit: 10.0,
                clear: 8.0,
                reference: Some(-3.5)
            }
        );
    }

    #[test]
    fn toml_typos_and_invalid_values_are_refused() {
        let typo = "[[rules]]\nkind = \"chi2\"\nfactor = 4.0\nfactr = 3.0\n";
        assert!(matches!(
            AlertConfig::from_toml(typo),
            Err(AlertError::Parse(m)) if m.contains("factr")
        ));
        let kind = "[[rules]]\nkind = \"treshold\"\nerror = \"EZ0B\"\nlimit = 3\nclear = 2\n";
        assert!(matches!(
            AlertConfig::from_toml(kind),
            Err(AlertError::Parse(_))
        ));
        assert!(matches!(
            AlertConfig::from_toml("rule = []"),
            Err(AlertError::Parse(_))
        ));
        let inverted =
            "[[rules]]\nkind = \"threshold\"\nerror = \"EZ0B\"\nlimit = 25\nclear = 30\n";
        assert!(matches!(
            AlertConfig::from_toml(inverted),
            Err(AlertError::InvalidRule { .. })
        ));
    }

    #[test]
    fn cycle_result_messages_become_inputs() {
        let msg = CycleResultMsg {
            cycle: 4,
            t_ns: T0,
            status: ResultStatus::Rejected,
            reason: Some("step b90: missing".into()),
            errors: None,
            sigma: None,
            residual_rms_um: None,
            chi2: None,
            dof: None,
            n_detections: Some(23),
            nuisance: None,
            redundancy_um: None,
            chi2_point: None,
            geometry: None,
            notes: None,
        };
        let Input::Cycle(c) = Input::from(&msg) else {
            unreachable!()
        };
        assert!(!c.ok);
        assert!(c.errors.is_empty());
        assert_eq!(c.reason.as_deref(), Some("step b90: missing"));
        let mut e = engine(vec![Rule::RejectedInARow { count: 1 }]);
        let ev = e.evaluate(&Input::from(&msg), T0);
        assert!(ev[0].message.ends_with("cycle 4: step b90: missing"));
        assert_eq!(
            e.watched_errors(),
            BTreeSet::new(),
            "no rule here watches an error"
        );
        assert_eq!(
            engine(default_rules()).watched_errors(),
            BTreeSet::from(["EX0B", "EZ0B"])
        );
    }

    #[test]
    fn clock_skew_raises_once_per_episode_and_resolves_when_quiet() {
        let mut e = engine(vec![Rule::ClockSkew {
            clear_after_min: 10.0,
        }]);
        let look = |t: i64, refused: u64, skew: f64| {
            Input::Clock(ClockInput {
                t_ns: t,
                refused,
                worst_skew_s: skew,
            })
        };
        let ev = e.evaluate(&look(T0, 2, 3600.0), T0);
        assert_eq!(
            (ev.len(), ev[0].kind, ev[0].value),
            (1, EventKind::Raised, 3600.0)
        );
        // More refusals in the episode: no new event; the largest skew is kept.
        assert!(
            e.evaluate(&look(T0 + units::NS_PER_MIN, 1, -90.0), T0)
                .is_empty()
        );
        assert_eq!(e.open_alerts()[0].value, 3600.0);
        // Quiet, but not yet 10 min since the last refusal.
        assert!(e.evaluate(&look(T0 + 600e9 as i64, 0, 0.0), T0).is_empty());
        let ev = e.evaluate(&look(T0 + 11 * units::NS_PER_MIN, 0, 0.0), T0);
        assert_eq!(ev[0].kind, EventKind::Resolved);
        assert!(e.open_alerts().is_empty());
        // Cycle inputs leave it alone, and it leaves the cycle rules alone.
        assert!(e.evaluate(&ok(1, &[("EZ0B", 1.0)]), T0).is_empty());
    }

    #[test]
    fn a_verification_that_exceeds_raises_and_one_within_resolves() {
        let mut e = engine(vec![Rule::Verification { critical_z: 4.0 }]);
        let check = |t_min: i64, exceeds: bool, z: f64| {
            Input::Verification(VerificationInput {
                t_ns: T0 + t_min * MIN,
                cycle: 7,
                exceeds,
                worst_abs_z: z,
                k: 2.0,
                summary: format!("rtest: z {z}"),
            })
        };
        assert!(e.evaluate(&check(0, false, 1.0), T0).is_empty());
        let ev = e.evaluate(&check(10, true, 3.0), T0 + 1);
        assert_eq!(ev.len(), 1);
        assert_eq!(
            (ev[0].kind, ev[0].rule.as_str(), ev[0].severity, ev[0].cycle),
            (EventKind::Raised, "verification", Severity::Warning, 7)
        );
        assert_eq!((ev[0].value, ev[0].message.as_str()), (3.0, "rtest: z 3"));
        // Beyond critical_z: escalated.
        let ev = e.evaluate(&check(20, true, 5.0), T0 + 2);
        assert_eq!(
            (ev[0].kind, ev[0].severity),
            (EventKind::Updated, Severity::Critical)
        );
        // An older verification within k sigma says nothing of the machine now.
        assert!(e.evaluate(&check(5, false, 0.5), T0 + 3).is_empty());
        assert_eq!(e.open_alerts().len(), 1);
        // A newer one does, and the state carries the order over a restart.
        let json = serde_json::to_string(e.state()).unwrap();
        let state: AlertState = serde_json::from_str(&json).unwrap();
        let (mut r, _) =
            AlertEngine::restore(vec![Rule::Verification { critical_z: 4.0 }], state, T0).unwrap();
        assert!(r.evaluate(&check(15, false, 0.5), T0 + 4).is_empty());
        let ev = r.evaluate(&check(30, false, 0.5), T0 + 5);
        assert_eq!(ev[0].kind, EventKind::Resolved);
        assert!(r.open_alerts().is_empty());
        // Cycles and clock looks leave it alone.
        let mut e = engine(vec![Rule::Verification { critical_z: 4.0 }]);
        assert!(e.evaluate(&rejected_cycle(1), T0).is_empty());
        assert!(e.evaluate(&check(0, true, 2.5), T0).len() == 1);
        assert!(e.evaluate(&ok(2, &[("EZ0B", 1.0)]), T0).is_empty());
        assert_eq!(e.open_alerts().len(), 1);
    }

    #[test]
    fn every_change_of_the_state_moves_its_edit_count_and_a_quiet_look_does_not() {
        // Every rule, then 3000 inputs of every kind drawn from a fixed seed (xorshift64): a
        // state that changed must have moved the count, or the machine core would not store it.
        let mut rules = default_rules();
        for r in [
            Rule::Chi2 { factor: 4.0 },
            Rule::ClockSkew {
                clear_after_min: 10.0,
            },
            Rule::Verification { critical_z: 4.0 },
        ] {
            if rules.iter().all(|have| have.name() != r.name()) {
                rules.push(r);
            }
        }
        let mut e = engine(rules);
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut draw = |n: u64| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x % n
        };
        let (mut cycle, mut t, mut quiet, mut changed) = (0_i64, T0, 0, 0);
        for _ in 0..3000 {
            t += MIN;
            let before = (e.state().clone(), e.edits());
            match draw(8) {
                0 | 1 => {
                    cycle += 1;
                    let v = draw(80) as f64 - 20.0;
                    e.evaluate(&ok(cycle, &[("EZ0B", v), ("EX0B", v / 2.0)]), t);
                }
                2 => {
                    cycle += 1;
                    e.evaluate(&rejected_cycle(cycle), t);
                }
                // A replayed cycle changes nothing.
                3 => drop(e.evaluate(&rejected_cycle(cycle), t)),
                4 => {
                    let refused = if draw(4) == 0 { 1 + draw(3) } else { 0 };
                    e.evaluate(
                        &Input::Clock(ClockInput {
                            t_ns: t,
                            refused,
                            worst_skew_s: 120.0,
                        }),
                        t,
                    );
                }
                5 => {
                    let z = draw(60) as f64 / 10.0;
                    e.evaluate(
                        &Input::Verification(VerificationInput {
                            t_ns: t,
                            cycle,
                            exceeds: z > 2.0,
                            worst_abs_z: z,
                            k: 2.0,
                            summary: format!("z {z}"),
                        }),
                        t,
                    );
                }
                6 => {
                    let ids: Vec<u64> = e.open_alerts().iter().map(|a| a.id).collect();
                    let id = ids.get(draw(3) as usize).copied().unwrap_or(999);
                    let _ = e.ack(id, "ops", t);
                }
                _ => drop(e.loop_fault(draw(2) == 0, 1, "store refused", t)),
            }
            if e.state() != &before.0 {
                changed += 1;
                assert_ne!(e.edits(), before.1, "a change the count did not see");
            } else if e.edits() == before.1 {
                quiet += 1;
            }
        }
        // Both kinds occur: changes, and inputs the count says changed nothing.
        assert!(
            changed > 300 && quiet > 100,
            "{changed} changes, {quiet} quiet"
        );
    }
}
