//! The measurement programs' golden files (the NC crate's `tests/golden`), read back and
//! replayed through the truth simulator: they measure what the plan measures.

use std::path::PathBuf;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_lab::nc_check::against_truth;
use driftwatch_nc::dialect::Dialect;
use driftwatch_sim::scenario::Scenario;

fn golden(d: Dialect) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../nc/tests/golden")
        .join(format!("patent_table_bc.{}", d.extension()))
}

/// The golden programs, read and replayed on the patent's warm machine, measure what the
/// plan measures: the same errors within 0.01 um / 0.1 urad and the same run time.
#[test]
fn golden_programs_replayed_solve_to_the_plans_errors() {
    let k = Kinematics::builtin("table_bc").unwrap();
    let plan = Plan::build(&k, &PlanConfig::load(&k.config.plan).unwrap()).unwrap();
    let scn = Scenario::load("patent").unwrap();
    for d in Dialect::ALL {
        let text = std::fs::read_to_string(golden(d)).unwrap();
        let c = against_truth(&k, &plan, &text, d, &scn, 40.0).unwrap();
        assert_eq!(c.approaches, plan.steps.len(), "{d}");
        assert_eq!(c.errors.len(), k.identify.len(), "{d}");
        // The machine is warm: the errors are not all zero, so agreement means something.
        assert!(
            c.errors.iter().any(|e| e.plan.abs() > 1.0),
            "{d}: {:?}",
            c.errors
        );
        assert!(c.worst("um") <= 0.01, "{d}: {:?}", c.errors);
        assert!(c.worst("urad") <= 0.1, "{d}: {:?}", c.errors);
        assert!(
            (c.program_time_s - c.plan_time_at_trips_s).abs() < 0.01,
            "{d}: program {} s, plan {} s at the same trips ({} s nominal)",
            c.program_time_s,
            c.plan_time_at_trips_s,
            c.plan_time_s
        );
    }
}
