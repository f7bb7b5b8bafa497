//! The integration tests: one binary, modules by capability, shared helpers.

mod helpers;
mod lab;

mod acquire;
mod align;
mod calibration;
mod can;
mod canopen;
mod cli;
mod comp;
mod comp_export;
mod console;
mod csv_inputs;
mod decoupling;
mod docs;
mod evaluate;
mod follower;
mod follower_selfcal;
mod follower_service;
mod fuzz;
mod hexapod;
mod hexapod_along;
mod hexapod_service;
mod links;
mod machine;
mod maintenance;
mod modbus;
mod plc;
mod ranges;
mod report;
mod report_budget;
mod service;
mod socketcan;
mod store;
mod trend;
mod user_text;
