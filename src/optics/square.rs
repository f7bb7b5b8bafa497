//! The optical square (issue 27): a pentaprism that turns a beam through 90° whatever its
//! angle of incidence in the prism's principal plane, as the laser systems use it to measure
//! the squareness of two axes against one beam.
//!
//! A pentaprism is two reflecting faces at 45° to each other: two reflections compose to a
//! rotation about the faces' line of intersection (the prism's axis) by twice the angle between
//! them, so the deviation does not depend on how the prism is turned in its plane. A prism whose
//! faces stand at 45° + δ/2 turns the beam by 90° + δ: δ is the square's deviation, stated on
//! its certificate with its uncertainty. Tilting the prism's axis out of the plane tilts the
//! turned beam out of the plane (the set-up aligns that), not within it.
//!
//! Modelled here as exactly that: two ideal plane mirrors (`trace::reflect`), no refraction
//! (a pentaprism's entry and exit faces are normal to the beam and only offset it).

use super::V3;
use super::trace::reflect;
use nalgebra::{Rotation3, Unit};

/// A pentaprism: its axis (the line its two faces meet on, unit) and its deviation from 90°.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OpticalSquare {
    axis: V3,
    /// The turn is 90° + this (rad), positive about `axis` (right hand).
    pub deviation_rad: f64,
}

impl OpticalSquare {
    /// A square turning the beam by 90° + `deviation_rad` about `axis` (right hand). `None`
    /// for an axis of zero or non-finite length or a non-finite deviation.
    pub fn new(axis: V3, deviation_rad: f64) -> Option<OpticalSquare> {
        let n = axis.norm();
        (n.is_finite() && n > 0.0 && deviation_rad.is_finite()).then(|| OpticalSquare {
            axis: axis / n,
            deviation_rad,
        })
    }

    /// The prism's axis (unit).
    pub fn axis(&self) -> V3 {
        self.axis
    }

    /// The two faces' unit normals for a beam `d`: the first at right angles to the axis, in
    /// the plane of `d` and the axis (any one when `d` lies along the axis), the second
    /// turned from it about the axis by 45° + δ/2.
    fn faces(&self, d: V3) -> (V3, V3) {
        let mut n1 = d - self.axis * d.dot(&self.axis);
        if n1.norm() < 1e-9 {
            n1 = self.axis.cross(&V3::x());
            if n1.norm() < 1e-9 {
                n1 = self.axis.cross(&V3::y());
            }
        }
        let n1 = n1.normalize();
        let half = std::f64::consts::FRAC_PI_4 + self.deviation_rad / 2.0;
        let turn = Rotation3::from_axis_angle(&Unit::new_normalize(self.axis), half);
        (n1, turn * n1)
    }

    /// The beam `d` (any length) after the prism: reflected by its two faces.
    pub fn turn(&self, d: V3) -> V3 {
        let (n1, n2) = self.faces(d);
        reflect(reflect(d, n1), n2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::RAD_PER_ARCSEC;

    fn angle(a: V3, b: V3) -> f64 {
        a.cross(&b).norm().atan2(a.dot(&b))
    }

    /// The constant deviation: in the principal plane the beam turns by 90° + δ about the axis
    /// whatever its incidence (the prism turned in its plane), its length kept.
    #[test]
    fn a_beam_in_the_plane_turns_by_ninety_degrees_and_the_deviation() {
        for delta_arcsec in [0.0, 3.0, -7.5] {
            let delta = delta_arcsec * RAD_PER_ARCSEC;
            let sq = OpticalSquare::new(V3::z() * 2.0, delta).expect("square");
            for incidence_deg in [0.0f64, 1.0, -20.0, 44.0, 170.0] {
                let (s, c) = incidence_deg.to_radians().sin_cos();
                let d = V3::new(c, s, 0.0) * 3.0;
                let out = sq.turn(d);
                assert!((out.norm() - 3.0).abs() < 1e-12);
                let want = std::f64::consts::FRAC_PI_2 + delta;
                assert!(
                    (angle(d, out) - want).abs() < 1e-12,
                    "δ {delta_arcsec}″, incidence {incidence_deg}°: turned by {} rad, want {want}",
                    angle(d, out)
                );
                // Right hand about +z: x̂ goes to ŷ.
                assert!(d.cross(&out).dot(&V3::z()) > 0.0);
                assert!(out.z.abs() < 1e-12);
            }
        }
    }

    /// A beam that leaves the plane by ε leaves it by ε after the prism too (the turn is a
    /// rotation about the axis): a tilted prism tilts the beam out of the plane only.
    #[test]
    fn a_beam_out_of_the_plane_keeps_its_component_along_the_axis() {
        let sq = OpticalSquare::new(V3::z(), 0.0).expect("square");
        let eps = 1e-4;
        let d = V3::new(1.0, 0.0, eps).normalize();
        let out = sq.turn(d);
        assert!((out.z - d.z).abs() < 1e-15);
        assert!((out.x).abs() < 1e-12 && (out.y - d.x).abs() < 1e-12);
        // The axis tilted by τ about the incoming beam: the turned beam leaves the plane by τ.
        let tau: f64 = 2e-4;
        let tilted = OpticalSquare::new(V3::new(0.0, -tau.sin(), tau.cos()), 0.0).expect("tilted");
        let out = tilted.turn(V3::x());
        assert!((out.z - tau.sin()).abs() < 1e-12, "{}", out.z);
        assert!((out.x).abs() < 1e-12);
    }

    #[test]
    fn a_square_needs_an_axis() {
        assert!(OpticalSquare::new(V3::zeros(), 0.0).is_none());
        assert!(OpticalSquare::new(V3::z(), f64::NAN).is_none());
    }
}
