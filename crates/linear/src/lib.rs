//! The linear axes (seed 004): their component errors and the laser step diagonal
//! measurement that finds straightness and squareness with a laser interferometer alone.
//!
//! Pure library code: no I/O, deterministic for a seed. [`axis_errors`] is the simulation's
//! model of the three axes' errors (positioning, straightness, squareness, as functions of the
//! commanded position); [`step_diagonal`] simulates the measurement on the four body diagonals
//! with set-up errors, noise and drift, and solves it with the conventional nine-unknown
//! formulation and with the set-up-robust one; [`correction_table`] is seed 003's in-process
//! correction table of a faced part and its cut-measure-correct loop.

pub mod axis_errors;
pub mod correction_table;
pub mod step_diagonal;
