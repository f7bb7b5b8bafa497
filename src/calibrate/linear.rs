//! The paper's calibration, with an offset: least squares `R = [E 1]·B` over N known poses,
//! solved by SVD. Columns of `[E 1]` are scaled to unit RMS first; singular values below
//! `LINEAR_RCOND · σ_max` count as zero, and a pose set that leaves the rank below 7 is refused
//! with the DOF it fails to excite.
//!
//! Readings taken at different travel or follower positions are first brought to one
//! reference position with the nominal model's zero-error readings (X2 moves 1:1 with D − d).
//! β itself stays fixed, as in the paper: it is exact only near the travel it was fitted at.
//! Poses at several stations on the axis under test (`super::Stations`) get one reading
//! offset per station after the first: `R = [E 1 S]·B` with S the stations' indicators.

use super::{CalError, PoseSample, Stations};
use crate::decouple::{self, Linear};
use crate::optics::{Layout, Pose};
use crate::units::{DOF_NAMES, Errors6};
use nalgebra::{DMatrix, Matrix6, Vector6};

/// Relative tolerance on singular values of the scaled design matrix.
pub const LINEAR_RCOND: f64 = 1e-10;

/// A fitted linear model `r = β·e + c` at a reference travel and follower position.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearFit {
    /// mm per mm (translations), mm per rad (rotations); rows readings, columns DOFs.
    pub beta: Matrix6<f64>,
    /// Readings at zero error at the reference position (mm).
    pub offset: Vector6<f64>,
    pub ref_travel: f64,
    pub ref_follower: f64,
    /// Rank of the scaled design matrix (7 when every DOF and the offset are determined).
    pub rank: usize,
    /// Singular values of the scaled design matrix, descending.
    pub singular_values: Vec<f64>,
    /// Residual RMS per reading channel (mm).
    pub residual_rms: [f64; 6],
    /// Condition number of β in µm per µm / per arcsec.
    pub condition_number: f64,
}

impl LinearFit {
    /// The decoupler for this fit with reading noise `sigma_mm`.
    pub fn linear(&self, sigma_mm: &[f64; 6]) -> Result<Linear, CalError> {
        Ok(Linear::new(self.beta, self.offset, sigma_mm)?)
    }
}

/// Zero-error readings of the nominal model relative to the reference position, cached per
/// distinct (travel, follower) pair.
pub(crate) struct TravelShift<'a> {
    nominal: &'a Layout,
    at_ref: Vector6<f64>,
    cache: Vec<((f64, f64), Vector6<f64>)>,
}

impl<'a> TravelShift<'a> {
    pub(crate) fn new(nominal: &'a Layout, travel: f64, follower: f64) -> Result<Self, CalError> {
        let at_ref =
            decouple::model_readings(nominal, &Pose::new(Errors6::ZERO, travel, follower))?;
        Ok(TravelShift {
            nominal,
            at_ref,
            cache: Vec::new(),
        })
    }

    pub(crate) fn shift(&mut self, travel: f64, follower: f64) -> Result<Vector6<f64>, CalError> {
        if let Some((_, v)) = self.cache.iter().find(|(k, _)| *k == (travel, follower)) {
            return Ok(*v);
        }
        let at =
            decouple::model_readings(self.nominal, &Pose::new(Errors6::ZERO, travel, follower))?;
        let v = at - self.at_ref;
        self.cache.push(((travel, follower), v));
        Ok(v)
    }
}

/// Fit β and offset to `samples`.
pub fn fit_linear(samples: &[PoseSample], nominal: &Layout) -> Result<LinearFit, CalError> {
    Ok(fit_linear_stations(samples, nominal, &Stations::of(samples, false))?.0)
}

