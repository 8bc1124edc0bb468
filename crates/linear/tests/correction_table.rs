//! Seed 003's correction table and its loop, on a simulated face.

use driftwatch_linear::axis_errors::Profile;
use driftwatch_linear::correction_table::{Face, LoopError, LoopSettings, Table, n_max, run};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn face(noise_um: f64) -> Face {
    Face {
        diameter_mm: 100.0,
        // 4 um of bow and 1 um of waviness across the radius.
        straightness: Profile {
            amplitudes_um: vec![4.0, 0.0, 1.0],
        },
        feed_mm_min: 20.0,
        drift_um_per_min: 0.8,
        drift_sd_um_per_min: 0.02,
        noise_um,
    }
}

#[test]
fn n_max_follows_the_nc_resolution() {
    // The seed's example resolution, 0.1 um: D / (2 x 0.1 um).
    assert_eq!(n_max(100.0, 0.1), 500_000);
    assert_eq!(n_max(10.0, 0.1), 50_000);
    assert_eq!(n_max(100.0, 1.0), 50_000);
}

#[test]
fn the_table_is_referenced_at_the_edge() {
    let t = Table::from_profile(&[50.0, 25.0, 0.0], &[2.0, 3.5, 1.0]);
    assert_eq!(t.d1_um, vec![0.0, 1.5, -1.0]);
    assert!((t.at(37.5) - 0.75).abs() < 1e-12);
    assert_eq!(
        t.csv(),
        "x_mm,dz_um\n50.0000,-0.0000\n25.0000,-1.5000\n0.0000,1.0000\n"
    );
}

#[test]
fn the_loop_converges_to_the_tolerance_and_reports_good() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let settings = LoopSettings {
        divisions: 50,
        resolution_um: 0.1,
        tolerance_um: 0.5,
        max_iterations: 6,
    };
    let r = run(&face(0.05), &settings, &mut rng).unwrap();
    for c in &r.cuts {
        println!(
            "cut {}: dz_max {:.3} um, true flatness {:.3} um",
            c.iteration, c.dz_max_um, c.true_flatness_um
        );
    }
    println!("{}", r.verdict);
    assert!(r.good && r.verdict == "GOOD", "{}", r.verdict);
    assert!(r.cuts[0].dz_max_um > 3.0, "the first cut shows the error");
    assert!(r.cuts.len() <= 3, "{} cuts", r.cuts.len());
    assert!(r.cuts.last().unwrap().true_flatness_um < 0.5);
}

#[test]
fn noise_above_the_tolerance_stops_at_the_cap_with_the_reason() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let settings = LoopSettings {
        divisions: 50,
        resolution_um: 0.1,
        tolerance_um: 0.5,
        max_iterations: 5,
    };
    let r = run(&face(0.6), &settings, &mut rng).unwrap();
    println!("{}", r.verdict);
    assert!(!r.good);
    assert_eq!(r.cuts.len(), 5);
    assert!(
        r.verdict.contains("NOT GOOD after 5 cuts") && r.verdict.contains("noise"),
        "{}",
        r.verdict
    );
    // More divisions than the resolution allows is refused.
    let too_many = LoopSettings {
        divisions: 600_000,
        ..settings
    };
    assert!(matches!(
        run(&face(0.05), &too_many, &mut rng),
        Err(LoopError::Divisions { n_max: 500_000, .. })
    ));
}
