//! The truth simulator and what runs on it: scenarios (spindle program, noise, effects, the
//! virtual machine's thermal channels), the virtual machine driven through a scenario, the
//! patent experiment. Pure code:
//! randomness only from seeded generators.

pub mod experiment;
pub mod scenario;
pub mod simulator;
