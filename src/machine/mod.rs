//! The whole machine (issue 27): three linear axes in a kinematic chain, their 21 geometric
//! errors after ISO 230-1 (`model`), the tool point's volumetric error anywhere in the volume,
//! an axis's table from what the head measured on it (`from_head`), and the controls'
//! volumetric compensation files (`isg_csv`: Beckhoff TwinCAT's; `grid`: the model at a grid's corners, as FANUC's
//! three-dimensional compensation interpolates them).
//!
//! So far the model, its first-order error at the tool, the grid and the Beckhoff file, held
//! against the twin's machine (`sim::machine`), which composes the same chain exactly and
//! applies a loaded file or a grid as its CNC would. Running each axis through the measuring
//! path into `from_head`, the squarenesses with an optical square, and the other controls'
//! files come next.

pub mod from_head;
pub mod grid;
pub mod isg_csv;
pub mod model;

pub use grid::Grid;
pub use model::{Chain, ComponentTable, MachineModel, Squareness, component_names};

use crate::comp::mapping::MachineAxis;
use thiserror::Error;

/// What a control compensates by: the tool point's error (mm, machine X, Y, Z) it expects at
/// a commanded position (mm) with a tool offset (mm).
pub trait Volumetric {
    fn error_at(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3];
}

impl Volumetric for MachineModel {
    fn error_at(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3] {
        MachineModel::error_at(self, cmd, tool)
    }
}

/// Why a machine model or its file could not be built or read.
#[derive(Debug, Error)]
pub enum MachineError {
    #[error("component errors of {axis}: {problem}")]
    Table { axis: MachineAxis, problem: String },
    #[error("chain {chain}: {problem}")]
    Chain { chain: String, problem: String },
    #[error("machine model: {0}")]
    Missing(String),
    #[error("{path}, line {line}: {problem}")]
    File {
        path: String,
        line: usize,
        problem: String,
    },
    #[error("{path}: {problem}")]
    Io { path: String, problem: String },
}

#[cfg(test)]
mod tests;
