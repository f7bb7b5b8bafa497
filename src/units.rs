//! The six errors, PSD readings and the unit conventions (DESIGN §1).
//!
//! Inside the crate every length is in millimetres and every angle in radians, as `f64`.
//! Micrometres and arcseconds exist only at the edges (files, CLI, console): the
//! `*_user` conversions below are the one place that scales between the two.

use nalgebra::Vector6;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Radians per arcsecond.
pub const RAD_PER_ARCSEC: f64 = PI / 648_000.0;
/// Millimetres per micrometre.
pub const MM_PER_UM: f64 = 1e-3;

/// Names of the six errors in `Errors6` order.
pub const DOF_NAMES: [&str; 6] = ["dx", "dy", "dz", "ex", "ey", "ez"];
/// What each DOF means for the head's frame (y along the travel).
pub const DOF_MEANING: [&str; 6] = [
    "horizontal straightness",
    "positioning",
    "vertical straightness",
    "pitch",
    "roll",
    "yaw",
];
/// User unit of each DOF.
pub const DOF_UNITS: [&str; 6] = ["µm", "µm", "µm", "arcsec", "arcsec", "arcsec"];
/// Names of the six readings in reading order.
pub const READING_NAMES: [&str; 6] = ["X1", "Y1", "X2", "Y2", "X3", "Y3"];

/// Internal → user scale of each DOF (mm → µm, rad → arcsec).
pub const DOF_TO_USER: [f64; 6] = [
    1.0 / MM_PER_UM,
    1.0 / MM_PER_UM,
    1.0 / MM_PER_UM,
    1.0 / RAD_PER_ARCSEC,
    1.0 / RAD_PER_ARCSEC,
    1.0 / RAD_PER_ARCSEC,
];

/// The six geometric errors of the moving module, in the head's frame: translations in mm,
/// rotations in rad. Order everywhere: dx, dy, dz, ex, ey, ez.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Errors6 {
    /// Horizontal straightness (mm).
    pub dx: f64,
    /// Positioning (mm).
    pub dy: f64,
    /// Vertical straightness (mm).
    pub dz: f64,
    /// Pitch, about x (rad).
    pub ex: f64,
    /// Roll, about y (rad).
    pub ey: f64,
    /// Yaw, about z (rad).
    pub ez: f64,
}

impl Errors6 {
    /// All zero.
    pub const ZERO: Errors6 = Errors6 {
        dx: 0.0,
        dy: 0.0,
        dz: 0.0,
        ex: 0.0,
        ey: 0.0,
        ez: 0.0,
    };

    /// From internal units (mm, rad) in DOF order.
    pub fn from_array(a: [f64; 6]) -> Self {
        Errors6 {
            dx: a[0],
            dy: a[1],
            dz: a[2],
            ex: a[3],
            ey: a[4],
            ez: a[5],
        }
    }

    /// To internal units (mm, rad) in DOF order.
    pub fn to_array(self) -> [f64; 6] {
        [self.dx, self.dy, self.dz, self.ex, self.ey, self.ez]
    }

    /// From user units (µm, arcsec) in DOF order.
    pub fn from_user(a: [f64; 6]) -> Self {
        let mut v = a;
        for (x, s) in v.iter_mut().zip(DOF_TO_USER) {
            *x /= s;
        }
        Self::from_array(v)
    }

    /// To user units (µm, arcsec) in DOF order.
    pub fn to_user(self) -> [f64; 6] {
        let mut v = self.to_array();
        for (x, s) in v.iter_mut().zip(DOF_TO_USER) {
            *x *= s;
        }
        v
    }

    /// As a column vector (internal units).
    pub fn to_vector(self) -> Vector6<f64> {
        Vector6::from(self.to_array())
    }

    /// From a column vector (internal units).
    pub fn from_vector(v: &Vector6<f64>) -> Self {
        Self::from_array([v[0], v[1], v[2], v[3], v[4], v[5]])
    }
}

/// Readings in user units (µm) → internal (mm).
pub fn readings_from_um(a: [f64; 6]) -> Vector6<f64> {
    Vector6::from(a) * MM_PER_UM
}

/// Readings internal (mm) → user units (µm).
pub fn readings_to_um(r: &Vector6<f64>) -> [f64; 6] {
    let mut out = [0.0; 6];
    for (o, x) in out.iter_mut().zip(r.iter()) {
        *o = x / MM_PER_UM;
    }
    out
}

/// A 6-vector of internal values → user units of the DOFs (µm, arcsec).
pub fn dof_vector_to_user(v: &Vector6<f64>) -> [f64; 6] {
    Errors6::from_vector(v).to_user()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn user_round_trip_and_scale() {
        let e = Errors6::from_user([1.0, -2.0, 3.0, 1.0, 10.0, -5.0]);
        assert!((e.dx - 0.001).abs() < 1e-15);
        assert!((e.ey - 10.0 * 4.848_136_811_095_36e-6).abs() < 1e-15);
        let back = e.to_user();
        for (a, b) in back.iter().zip([1.0, -2.0, 3.0, 1.0, 10.0, -5.0]) {
            assert!((a - b).abs() < 1e-12);
        }
    }
}
