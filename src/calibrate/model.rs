//! Model-based calibration (beyond the paper): fit the installation errors of the layout's
//! elements (offsets, tilts, PSD gains — the ones that change readings, see
//! `optics::install::observable_params`) so that the nonlinear model reproduces the readings
//! at every known pose. Because the fitted thing is the geometry, the model then holds at any
//! travel, where a fixed β does not.
//!
//! Solver: Levenberg–Marquardt on `Σ ((f(θ; pose_i) − r_i)/σ)² + Σ (θ_j/τ_j)²`. The second
//! term is a weak prior at the stated installation tolerances τ: it keeps parameters the poses
//! cannot separate at nominal instead of letting them wander. Jacobian by forward differences.
//! Stops when the relative cost decrease falls below `tol`; fails (`CalError::ModelFit`) when no
//! step lowers the cost from the start or the damping runs away.
//!
//! Poses at several stations on the axis under test (`super::Stations`) add six unknowns per
//! station after the first: the pose there is the hexapod's plus the station's offset (the
//! carriage's own errors, the follower's), with no prior (nothing is known of them).

use super::{CalError, PoseSample, Stations, add_errors};
use crate::decouple::model_readings;
use crate::optics::install::{InstallParam, Installation, observable_params};
use crate::optics::{Layout, Pose};
use crate::units::Errors6;
use nalgebra::{DMatrix, DVector};

/// Settings of the model fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelFitOptions {
    /// Prior standard deviation of element offsets (mm).
    pub prior_offset_mm: f64,
    /// Prior standard deviation of element tilts (rad).
    pub prior_tilt_rad: f64,
    /// Prior standard deviation of PSD gain errors (relative).
    pub prior_gain: f64,
    /// Reading noise used to weigh the data against the prior (mm).
    pub noise_mm: f64,
    pub max_iter: u32,
    /// Relative cost decrease below which the fit has converged.
    pub tol: f64,
}

impl Default for ModelFitOptions {
    fn default() -> Self {
        ModelFitOptions {
            prior_offset_mm: 0.5,
            prior_tilt_rad: 0.2_f64.to_radians(),
            prior_gain: 0.05,
            noise_mm: 1e-3,
            max_iter: 100,
            tol: 1e-10,
        }
    }
}

/// The fitted installation errors and how well they are known.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelFit {
    pub install: Installation,
    /// The nominal layout with `install` applied: the calibrated model.
    pub layout: Layout,
    /// The parameters fitted, as (element index, parameter).
    pub params: Vec<(usize, InstallParam)>,
    /// Posterior standard deviation of each fitted parameter (same units as the parameter).
    pub param_sd: Vec<f64>,
    /// Parameters the poses determine to better than a tenth of their prior.
    pub well_determined: usize,
    pub iterations: u32,
    pub converged: bool,
    /// Residual RMS per reading channel (mm).
    pub residual_rms: [f64; 6],
    /// Each station's offset (zero at the first).
    pub station_errors: Vec<Errors6>,
}

fn prior_of(p: InstallParam, o: &ModelFitOptions) -> f64 {
    match p {
        InstallParam::Offset(_) => o.prior_offset_mm,
        InstallParam::Tilt(_) => o.prior_tilt_rad,
        InstallParam::Gain(_) => o.prior_gain,
    }
}

fn step_of(p: InstallParam) -> f64 {
    match p {
        InstallParam::Offset(_) => 1e-6,
        InstallParam::Tilt(_) => 1e-8,
        InstallParam::Gain(_) => 1e-8,
    }
}

struct Problem<'a> {
    samples: &'a [PoseSample],
    stations: &'a Stations,
    nominal: &'a Layout,
    params: Vec<(usize, InstallParam)>,
    prior: Vec<f64>,
    noise: f64,
}

/// Forward-difference step of a station offset's DOF `k` (mm, rad).
fn station_step(k: usize) -> f64 {
    if k < 3 { 1e-6 } else { 1e-8 }
}

impl Problem<'_> {
    /// Installation parameters, then six per station after the first.
    fn unknowns(&self) -> usize {
        self.params.len() + 6 * (self.stations.len().max(1) - 1)
    }

    /// The offset of station `st` in `theta`.
    fn station(&self, theta: &DVector<f64>, st: usize) -> Errors6 {
        match st {
            0 => Errors6::ZERO,
            _ => {
                let o = self.params.len() + 6 * (st - 1);
                Errors6::from_array(std::array::from_fn(|k| theta[o + k]))
            }
        }
    }

    /// The pose of sample `i` with its station's offset.
    fn pose(&self, theta: &DVector<f64>, i: usize) -> Pose {
        let s = &self.samples[i];
        let st = self.stations.of.get(i).copied().unwrap_or(0);
        Pose {
            errors: add_errors(&s.pose.errors, &self.station(theta, st)),
            ..s.pose
        }
    }

    fn install(&self, theta: &DVector<f64>) -> Installation {
        let mut inst = Installation::none(self.nominal);
        for (k, (el, p)) in self.params.iter().enumerate() {
            inst.set(*el, *p, theta[k]);
        }
        inst
    }

    fn rows(&self) -> usize {
        6 * self.samples.len() + self.params.len()
    }

    /// Weighted residuals, or `None` when the model cannot trace some pose at `theta`.
    fn residuals(&self, theta: &DVector<f64>) -> Option<DVector<f64>> {
        let layout = self.install(theta).apply(self.nominal);
        let mut out = DVector::zeros(self.rows());
        for (i, s) in self.samples.iter().enumerate() {
            let f = model_readings(&layout, &self.pose(theta, i)).ok()?;
            for k in 0..6 {
                out[6 * i + k] = (f[k] - s.readings[k]) / self.noise;
            }
        }
        let base = 6 * self.samples.len();
        for k in 0..self.params.len() {
            out[base + k] = theta[k] / self.prior[k];
        }
        Some(out)
    }

    fn jacobian(&self, theta: &DVector<f64>, r0: &DVector<f64>) -> Option<DMatrix<f64>> {
        let mut j = DMatrix::zeros(self.rows(), self.unknowns());
        for (k, (_, p)) in self.params.iter().enumerate() {
            let h = step_of(*p);
            let mut t = theta.clone();
            t[k] += h;
            let r = self.residuals(&t)?;
            j.set_column(k, &((r - r0) / h));
        }
        // A station's offset moves only its own poses' readings: trace those alone.
        let layout = self.install(theta).apply(self.nominal);
        for k in self.params.len()..self.unknowns() {
            let st = 1 + (k - self.params.len()) / 6;
            let h = station_step((k - self.params.len()) % 6);
            let mut t = theta.clone();
            t[k] += h;
            for i in (0..self.samples.len()).filter(|&i| self.stations.of.get(i) == Some(&st)) {
                let f = model_readings(&layout, &self.pose(&t, i)).ok()?;
                for ch in 0..6 {
                    let r = (f[ch] - self.samples[i].readings[ch]) / self.noise;
                    j[(6 * i + ch, k)] = (r - r0[6 * i + ch]) / h;
                }
            }
        }
        Some(j)
    }
}

