//! The NCs of `bench fleet --link nc-push`: a day of one machine's NC traffic recorded once
//! from the simulator (spindle and state changes, the spindle's speed once a minute while it
//! turns, a temperature report a minute, and at every ten minutes of the day the detections a
//! cycle started then would give), replayed by a load generator over HTTP to every machine's
//! `nc_push` door as a gateway posts it, each machine at its own place in the day. Orders are
//! polled for and answered with the recorded detections nearest in time of day, posted as
//! they come. The service under test runs no simulator: only this generator, on a thread and
//! runtime of its own so that its CPU is not counted as the service's, knows the recording.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use serde_json::json;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{DetectionMsg, MachineStateKind};
use driftwatch_core::units::NS_PER_MIN;
use driftwatch_service::nc_push::{CycleOrder, PostedEvent};
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::VirtualMachine;

use super::cpu_time::thread_cpu_s;

const DAY_NS: i64 = 1440 * NS_PER_MIN;
/// A recorded cycle every this often in the day.
const SLOT_NS: i64 = 10 * NS_PER_MIN;
/// Requests of the generator in flight at once.
const IN_FLIGHT: usize = 32;

/// One day of one machine's NC traffic and the cycles it would have answered.
pub struct Recorded {
    /// The day's events, times from the day's start (ns), in time order.
    events: Vec<PostedEvent>,
    /// The program in force from each time of the day on: (from, rpm, state, program).
    program: Vec<(i64, f64, MachineStateKind, Option<String>)>,
    /// At `i * SLOT_NS` into the day: each detection's time from the cycle's start and the
    /// detection (its cycle number is the order's when replayed).
    cycles: Vec<Vec<(i64, DetectionMsg)>>,
    plan_rpm: f64,
    machine_time_ns: i64,
}

fn event(topic: &str, t_ns: i64, msg: serde_json::Value) -> PostedEvent {
    PostedEvent {
        topic: topic.to_string(),
        t_ns,
        msg,
    }
}

fn state_msg(state: MachineStateKind, program: &Option<String>) -> serde_json::Value {
    json!({"state": state, "program": program})
}

impl Recorded {
    /// Record the scenario's first day on its virtual machine (its program must repeat
    /// daily).
    pub fn record(scn: &Scenario, k: &Kinematics, plan: &Plan) -> Result<Recorded> {
        anyhow::ensure!(
            (scn.duration_min - 1440.0).abs() < 1e-9,
            "scenario {}: the NC traffic is recorded from a program that repeats every day",
            scn.name
        );
        let program: Vec<_> = scn
            .spindle
            .iter()
            .map(|s| {
                (
                    (s.at_min * 60.0 * 1e9).round() as i64,
                    s.rpm,
                    s.state,
                    s.program.clone(),
                )
            })
            .collect();
        let mut rec = Recorded {
            events: Vec::new(),
            program,
            cycles: Vec::new(),
            plan_rpm: plan.config.spindle_rpm,
            machine_time_ns: (plan.machine_time_s * 1e9).round() as i64,
        };
        let mut vm = VirtualMachine::new(k, scn)?;
        let t0 = vm.start_ns();
        // Every minute and every change of program, in time order.
        let mut times: Vec<i64> = (0..1440).map(|m| m * NS_PER_MIN).collect();
        times.extend(
            rec.program
                .iter()
                .map(|p| p.0)
                .filter(|t| (0..DAY_NS).contains(t)),
        );
        times.sort_unstable();
        times.dedup();
        let mut last: Option<(f64, MachineStateKind, Option<String>)> = None;
        for t in times {
            let before = last.as_ref().map_or(0.0, |l| l.0);
            vm.advance_to(t0 + t, before);
            let (rpm, state, prog) = rec.program_at(t);
            let changed_rpm = last.as_ref().is_none_or(|l| l.0 != rpm);
            let changed_state = last.as_ref().is_none_or(|l| (l.1, &l.2) != (state, &prog));
            let minute = t % NS_PER_MIN == 0;
            if changed_rpm || (minute && rpm > 0.0) {
                rec.events.push(event("/spindle", t, json!({"rpm": rpm})));
            }
            if changed_state {
                rec.events
                    .push(event("/machine/state", t, state_msg(state, &prog)));
            }
            if minute {
                for (sensor, celsius) in vm.temperatures(rpm) {
                    rec.events.push(event(
                        "/temperature",
                        t,
                        json!({"sensor": sensor, "celsius": celsius}),
                    ));
                }
            }
            if t % SLOT_NS == 0 {
                let mut probe = vm.clone();
                let mut dets = Vec::with_capacity(plan.steps.len());
                for step in &plan.steps {
                    probe.advance_to(t0 + t + (step.t_start_s * 1e9).round() as i64, rec.plan_rpm);
                    let d = probe.probe(k, step, 0, rec.plan_rpm);
                    dets.push((d.t_ns - t0 - t, d.msg));
                }
                rec.cycles.push(dets);
            }
            last = Some((rpm, state, prog));
        }
        Ok(rec)
    }

