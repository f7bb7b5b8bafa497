//! The twin's optical head: the nominal layout with installation errors applied, PSD gain
//! errors and Gaussian reading noise. Readings follow the PSDs' validity rules (apertures,
//! active areas) exactly as a real head would.

use super::{Rng, SimError};
use crate::optics::install::{ElementInstall, Installation};
use crate::optics::layout::Kind;
use crate::optics::{Layout, Pose, Readings};
use crate::units::Errors6;

/// How large the random installation errors are (uniform within ±).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstallSpec {
    /// Offset of each element along each world axis (mm).
    pub offset_mm: f64,
    /// Tilt of each element about each of its axes (degrees).
    pub tilt_deg: f64,
    /// Relative gain error of each PSD axis.
    pub gain_error: f64,
}

impl Default for InstallSpec {
    fn default() -> Self {
        InstallSpec {
            offset_mm: 0.5,
            tilt_deg: 0.2,
            gain_error: 0.0,
        }
    }
}

/// An installer aligns the head until every spot lies within this distance (mm, each axis)
/// of its PSD's centre at the home pose; the twin redraws heads that would fail that.
pub const ALIGN_LIMIT_MM: f64 = 2.0;
const MAX_DRAWS: usize = 10_000;

/// The twin's head.
#[derive(Clone, Debug)]
pub struct TwinHead {
    pub nominal: Layout,
    /// The true installation errors.
    pub install: Installation,
    /// The true layout (nominal with `install` applied).
    pub truth: Layout,
    /// Reading noise per PSD axis (mm, standard deviation).
    pub noise_mm: f64,
}

impl TwinHead {
    /// A head exactly as designed.
    pub fn ideal(nominal: &Layout, noise_mm: f64) -> Self {
        TwinHead {
            nominal: nominal.clone(),
            install: Installation::none(nominal),
            truth: nominal.clone(),
            noise_mm,
        }
    }

    /// A head with random installation errors within `spec`, aligned as an installer would.
    pub fn random(
        nominal: &Layout,
        spec: &InstallSpec,
        noise_mm: f64,
        rng: &mut Rng,
    ) -> Result<Self, SimError> {
        for v in [spec.offset_mm, spec.tilt_deg, spec.gain_error, noise_mm] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SimError::Input(format!(
                    "installation errors and noise must be finite and not negative (got {v})"
                )));
            }
        }
        let tilt = spec.tilt_deg.to_radians();
        for _ in 0..MAX_DRAWS {
            let install = Installation {
                elements: nominal
                    .elements
                    .iter()
                    .map(|el| {
                        let mut e = ElementInstall {
                            offset: std::array::from_fn(|_| {
                                rng.uniform(-1.0, 1.0) * spec.offset_mm
                            }),
                            tilt: std::array::from_fn(|_| rng.uniform(-1.0, 1.0) * tilt),
                            gain_error: [0.0; 2],
                        };
                        if el.kind == Kind::Psd {
                            e.gain_error =
                                std::array::from_fn(|_| rng.uniform(-1.0, 1.0) * spec.gain_error);
                        }
                        e
                    })
                    .collect(),
            };
            let mut install = install;
            if spec.tilt_deg > 0.0 || spec.offset_mm > 0.0 {
                factory_align(nominal, &mut install, rng);
            }
            let truth = install.apply(nominal);
            let home = truth.forward(&Pose::default());
            let aligned = home.psd.iter().all(|s| {
                s.as_ref()
                    .is_ok_and(|s| s.x.abs() <= ALIGN_LIMIT_MM && s.y.abs() <= ALIGN_LIMIT_MM)
            });
            if aligned {
                return Ok(TwinHead {
                    nominal: nominal.clone(),
                    install,
                    truth,
                    noise_mm,
                });
            }
        }
        Err(SimError::CannotAlign {
            offset_mm: spec.offset_mm,
            tilt_deg: spec.tilt_deg,
            limit_mm: ALIGN_LIMIT_MM,
            tries: MAX_DRAWS,
        })
    }

    /// Noise-free readings at a pose.
    pub fn exact(&self, pose: &Pose) -> Readings {
        self.truth.forward(pose)
    }

    /// Readings at a pose with PSD noise.
    pub fn read(&self, pose: &Pose, rng: &mut Rng) -> Readings {
        let mut r = self.truth.forward(pose);
        for s in r.psd.iter_mut().flatten() {
            s.x += rng.gauss(self.noise_mm);
            s.y += rng.gauss(self.noise_mm);
        }
        r
    }

    /// Readings at zero error with the follower following the travel (d = D).
    pub fn home_readings(&self) -> Readings {
        self.exact(&Pose::new(Errors6::ZERO, 0.0, 0.0))
    }
}

/// The factory's alignment tolerance of the beams' and the moving mirror's angles (rad).
const FACTORY_TOLERANCE_RAD: f64 = 20e-6;

