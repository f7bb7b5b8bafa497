//! How the head sits on the machine: the fixed module (with the follower stage, which is built
//! into the head's base) is mounted with a small yaw, pitch and two offsets relative to the
//! axis, adjusted by four screws. This is not the head's installation (what the hexapod
//! calibrates on the bench): mounting the head never changes its calibration.
//!
//! In the head's frame a mount is indistinguishable from a constant angular error plus a
//! straightness that grows with the travel: the carriage runs along `Rᵀ·travel_axis`, not
//! along the travel axis. [`Mount::head_pose`] turns the axis' true errors into the pose the
//! head sees.

use crate::optics::geometry::{V3, rot_zyx};
use crate::units::Errors6;
use nalgebra::Matrix3;

/// The four adjustment screws of the head's mount.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Screw {
    /// Turns the head about the vertical (z) through the pivot: the beam's horizontal angle.
    Yaw,
    /// Turns the head about the horizontal across the travel (x): the beam's vertical angle.
    Pitch,
    /// Shifts the head across the travel, horizontally.
    X,
    /// Shifts the head vertically.
    Z,
}

impl Screw {
    pub const ALL: [Screw; 4] = [Screw::Yaw, Screw::Pitch, Screw::X, Screw::Z];

    /// The screw's name as the user reads and types it.
    pub fn name(self) -> &'static str {
        match self {
            Screw::Yaw => "yaw",
            Screw::Pitch => "pitch",
            Screw::X => "x",
            Screw::Z => "z",
        }
    }

    /// The screw named `s` (case-insensitive).
    pub fn parse(s: &str) -> Option<Screw> {
        Screw::ALL
            .into_iter()
            .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
    }

    fn index(self) -> usize {
        self as usize
    }
}

impl std::fmt::Display for Screw {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The head's mount relative to the axis: a rotation about the pivot (yaw about z, then pitch
/// about x, rad) and an offset across the travel (x, z in mm).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Mount {
    pub yaw: f64,
    pub pitch: f64,
    pub x: f64,
    pub z: f64,
}

impl Mount {
    /// The mount as four numbers in [`Screw::ALL`] order.
    pub fn to_array(self) -> [f64; 4] {
        [self.yaw, self.pitch, self.x, self.z]
    }

    pub fn from_array(a: [f64; 4]) -> Mount {
        Mount {
            yaw: a[0],
            pitch: a[1],
            x: a[2],
            z: a[3],
        }
    }

    /// The value one screw sets (rad or mm).
    pub fn get(self, s: Screw) -> f64 {
        self.to_array()[s.index()]
    }

    /// This mount with `amount` (rad or mm) added by screw `s`.
    pub fn adjusted(self, s: Screw, amount: f64) -> Mount {
        let mut a = self.to_array();
        a[s.index()] += amount;
        Mount::from_array(a)
    }

    /// Sum of two mounts (small angles: an adjustment on top of a mount).
    pub fn plus(self, o: Mount) -> Mount {
        let (a, b) = (self.to_array(), o.to_array());
        Mount::from_array(std::array::from_fn(|i| a[i] + b[i]))
    }

    fn rotation(self) -> Matrix3<f64> {
        rot_zyx(self.pitch, 0.0, self.yaw)
    }

    /// The pose the head sees when the axis' carriage is at `travel` with true errors `e`:
    /// the moving module's motion expressed in the head's frame, for a head whose pivot is at
    /// `pivot` (head frame, mm), with the moving module's reference point `c` and the travel
    /// along `travel_axis` (both as in the layout).
    ///
    /// A point of the moving module goes to `p_A = C + D·a + δ + R_e·(p − C)` in the axis'
    /// frame; the head's frame is `p_A = R_m·(p_H − P) + P + t`, so in the head's frame the
    /// module moves by `R' = R_mᵀ·R_e` and `δ' = R_mᵀ·(C + D·a + δ − P − t) + P − C − D·a`.
    pub fn head_pose(
        &self,
        pivot: V3,
        c: V3,
        travel_axis: V3,
        travel: f64,
        e: &Errors6,
    ) -> Errors6 {
        if *self == Mount::default() {
            return *e;
        }
        let rm_t = self.rotation().transpose();
        let t = V3::new(self.x, 0.0, self.z);
        let r = rm_t * rot_zyx(e.ex, e.ey, e.ez);
        let a = travel_axis * travel;
        let d = rm_t * (c + a + V3::new(e.dx, e.dy, e.dz) - pivot - t) + pivot - c - a;
        // R = Rz(ez)·Ry(ey)·Rx(ex).
        let ey = (-r[(2, 0)]).clamp(-1.0, 1.0).asin();
        let ex = r[(2, 1)].atan2(r[(2, 2)]);
        let ez = r[(1, 0)].atan2(r[(0, 0)]);
        Errors6 {
            dx: d.x,
            dy: d.y,
            dz: d.z,
            ex,
            ey,
            ez,
        }
    }
}

/// What one turn of a screw does (rad or mm per turn, clockwise as the technician faces the
/// screw head), and where the head pivots.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MountGeometry {
    /// The pivot of the yaw and pitch screws, in the head's frame (mm).
    pub pivot_mm: [f64; 3],
    /// Per turn, in [`Screw::ALL`] order: yaw and pitch in rad, x and z in mm.
    pub per_turn: [f64; 4],
}

