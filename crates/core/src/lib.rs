//! driftwatch's functional core: units and time, geometry, kinematics, the tool-setter
//! measurement model, cycle plans, identification, cycle checks, the contract's recording types,
//! thermal lags, least squares, statistics. The thermal model and its competing families are the
//! `driftwatch-thermal` crate's.
//!
//! Pure code: no async runtime, no database, no network, no clock, no globals; deterministic for
//! a given seed. The only I/O is the loading of TOML descriptions by name or path (`source`);
//! recordings on disk are the `driftwatch-recording` crate's. The theory is in docs/physics.md.

pub mod clearance;
pub mod cycle;
pub mod error_name;
pub mod geometry;
pub mod identify;
pub mod kinematics;
pub mod least_squares;
pub mod linear_axes;
pub mod measurement;
pub mod patent_relations;
pub mod plan;
pub mod plan_design;
pub mod recording;
pub mod source;
pub mod stats;
pub mod thermal;
pub mod units;
