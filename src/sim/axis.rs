//! The twin's measured axis: a true six-DOF error profile along the travel and a carriage that
//! moves with a trapezoidal velocity profile.
//!
//! Each DOF's error is a smooth random shape (a low-order polynomial plus a few long-wavelength
//! harmonics) scaled to a stated peak; positioning adds the ball-screw's periodic error,
//! backlash (the carriage lags the command by half the backlash in the direction it last moved)
//! and a thermal drift that lengthens the axis over time.
//!
//! The axis can age (issue 15, [`Wear`]): wear of the screw and nut adds positioning error
//! where the axis works most and more backlash, and a steady thermal offset changes the scale.
//! It is set from the configuration (`[twin.axis] wear_*`) and changed while the twin runs
//! ([`AxisProfile::set_wear`]), so a maintenance re-measurement has something to find.

use super::Rng;
use crate::units::Errors6;
use std::f64::consts::PI;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// What years of use add to the axis (issue 15). All zero: as commissioned.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Wear {
    /// Peak of the positioning wear (µm): `p·sin²(π·u)` over the travel u ∈ [0, 1], worn
    /// most mid-travel where the axis works most, nothing at the ends.
    pub positioning_um: f64,
    /// Backlash added to the axis' own (µm).
    pub backlash_um: f64,
    /// A steady thermal offset (µm at the end of the travel, growing linearly from 0): the
    /// screw running warmer than when the axis was commissioned.
    pub thermal_um: f64,
}

impl Wear {
    /// Its positioning error (mm) at `u` of the travel, moving in `dir`.
    fn dy_mm(&self, u: f64, dir: Direction) -> f64 {
        let s = (PI * u).sin();
        let half = 0.5 * self.backlash_um;
        let b = match dir {
            Direction::Up => -half,
            Direction::Down => half,
        };
        (self.positioning_um * s * s + self.thermal_um * u + b) * 1e-3
    }
}

/// The wear in force, shared by the clones of a profile (the plant's and whoever ages it).
#[derive(Clone)]
struct WearCell(Arc<[AtomicU64; 3]>);

impl WearCell {
    fn new(w: Wear) -> Self {
        let c = WearCell(Arc::new(std::array::from_fn(|_| AtomicU64::new(0))));
        c.set(w);
        c
    }
    fn set(&self, w: Wear) {
        for (a, v) in self
            .0
            .iter()
            .zip([w.positioning_um, w.backlash_um, w.thermal_um])
        {
            a.store(v.to_bits(), Ordering::Relaxed);
        }
    }
    fn get(&self) -> Wear {
        let v = |k: usize| f64::from_bits(self.0[k].load(Ordering::Relaxed));
        Wear {
            positioning_um: v(0),
            backlash_um: v(1),
            thermal_um: v(2),
        }
    }
}

impl PartialEq for WearCell {
    fn eq(&self, other: &Self) -> bool {
        self.get() == other.get()
    }
}

impl std::fmt::Debug for WearCell {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.get().fmt(f)
    }
}

/// How large the twin's axis errors are. Peaks are the largest |value| over the travel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisSpec {
    /// Travel length (mm), from 0.
    pub length_mm: f64,
    /// Peak of the smooth positioning error (µm).
    pub positioning_um: f64,
    /// Amplitude of the ball-screw's periodic error (µm) and its lead (mm).
    pub periodic_um: f64,
    pub lead_mm: f64,
    /// Backlash (µm): the difference between approaching from below and from above.
    pub backlash_um: f64,
    /// Peak of each straightness (µm).
    pub straightness_um: f64,
    /// Peak of pitch and yaw (arcsec), and of roll (arcsec).
    pub pitch_yaw_arcsec: f64,
    pub roll_arcsec: f64,
    /// Thermal growth of the positioning scale (µm per metre per hour).
    pub thermal_um_per_m_per_h: f64,
    /// Ageing at the start (issue 15); changed later with `AxisProfile::set_wear`.
    pub wear: Wear,
}

