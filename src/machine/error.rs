//! Why a machine model or its file could not be built or read.

use crate::comp::mapping::MachineAxis;
use thiserror::Error;

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
