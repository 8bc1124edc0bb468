//! Every machine family of `config/machines/`: its conventions pinned (as
//! `docs/kinematics-conventions.md` states them), a noise-free round trip, Monte Carlo against
//! the Cramer-Rao bound, and the refusal of a plan that cannot separate its errors.

use driftwatch_core::geometry::Vec3;
use driftwatch_core::identify::{Identifier, Observation, SolveError, SolveOptions, identify};
use driftwatch_core::kinematics::{Kinematics, MachineState};
use driftwatch_core::measurement::{Approach, Axis, latched};
use driftwatch_core::plan::{Plan, PlanConfig};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

const FAMILIES: [&str; 5] = [
    "table_bc",
    "head_b_table_c",
    "table_d45_c",
    "head_d45_table_c",
    "trunnion_ac",
];

fn machine(name: &str) -> Kinematics {
    Kinematics::builtin(name).unwrap()
}

/// The machine's own plan (its `plan` key: on the new families the one `plan design` found).
fn own_plan(k: &Kinematics) -> Plan {
    Plan::build(k, &PlanConfig::load(&k.config.plan).unwrap()).unwrap()
}

/// The patent's poses on the machine (`patent` on table_bc, `<family>_patent` on the others).
fn patent_config(k: &Kinematics) -> PlanConfig {
    let name = if k.name == "table_bc" {
        "patent".to_string()
    } else {
        format!("{}_patent", k.name)
    };
    PlanConfig::load(&name).unwrap()
}

fn set(k: &Kinematics, s: &mut MachineState, name: &str, v: f64) {
    let id = k.error_id(name).unwrap();
    s.loc[id.axis][id.slot] = v * id.scale();
}

