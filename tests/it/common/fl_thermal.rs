//! fl-thermal (MIT; tests/data/fl-thermal) as events, for the tests that judge models and
//! diagnoses on it (`thermal`, `displacement`, `located`).

use driftwatch_recording::csv_import::{CsvOptions, RowTime, import_csv};
use driftwatch_thermal::model::{Event, events_from};

/// fl-thermal imported with or without its spindle column, all 16 temperatures and
/// `channels`; every row and cell read.
pub fn events(spindle: bool, channels: &[&str]) -> Vec<Event> {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/fl-thermal/fl_thermal.csv"
    ))
    .unwrap();
    let im = import_csv(
        &text,
        &CsvOptions {
            time: RowTime::Column("time_s".into()),
            start_ns: 0,
            spindle: spindle.then(|| "spindle_rpm".into()),
            temperatures: (1..=16).map(|i| format!("t{i}_C")).collect(),
            displacements: channels.iter().map(|c| c.to_string()).collect(),
            machine_id: "fl-thermal".into(),
        },
    )
    .unwrap();
    assert_eq!(im.rows, 11115);
    assert!(im.skipped.is_empty(), "{:?}", im.skipped);
    events_from(&[im.recording])
}

/// The five displacement channels.
pub const CHANNELS: [&str; 5] = ["ch1_um", "ch2_um", "ch3_um", "ch4_um", "ch5_um"];
