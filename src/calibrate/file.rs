//! The calibration file: TOML in user units (µm, arcsec, degrees) with its metadata (date,
//! layout hash, pose counts, residuals, condition number), the linear β and offset, and the
//! fitted installation errors. Loading checks the layout hash, so a calibration is never
//! applied to a head it was not made for.

use super::{CalError, Calibration, LinearFit, ModelPart};
use crate::optics::Layout;
use crate::optics::install::{ElementInstall, Installation};
use crate::units::{DOF_TO_USER, MM_PER_UM};
use nalgebra::{Matrix6, Vector6};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// File format version written by this build.
pub const FORMAT: u32 = 1;

/// The file as stored.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    pub meta: Meta,
    pub linear: LinearSection,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<ModelSection>,
}

/// `[meta]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Meta {
    pub format: u32,
    pub created: String,
    pub layout: String,
    pub layout_hash: String,
    pub poses: usize,
    pub fit_poses: usize,
    pub holdout_poses: usize,
    pub travel_mm: [f64; 2],
    /// Reading noise per channel X1..Y3 (µm), from the fit residuals.
    pub noise_um: [f64; 6],
}

/// `[linear]`: β in µm per µm / per arcsec, rows X1..Y3, columns dx..ez.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinearSection {
    pub rank: usize,
    pub rcond: f64,
    pub condition_number: f64,
    pub ref_travel_mm: f64,
    pub ref_follower_mm: f64,
    pub residual_rms_um: [f64; 6],
    /// Hold-out RMS per DOF (µm, arcsec).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout_rms: Option<[f64; 6]>,
    pub singular_values: Vec<f64>,
    pub offset_um: [f64; 6],
    pub beta: [[f64; 6]; 6],
}

/// `[model]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ModelSection {
    pub iterations: u32,
    pub converged: bool,
    pub fitted_params: usize,
    pub well_determined: usize,
    pub residual_rms_um: [f64; 6],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout_rms: Option<[f64; 6]>,
    /// Installation errors by element name.
    pub install: BTreeMap<String, InstallEntry>,
}

/// One element's fitted installation error.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct InstallEntry {
    pub offset_mm: [f64; 3],
    pub tilt_deg: [f64; 3],
    pub gain_error: [f64; 2],
}

fn um6(v: &[f64; 6]) -> [f64; 6] {
    v.map(|x| x / MM_PER_UM)
}
fn dof_user(v: &[f64; 6]) -> [f64; 6] {
    std::array::from_fn(|k| v[k] * DOF_TO_USER[k])
}
fn dof_internal(v: &[f64; 6]) -> [f64; 6] {
    std::array::from_fn(|k| v[k] / DOF_TO_USER[k])
}

impl CalibrationFile {
    /// The stored form of a calibration.
    pub fn from_calibration(c: &Calibration, nominal: &Layout) -> Self {
        let beta_user = crate::decouple::to_user_units(&c.linear.beta);
        let lin = &c.linear;
        CalibrationFile {
            meta: Meta {
                format: FORMAT,
                created: c.created.clone(),
                layout: c.layout_name.clone(),
                layout_hash: c.layout_hash.clone(),
                poses: c.poses,
                fit_poses: c.fit_poses,
                holdout_poses: c.holdout_poses,
                travel_mm: [c.travel_range.0, c.travel_range.1],
                noise_um: um6(&c.sigma_mm),
            },
            linear: LinearSection {
                rank: lin.rank,
                rcond: super::LINEAR_RCOND,
                condition_number: lin.condition_number,
                ref_travel_mm: lin.ref_travel,
                ref_follower_mm: lin.ref_follower,
                residual_rms_um: um6(&lin.residual_rms),
                holdout_rms: c.linear_holdout_rms.as_ref().map(dof_user),
                singular_values: lin.singular_values.clone(),
                offset_um: um6(&lin.offset.into()),
                beta: std::array::from_fn(|r| std::array::from_fn(|k| beta_user[(r, k)])),
            },
            model: c.model.as_ref().map(|m| ModelSection {
                iterations: m.iterations,
                converged: m.converged,
                fitted_params: m.fitted_params,
                well_determined: m.well_determined,
                residual_rms_um: um6(&m.residual_rms),
                holdout_rms: m.holdout_rms.as_ref().map(dof_user),
                install: m
                    .install
                    .to_named(nominal)
                    .into_iter()
                    .map(|(k, e)| {
                        (
                            k,
                            InstallEntry {
                                offset_mm: e.offset,
                                tilt_deg: e.tilt.map(f64::to_degrees),
                                gain_error: e.gain_error,
                            },
                        )
                    })
                    .collect(),
            }),
        }
    }

