//! The twin's hexapod: carries the moving module through known six-DOF poses for calibration
//! (the paper used a Newport HXP50). It may sit at several positions along a calibration
//! bench (`travels`) with the follower placed to match; its own repeatability can be added.

use super::{Rng, TwinHead};
use crate::calibrate::PoseSample;
use crate::optics::Pose;
use crate::units::Errors6;
use crate::util::progress::Progress;

/// The window the calibration poses cover (uniform within ± each half-range).
#[derive(Clone, Debug, PartialEq)]
pub struct PoseWindow {
    /// Half-range per DOF (internal units).
    pub half_range: Errors6,
    /// Bench positions (nominal travel D, mm); the follower stands at d = D.
    pub travels: Vec<f64>,
}

impl Default for PoseWindow {
    /// ±100 µm straightness, ±2 mm positioning (the follower window), ±60″ angles, at D = 0.
    fn default() -> Self {
        PoseWindow {
            half_range: Errors6::from_user([100.0, 2000.0, 100.0, 60.0, 60.0, 60.0]),
            travels: vec![0.0],
        }
    }
}

impl PoseWindow {
    /// `n` poses drawn uniformly in the window, cycling through the bench positions.
    pub fn draw(&self, n: usize, rng: &mut Rng) -> Vec<Pose> {
        let h = self.half_range.to_array();
        let travels = if self.travels.is_empty() {
            vec![0.0]
        } else {
            self.travels.clone()
        };
        (0..n)
            .map(|i| {
                let e = Errors6::from_array(std::array::from_fn(|k| rng.uniform(-h[k], h[k])));
                let d = travels[i % travels.len()];
                Pose::new(e, d, d)
            })
            .collect()
    }
}

/// A hexapod with its repeatability (standard deviation per DOF, internal units).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Hexapod {
    pub repeatability: Errors6,
}

impl Hexapod {
    /// Command each pose, read the head there, and record the commanded pose with the
    /// readings. Poses where a PSD reads nothing are skipped; their count is returned.
    pub fn acquire(
        &self,
        head: &TwinHead,
        poses: &[Pose],
        rng: &mut Rng,
        progress: &mut Progress,
    ) -> (Vec<PoseSample>, usize) {
        let rep = self.repeatability.to_array();
        let mut out = Vec::with_capacity(poses.len());
        let mut skipped = 0;
        for p in poses {
            let actual = Errors6::from_array({
                let c = p.errors.to_array();
                std::array::from_fn(|k| c[k] + rng.gauss(rep[k]))
            });
            let r = head.read(
                &Pose {
                    errors: actual,
                    ..*p
                },
                rng,
            );
            match r.vector() {
                Some(readings) => out.push(PoseSample { pose: *p, readings }),
                None => skipped += 1,
            }
            progress.inc();
        }
        (out, skipped)
    }
}
