//! The recording format on disk (docs/recording-format.md): `mcap_io` reads and writes the
//! contract's messages (the core's `recording` types) as MCAP files, `csv_import` turns a
//! thermal-test table into a recording. The one crate of the product's pure side that touches
//! files; the message types and their schemas stay in the core, which does no I/O.

pub mod csv_import;
pub mod mcap_io;
