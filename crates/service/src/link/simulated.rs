//! The simulated link: the truth simulator's virtual machine run through a scenario's day
//! program in the caller's time, so the service can run hours of a plant day in seconds on an
//! injectable clock. Its ground truth is recorded beside what it reports, never served.

use std::borrow::Cow;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{
    self as rec, MachineStateKind, SpindleMsg, StateMsg, TemperatureMsg, Timed,
};
use driftwatch_sim::scenario::{ProgramSegment, Scenario};
use driftwatch_sim::simulator::{SimError, TruthSample, VirtualMachine};

use super::{LinkError, LinkEvent, MachineLink, RawJson};

struct ActiveCycle {
    number: i64,
    start_s: f64,
    next_step: usize,
}

/// A virtual machine running a scenario's spindle program day after day; cycles run when the
/// service asks for them.
pub struct Simulated {
    k: Kinematics,
    plan: Plan,
    scn: Scenario,
    vm: VirtualMachine,
    /// Seconds since the scenario start reached by the last poll.
    now_s: f64,
    last_rpm: f64,
    last_state: Option<(MachineStateKind, Option<String>)>,
    next_sample_s: f64,
    next_heartbeat_s: f64,
    active: Option<ActiveCycle>,
    /// The end of the last cycle, for the truth at its reference time.
    cycle_snapshots: Vec<VirtualMachine>,
    pending: Vec<LinkEvent>,
}

impl Simulated {
    pub fn new(k: Kinematics, plan: Plan, scn: Scenario) -> Result<Self, SimError> {
        let vm = VirtualMachine::new(&k, &scn)?;
        Ok(Simulated {
            k,
            plan,
            scn,
            vm,
            now_s: 0.0,
            last_rpm: f64::NAN,
            last_state: None,
            next_sample_s: 0.0,
            next_heartbeat_s: 0.0,
            active: None,
            cycle_snapshots: Vec::new(),
            pending: Vec::new(),
        })
    }

    pub fn start_ns(&self) -> i64 {
        self.vm.start_ns()
    }

    /// Bring the virtual machine to `t_ns` as if it had run its program unobserved (no
    /// measurement cycles), and say nothing of that time: the next poll reports the spindle
    /// and state of `t_ns` as news. A restarted service resumes here rather than replay a day
    /// its store has seen.
    pub fn resume_at(&mut self, t_ns: i64) {
        if t_ns <= self.to_ns(self.now_s) {
            return;
        }
        let _ = self.poll(t_ns);
        self.pending.clear();
        self.last_rpm = f64::NAN;
        self.last_state = None;
    }

    fn to_ns(&self, t_s: f64) -> i64 {
        self.vm.start_ns() + (t_s * 1e9).round() as i64
    }

    fn program_period_s(&self) -> f64 {
        self.scn.duration_min * 60.0
    }

    /// The program segment in force at `t_s` (the program repeats every `duration_min`).
    fn segment_at(&self, t_s: f64) -> Option<&ProgramSegment> {
        let local = t_s.rem_euclid(self.program_period_s());
        self.scn
            .spindle
            .iter()
            .rev()
            .find(|s| s.at_min * 60.0 <= local)
    }

    /// The program's speed, state and name at `t_s`.
    fn program_at(&self, t_s: f64) -> (f64, MachineStateKind, Option<Cow<'_, str>>) {
        match self.segment_at(t_s) {
            Some(s) => (s.rpm, s.state, s.program.as_deref().map(Cow::Borrowed)),
            None => (0.0, MachineStateKind::Off, None),
        }
    }

    /// The next program change after `t_s`.
    fn next_program_change(&self, t_s: f64) -> f64 {
        let period = self.program_period_s();
        let base = (t_s / period).floor() * period;
        let local = t_s - base;
        self.scn
            .spindle
            .iter()
            .map(|s| s.at_min * 60.0)
            .find(|a| *a > local + 1e-9)
            .map(|a| base + a)
            .unwrap_or(
                base + period
                    + self
                        .scn
                        .spindle
                        .first()
                        .map(|s| s.at_min * 60.0)
                        .unwrap_or(0.0),
            )
    }

    /// The spindle speed, state and program at `t_s`, a cycle's while one runs.
    fn rpm_and_state(&self, t_s: f64) -> (f64, MachineStateKind, Option<Cow<'_, str>>) {
        match &self.active {
            Some(c) => (
                self.plan.config.spindle_rpm,
                MachineStateKind::Measuring,
                Some(Cow::Owned(format!("driftwatch cycle {}", c.number))),
            ),
            None => self.program_at(t_s),
        }
    }

