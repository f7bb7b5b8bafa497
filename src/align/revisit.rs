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
//! A return that agrees measures what is left of the turns taken out since the zero: the
//! mean's square plus its variance, for pitch and yaw and for the two straightnesses at the
//! zero ([`Revisit::take_agreement`]). That is the turns' uncertainty from then on, in place
//! of the model's, which a knock's fit alone can state only loosely.
//!
//! Sans-I/O: the caller gives each frame's time, measured position and its pitch, yaw, dx
//! and dz relative to the zero, and says when the zero is taken or forgotten.

use super::knock::Knock;
use super::mount::Mount;

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
    /// Significance a turn needs (standard deviations of the mean and the zero together)
    /// whatever was stated.
    pub z: f64,
    /// A turn beyond this many of what the captures since the last agreement stated for the
    /// turns (with the mean's own sd) is one: they were stated wrong, and are taken again.
    pub k_stated: f64,
    /// The smallest turn reported (rad): what an axis repeats its pitch and yaw to at one
    /// place, approached from one side.
    pub min_rad: f64,
    /// The smallest shift across reported (mm): what it repeats its straightnesses to there.
    pub min_mm: f64,
}

impl Default for RevisitSettings {
    /// 0.2 s to settle and 0.5 s averaged at 500 Hz (inside a capture's dwell). 0.3 µrad,
    /// 0.06″: a good axis' pitch and yaw at one place, approached from one side (the twin's
    /// returns without a knock agree within 0.15 µrad); a turn of 1 µrad, which a fixed
    /// threshold there let pass, moves a straightness by 1.4 µm at a metre from the pivot
    /// (storm seed 15: five passes 1.5 µm apart in dx).
    fn default() -> Self {
        RevisitSettings {
            tolerance_mm: 0.05,
            away_mm: 1.0,
            settle: 100,
            frames: 250,
            z: 5.5,
            k_stated: 2.0,
            min_rad: 0.3e-6,
            min_mm: 0.3e-3,
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

/// The check of each return to the zero.
#[derive(Clone, Debug)]
pub struct Revisit {
    settings: RevisitSettings,
    zero: Option<Place>,
    /// The side of the zero the carriage was last away on.
    side: Option<i8>,
    /// The newest frame's time, and the time the head last agreed with the zero (µs).
    last_us: i64,
    agreed_us: i64,
    /// Frames at the zero since arriving, and the sums of pitch, yaw, dx and dz (and their
    /// squares) averaged.
    seen: usize,
    sum: [f64; REVISIT_CHANNELS],
    sum_sq: [f64; REVISIT_CHANNELS],
    n: usize,
    /// This stay at the zero is judged.
    judged: bool,
    /// The newest return that agreed, not yet taken.
    agreement: Option<Agreement>,
}

/// Pitch, yaw (rad), dx and dz (mm), relative to the zero: what a return averages.
pub const REVISIT_CHANNELS: usize = 4;

/// A return to the zero that agreed with it: per channel (pitch, yaw, dx, dz), the mean's
/// square plus its variance (the frames' over their number and the zero's own): how far the
/// head may be from the zero's reading there, turns taken out (rad², mm²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Agreement {
    pub second_moment: [f64; REVISIT_CHANNELS],
}

impl Revisit {
    pub fn new(settings: RevisitSettings) -> Self {
        Revisit {
            settings,
            zero: None,
            side: None,
            last_us: 0,
            agreed_us: 0,
            seen: 0,
            sum: [0.0; REVISIT_CHANNELS],
            sum_sq: [0.0; REVISIT_CHANNELS],
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
        self.agreed_us = self.last_us;
        self.agreement = None;
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
        self.restart();
        self.judged = false;
    }

    /// When the head last agreed with the zero (µs).
    pub fn agreed_us(&self) -> i64 {
        self.agreed_us
    }

    /// No zero (forgotten, or another decoupling): nothing to check against.
    pub fn forget(&mut self) {
        self.zero = None;
        self.agreement = None;
        self.restart();
    }

    /// The frames averaged so far do not count (the head's turn changed under them).
    pub fn restart(&mut self) {
        self.seen = 0;
        self.sum = [0.0; REVISIT_CHANNELS];
        self.sum_sq = [0.0; REVISIT_CHANNELS];
        self.n = 0;
    }

    /// The newest return that agreed with the zero since last asked.
    pub fn take_agreement(&mut self) -> Option<Agreement> {
        self.agreement.take()
    }

    /// One frame at `unix_us`: the measured position (mm), pitch, yaw (rad), dx and dz (mm)
    /// relative to the zero, the zero's own standard uncertainty of each, and the standard
    /// uncertainty of each the turns found are stated with now. A turn found (beyond the
    /// mean's noise, or beyond what was stated): the knock, at the time the head last agreed
    /// with the zero. Pitch and yaw that agree, dx or dz that do not: the head shifted across
    /// (a reference moved by a translation, as the run's judge shifts the zero for a turn it
    /// cannot tell from one), a knock of x and z. A return that agrees in all four leaves its
    /// [`Agreement`].
    pub fn push(
        &mut self,
        unix_us: i64,
        position: f64,
        rel: [f64; REVISIT_CHANNELS],
        zero_sd: [f64; REVISIT_CHANNELS],
        stated_sd: [f64; REVISIT_CHANNELS],
    ) -> Option<Knock> {
        if !(position.is_finite() && rel.iter().all(|a| a.is_finite())) {
            return None;
        }
        self.last_us = unix_us;
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
        if self.judged || self.side.is_none() {
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
        for (k, a) in rel.iter().enumerate() {
            self.sum[k] += a;
            self.sum_sq[k] += a * a;
        }
        self.n += 1;
        if self.n < s.frames {
            return None;
        }
        self.judged = true;
        let n = self.n as f64;
        let mean: [f64; REVISIT_CHANNELS] = std::array::from_fn(|k| self.sum[k] / n);
        let sd: [f64; REVISIT_CHANNELS] = std::array::from_fn(|k| {
            let var_frame = ((self.sum_sq[k] - n * mean[k] * mean[k]) / (n - 1.0)).max(0.0);
            (var_frame / n + zero_sd[k] * zero_sd[k]).sqrt()
        });
        let z = (0..REVISIT_CHANNELS)
            .map(|k| mean[k].abs() / sd[k].max(f64::MIN_POSITIVE))
            .fold(0.0, f64::max);
        let off = |k: usize, min: f64| {
            let stated = s.k_stated * stated_sd[k].hypot(sd[k]);
            mean[k].abs() > (s.z * sd[k]).min(stated).max(min)
        };
        let turned = (0..2).any(|k| off(k, s.min_rad));
        let shifted = !turned && (2..4).any(|k| off(k, s.min_mm));
        tracing::debug!(
            pitch_urad = mean[0] * 1e6,
            yaw_urad = mean[1] * 1e6,
            sd_urad = sd[1] * 1e6,
            dx_um = mean[2] * 1e3,
            dz_um = mean[3] * 1e3,
            turned,
            shifted,
            "back at the zero: pitch and yaw against the zero's"
        );
        let since = std::mem::replace(&mut self.agreed_us, unix_us);
        if shifted {
            return Some(Knock {
                unix_us: since,
                turn: Mount {
                    x: -mean[2],
                    z: -mean[3],
                    ..Mount::default()
                },
                sd_rad: [0.0; 2],
                sd_mm: [sd[2], sd[3]],
                z,
            });
        }
        if !turned {
            self.agreement = Some(Agreement {
                second_moment: std::array::from_fn(|k| mean[k] * mean[k] + sd[k] * sd[k]),
            });
        }
        turned.then_some(Knock {
            unix_us: since,
            turn: Mount {
                yaw: -mean[1],
                pitch: -mean[0],
                ..Mount::default()
            },
            sd_rad: [sd[1], sd[0]],
            sd_mm: [0.0; 2],
            z,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Rng;

    /// Frames every 2 ms from `t0` (µs) at `position` with pitch and yaw `angles` plus 1.4 µrad
    /// of noise each (dx and dz: 0.5 µm of noise about none): the knock found, if any.
    fn stay(
        r: &mut Revisit,
        rng: &mut Rng,
        t0: i64,
        position: f64,
        angles: [f64; 2],
        frames: usize,
    ) -> Option<Knock> {
        let rel = [angles[0], angles[1], 0.0, 0.0];
        stay_at(r, rng, t0, position, rel, [0.0; REVISIT_CHANNELS], frames)
    }

    /// As `stay`, with dx and dz (mm) about `rel`'s too, and the turns stated to `stated`.
    fn stay_at(
        r: &mut Revisit,
        rng: &mut Rng,
        t0: i64,
        position: f64,
        rel: [f64; REVISIT_CHANNELS],
        stated: [f64; REVISIT_CHANNELS],
        frames: usize,
    ) -> Option<Knock> {
        let zero_sd = std::array::from_fn(zero_sd_of);
        let mut found = None;
        for i in 0..frames {
            let a: [f64; REVISIT_CHANNELS] =
                std::array::from_fn(|k| rel[k] + rng.gauss(noise_of(k)));
            if let Some(k) = r.push(t0 + 2000 * i as i64, position, a, zero_sd, stated) {
                assert!(found.is_none(), "one knock a stay");
                found = Some(k);
            }
        }
        found
    }

    /// A return that agrees states what is left: the residual's square plus the variance of
    /// its mean (250 frames of 1.4 µrad and 0.5 µm, and the zero's own), per channel.
    #[test]
    fn a_return_that_agrees_measures_what_is_left_of_the_turns() {
        let mut rng = Rng::new(11);
        let mut r = Revisit::new(RevisitSettings::default());
        assert!(stay(&mut r, &mut rng, 0, -2.0, [0.0; 2], 10).is_none());
        r.set_zero(0.0);
        assert!(r.take_agreement().is_none());
        assert!(stay(&mut r, &mut rng, 1_000_000, 400.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 2_000_000, -2.0, [0.0; 2], 10).is_none());
        // Left over: pitch 0.25 µrad and dx 0.2 µm, within what was stated (0.3 µrad, 0.2 µm).
        let rel = [0.25e-6, 0.0, 0.2e-3, 0.0];
        let stated = [0.3e-6, 0.3e-6, 0.2e-3, 0.2e-3];
        assert!(stay_at(&mut r, &mut rng, 3_000_000, 0.0, rel, stated, 500).is_none());
        let a = r.take_agreement().expect("the return agreed");
        assert!(r.take_agreement().is_none(), "taken once");
        let mean_var = |k: usize| (noise_of(k) / 250f64.sqrt()).powi(2) + zero_sd_of(k).powi(2);
        for (k, want) in rel.iter().enumerate() {
            let expect = want * want + mean_var(k);
            // The mean scatters by its sd: the second moment within 3 sd of the mean's square.
            let slack = 2.0 * want.abs() * 3.0 * mean_var(k).sqrt() + 9.0 * mean_var(k);
            assert!(
                (a.second_moment[k] - expect).abs() < slack,
                "channel {k}: {:e} against {expect:e}",
                a.second_moment[k]
            );
        }
        // A return that finds a turn leaves none; nor does a forgotten zero.
        assert!(stay(&mut r, &mut rng, 4_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 5_000_000, 0.0, [0.0, 3.0e-6], 500).is_some());
        assert!(r.take_agreement().is_none());
        assert!(stay(&mut r, &mut rng, 6_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 7_000_000, 0.0, [0.0; 2], 500).is_none());
        r.forget();
        assert!(r.take_agreement().is_none());
    }

    /// Pitch and yaw agree, dx does not (the run's judge shifted the zero for a turn it could
    /// not tell from a shift): a knock of x, dated at the last agreement, that the shift's
    /// undoing takes out; below a straightness' repeatability, none.
    #[test]
    fn a_return_that_reads_the_zero_shifted_across_finds_the_shift() {
        let mut rng = Rng::new(12);
        let mut r = Revisit::new(RevisitSettings::default());
        assert!(stay(&mut r, &mut rng, 0, -2.0, [0.0; 2], 10).is_none());
        r.set_zero(0.0);
        assert!(stay(&mut r, &mut rng, 1_000_000, 400.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 2_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 3_000_000, 0.0, [0.0; 2], 500).is_none());
        let agreed = r.agreed_us();
        let shifted = [0.0, 0.0, -1.37e-3, 0.0];
        assert!(stay(&mut r, &mut rng, 4_000_000, 400.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut r, &mut rng, 5_000_000, -2.0, [0.0; 2], 10).is_none());
        let none = [0.0; REVISIT_CHANNELS];
        let k = stay_at(&mut r, &mut rng, 6_000_000, 0.0, shifted, none, 500).expect("found");
        assert_eq!(k.unix_us, agreed);
        assert_eq!((k.turn.yaw, k.turn.pitch), (0.0, 0.0));
        assert!(
            (k.turn.x - 1.37e-3).abs() < 4.0 * k.sd_mm[0],
            "{}",
            k.describe()
        );
        assert!(k.turn.z.abs() < 4.0 * k.sd_mm[1], "{}", k.describe());
        assert!(
            k.describe().starts_with("shifted x +1.3"),
            "{}",
            k.describe()
        );
        // Below what a straightness repeats to at one place (0.3 µm), none.
        let within = [0.0, 0.0, 0.2e-3, -0.2e-3];
        assert!(stay(&mut r, &mut rng, 7_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay_at(&mut r, &mut rng, 8_000_000, 0.0, within, none, 500).is_none());
        assert!(r.take_agreement().is_some());
    }

    fn noise_of(k: usize) -> f64 {
        [1.4e-6, 1.4e-6, 0.5e-3, 0.5e-3][k]
    }

    fn zero_sd_of(k: usize) -> f64 {
        [0.05e-6, 0.05e-6, 0.02e-3, 0.02e-3][k]
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
        // A turn within what the turns were stated to is no knock (0.6 µrad, stated 0.5 µrad:
        // 2 u is 1.0 µrad, though the mean's noise alone, 0.09 µrad, would call it one).
        let (small, stated) = ([0.0, 0.6e-6, 0.0, 0.0], [0.5e-6, 0.5e-6, 0.0, 0.0]);
        assert!(stay(&mut r, &mut rng, 9_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay_at(&mut r, &mut rng, 9_100_000, 0.0, small, stated, 500).is_none());
        // Beyond what was stated, it is one, small as it is: the captures since were stated
        // without it.
        assert!(stay(&mut r, &mut rng, 9_200_000, -2.0, [0.0; 2], 10).is_none());
        let stated = [0.1e-6, 0.1e-6, 0.0, 0.0];
        let found = stay_at(&mut r, &mut rng, 9_300_000, 0.0, small, stated, 500);
        assert!(found.is_some_and(|k| (k.turn.yaw + 0.6e-6).abs() < 0.4e-6));
        // Nor is anything a knock without a zero.
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
        assert!((k.turn.yaw + 4.0e-6).abs() < 0.5e-6, "yaw {:e}", k.turn.yaw);
        // Unturned, it agrees at that return instead, and the agreement moves on.
        let mut calm = Revisit::new(RevisitSettings::default());
        calm.restore(kept);
        assert!(stay(&mut calm, &mut rng, 10_000_000, -2.0, [0.0; 2], 10).is_none());
        assert!(stay(&mut calm, &mut rng, 11_000_000, 0.0, [0.0; 2], 500).is_none());
        assert_eq!(calm.agreed_us(), 11_000_000 + 2000 * 349);
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
