//! The diagnosis as a self-contained HTML page with SVG plots (pure: a string out).

use driftwatch_core::units;
use plotters::prelude::*;

use crate::cycles::Diagnosis;

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

type Points = Vec<(f64, f64)>;

/// A scatter plot of some point series, as SVG.
fn scatter(title: &str, x: &str, y: &str, series: &[(&str, RGBColor, Points)]) -> String {
    let mut buf = String::new();
    let drawn = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut buf, (900, 320)).into_drawing_area();
        root.fill(&WHITE)?;
        let all = series.iter().flat_map(|s| s.2.iter());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for (a, b) in all {
            x0 = x0.min(*a);
            x1 = x1.max(*a);
            y0 = y0.min(*b);
            y1 = y1.max(*b);
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, -1.0, 1.0);
        }
        let px = 0.02 * (x1 - x0).max(1e-9);
        let py = 0.05 * (y1 - y0).max(1e-9);
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(8)
            .x_label_area_size(32)
            .y_label_area_size(55)
            .build_cartesian_2d((x0 - px)..(x1 + px), (y0 - py)..(y1 + py))?;
        chart.configure_mesh().x_desc(x).y_desc(y).draw()?;
        for (label, color, pts) in series {
            let c = *color;
            chart
                .draw_series(pts.iter().map(|p| Circle::new(*p, 1, c.filled())))?
                .label(*label)
                .legend(move |(x, y)| Circle::new((x + 8, y), 3, c.filled()));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
        Ok(())
    })();
    match drawn {
        Ok(()) => buf,
        Err(e) => format!("<p>(plot not drawn: {})</p>", esc(&e.to_string())),
    }
}

fn f(v: f64) -> String {
    format!("{v:.3}")
}

/// The report: what was found in words, the figures before and after, the plots.
pub fn html(d: &Diagnosis, title: &str) -> String {
    let mut h = String::new();
    intro(&mut h, d, title);
    found(&mut h, d);
    fit_tables(&mut h, d);
    plots(&mut h, d);
    channels_and_refused(&mut h, d);
    h.push_str("</body></html>\n");
    h
}

