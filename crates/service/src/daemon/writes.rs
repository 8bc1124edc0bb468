//! A machine loop's writes, in the order its core decided them: the store's rows, the MCAP
//! recording, the alerts' webhooks, and the served set shown to the API once its row is
//! committed ([`Writer`]).
//!
//! They run either on the loop's own thread, each as it comes ([`Writes::Inline`]), or on a
//! thread of their own that the loop hands them to ([`Writes::Apart`]): then a loop behind its
//! clock (a replay as fast as it goes) decides its next steps while the last ones are written,
//! and one machine uses two cores. Both run the same [`Writer`], so the rules are one:
//! - the writes run in order, and one that fails stays at the head of the queue with every
//!   write behind it, and is tried again before anything new (nothing is lost or repeated);
//! - a set is shown to the API (and so handed to a link that writes it to the NC) only once
//!   the store holds it;
//! - the loop steps no further while its writes fail: it learns of a failure at its next step,
//!   tries the failed write again there ([`Writes::retry_failed`]), and fails that step if it
//!   fails again, as an inline write fails the step it runs in;
//! - apart, a loop that has caught up with its clock waits for its writes before it sleeps
//!   ([`super::run_machine`]), so a reader who saw a step sees its rows; one behind its clock
//!   runs at most [`BEHIND_MAX`] hand-overs ahead of its writer, then waits for it
//!   ([`Writes::settle`]), so the writes held in memory stay bounded.
//!
//! Apart, a loop behind its clock may so ask the machine for a cycle before the rows of its
//! last steps are committed: its cycle's rows follow them in order, and a failure among them
//! stops the loop at its next step as it would have stopped it inline.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{Notify, mpsc, oneshot};
use tracing::warn;

use super::{DaemonError, MachineView, NcBody};
use crate::recorder::{ClosedFile, Recorder};
use crate::store::{AlertEventKind, DetectionRow, FileStatus, NewAlertEvent, Store};
use driftwatch_core::recording as rec;
use driftwatch_machine::compensation::{self, CompensationSet};
use driftwatch_machine::machine_core::{Effect, Record};

/// A piece of work for a loop: the core's effects, and what the loop does on its own behalf in
/// the same order (the store rows of a recording file that opened or closed, an alert already
/// sent).
#[derive(Debug)]
pub(crate) enum Job {
    Core(Effect),
    FileOpened(PathBuf),
    FileClosed(ClosedFile),
    /// An alert event already shown and sent (the loop's health alert, raised while the
    /// queue is held up by the fault it reports): only stored.
    StoreAlert(Box<driftwatch_machine::alerts::AlertEvent>),
}

impl Job {
    /// Whether the writer runs it; the rest (a link's call, a solve, the view, a log line) are
    /// the loop's.
    pub(crate) fn is_write(&self) -> bool {
        !matches!(
            self,
            Job::Core(
                Effect::RequestCycle { .. }
                    | Effect::AbortCycle { .. }
                    | Effect::Solve(_)
                    | Effect::PublishView
                    | Effect::Log(..)
            )
        )
    }

    /// A write that may wait for the next one to be handed over with it: a message for the
    /// recording, which the recorder holds in memory until its next flush anyway.
    fn may_wait(&self) -> bool {
        matches!(self, Job::Core(Effect::Record(_)))
    }
}

/// The writes a writer's queue keeps room for between bursts.
const QUEUE_KEPT: usize = 16;

/// Writes held back by an apart loop before it wakes its writer for them, unless one that may
/// not wait comes first: a wake of another thread costs some 2 us, and most steps of a replay
/// give only a message or two for the recording (a wake at each of the simulated year's 2.1
/// million steps cost it about 4 s).
const HELD_MAX: usize = 64;

/// What runs a loop's writes: its store, its recorder, its webhooks and the set its view
/// shows.
pub(crate) struct Writer {
    id: String,
    store: Store,
    recorder: Recorder,
    notifier: crate::webhook::Notifier,
    view: Arc<Mutex<MachineView>>,
    /// Apart: what wakes the loop when a set is stored, so that a link that writes the set to
    /// the NC gets it at once, not at the loop's next step.
    wake: Option<Arc<Notify>>,
    /// Writes not yet made, in order, each with the service clock of the step that decided
    /// it (recording files follow that clock); a failed one stays at the head.
    queue: VecDeque<(i64, Job)>,
}

