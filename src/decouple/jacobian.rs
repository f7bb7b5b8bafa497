//! β(D): the sensitivity of the six readings to the six errors, by central differences of the
//! forward model at travel D (DESIGN §3), and the noise figures derived from it.

use super::DecoupleError;
use crate::optics::{Layout, Pose};
use crate::units::{DOF_TO_USER, Errors6, MM_PER_UM};
use nalgebra::{Matrix6, Vector6};

/// Central-difference step for translations (mm) and rotations (rad).
const STEP_MM: f64 = 1e-3;
const STEP_RAD: f64 = 5e-6;

/// ∂readings/∂errors at `pose` (internal units: mm per mm, mm per rad). Columns are DOFs,
/// rows readings. Geometry only: apertures are not checked.
pub fn jacobian(layout: &Layout, pose: &Pose) -> Result<Matrix6<f64>, DecoupleError> {
    let mut j = Matrix6::zeros();
    let base = pose.errors.to_array();
    for k in 0..6 {
        let h = if k < 3 { STEP_MM } else { STEP_RAD };
        let mut plus = base;
        let mut minus = base;
        plus[k] += h;
        minus[k] -= h;
        let rp = readings_at(layout, pose, plus)?;
        let rm = readings_at(layout, pose, minus)?;
        j.set_column(k, &((rp - rm) / (2.0 * h)));
    }
    Ok(j)
}

fn readings_at(layout: &Layout, pose: &Pose, e: [f64; 6]) -> Result<Vector6<f64>, DecoupleError> {
    let p = Pose {
        errors: Errors6::from_array(e),
        ..*pose
    };
    super::model_readings(layout, &p)
}

/// A Jacobian in user units: µm per µm (translations), µm per arcsec (rotations).
pub fn to_user_units(j: &Matrix6<f64>) -> Matrix6<f64> {
    let mut out = *j;
    for c in 0..6 {
        let s = 1.0 / MM_PER_UM / DOF_TO_USER[c];
        for r in 0..6 {
            out[(r, c)] *= s;
        }
    }
    out
}

/// Covariance of the errors (internal units) for independent reading noise with standard
/// deviations `sigma_mm` per channel: `(Jᵀ Σ⁻¹ J)⁻¹`. `None` when J is singular.
pub fn covariance(j: &Matrix6<f64>, sigma_mm: &[f64; 6]) -> Option<Matrix6<f64>> {
    let mut w = *j;
    for r in 0..6 {
        let s = sigma_mm[r];
        if s.is_nan() || s <= 0.0 {
            return None;
        }
        for c in 0..6 {
            w[(r, c)] /= s;
        }
    }
    let fisher = w.transpose() * w;
    fisher.cholesky().map(|c| c.inverse())
}

/// Standard deviations (internal units) from a covariance.
pub fn sd_of(cov: &Matrix6<f64>) -> Errors6 {
    Errors6::from_array(std::array::from_fn(|k| cov[(k, k)].max(0.0).sqrt()))
}

/// The Cramér–Rao bound per DOF (internal units) for noise `sigma_mm` on every PSD axis.
pub fn crlb(j: &Matrix6<f64>, sigma_mm: f64) -> Option<Errors6> {
    covariance(j, &[sigma_mm; 6]).map(|c| sd_of(&c))
}

/// Singular values (descending) and condition number of a matrix.
pub fn conditioning(m: &Matrix6<f64>) -> ([f64; 6], f64) {
    let sv = m.singular_values();
    let mut s: [f64; 6] = std::array::from_fn(|i| sv[i]);
    s.sort_by(|a, b| b.total_cmp(a));
    let cond = if s[5] > 0.0 {
        s[0] / s[5]
    } else {
        f64::INFINITY
    };
    (s, cond)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The design's finite-difference Jacobian of the reference layout at D = d = 0
    /// (`jacobian_nominal.finite_difference` in reference-layout.json), µm per µm / arcsec.
    const REFERENCE: [[f64; 6]; 6] = [
        [0.0, 0.0, 0.0, 0.0, 0.0, 3.4906585039872575],
        [0.0, 0.0, 0.0, -3.4906585039886586, 0.0, 0.0],
        [
            1.0000000000047748,
            1.0000000000047748,
            0.0,
            0.0,
            0.0,
            -1.648366515819788,
        ],
        [0.0, 0.0, 0.0, -0.7272205216643041, 0.7272205216643041, 0.0],
        [2.000000000014287, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 2.0, 0.0, -0.2908882086657216, 0.0],
    ];

    #[test]
    fn matches_reference_jacobian() {
        let l = Layout::reference();
        let j = to_user_units(&jacobian(&l, &Pose::default()).unwrap());
        for r in 0..6 {
            for c in 0..6 {
                assert!(
                    (j[(r, c)] - REFERENCE[r][c]).abs() < 1e-7,
                    "({r},{c}) {} vs {}",
                    j[(r, c)],
                    REFERENCE[r][c]
                );
            }
        }
        let (_, cond) = conditioning(&j);
        assert!((cond - 5.6).abs() < 0.05, "condition number {cond}");
    }

    #[test]
    fn crlb_matches_design_figures() {
        let l = Layout::reference();
        let j = jacobian(&l, &Pose::default()).unwrap();
        let b = crlb(&j, 1e-3).unwrap().to_user();
        // DESIGN §2 / reference-layout.json crlb_sigma_1um.
        let want = [
            0.4999999999964283,
            1.213669570829819,
            0.5401260141032934,
            0.28647889756541167,
            1.4046233005176363,
            0.28647889756552664,
        ];
        for k in 0..6 {
            assert!(
                (b[k] - want[k]).abs() < 1e-6,
                "dof {k}: {} vs {}",
                b[k],
                want[k]
            );
        }
    }

    #[test]
    fn p1_rows_grow_with_travel() {
        let l = Layout::reference();
        let j0 = jacobian(&l, &Pose::default()).unwrap();
        let j100 = jacobian(&l, &Pose::new(Errors6::ZERO, 100.0, 100.0)).unwrap();
        let ratio = j100[(0, 5)] / j0[(0, 5)];
        assert!((ratio - 1.2778).abs() < 1e-3, "{ratio}");
        assert!((j0[(0, 5)] - 720.0).abs() < 1e-6);
    }
}
