//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;

mod acquire;
mod calibration;
mod cli;
mod decoupling;
mod modbus;
