//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;
mod lab;

mod acquire;
mod calibration;
mod can;
mod canopen;
mod cli;
mod comp;
mod console;
mod decoupling;
mod evaluate;
mod fuzz;
mod links;
mod modbus;
mod plc;
mod resume;
mod service;
mod socketcan;
mod store;