    /// The spindle speed alone at `t_s`: it is asked several times a step, and the cycle's
    /// program name is a new string each time.
    fn rpm_at(&self, t_s: f64) -> f64 {
        match &self.active {
            Some(_) => self.plan.config.spindle_rpm,
            None => self.segment_at(t_s).map_or(0.0, |s| s.rpm),
        }
    }

    /// Time of the next thing that happens by itself.
    fn next_internal_s(&self) -> f64 {
        let mut t = self.next_program_change(self.now_s).min(self.next_sample_s);
        let rpm = self.rpm_at(self.now_s);
        if rpm > 0.0 {
            t = t.min(self.next_heartbeat_s);
        }
        if let Some(c) = &self.active {
            let due = match self.plan.steps.get(c.next_step) {
                Some(step) => c.start_s + step.t_start_s,
                None => c.start_s + self.plan.machine_time_s,
            };
            t = t.min(due);
        }
        t
    }

    fn emit_changes(&mut self, t_s: f64) {
        let t_ns = self.to_ns(t_s);
        let (rpm, state, program) = self.rpm_and_state(t_s);
        // The program's name is copied only when it changed (this runs every step).
        let changed = self.last_state.as_ref().map(|(s, p)| (s, p.as_deref()))
            != Some((&state, program.as_deref()));
        let program = changed.then(|| program.map(Cow::into_owned));
        if rpm != self.last_rpm {
            self.pending.push(LinkEvent::Spindle(Timed {
                t_ns,
                msg: SpindleMsg { rpm },
            }));
            self.last_rpm = rpm;
        }
        if let Some(program) = program {
            self.pending.push(LinkEvent::State(Timed {
                t_ns,
                msg: StateMsg {
                    state,
                    program: program.clone(),
                },
            }));
            self.last_state = Some((state, program));
        }
    }

    fn step_to(&mut self, t_s: f64) {
        let rpm = self.rpm_at(self.now_s);
        self.vm.advance_to(self.to_ns(t_s), rpm);
        self.now_s = t_s;
        self.emit_changes(t_s);
        let rpm = self.rpm_at(t_s);
        let t_ns = self.to_ns(t_s);
        if t_s >= self.next_heartbeat_s {
            if rpm > 0.0 {
                self.pending.push(LinkEvent::Spindle(Timed {
                    t_ns,
                    msg: SpindleMsg { rpm },
                }));
            }
            self.next_heartbeat_s = t_s + 10.0;
        }
        if t_s >= self.next_sample_s {
            for (sensor, celsius) in self.vm.temperatures(rpm) {
                self.pending.push(LinkEvent::Temperature(Timed {
                    t_ns,
                    msg: TemperatureMsg { sensor, celsius },
                }));
            }
            // At 1e-4 um (0.1 nm): far more than any measurement sees, and it compresses
            // several times better than every binary64 digit.
            let truth = self.vm.truth(&self.k, rpm, None).rounded(1e-4);
            match serde_json::value::to_raw_value(&truth) {
                Ok(json) => self.pending.push(LinkEvent::Record {
                    topic: rec::TOPIC_TRUTH,
                    t_ns: truth.t_ns,
                    json: RawJson(json),
                }),
                Err(e) => tracing::warn!("the simulated truth at {t_ns} ns is not recorded: {e}"),
            }
            self.next_sample_s = t_s + self.scn.sample_s;
        }
        let Some(c) = &mut self.active else { return };
        let number = c.number;
        match self.plan.steps.get(c.next_step) {
            Some(step) if t_s >= c.start_s + step.t_start_s - 1e-9 => {
                c.next_step += 1;
                let step = step.clone();
                self.cycle_snapshots.push(self.vm.clone());
                let d = self.vm.probe(&self.k, &step, number, rpm);
                self.pending.push(LinkEvent::Detection(d));
            }
            None if t_s >= c.start_s + self.plan.machine_time_s - 1e-9 => {
                self.active = None;
                self.pending.push(LinkEvent::CycleDone {
                    cycle: number,
                    t_ns,
                });
                self.emit_changes(t_s);
            }
            _ => {}
        }
    }

