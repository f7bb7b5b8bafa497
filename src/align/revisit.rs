//! A knock in a move, found where the carriage comes back to the zero (issue 24).
//!
//! [`KnockWatch`](super::KnockWatch) finds a knock in frames where the carriage stands or goes
//! one way over a short span; in a move the axis' own angular waviness hides it. A return to
//! the zero reference's position, from the side the zero was approached from, is a check no
//! move can hide: there the head reads the pitch and yaw it read at the zero (relative to the
//! zero: none), within the noise of the mean and the axis' angular repeatability. A mean
//! beyond that is a turn of the head since the last return that agreed, and is reported as a
//! knock at that return's time, so that everything measured since is taken again, with the
//! turn taken out.
//!
//! Sans-I/O: the caller gives each frame's time, measured position and its pitch and yaw
//! relative to the zero, and says when the zero is taken or forgotten.

use super::knock::Knock;
use super::mount::Mount;
use crate::util::clock::{FrameTime, Stamp};

/// How the check decides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RevisitSettings {
    /// The carriage is back at the zero within this (mm).
    pub tolerance_mm: f64,
    /// Further than this from the zero (mm), the carriage was away, on one side.
    pub away_mm: f64,
    /// Frames skipped after arriving (the carriage settling), then frames averaged.
    pub settle: usize,
    pub frames: usize,
    /// Significance a turn needs (standard deviations of the mean and the zero together).
    pub z: f64,
    /// The smallest turn reported (rad): an axis' angular repeatability at one place.
    pub min_rad: f64,
}

impl Default for RevisitSettings {
    /// 0.2 s to settle and 0.5 s averaged at 500 Hz (inside a capture's dwell); 0.5 µrad, 0.1″,
    /// as the knock watch's smallest (`KnockSettings`): a turn under it moves a straightness by
    /// at most 0.5 µm per metre from the pivot, while one of 1 µrad missed by the watch and
    /// passed here put a storm's pass 1.4 µm off in dx at 900 mm (twin seed 24). A machine
    /// axis whose yaw or pitch repeats worse than that at one place has its captures retaken
    /// after such a return, which costs a pass, never a wrong capture.
    fn default() -> Self {
        RevisitSettings {
            tolerance_mm: 0.05,
            away_mm: 1.0,
            settle: 100,
            frames: 250,
            z: 5.5,
            min_rad: 0.5e-6,
        }
    }
}

/// The zero's place: its measured position, and the side the carriage came from (-1 below,
/// +1 above; `None` until a return tells it).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Place {
    position: f64,
    side: Option<i8>,
}

/// What a restarted service needs to go on checking returns to the zero it had: where the
/// zero is, the side it is approached from (when known) and when the head last agreed with it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RevisitState {
    pub position_mm: f64,
    pub side: Option<i8>,
    pub agreed_us: i64,
}

/// A return that agreed with the zero: what the head read there against the zero, averaged
/// over the stay so far. The turns found before it are known from then on to within this
/// (`service::measure` bounds their variance by it).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Agreement {
    /// When the head agreed (µs): one agreement a stay.
    pub unix_us: i64,
    /// The mean pitch and yaw (rad) and the straightnesses dx and dz (mm) against the zero's.
    pub mean: [f64; READ],
    /// The mean's standard uncertainty: the frames' and the zero's own.
    pub sd: [f64; READ],
}

