//! `plan_design` against the shipped plans and the solver: the drift alias of the patent plans,
//! the designed plan read back, the Pareto front, where `patent` sits, a budget too small.

use std::sync::OnceLock;

use driftwatch_core::identify::{Identifier, Observation, SolveOptions, mean_time_ns};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::measurement::Axis;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::plan_design::{
    DesignError, DesignOptions, PlanDesign, Weight, design, evaluate, pareto_front,
};
use driftwatch_core::units::ns_to_min;

const SIGMA_UM: f64 = 0.5;

fn table_bc() -> Kinematics {
    Kinematics::builtin("table_bc").unwrap()
}

/// The default design for table_bc (unit weights, the patent's 57.8 s as budget), run once for
/// the tests that read it.
fn default_design() -> &'static PlanDesign {
    static D: OnceLock<PlanDesign> = OnceLock::new();
    D.get_or_init(|| {
        design(
            &table_bc(),
            &PlanConfig::load("patent").unwrap(),
            &DesignOptions::new(SIGMA_UM),
        )
        .unwrap()
    })
}

fn template(k: &Kinematics, cfg: &PlanConfig) -> Vec<Observation> {
    Plan::build(k, cfg)
        .unwrap()
        .observations(k, &k.nominal_state())
        .unwrap()
}

#[test]
fn time_symmetric_patent_has_no_drift_alias_and_the_sequential_one_has() {
    let k = table_bc();
    let opts = DesignOptions::new(SIGMA_UM);
    let sym = evaluate(&k, &PlanConfig::load("patent").unwrap(), &opts).unwrap();
    let seq = evaluate(&k, &PlanConfig::load("patent_sequential").unwrap(), &opts).unwrap();
    assert!(sym.alias_ok(), "{}", sym.max_alias);
    assert!(
        sym.max_alias < 1e-6 * sym.worst,
        "patent: {} on {}",
        sym.max_alias,
        sym.max_alias_at
    );
    assert!(
        !seq.alias_ok(),
        "patent_sequential passes: {}",
        seq.max_alias
    );
    // The sequential order puts a large part of a sigma per um/min into the orientations.
    assert!(
        seq.max_alias > 0.15 * seq.worst,
        "{} on {}",
        seq.max_alias,
        seq.max_alias_at
    );
}

/// The alias is what the solver really does: a drift of 1 um/min along Z added to noise-free
/// readings of the sequential plan moves the estimates by the predicted biases.
#[test]
fn drift_alias_predicts_the_solver_bias() {
    let k = table_bc();
    let cfg = PlanConfig::load("patent_sequential").unwrap();
    let e = evaluate(&k, &cfg, &DesignOptions::new(SIGMA_UM)).unwrap();
    let obs = template(&k, &cfg);
    let t_ref = mean_time_ns(obs.iter().map(|o| o.t_ns));
    let id = Identifier::new(&k, &obs, &SolveOptions::new(SIGMA_UM)).unwrap();
    for alias in &e.alias {
        let drifted: Vec<Observation> = obs
            .iter()
            .map(|o| {
                let mut o = o.clone();
                if o.approach.axis == alias.axis {
                    // identify.rs: a drift rate v moves a reading by -v (t - t_ref), um.
                    o.position[alias.axis.index()] -= 1e-3 * ns_to_min(o.t_ns - t_ref);
                }
                o
            })
            .collect();
        let sol = id.solve(&drifted).unwrap();
        // Within 5 %: the alias is linear at the nominal state, the solver is not; a z touch
        // under a beam tilted by the aliased EA0C/EB0C trips r |tilt| higher (physics 1.3),
        // r / R = 5 % of the orientation's own sensitivity.
        for (est, bias) in sol.errors.iter().zip(&alias.bias) {
            assert!(
                (est.value - bias).abs() < 2e-3 + 0.05 * bias.abs(),
                "drift along {}: {} estimated {} against alias {}",
                alias.axis.name(),
                est.name,
                est.value,
                bias
            );
        }
    }
    assert!(e.alias.iter().any(|a| a.axis == Axis::Z));
}

#[test]
fn tip_weight_scales_orientations_by_the_lever() {
    let k = table_bc();
    let cfg = PlanConfig::load("patent").unwrap();
    let mut opts = DesignOptions::new(SIGMA_UM);
    let unit = evaluate(&k, &cfg, &opts).unwrap();
    opts.weight = Weight::Tip { lever_mm: 200.0 };
    let tip = evaluate(&k, &cfg, &opts).unwrap();
    for ((s, w), u) in tip.sigmas.iter().zip(&tip.weighted).zip(&unit.weighted) {
        let f = if s.unit == "urad" { 0.2 } else { 1.0 };
        assert!((w - u * f).abs() < 1e-12, "{}: {w} vs {u}", s.name);
    }
    let max = tip.weighted.iter().copied().fold(0.0, f64::max);
    assert_eq!(tip.worst, max);
}

