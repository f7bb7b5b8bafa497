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

/// A calibration's own term in an uncertainty budget (ISO/TR 230-9), per DOF in user units
/// (µm, arcsec), from its hold-out poses: see [`CalibrationFile::budget_term`].
#[derive(Clone, Debug, PartialEq)]
pub struct BudgetTerm {
    /// The standard uncertainty per DOF.
    pub u: [f64; 6],
    /// The hold-out RMS error h per DOF of the fit the head decouples with.
    pub holdout: [f64; 6],
    /// The Cramér–Rao bound b per DOF of one pose's reading.
    pub bound: [f64; 6],
    /// Hold-out poses N.
    pub poses: usize,
    /// "model" or "linear": the fit h is of (the one the head decouples with).
    pub fit: &'static str,
}

impl BudgetTerm {
    /// The formula and its inputs, in words.
    pub fn words(&self) -> String {
        format!(
            "the {} fit's hold-out error h beyond the Cramér–Rao bound b of one pose's reading \
             (the fit's residual noise through its β), √(max(0, h² − b²) + √(2/N)·b²), N = {} poses",
            self.fit, self.poses
        )
    }
}

impl CalibrationFile {
    /// The calibration's own standard uncertainty per DOF, as the budget states it (the same
    /// formula as the demo's calibration study, [`crate::evaluate::uncertainty::calibration_u`]):
    /// h the hold-out RMS of the fit the head decouples with (the model when fitted, else the
    /// linear β), b the Cramér–Rao bound of one hold-out pose's reading — the readings as the
    /// pose set holds them (a bench's dwell mean or one frame), their noise σ per channel from
    /// the fit's residuals (`meta.noise_um`), through the calibrated β:
    /// `b = √diag((βᵀ·Σ⁻¹·β)⁻¹)`, Σ = diag(σ²) — and N the hold-out poses;
    /// `u² = max(0, h² − b²) + √(2/N)·b²`. `Err`: why the term cannot be stated (no hold-out
    /// poses, a singular β).
    pub fn budget_term(&self) -> Result<BudgetTerm, String> {
        let model = self.model.as_ref().and_then(|m| m.holdout_rms);
        let (holdout, fit) = match (model, self.linear.holdout_rms) {
            (Some(h), _) => (h, "model"),
            (None, Some(h)) if self.model.is_none() => (h, "linear"),
            _ => {
                return Err(
                    "the calibration has no hold-out error (fitted with every pose, none held \
                     out): its own error cannot be told from the noise"
                        .into(),
                );
            }
        };
        let poses = self.meta.holdout_poses;
        if poses == 0 {
            return Err("the calibration names no hold-out poses".into());
        }
        let mut beta = Matrix6::zeros();
        for r in 0..6 {
            for k in 0..6 {
                beta[(r, k)] = self.linear.beta[r][k];
            }
        }
        let all_finite = holdout
            .iter()
            .chain(&self.meta.noise_um)
            .all(|x| x.is_finite())
            && beta.iter().all(|x| x.is_finite());
        if !all_finite {
            return Err("the calibration's hold-out, noise or β has a non-finite value".into());
        }
        // β in µm per (µm | arcsec) and σ in µm: the covariance is in µm² and arcsec².
        let cov = crate::decouple::covariance(&beta, &self.meta.noise_um).ok_or_else(|| {
            "the calibration's β with its noise gives no bound (singular, or a noise of zero)"
                .to_string()
        })?;
        let bound: [f64; 6] = std::array::from_fn(|k| cov[(k, k)].max(0.0).sqrt());
        Ok(BudgetTerm {
            u: crate::evaluate::uncertainty::calibration_u(&holdout, &bound, poses),
            holdout,
            bound,
            poses,
            fit,
        })
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    /// A calibration with a diagonal β (µm per µm / arcsec): the bound of one reading is then
    /// σ_k/β_kk for each DOF, by hand.
    fn file(holdout: Option<[f64; 6]>, model_holdout: Option<[f64; 6]>) -> CalibrationFile {
        let diag = [2.0, 1.0, 2.0, 4.0, 0.5, 4.0];
        CalibrationFile {
            meta: Meta {
                format: FORMAT,
                created: "2026-03-01T10:00:00Z".into(),
                layout: "reference".into(),
                layout_hash: "0".into(),
                poses: 250,
                fit_poses: 200,
                holdout_poses: 50,
                travel_mm: [0.0, 0.0],
                noise_um: [1.0, 2.0, 1.0, 1.0, 2.0, 1.0],
            },
            linear: LinearSection {
                rank: 6,
                rcond: 1e-12,
                condition_number: 8.0,
                ref_travel_mm: 0.0,
                ref_follower_mm: 0.0,
                residual_rms_um: [1.0; 6],
                holdout_rms: holdout,
                singular_values: diag.to_vec(),
                offset_um: [0.0; 6],
                beta: std::array::from_fn(|r| {
                    std::array::from_fn(|k| if r == k { diag[k] } else { 0.0 })
                }),
            },
            model: model_holdout.map(|h| ModelSection {
                iterations: 5,
                converged: true,
                fitted_params: 12,
                well_determined: 12,
                residual_rms_um: [1.0; 6],
                holdout_rms: Some(h),
                install: BTreeMap::new(),
            }),
        }
    }

    /// b = σ/β = (0.5, 2, 0.5, 0.25, 4, 0.25); N = 50, so √(2/N) = 0.2;
    /// u² = max(0, h² − b²) + 0.2·b²: h = 0.6 → 0.11 + 0.05 = 0.16 (u = 0.4); h = 1 below
    /// b = 2 → 0.8; h = b = 0.5 → 0.05; 0.1875 + 0.0125 = 0.2; 9 + 3.2 = 12.2; 0.0125.
    #[test]
    fn the_budget_term_is_the_hold_out_beyond_the_bound() {
        let h = [0.6, 1.0, 0.5, 0.5, 5.0, 0.2];
        let t = file(Some(h), None).budget_term().expect("a hold-out");
        let want = [0.16f64, 0.8, 0.05, 0.2, 12.2, 0.0125].map(f64::sqrt);
        for (k, (got, want)) in t.u.iter().zip(want).enumerate() {
            assert!((got - want).abs() < 1e-12, "dof {k}: {got} vs {want}");
        }
        assert_eq!(t.bound, [0.5, 2.0, 0.5, 0.25, 4.0, 0.25]);
        assert_eq!((t.fit, t.poses), ("linear", 50));
        assert!(t.words().contains("N = 50 poses"), "{}", t.words());
        // The model's hold-out, when fitted, is the one the head decouples with.
        let t = file(Some([9.0; 6]), Some(h)).budget_term().expect("model");
        assert_eq!(t.fit, "model");
        assert!((t.u[0] - 0.4).abs() < 1e-12);
        // No hold-out: not stated, and why.
        let e = file(None, None).budget_term().unwrap_err();
        assert!(e.contains("no hold-out"), "{e}");
    }
}
