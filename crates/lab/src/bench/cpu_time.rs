//! CPU time and memory of processes, threads and the machine, read from Linux's /proc (the
//! workspace forbids unsafe code, so no getrusage): what the benchmarks report as their cost.

/// The fields of `/proc/PID/stat` after the command name (which may hold spaces): index 0 is
/// the state, 1 the parent, 11-14 utime, stime, cutime, cstime in clock ticks.
pub(super) fn proc_stat(pid: &str) -> Option<Vec<u64>> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &text[text.rfind(')')? + 1..];
    Some(
        rest.split_whitespace()
            .map(|w| w.parse().unwrap_or(0))
            .collect(),
    )
}

/// CPU seconds of process `pid`, its reaped children and its live children (a PostgreSQL
/// server: the postmaster, the backends that ended, and the connections still open).
pub(super) fn tree_cpu_s(pid: u32, tick: f64) -> f64 {
    let own = |f: &[u64]| f.get(11..15).map_or(0, |c| c.iter().sum::<u64>());
    let mut ticks = proc_stat(&pid.to_string()).map_or(0, |f| own(&f));
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if let Some(f) = proc_stat(&name)
            && f.get(1) == Some(&u64::from(pid))
        {
            ticks += own(&f);
        }
    }
    ticks as f64 / tick
}

/// This process's CPU time, user and system, s (what getrusage(RUSAGE_SELF) gives, read from
/// /proc: the workspace forbids unsafe code).
pub(super) fn own_cpu_s(tick: f64) -> (f64, f64) {
    let f = proc_stat("self").unwrap_or_default();
    let at = |i: usize| f.get(i).copied().unwrap_or(0) as f64 / tick;
    (at(11), at(12))
}

/// Clock ticks per second of /proc's times (USER_HZ; 100 on every Linux this runs on).
pub(super) fn clock_tick() -> f64 {
    std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8_lossy(&o.stdout).trim().parse().ok())
        .filter(|t: &f64| *t > 0.0)
        .unwrap_or(100.0)
}

/// The peak resident set of this process, bytes (VmHWM: getrusage's ru_maxrss).
pub(super) fn peak_rss() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Busy time of every core of the machine so far, s (/proc/stat: all but idle and iowait).
pub(super) fn machine_busy_s(tick: f64) -> f64 {
    let stat = std::fs::read_to_string("/proc/stat").unwrap_or_default();
    let f: Vec<f64> = stat
        .lines()
        .next()
        .unwrap_or_default()
        .split_whitespace()
        .skip(1)
        .take(8) // user nice system idle iowait irq softirq steal (guest time is in user)
        .map(|w| w.parse().unwrap_or(0.0))
        .collect();
    let idle = f.get(3).unwrap_or(&0.0) + f.get(4).unwrap_or(&0.0);
    (f.iter().sum::<f64>() - idle) / tick
}

/// CPU seconds of the calling thread (/proc/thread-self/stat: utime + stime).
pub(super) fn thread_cpu_s(tick: f64) -> f64 {
    let f = proc_stat("thread-self").unwrap_or_default();
    f.get(11..13).map_or(0, |c| c.iter().sum::<u64>()) as f64 / tick
}