#[test]
fn designed_plan_read_back_has_the_reported_sigmas() {
    let d = default_design();
    let k = table_bc();
    let text = toml::to_string(&d.chosen.config).unwrap();
    let path =
        std::env::temp_dir().join(format!("driftwatch-designed-{}.toml", std::process::id()));
    std::fs::write(&path, &text).unwrap();
    let back = PlanConfig::load(path.to_str().unwrap()).unwrap();
    std::fs::remove_file(&path).ok();
    let plan = Plan::build(&k, &back).unwrap();
    assert!((plan.machine_time_s - d.chosen.machine_time_s).abs() < 1e-9);
    assert!(plan.machine_time_s <= d.budget_s);
    let obs = template(&k, &back);
    let id = Identifier::new(&k, &obs, &SolveOptions::new(SIGMA_UM)).unwrap();
    let cr = id.cramer_rao(&obs).unwrap();
    for (reported, e) in d.chosen.sigmas.iter().zip(&cr) {
        assert_eq!(reported.name, e.name);
        assert!(
            (reported.sigma - e.sigma).abs() < 1e-9 * e.sigma,
            "{}: {} vs {}",
            e.name,
            reported.sigma,
            e.sigma
        );
    }
    let worst = cr
        .iter()
        .take(k.identify.len())
        .map(|e| e.sigma)
        .fold(0.0, f64::max);
    assert!((worst - d.chosen.worst).abs() < 1e-9 * worst);
}

#[test]
fn pareto_front_is_sorted_and_non_dominated() {
    let d = default_design();
    assert!(d.front.len() >= 3, "front of {}", d.front.len());
    for w in d.front.windows(2) {
        assert!(w[0].machine_time_s <= w[1].machine_time_s);
        assert!(
            w[1].worst < w[0].worst,
            "{} then {}",
            w[0].worst,
            w[1].worst
        );
    }
    for e in &d.front {
        assert!(e.alias_ok());
    }
    // Nothing on the front beats the chosen plan within the budget.
    assert!(
        d.front
            .iter()
            .filter(|e| e.machine_time_s <= d.budget_s)
            .all(|e| e.worst >= d.chosen.worst)
    );
    // And the front of the front is itself.
    let refs: Vec<_> = d.front.iter().collect();
    assert_eq!(pareto_front(&refs).len(), d.front.len());
}

/// Where the shipped `patent` plan sits: never below the front (it is one of the plans
/// searched), but not near it either: with the setter nuisances still estimated, the search
/// finds plans (repeated touches, B = +-45 poses) with a worst sigma (EA0C) a third lower in
/// the same time, the design goal's second figure. Its first (the patent's worst sigma in 60 % of
/// its time) is not reached: the front needs about 71 %.
#[test]
fn patent_sits_above_the_front_on_table_bc() {
    let d = default_design();
    let r = &d.reference;
    let ratio = r.ratio.unwrap();
    assert!(ratio >= 1.0 - 1e-9, "patent below its own front: {ratio}");
    assert!(d.chosen.machine_time_s <= r.evaluation.machine_time_s);
    assert!(
        d.chosen.worst <= 0.75 * r.evaluation.worst,
        "{} vs {}",
        d.chosen.worst,
        r.evaluation.worst
    );
    // Every setter nuisance the patent estimates, the chosen plan estimates too.
    for n in r
        .evaluation
        .nuisances
        .iter()
        .filter(|n| n.starts_with("setter"))
    {
        assert!(d.chosen.nuisances.contains(n), "{n} held");
    }
    assert!(r.front_time_at_worst.unwrap() < r.evaluation.machine_time_s);
}

#[test]
fn a_budget_too_small_is_refused_with_the_reason() {
    let k = table_bc();
    let mut opts = DesignOptions::new(SIGMA_UM);
    opts.budget_s = Some(8.0);
    let err = design(&k, &PlanConfig::load("patent").unwrap(), &opts).unwrap_err();
    let text = err.to_string();
    match &err {
        DesignError::Infeasible {
            budget_s,
            fastest_s,
            reason,
        } => {
            assert_eq!(*budget_s, 8.0);
            assert!(fastest_s.is_some_and(|f| f > 8.0), "{text}");
            assert!(reason.contains("cannot"), "{text}");
        }
        other => panic!("expected Infeasible, got {other:?}"),
    }
    assert!(text.contains("8.0 s"), "{text}");
}

/// Two runs of a design give the same plans, evaluation for evaluation (a 25-s budget keeps
/// the two searches short; the default run is shared by the other tests).
#[test]
fn the_search_is_deterministic() {
    let k = table_bc();
    let mut opts = DesignOptions::new(SIGMA_UM);
    opts.budget_s = Some(25.0);
    let reference = PlanConfig::load("patent").unwrap();
    let a = design(&k, &reference, &opts).unwrap();
    let b = design(&k, &reference, &opts).unwrap();
    assert!(a.evaluated > 1000, "{}", a.evaluated);
    assert_eq!(a.evaluated, b.evaluated);
    assert_eq!(a.chosen.poses_text(&k), b.chosen.poses_text(&k));
    assert_eq!(a.chosen.worst, b.chosen.worst);
    let fa: Vec<_> = a.front.iter().map(|e| e.poses_text(&k)).collect();
    let fb: Vec<_> = b.front.iter().map(|e| e.poses_text(&k)).collect();
    assert_eq!(fa, fb);
}
