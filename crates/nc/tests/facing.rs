//! The lathe facing pass: every dialect's program reads back to the points it was given.

use driftwatch_nc::dialect::Dialect;
use driftwatch_nc::facing::{FacingError, FacingPass, facing_program, x_is_diameter};

/// The X and Z words of a program's feed moves (`G01`/`G1`, HEIDENHAIN `L` without `FMAX`),
/// modal as the controls read them: a word not given keeps its value. Comments are skipped.
pub fn feed_points(d: Dialect, text: &str) -> Vec<(f64, f64)> {
    let (mut x, mut z) = (f64::NAN, f64::NAN);
    let mut feed = false;
    let mut out = Vec::new();
    for raw in text.lines() {
        let mut line = raw.trim();
        if d == Dialect::Heidenhain {
            // The block number.
            line = line.split_once(' ').map_or("", |(_, rest)| rest);
        }
        let line = line.split([';', '(']).next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        let mut moved = false;
        match d {
            Dialect::Heidenhain => {
                if words.first() != Some(&"L") {
                    continue;
                }
                feed = !words.contains(&"FMAX");
            }
            _ => {
                for w in &words {
                    match *w {
                        "G00" | "G0" => feed = false,
                        "G01" | "G1" => feed = true,
                        _ => {}
                    }
                }
            }
        }
        for w in &words {
            if let Some(v) = w.strip_prefix('X').and_then(|v| v.parse::<f64>().ok()) {
                x = v;
                moved = true;
            }
            if let Some(v) = w.strip_prefix('Z').and_then(|v| v.parse::<f64>().ok()) {
                z = v;
                moved = true;
            }
        }
        if moved && feed {
            let r = if x_is_diameter(d) { x / 2.0 } else { x };
            out.push((r, z));
        }
    }
    out
}

fn pass() -> FacingPass {
    FacingPass {
        number: 9200,
        comments: vec!["correction table test (seed 003)".into()],
        points: (0..=10)
            .map(|i| {
                let r = 50.0 - 5.0 * i as f64;
                (r, -0.0031 * (i as f64 * 0.7).sin() + 0.00004 * i as f64)
            })
            .collect(),
        feed_mm_min: 20.0,
        clearance_mm: 1.0,
        decimals: 4,
    }
}

#[test]
fn every_dialect_reads_back_to_the_points_within_its_increment() {
    let p = pass();
    for d in Dialect::ALL {
        let text = facing_program(d, &p).unwrap();
        println!("{d}:\n{text}");
        let back = feed_points(d, &text);
        assert_eq!(back.len(), p.points.len(), "{d}: {back:?}");
        // Half the last decimal (a diameter's rounding halves in the radius).
        let tol = 0.5e-4 + 1e-12;
        for ((r, z), (rb, zb)) in p.points.iter().zip(&back) {
            assert!((r - rb).abs() <= tol, "{d}: radius {rb} for {r}");
            assert!((z - zb).abs() <= tol, "{d}: Z {zb} for {z}");
        }
        // The header names what the pass is and how X is meant.
        assert!(text.contains("LATHE FACING PASS"), "{d}");
        assert!(text.contains("CORRECTION TABLE TEST"), "{d}");
        let mode = if x_is_diameter(d) {
            "X IS THE DIAMETER"
        } else {
            "X IS THE RADIUS"
        };
        assert!(text.contains(mode), "{d}");
    }
    // FANUC lathes take X as the diameter: the edge of a 100 mm face is X100.
    let fanuc = facing_program(Dialect::Fanuc, &p).unwrap();
    assert!(fanuc.contains("\nG00 X100.0000 Z"), "{fanuc}");
    let iso = facing_program(Dialect::Iso, &p).unwrap();
    assert!(
        iso.contains("\nG0 X50.0000 Z") && iso.contains(" G8\n"),
        "{iso}"
    );
}

#[test]
fn bad_passes_are_refused() {
    let mut p = pass();
    p.decimals = 5;
    assert!(matches!(
        facing_program(Dialect::Heidenhain, &p),
        Err(FacingError::Decimals { max: 4, .. })
    ));
    assert!(facing_program(Dialect::Fanuc, &p).is_ok());
    p.points.truncate(1);
    assert_eq!(
        facing_program(Dialect::Fanuc, &p),
        Err(FacingError::TooFewPoints)
    );
    let mut p = pass();
    p.points[3].0 = f64::NAN;
    assert_eq!(
        facing_program(Dialect::Siemens, &p),
        Err(FacingError::BadPoint(4))
    );
}