impl Writer {
    pub(crate) fn new(
        id: &str,
        store: Store,
        recorder: Recorder,
        view: Arc<Mutex<MachineView>>,
    ) -> Self {
        Writer {
            id: id.to_string(),
            store,
            recorder,
            notifier: Default::default(),
            view,
            wake: None,
            queue: VecDeque::new(),
        }
    }

    /// Make every queued write in order; one that fails stays at the head, and its error is
    /// returned.
    async fn drain(&mut self) -> Result<(), DaemonError> {
        while let Some((now, job)) = self.queue.pop_front() {
            match self.run(&job, now).await {
                // What a write gives (a rotated file's rows) runs before the rest.
                Ok(follow) => {
                    for j in follow.into_iter().rev() {
                        self.queue.push_front((now, j));
                    }
                }
                Err(e) => {
                    self.queue.push_front((now, job));
                    return Err(e);
                }
            }
        }
        // Empty now: a burst's room would stay with the loop for good.
        self.queue.shrink_to(QUEUE_KEPT);
        Ok(())
    }

    /// Make one write; returns the writes it gives, to make next.
    async fn run(&mut self, job: &Job, now: i64) -> Result<Vec<Job>, DaemonError> {
        let effect = match job {
            Job::Core(e) => e,
            Job::FileOpened(path) => {
                self.store
                    .mcap_file_opened(&self.id, &path.display().to_string(), now)
                    .await?;
                return Ok(Vec::new());
            }
            Job::FileClosed(f) => {
                self.file_closed(f, now).await?;
                return Ok(Vec::new());
            }
            Job::StoreAlert(ev) => {
                self.store_alert(ev).await?;
                return Ok(Vec::new());
            }
        };
        match effect {
            Effect::Record(r) => return self.record_core(r, now),
            Effect::FlushRecording => self.recorder.flush()?,
            Effect::StoreSamples(rows) => self.store.add_samples(&self.id, rows).await?,
            Effect::OpenCycle {
                number,
                t_ns,
                trigger,
                attempt,
            } => {
                self.store
                    .open_cycle(&self.id, *number, *t_ns, trigger, *attempt)
                    .await?
            }
            Effect::StoreDetections { number, rows } => {
                let rows: Vec<DetectionRow> = rows
                    .iter()
                    .map(|r| DetectionRow {
                        t_ns: r.t_ns,
                        step: &r.step,
                        payload: r.payload.clone(),
                    })
                    .collect();
                self.store.add_detections(&self.id, *number, &rows).await?
            }
            Effect::AbandonCycle {
                number,
                t_ns,
                reason,
            } => {
                self.store
                    .abandon_cycle(&self.id, *number, *t_ns, reason)
                    .await?
            }
            Effect::CloseCycle { result, t_ns, set } => {
                let stored = set.as_deref().map(crate::store::NewCompensation::of);
                self.store
                    .close_cycle_with(&self.id, result, *t_ns, stored.as_ref())
                    .await?;
                if let Some(set) = set {
                    self.stored(set);
                }
            }
            Effect::StoreSet(set) => {
                self.store
                    .insert_compensation(&self.id, &crate::store::NewCompensation::of(set))
                    .await?;
                self.stored(set);
            }
            Effect::Alert(ev) => {
                warn!(machine = %self.id, alert = ev.id, rule = %ev.rule, kind = ?ev.kind, "{}", ev.message);
                self.store_alert(ev).await?;
                self.notifier.notify(&self.id, ev);
            }
            Effect::StoreAlertState { t_ns, state } => {
                self.store.put_alert_state(&self.id, *t_ns, state).await?
            }
            Effect::Acknowledged { alert, by, t_ns } => {
                self.store
                    .add_alert_event(
                        &self.id,
                        &NewAlertEvent {
                            alert: *alert as i64,
                            t_ns: *t_ns,
                            kind: AlertEventKind::Acknowledged,
                            rule: "",
                            severity: None,
                            message: &format!("acknowledged by {by}"),
                            value: None,
                        },
                    )
                    .await?
            }
            // The loop's own: never queued here.
            Effect::RequestCycle { .. }
            | Effect::AbortCycle { .. }
            | Effect::Solve(_)
            | Effect::PublishView
            | Effect::Log(..) => {}
        }
        Ok(Vec::new())
    }