impl Default for AxisSpec {
    fn default() -> Self {
        AxisSpec {
            length_mm: 1000.0,
            positioning_um: 30.0,
            periodic_um: 2.0,
            lead_mm: 10.0,
            backlash_um: 5.0,
            straightness_um: 20.0,
            pitch_yaw_arcsec: 8.0,
            roll_arcsec: 4.0,
            thermal_um_per_m_per_h: 0.0,
            wear: Wear::default(),
        }
    }
}

/// One DOF's smooth shape on u ∈ [0, 1]: a cubic plus harmonics, scaled to a peak.
#[derive(Clone, Debug, PartialEq)]
struct Shape {
    poly: [f64; 4],
    harmonics: Vec<(f64, f64, f64)>,
    scale: f64,
}

impl Shape {
    fn random(rng: &mut Rng, peak: f64) -> Shape {
        let poly = [
            0.0,
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ];
        let harmonics = (0..3)
            .map(|k| {
                let cycles = rng.uniform(1.0, 3.0) * (k + 1) as f64;
                (
                    rng.uniform(-0.4, 0.4) / (k + 1) as f64,
                    cycles,
                    rng.uniform(0.0, 2.0 * PI),
                )
            })
            .collect();
        let mut s = Shape {
            poly,
            harmonics,
            scale: 1.0,
        };
        let raw_peak = (0..=400)
            .map(|i| s.raw(i as f64 / 400.0).abs())
            .fold(0.0, f64::max);
        s.scale = if raw_peak > 0.0 { peak / raw_peak } else { 0.0 };
        s
    }

    fn raw(&self, u: f64) -> f64 {
        let p = self.poly;
        let poly = p[0] + u * (p[1] + u * (p[2] + u * p[3]));
        let h: f64 = self
            .harmonics
            .iter()
            .map(|(a, c, ph)| a * ((2.0 * PI * c * u + ph).sin() - ph.sin()))
            .sum();
        poly + h
    }

    fn at(&self, u: f64) -> f64 {
        self.scale * self.raw(u)
    }
}

/// Direction the carriage last moved in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    Up,
    Down,
}

/// The axis' true errors as a function of nominal position, direction and time.
#[derive(Clone, Debug, PartialEq)]
pub struct AxisProfile {
    pub spec: AxisSpec,
    shapes: [Shape; 6],
    periodic_phase: f64,
    wear: WearCell,
}

impl AxisProfile {
    /// A random profile within `spec`.
    pub fn random(spec: &AxisSpec, rng: &mut Rng) -> Self {
        let peaks = Errors6::from_user([
            spec.straightness_um,
            spec.positioning_um,
            spec.straightness_um,
            spec.pitch_yaw_arcsec,
            spec.roll_arcsec,
            spec.pitch_yaw_arcsec,
        ])
        .to_array();
        AxisProfile {
            spec: *spec,
            shapes: std::array::from_fn(|k| Shape::random(rng, peaks[k])),
            periodic_phase: rng.uniform(0.0, 2.0 * PI),
            wear: WearCell::new(spec.wear),
        }
    }

    /// Age the axis: `w` replaces the wear in force (for every clone of this profile, so the
    /// running plant's axis ages at once).
    pub fn set_wear(&self, w: Wear) {
        self.wear.set(w);
    }

    /// The wear in force.
    pub fn wear(&self) -> Wear {
        self.wear.get()
    }

    /// The positioning error (mm) the wear in force adds at nominal position `d`, moving in
    /// `dir` (what a re-measurement should find on top of the commissioned axis).
    pub fn wear_dy(&self, d: f64, dir: Direction) -> f64 {
        self.wear_dy_of(&self.wear.get(), d, dir)
    }

    /// The positioning error (mm) wear `w` would add at `d` moving in `dir`: what the axis
    /// would read on a day it had aged that far.
    pub fn wear_dy_of(&self, w: &Wear, d: f64, dir: Direction) -> f64 {
        let u = (d / self.spec.length_mm.max(1e-9)).clamp(-0.1, 1.1);
        w.dy_mm(u, dir)
    }

