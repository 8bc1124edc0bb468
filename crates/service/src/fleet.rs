//! A fleet of service processes on one database: each machine is run by the one process that
//! holds its lease (`store::leases`), and any process answers the API for any machine.
//!
//! Every process configures every machine. Its supervisor, every fifth of the lease time:
//! - renews the leases of the machines it runs; one it can no longer renew (another process
//!   took it) or has not renewed for two thirds of the lease time (the database is out of
//!   reach) has its loop stopped, and the loop's writes are fenced by the lease in any case;
//! - takes each machine nobody holds or whose lease expired (up to `max_machines`), and runs
//!   it from the stored state, as a restarted process would: the open cycle abandoned, the
//!   scheduler's memory and the thermal model rebuilt from history, the served set restored;
//! - shows each machine another process runs from the database: its served set (what the NC
//!   endpoint answers), its cycles and who runs it. Requests that change such a machine are
//!   refused with the holder's name and address.
//!
//! On a clean stop the loops end and the leases are released, so that the others take the
//! machines over at once rather than after the lease time.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::clock::ServiceClock;
use crate::daemon::{FleetView, MachineHandle, MachineRuntime, NcBody, Settings, run_machine};
use crate::link::{LinkError, LinkEvent, MachineLink};
use crate::recorder::Recorder;
use crate::store::{Lease, LeaseRow, Store, StoreError};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::MachineInfo;

/// A machine's link shared between the loops that run it one after another in this process
/// (a lease lost and taken again): the loop borrows it, the slot keeps it.
#[derive(Clone)]
pub struct SharedLink(Arc<Mutex<Box<dyn MachineLink>>>);

impl SharedLink {
    pub fn new(link: Box<dyn MachineLink>) -> Self {
        SharedLink(Arc::new(Mutex::new(link)))
    }

    fn with<T>(&self, f: impl FnOnce(&mut Box<dyn MachineLink>) -> T) -> T {
        // A loop that panicked holding it leaves the link as it was: go on with it.
        let mut guard = self.0.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut guard)
    }
}

impl MachineLink for SharedLink {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        self.with(|l| l.poll(now_ns))
    }
    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        self.with(|l| l.request_cycle(number, now_ns))
    }
    fn abort_cycle(&mut self, number: i64, now_ns: i64) {
        self.with(|l| l.abort_cycle(number, now_ns))
    }
    fn next_event_ns(&self) -> Option<i64> {
        self.with(|l| l.next_event_ns())
    }
    fn waker(&self) -> Option<Arc<tokio::sync::Notify>> {
        self.with(|l| l.waker())
    }
    fn serve(&mut self, set: &driftwatch_machine::compensation::CompensationSet) {
        self.with(|l| l.serve(set))
    }
    fn resume_at(&mut self, t_ns: i64) {
        self.with(|l| l.resume_at(t_ns))
    }
    fn set_clock(&mut self, clock: &crate::clock::ServiceClock) {
        self.with(|l| l.set_clock(clock))
    }
}

/// One configured machine in a fleet process.
pub struct Slot {
    pub id: String,
    pub kinematics: Kinematics,
    pub plan: Arc<Plan>,
    pub settings: Settings,
    pub link: SharedLink,
    pub handle: MachineHandle,
    running: Option<Running>,
}

impl Slot {
    /// A machine not run yet: the API's handle of it shows nothing until the supervisor
    /// takes it or reads it from the database.
    pub fn new(
        id: String,
        kinematics: Kinematics,
        plan: Arc<Plan>,
        settings: Settings,
        link: Box<dyn MachineLink>,
        nc: Option<crate::nc_push::NcPushHandle>,
    ) -> Self {
        let view = crate::daemon::MachineView {
            id: id.clone(),
            kinematics: kinematics.name.clone(),
            ..Default::default()
        };
        let handle = MachineHandle {
            view: Arc::new(Mutex::new(view)),
            inbox: Default::default(),
            nc,
            kinematics: Some(Arc::new(kinematics.clone())),
        };
        let link = SharedLink::new(link);
        Slot {
            id,
            kinematics,
            plan,
            settings,
            link,
            handle,
            running: None,
        }
    }
}