    /// A set the store now holds: it is the one served (the core decides a set before it is
    /// stored, so its own may be ahead of this), and the view shows it (with its NC
    /// body, serialised once per version). The copies are made before the lock is taken and
    /// the old ones dropped after it is released, so that the NC's reads never wait on them.
    fn stored(&mut self, set: &CompensationSet) {
        let nc = NcBody::of(set);
        let mut shown = Some(set.clone());
        let mut old = None;
        if let Ok(mut v) = self.view.lock() {
            std::mem::swap(&mut v.compensation, &mut shown);
            old = Some(std::mem::replace(&mut v.nc_body, nc));
        }
        drop((shown, old));
        if let Some(wake) = &self.wake {
            wake.notify_one();
        }
    }

    async fn store_alert(
        &mut self,
        ev: &driftwatch_machine::alerts::AlertEvent,
    ) -> Result<(), DaemonError> {
        let row = NewAlertEvent {
            alert: ev.id as i64,
            t_ns: ev.t_ns,
            kind: ev.kind.into(),
            rule: &ev.rule,
            severity: Some(ev.severity.into()),
            message: &ev.message,
            // An alert resolved at a restart has no value to report.
            value: Some(ev.value).filter(|v| v.is_finite()),
        };
        Ok(self.store.add_alert_event(&self.id, &row).await?)
    }

    fn record_core(&mut self, r: &Record, now: i64) -> Result<Vec<Job>, DaemonError> {
        match r {
            Record::Spindle(m) => self.record(rec::TOPIC_SPINDLE, m.t_ns, now, &m.msg),
            Record::State(m) => self.record(rec::TOPIC_STATE, m.t_ns, now, &m.msg),
            Record::Temperature(m) => self.record(rec::TOPIC_TEMPERATURE, m.t_ns, now, &m.msg),
            Record::Detection(m) => self.record(rec::TOPIC_DETECTION, m.t_ns, now, &m.msg),
            Record::Compensation { t_ns, set } => self.record(
                rec::TOPIC_COMPENSATION,
                *t_ns,
                now,
                &compensation::compensation_message(set),
            ),
            Record::Result { t_ns, result } => self.record(rec::TOPIC_RESULT, *t_ns, now, result),
            Record::Raw { topic, t_ns, json } => self.record(topic, *t_ns, now, json),
        }
    }

    /// Write one message; a file that rotated gives its store rows as the next writes.
    fn record<T: serde::Serialize>(
        &mut self,
        topic: &str,
        t_ns: i64,
        now: i64,
        msg: &T,
    ) -> Result<Vec<Job>, DaemonError> {
        let rotation = self.recorder.write(topic, t_ns, now, msg)?;
        Ok(rotation
            .recovered
            .into_iter()
            .map(Job::FileClosed)
            .chain(rotation.closed.map(Job::FileClosed))
            .chain(rotation.opened.map(Job::FileOpened))
            .collect())
    }

    /// Close the recording for good (the service stops) and store its files' rows.
    async fn stop(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        self.drain().await?;
        for closed in self.recorder.stop(now_ns)? {
            self.file_closed(&closed, now_ns).await?;
        }
        Ok(())
    }

    async fn file_closed(&mut self, f: &ClosedFile, now_ns: i64) -> Result<(), DaemonError> {
        self.store
            .mcap_file_closed(
                &self.id,
                &f.partial.display().to_string(),
                &f.path.display().to_string(),
                now_ns,
                if f.recovered {
                    FileStatus::Recovered
                } else {
                    FileStatus::Closed
                },
                f.messages as i64,
            )
            .await?;
        Ok(())
    }
}

/// What a loop tells its writer's thread.
enum Msg {
    Jobs(Vec<(i64, Job)>),
    /// Make every write before this, trying a failed one again; answer how that went.
    Settle(oneshot::Sender<Result<(), DaemonError>>),
    /// Show the machine in this view, and wake its loop by this, from now on.
    View(Arc<Mutex<MachineView>>, Option<Arc<Notify>>),
    Notifier(crate::webhook::Notifier),
    /// Hand the writer back to the loop and end.
    Return(oneshot::Sender<Box<Writer>>),
}