    /// A perfect axis of the given length.
    pub fn perfect(length_mm: f64) -> Self {
        let spec = AxisSpec {
            length_mm,
            positioning_um: 0.0,
            periodic_um: 0.0,
            backlash_um: 0.0,
            straightness_um: 0.0,
            pitch_yaw_arcsec: 0.0,
            roll_arcsec: 0.0,
            thermal_um_per_m_per_h: 0.0,
            wear: Wear::default(),
            ..AxisSpec::default()
        };
        AxisProfile::random(&spec, &mut Rng::new(0))
    }

    /// True errors (internal units) at nominal position `d` (mm), having last moved in `dir`,
    /// `hours` after the start.
    pub fn errors(&self, d: f64, dir: Direction, hours: f64) -> Errors6 {
        let u = (d / self.spec.length_mm.max(1e-9)).clamp(-0.1, 1.1);
        let mut e: [f64; 6] = std::array::from_fn(|k| self.shapes[k].at(u));
        let um = 1e-3;
        e[1] += self.spec.periodic_um
            * um
            * ((2.0 * PI * d / self.spec.lead_mm.max(1e-9) + self.periodic_phase).sin()
                - self.periodic_phase.sin());
        let half = 0.5 * self.spec.backlash_um * um;
        e[1] += match dir {
            Direction::Up => -half,
            Direction::Down => half,
        };
        e[1] += self.spec.thermal_um_per_m_per_h * um * (d / 1000.0) * hours;
        e[1] += self.wear.get().dy_mm(u, dir);
        Errors6::from_array(e)
    }
}

/// The carriage: trapezoidal moves between nominal positions.
#[derive(Clone, Debug, PartialEq)]
pub struct Carriage {
    /// Feed (mm/s) and acceleration (mm/s²).
    pub feed: f64,
    pub accel: f64,
    from: f64,
    to: f64,
    start: Instant,
    duration: Duration,
    direction: Direction,
}

impl Carriage {
    /// At rest at `position`.
    pub fn new(position: f64, feed: f64, accel: f64, now: Instant) -> Self {
        Carriage {
            feed: feed.max(1e-6),
            accel: accel.max(1e-6),
            from: position,
            to: position,
            start: now,
            duration: Duration::ZERO,
            direction: Direction::Up,
        }
    }

    /// Start a move to `target` from wherever the carriage is at `now`.
    pub fn move_to(&mut self, target: f64, now: Instant) {
        let here = self.position(now);
        let dist = (target - here).abs();
        // Trapezoid (or triangle when too short to reach the feed).
        let t_acc = self.feed / self.accel;
        let d_acc = self.feed * t_acc;
        let secs = if dist >= d_acc {
            2.0 * t_acc + (dist - d_acc) / self.feed
        } else {
            2.0 * (dist / self.accel).sqrt()
        };
        if target != here {
            self.direction = if target > here {
                Direction::Up
            } else {
                Direction::Down
            };
        }
        self.from = here;
        self.to = target;
        self.start = now;
        self.duration = Duration::from_secs_f64(secs);
    }

    /// Nominal position at `now` (mm).
    pub fn position(&self, now: Instant) -> f64 {
        let t = now.saturating_duration_since(self.start).as_secs_f64();
        let total = self.duration.as_secs_f64();
        if t >= total || total == 0.0 {
            return self.to;
        }
        let dist = (self.to - self.from).abs();
        let sign = (self.to - self.from).signum();
        let t_acc = (self.feed / self.accel).min(total / 2.0);
        let v = self.accel * t_acc;
        let s = if t < t_acc {
            0.5 * self.accel * t * t
        } else if t < total - t_acc {
            0.5 * self.accel * t_acc * t_acc + v * (t - t_acc)
        } else {
            let r = total - t;
            dist - 0.5 * self.accel * r * r
        };
        self.from + sign * s.clamp(0.0, dist)
    }

    /// Whether a move is under way at `now`.
    pub fn is_moving(&self, now: Instant) -> bool {
        now.saturating_duration_since(self.start) < self.duration
    }

    /// The target of the last move.
    pub fn target(&self) -> f64 {
        self.to
    }

    /// The direction of the last move.
    pub fn direction(&self) -> Direction {
        self.direction
    }

