//! From six readings back to the six errors (DESIGN §3).
//!
//! - Linear with offset: `e = β⁻¹·(r − c)`. The paper's form has no `c`; with real installation
//!   errors that is off by millimetres, so the offset (or a zero reference) is always part of it.
//! - Nonlinear: Gauss–Newton on the forward model at the known travel D and follower d, started
//!   from the linear estimate with β(D). Needed for large errors and long travel, where a fixed
//!   β is wrong (the P1 lever grows with D).
//! - Every estimate carries its covariance `(Jᵀ Σ⁻¹ J)⁻¹` from the PSD noise.

pub mod jacobian;

pub use jacobian::{conditioning, covariance, crlb, jacobian, sd_of, to_user_units};

use crate::optics::{Layout, Pose};
use crate::units::{Errors6, MM_PER_UM};
use nalgebra::{Matrix6, Vector6};
use thiserror::Error;

/// Why a decoupling failed.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum DecoupleError {
    /// The model cannot trace the pose (a PSD would read nothing there).
    #[error("the model gives no reading at this pose: {reason}")]
    NotTraceable { reason: String },
    /// β is singular: the readings do not determine the six errors.
    #[error("the sensitivity matrix is singular: the readings do not determine all six errors")]
    Singular,
    /// Gauss–Newton did not converge.
    #[error(
        "no convergence after {iterations} iterations (last step {step_um:.3e} µm): the readings are far from any pose the model can trace"
    )]
    NoConvergence { iterations: u32, step_um: f64 },
}

/// An estimate of the six errors with its covariance (internal units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    pub errors: Errors6,
    pub cov: Matrix6<f64>,
    /// Gauss–Newton iterations used (0 for a linear estimate).
    pub iterations: u32,
}

impl Estimate {
    /// Standard deviation per DOF (internal units).
    pub fn sd(&self) -> Errors6 {
        sd_of(&self.cov)
    }
}

/// A linear decoupler with offset: `e = β⁻¹·(r − c)`, covariance precomputed.
#[derive(Clone, Debug, PartialEq)]
pub struct Linear {
    pub beta: Matrix6<f64>,
    pub offset: Vector6<f64>,
    beta_inv: Matrix6<f64>,
    cov: Matrix6<f64>,
}

impl Linear {
    /// From β (mm per mm / per rad), offset c (mm) and reading noise (mm per channel).
    pub fn new(
        beta: Matrix6<f64>,
        offset: Vector6<f64>,
        sigma_mm: &[f64; 6],
    ) -> Result<Self, DecoupleError> {
        let beta_inv = beta.try_inverse().ok_or(DecoupleError::Singular)?;
        let cov = covariance(&beta, sigma_mm).ok_or(DecoupleError::Singular)?;
        Ok(Linear {
            beta,
            offset,
            beta_inv,
            cov,
        })
    }

    /// The errors (internal units) for readings `r` (mm).
    #[inline]
    pub fn solve(&self, r: &Vector6<f64>) -> Vector6<f64> {
        self.beta_inv * (r - self.offset)
    }

    /// The estimate with covariance.
    pub fn estimate(&self, r: &Vector6<f64>) -> Estimate {
        Estimate {
            errors: Errors6::from_vector(&self.solve(r)),
            cov: self.cov,
            iterations: 0,
        }
    }
}

/// Stopping rule of the nonlinear solver: it stops when a step is below `tol_mm` in every
/// translation and `tol_rad` in every rotation, and fails after `max_iter` iterations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveOptions {
    pub max_iter: u32,
    pub tol_mm: f64,
    pub tol_rad: f64,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            max_iter: 30,
            tol_mm: 1e-8,
            tol_rad: 5e-11,
        }
    }
}

/// The model's readings at a pose (geometry only, no aperture checks), or why there are none.
pub fn model_readings(layout: &Layout, pose: &Pose) -> Result<Vector6<f64>, DecoupleError> {
    let r = layout.forward_unbounded(pose);
    r.vector().ok_or_else(|| DecoupleError::NotTraceable {
        reason: r
            .first_invalid()
            .map(|i| layout.describe(&i))
            .unwrap_or_default(),
    })
}

/// The linear estimate with β(D) and offset f(0, D, d): one forward-model Jacobian, no
/// iteration. Exact to first order.
pub fn solve_linear(
    layout: &Layout,
    r: &Vector6<f64>,
    travel: f64,
    follower: f64,
    sigma_mm: &[f64; 6],
) -> Result<Estimate, DecoupleError> {
    let pose0 = Pose::new(Errors6::ZERO, travel, follower);
    let beta = jacobian(layout, &pose0)?;
    let offset = model_readings(layout, &pose0)?;
    Ok(Linear::new(beta, offset, sigma_mm)?.estimate(r))
}

