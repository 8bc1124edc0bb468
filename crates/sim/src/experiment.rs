//! The patent experiment end to end: simulate the schedule of the patent, solve every cycle
//! truth-free, and set the identified errors next to the truth at each cycle's reference
//! time. Returns tables and an SVG plot as strings; writing them is the caller's business.

use driftwatch_core::units;
use std::collections::BTreeMap;
use std::fmt::Write as _;

use plotters::prelude::*;
use serde::Serialize;

use crate::scenario::Scenario;
use crate::simulator::{SimError, Simulation, simulate};
use driftwatch_core::cycle::{CycleChecks, CycleOutcome, process_all};
use driftwatch_core::error_name::ErrorName;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::Plan;

#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub cycle: i64,
    /// Reference time, min from the scenario start.
    pub t_min: f64,
    pub ok: bool,
    pub reason: Option<String>,
    /// name -> (identified, sigma, truth)
    pub values: BTreeMap<String, (f64, f64, f64)>,
}

/// The patent's three figures on any machine: the tilting axis' second identified position
/// error (EZ0B on the patent's machine) and its first (EX0B), each family's own names.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// The error the patent reports rising about 80 um and dropping 45 um (identify[1]).
    pub main: String,
    /// Identified `main` at the last cycle before the stop minus at the first cycle, um.
    pub main_rise_um: f64,
    /// Identified `main` at the last cycle before the stop minus 30 min after it, um.
    pub main_drop_um: f64,
    /// The error the patent reports rising about 20 um (identify[0]).
    pub second: String,
    pub second_rise_um: f64,
    /// Largest |identified - truth| / sigma over every error of every cycle.
    pub max_abs_z: f64,
    pub cycles_ok: usize,
    pub cycles: usize,
}

pub struct Experiment {
    pub simulation: Simulation,
    pub outcomes: Vec<CycleOutcome>,
    pub rows: Vec<Row>,
    pub summary: Summary,
}

/// Run a scenario and solve its cycles. `stop_min` is when the spindle stops (210 in the
/// patent); the summary compares the cycles at 0, `stop_min` and `stop_min + 30`.
pub fn run(
    scn: &Scenario,
    k: &Kinematics,
    plan: &Plan,
    checks: &CycleChecks,
    stop_min: f64,
) -> Result<Experiment, SimError> {
    let simulation = simulate(scn, k, plan)?;
    let detections = simulation.detection_stream();
    let (outcomes, _) = process_all(k, &detections, checks);
    let start = scn.start_ns();
    let mut rows = Vec::new();
    for (o, c) in outcomes.iter().zip(&simulation.cycles) {
        let mut values = BTreeMap::new();
        if let Some(s) = &o.solution {
            for e in &s.errors {
                let truth = c.truth.apparent.get(&e.name).copied().unwrap_or(f64::NAN);
                values.insert(e.name.clone(), (e.value, e.sigma, truth));
            }
        }
        rows.push(Row {
            cycle: o.cycle,
            t_min: units::ns_to_min(o.t_ref_ns - start),
            ok: o.is_ok(),
            reason: o.reason.clone(),
            values,
        });
    }
    let starts: Vec<f64> = simulation
        .cycles
        .iter()
        .map(|c| units::ns_to_min(c.start_ns - start))
        .collect();
    let nearest = |t: f64| {
        starts
            .iter()
            .enumerate()
            .min_by(|a, b| (a.1 - t).abs().total_cmp(&(b.1 - t).abs()))
            .map(|(i, _)| i)
    };
    let value = |i: Option<usize>, name: &str| {
        i.and_then(|i| rows.get(i))
            .and_then(|r| r.values.get(name))
            .map(|v| v.0)
            .unwrap_or(f64::NAN)
    };
    let (c0, cs, c30) = (nearest(0.0), nearest(stop_min), nearest(stop_min + 30.0));
    let max_abs_z = rows
        .iter()
        .flat_map(|r| r.values.values())
        .map(|(v, s, t)| ((v - t) / s).abs())
        .fold(0.0, f64::max);
    let names = k.identify_names();
    let name = |i: usize| names.get(i).cloned().unwrap_or_default();
    let (main, second) = (name(1), name(0));
    let summary = Summary {
        main_rise_um: value(cs, &main) - value(c0, &main),
        main_drop_um: value(cs, &main) - value(c30, &main),
        second_rise_um: value(cs, &second) - value(c0, &second),
        main,
        second,
        max_abs_z,
        cycles_ok: rows.iter().filter(|r| r.ok).count(),
        cycles: rows.len(),
    };
    Ok(Experiment {
        simulation,
        outcomes,
        rows,
        summary,
    })
}

impl Experiment {
    pub fn names(&self) -> Vec<String> {
        self.rows
            .iter()
            .find(|r| r.ok)
            .map(|r| r.values.keys().cloned().collect())
            .unwrap_or_default()
    }

    /// One record per cycle, written to `out`: identified, sigma and truth of each error, and
    /// the reason a cycle was rejected (quoted by the csv crate where it needs to be).
    pub fn write_csv<W: std::io::Write>(&self, out: W) -> Result<(), csv::Error> {
        let names = self.names();
        let mut w = csv::Writer::from_writer(out);
        let mut header = vec!["cycle".to_string(), "t_min".into(), "status".into()];
        for n in &names {
            header.extend([n.clone(), format!("{n}_sigma"), format!("{n}_truth")]);
        }
        header.push("reason".into());
        w.write_record(&header)?;
        for r in &self.rows {
            let status = if r.ok { "ok" } else { "rejected" };
            let mut rec = vec![
                r.cycle.to_string(),
                format!("{:.3}", r.t_min),
                status.into(),
            ];
            for n in &names {
                match r.values.get(n) {
                    Some((v, s, t)) => {
                        rec.extend([format!("{v:.4}"), format!("{s:.4}"), format!("{t:.4}")])
                    }
                    None => rec.extend([String::new(), String::new(), String::new()]),
                }
            }
            rec.push(r.reason.clone().unwrap_or_default());
            w.write_record(&rec)?;
        }
        w.flush()?;
        Ok(())
    }