/// A loop's writes and where they run.
pub(crate) enum Writes {
    Inline(Box<Writer>),
    Apart(Apart),
}

/// Hand-overs an apart loop may run ahead of its writer before it waits for it: some 256
/// steps' writes, a few megabytes.
const BEHIND_MAX: usize = 256;

/// A writer on a thread of its own, and the writes the loop holds for it.
pub(crate) struct Apart {
    /// Hand-overs the writer has not finished.
    behind: Arc<AtomicUsize>,
    tx: mpsc::UnboundedSender<Msg>,
    held: Vec<(i64, Job)>,
    /// A held write that may not wait for the next ones.
    due: bool,
    /// Set by the writer when a write failed; cleared when a settle made them all.
    failing: Arc<AtomicBool>,
}

impl Writes {
    /// Queue a write decided at service time `now`. Inline it is made at once, and its error
    /// returned (the write stays at the head of the queue); apart it is held for the writer.
    pub(crate) async fn push(&mut self, job: Job, now: i64) -> Result<(), DaemonError> {
        match self {
            // Nothing failed before it (the usual case): made at once, not through the queue.
            Writes::Inline(w) if w.queue.is_empty() => match w.run(&job, now).await {
                Ok(follow) if follow.is_empty() => Ok(()),
                Ok(follow) => {
                    w.queue.extend(follow.into_iter().map(|j| (now, j)));
                    w.drain().await
                }
                Err(e) => {
                    w.queue.push_front((now, job));
                    Err(e)
                }
            },
            Writes::Inline(w) => {
                w.queue.push_back((now, job));
                w.drain().await
            }
            Writes::Apart(a) => {
                a.due |= !job.may_wait();
                a.held.push((now, job));
                Ok(())
            }
        }
    }

    /// Every write queued so far made, a failed one tried again first: its error if it fails.
    pub(crate) async fn settle(&mut self) -> Result<(), DaemonError> {
        match self {
            Writes::Inline(w) => w.drain().await,
            Writes::Apart(a) => {
                a.hand_over()?;
                let (tx, rx) = oneshot::channel();
                a.send(Msg::Settle(tx))?;
                rx.await.map_err(|_| gone())?
            }
        }
    }

    /// Before a step takes anything new: writes that failed (inline: any left in the queue;
    /// apart: the writer said so) are tried again, and the step fails if they fail again.
    pub(crate) async fn retry_failed(&mut self) -> Result<(), DaemonError> {
        match self {
            Writes::Inline(w) if w.queue.is_empty() => Ok(()),
            Writes::Apart(a) if !a.failing.load(Ordering::Acquire) => Ok(()),
            _ => self.settle().await,
        }
    }