    /// When the current move ends.
    pub fn end(&self) -> Instant {
        self.start + self.duration
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profile_peaks_and_backlash() {
        let spec = AxisSpec::default();
        let p = AxisProfile::random(&spec, &mut Rng::new(1));
        let mut peak = [0.0f64; 6];
        for i in 0..=1000 {
            let d = i as f64;
            let up = p.errors(d, Direction::Up, 0.0).to_user();
            let down = p.errors(d, Direction::Down, 0.0).to_user();
            assert!((down[1] - up[1] - spec.backlash_um).abs() < 1e-9);
            for k in 0..6 {
                peak[k] = peak[k].max(up[k].abs());
            }
        }
        // Peaks are set on a 401-point grid: the true maximum may exceed it by a hair.
        assert!(peak[0] > 15.0 && peak[0] <= 20.0 * 1.01, "{peak:?}");
        // Smooth shape, periodic term (its range is twice its amplitude) and half the backlash.
        assert!(
            peak[1] > 25.0 && peak[1] <= 30.0 * 1.01 + 2.0 * 2.0 + 2.5,
            "{peak:?}"
        );
        // Zero at the start of travel, apart from backlash.
        let z = p.errors(0.0, Direction::Up, 0.0).to_user();
        assert!((z[1] + 2.5).abs() < 1e-9 && z[0].abs() < 1e-9);
    }

    #[test]
    fn carriage_moves_trapezoid() {
        let t0 = crate::util::clock::now();
        let mut c = Carriage::new(0.0, 50.0, 500.0, t0);
        c.move_to(100.0, t0);
        // 0.1 s ramps of 2.5 mm each, 95 mm at 50 mm/s: 2.1 s.
        assert!((c.end() - t0).as_secs_f64() - 2.1 < 1e-9);
        let mid = c.position(t0 + Duration::from_secs_f64(1.05));
        assert!((mid - 50.0).abs() < 1e-9, "{mid}");
        assert!((c.position(t0 + Duration::from_millis(100)) - 2.5).abs() < 1e-9);
        assert_eq!(c.position(t0 + Duration::from_secs(3)), 100.0);
        assert!(!c.is_moving(t0 + Duration::from_secs(3)));
        assert_eq!(c.direction(), Direction::Up);
        c.move_to(90.0, t0 + Duration::from_secs(3));
        assert_eq!(c.direction(), Direction::Down);
    }

    #[test]
    fn wear_adds_positioning_backlash_and_a_thermal_offset() {
        let spec = AxisSpec::default();
        let p = AxisProfile::random(&spec, &mut Rng::new(1));
        let new = |d: f64, dir| p.errors(d, dir, 0.0).to_user();
        let before: Vec<[f64; 6]> = [0.0, 500.0, 1000.0]
            .iter()
            .flat_map(|&d| [new(d, Direction::Up), new(d, Direction::Down)])
            .collect();
        let clone = p.clone();
        clone.set_wear(Wear {
            positioning_um: 4.0,
            backlash_um: 2.0,
            thermal_um: 3.0,
        });
        // The plant's copy ages with the one it was handed to.
        assert_eq!(p.wear().positioning_um, 4.0);
        let after: Vec<[f64; 6]> = [0.0, 500.0, 1000.0]
            .iter()
            .flat_map(|&d| [new(d, Direction::Up), new(d, Direction::Down)])
            .collect();
        // dy: −1/+1 µm of backlash at 0; 4 µm of wear and 1.5 µm thermal mid-travel; 3 µm
        // thermal at the end (sin²(π) = 0). Nothing else moves.
        let want = [
            -1.0,
            1.0,
            4.0 + 1.5 - 1.0,
            4.0 + 1.5 + 1.0,
            3.0 - 1.0,
            3.0 + 1.0,
        ];
        for (k, w) in want.iter().enumerate() {
            assert!(
                (after[k][1] - before[k][1] - w).abs() < 1e-9,
                "{k}: {} {}",
                after[k][1] - before[k][1],
                w
            );
            for dof in [0, 2, 3, 4, 5] {
                assert_eq!(after[k][dof], before[k][dof]);
            }
        }
        assert!((p.wear_dy(500.0, Direction::Down) * 1e3 - 6.5).abs() < 1e-9);
    }
}
