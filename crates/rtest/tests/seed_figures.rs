//! Seed 002's findings, reproduced in simulation, and the R-test's own round trip.

use driftwatch_core::geometry::{Mat3, Vec3};
use driftwatch_core::kinematics::{Kinematics, MachineState};
use driftwatch_rtest::identify::{Options, identify};
use driftwatch_rtest::instrument::{Calibration, Imperfections, Instrument, Setting, calibrate};
use driftwatch_rtest::kinematic_test::{Setup, TestKind, TestSpec, simulate};
use driftwatch_rtest::process::{Processed, process};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

fn with_errors(k: &Kinematics, errors: &[(&str, f64)]) -> MachineState {
    let mut s = k.nominal_state();
    for (n, v) in errors {
        let id = k.error_id(n).unwrap();
        s.loc[id.axis][id.slot] += v * id.scale();
    }
    s
}

fn run_all(
    k: &Kinematics,
    truth: MachineState,
    inst: &Instrument,
    cal: &Calibration,
    setup: &Setup,
    rng: &mut ChaCha8Rng,
) -> Vec<Processed> {
    TestKind::ALL
        .iter()
        .map(|&kind| {
            let spec = TestSpec::default_for(k, kind).unwrap();
            let run = simulate(k, &spec, inst, &mut |_, _| truth, 0, setup, rng).unwrap();
            process(k, &run, cal).unwrap()
        })
        .collect()
}

/// Seed: "the set-ups agree within about 2 um". The three settings, each a device of its
/// own with the seed's imperfections (calibrated), on the same motions of the same machine.
#[test]
fn the_e_j_and_es_settings_agree_within_2_um_on_the_same_motion() {
    let k = Kinematics::builtin("table_bc").unwrap();
    let truth = with_errors(
        &k,
        &[
            ("EX0B", 8.0),
            ("EZ0B", -12.0),
            ("EX0C", 10.0),
            ("EY0C", -6.0),
            ("EA0C", 25.0),
            ("EB0C", -18.0),
            ("EA0B", 10.0),
        ],
    );
    let mut rng = ChaCha8Rng::seed_from_u64(2002);
    let setup = Setup::default();
    let mut curves = Vec::new();
    for setting in Setting::ALL {
        let inst = Instrument::drawn(setting, &Imperfections::seed(), &mut rng);
        let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
        curves.push(run_all(&k, truth, &inst, &cal, &setup, &mut rng));
    }
    let mut worst: f64 = 0.0;
    let mut largest: f64 = 0.0;
    for t in 0..3 {
        for i in 0..curves[0][t].points.len() {
            let e = curves[0][t].points[i].table_um;
            largest = largest.max(e.norm());
            for other in &curves[1..] {
                worst = worst.max((other[t].points[i].table_um - e).norm());
            }
        }
    }
    println!(
        "largest deviation {largest:.2} um, largest difference between settings {worst:.3} um"
    );
    assert!(
        largest > 20.0,
        "the motions must show the errors: {largest}"
    );
    assert!(worst < 2.0, "settings differ by {worst} um");
    // Not by luck of a zero reading: each setting's own curve is not the others' to 0.01 um.
    assert!(worst > 0.01);
}

/// Seed Table 1: moves of +-50 um along each linear axis were read within 1 um; the cause of
/// the larger error the seed saw was sensor cross-axis misalignment within +-0.5 deg. Over
/// 200 devices drawn with that misalignment: the error of a +-50 um move with the design
/// transform alone, and after the calibration motion.
#[test]
fn a_50_um_move_is_read_within_1_um_and_calibration_removes_the_misalignment() {
    let mut rng = ChaCha8Rng::seed_from_u64(50);
    let id = Mat3::identity();
    let (mut worst_design, mut worst_cal, mut mean_design) = (0.0f64, 0.0f64, 0.0);
    let n = 200;
    for i in 0..n {
        let setting = Setting::ALL[i % 3];
        let inst = Instrument::drawn(setting, &Imperfections::seed(), &mut rng);
        let design = Calibration::design(setting, inst.reading_sigma_um(), 0.5, 0.13);
        let cal = calibrate(&inst, 0.1, 3, 0.0, 0.13, &mut rng).unwrap();
        let mut this = 0.0f64;
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let mut b = Vec3::zeros();
                b[axis] = sign * 0.05;
                let r = inst.read(&b, &id, &mut rng).unwrap();
                let e_design = (design.displacement(&r).unwrap() - b * 1e3).abs().max();
                let e_cal = (cal.displacement(&r).unwrap() - b * 1e3).abs().max();
                this = this.max(e_design);
                worst_cal = worst_cal.max(e_cal);
            }
        }
        worst_design = worst_design.max(this);
        mean_design += this / n as f64;
    }
    println!(
        "+-50 um moves, largest component error: design transform mean {mean_design:.3} max {worst_design:.3} um; calibrated max {worst_cal:.3} um"
    );
    // 0.5 deg across 50 um is 0.44 um: the design transform stays under 1 um (the seed's
    // claim) but shows it; the calibration leaves the noise and the ball's form.
    assert!(
        worst_design < 1.0 && mean_design > 0.15,
        "{mean_design} {worst_design}"
    );
    assert!(worst_cal < 0.3, "{worst_cal}");
}