    /// The program in force at `t` ns into the day.
    fn program_at(&self, t: i64) -> (f64, MachineStateKind, Option<String>) {
        let t = t.rem_euclid(DAY_NS);
        match self.program.iter().rposition(|p| p.0 <= t) {
            Some(i) => {
                let p = &self.program[i];
                (p.1, p.2, p.3.clone())
            }
            None => (0.0, MachineStateKind::Off, None),
        }
    }

    /// Events a machine-day of this traffic posts without cycles.
    pub fn events_per_day(&self) -> usize {
        self.events.len()
    }
}

/// One NC replaying the recorded day from `shift` ns into it.
struct Nc {
    id: String,
    /// The service time of the recorded day's start of the current lap.
    day0: i64,
    /// The next recorded event.
    next: usize,
    /// The cycle being answered: its end, and its events not yet posted.
    cycle_end: Option<i64>,
    pending: VecDeque<PostedEvent>,
}

impl Nc {
    fn new(id: String, t0: i64, shift: i64, rec: &Recorded) -> (Nc, Vec<PostedEvent>) {
        let day0 = t0 - shift;
        let next = rec.events.partition_point(|e| e.t_ns < shift);
        let (rpm, state, prog) = rec.program_at(shift);
        let start = vec![
            event("/spindle", t0, json!({"rpm": rpm})),
            event("/machine/state", t0, state_msg(state, &prog)),
        ];
        let nc = Nc {
            id,
            day0,
            next,
            cycle_end: None,
            pending: VecDeque::new(),
        };
        (nc, start)
    }

    /// Everything that happened up to `upto`: the cycle's events, then the recording's (while
    /// a cycle runs, only its temperatures: the cycle owns the spindle and the state).
    fn due(&mut self, rec: &Recorded, upto: i64) -> Vec<PostedEvent> {
        let mut out = Vec::new();
        while self.pending.front().is_some_and(|e| e.t_ns <= upto) {
            out.extend(self.pending.pop_front());
        }
        if self.pending.is_empty() {
            // A cycle's answer grows this; kept, it would be counted as the service's memory
            // (the generator runs in the service's process).
            self.pending = VecDeque::new();
        }
        if self.cycle_end.is_some_and(|end| end <= upto) && self.pending.is_empty() {
            self.cycle_end = None;
        }
        loop {
            if self.next == rec.events.len() {
                self.next = 0;
                self.day0 += DAY_NS;
            }
            let e = &rec.events[self.next];
            let t = self.day0 + e.t_ns;
            if t > upto {
                break;
            }
            self.next += 1;
            if self.cycle_end.is_some_and(|end| t < end) && e.topic != "/temperature" {
                continue;
            }
            out.push(PostedEvent {
                topic: e.topic.clone(),
                t_ns: t,
                msg: e.msg.clone(),
            });
        }
        out.sort_by_key(|e| e.t_ns);
        out
    }

    /// Run `order` from `now`: the recorded cycle nearest in time of day, posted as it comes,
    /// and the program's spindle and state again at its end.
    fn answer(&mut self, rec: &Recorded, order: &CycleOrder, now: i64) {
        let of_day = (now - self.day0).rem_euclid(DAY_NS);
        let slot = ((of_day + SLOT_NS / 2) / SLOT_NS) as usize % rec.cycles.len().max(1);
        let end = now + rec.machine_time_ns;
        let measuring = Some(format!("driftwatch cycle {}", order.cycle));
        self.pending.push_back(event(
            "/machine/state",
            now,
            state_msg(MachineStateKind::Measuring, &measuring),
        ));
        self.pending
            .push_back(event("/spindle", now, json!({"rpm": rec.plan_rpm})));
        for (dt, d) in rec.cycles.get(slot).into_iter().flatten() {
            let mut d = d.clone();
            d.cycle = order.cycle;
            let msg = serde_json::to_value(&d).unwrap_or_default();
            self.pending
                .push_back(event("/probe/detection", now + dt, msg));
        }
        let (rpm, state, prog) = rec.program_at(end - self.day0);
        self.pending
            .push_back(event("/machine/state", end, state_msg(state, &prog)));
        self.pending
            .push_back(event("/spindle", end, json!({"rpm": rpm})));
        self.cycle_end = Some(end);
    }
}

