//! `/metrics` (Prometheus text) and the request-latency histograms behind it.

use std::collections::BTreeMap;
use std::sync::Mutex;

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{Shared, view};
use crate::daemon::MachineView;

/// Upper bounds of the request-latency histogram, seconds.
const LATENCY_BUCKETS: [f64; 12] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5,
];

/// Request latency per route (the route pattern, never the raw path, so ids do not make
/// new series): cumulative bucket counts, count and sum as Prometheus histograms want them.
#[derive(Default)]
pub struct RequestLatency {
    routes: Mutex<BTreeMap<String, LatencyHistogram>>,
}

#[derive(Default, Clone)]
pub(super) struct LatencyHistogram {
    buckets: [u64; LATENCY_BUCKETS.len()],
    count: u64,
    sum: f64,
}

impl RequestLatency {
    fn observe(&self, route: &str, seconds: f64) {
        if let Ok(mut m) = self.routes.lock() {
            let h = match m.get_mut(route) {
                Some(h) => h,
                None => m.entry(route.to_string()).or_default(),
            };
            for (b, le) in h.buckets.iter_mut().zip(LATENCY_BUCKETS) {
                if seconds <= le {
                    *b += 1;
                }
            }
            h.count += 1;
            h.sum += seconds;
        }
    }

    fn render(&self, out: &mut String) {
        let name = "driftwatch_http_request_duration_seconds";
        out.push_str(&format!(
            "# HELP {name} Time to answer an HTTP request, by route.\n# TYPE {name} histogram\n"
        ));
        let routes = match self.routes.lock() {
            Ok(m) => m.clone(),
            Err(_) => return,
        };
        for (route, h) in routes {
            for (n, le) in h.buckets.iter().zip(LATENCY_BUCKETS) {
                out.push_str(&format!(
                    "{name}_bucket{{route=\"{route}\",le=\"{le}\"}} {n}\n"
                ));
            }
            out.push_str(&format!(
                "{name}_bucket{{route=\"{route}\",le=\"+Inf\"}} {c}\n{name}_sum{{route=\"{route}\"}} {s}\n{name}_count{{route=\"{route}\"}} {c}\n",
                c = h.count,
                s = h.sum
            ));
        }
    }
}

pub(super) async fn timed(State(st): State<Shared>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map_or("unmatched", |p| p.as_str())
        .to_string();
    let t0 = std::time::Instant::now();
    let res = next.run(req).await;
    st.latency.observe(&route, t0.elapsed().as_secs_f64());
    res
}

/// Prometheus text: cycles by status, solve time, compensation version, open alerts.
#[utoipa::path(get, path = "/metrics", responses((status = 200, description = "Prometheus text: cycles by outcome, solve time, compensation version, open alerts, machine-loop faults, webhook outcomes, request latency by route", body = String, content_type = "text/plain")))]
pub(super) async fn metrics(State(st): State<Shared>) -> Response {
    let mut out = String::new();
    let mut metric = |name: &str, kind: &str, help: &str, rows: Vec<(String, f64)>| {
        out.push_str(&format!("# HELP {name} {help}\n# TYPE {name} {kind}\n"));
        for (labels, v) in rows {
            out.push_str(&format!("{name}{{{labels}}} {v}\n"));
        }
    };
    let views: Vec<MachineView> = st.machines.values().map(view).collect();
    let per = |f: &dyn Fn(&MachineView) -> f64| -> Vec<(String, f64)> {
        views
            .iter()
            .map(|v| (format!("machine=\"{}\"", v.id), f(v)))
            .collect()
    };
    let mut cycles = Vec::new();
    for v in &views {
        for (status, n) in [
            ("ok", v.cycles_ok),
            ("rejected", v.cycles_rejected),
            ("abandoned", v.cycles_abandoned),
        ] {
            cycles.push((
                format!("machine=\"{}\",status=\"{status}\"", v.id),
                n as f64,
            ));
        }
    }
    metric(
        "driftwatch_cycles_total",
        "counter",
        "Measurement cycles by outcome.",
        cycles,
    );
    metric(
        "driftwatch_solve_seconds_sum",
        "counter",
        "Time spent validating and solving cycles.",
        per(&|v| v.solve_seconds_sum),
    );
    metric(
        "driftwatch_machine_faults_total",
        "counter",
        "Steps of a machine loop that failed (a store or recorder error) and were tried again.",
        per(&|v| v.faults as f64),
    );
    metric(
        "driftwatch_compensation_version",
        "gauge",
        "Version of the compensation set served to the NC (0: none).",
        per(&|v| v.compensation.as_ref().map_or(0.0, |c| c.version as f64)),
    );
    metric(
        "driftwatch_open_alerts",
        "gauge",
        "Alerts open now.",
        per(&|v| v.open_alerts.len() as f64),
    );
    metric(
        "driftwatch_nc_events_refused_clock_skew_total",
        "counter",
        "NC events refused because their time lay beyond the tolerance from the service clock.",
        st.machines
            .iter()
            .filter_map(|(id, h)| {
                let n = h.nc.as_ref()?.refused_clock_skew();
                Some((format!("machine=\"{id}\""), n as f64))
            })
            .collect(),
    );
    metric(
        "driftwatch_nc_stray_detections_total",
        "counter",
        "NC detections of no ordered cycle: counted, not kept.",
        st.machines
            .iter()
            .filter_map(|(id, h)| {
                let n = h.nc.as_ref()?.stray_detections();
                Some((format!("machine=\"{id}\""), n as f64))
            })
            .collect(),
    );
    use std::sync::atomic::Ordering::Relaxed;
    let w = &st.webhooks;
    metric(
        "driftwatch_webhook_events_total",
        "counter",
        "Alert events by webhook outcome (retried counts attempts that failed and were retried).",
        [
            ("delivered", &w.delivered),
            ("retried", &w.retried),
            ("failed", &w.failed),
            ("dropped", &w.dropped),
        ]
        .into_iter()
        .map(|(k, n)| (format!("outcome=\"{k}\""), n.load(Relaxed) as f64))
        .collect(),
    );
    st.latency.render(&mut out);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}
