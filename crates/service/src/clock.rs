//! The service clock: the one notion of time of every machine loop. In production it is the
//! wall clock, sped up `scale` times for a simulated plant; in tests and benchmarks it is a
//! manual clock that its hand moves (hours of a plant day in seconds, without sleeping on the
//! wall clock) and may set running at any pace from where it stands.
//!
//! The loops sleep on it until the time they asked for, not on a wall-clock timer: a quiet
//! machine costs nothing between its wakes. A held manual clock also wakes every sleeper when
//! its hand moves, so that a test that moves it sees every loop step to the new time.

use std::time::{Duration, Instant};

use tokio::sync::watch;

/// How the clock moves now.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pace {
    /// Standing at this time, ns since the Unix epoch, until the hand moves it.
    Held(i64),
    /// `t0_ns` at `wall0`, advancing `scale` ns per wall ns.
    Running {
        t0_ns: i64,
        wall0: Instant,
        scale: f64,
    },
}

impl Pace {
    fn now_ns(&self) -> i64 {
        match *self {
            Pace::Held(t) => t,
            Pace::Running {
                t0_ns,
                wall0,
                scale,
            } => t0_ns.saturating_add((wall0.elapsed().as_secs_f64() * scale * 1e9) as i64),
        }
    }
}

/// Machine time for the loops, ns since the Unix epoch.
#[derive(Clone, Debug)]
pub struct ServiceClock {
    pace: watch::Receiver<Pace>,
    /// Whether a hand moves it (a manual clock), as the API says.
    manual: bool,
}

/// The hand that moves a manual [`ServiceClock`].
#[derive(Debug)]
pub struct ManualClock(watch::Sender<Pace>);

impl ManualClock {
    /// Hold the clock at `t_ns` (never back: an earlier time holds it where it stands).
    pub fn set(&self, t_ns: i64) {
        self.0.send_if_modified(|pace| {
            let now = pace.now_ns();
            let moved = t_ns > now || matches!(pace, Pace::Running { .. });
            if moved {
                *pace = Pace::Held(t_ns.max(now));
            }
            moved
        });
    }

    /// Set the clock running from where it stands, `scale` machine ns per wall ns (1: the
    /// wall clock's pace): the loops then wake only when their own time comes, as in
    /// production.
    pub fn run(&self, scale: f64) {
        self.0.send_modify(|pace| {
            *pace = Pace::Running {
                t0_ns: pace.now_ns(),
                wall0: Instant::now(),
                scale,
            }
        });
    }

    pub fn now_ns(&self) -> i64 {
        self.0.borrow().now_ns()
    }
}

impl ServiceClock {
    /// The wall clock from now, machine time `t0_ns`, `scale` times faster.
    pub fn scaled(t0_ns: i64, scale: f64) -> Self {
        let (_, pace) = watch::channel(Pace::Running {
            t0_ns,
            wall0: Instant::now(),
            scale,
        });
        ServiceClock {
            pace,
            manual: false,
        }
    }

    /// A clock that stands at `t0_ns` until the returned hand moves it.
    pub fn manual(t0_ns: i64) -> (Self, ManualClock) {
        let (tx, pace) = watch::channel(Pace::Held(t0_ns));
        (ServiceClock { pace, manual: true }, ManualClock(tx))
    }

    pub fn now_ns(&self) -> i64 {
        self.pace.borrow().now_ns()
    }

    /// Whether a hand moves it.
    pub fn is_manual(&self) -> bool {
        self.manual
    }

    /// Machine ns per wall ns while it runs (`None`: held by its hand).
    pub fn scale(&self) -> Option<f64> {
        match *self.pace.borrow() {
            Pace::Held(_) => None,
            Pace::Running { scale, .. } => Some(scale),
        }
    }

    /// The time now, as a loop looks at it before it steps: the hand's moves up to this look
    /// count as seen by this clock (its own copy), and a later [`Self::sleep_until`] wakes at
    /// the next one. A move made while the loop stepped is not lost: it wakes the sleep at once.
    pub fn look(&mut self) -> i64 {
        self.pace.borrow_and_update().now_ns()
    }