/// What the generator did in one tick or phase.
#[derive(Debug, Default, Clone, Copy)]
pub struct Sent {
    pub posts: u64,
    pub events: u64,
    pub order_polls: u64,
    pub orders: u64,
    /// Answers other than 202/200/204 (or no answer).
    pub errors: u64,
}

impl Sent {
    pub fn add(&mut self, o: Sent) {
        self.posts += o.posts;
        self.events += o.events;
        self.order_polls += o.order_polls;
        self.orders += o.orders;
        self.errors += o.errors;
    }
}

/// One machine's traffic up to `upto`: its due events posted, and its order asked for
/// (`ask`) when no cycle runs and answered from `upto`.
async fn tick_one(
    client: &reqwest::Client,
    base: &str,
    rec: &Recorded,
    nc: &mut Nc,
    upto: i64,
    ask: bool,
) -> Sent {
    let mut s = Sent::default();
    let events_url = format!("{base}/api/v1/machines/{}/nc/events", nc.id);
    let post = async |s: &mut Sent, events: Vec<PostedEvent>| {
        if events.is_empty() {
            return;
        }
        s.posts += 1;
        s.events += events.len() as u64;
        let url = &events_url;
        let body = json!({"events": events}).to_string();
        let req = client
            .post(url)
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .body(body);
        match req.send().await {
            Ok(r) if r.status().as_u16() == 202 => {
                let _ = r.bytes().await;
            }
            _ => s.errors += 1,
        }
    };
    let due = nc.due(rec, upto);
    post(&mut s, due).await;
    if ask && nc.cycle_end.is_none() {
        s.order_polls += 1;
        let url = format!("{base}/api/v1/machines/{}/nc/request", nc.id);
        match client.get(&url).send().await {
            Ok(r) if r.status().as_u16() == 200 => match r
                .bytes()
                .await
                .ok()
                .and_then(|b| serde_json::from_slice::<CycleOrder>(&b).ok())
            {
                Some(order) => {
                    s.orders += 1;
                    nc.answer(rec, &order, upto);
                    let due = nc.due(rec, upto);
                    post(&mut s, due).await;
                }
                None => s.errors += 1,
            },
            Ok(r) if r.status().as_u16() == 204 => {}
            _ => s.errors += 1,
        }
    }
    s
}

/// The NCs, split into `IN_FLIGHT` groups that run side by side.
struct Ncs {
    groups: Vec<Vec<Nc>>,
}

impl Ncs {
    /// Each group in turn takes every machine's traffic up to `upto`; `ask(i)` says whether
    /// machine `i` (its place in the fleet) asks for its order now.
    async fn tick(
        &mut self,
        client: &reqwest::Client,
        base: &Arc<str>,
        rec: &Arc<Recorded>,
        upto: i64,
        ask: impl Fn(usize) -> bool,
    ) -> Sent {
        let mut tasks = tokio::task::JoinSet::new();
        for (g, group) in std::mem::take(&mut self.groups).into_iter().enumerate() {
            let asks: Vec<bool> = (0..group.len()).map(|j| ask(g + j * IN_FLIGHT)).collect();
            let (client, base, rec) = (client.clone(), base.clone(), rec.clone());
            tasks.spawn(async move {
                let mut group = group;
                let mut sent = Sent::default();
                for (nc, ask) in group.iter_mut().zip(asks) {
                    sent.add(tick_one(&client, &base, &rec, nc, upto, ask).await);
                }
                (g, group, sent)
            });
        }
        let mut back: Vec<(usize, Vec<Nc>)> = Vec::new();
        let mut sent = Sent::default();
        while let Some(done) = tasks.join_next().await {
            match done {
                Ok((g, group, s)) => {
                    back.push((g, group));
                    sent.add(s);
                }
                Err(_) => sent.errors += 1,
            }
        }
        back.sort_by_key(|(g, _)| *g);
        self.groups = back.into_iter().map(|(_, group)| group).collect();
        sent
    }
}

