//! The linear axes (seed 004; issue 19): their component errors and the laser step diagonal
//! measurement that finds straightness and squareness with a laser interferometer alone.
//!
//! Pure library code: no I/O, deterministic for a seed. [`axis_errors`] is the simulation's
//! model of the three axes' errors (positioning, straightness, squareness, as functions of the
//! commanded position); [`step_diagonal`] simulates the measurement on the four body diagonals
//! with set-up errors, noise and drift, and solves it with the conventional nine-unknown
//! formulation and with the set-up-robust one.

pub mod axis_errors;
pub mod step_diagonal;
