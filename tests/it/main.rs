//! The root package's integration tests, one module per subject, in one test binary: the
//! service, its dependencies (tokio, sqlx, axum, async-opcua, ...) and the helpers of `common`
//! are compiled and linked once instead of once per subject.
//!
//! Run one subject with a module filter: `cargo test --test it -- api::` (several:
//! `-- api:: daemon::`), one test by its path (`-- faults::a_restart_restores`), the ignored ones with
//! `-- located:: --ignored`. `./test.sh` runs the modules that take their store from `common`
//! again on PostgreSQL the same way.
//!
//! Every module runs in this one process at the same time as the others, so none may rely on
//! being alone in it: scratch directories carry the module's prefix, the throwaway PostgreSQL
//! server of `common` is one for the process (each data directory its own database), the
//! services have their own metrics recorders (none global), and no test sets an environment
//! variable or changes the current directory (`set_var` and `set_current_dir` would reach
//! every other test).

mod common;

mod api;
mod cli;
mod conformance;
mod crash;
mod daemon;
mod diagnosis;
mod displacement;
mod faults;
mod fleet;
mod located;
mod nc_cli;
mod nc_offsets;
mod nc_push;
mod opcua;
mod service;
mod solver;
mod thermal;
mod verification;
mod webhook;
