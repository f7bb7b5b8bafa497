//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;

mod calibration;
mod cli;
mod decoupling;
mod store;
