//! The service clock: the one notion of time of every machine loop. In production it is the
//! wall clock, sped up `scale` times for a simulated plant; in tests it is a manual clock that
//! the test moves, so that hours of a plant day run in seconds without sleeping on the wall
//! clock.

use std::time::{Duration, Instant};

use tokio::sync::watch;

/// Machine time for the loops, ns since the Unix epoch.
#[derive(Clone, Debug)]
pub enum ServiceClock {
    /// `t0_ns` at `wall0`, advancing `scale` ns per wall ns.
    Scaled {
        t0_ns: i64,
        wall0: Instant,
        scale: f64,
    },
    /// Wherever the [`ManualClock`] put it.
    Manual(watch::Receiver<i64>),
}

/// The hand that moves a manual [`ServiceClock`].
#[derive(Debug)]
pub struct ManualClock(watch::Sender<i64>);

impl ManualClock {
    /// Move the clock to `t_ns` (never back: an earlier time is ignored).
    pub fn set(&self, t_ns: i64) {
        self.0.send_if_modified(|now| {
            let later = t_ns > *now;
            if later {
                *now = t_ns;
            }
            later
        });
    }

    pub fn now_ns(&self) -> i64 {
        *self.0.borrow()
    }
}

impl ServiceClock {
    /// The wall clock from now, machine time `t0_ns`, `scale` times faster.
    pub fn scaled(t0_ns: i64, scale: f64) -> Self {
        ServiceClock::Scaled {
            t0_ns,
            wall0: Instant::now(),
            scale,
        }
    }

    /// A clock that stands at `t0_ns` until the returned hand moves it.
    pub fn manual(t0_ns: i64) -> (Self, ManualClock) {
        let (tx, rx) = watch::channel(t0_ns);
        (ServiceClock::Manual(rx), ManualClock(tx))
    }

    pub fn now_ns(&self) -> i64 {
        match self {
            ServiceClock::Scaled {
                t0_ns,
                wall0,
                scale,
            } => t0_ns.saturating_add((wall0.elapsed().as_secs_f64() * scale * 1e9) as i64),
            ServiceClock::Manual(rx) => *rx.borrow(),
        }
    }

    /// Wait until machine time `t_ns`, or at most `max_wall` of wall time (the loops look at
    /// their inboxes at least that often).
    pub async fn sleep_until(&self, t_ns: i64, max_wall: Duration) {
        match self {
            ServiceClock::Scaled { scale, .. } => {
                let dt = (t_ns.saturating_sub(self.now_ns())) as f64 / 1e9 / scale;
                let nap = Duration::from_secs_f64(dt.clamp(0.0, 3600.0)).min(max_wall);
                tokio::time::sleep(nap).await;
            }
            ServiceClock::Manual(rx) => {
                let mut rx = rx.clone();
                // A dropped hand leaves the clock where it stands: wait out `max_wall`.
                let reached = async {
                    if rx.wait_for(|now| *now >= t_ns).await.is_err() {
                        std::future::pending::<()>().await;
                    }
                };
                let _ = tokio::time::timeout(max_wall, reached).await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_manual_clock_moves_only_forward_and_wakes_its_sleepers() {
        let (clock, hand) = ServiceClock::manual(1_000);
        assert_eq!(clock.now_ns(), 1_000);
        hand.set(500);
        assert_eq!(clock.now_ns(), 1_000, "a manual clock never goes back");
        let sleeper = {
            let clock = clock.clone();
            tokio::spawn(async move {
                clock.sleep_until(5_000, Duration::from_secs(3600)).await;
                clock.now_ns()
            })
        };
        tokio::task::yield_now().await;
        hand.set(5_000);
        let woke_at = tokio::time::timeout(Duration::from_secs(60), sleeper)
            .await
            .expect("the sleeper wakes when the clock reaches its time")
            .expect("the sleeper does not panic");
        assert_eq!(woke_at, 5_000);
    }

    #[test]
    fn a_scaled_clock_starts_at_its_origin() {
        let clock = ServiceClock::scaled(7_000_000_000, 60.0);
        let t = clock.now_ns();
        // Within a minute of wall time (3600 s of machine time), however loaded the machine.
        assert!((7_000_000_000..7_000_000_000 + 3_600 * 1_000_000_000).contains(&t));
    }
}