/// Gauss–Newton on the forward model at travel `travel` and follower `follower`. Starts from
/// the linear estimate with β(D); iterates with that Jacobian while it converges fast (each
/// step at least 4× smaller than the last) and re-evaluates it at the current estimate
/// otherwise.
pub fn solve_nonlinear(
    layout: &Layout,
    r: &Vector6<f64>,
    travel: f64,
    follower: f64,
    sigma_mm: &[f64; 6],
    opts: &SolveOptions,
) -> Result<Estimate, DecoupleError> {
    let j = jacobian(layout, &Pose::new(Errors6::ZERO, travel, follower))?;
    solve_nonlinear_from(layout, r, travel, follower, opts, &Start::new(j, sigma_mm)?)
}

type Lu6 = nalgebra::LU<f64, nalgebra::Const<6>, nalgebra::Const<6>>;

/// Where Gauss–Newton starts: a β with its factorisation and the covariance it gives for the
/// reading noise (what a converged solution reports while β is still its Jacobian).
#[derive(Clone, Debug)]
pub struct Start {
    lu: Lu6,
    cov: Matrix6<f64>,
    sigma_mm: [f64; 6],
}

impl Start {
    pub fn new(beta: Matrix6<f64>, sigma_mm: &[f64; 6]) -> Result<Start, DecoupleError> {
        Ok(Start {
            lu: beta.lu(),
            cov: covariance(&beta, sigma_mm).ok_or(DecoupleError::Singular)?,
            sigma_mm: *sigma_mm,
        })
    }
}

/// `solve_nonlinear` starting from a given β (the Jacobian at zero error near this travel and
/// follower position, e.g. cached from the previous frame). The solution does not depend on
/// it as long as the iteration converges: every step uses the exact forward model.
pub fn solve_nonlinear_from(
    layout: &Layout,
    r: &Vector6<f64>,
    travel: f64,
    follower: f64,
    opts: &SolveOptions,
    start: &Start,
) -> Result<Estimate, DecoupleError> {
    let pose0 = Pose::new(Errors6::ZERO, travel, follower);
    // The Jacobian re-evaluated at the estimate when convergence slows (`None`: β itself).
    let mut moved: Option<(Matrix6<f64>, Lu6)> = None;
    let f0 = model_readings(layout, &pose0)?;
    let mut e = start.lu.solve(&(r - f0)).ok_or(DecoupleError::Singular)?;
    let mut prev = f64::INFINITY;
    for it in 1..=opts.max_iter {
        let pose = Pose::new(Errors6::from_vector(&e), travel, follower);
        let f = model_readings(layout, &pose)?;
        let lu = moved.as_ref().map_or(&start.lu, |(_, lu)| lu);
        let de = lu.solve(&(r - f)).ok_or(DecoupleError::Singular)?;
        e += de;
        let step = (0..6)
            .map(|k| de[k].abs() / if k < 3 { opts.tol_mm } else { opts.tol_rad })
            .fold(0.0, f64::max);
        if step <= 1.0 {
            let cov = match &moved {
                None => start.cov,
                Some((j, _)) => covariance(j, &start.sigma_mm).ok_or(DecoupleError::Singular)?,
            };
            return Ok(Estimate {
                errors: Errors6::from_vector(&e),
                cov,
                iterations: it,
            });
        }
        if step > 0.25 * prev {
            let j = jacobian(
                layout,
                &Pose::new(Errors6::from_vector(&e), travel, follower),
            )?;
            moved = Some((j, j.lu()));
        }
        prev = step;
        if it == opts.max_iter {
            return Err(DecoupleError::NoConvergence {
                iterations: it,
                step_um: de.fixed_rows::<3>(0).amax() / MM_PER_UM,
            });
        }
    }
    Err(DecoupleError::NoConvergence {
        iterations: 0,
        step_um: f64::NAN,
    })
}

/// β(D) kept between frames: reused while travel and follower stay within `BETA_REUSE_MM` of
/// where it was computed (β changes by about 0.3 % per mm of travel; the nonlinear solution
/// does not depend on the β it starts from, only on the exact forward model).
#[derive(Clone, Debug, Default)]
pub struct BetaCache {
    at: Option<(f64, f64)>,
    beta: Matrix6<f64>,
    inverse: Matrix6<f64>,
    /// The Gauss–Newton start from `beta` (nonlinear decoupling only), made on first use.
    start: Option<Start>,
}

/// How far travel or follower may move before β(D) is recomputed (mm).
pub const BETA_REUSE_MM: f64 = 0.05;

