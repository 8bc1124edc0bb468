//! `/metrics`: Prometheus text through the `metrics` facade and its Prometheus exporter. Each
//! service has its own recorder (no global one: tests run several services in one process),
//! used through `metrics::with_local_recorder`. The request-latency histograms are observed
//! as requests end; the machine figures are read from the machine views at each scrape.

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use metrics::{counter, describe_counter, describe_gauge, describe_histogram, gauge, histogram};
use metrics_exporter_prometheus::{
    Matcher, PrometheusBuilder, PrometheusHandle, PrometheusRecorder,
};

use super::{Shared, view};
use crate::daemon::MachineView;

/// Upper bounds of the request-latency histogram, seconds.
const LATENCY_BUCKETS: [f64; 12] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5,
];

const REQUEST_SECONDS: &str = "driftwatch_http_request_duration_seconds";

/// Requests observed between two drains of the latency histograms.
const UPKEEP_EVERY: u64 = 1024;

/// The service's metrics: its recorder and the handle that renders it.
pub struct Metrics {
    recorder: PrometheusRecorder,
    handle: PrometheusHandle,
    /// Requests observed so far: every [`UPKEEP_EVERY`]th drains the histograms.
    observed: std::sync::atomic::AtomicU64,
}

impl Default for Metrics {
    fn default() -> Self {
        let builder = PrometheusBuilder::new();
        // Fails only for an empty bucket list; the summary it falls back to still counts.
        let builder = builder
            .set_buckets_for_metric(Matcher::Full(REQUEST_SECONDS.into()), &LATENCY_BUCKETS)
            .unwrap_or_else(|_| PrometheusBuilder::new());
        let recorder = builder.build_recorder();
        let handle = recorder.handle();
        let m = Metrics {
            recorder,
            handle,
            observed: std::sync::atomic::AtomicU64::new(0),
        };
        m.with(describe);
        m
    }
}

impl Metrics {
    /// Run `f` with this service's recorder as the `metrics` macros' target.
    fn with<T>(&self, f: impl FnOnce() -> T) -> T {
        metrics::with_local_recorder(&self.recorder, f)
    }

    fn observe_request(&self, route: String, seconds: f64) {
        self.with(|| histogram!(REQUEST_SECONDS, "route" => route).record(seconds));
        // The exporter keeps every observed value until its histograms are drained, which
        // a scrape does: a service nobody scrapes would grow by every request it answers
        // (some 16 bytes each: 1.4 GB a day at 1000 requests a second). Draining them here,
        // every so many requests, bounds that whoever scrapes and however often.
        let n = self
            .observed
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if n % UPKEEP_EVERY == UPKEEP_EVERY - 1 {
            self.handle.run_upkeep();
        }
    }
}

fn describe() {
    describe_counter!("driftwatch_cycles_total", "Measurement cycles by outcome.");
    describe_gauge!(
        "driftwatch_solve_seconds_sum",
        "Time spent validating and solving cycles, s (a running total)."
    );
    describe_counter!(
        "driftwatch_machine_faults_total",
        "Steps of a machine loop that failed (a store or recorder error) and were tried again."
    );
    describe_gauge!(
        "driftwatch_machine_failing",
        "1 while a machine loop's steps fail (its store or recorder refuses writes): the NC is \
         served the last stored set, and no new one, until the fault clears."
    );
    describe_gauge!(
        "driftwatch_compensation_version",
        "Version of the compensation set served to the NC (0: none)."
    );
    describe_gauge!("driftwatch_open_alerts", "Alerts open now.");
    describe_gauge!(
        "driftwatch_served_error",
        "Each error of the compensation set served to the NC, in its unit (um or urad)."
    );
    describe_gauge!(
        "driftwatch_served_error_sigma",
        "The standard uncertainty of each served error, in its unit (um or urad)."
    );
    describe_gauge!(
        "driftwatch_served_valid_from_seconds",
        "When the served set became valid, s since the Unix epoch (its age: time() minus this)."
    );
    describe_gauge!(
        "driftwatch_served_measured",
        "1 when the served set was measured by a cycle, 0 when the thermal model predicted it."
    );
    describe_counter!(
        "driftwatch_nc_events_refused_clock_skew_total",
        "NC events refused because their time lay beyond the tolerance from the service clock."
    );
    describe_counter!(
        "driftwatch_nc_stray_detections_total",
        "NC detections of no ordered cycle: counted, not kept."
    );
    describe_counter!(
        "driftwatch_webhook_events_total",
        "Alert events by webhook outcome (retried counts attempts that failed and were retried)."
    );
    describe_histogram!(REQUEST_SECONDS, "Time to answer an HTTP request, by route.");
}