/// The BK2 and XYC reports of a machine whose C axis sits 10 um off: a once-per-revolution
/// radial component of 10 um, on every family with a C table.
#[test]
fn a_10_um_c_axis_offset_is_a_once_per_revolution_radial_component_of_10_um() {
    for name in [
        "table_bc",
        "table_d45_c",
        "trunnion_ac",
        "head_b_table_c",
        "head_d45_table_c",
    ] {
        let k = Kinematics::builtin(name).unwrap();
        let c = k.table_axis().unwrap();
        // The C line's first position error (X for all but the trunnion's Y-first order).
        let err = k.rotary[c].error_names[0].to_string();
        let truth = with_errors(&k, &[(err.as_str(), 10.0)]);
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let inst = Instrument::drawn(Setting::E, &Imperfections::seed(), &mut rng);
        let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
        for kind in [TestKind::Bk2, TestKind::Xyc] {
            let spec = TestSpec::default_for(&k, kind).unwrap();
            let run = simulate(
                &k,
                &spec,
                &inst,
                &mut |_, _| truth,
                0,
                &Setup::default(),
                &mut rng,
            )
            .unwrap();
            let p = process(&k, &run, &cal).unwrap();
            let h = p.radial.first_harmonic_um.unwrap();
            println!(
                "{name} {} ({err} = 10 um): radial once per revolution {h:.3} um, range {:.3} um",
                p.test, p.radial.range_um
            );
            assert!((h - 10.0).abs() < 0.15, "{name} {}: {h}", p.test);
            assert!((p.radial.range_um - 20.0).abs() < 0.5);
        }
    }
}

/// Round trip, Monte Carlo: location errors put into the virtual machine come back from the
/// R-test within their reported uncertainties. 500 runs, each with its own errors, device
/// (seed imperfections, calibrated), set-up and ball calibration error: the sample standard
/// deviation of (estimate - truth) within 10 % of the mean reported uncertainty.
#[test]
fn identified_errors_come_back_within_their_uncertainties_over_500_runs() {
    let k = Kinematics::builtin("table_bc").unwrap();
    let names = k.identify_names();
    let mut rng = ChaCha8Rng::seed_from_u64(500);
    let runs = 500;
    let head_sigma_um = 0.5;
    let mut dev: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    let mut sig: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for _ in 0..runs {
        let values: Vec<(&str, f64)> = names
            .iter()
            .map(|n| (n.as_str(), rng.random_range(-20.0..20.0)))
            .collect();
        let truth = with_errors(&k, &values);
        let inst = Instrument::drawn(Setting::E, &Imperfections::seed(), &mut rng);
        let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
        let mut normal = |s: f64| {
            let z: f64 = StandardNormal.sample(&mut rng);
            s * z * 1e-3
        };
        let setup = Setup {
            table_object_mm: Vec3::new(normal(20.0), normal(20.0), normal(20.0)),
            head_object_mm: Vec3::new(
                normal(head_sigma_um),
                normal(head_sigma_um),
                normal(head_sigma_um),
            ),
        };
        let procs = run_all(&k, truth, &inst, &cal, &setup, &mut rng);
        let opts = Options {
            head_sigma_um,
            ..Options::default()
        };
        let id = identify(&k, &procs, &opts).unwrap();
        for (j, (n, v)) in values.iter().enumerate() {
            let e = &id.errors[*n];
            dev[j].push(e.value - v);
            sig[j].push(e.sigma);
        }
    }
    for (j, n) in names.iter().enumerate() {
        let m = dev[j].iter().sum::<f64>() / runs as f64;
        let sd = (dev[j].iter().map(|d| (d - m).powi(2)).sum::<f64>() / (runs - 1) as f64).sqrt();
        let reported = sig[j].iter().sum::<f64>() / runs as f64;
        println!(
            "{n}: bias {m:+.4}, sample SD {sd:.4}, mean reported {reported:.4} (ratio {:.3})",
            sd / reported
        );
        assert!(
            (sd / reported - 1.0).abs() < 0.10,
            "{n}: SD {sd} against reported {reported}"
        );
        assert!(m.abs() < 4.0 * sd / (runs as f64).sqrt(), "{n}: bias {m}");
    }
}