    /// A table for people.
    pub fn table(&self) -> String {
        let names = self.names();
        let mut out = String::new();
        let _ = write!(out, "{:>5} {:>8}", "cycle", "t/min");
        for n in &names {
            let unit = driftwatch_core::error_name::channel_unit(n);
            let _ = write!(out, " {:>24}", format!("{n} id/truth [{unit}]"));
        }
        out.push('\n');
        for r in &self.rows {
            let _ = write!(out, "{:>5} {:>8.1}", r.cycle, r.t_min);
            if !r.ok {
                let _ = writeln!(out, " rejected: {}", r.reason.clone().unwrap_or_default());
                continue;
            }
            for n in &names {
                let (v, s, t) = r.values[n];
                let _ = write!(out, " {:>24}", format!("{v:8.2}+-{s:.2} / {t:8.2}"));
            }
            out.push('\n');
        }
        out
    }

    /// Identified values with 2-sigma bars against the truth curve, positions and orientations.
    pub fn svg(&self, title: &str) -> Result<String, String> {
        let mut buf = String::new();
        {
            let root = SVGBackend::with_string(&mut buf, (1000, 760)).into_drawing_area();
            root.fill(&WHITE).map_err(|e| e.to_string())?;
            let root = root
                .titled(title, ("sans-serif", 18))
                .map_err(|e| e.to_string())?;
            let panels = root.split_evenly((2, 1));
            let start = self.simulation.truth.first().map(|t| t.t_ns).unwrap_or(0);
            // The identified errors by kind, as the rows name them.
            let names = self.names();
            let (angular, linear): (Vec<&str>, Vec<&str>) = names
                .iter()
                .map(|n| n.as_str())
                .partition(|n| ErrorName::parse(n).is_ok_and(|e| e.is_angular()));
            let groups: [(&str, &[&str]); 2] = [
                ("position errors [um]", &linear),
                ("orientation errors [urad]", &angular),
            ];
            let colors = [RED, BLUE, GREEN, MAGENTA];
            for (panel, (ylabel, names)) in panels.iter().zip(groups) {
                let mut lo = f64::INFINITY;
                let mut hi = f64::NEG_INFINITY;
                for t in &self.simulation.truth {
                    for n in names {
                        if let Some(v) = t.apparent.get(*n) {
                            lo = lo.min(*v);
                            hi = hi.max(*v);
                        }
                    }
                }
                for r in &self.rows {
                    for n in names {
                        if let Some((v, s, _)) = r.values.get(*n) {
                            lo = lo.min(v - 2.0 * s);
                            hi = hi.max(v + 2.0 * s);
                        }
                    }
                }
                if !lo.is_finite() {
                    lo = -1.0;
                    hi = 1.0;
                }
                let pad = 0.05 * (hi - lo).max(1.0);
                let t_end = self
                    .simulation
                    .truth
                    .last()
                    .map(|t| units::ns_to_min(t.t_ns - start))
                    .unwrap_or(1.0);
                let mut chart = ChartBuilder::on(panel)
                    .margin(10)
                    .x_label_area_size(35)
                    .y_label_area_size(55)
                    .build_cartesian_2d(0.0..t_end.max(1.0), (lo - pad)..(hi + pad))
                    .map_err(|e| e.to_string())?;
                chart
                    .configure_mesh()
                    .x_desc("time [min]")
                    .y_desc(ylabel)
                    .draw()
                    .map_err(|e| e.to_string())?;
                for (n, color) in names.iter().zip(colors) {
                    let truth: Vec<(f64, f64)> = self
                        .simulation
                        .truth
                        .iter()
                        .filter_map(|t| {
                            t.apparent
                                .get(*n)
                                .map(|v| (units::ns_to_min(t.t_ns - start), *v))
                        })
                        .collect();
                    chart
                        .draw_series(LineSeries::new(truth, color.stroke_width(1)))
                        .map_err(|e| e.to_string())?
                        .label(format!("{n} truth / identified"))
                        .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color));
                    let pts: Vec<(f64, f64, f64)> = self
                        .rows
                        .iter()
                        .filter_map(|r| r.values.get(*n).map(|(v, s, _)| (r.t_min, *v, *s)))
                        .collect();
                    chart
                        .draw_series(pts.iter().map(|(t, v, s)| {
                            ErrorBar::new_vertical(
                                *t,
                                v - 2.0 * s,
                                *v,
                                v + 2.0 * s,
                                color.filled(),
                                6,
                            )
                        }))
                        .map_err(|e| e.to_string())?;
                    chart
                        .draw_series(
                            pts.iter()
                                .map(|(t, v, _)| Circle::new((*t, *v), 3, color.filled())),
                        )
                        .map_err(|e| e.to_string())?;
                }
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::UpperLeft)
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .draw()
                    .map_err(|e| e.to_string())?;
            }
            root.present().map_err(|e| e.to_string())?;
        }
        Ok(buf)
    }
}