/// How the generator moves the NCs' time.
pub enum Drive {
    /// Post everything up to this service time and ask every idle NC for its order.
    To(i64),
    /// Follow `now` (the service clock) for `span` of wall time: each second every NC posts
    /// what happened, and asks for its order every `order_poll_s`, the NCs spread over it.
    Paced {
        clock: driftwatch_service::clock::ServiceClock,
        span: Duration,
        order_poll_s: u64,
    },
}

enum Cmd {
    Drive(Drive, tokio::sync::oneshot::Sender<Sent>),
    /// CPU seconds of the generator's thread so far.
    Cpu(tokio::sync::oneshot::Sender<f64>),
}

/// The load generator: its own thread and runtime, driven by commands.
pub struct Generator {
    tx: tokio::sync::mpsc::UnboundedSender<Cmd>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Generator {
    /// NCs `ids` at the service at `addr`, their days shifted evenly over `stagger_ns`; each
    /// first posts its program's spindle and state at `t0`.
    pub fn start(
        addr: std::net::SocketAddr,
        token: &str,
        ids: Vec<String>,
        rec: Recorded,
        t0: i64,
        stagger_ns: i64,
        tick: f64,
    ) -> Result<Generator> {
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Cmd>();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<()>>();
        let token = token.to_string();
        let thread = std::thread::Builder::new()
            .name("nc-load".into())
            .spawn(move || {
                let rt = match tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = ready_tx.send(Err(e.into()));
                        return;
                    }
                };
                rt.block_on(async move {
                    let mut auth = reqwest::header::HeaderMap::new();
                    match reqwest::header::HeaderValue::from_str(&format!("Bearer {token}")) {
                        Ok(v) => {
                            auth.insert(reqwest::header::AUTHORIZATION, v);
                        }
                        Err(e) => {
                            let _ = ready_tx.send(Err(e.into()));
                            return;
                        }
                    }
                    let client = match reqwest::Client::builder()
                        .pool_max_idle_per_host(IN_FLIGHT)
                        .default_headers(auth)
                        .build()
                    {
                        Ok(c) => c,
                        Err(e) => {
                            let _ = ready_tx.send(Err(e.into()));
                            return;
                        }
                    };
                    let base: Arc<str> = format!("http://{addr}").into();
                    let rec = Arc::new(rec);
                    let n = ids.len().max(1) as i64;
                    let mut groups: Vec<Vec<Nc>> = (0..IN_FLIGHT).map(|_| Vec::new()).collect();
                    for (i, id) in ids.into_iter().enumerate() {
                        let shift = (stagger_ns * i as i64 / n).rem_euclid(DAY_NS);
                        // Its spindle and state at the start, before anything else.
                        let (mut nc, start) = Nc::new(id, t0, shift, &rec);
                        nc.pending.extend(start);
                        groups[i % IN_FLIGHT].push(nc);
                    }
                    let mut ncs = Ncs { groups };
                    let _ = ready_tx.send(Ok(()));
                    while let Some(cmd) = rx.recv().await {
                        match cmd {
                            Cmd::Cpu(back) => {
                                let _ = back.send(thread_cpu_s(tick));
                            }
                            Cmd::Drive(Drive::To(upto), back) => {
                                let sent = ncs.tick(&client, &base, &rec, upto, |_| true).await;
                                let _ = back.send(sent);
                            }
                            Cmd::Drive(
                                Drive::Paced {
                                    clock,
                                    span,
                                    order_poll_s,
                                },
                                back,
                            ) => {
                                let mut sent = Sent::default();
                                let wall0 = Instant::now();
                                let mut every = tokio::time::interval(Duration::from_secs(1));
                                every.set_missed_tick_behavior(
                                    tokio::time::MissedTickBehavior::Delay,
                                );
                                let period = order_poll_s.max(1) as usize;
                                let mut second = 0usize;
                                while wall0.elapsed() < span {
                                    every.tick().await;
                                    let now = clock.now_ns();
                                    let s = second;
                                    sent.add(
                                        ncs.tick(&client, &base, &rec, now, |i| {
                                            (i + s).is_multiple_of(period)
                                        })
                                        .await,
                                    );
                                    second += 1;
                                }
                                let _ = back.send(sent);
                            }
                        }
                    }
                });
            })
            .context("starting the load generator's thread")?;
        ready_rx
            .recv()
            .context("the load generator's thread ended at its start")??;
        Ok(Generator {
            tx,
            thread: Some(thread),
        })
    }

    /// Run `drive` and say what was sent.
    pub async fn drive(&self, drive: Drive) -> Result<Sent> {
        let (back, sent) = tokio::sync::oneshot::channel();
        self.tx
            .send(Cmd::Drive(drive, back))
            .map_err(|_| anyhow::anyhow!("the load generator has stopped"))?;
        sent.await
            .map_err(|_| anyhow::anyhow!("the load generator stopped mid-drive"))
    }

    /// CPU seconds the generator's thread has used.
    pub async fn cpu_s(&self) -> Result<f64> {
        let (back, cpu) = tokio::sync::oneshot::channel();
        self.tx
            .send(Cmd::Cpu(back))
            .map_err(|_| anyhow::anyhow!("the load generator has stopped"))?;
        cpu.await
            .map_err(|_| anyhow::anyhow!("the load generator has stopped"))
    }
}