/// What else the tests see: asked for every error, the R-test finds the linear axes'
/// squareness, the rotary axes' orientations that the tool setter holds and the C axis'
/// angular positioning error (its harmonics), and names what a single ball cannot separate
/// instead of guessing.
#[test]
fn asked_for_everything_it_finds_squareness_and_indexing_and_names_what_it_cannot_separate() {
    let k = Kinematics::builtin("table_bc").unwrap();
    let mut truth = with_errors(&k, &[("EX0C", 10.0), ("EA0B", 30.0), ("EZ0B", -8.0)]);
    truth.linear.sxy = 20e-6;
    truth.linear.syz = -15e-6;
    let c = k.table_axis().unwrap();
    // C positions 20 urad cos(2 C) + 10 urad sin(C) off its command.
    let mut state_at = |_: i64, a: &[f64; 3]| {
        let mut s = truth;
        let t = a[c].to_radians();
        s.angle_error[c] = 20e-6 * (2.0 * t).cos() + 10e-6 * t.sin();
        s
    };
    let mut rng = ChaCha8Rng::seed_from_u64(230);
    let inst = Instrument::drawn(Setting::E, &Imperfections::seed(), &mut rng);
    let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
    let procs: Vec<Processed> = TestKind::ALL
        .iter()
        .map(|&kind| {
            let spec = TestSpec::default_for(&k, kind).unwrap();
            let run = simulate(
                &k,
                &spec,
                &inst,
                &mut state_at,
                0,
                &Setup::default(),
                &mut rng,
            )
            .unwrap();
            process(&k, &run, &cal).unwrap()
        })
        .collect();
    let opts = Options {
        errors: driftwatch_rtest::identify::all_errors(&k),
        ..Options::default()
    };
    let id = identify(&k, &procs, &opts).unwrap();
    for (name, v) in [
        ("EX0C", 10.0),
        ("EA0B", 30.0),
        ("EZ0B", -8.0),
        ("squareness_xy_urad", 20.0),
        ("squareness_yz_urad", -15.0),
        ("squareness_xz_urad", 0.0),
        ("C_index_cos2_urad", 20.0),
        ("C_index_sin2_urad", 0.0),
        ("C_index_sin1_urad", 10.0),
    ] {
        let e = &id.errors[name];
        println!("{name}: {:.3} +- {:.3} (true {v})", e.value, e.sigma);
        assert!(
            (e.value - v).abs() < 4.0 * e.sigma,
            "{name}: {} +- {}",
            e.value,
            e.sigma
        );
    }
    let tied: Vec<&str> = id
        .not_identifiable
        .iter()
        .map(|m| m.split(':').next().unwrap())
        .collect();
    println!("not identifiable: {:?}", id.not_identifiable);
    assert!(
        tied.contains(&"EC0C") && tied.contains(&"scale_z_ppm"),
        "{tied:?}"
    );
}

/// Every built-in family: its own six errors put in come back from BK1, BK2 and XYC within
/// their uncertainties, each setting.
#[test]
fn every_family_identifies_its_six_errors_from_the_r_test() {
    for name in [
        "table_bc",
        "table_d45_c",
        "trunnion_ac",
        "head_b_table_c",
        "head_d45_table_c",
    ] {
        let k = Kinematics::builtin(name).unwrap();
        let names = k.identify_names();
        let values: Vec<(&str, f64)> = names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), [12.0, -7.0, 5.0, -9.0, 20.0, -15.0][i % 6]))
            .collect();
        let truth = with_errors(&k, &values);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for setting in Setting::ALL {
            let inst = Instrument::drawn(setting, &Imperfections::seed(), &mut rng);
            let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
            let setup = Setup {
                table_object_mm: Vec3::new(0.02, -0.01, 0.015),
                head_object_mm: Vec3::zeros(),
            };
            let procs = run_all(&k, truth, &inst, &cal, &setup, &mut rng);
            let id = identify(&k, &procs, &Options::default()).unwrap();
            assert!(
                id.not_identifiable.is_empty(),
                "{name}: {:?}",
                id.not_identifiable
            );
            for (n, v) in &values {
                let e = &id.errors[*n];
                assert!(
                    (e.value - v).abs() < 4.0 * e.sigma,
                    "{name} {setting:?} {n}: {} +- {} (true {v})",
                    e.value,
                    e.sigma
                );
            }
        }
    }
}
