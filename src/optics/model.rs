//! The forward model `(errors, travel D, follower d) → six readings` (DESIGN §1–§2).

use super::geometry::{Frame, module_transform};
use super::layout::{Layout, Module};
use super::trace::{Invalid, Spot, trace_path};
use crate::units::Errors6;
use nalgebra::Vector6;

/// Where the moving module and the follower are: the six errors, nominal travel D (mm) and
/// follower displacement d (mm).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    pub errors: Errors6,
    pub travel: f64,
    pub follower: f64,
}

impl Pose {
    /// A pose with the given errors at travel and follower positions.
    pub fn new(errors: Errors6, travel: f64, follower: f64) -> Self {
        Pose {
            errors,
            travel,
            follower,
        }
    }
}

/// The three PSDs' spots (mm), each valid or with the reason it is not.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Readings {
    pub psd: [Result<Spot, Invalid>; 3],
}

impl Readings {
    /// The six readings (X1, Y1, X2, Y2, X3, Y3) in mm when all three PSDs are valid.
    pub fn vector(&self) -> Option<Vector6<f64>> {
        let mut v = Vector6::zeros();
        for (k, s) in self.psd.iter().enumerate() {
            let s = s.as_ref().ok()?;
            v[2 * k] = s.x;
            v[2 * k + 1] = s.y;
        }
        Some(v)
    }

    /// The first invalid PSD's reason, if any.
    pub fn first_invalid(&self) -> Option<Invalid> {
        self.psd.iter().find_map(|s| s.err())
    }
}

impl Layout {
    /// Element `i`'s frame at a pose: moving elements follow the module transform, the follower
    /// translates along its axis, fixed elements stay.
    #[inline]
    fn frame_at(&self, i: usize, module_t: &nalgebra::Matrix4<f64>, follower: f64) -> Frame {
        let el = &self.elements[i];
        match el.module {
            Module::Fixed => el.frame,
            Module::Moving => el.frame.transformed(module_t),
            Module::Follower => el.frame.translated(self.follower_axis * follower),
        }
    }

    /// Trace the three paths at `pose`, as the PSDs would see it: a beam outside an aperture
    /// or a spot off a PSD's active area gives no reading.
    pub fn forward(&self, pose: &Pose) -> Readings {
        self.forward_with(pose, true)
    }

    /// Trace the geometry only, without aperture or active-area checks: the model used for
    /// decoupling and fitting, where a reading that arrived is valid by definition and the
    /// model's apertures are only approximate.
    pub fn forward_unbounded(&self, pose: &Pose) -> Readings {
        self.forward_with(pose, false)
    }

    fn forward_with(&self, pose: &Pose, apertures: bool) -> Readings {
        let t = module_transform(self.c, self.travel_axis, pose.travel, &pose.errors);
        let trace = |k: usize| {
            trace_path(&self.elements, &self.paths[k], k, apertures, |i| {
                self.frame_at(i, &t, pose.follower)
            })
        };
        Readings {
            psd: [trace(0), trace(1), trace(2)],
        }
    }

    /// One-line description of an invalid reading.
    pub fn describe(&self, inv: &Invalid) -> String {
        inv.describe(&self.elements, &self.paths)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::{MM_PER_UM, RAD_PER_ARCSEC};

    /// The first-order closed form of DESIGN §2 for the reference layout, in mm, from the
    /// layout's geometry: L1 = BS2→PBS (320) + PBS→PSD1 (40); the P2 yaw lever is twice
    /// MIRROR1→PSD2 (2·150) plus twice MIRROR1's x-offset from C (2·20); ρ2 = 150; the P3 roll
    /// lever is twice the corner cube apex's x (2·30).
    fn closed_form(e: &Errors6, travel: f64, follower: f64) -> [f64; 6] {
        let l1 = 320.0 + 40.0 + travel;
        [
            2.0 * l1 * e.ez,
            -2.0 * l1 * e.ex,
            e.dx + e.dy - (2.0 * 150.0 + 2.0 * 20.0) * e.ez + (travel - follower),
            150.0 * (e.ey - e.ex),
            2.0 * e.dx,
            2.0 * e.dz - 2.0 * 30.0 * e.ey,
        ]
    }

    #[test]
    fn zero_pose_reads_centres() {
        let l = Layout::reference();
        let r = l.forward(&Pose::default()).vector().unwrap();
        assert!(r.norm() < 1e-12, "{r}");
    }

    #[test]
    fn first_order_closed_form_within_1e_3_um() {
        let l = Layout::reference();
        let mut rng = crate::sim::rng::Rng::new(11);
        for k in 0..2000 {
            let e = if k < 12 {
                // Each DOF alone at ±1 µm / ±1″.
                let mut a = [0.0; 6];
                a[k % 6] = if k < 6 { 1.0 } else { -1.0 };
                Errors6::from_user(a)
            } else {
                Errors6::from_user(std::array::from_fn(|_| rng.uniform(-1.0, 1.0)))
            };
            let got = l.forward(&Pose::new(e, 0.0, 0.0)).vector().unwrap();
            let want = closed_form(&e, 0.0, 0.0);
            for i in 0..6 {
                let diff_um = (got[i] - want[i]) / MM_PER_UM;
                assert!(diff_um.abs() < 1e-3, "k {k} reading {i}: {diff_um} µm");
            }
        }
    }

    #[test]
    fn travel_lengthens_the_p1_lever() {
        let l = Layout::reference();
        let e = Errors6 {
            ez: 10.0 * RAD_PER_ARCSEC,
            ..Errors6::ZERO
        };
        let r0 = l.forward(&Pose::new(e, 0.0, 0.0)).vector().unwrap();
        let r100 = l.forward(&Pose::new(e, 100.0, 100.0)).vector().unwrap();
        let ratio = r100[0] / r0[0];
        assert!((ratio - 460.0 / 360.0).abs() < 1e-4, "{ratio}");
    }

    #[test]
    fn spot_off_psd2_is_invalid_with_reason() {
        let l = Layout::reference();
        let r = l.forward(&Pose::new(Errors6::ZERO, 10.0, 0.0));
        assert!(r.psd[0].is_ok() && r.psd[2].is_ok());
        let inv = r.psd[1].unwrap_err();
        let s = l.describe(&inv);
        assert!(s.contains("spot off PSD2 active area"), "{s}");
        assert!(r.vector().is_none());
    }

    #[test]
    fn tracer_refuses_wrong_polarisation() {
        // Validation refuses such a path on load; the tracer checks again (a hand-built path).
        use crate::optics::trace::{InvalidKind, trace_path};
        let l = Layout::reference();
        let mut path = l.paths[0].clone();
        path.steps.remove(5); // the second QWP pass: the PBS now sees CP
        let t = nalgebra::Matrix4::identity();
        let err = trace_path(&l.elements, &path, 0, true, |i| l.frame_at(i, &t, 0.0)).unwrap_err();
        assert_eq!(l.elements[err.element].name, "PBS");
        assert!(matches!(
            err.kind,
            InvalidKind::Polarisation {
                got: crate::optics::layout::Polarisation::Cp
            }
        ));
    }

    #[test]
    fn follower_moves_psd2_only() {
        let l = Layout::reference();
        let r = l
            .forward(&Pose::new(Errors6::ZERO, 0.0, 1.0))
            .vector()
            .unwrap();
        assert!((r[2] + 1.0).abs() < 1e-12);
        assert!(r[0].abs() + r[1].abs() + r[3].abs() + r[4].abs() + r[5].abs() < 1e-12);
    }
}