/// Times each request under its route pattern, never the raw path, so that ids make no new
/// series.
pub(super) async fn timed(State(st): State<Shared>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map_or("unmatched", |p| p.as_str())
        .to_string();
    let t0 = std::time::Instant::now();
    let res = next.run(req).await;
    st.metrics
        .observe_request(route, t0.elapsed().as_secs_f64());
    res
}

/// The machine loops' and webhooks' figures as they are now.
fn record_state(st: &super::ApiState) {
    use std::sync::atomic::Ordering::Relaxed;
    let views: Vec<MachineView> = st.machines.values().map(view).collect();
    for v in &views {
        let id = v.id.clone();
        for (status, n) in [
            ("ok", v.cycles.ok),
            ("rejected", v.cycles.rejected),
            ("abandoned", v.cycles.abandoned),
        ] {
            counter!("driftwatch_cycles_total", "machine" => id.clone(), "status" => status)
                .absolute(n);
        }
        gauge!("driftwatch_solve_seconds_sum", "machine" => id.clone())
            .set(v.cycles.solve_seconds_sum);
        counter!("driftwatch_machine_faults_total", "machine" => id.clone())
            .absolute(v.health.faults);
        gauge!("driftwatch_machine_failing", "machine" => id.clone()).set(if v.health.failing {
            1.0
        } else {
            0.0
        });
        gauge!("driftwatch_compensation_version", "machine" => id.clone())
            .set(v.compensation.as_ref().map_or(0.0, |c| c.version as f64));
        gauge!("driftwatch_open_alerts", "machine" => id.clone()).set(v.open_alerts.len() as f64);
        if let Some(c) = &v.compensation {
            for (name, value) in &c.errors {
                let labels = [
                    ("machine", id.clone()),
                    ("error", name.to_string()),
                    ("unit", name.unit().to_string()),
                ];
                gauge!("driftwatch_served_error", &labels).set(*value);
                if let Some(s) = c.sigma.get(name) {
                    gauge!("driftwatch_served_error_sigma", &labels).set(*s);
                }
            }
            gauge!("driftwatch_served_valid_from_seconds", "machine" => id.clone())
                .set(c.valid_from_ns as f64 * 1e-9);
            let measured = matches!(c.source, driftwatch_machine::compensation::Source::Measured);
            gauge!("driftwatch_served_measured", "machine" => id)
                .set(f64::from(u8::from(measured)));
        }
    }
    for (id, h) in &st.machines {
        if let Some(nc) = &h.nc {
            counter!("driftwatch_nc_events_refused_clock_skew_total", "machine" => id.clone())
                .absolute(nc.refused_clock_skew());
            counter!("driftwatch_nc_stray_detections_total", "machine" => id.clone())
                .absolute(nc.stray_detections());
        }
    }
    let w = &st.webhooks;
    for (outcome, n) in [
        ("delivered", &w.delivered),
        ("retried", &w.retried),
        ("failed", &w.failed),
        ("dropped", &w.dropped),
    ] {
        counter!("driftwatch_webhook_events_total", "outcome" => outcome).absolute(n.load(Relaxed));
    }
}

/// Prometheus text: cycles by status, solve time, compensation version, open alerts.
#[utoipa::path(get, path = "/metrics", responses((status = 200, description = "Prometheus text: cycles by outcome, solve time, compensation version, the served set's errors and uncertainties (by machine, error and unit), when it became valid and whether it was measured, open alerts, machine-loop faults, webhook outcomes, request latency by route", body = String, content_type = "text/plain")))]
pub(super) async fn metrics(State(st): State<Shared>) -> Response {
    st.metrics.with(|| record_state(&st));
    let out = st.metrics.handle.render();
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Requests observed with no scrape between, across several drains of the histograms
    /// (and a scrape in the middle of the count): the next scrape counts every one of them
    /// and sums their times, none lost or taken twice by the drains.
    #[test]
    fn drained_request_latencies_are_all_counted_at_the_next_scrape() {
        let m = Metrics::default();
        let route = "/api/v1/machines/{id}/compensation";
        let n = 10 * UPKEEP_EVERY + 17;
        let mut sum = 0.0;
        for i in 0..n {
            let seconds = 1e-4 * (i % 7) as f64;
            sum += seconds;
            m.observe_request(route.into(), seconds);
            if i == n / 2 {
                m.handle.render();
            }
        }
        let text = m.handle.render();
        let line = |what: &str| {
            let head = format!("{REQUEST_SECONDS}_{what}{{route=\"{route}\"}} ");
            text.lines()
                .find_map(|l| l.strip_prefix(&head))
                .unwrap_or_else(|| panic!("no {head} in {text}"))
                .parse::<f64>()
                .unwrap()
        };
        assert_eq!(line("count"), n as f64);
        assert!(
            (line("sum") - sum).abs() < 1e-9,
            "{} against {sum}",
            line("sum")
        );
    }
}
