//! Where a model and a recording differ (docs/physics.md 4): the cycle diagnosis (`cycles`) over
//! detections as rows (`rows`) and the library of candidate effects (`effects`); the
//! displacement diagnosis of thermal-test recordings (`displacement`); the surrogate series its
//! tests of significance compare with (`surrogates`); the HTML report (`report`). Pure code: no I/O, deterministic for a given seed.

pub mod cycles;
pub mod displacement;
pub mod effects;
pub mod report;
pub mod rows;
mod stepwise;
pub mod surrogates;