    /// Wait until machine time `t_ns`; while a hand holds the clock, also until the hand moves
    /// it after this clock's last [`Self::look`] (the loops then step to the time it was moved
    /// to). A running clock is slept on in naps of at most an hour of wall time, and the nap
    /// ends early when the hand changes the pace.
    pub async fn sleep_until(&mut self, t_ns: i64) {
        loop {
            // A move since the last look (made while the loop stepped) is news already: taking
            // it as seen here would leave the loop asleep behind a held clock.
            let moved = self.pace.has_changed().unwrap_or(false);
            let pace = *self.pace.borrow_and_update();
            let now = pace.now_ns();
            if now >= t_ns {
                return;
            }
            match pace {
                Pace::Held(_) => {
                    if moved {
                        return;
                    }
                    // A dropped hand leaves the clock where it stands for good.
                    if self.pace.changed().await.is_err() {
                        std::future::pending::<()>().await;
                    }
                    return;
                }
                Pace::Running { scale, .. } => {
                    let dt = (t_ns.saturating_sub(now)) as f64 / 1e9 / scale;
                    let nap = Duration::from_secs_f64(dt.clamp(0.0, 3600.0));
                    tokio::select! {
                        _ = tokio::time::sleep(nap) => {}
                        changed = self.pace.changed() => {
                            if changed.is_err() {
                                // No hand (a scaled clock): the pace is fixed; sleep it out.
                                tokio::time::sleep(nap).await;
                            }
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task that sleeps on `clock` until `t_ns` and returns the time it woke at.
    fn sleeper(clock: &ServiceClock, t_ns: i64) -> tokio::task::JoinHandle<i64> {
        let mut clock = clock.clone();
        tokio::spawn(async move {
            clock.sleep_until(t_ns).await;
            clock.now_ns()
        })
    }

    #[tokio::test]
    async fn a_manual_clock_moves_only_forward_and_wakes_its_sleepers() {
        let (clock, hand) = ServiceClock::manual(1_000);
        assert_eq!(clock.now_ns(), 1_000);
        hand.set(500);
        assert_eq!(clock.now_ns(), 1_000, "a manual clock never goes back");
        let sleeper = sleeper(&clock, 5_000);
        tokio::task::yield_now().await;
        hand.set(5_000);
        let woke_at = tokio::time::timeout(Duration::from_secs(60), sleeper)
            .await
            .expect("the sleeper wakes when the clock reaches its time")
            .expect("the sleeper does not panic");
        assert_eq!(woke_at, 5_000);
    }

    #[tokio::test]
    async fn a_held_clock_wakes_its_sleepers_at_every_move_of_its_hand() {
        let (clock, hand) = ServiceClock::manual(1_000);
        let sleeper = sleeper(&clock, 1_000_000);
        tokio::task::yield_now().await;
        hand.set(2_000);
        let woke_at = tokio::time::timeout(Duration::from_secs(60), sleeper)
            .await
            .expect("a move of the hand wakes the sleeper before its time")
            .expect("the sleeper does not panic");
        assert_eq!(woke_at, 2_000);
    }

    /// The hand moves while the loop steps (after its look, before it sleeps): the sleep
    /// that follows wakes at once, so the loop steps to the new time instead of sleeping
    /// behind a held clock until the hand's next move.
    #[tokio::test(start_paused = true)]
    async fn a_move_made_between_a_look_and_the_sleep_wakes_the_sleep_at_once() {
        let (mut clock, hand) = ServiceClock::manual(1_000);
        assert_eq!(clock.look(), 1_000);
        hand.set(2_000);
        tokio::time::timeout(Duration::from_secs(60), clock.sleep_until(1_000_000))
            .await
            .expect("the move made before the sleep wakes it");
        assert_eq!(clock.look(), 2_000);
        // Seen now: the next sleep waits for the next move (tokio's paused time: no wall wait).
        let waited = tokio::time::timeout(Duration::from_secs(60), clock.sleep_until(1_000_000));
        assert!(
            waited.await.is_err(),
            "no move since the look: the sleep waits"
        );
    }

    #[tokio::test]
    async fn a_running_clock_wakes_its_sleepers_only_once_their_time_has_come() {
        let (mut clock, hand) = ServiceClock::manual(1_000);
        assert_eq!(clock.scale(), None);
        // A machine second per wall nanosecond: the sleeper's 10 s of machine time pass at once.
        hand.run(1e9);
        assert_eq!(clock.scale(), Some(1e9));
        let t = 1_000 + 10_000_000_000;
        tokio::time::timeout(Duration::from_secs(60), clock.sleep_until(t))
            .await
            .expect("the running clock reaches the sleeper's time");
        assert!(clock.now_ns() >= t, "the sleeper woke before its time");
        // Held again where it ran to, and never back.
        let ran_to = clock.now_ns();
        hand.set(0);
        assert!(clock.now_ns() >= ran_to);
        assert_eq!(clock.scale(), None);
    }

    #[test]
    fn a_scaled_clock_starts_at_its_origin() {
        let clock = ServiceClock::scaled(7_000_000_000, 60.0);
        let t = clock.now_ns();
        // Within a minute of wall time (3600 s of machine time), however loaded the machine.
        assert!((7_000_000_000..7_000_000_000 + 3_600 * 1_000_000_000).contains(&t));
        assert!(!clock.is_manual());
        assert_eq!(clock.scale(), Some(60.0));
    }
}
