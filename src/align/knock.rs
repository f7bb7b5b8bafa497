//! The head knocked on its mount, seen in the stream of decoupled frames (issue 24).
//!
//! A machine axis' angular errors change smoothly with the carriage's position; a knock turns
//! the whole head on its mount at once, and everything it reads turns with it
//! ([`Mount::head_pose`]): pitch (ex) and yaw (ez) step by the turn, and the straightnesses
//! step by the turn times the distance from the mount's pivot, which grows with the travel.
//! A constant zero shift cannot undo that; the turn, once known, undoes it everywhere.
//!
//! [`KnockWatch`] fits the newest `2·half` frames' pitch and yaw, each as a parabola in the
//! carriage's position (an axis' waviness over the window) plus a step between the two halves, and tests the step against the
//! scatter about that fit. It reports a knock where the step's significance peaks (the step
//! in the middle of the window), with the turn that explains it and that turn's standard
//! uncertainty. The same fit gives the steps dx, dy and dz took with it ([`Step`]): a turn about
//! a pivot off the nominal one moves the head across and along the beam as well, by the turn
//! times the pivot's error (a real mount's pivot is known to a few centimetres), which the
//! turn alone does not undo. A knock that only shifts the head (no turn) is not seen here: the
//! run's judge finds such a shift against the captures from before (`run::judge`).
//!
//! Sans-I/O: the caller gives each frame's time, position and errors, and resets the watch
//! where the errors it gives step for another reason (a new zero, another decoupler).

use super::mount::Mount;
use crate::units::Errors6;
use crate::util::clock::{FrameTime, Stamp};
use nalgebra::{Matrix4, Vector4};
use std::collections::VecDeque;

/// How the watch decides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KnockSettings {
    /// Frames on each side of the step tested.
    pub half: usize,
    /// Significance a step needs (standard deviations, pitch and yaw together).
    pub z: f64,
    /// The smallest turn reported (rad): below it a knock moves a straightness by less than
    /// a tenth of a micrometre per 200 mm.
    pub min_rad: f64,
}

impl Default for KnockSettings {
    /// 160 frames a side (0.32 s at 500 Hz): with the carriage at rest a 2 µrad knock stands
    /// about 10 σ above the reference head's frame noise at the near end (1.4 µrad a frame).
    fn default() -> Self {
        KnockSettings {
            half: 160,
            z: 5.5,
            min_rad: 0.5e-6,
        }
    }
}

/// A knock found: when it happened and the turn it gave the head.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Knock {
    /// The first frame after the step (µs since the epoch; to within a few frames for a knock
    /// near the limit), or from the return to the zero that found it, the last agreement
    /// before: in words.
    pub unix_us: i64,
    /// The same frame in the order frames were read: the frames from it on read through the
    /// turn. The wall clock can step back between two frames; this cannot.
    pub since: FrameTime,
    /// The head's turn on its mount (yaw and pitch; no offsets).
    pub turn: Mount,
    /// Standard uncertainty of the turn's yaw and pitch (rad).
    pub sd_rad: [f64; 2],
    /// How many standard deviations the step stood out.
    pub z: f64,
    /// What dx, dy and dz stepped by with the turn, as read (found in the frames; none for a
    /// turn found at a return to the zero, where the carriage came back from a move).
    pub step: Option<Step>,
}

/// The steps of dx, dy and dz (mm) at a knock, as the head read them, and their standard
/// uncertainties.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step {
    pub mm: [f64; 3],
    pub sd_mm: [f64; 3],
}

impl Knock {
    /// The turn in words: "yaw -4.1 µrad, pitch +0.2 µrad".
    pub fn describe(&self) -> String {
        format!(
            "yaw {:+.1} µrad, pitch {:+.1} µrad (±{:.1} µrad)",
            self.turn.yaw * 1e6,
            self.turn.pitch * 1e6,
            self.sd_rad[0].max(self.sd_rad[1]) * 1e6
        )
    }
}

#[derive(Clone, Copy, Debug)]
struct Point {
    stamp: Stamp,
    position: f64,
    /// Pitch (ex) and yaw (ez), rad, then dx, dy, dz, mm: the angles decide, all five step.
    read: [f64; 5],
}

/// Below this spread of positions (mm) the window is at rest: no slope is fitted.
const AT_REST_MM: f64 = 0.1;

/// A moving window is tested only where the carriage went one way: its net move at least
/// this share of the positions' spread.
const MONOTONIC: f64 = 0.9;

/// The most the position columns may inflate the step's variance before a window is not
/// tested.
const BLUR: f64 = 8.0;

/// A step that crossed the threshold at the middle is confirmed where it lies within this
/// many standard deviations under it (the noise moves as the window does).
const CONFIRM_SLACK: f64 = 0.5;