    /// The end of a step: held writes go to the writer if one of them may not wait, or once
    /// enough are held; a loop too far ahead of its writer waits for it.
    pub(crate) async fn step_done(&mut self) -> Result<(), DaemonError> {
        match self {
            Writes::Apart(a) if a.due || a.held.len() >= HELD_MAX => {
                a.hand_over()?;
                if a.behind.load(Ordering::Acquire) > BEHIND_MAX {
                    return self.settle().await;
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    /// Show the machine in `view` from now on (and, apart, wake its loop by `wake`).
    pub(crate) fn set_view(&mut self, view: &Arc<Mutex<MachineView>>, wake: Option<Arc<Notify>>) {
        match self {
            Writes::Inline(w) => w.view = view.clone(),
            Writes::Apart(a) => {
                let _ = a.send(Msg::View(view.clone(), wake));
            }
        }
    }

    pub(crate) fn set_notifier(&mut self, notifier: crate::webhook::Notifier) {
        match self {
            Writes::Inline(w) => w.notifier = notifier,
            Writes::Apart(a) => {
                let _ = a.send(Msg::Notifier(notifier));
            }
        }
    }

    /// Move the writes to a thread of their own. Only where a write runs on the calling
    /// thread (SQLite outside a fleet: no runtime's reactor drives a connection the thread
    /// would open); otherwise they stay inline. A thread that cannot be started leaves them
    /// inline, and says why.
    pub(crate) fn go_apart(&mut self, wake: Option<Arc<Notify>>) -> Result<(), DaemonError> {
        let Writes::Inline(w) = self else {
            return Ok(());
        };
        if !w.store.writes_on_calling_thread() {
            return Ok(());
        }
        let failing = Arc::new(AtomicBool::new(!w.queue.is_empty()));
        let behind = Arc::new(AtomicUsize::new(0));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| DaemonError::Writes(format!("starting its runtime: {e}")))?;
        // The writer goes to the thread only once it runs, so that nothing is lost if it
        // cannot be started.
        let (give, take) =
            std::sync::mpsc::channel::<(Box<Writer>, mpsc::UnboundedReceiver<Msg>)>();
        let (failing_there, behind_there) = (failing.clone(), behind.clone());
        std::thread::Builder::new()
            .name(format!("writes {}", w.id).chars().take(15).collect())
            .spawn(move || {
                if let Ok((w, rx)) = take.recv() {
                    runtime.block_on(serve(w, rx, failing_there, behind_there));
                }
            })
            .map_err(|e| DaemonError::Writes(format!("starting its thread: {e}")))?;
        let (tx, rx) = mpsc::unbounded_channel();
        let apart = Writes::Apart(Apart {
            behind,
            tx,
            held: Vec::new(),
            due: false,
            failing,
        });
        let Writes::Inline(mut w) = std::mem::replace(self, apart) else {
            unreachable!("matched above");
        };
        w.wake = wake;
        if let Err(std::sync::mpsc::SendError((mut w, _))) = give.send((w, rx)) {
            w.wake = None;
            *self = Writes::Inline(w);
            return Err(DaemonError::Writes("its thread ended at its start".into()));
        }
        Ok(())
    }

    /// Bring the writes back to the loop's thread (the loop ends): every held write is handed
    /// over first, so none is lost.
    async fn inline(&mut self) -> Result<&mut Writer, DaemonError> {
        if let Writes::Apart(a) = self {
            a.hand_over()?;
            let (tx, rx) = oneshot::channel();
            a.send(Msg::Return(tx))?;
            let mut w = rx.await.map_err(|_| gone())?;
            w.wake = None;
            *self = Writes::Inline(w);
        }
        match self {
            Writes::Inline(w) => Ok(w),
            Writes::Apart(_) => unreachable!("made inline above"),
        }
    }

    /// The loop ends: every write made, the recording closed and its files' rows stored.
    pub(crate) async fn stop(&mut self, now_ns: i64) -> Result<(), DaemonError> {
        self.inline().await?.stop(now_ns).await
    }
}

impl Apart {
    fn send(&self, msg: Msg) -> Result<(), DaemonError> {
        self.tx.send(msg).map_err(|_| gone())
    }

    fn hand_over(&mut self) -> Result<(), DaemonError> {
        self.due = false;
        if self.held.is_empty() {
            return Ok(());
        }
        let held = std::mem::take(&mut self.held);
        self.behind.fetch_add(1, Ordering::AcqRel);
        self.send(Msg::Jobs(held))
    }
}

fn gone() -> DaemonError {
    DaemonError::Writes("its thread ended (a panic: see the log)".into())
}

/// The writer's thread: writes as they come while they succeed; after a failure only a
/// settle tries again (the loop's retry times pace it, as they pace an inline loop).
async fn serve(
    mut w: Box<Writer>,
    mut rx: mpsc::UnboundedReceiver<Msg>,
    failing: Arc<AtomicBool>,
    behind: Arc<AtomicUsize>,
) {
    while let Some(msg) = rx.recv().await {
        match msg {
            Msg::Jobs(jobs) => {
                w.queue.extend(jobs);
                if !failing.load(Ordering::Acquire) && w.drain().await.is_err() {
                    failing.store(true, Ordering::Release);
                }
                behind.fetch_sub(1, Ordering::AcqRel);
            }
            Msg::Settle(answer) => {
                let settled = w.drain().await;
                failing.store(settled.is_err(), Ordering::Release);
                let _ = answer.send(settled);
            }
            Msg::View(view, wake) => {
                w.view = view;
                w.wake = wake;
            }
            Msg::Notifier(n) => w.notifier = n,
            Msg::Return(back) => {
                let _ = back.send(w);
                return;
            }
        }
    }
}
