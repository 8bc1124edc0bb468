//! The lab, kept apart from the product: what measures driftwatch rather than runs a machine.
//! The benchmarks behind `driftwatch bench` (`bench`, with the reader of real thermal-test
//! sets, `thermal_sets`); the compensation strategies compared on the simulator's truth
//! (`strategies`); the measurement programs replayed through the simulator (`nc_check`) and
//! the R-test against the tool setter on one simulated machine (`rtest_crosscheck`); null
//! recordings that look like real data (`null_recordings`) and the diagnosis' calibration on
//! them (`calibration`).
//!
//! The product crates never depend on this one; it may use all of them.

pub mod bench;
pub mod calibration;
pub mod nc_check;
pub mod null_recordings;
pub mod rtest_crosscheck;
pub mod strategies;
pub mod thermal_sets;