impl Default for MountGeometry {
    /// The reference head's base: the pivot under the fixed module's centre (y = −380 mm);
    /// yaw and pitch by 0.25 mm-pitch fine screws on a 100 mm lever (2.5 mrad per turn);
    /// offsets by 0.5 mm-pitch screws.
    fn default() -> Self {
        MountGeometry {
            pivot_mm: [0.0, -380.0, 0.0],
            per_turn: [2.5e-3, 2.5e-3, 0.5, 0.5],
        }
    }
}

impl MountGeometry {
    /// Turns of screw `s` for an adjustment of `amount` (rad or mm).
    pub fn turns(&self, s: Screw, amount: f64) -> f64 {
        amount / self.per_turn[s.index()]
    }

    /// The adjustment (rad or mm) that `turns` of screw `s` make.
    pub fn amount(&self, s: Screw, turns: f64) -> f64 {
        turns * self.per_turn[s.index()]
    }

    pub fn pivot(&self) -> V3 {
        V3::from(self.pivot_mm)
    }

    /// Checks the geometry is usable: every screw moves something, the pivot is finite.
    pub fn validate(&self) -> Result<(), String> {
        for (s, v) in Screw::ALL.iter().zip(self.per_turn) {
            if !(v.is_finite() && v != 0.0) {
                return Err(format!(
                    "the {s} screw's travel per turn must be a non-zero number (got {v})"
                ));
            }
        }
        if !self.pivot_mm.iter().all(|v| v.is_finite()) {
            return Err("the mount's pivot must be finite (mm)".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry() -> (V3, V3, V3) {
        (
            V3::new(0.0, -380.0, 0.0),
            V3::zeros(),
            V3::new(0.0, 1.0, 0.0),
        )
    }

    #[test]
    fn no_mount_leaves_the_pose() {
        let (p, c, a) = geometry();
        let e = Errors6::from_user([3.0, -2.0, 1.0, 4.0, -5.0, 6.0]);
        assert_eq!(Mount::default().head_pose(p, c, a, 700.0, &e), e);
    }

    #[test]
    fn first_order_matches_the_rigid_body_algebra() {
        // δ' ≈ −t − ω×(C + D·a − P) with ω = (pitch, 0, yaw), angles −ω.
        let (p, c, a) = geometry();
        let m = Mount {
            yaw: 2e-4,
            pitch: -3e-4,
            x: 0.4,
            z: -0.7,
        };
        for d in [0.0, 500.0, 2000.0] {
            let got = m.head_pose(p, c, a, d, &Errors6::ZERO);
            let lever = d - p.y;
            assert!(
                (got.dx - (-m.x + m.yaw * lever)).abs() < 1e-6,
                "{d}: {}",
                got.dx
            );
            assert!(
                (got.dz - (-m.z - m.pitch * lever)).abs() < 1e-6,
                "{d}: {}",
                got.dz
            );
            assert!((got.ez + m.yaw).abs() < 1e-9 && (got.ex + m.pitch).abs() < 1e-9);
            assert!(got.ey.abs() < 1e-7);
            // Cosine error: the travel along the axis is shortened by D·(1 − cos).
            assert!(got.dy.abs() < 1e-3, "{}", got.dy);
        }
    }

    #[test]
    fn the_pose_is_exact_at_large_angles() {
        // A point carried by the module, mapped both ways, lands in the same place.
        let (p, c, a) = geometry();
        let m = Mount {
            yaw: 0.01,
            pitch: 0.02,
            x: 1.0,
            z: 2.0,
        };
        let e = Errors6 {
            ex: 0.003,
            ey: -0.002,
            ez: 0.001,
            dx: 0.1,
            dy: -0.05,
            dz: 0.02,
        };
        let d = 1500.0;
        let q = V3::new(10.0, 20.0, 30.0);
        let p_a = c + a * d + V3::new(e.dx, e.dy, e.dz) + rot_zyx(e.ex, e.ey, e.ez) * (q - c);
        let rm = rot_zyx(m.pitch, 0.0, m.yaw);
        let want = rm.transpose() * (p_a - p - V3::new(m.x, 0.0, m.z)) + p;
        let h = m.head_pose(p, c, a, d, &e);
        let got = c + a * d + V3::new(h.dx, h.dy, h.dz) + rot_zyx(h.ex, h.ey, h.ez) * (q - c);
        assert!((got - want).norm() < 1e-9, "{}", (got - want).norm());
    }

    #[test]
    fn screws_by_name_and_turns() {
        assert_eq!(Screw::parse(" Yaw"), Some(Screw::Yaw));
        assert_eq!(Screw::parse("roll"), None);
        let g = MountGeometry::default();
        assert!((g.turns(Screw::Yaw, 5e-3) - 2.0).abs() < 1e-12);
        assert!((g.amount(Screw::Z, -1.5) + 0.75).abs() < 1e-12);
        assert!(g.validate().is_ok());
        let bad = MountGeometry {
            per_turn: [0.0, 1.0, 1.0, 1.0],
            ..g
        };
        assert!(bad.validate().unwrap_err().contains("yaw screw"));
    }
}