/// The page's head and what was read.
fn intro(h: &mut String, d: &Diagnosis, title: &str) {
    h.push_str(&format!(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{t}</title><style>body{{font-family:sans-serif;max-width:1000px;margin:auto}}table{{border-collapse:collapse}}td,th{{border:1px solid #bbb;padding:2px 6px;font-size:13px}}</style></head><body><h1>{t}</h1>",
        t = esc(title)
    ));
    h.push_str(&format!(
        "<p>{} readings in {} cycles over {:.1} h, one-reading sigma {} um; the last of {} held-out blocks is the held-out part. Redundancy sigma (no thermal model): {}.</p>",
        d.readings,
        d.cycles,
        d.span_h,
        d.sigma_um,
        d.blocks.len(),
        d.redundancy
            .sigma_um
            .map_or("not estimated (under 20 cycles)".into(), |s| format!("{s:.3} um"))
    ));
}

/// What was found: the accepted terms, what is not identifiable, what stays unexplained.
fn found(h: &mut String, d: &Diagnosis) {
    h.push_str("<h2>What was found</h2>");
    if d.accepted.is_empty() {
        h.push_str("<p>No effect of the library passed the rules (delta-BIC &ge; 10, |t| &ge; 4, a better held-out fit in 2/3 of the blocks, a plausible size).</p>");
    }
    for a in &d.accepted {
        h.push_str(&format!(
            "<p><b>{}</b>. {}{}</p>",
            if a.named {
                esc(&a.label)
            } else {
                format!("Not named ({} or its ambiguity group)", esc(&a.label))
            },
            esc(&a.statement),
            a.ambiguity_group
                .iter()
                .map(|g| format!(
                    "<br>&ndash; {} {}: {}",
                    esc(&g.effect),
                    esc(&g.term),
                    esc(&g.reason)
                ))
                .collect::<String>()
        ));
    }
    for n in &d.not_identifiable {
        h.push_str(&format!(
            "<p><b>Not identifiable with this plan: {}</b>. {}. To split it: {}.</p>",
            esc(&n.label),
            esc(&n.reason),
            esc(&n.split_by)
        ));
    }
    for u in &d.unexplained {
        h.push_str(&format!(
            "<p><b>Unexplained</b>: chi2/dof {} after the search, Ljung-Box p {:.2e} on {} ({:.2e} over the {} channels tested); a discrepancy of {} um RMS beyond the noise. Where: {}.</p>",
            f(u.chi2_dof),
            u.ljung_box_p,
            esc(&u.channel),
            u.ljung_box_p_channels,
            u.channels_tested,
            f(u.discrepancy_um),
            esc(&u
                .located
                .iter()
                .map(|m| format!("{} {} ({:+.2} um, t {:.1})", m.by, m.group, m.mean_um, m.t))
                .collect::<Vec<_>>()
                .join("; "))
        ));
        if let Some(p) = &u.periodic {
            h.push_str(&format!(
                "<p><b>Unexplained periodic residual</b>: {}</p>",
                esc(&p.statement)
            ));
        }
    }
}

/// The fit before and after, the accepted terms' figures and where the baseline misses.
fn fit_tables(h: &mut String, d: &Diagnosis) {
    h.push_str("<h2>Fit before and after</h2><table><tr><th></th><th>parameters</th><th>chi2/dof</th><th>RMS training (um)</th><th>RMS held-out (um)</th></tr>");
    for (name, x) in [
        ("baseline", &d.baseline),
        ("with the accepted terms", &d.final_fit),
    ] {
        h.push_str(&format!(
            "<tr><td>{name}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            x.parameters,
            f(x.chi2_dof),
            f(x.rms_train_um),
            f(x.rms_heldout_um)
        ));
    }
    h.push_str("</table>");
    if d.baseline.heldout_extrapolates {
        h.push_str("<p><b>Note</b>: the held-out block holds spindle history the training part never saw (under two days of data); its RMS measures extrapolation, not the fit.</p>");
    }
    if !d.accepted.is_empty() {
        h.push_str("<h2>Accepted terms</h2><table><tr><th>effect</th><th>term</th><th>parameters</th><th>delta-BIC</th><th>|t|</th><th>held-out RMS before / after (um)</th><th>blocks better</th><th>named</th><th>ambiguity group</th></tr>");
        for a in &d.accepted {
            h.push_str(&format!(
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:.0}</td><td>{:.1}</td><td>{} / {}</td><td>{} of {}</td><td>{}</td><td>{}</td></tr>",
                esc(&a.effect),
                esc(&a.term),
                a.parameters
                    .iter()
                    .map(|p| format!("{:.4} &plusmn; {:.4} {}", p.value, p.sigma, esc(&p.unit)))
                    .collect::<Vec<_>>()
                    .join("<br>"),
                a.delta_bic,
                a.t,
                f(a.heldout_rms_before_um),
                f(a.heldout_rms_after_um),
                a.blocks_improved,
                a.blocks,
                if a.named { "yes" } else { "no" },
                esc(&a
                    .ambiguity_group
                    .iter()
                    .map(|g| format!("{} {} (cos {:.2}, delta-chi2 {:.1})", g.effect, g.term, g.cos, g.delta_chi2))
                    .collect::<Vec<_>>()
                    .join("; "))
            ));
        }
        h.push_str("</table>");
    }
    if !d.located.is_empty() {
        h.push_str("<h2>Where the baseline misses</h2><table><tr><th>by</th><th>group</th><th>readings</th><th>mean residual (um)</th><th>t</th></tr>");
        for m in d.located.iter().take(20) {
            h.push_str(&format!(
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:+.3}</td><td>{:.1}</td></tr>",
                esc(&m.by),
                esc(&m.group),
                m.n,
                m.mean_um,
                m.t
            ));
        }
        h.push_str("</table>");
    }
}