impl BetaCache {
    /// β⁻¹ at (about) this travel and follower position.
    fn get(
        &mut self,
        dec: &Decoupler,
        travel: f64,
        follower: f64,
    ) -> Result<Matrix6<f64>, DecoupleError> {
        let fresh = self.at.is_some_and(|(t, f)| {
            (t - travel).abs() < BETA_REUSE_MM && (f - follower).abs() < BETA_REUSE_MM
        });
        if !fresh {
            let beta = dec.beta(travel, follower)?;
            self.inverse = beta.try_inverse().ok_or(DecoupleError::Singular)?;
            self.beta = beta;
            self.start = None;
            self.at = Some((travel, follower));
        }
        Ok(self.inverse)
    }

    /// The Gauss–Newton start from the β of the last [`get`](Self::get).
    fn start(&mut self, sigma_mm: &[f64; 6]) -> Result<&Start, DecoupleError> {
        let start = match self.start.take() {
            Some(s) => s,
            None => Start::new(self.beta, sigma_mm)?,
        };
        Ok(self.start.insert(start))
    }
}

/// Where β and the offset come from.
#[derive(Clone, Debug)]
pub enum Source {
    /// The nominal layout's model, no installation errors known.
    Simulated(Layout),
    /// The layout with calibrated installation errors (model-based calibration).
    Model(Layout),
    /// A fitted linear β and offset, valid at its reference travel; away from it the nominal
    /// model's offset change with travel is applied (β stays fixed, as in the paper).
    Linear {
        linear: Box<Linear>,
        nominal: Layout,
        ref_travel: f64,
        ref_follower: f64,
    },
}

/// Linear (one-shot) or nonlinear (Gauss–Newton) decoupling for model sources.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    Linear,
    Nonlinear,
}

/// A configured decoupler: a source of β and offset, a method and the reading noise.
#[derive(Clone, Debug)]
pub struct Decoupler {
    pub source: Source,
    pub method: Method,
    pub sigma_mm: [f64; 6],
    pub options: SolveOptions,
}

impl Decoupler {
    /// The layout the decoupling models (a fitted β's nominal layout): where the moving
    /// module is and which way it travels.
    pub fn layout(&self) -> &Layout {
        match &self.source {
            Source::Simulated(l) | Source::Model(l) => l,
            Source::Linear { nominal, .. } => nominal,
        }
    }

    /// The sensitivity β at a pose with zero error: the model's Jacobian, or the fitted β.
    pub fn beta(&self, travel: f64, follower: f64) -> Result<Matrix6<f64>, DecoupleError> {
        match &self.source {
            Source::Simulated(l) | Source::Model(l) => {
                jacobian(l, &Pose::new(Errors6::ZERO, travel, follower))
            }
            Source::Linear { linear, .. } => Ok(linear.beta),
        }
    }

    /// Covariance of the errors caused by independent extra variances of the readings
    /// (`var`, mm² per channel): `β⁻¹·diag(var)·β⁻ᵀ`. Used to carry the stitching uncertainty
    /// of PSD2's position into the six errors.
    pub fn propagate(
        &self,
        var: &[f64; 6],
        travel: f64,
        follower: f64,
    ) -> Result<Matrix6<f64>, DecoupleError> {
        let inv = self
            .beta(travel, follower)?
            .try_inverse()
            .ok_or(DecoupleError::Singular)?;
        let d = Matrix6::from_diagonal(&Vector6::from(*var));
        Ok(inv * d * inv.transpose())
    }

    /// `decouple` and `propagate` together, reusing β(D) from `cache` when travel and follower
    /// have hardly moved: the per-frame path of the live service.
    pub fn decouple_cached(
        &self,
        r: &Vector6<f64>,
        travel: f64,
        follower: f64,
        extra_var: &[f64; 6],
        cache: &mut BetaCache,
    ) -> Result<(Estimate, Matrix6<f64>), DecoupleError> {
        let inv = cache.get(self, travel, follower)?;
        let est = match (&self.source, self.method) {
            (Source::Simulated(l) | Source::Model(l), Method::Nonlinear) => {
                let start = cache.start(&self.sigma_mm)?;
                solve_nonlinear_from(l, r, travel, follower, &self.options, start)?
            }
            _ => self.decouple(r, travel, follower)?,
        };
        let d = Matrix6::from_diagonal(&Vector6::from(*extra_var));
        Ok((est, inv * d * inv.transpose()))
    }

