//! Why a machine model or its file could not be built or read.

use crate::comp::mapping::MachineAxis;
use std::path::Path;
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

impl MachineError {
    /// What is wrong at `line` of the file at `path`.
    pub(crate) fn at(path: &str, line: usize, problem: String) -> MachineError {
        MachineError::File {
            path: path.to_string(),
            line,
            problem,
        }
    }
}

/// The text of the file at `path` and its name for errors.
pub(crate) fn read_text(path: &Path) -> Result<(String, String), MachineError> {
    let name = path.display().to_string();
    match std::fs::read_to_string(path) {
        Ok(text) => Ok((text, name)),
        Err(e) => Err(MachineError::Io {
            path: name,
            problem: e.to_string(),
        }),
    }
}
