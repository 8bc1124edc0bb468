//! The displacement diagnosis on real data from another lab (fl-thermal, MIT;
//! tests/data/fl-thermal): 46 h of a spindle thermal test with 5 displacement probes and 16
//! temperatures. Trained on 0-40 h, held out 40-46.3 h. Figures:
//! `cargo test --release --test displacement -- --nocapture`.

use driftwatch::csv_import::{CsvOptions, RowTime, import_csv};
use driftwatch::displacement_diagnosis::{
    DisplacementDiagnosis, DisplacementOptions, diagnose_displacements,
};
use driftwatch::thermal_model::{ModelInput, events_from};

const H: i64 = 3_600_000_000_000;

fn diagnosis() -> DisplacementDiagnosis {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/fl-thermal/fl_thermal.csv"
    ))
    .unwrap();
    let channels: Vec<String> = (1..=5).map(|i| format!("ch{i}_um")).collect();
    let im = import_csv(
        &text,
        &CsvOptions {
            time: RowTime::Column("time_s".into()),
            start_ns: 0,
            spindle: Some("spindle_rpm".into()),
            temperatures: (1..=16).map(|i| format!("t{i}_C")).collect(),
            displacements: channels.clone(),
            machine_id: "fl-thermal".into(),
        },
    )
    .unwrap();
    let ev = events_from(&[im.recording]);
    let opts = DisplacementOptions {
        n_ref_rpm: 5000.0,
        holdout_from_ns: Some(40 * H),
        ..Default::default()
    };
    diagnose_displacements(&ev, &channels, &opts).unwrap()
}

fn channel<'a>(
    d: &'a DisplacementDiagnosis,
    name: &str,
) -> &'a driftwatch::displacement_diagnosis::ChannelDiagnosis {
    d.channels.iter().find(|c| c.channel == name).unwrap()
}

#[test]
fn fl_thermal_diagnosis() {
    let d = diagnosis();
    for c in &d.channels {
        println!(
            "{}: one mode {} min {:.2} um; held-out RMS {:.2} -> {:.2} um, training {:.2} -> {:.2} um",
            c.channel,
            c.baseline_mode.as_ref().unwrap().tau_min,
            c.baseline_mode.as_ref().unwrap().gain_um,
            c.baseline.rms_heldout_um,
            c.final_fit.rms_heldout_um,
            c.baseline.rms_train_um,
            c.final_fit.rms_train_um
        );
        for s in &c.statements {
            println!("  {s}");
        }
        // The spindle-only baseline leaves structure; every channel's held-out fit improves.
        assert!(c.baseline.ljung_box_p < 1e-3, "{}", c.channel);
        assert!(
            c.final_fit.rms_heldout_um < 0.9 * c.baseline.rms_heldout_um,
            "{}: {:?} -> {:?}",
            c.channel,
            c.baseline,
            c.final_fit
        );
    }

    // The ~25-min periodic residual of ch1 and ch2, its driver among the 16 temperatures, and
    // the term that models it first, with a better held-out fit.
    for name in ["ch1_um", "ch2_um"] {
        let c = channel(&d, name);
        let p = c.periodic.as_ref().unwrap();
        assert!((20.0..=30.0).contains(&p.period_min), "{p:?}");
        assert_eq!(p.driver.as_deref(), Some("t4_C"), "{p:?}");
        assert!(p.matched && p.driver_r > 0.5, "{p:?}");
        let first = &c.accepted[0];
        assert!(
            matches!(&first.input, ModelInput::Temperature { sensor, .. } if sensor == "t4_C"),
            "{first:?}"
        );
        assert!(first.delta_bic >= 10.0 && first.t.abs() >= 4.0);
        assert!(c.final_fit.rms_heldout_um < 0.8 * c.baseline.rms_heldout_um);
    }
    assert!(
        channel(&d, "ch1_um").accepted[0].heldout_after_um
            < 0.85 * channel(&d, "ch1_um").baseline.rms_heldout_um
    );

    // The post-stop overshoot of ch5: after most stops the displacement leaves the range a
    // single mode moves in; the baseline cannot follow, a second mode of opposite sign does.
    let c5 = channel(&d, "ch5_um");
    let stops: Vec<_> = c5.transients.iter().filter(|t| t.to_rpm == 0.0).collect();
    assert!(stops.len() >= 4, "{:?}", c5.transients);
    assert!(
        stops
            .iter()
            .all(|t| t.excursion_um >= 2.0 && t.baseline_excursion_um < 0.5)
    );
    let opposite = c5.accepted.iter().any(|t| {
        t.effect == "second_mode"
            && t.value.signum() != c5.baseline_mode.as_ref().unwrap().gain_um.signum()
    });
    assert!(opposite, "{:?}", c5.accepted);
    let made: f64 = stops.iter().map(|t| t.final_excursion_um).sum::<f64>()
        / stops.iter().map(|t| t.excursion_um).sum::<f64>();
    println!(
        "ch5: the final model makes {:.0} % of the measured post-stop overshoot",
        100.0 * made
    );
    assert!(made > 0.6, "{made}");

    // The new model version carries the accepted inputs.
    assert!(d.model.temperatures.iter().any(|t| t.sensor == "t4_C"));
    assert!(d.model.taus_min.len() >= 2);
}