/// The id of the fleet's `i`-th machine.
pub fn fleet_id(i: usize) -> String {
    format!("m{:05}", i + 1)
}

impl Drop for Generator {
    fn drop(&mut self) {
        // Closing the command channel ends the thread's loop.
        let (tx, _) = tokio::sync::mpsc::unbounded_channel();
        drop(std::mem::replace(&mut self.tx, tx));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Order polls of a paced NC, s apart (a gateway's poll; `?wait_s=` long polls would let it
/// ask once a minute).
pub const ORDER_POLL_S: u64 = 10;

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::plan::PlanConfig;

    fn recorded() -> Recorded {
        let scn = Scenario::load("two_shift").expect("a built-in scenario");
        let k = Kinematics::load(&scn.machine).expect("its machine");
        let plan = Plan::build(&k, &PlanConfig::load(&scn.plan).expect("its plan"))
            .expect("the plan builds");
        Recorded::record(&scn, &k, &plan).expect("the day records")
    }

    /// The recorded day holds a temperature report a minute, the program's changes, and a
    /// cycle of the plan's steps every ten minutes; a replayed NC posts each event once, in
    /// time order, lap after lap, and while it answers an order only its temperatures.
    #[test]
    fn an_nc_replays_the_recorded_day_and_answers_an_order_with_a_recorded_cycle() {
        let rec = recorded();
        let temps = rec.events.iter().filter(|e| e.topic == "/temperature");
        let per_minute = temps.count() / 1440;
        assert!(per_minute >= 1, "{per_minute}");
        assert_eq!(rec.cycles.len(), 144);
        assert!(rec.events.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));

        let t0 = 1_000 * DAY_NS;
        let (mut nc, start) = Nc::new(fleet_id(0), t0, 6 * 60 * NS_PER_MIN, &rec);
        assert_eq!(start.len(), 2);
        let first = nc.due(&rec, t0 + 2 * DAY_NS - 1);
        assert_eq!(
            first.len(),
            2 * rec.events.len(),
            "two laps, each event once"
        );
        assert!(first.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));

        let now = t0 + 2 * DAY_NS;
        let steps = rec.cycles[0].len();
        let order = CycleOrder {
            cycle: 7,
            requested_ns: now,
            plan: "patent".into(),
            spindle_rpm: rec.plan_rpm,
            steps: Vec::new(),
        };
        nc.answer(&rec, &order, now);
        let end = now + rec.machine_time_ns;
        let during = nc.due(&rec, end - 1);
        let dets: Vec<_> = during
            .iter()
            .filter(|e| e.topic == "/probe/detection")
            .collect();
        assert_eq!(dets.len(), steps);
        assert!(dets.iter().all(|e| e.msg["cycle"] == 7));
        assert!(
            during
                .iter()
                .filter(|e| e.topic == "/machine/state")
                .all(|e| e.msg["state"] == "measuring"),
            "the recording's states wait while the cycle runs"
        );
        let after = nc.due(&rec, end);
        assert!(after.iter().any(|e| e.topic == "/machine/state"));
        assert_eq!(nc.cycle_end, None);
    }
}
