//! The R-test report as strings: per test the radial, axial and tangential deviations against
//! the turning angle, the radial deviation in polar form (as ISO 10791-6 plots it: a circle
//! of reference radius with the deviation magnified), the figures, and the identification.

use std::fmt::Write as _;

use crate::identify::Identification;
use crate::process::{Figures, Processed};

const W: f64 = 560.0;
const H: f64 = 260.0;
const COLOURS: [(&str, &str); 3] = [
    ("radial", "#1f77b4"),
    ("axial", "#2ca02c"),
    ("tangential", "#d62728"),
];

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Deviations against the turning angle, um.
pub fn deviation_svg(p: &Processed) -> String {
    let series: [Vec<(f64, f64)>; 3] = [
        p.points
            .iter()
            .map(|d| (d.angle_deg, d.radial_um))
            .collect(),
        p.points.iter().map(|d| (d.angle_deg, d.axial_um)).collect(),
        p.points
            .iter()
            .map(|d| (d.angle_deg, d.tangential_um))
            .collect(),
    ];
    let all = series.iter().flatten();
    let (a0, a1) = all.clone().fold((f64::MAX, f64::MIN), |(l, h), (a, _)| {
        (l.min(*a), h.max(*a))
    });
    let lim = all.map(|(_, v)| v.abs()).fold(1.0, f64::max) * 1.1;
    let (l, r, t, b) = (60.0, W - 110.0, 30.0, H - 40.0);
    let x = |a: f64| l + (a - a0) / (a1 - a0).max(1e-9) * (r - l);
    let y = |v: f64| (t + b) / 2.0 - v / lim * (b - t) / 2.0;
    let mut s = format!(
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" font-family="sans-serif" font-size="11">"#
    );
    let _ = write!(
        s,
        r#"<text x="{l}" y="18" font-size="13">{} ({}) — deviation against {} (deg), um</text>"#,
        esc(p.test),
        p.setting.name(),
        esc(&p.axis)
    );
    let _ = write!(
        s,
        r##"<rect x="{l}" y="{t}" width="{}" height="{}" fill="none" stroke="#999"/><line x1="{l}" y1="{y0}" x2="{r}" y2="{y0}" stroke="#ccc"/>"##,
        r - l,
        b - t,
        y0 = y(0.0)
    );
    for v in [-lim / 1.1, lim / 1.1] {
        let _ = write!(
            s,
            r#"<text x="{}" y="{}" text-anchor="end">{v:.2}</text>"#,
            l - 4.0,
            y(v) + 4.0
        );
    }
    let _ = write!(
        s,
        r#"<text x="{l}" y="{}">{a0:.0}</text><text x="{r}" y="{}" text-anchor="end">{a1:.0}</text>"#,
        b + 14.0,
        b + 14.0
    );
    for (k, ((name, colour), pts)) in COLOURS.iter().zip(&series).enumerate() {
        let path: Vec<String> = pts
            .iter()
            .map(|(a, v)| format!("{:.1},{:.1}", x(*a), y(*v)))
            .collect();
        let _ = write!(
            s,
            r#"<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{}"/><text x="{}" y="{}" fill="{colour}">{name}</text>"#,
            path.join(" "),
            r + 8.0,
            t + 14.0 + 16.0 * k as f64
        );
    }
    s.push_str("</svg>");
    s
}

/// The radial deviation in polar form: reference circle plus the deviation magnified.
pub fn polar_svg(p: &Processed) -> String {
    let (cx, cy, r0) = (130.0, 140.0, 80.0);
    let lim = p
        .points
        .iter()
        .map(|d| d.radial_um.abs())
        .fold(0.5, f64::max);
    let k = 40.0 / lim;
    let mut s = format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="260" height="270" font-family="sans-serif" font-size="11"><text x="10" y="16" font-size="13">{} radial (polar)</text><circle cx="{cx}" cy="{cy}" r="{r0}" fill="none" stroke="#ccc"/>"##,
        esc(p.test)
    );
    let pts: Vec<String> = p
        .points
        .iter()
        .map(|d| {
            let a = d.angle_deg.to_radians();
            let r = r0 + k * d.radial_um;
            format!("{:.1},{:.1}", cx + r * a.cos(), cy - r * a.sin())
        })
        .collect();
    let _ = write!(
        s,
        r##"<polyline fill="none" stroke="#1f77b4" stroke-width="1.5" points="{}"/><text x="10" y="262">circle: 0 um; {:.2} um per division of {:.0} px</text></svg>"##,
        pts.join(" "),
        lim,
        40.0
    );
    s
}

fn figures_row(name: &str, f: &Figures) -> String {
    let opt = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.3}"));
    format!(
        "<tr><td>{name}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
        f.range_um,
        f.max_abs_um,
        f.mean_um,
        opt(f.first_harmonic_um),
        opt(f.first_harmonic_peak_deg),
        opt(f.reversal_um)
    )
}

/// The whole report as one HTML page.
pub fn html(machine: &str, tests: &[Processed], id: Option<&Identification>) -> String {
    let mut s = format!(
        "<!doctype html><meta charset=utf-8><title>R-test {m}</title><body style=\"font-family:sans-serif;max-width:1000px\"><h1>R-test report: {m}</h1>",
        m = esc(machine)
    );
    s.push_str(
        "<p>Deviation of the spindle-side object's centre from the table-side object's, in \
         the directions of the turning axis (ISO 10791-6): radial from the axis to the ball, \
         axial along it, tangential their cross product. um.</p>",
    );
    for p in tests {
        let _ = write!(
            s,
            "<h2>{} — {} setting, turning {}</h2><p>Sensitivity: {}</p>{}{}<table border=1 cellpadding=3><tr><th></th><th>range</th><th>max |dev|</th><th>mean</th><th>once per rev.</th><th>its peak, deg</th><th>reversal</th></tr>{}{}{}</table>",
            esc(p.test),
            p.setting.name(),
            esc(&p.axis),
            esc(&p.calibration),
            deviation_svg(p),
            polar_svg(p),
            figures_row("radial", &p.radial),
            figures_row("axial", &p.axial),
            figures_row("tangential", &p.tangential)
        );
    }
    if let Some(id) = id {
        let _ = write!(
            s,
            "<h2>Location errors (apparent: relative to the spindle-side object)</h2><table border=1 cellpadding=3><tr><th>error</th><th>value</th><th>u (k=1)</th><th>unit</th></tr>"
        );
        for (n, e) in &id.errors {
            let _ = write!(
                s,
                "<tr><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{}</td></tr>",
                esc(n),
                e.value,
                e.sigma,
                e.unit
            );
        }
        let _ = write!(
            s,
            "</table><p>{} readings; chi-square {:.1} on {} degrees of freedom (Birge ratio {:.2}); residual RMS {:.3} um.</p>",
            id.n_readings, id.chi2, id.dof, id.birge, id.residual_rms_um
        );
        for n in &id.not_identifiable {
            let _ = write!(s, "<p>Not identifiable: {}</p>", esc(n));
        }
    }
    s.push_str("</body>");
    s
}
