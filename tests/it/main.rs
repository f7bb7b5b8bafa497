//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;

mod calibration;
mod can;
mod cli;
mod comp;
mod decoupling;
mod evaluate;
mod socketcan;
mod store;