impl Agreement {
    /// What it read, in words: "pitch +0.12 ± 0.05 µrad, yaw …, dx +0.03 ± 0.02 µm, dz …".
    pub fn words(&self) -> String {
        let name = ["pitch", "yaw", "dx", "dz"];
        let (unit, scale) = (["µrad", "µrad", "µm", "µm"], [1e6, 1e6, 1e3, 1e3]);
        (0..READ)
            .map(|k| {
                format!(
                    "{} {:+.2} ± {:.2} {}",
                    name[k],
                    self.mean[k] * scale[k],
                    self.sd[k] * scale[k],
                    unit[k]
                )
            })
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// What a return reads against the zero: pitch, yaw (rad), dx, dz (mm).
pub const READ: usize = 4;

/// The check of each return to the zero.
#[derive(Clone, Debug)]
pub struct Revisit {
    settings: RevisitSettings,
    zero: Option<Place>,
    /// The side of the zero the carriage was last away on.
    side: Option<i8>,
    /// The newest frame's stamp, and when the head last agreed with the zero (the wall clock
    /// in µs to keep and say, and in the order frames were read).
    last: Option<Stamp>,
    agreed_us: i64,
    agreed_at: FrameTime,
    /// Frames at the zero since arriving, and the sums of pitch and yaw (and squares) averaged.
    seen: usize,
    sum: [f64; READ],
    sum_sq: [f64; READ],
    n: usize,
    /// This stay at the zero is judged.
    judged: bool,
    /// This stay agreed: its frames go on refining what it read.
    agreement: Option<Agreement>,
}

impl Revisit {
    pub fn new(settings: RevisitSettings) -> Self {
        Revisit {
            settings,
            zero: None,
            side: None,
            last: None,
            agreed_us: 0,
            agreed_at: FrameTime::Kept(0),
            seen: 0,
            sum: [0.0; READ],
            sum_sq: [0.0; READ],
            n: 0,
            judged: false,
            agreement: None,
        }
    }

    /// The zero is taken at `position` (mm) with the newest frame: the head agrees with it
    /// there and then. The carriage stands at it: this stay is not judged.
    pub fn set_zero(&mut self, position: f64) {
        self.zero = Some(Place {
            position,
            side: self.side,
        });
        (self.agreed_us, self.agreed_at) = match self.last {
            Some(s) => (s.unix_us, s.order()),
            None => (0, FrameTime::Kept(0)),
        };
        self.restart();
        self.judged = true;
    }

    /// The zero checked against, when there is one.
    pub fn state(&self) -> Option<RevisitState> {
        self.zero.map(|z| RevisitState {
            position_mm: z.position,
            side: z.side,
            agreed_us: self.agreed_us,
        })
    }

    /// Go on checking against a zero kept across a restart: where the carriage is now is not
    /// known, so the first stay at the zero that follows a stay away is judged, and a turn
    /// found there is dated at the last agreement before the restart.
    pub fn restore(&mut self, state: RevisitState) {
        self.zero = Some(Place {
            position: state.position_mm,
            side: state.side,
        });
        self.side = None;
        self.agreed_us = state.agreed_us;
        self.agreed_at = FrameTime::Kept(state.agreed_us);
        self.restart();
        self.judged = false;
    }

    /// When the head last agreed with the zero (µs).
    pub fn agreed_us(&self) -> i64 {
        self.agreed_us
    }

    /// The agreement of the stay at the zero going on, when it agreed: refined with every
    /// frame while the carriage stays.
    pub fn agreement(&self) -> Option<Agreement> {
        self.agreement
    }

    /// No zero (forgotten, or another decoupling): nothing to check against.
    pub fn forget(&mut self) {
        self.zero = None;
        self.restart();
    }

    /// The frames averaged so far do not count (the head's turn changed under them).
    pub fn restart(&mut self) {
        self.seen = 0;
        self.sum = [0.0; READ];
        self.sum_sq = [0.0; READ];
        self.n = 0;
        self.agreement = None;
    }

    /// The mean of the frames averaged, and its standard uncertainty with the zero's own
    /// `zero_sd`.
    fn mean_and_sd(&self, zero_sd: [f64; READ]) -> ([f64; READ], [f64; READ]) {
        let n = self.n as f64;
        let mean: [f64; READ] = std::array::from_fn(|k| self.sum[k] / n);
        let sd: [f64; READ] = std::array::from_fn(|k| {
            let var_frame = ((self.sum_sq[k] - n * mean[k] * mean[k]) / (n - 1.0)).max(0.0);
            (var_frame / n + zero_sd[k] * zero_sd[k]).sqrt()
        });
        (mean, sd)
    }

    /// One frame read at `stamp`: the measured position (mm), what the head reads relative
    /// to the zero (pitch and yaw in rad, dx and dz in mm: the angles judge a turn, all four
    /// are what an agreement read), and the zero's own standard uncertainty of each. A turn
    /// found: the knock, at the time the head last agreed with the zero.
    pub fn push(
        &mut self,
        stamp: Stamp,
        position: f64,
        read: [f64; READ],
        zero_sd: [f64; READ],
    ) -> Option<Knock> {
        if !(position.is_finite() && read.iter().all(|a| a.is_finite())) {
            return None;
        }
        self.last = Some(stamp);
        let unix_us = stamp.unix_us;
        let s = self.settings;
        let place = self.zero.as_mut()?;
        let d = position - place.position;
        if d.abs() > s.away_mm {
            self.side = Some(if d > 0.0 { 1 } else { -1 });
            self.judged = false;
            self.restart();
            return None;
        }
        if d.abs() > s.tolerance_mm {
            self.restart();
            return None;
        }
        if self.judged && self.agreement.is_none() || self.side.is_none() {
            return None;
        }
        // The zero's side is the first return's when the zero's own approach is not known.
        if place.side.is_none() {
            place.side = self.side;
        }
        if place.side != self.side {
            if self.seen == 0 {
                tracing::debug!(position, "back at the zero from the other side: not judged");
                self.seen = 1;
            }
            return None;
        }
        self.seen += 1;
        if self.seen <= s.settle {
            return None;
        }
        for (k, a) in read.iter().enumerate() {
            self.sum[k] += a;
            self.sum_sq[k] += a * a;
        }
        self.n += 1;
        if self.n < s.frames {
            return None;
        }
        let (mean, sd) = self.mean_and_sd(zero_sd);
        if let Some(a) = self.agreement.as_mut() {
            a.mean = mean;
            a.sd = sd;
            return None;
        }
        self.judged = true;
        let z = (0..2)
            .map(|k| mean[k].abs() / sd[k].max(f64::MIN_POSITIVE))
            .fold(0.0, f64::max);
        let turned = (0..2).any(|k| mean[k].abs() > (s.z * sd[k]).max(s.min_rad));
        tracing::debug!(
            pitch_urad = mean[0] * 1e6,
            yaw_urad = mean[1] * 1e6,
            sd_urad = sd[1] * 1e6,
            turned,
            "back at the zero: pitch and yaw against the zero's"
        );
        let since_us = std::mem::replace(&mut self.agreed_us, unix_us);
        let since = std::mem::replace(&mut self.agreed_at, stamp.order());
        if !turned {
            self.agreement = Some(Agreement { unix_us, mean, sd });
        }
        turned.then_some(Knock {
            unix_us: since_us,
            since,
            turn: Mount {
                yaw: -mean[1],
                pitch: -mean[0],
                ..Mount::default()
            },
            sd_rad: [sd[1], sd[0]],
            z,
            step: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Rng;
    use crate::util::clock::stamp_us;

    /// Frames every 2 ms from `t0` (µs) at `position` with pitch and yaw `angles` plus 1.4 µrad
    /// of noise each: the knock found, if any.
    fn stay(
        r: &mut Revisit,
        rng: &mut Rng,
        t0: i64,
        position: f64,
        angles: [f64; 2],
        frames: usize,
    ) -> Option<Knock> {
        let mut found = None;
        for i in 0..frames {
            let a = [
                angles[0] + rng.gauss(1.4e-6),
                angles[1] + rng.gauss(1.4e-6),
                rng.gauss(0.5e-3),
                rng.gauss(0.5e-3),
            ];
            if let Some(k) = r.push(stamp_us(t0 + 2000 * i as i64), position, a, [0.05e-6; READ]) {
                assert!(found.is_none(), "one knock a stay");
                found = Some(k);
            }
        }
        found
    }

    #[test]
    fn a_turn_since_the_last_return_is_found_at_the_next_return_from_the_zero_s_side() {
        let mut rng = Rng::new(5);
        let mut r = Revisit::new(RevisitSettings::default());
        // Came from below, zero at 0 mm at t = 1 s.
        assert!(stay(&mut r, &mut rng, 0, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 1_000_000, 0.0, [0.0; 2], 10).is_none());
        r.set_zero(0.0);
        // Away above and back from below, unturned: agrees (at the stay's last frame).
        assert!(stay(&mut r, &mut rng, 2_000_000, 300.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 3_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 4_000_000, 0.01, [0.0; 2], 500).is_none());
        let agreed = 4_000_000 + 2000 * 349;
        // Knocked away (the head now reads yaw +3 µrad, pitch -2 µrad more); back from above
        // first: another side, not judged.
        let turned = [-2.0e-6, 3.0e-6];
        assert!(stay(&mut r, &mut rng, 5_000_000, 500.0, turned, 10).is_none());
        assert!(stay(&mut r, &mut rng, 6_000_000, 0.0, turned, 500).is_none());
        // From below: found, dated at the last agreement, the turn that undoes it.
        assert!(stay(&mut r, &mut rng, 7_000_000, -2.0, turned, 10).is_none());
        let k = stay(&mut r, &mut rng, 8_000_000, 0.0, turned, 500).expect("the turn found");
        assert_eq!(k.unix_us, agreed);
        assert_eq!(k.since, stamp_us(agreed).order());
        assert!((k.turn.yaw + 3.0e-6).abs() < 0.5e-6, "yaw {:e}", k.turn.yaw);
        assert!(
            (k.turn.pitch - 2.0e-6).abs() < 0.5e-6,
            "pitch {:e}",
            k.turn.pitch
        );
        assert!(
            k.sd_rad[0] < 0.15e-6 && k.sd_rad[0] > 0.05e-6,
            "{:?}",
            k.sd_rad
        );
        // A turn below the axis' repeatability is no knock; nor is anything without a zero.
        assert!(stay(&mut r, &mut rng, 9_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 9_100_000, 0.0, [0.0, 0.35e-6], 500).is_none());
        r.forget();
        assert!(stay(&mut r, &mut rng, 10_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 11_000_000, 0.0, turned, 500).is_none());
    }

    #[test]
    fn a_zero_kept_across_a_restart_is_checked_at_the_first_return_and_a_turn_dated_before_it() {
        let mut rng = Rng::new(7);
        let mut r = Revisit::new(RevisitSettings::default());
        assert!(stay(&mut r, &mut rng, 0, -2.0, [0.0; 2], 10).is_none());
        r.set_zero(0.0);
        assert!(stay(&mut r, &mut rng, 1_000_000, 400.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 2_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 3_000_000, 0.0, [0.0; 2], 500).is_none());
        let kept = r.state().expect("a zero");
        assert_eq!(kept.side, Some(-1));
        assert_eq!(kept.agreed_us, 3_000_000 + 2000 * 349);
        // The service restarts; the head was knocked while nobody watched. Where the carriage
        // stands when the frames come back is not a return: not judged.
        let mut back = Revisit::new(RevisitSettings::default());
        back.restore(kept);
        assert_eq!(back.state(), Some(kept));
        let turned = [0.0, 4.0e-6];
        assert!(stay(&mut back, &mut rng, 9_000_000, 0.0, turned, 500).is_none());
        // The first return from the zero's side is: found, dated at the agreement before.
        assert!(stay(&mut back, &mut rng, 10_000_000, -2.0, turned, 10).is_none());
        let k = stay(&mut back, &mut rng, 11_000_000, 0.0, turned, 500).expect("found");
        assert_eq!(k.unix_us, kept.agreed_us);
        // Before every frame of the new process, whatever its wall clock says.
        assert_eq!(k.since, FrameTime::Kept(kept.agreed_us));
        assert!((k.turn.yaw + 4.0e-6).abs() < 0.5e-6, "yaw {:e}", k.turn.yaw);
        // Unturned, it agrees at that return instead, and the agreement moves on.
        let mut calm = Revisit::new(RevisitSettings::default());
        calm.restore(kept);
        assert!(stay(&mut calm, &mut rng, 10_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut calm, &mut rng, 11_000_000, 0.0, [0.0; 2], 500).is_none());
        assert_eq!(calm.agreed_us(), 11_000_000 + 2000 * 349);
    }

    #[test]
    fn an_agreeing_stay_reports_what_it_read_refined_until_the_carriage_leaves() {
        let mut rng = Rng::new(8);
        let mut r = Revisit::new(RevisitSettings::default());
        assert!(stay(&mut r, &mut rng, 0, -2.0, [0.0; 2], 10).is_none());
        r.set_zero(0.0);
        assert!(
            r.agreement().is_none(),
            "the zero's own stay is no agreement"
        );
        assert!(stay(&mut r, &mut rng, 1_000_000, 300.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 2_000_000, -2.0, [0.0; 2], 10).is_none());
        // 0.4 µrad of pitch left over, under what a return calls a turn.
        let left = [0.4e-6, 0.0];
        assert!(stay(&mut r, &mut rng, 3_000_000, 0.0, left, 349).is_none());
        assert!(r.agreement().is_none(), "not judged yet");
        assert!(stay(&mut r, &mut rng, 3_698_000, 0.0, left, 1).is_none());
        let first = r.agreement().expect("agreed");
        assert_eq!(first.unix_us, 3_698_000);
        assert!(stay(&mut r, &mut rng, 3_700_000, 0.0, left, 650).is_none());
        let last = r.agreement().expect("still agreed");
        assert_eq!(last.unix_us, first.unix_us, "one agreement a stay");
        // 250 frames, then 900: the frames' part of the sd falls by √(900/250).
        let frames = |a: Agreement| (a.sd[0].powi(2) - 0.05e-6f64.powi(2)).sqrt();
        let ratio = frames(first) / frames(last);
        assert!((ratio - 1.9).abs() < 0.25, "sd {first:?} then {last:?}");
        // 1.4 µrad a frame over 900 frames: the mean within 3 of its 0.05 µrad.
        assert!(
            (last.mean[0] - left[0]).abs() < 3.0 * last.sd[0],
            "{last:?}"
        );
        // The straightnesses read 0.5 µm a frame: their mean over 900 frames to 0.017 µm.
        assert!(
            last.mean[2].abs() < 3.0 * last.sd[2] && last.sd[2] < 0.02e-3,
            "{last:?}"
        );
        // Away: gone; the next stay agrees anew.
        assert!(stay(&mut r, &mut rng, 5_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(r.agreement().is_none());
        assert!(stay(&mut r, &mut rng, 6_000_000, 0.0, [0.0; 2], 400).is_none());
        let next = r.agreement().expect("the next stay agreed");
        assert!(next.unix_us > last.unix_us);
    }

    #[test]
    fn a_stay_too_short_or_off_the_zero_is_not_judged() {
        let mut rng = Rng::new(6);
        let mut r = Revisit::new(RevisitSettings::default());
        r.set_zero(0.0);
        let turned = [0.0, 5.0e-6];
        assert!(stay(&mut r, &mut rng, 0, -3.0, turned, 10).is_none());
        // 0.6 s: settling and averaging need 0.7 s.
        assert!(stay(&mut r, &mut rng, 1_000_000, 0.0, turned, 300).is_none());
        // 0.1 mm off the zero.
        assert!(stay(&mut r, &mut rng, 2_000_000, 0.1, turned, 500).is_none());
        // Away and back for long enough: found.
        assert!(stay(&mut r, &mut rng, 3_000_000, -3.0, turned, 10).is_none());
        assert!(stay(&mut r, &mut rng, 4_000_000, 0.0, turned, 400).is_some());
    }
}