/// Beyond this spread of positions (mm) a parabola no longer describes an axis' angles over
/// the window (a short axis may wave by 3 µrad a millimetre): no step is tested. A knock in a
/// move is left to the run's judge, which finds it against the captures from before.
const SPAN_MM: f64 = 2.0;

/// Watches for knocks.
#[derive(Clone, Debug)]
pub struct KnockWatch {
    settings: KnockSettings,
    window: VecDeque<Point>,
    /// Frames since a step at the window's middle crossed the threshold.
    pending: Option<usize>,
}

impl KnockWatch {
    pub fn new(settings: KnockSettings) -> Self {
        KnockWatch {
            settings,
            window: VecDeque::with_capacity(2 * settings.half + 1),
            pending: None,
        }
    }

    /// Forget the frames seen: the errors given from now on step for another reason.
    pub fn reset(&mut self) {
        self.window.clear();
        self.pending = None;
    }

    /// One frame read at `stamp`, the carriage at `position` (mm) and `errors` (the head's
    /// frame, internal units). Returns a knock once its step has passed the window's middle.
    /// After a knock the watch starts again: the caller corrects what follows by its turn.
    pub fn push(&mut self, stamp: Stamp, position: f64, errors: &Errors6) -> Option<Knock> {
        let read = [errors.ex, errors.ez, errors.dx, errors.dy, errors.dz];
        if !(position.is_finite() && read.iter().all(|v| v.is_finite())) {
            return None;
        }
        let n = 2 * self.settings.half;
        self.window.push_back(Point {
            stamp,
            position,
            read,
        });
        if self.window.len() > n {
            self.window.pop_front();
        }
        if self.window.len() < n {
            return None;
        }
        match self.pending {
            None => {
                let crossed = self.step_at(self.settings.half).is_some_and(|k| {
                    k.z >= self.settings.z
                        && k.turn.yaw.abs().max(k.turn.pitch.abs()) >= self.settings.min_rad
                });
                if crossed {
                    self.pending = Some(0);
                }
                None
            }
            Some(waited) if waited + 1 < self.settings.half / 2 => {
                self.pending = Some(waited + 1);
                None
            }
            Some(_) => {
                // A step stands out at the middle first when it has come into the window's
                // second half (a large one as soon as it is in): half a half later it lies
                // within the middle half, where the split that stands out most finds it.
                self.pending = None;
                let quarter = self.settings.half / 4;
                let knock = (quarter..n - quarter)
                    .filter_map(|split| self.step_at(split))
                    .max_by(|a, b| a.z.total_cmp(&b.z))
                    .filter(|k| {
                        k.z >= self.settings.z - CONFIRM_SLACK
                            && k.turn.yaw.abs().max(k.turn.pitch.abs()) >= self.settings.min_rad
                    });
                if knock.is_some() {
                    self.window.clear();
                }
                knock
            }
        }
    }

