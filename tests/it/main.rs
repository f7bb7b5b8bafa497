//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;

mod calibration;
mod canopen;
mod cli;
mod decoupling;