/// Fit the installation errors to `samples`. `on_iter(iteration, cost)` reports progress.
pub fn fit_model(
    samples: &[PoseSample],
    nominal: &Layout,
    opts: &ModelFitOptions,
    on_iter: &mut dyn FnMut(u32, f64),
) -> Result<ModelFit, CalError> {
    fit_model_stations(
        samples,
        nominal,
        &Stations::of(samples, false),
        opts,
        on_iter,
    )
}

/// Fit the installation errors and each station's offset to `samples`.
pub fn fit_model_stations(
    samples: &[PoseSample],
    nominal: &Layout,
    stations: &Stations,
    opts: &ModelFitOptions,
    on_iter: &mut dyn FnMut(u32, f64),
) -> Result<ModelFit, CalError> {
    let params = observable_params(nominal);
    let prior: Vec<f64> = params.iter().map(|(_, p)| prior_of(*p, opts)).collect();
    let needed = (params.len() + 6 * (stations.len().max(1) - 1)).div_ceil(6) + 1;
    if samples.len() < needed {
        return Err(CalError::TooFewPoses {
            n: samples.len(),
            needed,
        });
    }
    let prob = Problem {
        samples,
        stations,
        nominal,
        params,
        prior,
        noise: opts.noise_mm,
    };
    let np = prob.unknowns();
    let mut theta = DVector::zeros(np);
    let mut r = prob.residuals(&theta).ok_or_else(|| CalError::ModelFit {
        problem: "the nominal model cannot trace some calibration poses".into(),
    })?;
    let mut cost = r.norm_squared();
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut iterations = 0;
    let mut jac = prob
        .jacobian(&theta, &r)
        .ok_or_else(|| CalError::ModelFit {
            problem: "the model cannot trace some poses near the start".into(),
        })?;
    while iterations < opts.max_iter {
        iterations += 1;
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * &r;
        let mut accepted = false;
        for _ in 0..30 {
            let mut a = jtj.clone();
            for k in 0..np {
                a[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
            }
            let Some(ch) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = -ch.solve(&g);
            let trial = &theta + &delta;
            match prob.residuals(&trial) {
                Some(rt) if rt.norm_squared() < cost => {
                    let new_cost = rt.norm_squared();
                    let rel = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
                    theta = trial;
                    r = rt;
                    cost = new_cost;
                    lambda = (lambda / 3.0).max(1e-12);
                    accepted = true;
                    if rel < opts.tol {
                        converged = true;
                    }
                    break;
                }
                _ => lambda *= 4.0,
            }
            if lambda > 1e12 {
                break;
            }
        }
        on_iter(iterations, cost);
        if !accepted {
            // No step lowers the cost: at a minimum to machine precision, or stuck.
            converged = iterations > 1;
            if !converged {
                return Err(CalError::ModelFit {
                    problem: "no Levenberg–Marquardt step lowers the cost from the start".into(),
                });
            }
            break;
        }
        if converged {
            break;
        }
        jac = prob
            .jacobian(&theta, &r)
            .ok_or_else(|| CalError::ModelFit {
                problem: "the model cannot trace some poses during the fit".into(),
            })?;
    }
    let install = prob.install(&theta);
    let layout = install.apply(nominal);
    let jtj = jac.transpose() * &jac;
    let param_sd: Vec<f64> = match jtj.cholesky() {
        Some(ch) => {
            let inv = ch.inverse();
            (0..prob.params.len())
                .map(|k| inv[(k, k)].max(0.0).sqrt())
                .collect()
        }
        None => prob.prior.clone(),
    };
    let well_determined = param_sd
        .iter()
        .zip(&prob.prior)
        .filter(|(sd, pr)| **sd < 0.1 * **pr)
        .count();
    let n = samples.len();
    let residual_rms = std::array::from_fn(|k| {
        let ss: f64 = (0..n).map(|i| r[6 * i + k].powi(2)).sum();
        (ss / n as f64).sqrt() * opts.noise_mm
    });
    let station_errors = (0..stations.len().max(1))
        .map(|st| prob.station(&theta, st))
        .collect();
    Ok(ModelFit {
        install,
        layout,
        station_errors,
        params: prob.params,
        param_sd,
        well_determined,
        iterations,
        converged,
        residual_rms,
    })
}
