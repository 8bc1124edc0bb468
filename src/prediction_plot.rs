//! `predict --plot`: measured and predicted values of each channel, the prediction's band and
//! where the updates stop, as one SVG (pure: a string out).

use plotters::prelude::*;

/// One channel's panel; times in h from the recording's start.
#[derive(Debug, Clone, Default)]
pub struct Panel {
    pub channel: String,
    /// What served it (grey box, arx, ...).
    pub source: String,
    pub unit: String,
    pub measured: Vec<(f64, f64)>,
    /// Time, value and the half-width of the band drawn (one sigma or the 68 % band).
    pub predicted: Vec<(f64, f64, f64)>,
    /// Where corrections stop and the prediction runs alone.
    pub boundary_h: Option<f64>,
}

/// Every panel stacked, 900 px wide and 260 px per channel.
pub fn svg(panels: &[Panel]) -> Result<String, String> {
    let mut buf = String::new();
    {
        let h = 260 * panels.len().max(1) as u32;
        let root = SVGBackend::with_string(&mut buf, (900, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        for (area, p) in root
            .split_evenly((panels.len().max(1), 1))
            .iter()
            .zip(panels)
        {
            draw(area, p).map_err(|e| format!("{}: {e}", p.channel))?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(buf)
}

fn draw(
    area: &DrawingArea<SVGBackend, plotters::coord::Shift>,
    p: &Panel,
) -> Result<(), Box<dyn std::error::Error>> {
    let xs = p
        .measured
        .iter()
        .map(|m| m.0)
        .chain(p.predicted.iter().map(|q| q.0));
    let ys = p
        .measured
        .iter()
        .map(|m| m.1)
        .chain(p.predicted.iter().flat_map(|q| [q.1 - q.2, q.1 + q.2]))
        .filter(|v| v.is_finite());
    let (x0, x1) = xs.fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)));
    let (y0, y1) = ys.fold((f64::MAX, f64::MIN), |(a, b), y| (a.min(y), b.max(y)));
    let (x0, x1) = if x0 < x1 { (x0, x1) } else { (0.0, 1.0) };
    let (y0, y1) = if y0 < y1 { (y0, y1) } else { (-1.0, 1.0) };
    let py = 0.05 * (y1 - y0);
    let mut chart = ChartBuilder::on(area)
        .caption(
            format!("{} (predicted: {})", p.channel, p.source),
            ("sans-serif", 15),
        )
        .margin(8)
        .x_label_area_size(30)
        .y_label_area_size(55)
        .build_cartesian_2d(x0..x1, (y0 - py)..(y1 + py))?;
    chart
        .configure_mesh()
        .x_desc("h")
        .y_desc(p.unit.as_str())
        .draw()?;
    let band: Vec<(f64, f64)> = p
        .predicted
        .iter()
        .filter(|q| q.1.is_finite() && q.2.is_finite())
        .map(|q| (q.0, q.1 + q.2))
        .chain(
            p.predicted
                .iter()
                .rev()
                .filter(|q| q.1.is_finite() && q.2.is_finite())
                .map(|q| (q.0, q.1 - q.2)),
        )
        .collect();
    let blue = RGBColor(40, 90, 200);
    chart
        .draw_series(std::iter::once(Polygon::new(band, blue.mix(0.18).filled())))?
        .label("band")
        .legend(move |(x, y)| {
            Rectangle::new([(x, y - 4), (x + 14, y + 4)], blue.mix(0.18).filled())
        });
    chart
        .draw_series(std::iter::once(PathElement::new(
            p.predicted
                .iter()
                .filter(|q| q.1.is_finite())
                .map(|q| (q.0, q.1))
                .collect::<Vec<_>>(),
            blue.stroke_width(2),
        )))?
        .label("predicted")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 14, y)], blue.stroke_width(2)));
    chart
        // At most about 1500 points a panel: a 15-s log over days would make a file of
        // tens of MB.
        .draw_series(
            p.measured
                .iter()
                .step_by(p.measured.len().div_ceil(1500).max(1))
                .map(|m| Circle::new(*m, 1, BLACK.filled())),
        )?
        .label("measured")
        .legend(|(x, y)| Circle::new((x + 7, y), 3, BLACK.filled()));
    if let Some(b) = p.boundary_h.filter(|b| (x0..=x1).contains(b)) {
        let red = RGBColor(200, 40, 40);
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(b, y0 - py), (b, y1 + py)],
                red.stroke_width(1),
            )))?
            .label("updates stop")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 14, y)], red));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panel_per_channel_with_its_band_and_boundary() {
        let p = Panel {
            channel: "ch1".into(),
            source: "grey box".into(),
            unit: "um".into(),
            measured: (0..50)
                .map(|i| (i as f64 * 0.1, (i as f64).sin()))
                .collect(),
            predicted: (0..50)
                .map(|i| (i as f64 * 0.1, (i as f64).sin(), 0.2))
                .collect(),
            boundary_h: Some(3.0),
        };
        let mut q = p.clone();
        q.channel = "ch3".into();
        let s = svg(&[p, q]).unwrap();
        assert!(s.starts_with("<svg") && s.contains("ch1 (predicted: grey box)"));
        assert!(s.contains("ch3 (predicted: grey box)") && s.contains("updates stop"));
        assert!(s.contains("<polygon"), "the band is drawn");
    }
}
