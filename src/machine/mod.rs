//! The whole machine (issue 27): three linear axes in a kinematic chain, their 21 geometric
//! errors after ISO 230-1 (`model`), the tool point's volumetric error anywhere in the volume,
//! an axis's table from what the head measured on it (`from_head`, refined between the targets
//! by a spline), the squarenesses from two axes' straightness against one beam turned by an
//! optical square (`squareness`), and what the controls compensate by, each file with its one
//! reader: `isg_csv` (Beckhoff TwinCAT's volumetric file), `heidenhain` (KinematicsComp's COM
//! tables and the kinematics excerpt), `fanuc_grid` (the model at a grid's corners, `grid`, as
//! FANUC's three-dimensional compensation interpolates them), `siemens` (EEC and CEC tables);
//! `volume` surveys the tool point's error over the volume, uncompensated or as a control's
//! compensation leaves it.
//! Each module states what of its format is confirmed from which manual page and what is not.
//!
//! Held against the twin's machine (`sim::machine`), which composes the same chain exactly and
//! applies a loaded file or a grid as its CNC would; `sim::machine_lab` measures it set-up by
//! set-up through the product's path; `commission` keeps the machine record, its plan and its
//! report.

mod error;
pub mod exports;
pub mod fanuc_grid;
pub mod from_head;
pub mod grid;
pub mod heidenhain;
pub mod isg_csv;
pub mod model;
pub mod siemens;
pub mod squareness;
pub mod volume;

pub use error::MachineError;
pub use grid::Grid;
pub use model::{Chain, ComponentTable, MachineModel, Squareness, Volumetric, component_names};

#[cfg(test)]
mod tests;
