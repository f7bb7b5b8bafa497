//! The whole machine (issue 27): three linear axes in a kinematic chain, their 21 geometric
//! errors after ISO 230-1 (`model`), the tool point's volumetric error anywhere in the volume,
//! an axis's table from what the head measured on it (`from_head`), and what the controls
//! compensate by (`isg_csv`: Beckhoff TwinCAT's file; `grid`: the model at a grid's corners,
//! as FANUC's three-dimensional compensation interpolates them).
//!
//! So far the model, its first-order error at the tool, the grid and the Beckhoff file, held
//! against the twin's machine (`sim::machine`), which composes the same chain exactly and
//! applies a loaded file or a grid as its CNC would. Running each axis through the measuring
//! path into `from_head`, the squarenesses with an optical square, and the other controls'
//! files come next.

mod error;
pub mod from_head;
pub mod grid;
pub mod isg_csv;
pub mod model;

pub use error::MachineError;
pub use grid::Grid;
pub use model::{Chain, ComponentTable, MachineModel, Squareness, Volumetric, component_names};

#[cfg(test)]
mod tests;
