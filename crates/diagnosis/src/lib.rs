//! Where a model and a recording differ (docs/physics.md 4): the cycle diagnosis (`cycles`) over
//! detections as rows (`rows`) and the library of candidate effects (`effects`); the
//! displacement diagnosis of thermal-test recordings (`displacement`); null recordings that look
//! like real data (`surrogates`) and the diagnosis' calibration on them (`calibration`); the
//! HTML report (`report`). Pure code: no I/O, deterministic for a given seed.

pub mod calibration;
pub mod cycles;
pub mod displacement;
pub mod effects;
pub mod report;
pub mod rows;
mod stepwise;
pub mod surrogates;
