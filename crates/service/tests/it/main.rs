//! The service crate's integration tests, one binary (each test binary links the whole
//! service and its runtime, so one link instead of one per file): an MTConnect agent served
//! over HTTP to the `mtconnect` link, and webhooks delivered over TLS.

mod mtconnect;
mod webhook_tls;
