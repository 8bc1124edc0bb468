//! The service shell around the core: machine links (simulated, or a real NC posting to its
//! door or as an OPC UA server), the loop of each machine, SQLite storage, MCAP recorders, the HTTP API, webhook
//! delivery and the configuration. The only crate with an async runtime, a database and a
//! network.

pub mod api;
pub mod clock;
pub mod config;
pub mod daemon;
pub mod dir_lock;
pub mod fleet;
pub mod http_server;
pub mod launch;
pub mod link;
pub mod mtconnect;
pub mod mtconnect_link;
pub mod nc_push;
pub mod opcua;
pub mod recorder;
pub mod series;
pub mod store;
pub mod webhook;

/// A test's scratch directory (named after `name`) and its path; the directory is removed
/// when the first is dropped, at the test's end.
#[cfg(test)]
pub(crate) fn scratch_dir(name: &str) -> (tempfile::TempDir, std::path::PathBuf) {
    let tmp = tempfile::Builder::new()
        .prefix(&format!("driftwatch-{name}-"))
        .tempdir()
        .unwrap();
    let path = tmp.path().to_path_buf();
    (tmp, path)
}
