//! A model's files for every control, written to a directory and read back by each format's
//! own reader: what the control would load, ready for the twin's CNC to apply
//! (`sim::machine::TwinMachine::volumetric`) against the model itself.

use super::error::MachineError;
use super::grid::Grid;
use super::model::{MachineModel, Volumetric};
use super::{fanuc_grid, heidenhain, isg_csv, siemens};
use std::path::{Path, PathBuf};

/// FANUC's grid is no coarser than this (mm). The trilinear blend between corners cuts the
/// axes' shorter waves: on the twin's machine (seed 101, 1000 points, a 150 mm tool) the model
/// compensates to 1.56 µm largest and 0.80 µm RMS; the model sampled at the corners of a 25 mm
/// grid to 2.95 and 1.31, of 10 mm to 1.58 and 0.81 (101 × 61 × 51 corners, a file of 13 MB),
/// of 5 mm as the model; the 10 mm grid curvature-balanced (as written) to 1.52 and 0.80. How
/// many corners a FANUC control takes is not confirmed (see `fanuc_grid`).
pub const GRID_STEP_MM: f64 = 10.0;
/// Siemens's tables are no coarser than this (mm), the model's own step.
pub const TABLE_STEP_MM: f64 = 5.0;

/// One control's files, read back.
pub struct Export {
    pub control: &'static str,
    /// The file, or the directory of the control's files.
    pub path: PathBuf,
    /// What of the model the files carry, in words.
    pub carries: String,
    /// The model as read back from the files, as the control would apply it.
    pub applied: Box<dyn Volumetric>,
}

fn write_file(path: &Path, text: &str) -> Result<(), MachineError> {
    std::fs::write(path, text).map_err(|e| MachineError::Io {
        path: path.display().to_string(),
        problem: e.to_string(),
    })
}

fn write_dir(dir: &Path, files: &[(String, String)]) -> Result<(), MachineError> {
    std::fs::create_dir_all(dir).map_err(|e| MachineError::Io {
        path: dir.display().to_string(),
        problem: e.to_string(),
    })?;
    files
        .iter()
        .try_for_each(|(name, text)| write_file(&dir.join(name), text))
}

/// Write `model`'s files for Beckhoff (`volumetric-beckhoff.csv`), HEIDENHAIN (`heidenhain/`),
/// FANUC (`fanuc-grid.txt`, taken with `tool_mm`) and Siemens (`siemens/`) into `dir`, each
/// headed by `title`, and read each back.
pub fn write_and_read_back(
    model: &MachineModel,
    dir: &Path,
    title: &str,
    tool_mm: [f64; 3],
) -> Result<Vec<Export>, MachineError> {
    let mut out = Vec::new();

    let path = dir.join("volumetric-beckhoff.csv");
    write_file(
        &path,
        &isg_csv::write(model.tables(), model.squareness, title),
    )?;
    let file = isg_csv::read(&path)?;
    let squareness = file.squareness.ok_or_else(|| MachineError::Io {
        path: path.display().to_string(),
        problem: "no squarenesses read back".into(),
    })?;
    out.push(Export {
        control: "Beckhoff TwinCAT CNC (TF5280, ISG_CSV)",
        path,
        carries: "the 21 errors".into(),
        applied: Box::new(MachineModel::new(model.chain, file.tables, squareness)?),
    });

    let path = dir.join("heidenhain");
    write_dir(&path, &heidenhain::write(model, title))?;
    let back = heidenhain::read(&path)?;
    out.push(Export {
        control: "HEIDENHAIN KinematicsComp (COM tables, kinematics excerpt)",
        path,
        carries: "the 21 errors".into(),
        applied: Box::new(MachineModel::new(
            model.chain,
            back.tables,
            back.squareness,
        )?),
    });

    let (from, to): ([f64; 3], [f64; 3]) = {
        let t = model.tables();
        (
            std::array::from_fn(|k| t[k].positions_mm()[0]),
            std::array::from_fn(|k| *t[k].positions_mm().last().unwrap_or(&0.0)),
        )
    };
    let grid = Grid::of_model(model, from, to, [GRID_STEP_MM; 3], tool_mm)?.curvature_balanced();
    let path = dir.join("fanuc-grid.txt");
    write_file(&path, &fanuc_grid::write(&grid, title))?;
    out.push(Export {
        control: "FANUC three-dimensional error compensation (grid)",
        carries: format!(
            "the 21 errors at the corners of a {GRID_STEP_MM:.0} mm grid, for a tool of ({:.0}, {:.0}, {:.0}) mm",
            tool_mm[0], tool_mm[1], tool_mm[2]
        ),
        applied: Box::new(fanuc_grid::read(&path)?),
        path,
    });

    let path = dir.join("siemens");
    write_dir(&path, &siemens::write(model, TABLE_STEP_MM, title))?;
    let tables = siemens::read(&path)?;
    out.push(Export {
        control: "Siemens SINUMERIK (EEC and CEC tables)",
        path,
        carries: "positioning, straightness and squareness; not the angles (pitch, yaw, roll)"
            .into(),
        applied: Box::new(MachineModel::new(model.chain, tables, Default::default())?),
    });
    Ok(out)
}