struct Running {
    lease: Lease,
    stop: CancellationToken,
    task: JoinHandle<()>,
    renewed: Instant,
}

/// The supervisor of this process's part of the fleet.
pub struct Fleet {
    pub process: String,
    pub url: Option<String>,
    pub ttl: Duration,
    pub max_machines: usize,
    pub store: Store,
    pub clock: ServiceClock,
    pub mcap_dir: PathBuf,
    pub max_file_bytes: u64,
    pub notifier: crate::webhook::Notifier,
    pub slots: Vec<Slot>,
}

impl Fleet {
    /// Renew, take and show machines until `shutdown`; then stop the loops and release.
    pub async fn run(mut self, shutdown: CancellationToken) {
        let tick = (self.ttl / 5).max(Duration::from_millis(100));
        info!(process = %self.process, lease_s = self.ttl.as_secs_f64(), machines = self.slots.len(), "fleet: supervising");
        loop {
            self.tick(&shutdown).await;
            tokio::select! {
                _ = tokio::time::sleep(tick) => {}
                _ = shutdown.cancelled() => break,
            }
        }
        for s in &mut self.slots {
            if let Some(r) = s.running.take() {
                r.stop.cancel();
                if let Err(e) = r.task.await {
                    error!(machine = %s.id, error = %e, "a machine loop panicked");
                }
                match self.store.release_lease(&r.lease).await {
                    Ok(()) => info!(machine = %s.id, term = r.lease.term, "fleet: lease released"),
                    Err(e) => {
                        warn!(machine = %s.id, error = %e, "fleet: could not release the lease; it expires by itself")
                    }
                }
            }
        }
    }

    async fn tick(&mut self, shutdown: &CancellationToken) {
        let ttl_ms = self.ttl.as_millis() as i64;
        let leases: BTreeMap<String, LeaseRow> = match self.store.leases().await {
            Ok(rows) => rows
                .into_iter()
                .map(|r| (r.machine_id.clone(), r))
                .collect(),
            Err(e) => {
                warn!(error = %e, "fleet: cannot read the leases");
                BTreeMap::new()
            }
        };
        let mut held = self.slots.iter().filter(|s| s.running.is_some()).count();
        for i in 0..self.slots.len() {
            self.keep(i, ttl_ms).await;
            if self.slots[i].running.is_none()
                && held < self.max_machines
                && !shutdown.is_cancelled()
            {
                self.take(i, ttl_ms, shutdown).await;
            }
            let slot = &self.slots[i];
            if slot.running.is_none()
                && let Err(e) = follow(&self.store, slot, leases.get(&slot.id)).await
            {
                warn!(machine = %slot.id, error = %e, "fleet: cannot show a machine run elsewhere");
            }
            held = self.slots.iter().filter(|s| s.running.is_some()).count();
        }
    }

    /// Renew the lease of a machine run here; stop its loop when the lease is gone or cannot
    /// be shown to be held; forget a loop that ended.
    async fn keep(&mut self, i: usize, ttl_ms: i64) {
        let slot = &mut self.slots[i];
        let Some(r) = slot.running.as_mut() else {
            return;
        };
        if r.task.is_finished() {
            info!(machine = %slot.id, term = r.lease.term, "fleet: the machine's loop ended");
            // Held still (the loop stopped for failed renewals): another process may take it
            // now rather than after the lease time. Not held: nothing happens.
            if let Err(e) = self.store.release_lease(&r.lease).await {
                warn!(machine = %slot.id, error = %e, "fleet: could not release the lease; it expires by itself");
            }
            slot.running = None;
            return;
        }
        let sent = Instant::now();
        match self.store.renew_lease(&r.lease, ttl_ms).await {
            Ok(true) => r.renewed = sent,
            Ok(false) => {
                warn!(machine = %slot.id, term = r.lease.term, "fleet: another process took the machine; stopping its loop here");
                r.stop.cancel();
            }
            Err(e) => {
                if r.renewed.elapsed() > self.ttl * 2 / 3 {
                    warn!(machine = %slot.id, error = %e, "fleet: the lease could not be renewed in time; stopping the loop (its writes are fenced)");
                    r.stop.cancel();
                } else {
                    warn!(machine = %slot.id, error = %e, "fleet: renewing the lease failed; trying again");
                }
            }
        }
    }