    /// The truth at `t_ns` inside the last cycle (for tests and the experiment view).
    pub fn cycle_truth(&self, t_ns: i64) -> Option<TruthSample> {
        let snap = self
            .cycle_snapshots
            .iter()
            .rev()
            .find(|v| v.now_ns() <= t_ns)
            .or(self.cycle_snapshots.first())?;
        Some(snap.truth_at(&self.k, t_ns, self.plan.config.spindle_rpm, None))
    }
}

impl MachineLink for Simulated {
    fn resume_at(&mut self, t_ns: i64) {
        Simulated::resume_at(self, t_ns)
    }

    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        let now_s = (now_ns - self.vm.start_ns()) as f64 / 1e9;
        if self.last_state.is_none() {
            self.emit_changes(self.now_s);
        }
        loop {
            let next = self.next_internal_s();
            if next > now_s {
                break;
            }
            self.step_to(next.max(self.now_s));
        }
        if now_s > self.now_s {
            let rpm = self.rpm_at(self.now_s);
            self.vm.advance_to(now_ns, rpm);
            self.now_s = now_s;
        }
        // A detection is stamped at its trip, a moment after its approach starts: hand out
        // only what has happened by now, in time order.
        self.pending.sort_by_key(LinkEvent::t_ns);
        let later = self.pending.partition_point(|e| e.t_ns() <= now_ns);
        let rest = self.pending.split_off(later);
        std::mem::replace(&mut self.pending, rest)
    }

    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        if let Some(c) = &self.active {
            return Err(LinkError::Busy(c.number));
        }
        let _ = self.poll(now_ns);
        let (_, state, _) = self.program_at(self.now_s);
        if state != MachineStateKind::Idle {
            return Err(LinkError::NotIdle(state));
        }
        self.cycle_snapshots.clear();
        self.active = Some(ActiveCycle {
            number,
            start_s: self.now_s,
            next_step: 0,
        });
        self.emit_changes(self.now_s);
        Ok(())
    }

    fn abort_cycle(&mut self, number: i64, now_ns: i64) {
        if self.active.as_ref().is_some_and(|c| c.number == number) {
            self.active = None;
            let t_s = (now_ns - self.vm.start_ns()) as f64 / 1e9;
            self.emit_changes(t_s.max(self.now_s));
        }
    }

    fn next_event_ns(&self) -> Option<i64> {
        Some(self.to_ns(self.next_internal_s()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::plan::PlanConfig;
    use driftwatch_core::units;

    fn link() -> Simulated {
        let scn = Scenario::load("patent").unwrap();
        let k = Kinematics::load(&scn.machine).unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        Simulated::new(k, plan, scn).unwrap()
    }

    #[test]
    fn a_requested_cycle_yields_every_step_then_done() {
        let mut l = link();
        let t0 = l.start_ns();
        let ev = l.poll(t0 + units::NS_PER_MIN);
        assert!(
            ev.iter()
                .any(|e| matches!(e, LinkEvent::Spindle(s) if s.msg.rpm == 20000.0))
        );
        l.request_cycle(1, t0 + units::NS_PER_MIN).unwrap();
        assert_eq!(
            l.request_cycle(2, t0 + 61_000_000_000),
            Err(LinkError::Busy(1))
        );
        let ev = l.poll(t0 + 300_000_000_000);
        let dets: Vec<_> = ev
            .iter()
            .filter_map(|e| match e {
                LinkEvent::Detection(d) => Some(d),
                _ => None,
            })
            .collect();
        assert_eq!(dets.len(), 24);
        assert!(dets.windows(2).all(|w| w[1].t_ns > w[0].t_ns));
        assert!(
            ev.iter()
                .any(|e| matches!(e, LinkEvent::CycleDone { cycle: 1, .. }))
        );
        assert!(ev.iter().any(
            |e| matches!(e, LinkEvent::State(s) if s.msg.state == MachineStateKind::Measuring)
        ));
        // Events come in time order.
        assert!(ev.windows(2).all(|w| w[1].t_ns() >= w[0].t_ns()));
    }

    #[test]
    fn a_cutting_machine_refuses_a_cycle() {
        let mut scn = Scenario::load("patent").unwrap();
        scn.spindle[0].state = MachineStateKind::Cutting;
        let k = Kinematics::load(&scn.machine).unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let mut l = Simulated::new(k, plan, scn).unwrap();
        let t = l.start_ns() + 1_000_000_000;
        assert_eq!(
            l.request_cycle(1, t),
            Err(LinkError::NotIdle(MachineStateKind::Cutting))
        );
    }
}
