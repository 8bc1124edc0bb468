//! The R-test (seed 002; ISO 10791-6): a second, independent instrument for the rotary axes'
//! location errors, and the tool setter's check.
//!
//! Pure library code: no I/O, no clock, deterministic for a seed. The layers follow the
//! instrument's data: [`instrument`] (ball, sensors, settings, exact readings, calibration),
//! [`kinematic_test`] (the BK1, BK2 and XYC motions and their simulation on a machine state),
//! [`process`] (readings to radial, axial and tangential deviations and the test's figures),
//! [`identify`] (location errors by least squares with uncertainties and identifiability),
//! [`report`] (SVG plots and an HTML page as strings), [`recording`] (runs as the
//! `/rtest/setup` and `/rtest/reading` messages and back, and device CSV exports).

pub mod identify;
pub mod instrument;
pub mod kinematic_test;
pub mod process;
pub mod recording;
pub mod report;