/// The spots' slopes over 1000 mm of travel with no axis error and the follower following: the
/// beams' angles to the travel (X2, Y2 for beam A; X3, Y3 for beam B) and the moving
/// splitter's angle to beam A (X1, Y1). Zero on a factory-aligned head.
fn slopes(layout: &Layout) -> Option<[f64; 6]> {
    let at = |d: f64| {
        layout
            .forward_unbounded(&Pose::new(Errors6::ZERO, d, d))
            .vector()
    };
    let (a, b) = (at(0.0)?, at(1000.0)?);
    Some(std::array::from_fn(|i| b[i] - a[i]))
}

/// Align the head as its maker does, before it ships: tilt the laser until beam A runs
/// parallel to the housing's travel axis, the fold mirror until beam B does, and the moving
/// splitter until it returns beam A on itself, each within the factory's tolerance. (A head
/// whose two beams are not parallel cannot be aligned to any axis: over 2 m the corner cube's
/// spot would walk off PSD3 whatever the mount.) Layouts without those elements are left.
fn factory_align(nominal: &Layout, install: &mut Installation, rng: &mut Rng) {
    let find = |name: &str| nominal.elements.iter().position(|e| e.name == name);
    let (Some(laser), Some(fold), Some(splitter)) = (find("LASER"), find("M0"), find("BS2")) else {
        return;
    };
    let params = [
        (laser, 0),
        (laser, 1),
        (fold, 0),
        (fold, 1),
        (splitter, 0),
        (splitter, 1),
    ];
    let tilt = |i: &Installation, (e, k): (usize, usize)| i.elements[e].tilt[k];
    let set = |i: &mut Installation, (e, k): (usize, usize), v: f64| i.elements[e].tilt[k] = v;
    for _ in 0..4 {
        let Some(r) = slopes(&install.apply(nominal)) else {
            return;
        };
        if r.iter().all(|v| v.abs() < 1e-6) {
            break;
        }
        let h = 1e-5;
        let mut j = nalgebra::Matrix6::zeros();
        for (c, &p) in params.iter().enumerate() {
            let v = tilt(install, p);
            set(install, p, v + h);
            let hi = slopes(&install.apply(nominal));
            set(install, p, v - h);
            let lo = slopes(&install.apply(nominal));
            set(install, p, v);
            let (Some(hi), Some(lo)) = (hi, lo) else {
                return;
            };
            for row in 0..6 {
                j[(row, c)] = (hi[row] - lo[row]) / (2.0 * h);
            }
        }
        let Ok(step) = j.svd(true, true).solve(&nalgebra::Vector6::from(r), 1e-12) else {
            return;
        };
        for (c, &p) in params.iter().enumerate() {
            set(install, p, tilt(install, p) - step[c]);
        }
    }
    for p in params {
        let v = tilt(install, p) + rng.uniform(-1.0, 1.0) * FACTORY_TOLERANCE_RAD;
        set(install, p, v);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_head_is_aligned_and_reproducible() {
        let l = Layout::reference();
        let a = TwinHead::random(&l, &InstallSpec::default(), 1e-3, &mut Rng::new(5)).unwrap();
        let b = TwinHead::random(&l, &InstallSpec::default(), 1e-3, &mut Rng::new(5)).unwrap();
        assert_eq!(a.install, b.install);
        let home = a.home_readings().vector().unwrap();
        assert!(home.amax() <= ALIGN_LIMIT_MM);
        // Errors really are there: some spot sits well away from the nominal centre.
        assert!(home.amax() > 0.05, "{home}");
        let max_off = a
            .install
            .elements
            .iter()
            .flat_map(|e| e.offset)
            .fold(0.0_f64, |m, x| m.max(x.abs()));
        assert!(max_off > 0.3 && max_off <= 0.5);
    }

    #[test]
    fn random_heads_leave_the_factory_aligned() {
        // Over 1000 mm the spots walk by at most twice the tolerance times the lever (µm), where
        // unaligned 0.2° tilts would walk them by millimetres.
        let l = Layout::reference();
        for seed in 1..6 {
            let h =
                TwinHead::random(&l, &InstallSpec::default(), 1e-3, &mut Rng::new(seed)).unwrap();
            let s = slopes(&h.truth).unwrap();
            let worst = s.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            assert!(worst < 0.12, "seed {seed}: {s:?}");
        }
        let mut rng = Rng::new(3);
        let mut i = Installation::none(&l);
        for e in &mut i.elements {
            e.tilt = [2e-3, -3e-3, 1e-3];
        }
        let before = slopes(&i.apply(&l)).unwrap();
        assert!(before.iter().any(|v| v.abs() > 1.0), "{before:?}");
        factory_align(&l, &mut i, &mut rng);
        let after = slopes(&i.apply(&l)).unwrap();
        assert!(after.iter().all(|v| v.abs() < 0.12), "{after:?}");
    }

    #[test]
    fn noise_has_the_stated_spread() {
        let l = Layout::reference();
        let h = TwinHead::ideal(&l, 1e-3);
        let mut rng = Rng::new(9);
        let n = 20_000;
        let ss: f64 = (0..n)
            .map(|_| h.read(&Pose::default(), &mut rng).vector().unwrap()[3].powi(2))
            .sum();
        let sd = (ss / n as f64).sqrt();
        assert!((sd - 1e-3).abs() < 3e-5, "{sd}");
    }
}
