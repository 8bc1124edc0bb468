//! The lab's cross-checks against the truth simulator, one binary (the lab links the whole
//! service): the NC programs' golden files replayed, and the R-test against the tool setter.

mod nc_programs;
mod rtest_cross_instrument;