    /// The step before frame `split` of the window, each angle (and each straightness and dy)
    /// fitted as a + b·x + q·x² + c·step (x the position from the window's mean; at rest,
    /// a + c·step).
    fn step_at(&self, split: usize) -> Option<Knock> {
        let n = self.window.len();
        let mean_pos = self.window.iter().map(|p| p.position).sum::<f64>() / n as f64;
        let (lo, hi) = self
            .window
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
                (a.min(p.position), b.max(p.position))
            });
        if hi - lo > SPAN_MM {
            return None;
        }
        let moving = hi - lo > AT_REST_MM;
        // There and back (an overrun and the return to a target): an axis' angles at the same
        // position differ with the direction of travel, and would pass for a step.
        let net = self.window[n - 1].position - self.window[0].position;
        if moving && net.abs() < MONOTONIC * (hi - lo) {
            return None;
        }
        // Scaled to the window's half span, so the normal equations stay well conditioned.
        let span = if moving { 0.5 * (hi - lo) } else { 1.0 };
        let row = |i: usize, p: &Point| {
            let x = if moving {
                (p.position - mean_pos) / span
            } else {
                0.0
            };
            Vector4::new(1.0, x, x * x, if i >= split { 1.0 } else { 0.0 })
        };
        let mut xtx = Matrix4::zeros();
        let mut xty = [Vector4::zeros(); 5];
        for (i, p) in self.window.iter().enumerate() {
            let x = row(i, p);
            xtx += x * x.transpose();
            for (sum, v) in xty.iter_mut().zip(p.read) {
                *sum += x * v;
            }
        }
        if !moving {
            xtx[(1, 1)] = 1.0;
            xtx[(2, 2)] = 1.0;
        }
        let inv = xtx.try_inverse()?;
        // How far the position columns blur the step: at rest the step's variance is
        // 1/n₁ + 1/n₂ of a frame's; moving steadily about four times that. A window where the
        // carriage rests and moves (a stop-and-go step, a start) tells a step from the axis'
        // own change over the move by a few frames only: not tested.
        let at_rest = 1.0 / split as f64 + 1.0 / (n - split) as f64;
        if inv[(3, 3)] > BLUR * at_rest {
            return None;
        }
        let dof = n as f64 - if moving { 4.0 } else { 2.0 };
        let mut c = [0.0; 5];
        let mut sd = [0.0; 5];
        for a in 0..5 {
            let beta = inv * xty[a];
            let rss: f64 = self
                .window
                .iter()
                .enumerate()
                .map(|(i, p)| (p.read[a] - row(i, p).dot(&beta)).powi(2))
                .sum();
            let var_c = rss / dof * inv[(3, 3)];
            // The angles decide: without scatter there is no significance to test.
            if var_c.is_nan() || a < 2 && var_c <= 0.0 {
                return None;
            }
            c[a] = beta[3];
            sd[a] = var_c.max(0.0).sqrt();
        }
        let chi2 = (0..2).map(|a| c[a] * c[a] / (sd[a] * sd[a])).sum::<f64>();
        let first = self.window[split];
        // The head turned by t: it reads pitch and yaw less by t (Mount::head_pose).
        Some(Knock {
            unix_us: first.stamp.unix_us,
            since: first.stamp.order(),
            turn: Mount {
                yaw: -c[1],
                pitch: -c[0],
                x: 0.0,
                z: 0.0,
            },
            sd_rad: [sd[1], sd[0]],
            z: chi2.sqrt(),
            step: Some(Step {
                mm: [c[2], c[3], c[4]],
                sd_mm: [sd[2], sd[3], sd[4]],
            }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Rng;
    use crate::util::clock::stamp_us;

    /// Frames at 500 Hz of a carriage at `speed` mm/s from 0 mm whose true pitch and yaw
    /// wave with the position (8″ over 300 mm wavelengths), 1.4 µrad of noise, the head
    /// turned by `knock` from frame `at` on. Returns the watch's knocks with their frame.
    fn watch(
        seed: u64,
        speed: f64,
        frames: usize,
        knock: Option<(usize, f64, f64)>,
    ) -> Vec<(usize, Knock)> {
        watch_shifted(seed, speed, frames, knock, [0.0; 3])
    }

    /// As [`watch`], the straightnesses and dy waving too (a micrometre over the same
    /// wavelengths, 0.3 µm of noise), and stepping by `shift` (mm) with the knock.
    fn watch_shifted(
        seed: u64,
        speed: f64,
        frames: usize,
        knock: Option<(usize, f64, f64)>,
        shift: [f64; 3],
    ) -> Vec<(usize, Knock)> {
        let mut rng = Rng::new(seed);
        let mut w = KnockWatch::new(KnockSettings::default());
        let amp = 8.0 * 4.848e-6;
        let mut out = Vec::new();
        let mut turned = (0.0, 0.0);
        let mut moved = [0.0; 3];
        for i in 0..frames {
            if let Some((at, yaw, pitch)) = knock
                && i == at
            {
                turned = (yaw, pitch);
                moved = shift;
            }
            let pos = speed * i as f64 / 500.0;
            let k = std::f64::consts::TAU * pos / 300.0;
            let wave = |j: f64| 1e-3 * (j * k).sin();
            let e = Errors6 {
                ex: amp * k.sin() - turned.1 + rng.gauss(1.4e-6),
                ez: amp * (1.3 * k).cos() - turned.0 + rng.gauss(1.4e-6),
                dx: wave(0.7) + moved[0] + rng.gauss(0.3e-3),
                dy: wave(1.1) + moved[1] + rng.gauss(0.3e-3),
                dz: wave(0.9) + moved[2] + rng.gauss(0.3e-3),
                ..Errors6::ZERO
            };
            if let Some(found) = w.push(stamp_us(i as i64), pos + rng.gauss(1e-3), &e) {
                out.push((i, found));
            }
        }
        out
    }

    #[test]
    fn a_knock_is_found_at_its_frame_with_its_turn_at_rest_and_moving() {
        // At the near end's frame noise (1.4 µrad), the smallest knock found every time is
        // 2 µrad at rest, 3 µrad creeping (the slope fitted costs half the resolution).
        for (seed, speed) in [(1, 0.0), (2, 2.0), (3, 0.0), (4, 2.0)] {
            let smallest = if speed == 0.0 { 2e-6 } else { 3e-6 };
            for (yaw, pitch) in [
                (smallest, 0.0),
                (-10e-6, 0.0),
                (0.0, -smallest),
                (-4e-6, 5e-6),
            ] {
                let got = watch(seed, speed, 2000, Some((1000, yaw, pitch)));
                assert_eq!(got.len(), 1, "seed {seed} at {speed} mm/s: {got:?}");
                let (i, k) = got[0];
                // The step's frame, to within a few frames (the smallest knock's peak is broad).
                assert!(
                    (k.unix_us - 1000).abs() <= 24,
                    "frame {} at {speed} mm/s",
                    k.unix_us
                );
                // Reported within a window of the step.
                assert!((1000..=1000 + 160 + 80).contains(&i), "at frame {i}");
                for (est, truth, sd) in [
                    (k.turn.yaw, yaw, k.sd_rad[0]),
                    (k.turn.pitch, pitch, k.sd_rad[1]),
                ] {
                    assert!(sd > 0.05e-6 && sd < 0.5e-6, "sd {sd}");
                    assert!(
                        (est - truth).abs() < 4.0 * sd,
                        "at {speed} mm/s: {est:e} for {truth:e} (sd {sd:e})"
                    );
                }
            }
        }
    }

    #[test]
    fn a_knock_s_steps_in_the_straightnesses_and_dy_are_read_with_its_turn() {
        // A 10 µrad yaw about a pivot 15 mm off: dx steps by the turn's lever (here stated
        // as read), dy by 0.15 µm, dz not; at rest and creeping, each within 4 of its sd.
        for (seed, speed) in [(21, 0.0), (22, 2.0), (23, 0.0)] {
            let shift = [-2.1e-3, 0.15e-3, 0.0];
            let got = watch_shifted(seed, speed, 2000, Some((1000, 10e-6, 0.0)), shift);
            assert_eq!(got.len(), 1, "seed {seed} at {speed} mm/s: {got:?}");
            let step = got[0]
                .1
                .step
                .expect("a knock in the frames reads its steps");
            for ((got, sd), want) in step.mm.iter().zip(step.sd_mm).zip(shift) {
                // 0.3 µm a frame over 160 frames a side: 0.034 µm at rest.
                assert!(sd > 0.01e-3 && sd < 0.1e-3, "sd {:?}", step.sd_mm);
                assert!(
                    (got - want).abs() < 4.0 * sd,
                    "seed {seed} at {speed} mm/s: step {got:e} for {want:e} (sd {sd:e})"
                );
            }
        }
    }

    #[test]
    fn no_knock_in_noise_and_a_waving_axis_and_none_below_the_limits() {
        // 60 s of frames at rest, creeping, at the feed and fast (not tested): nothing.
        for (seed, speed) in [(11, 0.0), (12, 2.0), (13, 33.0), (15, 200.0)] {
            let got = watch(seed, speed, 30_000, None);
            assert!(got.is_empty(), "seed {seed} at {speed} mm/s: {got:?}");
        }
        // A turn well inside the noise of a window is not reported.
        let got = watch(14, 0.0, 3000, Some((1500, 0.2e-6, 0.0)));
        assert!(got.is_empty(), "{got:?}");
        // Nor an overrun and the return: 2 mm out and back at 20 mm/s, the axis' angles
        // 1.5 µrad apart with the direction of travel.
        let mut w = KnockWatch::new(KnockSettings::default());
        let mut rng = Rng::new(17);
        for i in 0..3000usize {
            let s = i as f64 / 500.0;
            let (pos, back) = match s {
                s if s < 2.0 => (0.0, false),
                s if s < 2.1 => (20.0 * (s - 2.0), false),
                s if s < 2.2 => (2.0 - 20.0 * (s - 2.1), true),
                _ => (0.0, true),
            };
            let e = Errors6 {
                ez: if back { 1.5e-6 } else { 0.0 } + rng.gauss(1.4e-6),
                ex: rng.gauss(1.4e-6),
                ..Errors6::ZERO
            };
            assert!(w.push(stamp_us(i as i64), pos, &e).is_none(), "at {s} s");
        }
        // Nor a knock in a move at the feed (the axis' own waves would pass for knocks).
        let got = watch(16, 50.0, 3000, Some((1500, 10e-6, 0.0)));
        assert!(got.is_empty(), "{got:?}");
    }

    #[test]
    fn a_reset_forgets_and_bad_numbers_are_skipped() {
        let mut w = KnockWatch::new(KnockSettings::default());
        let e = Errors6::ZERO;
        for i in 0..100 {
            assert!(w.push(stamp_us(i), 0.0, &e).is_none());
        }
        w.reset();
        assert!(w.window.is_empty());
        let nan = Errors6 {
            ez: f64::NAN,
            ..Errors6::ZERO
        };
        assert!(w.push(stamp_us(0), 0.0, &nan).is_none());
        assert!(w.push(stamp_us(0), f64::INFINITY, &e).is_none());
        assert!(w.window.is_empty());
    }
}