/// Fit β, the offset and each station's reading offset (mm; zero at the first) to `samples`.
pub fn fit_linear_stations(
    samples: &[PoseSample],
    nominal: &Layout,
    stations: &Stations,
) -> Result<(LinearFit, Vec<Vector6<f64>>), CalError> {
    let n = samples.len();
    let ns = stations.len().max(1);
    let cols = 6 + ns;
    if n < cols {
        return Err(CalError::TooFewPoses { n, needed: cols });
    }
    let ref_travel = samples.iter().map(|s| s.pose.travel).sum::<f64>() / n as f64;
    let ref_follower = samples.iter().map(|s| s.pose.follower).sum::<f64>() / n as f64;
    let mut shift = TravelShift::new(nominal, ref_travel, ref_follower)?;

    let mut a = DMatrix::<f64>::zeros(n, cols);
    let mut r = DMatrix::<f64>::zeros(n, 6);
    for (i, s) in samples.iter().enumerate() {
        let e = s.pose.errors.to_array();
        for k in 0..6 {
            a[(i, k)] = e[k];
        }
        a[(i, 6)] = 1.0;
        match stations.of.get(i) {
            Some(&st) if st > 0 => a[(i, 6 + st)] = 1.0,
            _ => {}
        }
        let y = s.readings - shift.shift(s.pose.travel, s.pose.follower)?;
        for k in 0..6 {
            r[(i, k)] = y[k];
        }
    }
    // Scale each column to unit RMS so translations (mm) and rotations (rad) weigh alike.
    let mut scale = vec![1.0; cols];
    for (k, sc) in scale.iter_mut().enumerate().filter(|(k, _)| *k != 6) {
        let rms = (a.column(k).norm_squared() / n as f64).sqrt();
        *sc = if rms > 0.0 { rms } else { 1.0 };
        a.column_mut(k).scale_mut(1.0 / *sc);
    }
    let svd = a.clone().svd(true, true);
    let mut sv: Vec<f64> = svd.singular_values.iter().copied().collect();
    sv.sort_by(|x, y| y.total_cmp(x));
    let tol = LINEAR_RCOND * sv[0];
    let rank = sv.iter().filter(|&&s| s > tol).count();
    if rank < cols {
        let v_t = svd
            .v_t
            .as_ref()
            .ok_or(CalError::Internal("SVD without V"))?;
        // The right singular vector of the smallest singular value names what is not excited.
        let (imin, _) = svd
            .singular_values
            .iter()
            .enumerate()
            .min_by(|x, y| x.1.total_cmp(y.1))
            .ok_or(CalError::Internal("empty SVD"))?;
        let row = v_t.row(imin);
        let (kmax, _) = row
            .iter()
            .enumerate()
            .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
            .ok_or(CalError::Internal("empty SVD"))?;
        let weakest = match kmax {
            0..6 => DOF_NAMES[kmax].to_string(),
            6 => "the offset".to_string(),
            k => {
                let (t, f) = stations.at[k - 6];
                format!("the offset at travel {t} mm (follower {f} mm)")
            }
        };
        return Err(CalError::LowRank {
            rank,
            needed: cols,
            weakest,
        });
    }
    let b = svd
        .solve(&r, tol)
        .map_err(|_| CalError::Internal("SVD solve failed"))?;
    let mut beta = Matrix6::zeros();
    let mut offset = Vector6::zeros();
    for ch in 0..6 {
        for k in 0..6 {
            beta[(ch, k)] = b[(k, ch)] / scale[k];
        }
        offset[ch] = b[(6, ch)];
    }
    let station_offsets = (0..ns)
        .map(|st| match st {
            0 => Vector6::zeros(),
            _ => Vector6::from_fn(|ch, _| b[(6 + st, ch)] / scale[6 + st]),
        })
        .collect();
    let resid = &r - &a * &b;
    let residual_rms =
        std::array::from_fn(|ch| (resid.column(ch).norm_squared() / n as f64).sqrt());
    let (_, condition_number) = decouple::conditioning(&decouple::to_user_units(&beta));
    Ok((
        LinearFit {
            beta,
            offset,
            ref_travel,
            ref_follower,
            rank,
            singular_values: sv,
            residual_rms,
            condition_number,
        },
        station_offsets,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decouple::jacobian;

    fn samples_from(layout: &Layout, poses: &[Pose]) -> Vec<PoseSample> {
        poses
            .iter()
            .map(|p| PoseSample {
                pose: *p,
                readings: layout.forward(p).vector().unwrap(),
            })
            .collect()
    }

    #[test]
    fn recovers_reference_beta_without_noise() {
        let l = Layout::reference();
        let mut rng = crate::sim::rng::Rng::new(3);
        let poses: Vec<Pose> = (0..60)
            .map(|_| {
                Pose::new(
                    Errors6::from_user(std::array::from_fn(|_| rng.uniform(-1.0, 1.0))),
                    0.0,
                    0.0,
                )
            })
            .collect();
        let fit = fit_linear(&samples_from(&l, &poses), &l).unwrap();
        let j = jacobian(&l, &Pose::default()).unwrap();
        // Agreement to 1e-5 of β's scale: the model's own curvature over ±1 µm / ±1″ is ~1e-6.
        let worst = (fit.beta - j).amax() / j.amax();
        assert!(worst < 1e-5, "{worst}");
        assert!(fit.offset.amax() < 1e-7, "{}", fit.offset.amax());
        assert_eq!(fit.rank, 7);
        assert!((fit.condition_number - 5.6).abs() < 0.05);
    }

    #[test]
    fn unexcited_dof_is_named() {
        let l = Layout::reference();
        let mut rng = crate::sim::rng::Rng::new(4);
        let poses: Vec<Pose> = (0..40)
            .map(|_| {
                let mut a: [f64; 6] = std::array::from_fn(|_| rng.uniform(-20.0, 20.0));
                a[4] = 0.0; // roll never moved
                Pose::new(Errors6::from_user(a), 0.0, 0.0)
            })
            .collect();
        let err = fit_linear(&samples_from(&l, &poses), &l).unwrap_err();
        assert!(matches!(err, CalError::LowRank { rank: 6, .. }), "{err}");
        assert!(err.to_string().contains("ey"), "{err}");
    }

    #[test]
    fn too_few_poses() {
        let l = Layout::reference();
        let err = fit_linear(&samples_from(&l, &[Pose::default(); 3]), &l).unwrap_err();
        assert!(matches!(err, CalError::TooFewPoses { n: 3, .. }));
    }
}
