//! The decisions of one machine, without I/O: its thermal phase from the stream of spindle
//! speeds and NC states, when the next measurement cycle is due, the validation of a cycle
//! result and the compensation sets built from it, the thermal model as a machine keeps it,
//! alerts, and the comparison of its results with a reference instrument's (verification). Times come in as arguments; nothing here awaits, sleeps or touches storage.

pub mod alerts;
pub mod compensation;
pub mod link_event;
pub mod live_model;
pub mod machine_core;
pub mod nc_door;
pub mod nc_offsets;
pub mod phase;
pub mod scheduler;
pub mod tool_tip;
pub mod verification;