    /// Take machine `i` if its lease is free or expired, and run it from the stored state.
    async fn take(&mut self, i: usize, ttl_ms: i64, shutdown: &CancellationToken) {
        let id = self.slots[i].id.clone();
        let lease = match self
            .store
            .acquire_lease(&id, &self.process, self.url.as_deref(), ttl_ms)
            .await
        {
            Ok(Some(lease)) => lease,
            Ok(None) => return,
            Err(e) => {
                warn!(machine = %id, error = %e, "fleet: cannot try the machine's lease");
                return;
            }
        };
        let renewed = Instant::now();
        let now = self.clock.now_ns();
        match self.start(i, &lease, now).await {
            Ok(rt) => {
                info!(machine = %id, term = lease.term, process = %self.process, "fleet: running the machine");
                let stop = shutdown.child_token();
                let task = tokio::spawn(run_machine(
                    Box::new(rt),
                    self.clock.clone(),
                    now,
                    None,
                    stop.clone(),
                ));
                self.slots[i].running = Some(Running {
                    lease,
                    stop,
                    task,
                    renewed,
                });
            }
            Err(e) => {
                error!(machine = %id, error = %e, "fleet: could not start the machine; releasing its lease");
                if let Err(e) = self.store.release_lease(&lease).await {
                    warn!(machine = %id, error = %e, "fleet: could not release the lease");
                }
            }
        }
    }

    async fn start(&self, i: usize, lease: &Lease, now: i64) -> Result<MachineRuntime, String> {
        let slot = &self.slots[i];
        let info = MachineInfo {
            machine_id: slot.id.clone(),
            kinematics: slot.kinematics.name.clone(),
            software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        };
        let recorder =
            Recorder::new(&self.mcap_dir, info, self.max_file_bytes).map_err(|e| e.to_string())?;
        let mut link = slot.link.clone();
        // A simulated machine ran on unobserved while another process had it.
        link.resume_at(now);
        let mut rt = MachineRuntime::new(
            &slot.id,
            slot.kinematics.clone(),
            &slot.plan,
            Box::new(link),
            &slot.settings,
            self.store.fenced(lease),
            recorder,
            now,
        )
        .await
        .map_err(|e| e.to_string())?;
        rt.set_notifier(self.notifier.clone());
        rt.adopt(&slot.handle.view, &slot.handle.inbox);
        if let Ok(mut v) = slot.handle.view.lock() {
            v.fleet = Some(FleetView {
                holder: Some(self.process.clone()),
                url: self.url.clone(),
                term: Some(lease.term),
                here: true,
            });
        }
        Ok(rt)
    }
}

/// Show a machine another process runs (or nobody) from the database.
async fn follow(store: &Store, slot: &Slot, lease: Option<&LeaseRow>) -> Result<(), StoreError> {
    let live = lease.filter(|l| l.expires_ms > l.now_ms);
    let fleet = FleetView {
        holder: live.map(|l| l.holder.clone()),
        url: live.and_then(|l| l.url.clone()),
        term: live.map(|l| l.term),
        here: false,
    };
    let stored_version = slot
        .handle
        .view
        .lock()
        .ok()
        .and_then(|v| v.compensation.as_ref().map(|c| c.version));
    let set = store.latest_compensation(&slot.id).await?;
    let last = store.last_closed_cycle(&slot.id).await?;
    let open = store.open_cycles(&slot.id).await?.last().copied();
    let fresh = set.as_ref().map(|c| c.version) != stored_version;
    let nc = if fresh {
        set.as_ref().and_then(NcBody::of)
    } else {
        None
    };
    if let Ok(mut v) = slot.handle.view.lock() {
        v.fleet = Some(fleet);
        v.cycles.last = last;
        v.cycles.open = open;
        // What only the running loop knows is not shown stale.
        v.phase = None;
        v.open_alerts.clear();
        v.thermal = Default::default();
        if fresh {
            v.compensation = set;
            v.nc_body = nc;
        }
    }
    Ok(())
}
