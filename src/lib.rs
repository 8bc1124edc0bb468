//! driftwatch: keeps a 5-axis machine tool's rotary-axis compensation true while it heats up
//! and cools down.
//!
//! The library is the functional core: kinematics, the tool-setter measurement model, cycle
//! plans, the thermal model, the truth simulator and the identification are pure code (no I/O,
//! no globals, deterministic for a given seed). The service shell around it: `store`, `recorder`,
//! `link`, `nc_push`, `daemon`, `api`, `webhook` and the binary.

pub mod alerts;
pub mod api;
pub mod compensation;
pub mod config;
pub mod csv_import;
pub mod cycle;
pub mod daemon;
pub mod diagnosis;
pub mod diagnosis_calibration;
pub mod diagnosis_report;
pub mod displacement_diagnosis;
pub mod effects;
pub mod experiment;
pub mod families;
pub mod geometry;
pub mod identify;
pub mod kinematics;
pub mod link;
pub mod live_model;
pub mod lsq;
pub mod measurement;
pub mod nc_push;
pub mod patent_relations;
pub mod phase;
pub mod plan;
pub mod prediction_plot;
pub mod recorder;
pub mod recording;
pub mod rows;
pub mod scenario;
pub mod scheduler;
pub mod series;
pub mod simulator;
pub mod source;
pub mod stats;
pub mod store;
pub mod strategies;
pub mod surrogates;
pub mod thermal;
pub mod thermal_model;
pub mod units;
pub mod webhook;