fn observe(
    k: &Kinematics,
    plan: &Plan,
    truth: &MachineState,
    sigma_um: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<Observation> {
    let mut obs = plan.observations(k, truth).unwrap();
    for o in &mut obs {
        let z: f64 = StandardNormal.sample(rng);
        o.position[o.approach.axis.index()] += sigma_um * z * 1e-3;
    }
    obs
}

/// The largest |difference| so far, positions (um) and orientations (urad) apart.
fn worst_by_unit<'a>(
    worst: (f64, f64),
    diffs: impl Iterator<Item = (&'a driftwatch_core::identify::Estimate, f64)>,
) -> (f64, f64) {
    diffs.fold(worst, |(um, urad), (e, d)| {
        if e.unit == "um" {
            (um.max(d.abs()), urad)
        } else {
            (um, urad.max(d.abs()))
        }
    })
}

fn close(a: Vec3, b: Vec3, tol: f64) -> bool {
    (a - b).norm() < tol
}

#[test]
fn every_family_loads_and_its_own_plan_identifies_its_six_errors() {
    for name in FAMILIES {
        let k = machine(name);
        let p = own_plan(&k);
        let obs = p.observations(&k, &k.nominal_state()).unwrap();
        let id = Identifier::new(&k, &obs, &SolveOptions::new(k.setter.sigma_um))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let crb = id.cramer_rao(&obs).unwrap();
        assert_eq!(
            crb.iter()
                .take(6)
                .map(|e| e.name.clone())
                .collect::<Vec<_>>(),
            k.identify_names(),
            "{name}"
        );
        println!(
            "{name}: plan '{}', {} approaches, {:.1} s; CRB {}",
            p.name,
            p.steps.len(),
            p.machine_time_s,
            crb.iter()
                .take(6)
                .map(|e| format!("{} {:.3} {}", e.name, e.sigma, e.unit))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
}

/// head_b_table_c: B turns the head in the direct sense; its line is in the head frame, so the
/// zero pose is the reference and the pivot errors move the tip by `(I - R) delta`.
#[test]
fn head_b_turns_the_tool_in_the_direct_sense_about_its_pivot() {
    let k = machine("head_b_table_c");
    let s = k.nominal_state();
    // B = +90: the tool axis (tip into spindle) turns from +Z to +X, the tip points -X.
    let t = k.pose_geometry(&s, &[90.0, 0.0]).tool;
    assert!(close(t.axis, Vec3::x(), 1e-12), "{}", t.axis);
    // Without errors the NC's head model is right: the tip is where it is commanded.
    assert!(close(t.actual, t.nominal, 1e-12));
    // The nominal offset is the pivot's: the tip swings on a 200 mm arm about the B line.
    assert!(
        close(t.nominal, Vec3::new(-200.0, 0.0, 200.0), 1e-9),
        "{}",
        t.nominal
    );
    let mut e = k.nominal_state();
    set(&k, &mut e, "EX0B", 10.0);
    set(&k, &mut e, "EZ0B", -4.0);
    set(&k, &mut e, "EA0B", 50.0);
    // Zero pose: no error shows.
    let t0 = k.pose_geometry(&e, &[0.0, 0.0]).tool;
    assert!(close(t0.actual, Vec3::zeros(), 1e-12) && close(t0.axis, Vec3::z(), 1e-12));
    // B = -90: R X = +Z and R Z = -X, so EX0B moves the tip by (1, 0, -1) EX0B and EZ0B by
    // (1, 0, 1) EZ0B; EA0B tilts the line, moving the tip by about 200 mm * EA0B along Y.
    set(&k, &mut e, "EA0B", 0.0);
    let t = k.pose_geometry(&e, &[-90.0, 0.0]).tool;
    let want = Vec3::new(0.010 - 0.004, 0.0, -0.010 - 0.004);
    assert!(
        close(t.actual - t.nominal, want, 1e-9),
        "{}",
        t.actual - t.nominal
    );
    assert!(close(t.axis, -Vec3::x(), 1e-12));
}

/// table_d45_c: D lies in the Y-Z plane at 45 degrees; D = +-180 turn the table top to face +Y,
/// the setter to (0, H, -R); the D errors are named in D's own frame (X', Y' = D, Z').
#[test]
fn table_d45_turns_the_table_top_to_face_plus_y_at_180() {
    let k = machine("table_d45_c");
    let s = k.nominal_state();
    for d in [180.0, -180.0] {
        let t = k.pose_transform(&s, &[d, 0.0]);
        assert!(close(t.vector(&Vec3::z()), Vec3::y(), 1e-12));
        // The setter's beam point (0, -R, H) = (0, -100, 70) goes to (0, H, -R), beam along X.
        let (p, dir) = k.beam_in_machine(&s, &[d, 0.0]);
        assert!(close(p, Vec3::new(0.0, 70.0, -100.0), 1e-9), "{p}");
        assert!((dir.x.abs() - 1.0).abs() < 1e-12);
    }
    // Table sense: D = -90 turns the table negatively about (0, 1, 1)/sqrt2, taking the table
    // normal to (1/sqrt2, 1/2, 1/2).
    let n = k.pose_transform(&s, &[-90.0, 0.0]).vector(&Vec3::z());
    let h = std::f64::consts::FRAC_1_SQRT_2;
    assert!(close(n, Vec3::new(h, 0.5, 0.5), 1e-12), "{n}");
    // EZ0D moves the line along Z' = (0, -1, 1)/sqrt2, EX0D along X; a point of the moved,
    // tilted line stays put under any D, and the zero pose shows none of it.
    let mut e = k.nominal_state();
    set(&k, &mut e, "EX0D", 12.0);
    set(&k, &mut e, "EZ0D", -30.0);
    set(&k, &mut e, "EA0D", 80.0);
    let t0 = k.pose_transform(&e, &[0.0, 0.0]);
    assert!(close(
        t0.point(&Vec3::new(50.0, 20.0, -10.0)),
        Vec3::new(50.0, 20.0, -10.0),
        1e-12
    ));
    let (off, dir) = k.lines(&e);
    let q = Vec3::new(0.012, 0.030 * h, -0.030 * h);
    assert!(close(off[0], q, 1e-12), "{}", off[0]);
    // EA0D turns D about X: first order (0, 1, 1)/sqrt2 + EA0D (0, -1, 1)/sqrt2.
    let want = Vec3::new(0.0, h * (1.0 - 80e-6), h * (1.0 + 80e-6)).normalize();
    assert!(close(dir[0], want, 1e-8), "{}", dir[0]);
    let p = q + dir[0] * 150.0;
    let t = k.pose_transform(&e, &[133.0, 0.0]);
    assert!(close(t.point(&p), p, 1e-9));
    // The C line, measured from D, inherits the part of D's offset square to C.
    set(&k, &mut e, "EX0C", 5.0);
    set(&k, &mut e, "EY0C", 7.0);
    let (off, _) = k.lines(&e);
    assert!(close(
        off[1],
        Vec3::new(0.012 + 0.005, 0.030 * h + 0.007, 0.0),
        1e-12
    ));
}

/// head_d45_table_c: D = 180 turns the spindle from +Z to +Y (the tool points -Y, parallel to
/// the table top); an offset of the D line square to it moves the tip by twice the offset.
#[test]
fn head_d45_lays_the_spindle_along_y_at_180() {
    let k = machine("head_d45_table_c");
    let s = k.nominal_state();
    for d in [180.0, -180.0] {
        let t = k.pose_geometry(&s, &[d, 0.0]).tool;
        assert!(close(t.axis, Vec3::y(), 1e-12), "{}", t.axis);
        // The tip swings about the D line, which crosses the spindle axis 200 mm above it.
        assert!(
            close(t.nominal, Vec3::new(0.0, -200.0, 200.0), 1e-9),
            "{}",
            t.nominal
        );
    }
    let mut e = k.nominal_state();
    set(&k, &mut e, "EX0D", 6.0);
    set(&k, &mut e, "EZ0D", -20.0);
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let t = k.pose_geometry(&e, &[180.0, 0.0]).tool;
    let want = Vec3::new(0.012, 0.040 * h, -0.040 * h);
    assert!(
        close(t.actual - t.nominal, want, 1e-9),
        "{}",
        t.actual - t.nominal
    );
    let t0 = k.pose_geometry(&e, &[0.0, 0.0]).tool;
    assert!(close(t0.actual, Vec3::zeros(), 1e-12));
}

/// trunnion_ac: A turns the table in the ISO 841 sense about X; A = -90 makes the table top
/// face -Y; EY0C is measured from the A line.
#[test]
fn trunnion_a_minus_90_turns_the_table_top_to_face_minus_y() {
    let k = machine("trunnion_ac");
    let s = k.nominal_state();
    let t = k.pose_transform(&s, &[-90.0, 0.0]);
    assert!(close(t.vector(&Vec3::z()), -Vec3::y(), 1e-12));
    let (p, _) = k.beam_in_machine(&s, &[-90.0, 0.0]);
    assert!(close(p, Vec3::new(0.0, -70.0, -100.0), 1e-9), "{p}");
    let mut e = k.nominal_state();
    set(&k, &mut e, "EY0A", 9.0);
    set(&k, &mut e, "EZ0A", -3.0);
    set(&k, &mut e, "EY0C", 2.0);
    set(&k, &mut e, "EX0C", 4.0);
    let (off, _) = k.lines(&e);
    assert!(close(off[0], Vec3::new(0.0, 0.009, -0.003), 1e-12));
    assert!(
        close(off[1], Vec3::new(0.004, 0.011, 0.0), 1e-12),
        "{}",
        off[1]
    );
}

/// The apparent errors: a tool-tip displacement `s` reads exactly as the lines (table and
/// head) and the setter moved by `-s` with the tip at zero, on every family and pose.
#[test]
fn apparent_state_gives_the_same_readings_on_every_family() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for name in FAMILIES {
        let k = machine(name);
        let p = own_plan(&k);
        for _ in 0..20 {
            let mut s = k.nominal_state();
            for axis in 0..k.rotary.len() {
                for slot in 0..4 {
                    let lim = if slot < 2 { 0.05 } else { 2e-4 };
                    s.loc[axis][slot] = rng.random_range(-lim..lim);
                }
            }
            s.tool_tip = Vec3::new(
                rng.random_range(-0.02..0.02),
                rng.random_range(-0.02..0.02),
                rng.random_range(-0.1..0.1),
            );
            let a = k.apparent_state(&s);
            assert_eq!(a.tool_tip, Vec3::zeros());
            for st in &p.steps {
                let v1 = latched(&k, &s, &st.angles, &st.approach, &st.start, None)
                    .unwrap_or_else(|e| panic!("{name} {}: {e}", st.label));
                let v2 = latched(&k, &a, &st.angles, &st.approach, &st.start, None)
                    .unwrap_or_else(|e| panic!("{name} {}: {e}", st.label));
                assert!((v1 - v2).abs() < 1e-11, "{name} {}: {v1} vs {v2}", st.label);
            }
        }
    }
}

/// Random errors within +-100 um and +-300 urad and a setter off by up to 0.5 mm are recovered
/// from noise-free readings of each family's own plan and of its patent-pattern plan.
#[test]
fn noise_free_round_trip_on_every_family() {
    let mut rng = ChaCha8Rng::seed_from_u64(16);
    for name in FAMILIES {
        let k = machine(name);
        let plans = [own_plan(&k), Plan::build(&k, &patent_config(&k)).unwrap()];
        let mut worst = (0.0f64, 0.0f64);
        for i in 0..200 {
            let p = &plans[i % 2];
            let mut truth = k.nominal_state();
            let vals: Vec<f64> = k
                .identify
                .iter()
                .map(|id| {
                    let lim = if id.is_position() { 100.0 } else { 300.0 };
                    let v = rng.random_range(-lim..lim);
                    truth.loc[id.axis][id.slot] = v * id.scale();
                    v
                })
                .collect();
            truth.beam_point += Vec3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
            );
            let obs = observe(&k, p, &truth, 0.0, &mut rng);
            let sol = identify(&k, &obs, &SolveOptions::new(0.5))
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            let diffs = sol.errors.iter().zip(&vals).map(|(e, v)| (e, e.value - v));
            worst = worst_by_unit(worst, diffs);
        }
        println!(
            "{name}: worst noise-free error {:.2e} um, {:.2e} urad",
            worst.0, worst.1
        );
        assert!(worst.0 < 1e-3 && worst.1 < 1e-2, "{name}: {worst:?}");
    }
}

/// 4000 noisy cycles of each family's own plan: the sample SD of each error within 5 % of its
/// Cramer-Rao bound and the bias under 0.05 SD (the SD's relative standard error is 1.1 %,
/// the mean's 0.016 SD).
#[test]
fn monte_carlo_matches_the_cramer_rao_bound_on_every_family() {
    let sigma = 0.5;
    for (f, name) in FAMILIES.into_iter().enumerate() {
        let k = machine(name);
        let p = own_plan(&k);
        let mut truth = k.nominal_state();
        // Orientation errors kept away from zero beam slope (the flat end's kink).
        let vals: Vec<f64> = k
            .identify
            .iter()
            .enumerate()
            .map(|(i, id)| {
                let v = if id.is_position() {
                    [20.0, 80.0, -35.0, 12.0][i % 4]
                } else {
                    [60.0, -150.0][i % 2]
                };
                truth.loc[id.axis][id.slot] = v * id.scale();
                v
            })
            .collect();
        let mut rng = ChaCha8Rng::seed_from_u64(2024 + f as u64);
        let template = p.observations(&k, &k.nominal_state()).unwrap();
        let id = Identifier::new(&k, &template, &SolveOptions::new(sigma)).unwrap();
        let crb = id.cramer_rao(&template).unwrap();
        let trials = 4000;
        let mut est: Vec<Vec<f64>> = (0..6).map(|_| Vec::with_capacity(trials)).collect();
        for _ in 0..trials {
            let obs = observe(&k, &p, &truth, sigma, &mut rng);
            let s = id.solve(&obs).unwrap();
            for (i, e) in s.errors.iter().enumerate() {
                est[i].push(e.value);
            }
        }
        for i in 0..6 {
            let n = trials as f64;
            let mean = est[i].iter().sum::<f64>() / n;
            let sd = (est[i].iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            let (e, bias) = (&crb[i], (mean - vals[i]) / sd);
            println!(
                "{name} {}: sd {sd:.4} {}, CRB {:.4}, bias {bias:+.4} sd",
                e.name, e.unit, e.sigma
            );
            assert!((sd / e.sigma - 1.0).abs() < 0.05, "{name} {}", e.name);
            assert!(bias.abs() < 0.05, "{name} {}: bias {bias}", e.name);
        }
    }
}

/// A plan without a tilted pose cannot see where the tilting axis is: refused, naming the
/// errors it cannot separate and the pose to add.
#[test]
fn a_plan_without_a_tilted_pose_is_refused_on_every_family() {
    for name in FAMILIES {
        let k = machine(name);
        let mut cfg = patent_config(&k);
        cfg.poses.retain(|p| p.b_deg == 0.0);
        let p = Plan::build(&k, &cfg).unwrap();
        let obs = p.observations(&k, &k.nominal_state()).unwrap();
        let err = identify(&k, &obs, &SolveOptions::new(0.5)).unwrap_err();
        let text = err.to_string();
        println!("{name}: {text}");
        assert!(matches!(err, SolveError::NotIdentifiable { .. }), "{name}");
        let tilt = k.tilting_axes()[0].to_string();
        assert!(text.contains(&format!("E{}0{tilt}", if tilt == "A" { "Y" } else { "X" })));
        assert!(text.contains(&format!(
            "the position of the {tilt} axis shows only when it turns"
        )));
    }
}

/// The patent's D poses (D = 0 and D = +-180 only) lay the beam along X wherever the D line's
/// X position would show: on the table D machine only EX0D + EX0C is seen, on the head D
/// machine EX0D not at all. Both are refused naming that.
#[test]
fn the_patents_own_d_poses_cannot_see_the_d_lines_x_position() {
    for (name, says) in [
        ("table_d45_c", "(+1.000 EX0D -1.000 EX0C)"),
        ("head_d45_table_c", "EX0D (no reading depends on it)"),
    ] {
        let k = machine(name);
        let mut cfg = patent_config(&k);
        cfg.poses
            .retain(|p| p.b_deg == 0.0 || (p.b_deg.abs() == 180.0 && p.c_deg != -45.0));
        assert_eq!(cfg.poses.len(), 6);
        let p = Plan::build(&k, &cfg).unwrap();
        let obs = p.observations(&k, &k.nominal_state()).unwrap();
        let text = identify(&k, &obs, &SolveOptions::new(0.5))
            .unwrap_err()
            .to_string();
        println!("{name}: {text}");
        assert!(text.contains(says), "{name}: {text}");
    }
}

/// The end face meets the beam moving out of the spindle whatever the tool axis: an approach
/// into the spindle is refused with the reason.
#[test]
fn an_end_face_approach_into_the_spindle_or_an_oblique_one_is_refused() {
    let k = machine("head_d45_table_c");
    let s = k.nominal_state();
    let into = Approach {
        axis: Axis::Y,
        direction: 1,
        feed_mm_min: 100.0,
    };
    let e = latched(
        &k,
        &s,
        &[180.0, -180.0],
        &into,
        &Vec3::new(0.0, 90.0, 70.0),
        None,
    )
    .unwrap_err();
    assert!(e.to_string().contains("out of the spindle"), "{e}");
    // At D = -90 the tool axis is 45 deg from X: an approach along X is neither end face nor
    // lateral, and is refused rather than guessed (a plan with it does not build).
    let oblique = Approach {
        axis: Axis::X,
        direction: -1,
        feed_mm_min: 100.0,
    };
    let e = latched(
        &k,
        &s,
        &[-90.0, -135.0],
        &oblique,
        &Vec3::new(50.0, 0.0, 70.0),
        None,
    )
    .unwrap_err();
    assert!(e.to_string().contains("45.0 deg from the tool axis"), "{e}");
    let mut cfg = PlanConfig::load("head_d45_table_c_patent").unwrap();
    cfg.poses[0].b_deg = -90.0;
    cfg.poses[0].approaches = vec!["x-".into()];
    let e = Plan::build(&k, &cfg).unwrap_err().to_string();
    assert!(e.contains("neither along it nor across it"), "{e}");
}

/// The patent's first-order relations, derived by hand for each family's poses
/// (`patent_relations`), agree with the exact solver within second-order terms: an
/// independent check of each family's chain, signs and senses. The bound: products of two
/// small quantities, |theta|^2 * L with L ~ 200 mm and setter offsets (<= 0.1 mm) times angles
/// (<= 50 urad): 0.1 mm * 50e-6 = 5 nm, doubled for sums of such terms; orientations: that
/// over the 2R = 200 mm lever, 0.05 urad. On table_bc both the patent's orders are checked.
#[test]
fn first_order_relations_agree_with_the_exact_solver_on_every_family() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for name in FAMILIES {
        let k = machine(name);
        let mut plans = vec![Plan::build(&k, &patent_config(&k)).unwrap()];
        if name == "table_bc" {
            plans.push(Plan::build(&k, &PlanConfig::load("patent_sequential").unwrap()).unwrap());
        }
        let mut worst = (0.0f64, 0.0f64);
        for i in 0..100 * plans.len() {
            let p = &plans[i % plans.len()];
            let mut truth = k.nominal_state();
            for id in &k.identify {
                let lim = if id.is_position() { 10.0 } else { 50.0 };
                truth.loc[id.axis][id.slot] = rng.random_range(-lim..lim) * id.scale();
            }
            truth.beam_point += Vec3::new(
                0.0,
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
            );
            let obs = observe(&k, p, &truth, 0.0, &mut rng);
            let exact = identify(&k, &obs, &SolveOptions::new(0.5)).unwrap();
            let first = driftwatch_core::patent_relations::estimate(&k, &obs)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            let diffs = exact
                .errors
                .iter()
                .map(|e| (e, e.value - first.errors[&e.name]));
            worst = worst_by_unit(worst, diffs);
        }
        println!(
            "{name}: largest difference exact vs first-order {:.4} um, {:.4} urad",
            worst.0, worst.1
        );
        assert!(worst.0 < 0.01 && worst.1 < 0.05, "{name}: {worst:?}");
    }
}

/// The apparent errors each family's conventions state: a tool-tip displacement s = (sx, sy,
/// sz) moves the identified errors by these amounts (and no others), to first order.
#[test]
fn apparent_errors_follow_the_documented_rule_of_each_family() {
    let (sx, sy, sz) = (3.0, -2.0, -20.0);
    let h = std::f64::consts::FRAC_1_SQRT_2;
    for (name, want) in [
        (
            "table_bc",
            vec![("EX0B", -sx), ("EZ0B", -sz), ("EY0C", -sy), ("EX0C", 0.0)],
        ),
        (
            "head_b_table_c",
            vec![("EX0B", -sx), ("EZ0B", -sz), ("EX0C", -sx), ("EY0C", -sy)],
        ),
        (
            "table_d45_c",
            vec![
                ("EX0D", -sx),
                ("EZ0D", (sy - sz) * h),
                ("EX0C", 0.0),
                ("EY0C", -(sy + sz) / 2.0),
            ],
        ),
        (
            "head_d45_table_c",
            vec![
                ("EX0D", -sx),
                ("EZ0D", (sy - sz) * h),
                ("EX0C", -sx),
                ("EY0C", -sy),
            ],
        ),
        (
            "trunnion_ac",
            vec![("EY0A", -sy), ("EZ0A", -sz), ("EX0C", -sx), ("EY0C", 0.0)],
        ),
    ] {
        let k = machine(name);
        let mut s = k.nominal_state();
        s.tool_tip = Vec3::new(sx, sy, sz) * 1e-3;
        let a = k.apparent_state(&s);
        for id in &k.identify {
            let n = k.error_name(*id);
            let got = a.loc[id.axis][id.slot] / id.scale();
            let expect = want.iter().find(|(w, _)| *w == n).map_or(0.0, |w| w.1);
            assert!((got - expect).abs() < 1e-9, "{name} {n}: {got} vs {expect}");
        }
    }
}

/// The error of `name` on `s` (um or urad).
fn get(k: &Kinematics, s: &MachineState, name: &str) -> f64 {
    let id = k.error_id(name).unwrap();
    s.loc[id.axis][id.slot] / id.scale()
}

/// Each line's actual direction is its nominal one turned first about the first orientation
/// error's direction, then about the second's (fixed directions, right-handed), exactly as
/// the contract writes it per family; with tilts large enough that the order and the first
/// order approximation both show.
#[test]
fn line_directions_are_the_stated_exact_rotations_on_every_family() {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let (xd, yd, zd) = (Vec3::x(), Vec3::new(0.0, h, h), Vec3::new(0.0, -h, h));
    for name in FAMILIES {
        let k = machine(name);
        let mut s = k.nominal_state();
        let (first, second) = (0.05, -0.03);
        for ax in &k.rotary {
            set(&k, &mut s, ax.error_names[2].as_str(), first * 1e6);
            set(&k, &mut s, ax.error_names[3].as_str(), second * 1e6);
        }
        let (_, dirs) = k.lines(&s);
        for (i, ax) in k.rotary.iter().enumerate() {
            let (a, b) = (first, second);
            let want = match ax.name.as_str() {
                // u_B = Rz(EC0B) Rx(EA0B) Y
                "B" => Vec3::new(-b.sin() * a.cos(), b.cos() * a.cos(), a.sin()),
                // u_C = Ry(EB0C) Rx(EA0C) Z
                "C" => Vec3::new(a.cos() * b.sin(), -a.sin(), a.cos() * b.cos()),
                // u_D = Rot(Z', EC0D) Rot(X', EA0D) Y'
                "D" => xd * (-b.sin() * a.cos()) + yd * (b.cos() * a.cos()) + zd * a.sin(),
                // u_A = Rz(EC0A) Ry(EB0A) X
                "A" => Vec3::new(b.cos() * a.cos(), b.sin() * a.cos(), -a.sin()),
                other => panic!("{other}"),
            };
            assert!(
                close(dirs[i], want, 1e-15),
                "{name} {}: {} vs {want}",
                ax.name,
                dirs[i]
            );
        }
    }
}

/// The apparent errors exactly, tilted lines included: each line shifted by -s is named where
/// it crosses the plane through its nominal point square to its nominal direction, so a
/// tilted line's position errors also take `s.u0` times its tilt (tan, over cos), and a line
/// measured from its parent takes the difference of the two. The contract's formulas per
/// family, with tilts large enough that the first-order forms would fail.
#[test]
fn apparent_errors_are_exact_for_tilted_lines_on_every_family() {
    let (sx, sy, sz) = (30.0, -20.0, -200.0);
    let h = std::f64::consts::FRAC_1_SQRT_2;
    // Components of s in the D frame (X', Y' = D, Z').
    let (sdy, sdz) = ((sy + sz) * h, (sz - sy) * h);
    let tilts = [
        ("EA0B", 0.05),
        ("EC0B", -0.03),
        ("EA0C", 0.04),
        ("EB0C", -0.06),
        ("EA0D", 0.05),
        ("EC0D", -0.03),
        ("EB0A", 0.05),
        ("EC0A", -0.03),
    ];
    let positions = [("EX0", 11.0), ("EY0", -7.0), ("EZ0", 5.0)];
    for name in FAMILIES {
        let k = machine(name);
        let mut s = k.nominal_state();
        for ax in &k.rotary {
            for (slot, n) in ax.error_names.iter().enumerate().take(4) {
                let n = n.as_str();
                let v = match slot {
                    0 | 1 => positions.iter().find(|p| n.starts_with(p.0)).unwrap().1,
                    _ => tilts.iter().find(|t| t.0 == n).unwrap().1 * 1e6,
                };
                set(&k, &mut s, n, v);
            }
        }
        s.tool_tip = Vec3::new(sx, sy, sz) * 1e-3;
        let a = k.apparent_state(&s);
        let e = |n: &str| get(&k, &s, n);
        let t = |n: &str| (e(n) * 1e-6).tan();
        let c = |n: &str| (e(n) * 1e-6).cos();
        // EX0C and EY0C of an absolute C line.
        let c_abs = [
            ("EX0C", e("EX0C") - sx + sz * t("EB0C")),
            ("EY0C", e("EY0C") - sy - sz * t("EA0C") / c("EB0C")),
        ];
        let want: Vec<(&str, f64)> = match name {
            "table_bc" => vec![
                ("EX0B", e("EX0B") - sx - sy * t("EC0B")),
                ("EZ0B", e("EZ0B") - sz + sy * t("EA0B") / c("EC0B")),
                ("EX0C", e("EX0C") + sz * t("EB0C") + sy * t("EC0B")),
                ("EY0C", e("EY0C") - sy - sz * t("EA0C") / c("EB0C")),
            ],
            "head_b_table_c" => vec![
                ("EX0B", e("EX0B") - sx - sy * t("EC0B")),
                ("EZ0B", e("EZ0B") - sz + sy * t("EA0B") / c("EC0B")),
                c_abs[0],
                c_abs[1],
            ],
            "table_d45_c" => vec![
                ("EX0D", e("EX0D") - sx - sdy * t("EC0D")),
                ("EZ0D", e("EZ0D") - sdz + sdy * t("EA0D") / c("EC0D")),
                ("EX0C", e("EX0C") + sz * t("EB0C") + sdy * t("EC0D")),
                (
                    "EY0C",
                    e("EY0C") - (sy + sz) / 2.0 - sz * t("EA0C") / c("EB0C")
                        + sdy * h * t("EA0D") / c("EC0D"),
                ),
            ],
            "head_d45_table_c" => vec![
                ("EX0D", e("EX0D") - sx - sdy * t("EC0D")),
                ("EZ0D", e("EZ0D") - sdz + sdy * t("EA0D") / c("EC0D")),
                c_abs[0],
                c_abs[1],
            ],
            "trunnion_ac" => vec![
                ("EY0A", e("EY0A") - sy + sx * t("EC0A")),
                ("EZ0A", e("EZ0A") - sz - sx * t("EB0A") / c("EC0A")),
                ("EX0C", e("EX0C") - sx + sz * t("EB0C")),
                (
                    "EY0C",
                    e("EY0C") - sz * t("EA0C") / c("EB0C") - sx * t("EC0A"),
                ),
            ],
            other => panic!("{other}"),
        };
        for (n, w) in want {
            let got = get(&k, &a, n);
            assert!((got - w).abs() < 1e-9, "{name} {n}: {got} vs {w}");
        }
        // Orientations and zero angles are not moved by s.
        for ax in &k.rotary {
            for n in &ax.error_names[2..] {
                assert_eq!(
                    get(&k, &a, n.as_str()),
                    get(&k, &s, n.as_str()),
                    "{name} {n}"
                );
            }
        }
    }
}

/// The zero-angle error (EB0D here; EB0B, EC0C and EA0A alike) is added to the commanded
/// angle: unlike the four line errors it turns the axis at D = 0 too. On table_d45_c, EB0D
/// turns the table by -EB0D about the D line at D = 0 (the table top tilts by EB0D/sqrt2
/// towards -X) and every D pose reads as D + EB0D; on head_d45_table_c it turns the head by
/// +EB0D at D = 0, moving the tip by (I - R) q_D and tilting the tool. The line errors
/// EX0D, EZ0D, EA0D, EC0D leave the zero pose alone.
#[test]
fn the_zero_angle_error_turns_a_d_axis_at_d_0_and_the_line_errors_do_not() {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let u = Vec3::new(0.0, h, h);
    let eps = 100e-6;
    // table_d45_c.
    let k = machine("table_d45_c");
    let mut lines_only = k.nominal_state();
    for (n, v) in [
        ("EX0D", 20.0),
        ("EZ0D", -15.0),
        ("EA0D", 80.0),
        ("EC0D", -60.0),
    ] {
        set(&k, &mut lines_only, n, v);
    }
    let t = k.pose_transform(&lines_only, &[0.0, 0.0]);
    assert!(close(t.vector(&Vec3::z()), Vec3::z(), 1e-15) && t.t.norm() < 1e-15);
    let mut s = k.nominal_state();
    set(&k, &mut s, "EB0D", eps * 1e6);
    let t = k.pose_transform(&s, &[0.0, 0.0]);
    let rot = driftwatch_core::geometry::rotation(&u, -eps);
    assert!((t.r - rot).norm() < 1e-15 && t.t.norm() < 1e-15);
    // The table top tilts by eps/sqrt2 towards -X; the setter's point (0, -100, 70) moves
    // by -eps u x p = -eps (170, 0, 0)/sqrt2 (along the beam), the beam rises along +X.
    let normal = t.vector(&Vec3::z());
    assert!(
        (normal.x + eps * h).abs() < 1e-8 && normal.y.abs() < 1e-8,
        "{normal}"
    );
    let (p, dir) = k.beam_in_machine(&s, &[0.0, 0.0]);
    assert!(close(p, rot * Vec3::new(0.0, -100.0, 70.0), 1e-12));
    assert!(
        close(p, Vec3::new(-170.0 * h * eps, -100.0, 70.0), 1e-6),
        "{p}"
    );
    assert!((dir.z - eps * h).abs() < 1e-8 && (dir.y + eps * h).abs() < 1e-8);
    // Elsewhere it reads as a commanded D + EB0D, whatever the pose.
    for (d, c) in [(0.0, -90.0), (-90.0, -135.0), (180.0, 0.0)] {
        let a = k.pose_transform(&s, &[d, c]);
        let b = k.pose_transform(&k.nominal_state(), &[d + eps.to_degrees(), c]);
        assert!((a.r - b.r).norm() < 1e-12 && (a.t - b.t).norm() < 1e-12);
    }
    // So the C cycle at D = 0 sees it: the end face reads the beam's slope, r eps/sqrt2.
    let ap = Approach {
        axis: Axis::Z,
        direction: -1,
        feed_mm_min: 100.0,
    };
    let at = Vec3::new(0.0, -100.0, 0.0);
    let z0 = latched(&k, &k.nominal_state(), &[0.0, 0.0], &ap, &at, None).unwrap();
    let z1 = latched(&k, &s, &[0.0, 0.0], &ap, &at, None).unwrap();
    let slope_rise = 5.0 * eps * h;
    assert!((z1 - z0 - slope_rise).abs() < 1e-5, "{}", z1 - z0);
    // head_d45_table_c: the head turns by +EB0D about the D line, 200 mm above the tip.
    let k = machine("head_d45_table_c");
    let mut lines_only = k.nominal_state();
    for (n, v) in [
        ("EX0D", 20.0),
        ("EZ0D", -15.0),
        ("EA0D", 80.0),
        ("EC0D", -60.0),
    ] {
        set(&k, &mut lines_only, n, v);
    }
    let t = k.pose_geometry(&lines_only, &[0.0, 0.0]).tool;
    assert!(close(t.actual, Vec3::zeros(), 1e-15) && close(t.axis, Vec3::z(), 1e-15));
    let mut s = k.nominal_state();
    set(&k, &mut s, "EB0D", eps * 1e6);
    let t = k.pose_geometry(&s, &[0.0, 0.0]).tool;
    let q = Vec3::new(0.0, 0.0, 200.0);
    let rot = driftwatch_core::geometry::rotation(&u, eps);
    assert!(close(t.nominal, Vec3::zeros(), 1e-15));
    assert!(close(t.actual, q - rot * q, 1e-15), "{}", t.actual);
    assert!(close(t.axis, rot * Vec3::z(), 1e-15));
    // About -200 mm eps/sqrt2 along X: -14.1 um.
    assert!((t.actual.x + 200.0 * eps * h).abs() < 1e-8, "{}", t.actual);
    // Held at 0, a real EB0D is read as other errors (the contract's figures, noise-free):
    // on the D table mostly as EB0C near -EB0D/sqrt2, on the D head as the tip's shift at
    // D = 0 in EX0D and EX0C alike.
    for (name, want) in [
        ("table_d45_c", vec![("EB0C", -80.0, -65.0)]),
        (
            "head_d45_table_c",
            vec![("EX0D", 13.6, 14.0), ("EX0C", 13.6, 14.0)],
        ),
    ] {
        let k = machine(name);
        for p in [own_plan(&k), Plan::build(&k, &patent_config(&k)).unwrap()] {
            let mut truth = k.nominal_state();
            set(&k, &mut truth, "EB0D", eps * 1e6);
            let obs = p.observations(&k, &truth).unwrap();
            let sol = identify(&k, &obs, &SolveOptions::new(0.5)).unwrap();
            for (n, lo, hi) in &want {
                let v = sol.error(n).unwrap().value;
                assert!(*lo < v && v < *hi, "{name} {}: {n} {v}", p.name);
            }
        }
    }
}