/// The residuals against time, each accepted term's footprint, the per-cycle redundancy.
fn plots(h: &mut String, d: &Diagnosis) {
    let s = &d.series;
    let t0 = s.t_ns.iter().copied().min().unwrap_or(0);
    let hours = |i: usize| units::ns_to_h(s.t_ns[i] - t0);
    let pts = |v: &[f64]| -> Points { (0..v.len()).map(|i| (hours(i), v[i])).collect() };
    h.push_str("<h2>Residuals against time</h2>");
    h.push_str(&scatter(
        "residual of every reading",
        "hours since the first reading",
        "residual [um]",
        &[
            ("baseline", RGBColor(200, 60, 60), pts(&s.baseline_um)),
            (
                "with the accepted terms",
                RGBColor(40, 80, 200),
                pts(&s.final_um),
            ),
        ],
    ));
    for (term, foot) in &s.footprints {
        h.push_str(&format!("<h3>{}</h3>", esc(term)));
        h.push_str(&scatter(
            "signature: the term's footprint on every reading",
            "hours since the first reading",
            "footprint [um]",
            &[("footprint", RGBColor(40, 140, 60), pts(foot))],
        ));
        let vs: Points = foot
            .iter()
            .zip(&s.baseline_um)
            .map(|(a, b)| (*a, *b))
            .collect();
        h.push_str(&scatter(
            "baseline residual against the term (its driver times its signature)",
            "footprint [um]",
            "baseline residual [um]",
            &[("readings", RGBColor(120, 60, 160), vs)],
        ));
    }
    let r: Points = d
        .redundancy
        .cycles
        .iter()
        .map(|(_, t, c)| (units::ns_to_h(t - t0), *c))
        .collect();
    h.push_str(&format!(
        "<h2>Per-cycle redundancy chi-square ({} dof; alarms at the 0.999 quantile: {})</h2>",
        d.redundancy.dof,
        d.redundancy.alarms.len()
    ));
    h.push_str(&scatter(
        "free of every location error",
        "hours since the first reading",
        "chi-square",
        &[("cycles", RGBColor(90, 90, 90), r)],
    ));
}

/// Per channel before and after, the strong candidates refused, what was not tried.
fn channels_and_refused(h: &mut String, d: &Diagnosis) {
    h.push_str("<h2>Per channel</h2><table><tr><th>channel</th><th>n</th><th>chi2/dof before / after</th><th>RMS training before / after (um)</th><th>RMS held-out before / after (um)</th></tr>");
    for c in &d.channels {
        h.push_str(&format!(
            "<tr><td>{}</td><td>{}</td><td>{} / {}</td><td>{} / {}</td><td>{} / {}</td></tr>",
            esc(&c.channel),
            c.n,
            f(c.chi2_dof_before),
            f(c.chi2_dof_after),
            f(c.rms_train_before_um),
            f(c.rms_train_after_um),
            f(c.rms_heldout_before_um),
            f(c.rms_heldout_after_um)
        ));
    }
    h.push_str("</table>");
    if !d.refused.is_empty() {
        h.push_str("<h2>Strong candidates refused</h2><ul>");
        for r in &d.refused {
            h.push_str(&format!(
                "<li>{}: {} (delta-BIC {:.0}, |t| {:.1}): {}</li>",
                esc(&r.effect),
                esc(&r.term),
                r.delta_bic,
                r.t,
                esc(&r.reason)
            ));
        }
        h.push_str("</ul>");
    }
    if !d.not_tested.is_empty() {
        h.push_str(&format!(
            "<p>{} slow or daily candidates were not tried: they need two days of data.</p>",
            d.not_tested.len()
        ));
    }
}