    /// Decouple readings `r` (mm) taken at travel `travel` with the follower at `follower`.
    pub fn decouple(
        &self,
        r: &Vector6<f64>,
        travel: f64,
        follower: f64,
    ) -> Result<Estimate, DecoupleError> {
        match &self.source {
            Source::Simulated(l) | Source::Model(l) => match self.method {
                Method::Linear => solve_linear(l, r, travel, follower, &self.sigma_mm),
                Method::Nonlinear => {
                    solve_nonlinear(l, r, travel, follower, &self.sigma_mm, &self.options)
                }
            },
            Source::Linear {
                linear,
                nominal,
                ref_travel,
                ref_follower,
            } => {
                let shift = if travel == *ref_travel && follower == *ref_follower {
                    Vector6::zeros()
                } else {
                    let at = model_readings(nominal, &Pose::new(Errors6::ZERO, travel, follower))?;
                    let at_ref = model_readings(
                        nominal,
                        &Pose::new(Errors6::ZERO, *ref_travel, *ref_follower),
                    )?;
                    at - at_ref
                };
                Ok(linear.estimate(&(r - shift)))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nonlinear_recovers_large_errors_at_long_travel() {
        let l = Layout::reference();
        let e = Errors6::from_user([400.0, -300.0, 250.0, 150.0, -120.0, 180.0]);
        let pose = Pose::new(e, 600.0, 600.5);
        let r = l.forward(&pose).vector().unwrap();
        let est =
            solve_nonlinear(&l, &r, 600.0, 600.5, &[1e-3; 6], &SolveOptions::default()).unwrap();
        let got = est.errors.to_user();
        let want = e.to_user();
        for k in 0..6 {
            assert!(
                (got[k] - want[k]).abs() < 1e-4,
                "dof {k}: {} vs {}",
                got[k],
                want[k]
            );
        }
        // The linear estimate alone is visibly off at this size.
        let lin = solve_linear(&l, &r, 600.0, 600.5, &[1e-3; 6]).unwrap();
        let worst = (0..6)
            .map(|k| (lin.errors.to_user()[k] - want[k]).abs())
            .fold(0.0, f64::max);
        assert!(worst > 0.01, "linear error {worst}");
    }

    #[test]
    fn linear_source_applies_offset_and_travel_shift() {
        let l = Layout::reference();
        let beta = jacobian(&l, &Pose::default()).unwrap();
        let lin = Linear::new(beta, Vector6::zeros(), &[1e-3; 6]).unwrap();
        let d = Decoupler {
            source: Source::Linear {
                linear: Box::new(lin),
                nominal: l.clone(),
                ref_travel: 0.0,
                ref_follower: 0.0,
            },
            method: Method::Linear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        // Pure positioning at travel 50 with the follower at 49: X2 = dy + (D − d).
        let e = Errors6 {
            dy: 0.01,
            ..Errors6::ZERO
        };
        let r = l.forward(&Pose::new(e, 50.0, 49.0)).vector().unwrap();
        let est = d.decouple(&r, 50.0, 49.0).unwrap();
        assert!((est.errors.dy - 0.01).abs() < 1e-9);
        assert!(est.errors.ez.abs() < 1e-12);
    }

    #[test]
    fn propagate_matches_covariance_formula() {
        let l = Layout::reference();
        let d = Decoupler {
            source: Source::Simulated(l.clone()),
            method: Method::Nonlinear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        // Variance on every channel must equal the noise covariance (Jᵀ Σ⁻¹ J)⁻¹.
        let c = d.propagate(&[1e-6; 6], 0.0, 0.0).unwrap();
        let j = jacobian(&l, &Pose::default()).unwrap();
        let want = covariance(&j, &[1e-3; 6]).unwrap();
        assert!((c - want).amax() / want.amax() < 1e-9);
        // X2 alone (PSD2's position along its axis) moves dy 1:1 and nothing else.
        let c = d
            .propagate(&[0.0, 0.0, 1e-6, 0.0, 0.0, 0.0], 0.0, 0.0)
            .unwrap();
        assert!((c[(1, 1)] - 1e-6).abs() < 1e-12);
        assert!(c[(0, 0)].abs() < 1e-15 && c[(5, 5)].abs() < 1e-15);
    }

    #[test]
    fn decoupling_model_ignores_apertures() {
        // The PSDs would not see this spot (50 mm off PSD2), but a model used for decoupling
        // must not refuse a reading that arrived.
        let l = Layout::reference();
        let pose = Pose::new(Errors6::ZERO, 50.0, 0.0);
        assert!(l.forward(&pose).vector().is_none());
        let r = model_readings(&l, &pose).unwrap();
        assert!((r[2] - 50.0).abs() < 1e-9);
    }

    #[test]
    fn parallel_beam_is_not_traceable() {
        // Yaw of 90° turns MIRROR1 so P2 runs parallel to PSD2's plane.
        let l = Layout::reference();
        let e = Errors6 {
            ez: std::f64::consts::FRAC_PI_2,
            ..Errors6::ZERO
        };
        let err = model_readings(&l, &Pose::new(e, 0.0, 0.0)).unwrap_err();
        assert!(matches!(err, DecoupleError::NotTraceable { .. }), "{err}");
    }
}