    /// Back to a calibration for `nominal`, checking the layout hash and the values.
    pub fn to_calibration(&self, nominal: &Layout, label: &str) -> Result<Calibration, CalError> {
        let bad = |problem: String| CalError::File {
            path: label.to_string(),
            problem,
        };
        if self.meta.format != FORMAT {
            return Err(bad(format!(
                "format {} is not supported (this build reads format {FORMAT}): re-run calibrate fit",
                self.meta.format
            )));
        }
        if self.meta.layout_hash != nominal.hash() {
            return Err(bad(format!(
                "made for layout {} ({}), but the layout in use is {} ({}): pass the layout it was made with (--layout) or calibrate again",
                self.meta.layout,
                self.meta.layout_hash,
                nominal.name,
                nominal.hash()
            )));
        }
        let finite = |name: &str, v: &[f64]| {
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(bad(format!("{name} has a non-finite value")))
            }
        };
        finite("meta.noise_um", &self.meta.noise_um)?;
        if self.meta.noise_um.iter().any(|x| *x <= 0.0) {
            return Err(bad("meta.noise_um must be positive on every channel".into()));
        }
        finite("linear.offset_um", &self.linear.offset_um)?;
        for (r, row) in self.linear.beta.iter().enumerate() {
            finite(&format!("linear.beta row {}", r + 1), row)?;
        }
        let mut beta_user = Matrix6::zeros();
        for r in 0..6 {
            for k in 0..6 {
                beta_user[(r, k)] = self.linear.beta[r][k];
            }
        }
        // Back from µm per user unit to mm per internal unit.
        let mut beta = beta_user;
        for k in 0..6 {
            let s = MM_PER_UM * DOF_TO_USER[k];
            for r in 0..6 {
                beta[(r, k)] *= s;
            }
        }
        if beta.try_inverse().is_none() {
            return Err(bad("linear.beta is singular".into()));
        }
        let linear = LinearFit {
            beta,
            offset: Vector6::from(self.linear.offset_um) * MM_PER_UM,
            ref_travel: self.linear.ref_travel_mm,
            ref_follower: self.linear.ref_follower_mm,
            rank: self.linear.rank,
            singular_values: self.linear.singular_values.clone(),
            residual_rms: self.linear.residual_rms_um.map(|x| x * MM_PER_UM),
            condition_number: self.linear.condition_number,
        };
        let model = match &self.model {
            None => None,
            Some(m) => {
                let mut named = BTreeMap::new();
                for (name, e) in &m.install {
                    let all: Vec<f64> = e
                        .offset_mm
                        .iter()
                        .chain(&e.tilt_deg)
                        .chain(&e.gain_error)
                        .copied()
                        .collect();
                    finite(&format!("model.install.{name}"), &all)?;
                    named.insert(
                        name.clone(),
                        ElementInstall {
                            offset: e.offset_mm,
                            tilt: e.tilt_deg.map(f64::to_radians),
                            gain_error: e.gain_error,
                        },
                    );
                }
                let install = Installation::from_named(nominal, &named)
                    .map_err(|p| bad(format!("model.install: {p}")))?;
                Some(ModelPart {
                    layout: install.apply(nominal),
                    install,
                    iterations: m.iterations,
                    converged: m.converged,
                    fitted_params: m.fitted_params,
                    well_determined: m.well_determined,
                    residual_rms: m.residual_rms_um.map(|x| x * MM_PER_UM),
                    holdout_rms: m.holdout_rms.as_ref().map(dof_internal),
                })
            }
        };
        Ok(Calibration {
            created: self.meta.created.clone(),
            layout_name: self.meta.layout.clone(),
            layout_hash: self.meta.layout_hash.clone(),
            poses: self.meta.poses,
            fit_poses: self.meta.fit_poses,
            holdout_poses: self.meta.holdout_poses,
            travel_range: (self.meta.travel_mm[0], self.meta.travel_mm[1]),
            sigma_mm: self.meta.noise_um.map(|x| x * MM_PER_UM),
            linear,
            linear_holdout_rms: self.linear.holdout_rms.as_ref().map(dof_internal),
            model,
        })
    }

    /// As TOML text.
    pub fn to_toml(&self) -> String {
        let body = toml::to_string(self).unwrap_or_default();
        format!(
            "# axiscomp calibration (units: µm, arcsec, degrees; beta rows X1..Y3, columns dx..ez)\n{body}"
        )
    }

    /// Write to `path`.
    pub fn save(&self, path: &Path) -> Result<(), CalError> {
        std::fs::write(path, self.to_toml()).map_err(|e| CalError::File {
            path: path.display().to_string(),
            problem: format!("cannot write it: {e}"),
        })
    }

    /// Parse TOML text; `label` names the source in errors.
    pub fn parse(text: &str, label: &str) -> Result<CalibrationFile, CalError> {
        toml::from_str(text).map_err(|e| CalError::File {
            path: label.to_string(),
            problem: crate::util::toml_error_line(text, &e),
        })
    }

    /// Read `path` and turn it into a calibration for `nominal`.
    pub fn load(path: &Path, nominal: &Layout) -> Result<Calibration, CalError> {
        let label = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| CalError::File {
            path: label.clone(),
            problem: format!("cannot read it: {e}"),
        })?;
        Self::parse(&text, &label)?.to_calibration(nominal, &label)
    }
}