/// The report of a displacement diagnosis: statements, figures per channel, each channel's
/// measurement against the baseline and the final model, and the residuals before and after.
pub fn displacement_html(d: &crate::displacement::DisplacementDiagnosis, title: &str) -> String {
    let mut h = String::new();
    h.push_str(&format!(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{t}</title><style>body{{font-family:sans-serif;max-width:1000px;margin:auto}}table{{border-collapse:collapse}}td,th{{border:1px solid #bbb;padding:2px 6px;font-size:13px}}</style></head><body><h1>{t}</h1>",
        t = esc(title)
    ));
    h.push_str(&format!(
        "<p>{} displacement channels over {:.1} h, {} logged temperatures. Baseline: one thermal mode of the spindle heat input per channel. Everything is fitted on 0-{:.1} h; the rest is held out.</p>",
        d.channels.len(),
        d.span_h,
        d.sensors.len(),
        d.heldout_from_h
    ));
    h.push_str("<h2>What was found</h2>");
    for c in &d.channels {
        for s in &c.statements {
            h.push_str(&format!("<p>{}</p>", esc(s)));
        }
    }
    h.push_str("<h2>Fit before and after</h2><table><tr><th>channel</th><th>baseline mode</th><th>terms</th><th>RMS training (um)</th><th>RMS held-out (um)</th></tr>");
    for c in &d.channels {
        h.push_str(&format!(
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{} &rarr; {}</td><td>{} &rarr; {}</td></tr>",
            esc(&c.channel),
            match &c.baseline_mode {
                Some(m) => format!("{} min, {:.2} um", m.tau_min, m.gain_um),
                None => "offset alone (no spindle log)".into(),
            },
            c.accepted.len(),
            f(c.baseline.rms_train_um),
            f(c.final_fit.rms_train_um),
            f(c.baseline.rms_heldout_um),
            f(c.final_fit.rms_heldout_um)
        ));
    }
    h.push_str("</table><h2>Accepted terms</h2><table><tr><th>channel</th><th>effect</th><th>term</th><th>value</th><th>delta-BIC</th><th>t</th><th>held-out before &rarr; after (um)</th><th>ambiguous with</th></tr>");
    for c in &d.channels {
        for t in &c.accepted {
            h.push_str(&format!(
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{} &plusmn; {} {}</td><td>{:.1}</td><td>{:.1}</td><td>{} &rarr; {}</td><td>{}</td></tr>",
                esc(&c.channel),
                t.effect,
                esc(&t.term),
                f(t.value),
                f(t.sigma),
                esc(t.unit),
                t.delta_bic,
                t.t,
                f(t.heldout_before_um),
                f(t.heldout_after_um),
                esc(&t.ambiguous_with.join(", "))
            ));
        }
    }
    h.push_str("</table>");
    located_table(&mut h, d);
    for c in &d.channels {
        let s = &c.series;
        let pts = |v: &[f64]| -> Points { s.t_h.iter().copied().zip(v.iter().copied()).collect() };
        h.push_str(&format!("<h2>{}</h2>", esc(&c.channel)));
        h.push_str(&scatter(
            &format!(
                "{}: measured and models (held out from {:.1} h)",
                c.channel, d.heldout_from_h
            ),
            "time (h)",
            "um",
            &[
                ("measured", BLACK, pts(&s.y_um)),
                ("baseline", RED, pts(&s.baseline_um)),
                ("with the accepted terms", BLUE, pts(&s.final_um)),
            ],
        ));
        let res = |m: &[f64]| -> Vec<f64> { s.y_um.iter().zip(m).map(|(a, b)| a - b).collect() };
        h.push_str(&scatter(
            &format!("{}: residual", c.channel),
            "time (h)",
            "um",
            &[
                ("baseline", RED, pts(&res(&s.baseline_um))),
                ("with the accepted terms", BLUE, pts(&res(&s.final_um))),
            ],
        ));
    }
    h.push_str("</body></html>");
    h
}

/// The located terms: what the forward selection left, tied to a temperature and modelled,
/// with the held-out end before and after and the verdict.
fn located_table(h: &mut String, d: &crate::displacement::DisplacementDiagnosis) {
    let located: Vec<_> = d
        .channels
        .iter()
        .flat_map(|c| {
            c.located_term
                .iter()
                .chain(&c.late_term)
                .map(move |l| (c, l))
        })
        .collect();
    if located.is_empty() {
        return;
    }
    h.push_str("<h2>Located and modelled</h2><p>What the accepted terms leave, located (an onset and the temperature it follows, on the training part) and fitted as one more term of the model, judged by the same rules; accepted, it is part of the final model above.</p><table><tr><th>channel</th><th>term</th><th>gain (um/K)</th><th>delta-BIC (bar)</th><th>t</th><th>rolling origins</th><th>held-out before &rarr; after (um)</th><th>verdict</th><th>what would split it</th></tr>");
    for (c, l) in located {
        let verdict = match l.reason {
            None => "accepted".to_string(),
            Some(r) => format!(
                "not confirmed: {}{}",
                r.words(),
                l.rule
                    .as_ref()
                    .map(|r| format!(" ({r})"))
                    .unwrap_or_default()
            ),
        };
        h.push_str(&format!(
            "<tr><td>{}</td><td>{}</td><td>{} &plusmn; {}</td><td>{:.1} ({:.1})</td><td>{:.1}</td><td>{} of {}</td><td>{} &rarr; {}</td><td>{}</td><td>{}</td></tr>",
            esc(&c.channel),
            esc(&l.term),
            f(l.gain_um_per_k),
            f(l.sigma_um_per_k),
            l.delta_bic,
            l.bar,
            l.t,
            l.blocks_improved,
            l.blocks,
            f(l.heldout_before_um),
            f(l.heldout_after_um),
            esc(&verdict),
            esc(l.split_by.as_deref().unwrap_or(""))
        ));
    }
    h.push_str("</table>");
}
