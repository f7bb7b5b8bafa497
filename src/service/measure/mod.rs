//! The live measurement: each valid frame, with PSD2's stitched position, is decoupled into the
//! six errors; the live value is the mean over a short window, with its covariance: the
//! per-frame noise covariance divided by the frames averaged, plus the stitching uncertainty
//! carried through β, plus the zero reference's own uncertainty when one is set.
//!
//! A zero reference averages every frame from when it was asked for (`start_zero`) to when
//! it is taken (`set_zero`), not only the live window: its noise is in every later reading.
//!
//! The nominal travel D comes from whoever knows it (the run plan, the CNC); without it D is
//! estimated as PSD2's position plus the spot's offset on it, which is good enough for β but
//! leaves positioning undefined (`LiveErrors::nominal` is `None`). Pure logic; time is an
//! argument.
//!
//! A knock that turns the head on its mount (`align::knock`) is found in the frames and taken
//! out of every later frame by the turn it gave (a constant angle and a straightness growing
//! with the distance from the mount's pivot), its uncertainty carried with the stitching's.
//! A knock in a move, which the frames alone cannot tell from the axis' own angles, is found
//! at the carriage's next return to the zero (`align::revisit`) and taken out the same way.
//! A new zero, or none, starts from the head as it stands.
//!
//! The zero, the turns found since and the place of the zero are the reference every reading
//! rests on: each change is offered for the store (`take_reference_change`), and a restarted
//! service takes them back (`restore_reference`) and checks them at the carriage's first
//! return to the zero, so that a service killed in a run does not go on without them.

use crate::acquire::Frame;
use crate::align::{Agreement, Knock, Mount, RevisitState};
use crate::decouple::{BetaCache, DecoupleError, Decoupler};
use crate::evaluate::recorded::{RecordedCalibration, Stated};
use crate::run::FrameSample;
use crate::track::{Stitch, StitchAnchor};
use crate::units::Errors6;
use nalgebra::{Matrix6, Vector6};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
pub use turned::Shifts;
use turned::Turned;

mod turned;

/// The live six errors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiveErrors {
    /// Mean over the window, minus the zero reference when set (internal units).
    pub errors: Errors6,
    /// Standard deviation of `errors` (internal units).
    pub sd: Errors6,
    /// Frames averaged.
    pub frames: usize,
    /// The travel D used for the decoupling (mm).
    pub travel_mm: f64,
    /// The nominal position, when known.
    pub nominal: Option<f64>,
    /// Measured carriage position: D + dy (mm).
    pub position_mm: f64,
    /// Whether a zero reference is subtracted.
    pub zeroed: bool,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Zero {
    errors: Vector6<f64>,
    cov: Matrix6<f64>,
    /// Where the stitch stood when the zero was taken.
    stitch: Option<StitchAnchor>,
}

/// The zero reference in force, as kept across a restart (internal units).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReferenceState {
    /// The zero's six errors, and their covariance (36 values, row by row).
    pub errors: [f64; 6],
    pub cov: Vec<f64>,
    /// The turns of the head found since the zero: yaw and pitch (rad), and their variance.
    pub turn_rad: [f64; 2],
    pub turn_var_rad2: [f64; 2],
    /// Where the zero is, for the check of each return to it.
    pub revisit: Option<RevisitState>,
    /// Where PSD2's stitch stood at the zero: a restarted service bridges from it by the
    /// follower's encoder (none in a row kept before it was recorded).
    #[serde(default)]
    pub stitch: Option<StitchAnchor>,
    /// What the last return to the zero that agreed read of the turns found before it, with
    /// `turn_var_rad2` the turns' variance since (none before one, or in a row kept before it
    /// was recorded).
    #[serde(default)]
    pub seen: Option<Agreement>,
    /// What the knocks moved the head by beyond their turns (none in a row kept before it was
    /// recorded: every turn's move is then taken as unread).
    #[serde(default)]
    pub shifts: Option<Shifts>,
}

impl ReferenceState {
    /// Refuse a state that cannot be a reference (a damaged or foreign row).
    fn check(&self) -> Result<(), String> {
        let numbers = self
            .errors
            .iter()
            .chain(&self.cov)
            .chain(&self.turn_rad)
            .chain(&self.turn_var_rad2);
        if self.cov.len() != 36 {
            return Err(format!(
                "its covariance has {} values, not 36",
                self.cov.len()
            ));
        }
        if numbers.clone().any(|v| !v.is_finite()) {
            return Err("it holds a value that is not a finite number".into());
        }
        if self.turn_var_rad2.iter().any(|v| *v < 0.0) {
            return Err("a turn's variance is negative".into());
        }
        if let Some(a) = &self.seen
            && (a.mean.iter().chain(&a.sd).any(|v| !v.is_finite()) || a.sd.iter().any(|v| *v < 0.0))
        {
            return Err("the last return's reading is not a finite mean and sd".into());
        }
        if let Some(m) = &self.shifts
            && (m.numbers().any(|v| !v.is_finite()) || m.var_mm2.iter().any(|v| *v < 0.0))
        {
            return Err("the knocks' moves are not finite numbers with a variance".into());
        }
        self.stitch.as_ref().map_or(Ok(()), StitchAnchor::check)
    }
}

/// A name of the decoupling `d` (its model, calibration, method and noise): a zero kept with
/// one name is not taken by a service that decouples with another.
pub fn decoupler_name(d: &Decoupler) -> String {
    // FNV-1a over the decoupler's full description: stable for equal decouplers.
    let text = format!("{d:?}");
    let hash = text.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    });
    format!("{hash:016x}")
}

#[derive(Clone, Copy, Debug)]
struct Sample {
    at: Instant,
    errors: Vector6<f64>,
    travel: f64,
    follower: f64,
    stitch_var: [f64; 2],
}

/// The frames averaged for a zero reference: their sum and count.
#[derive(Clone, Copy, Debug, Default)]
struct ZeroAverage {
    sum: Vector6<f64>,
    n: usize,
}

/// The live pipeline.
#[derive(Debug)]
pub struct Measure {
    decoupler: Decoupler,
    beta: BetaCache,
    window: Duration,
    samples: VecDeque<Sample>,
    frame_cov: Matrix6<f64>,
    nominal: Option<f64>,
    zero: Option<Zero>,
    /// The frames since a zero reference was asked for, while it is on its way.
    zero_average: Option<ZeroAverage>,
    /// The newest frame's readings (mm, PSD2 as read), travel and follower position: what a
    /// calibration waiting to be accepted is judged on.
    last_input: Option<(Vector6<f64>, f64, f64)>,
    turned: Turned,
    /// The reference changed since last taken for the store.
    reference_changed: bool,
    /// The calibration in use's own variance per error (internal units²): the term the run's
    /// budget states for it, in every frame's systematic variance.
    calibration_var: [f64; 6],
}

impl Measure {
    /// A pipeline averaging over `window`.
    pub fn new(decoupler: Decoupler, window: Duration) -> Self {
        Measure {
            decoupler,
            beta: BetaCache::default(),
            window,
            samples: VecDeque::new(),
            frame_cov: Matrix6::zeros(),
            nominal: None,
            zero: None,
            zero_average: None,
            last_input: None,
            turned: Turned::new(),
            reference_changed: false,
            calibration_var: [0.0; 6],
        }
    }

    /// The calibration in use's own standard uncertainty (its term in a run's budget,
    /// `CalibrationFile::budget_term`): every capture's u carries it from now on, as the
    /// report's budget does. Not stated (the nominal layout): none.
    pub fn set_calibration_u(&mut self, term: &Stated<RecordedCalibration>) {
        let u = term
            .value()
            .map_or(Errors6::ZERO, |c| Errors6::from_user(c.u_um_arcsec));
        self.calibration_var = u.to_array().map(|v| v * v);
    }

    /// The zero reference in force, as kept across a restart; `None` without a zero.
    pub fn reference_state(&self) -> Option<ReferenceState> {
        let z = self.zero?;
        Some(ReferenceState {
            errors: std::array::from_fn(|k| z.errors[k]),
            cov: z.cov.transpose().iter().copied().collect(),
            turn_rad: [self.turned.turn.yaw, self.turned.turn.pitch],
            turn_var_rad2: self.turned.var,
            seen: self.turned.seen,
            shifts: Some(self.turned.shifts),
            revisit: self.turned.revisit.state(),
            stitch: z.stitch,
        })
    }

    /// The reference when it changed since last asked: `Some(None)` when it was forgotten.
    pub fn take_reference_change(&mut self) -> Option<Option<ReferenceState>> {
        std::mem::take(&mut self.reference_changed).then(|| self.reference_state())
    }

    /// Take back a zero reference kept across a restart: readings are relative to it again,
    /// the turns found before are taken out, and the next return to the zero checks it.
    pub fn restore_reference(&mut self, state: &ReferenceState) -> Result<(), String> {
        state.check()?;
        let cov = Matrix6::from_row_slice(&state.cov);
        self.zero = Some(Zero {
            errors: Vector6::from_row_slice(&state.errors),
            cov,
            stitch: state.stitch,
        });
        self.zero_average = None;
        self.turned.reset();
        self.turned.turn = Mount {
            yaw: state.turn_rad[0],
            pitch: state.turn_rad[1],
            ..Mount::default()
        };
        self.turned.var = state.turn_var_rad2;
        self.turned.seen = state.seen;
        self.turned.shifts = state
            .shifts
            .unwrap_or_else(|| Shifts::unread(state.turn_rad, state.turn_var_rad2 != [0.0; 2]));
        if let Some(r) = state.revisit {
            self.turned.revisit.restore(r);
        }
        self.samples.clear();
        Ok(())
    }

    /// A knock found in the frames since last asked (its turn is taken out of every frame
    /// from it on).
    pub fn take_knock(&mut self) -> Option<Knock> {
        self.turned.found.take()
    }

    /// A return to the zero agreed since last asked, while the turns found since the last one
    /// were known only by their own variance: from now on they are bounded by what it read.
    /// The captures taken since the last knock read through the same turns, and their u may
    /// be stated again by [`Measure::turns_var`] (`RunMachine::turns_bounded`).
    pub fn take_bounded(&mut self) -> Option<Agreement> {
        self.turned.bounded.take()
    }

    /// The variance the turns found add to each error at `travel` (internal units²), as they
    /// are known now.
    pub fn turns_var(&self, travel: f64) -> Errors6 {
        Errors6::from_array(self.turned_var(travel))
    }

    /// Set or clear the nominal travel; the averaging window restarts.
    pub fn set_nominal(&mut self, nominal: Option<f64>) {
        if nominal != self.nominal {
            self.samples.clear();
            if let Some(a) = self.zero_average.as_mut() {
                *a = ZeroAverage::default();
            }
        }
        self.nominal = nominal;
    }

    /// The nominal travel, when known.
    pub fn nominal(&self) -> Option<f64> {
        self.nominal
    }

    /// The carriage position of the newest frame decoupled (travel plus dy, mm).
    pub fn position(&self) -> Option<f64> {
        self.samples.back().map(|s| s.travel + s.errors[1])
    }

    /// The measured carriage position (travel plus dy, mm) of the frame decoupled at `at`.
    pub fn position_at(&self, at: Instant) -> Option<f64> {
        self.samples
            .back()
            .filter(|s| s.at == at)
            .map(|s| s.travel + s.errors[1])
    }

    /// Drop the averaging window (the carriage moved, the stitch changed); a zero reference
    /// on its way starts its average again.
    pub fn restart(&mut self) {
        self.samples.clear();
        if let Some(a) = self.zero_average.as_mut() {
            *a = ZeroAverage::default();
        }
    }

    /// A zero reference is asked for: forget the one in force and average every frame from
    /// now until [`Measure::set_zero`].
    pub fn start_zero(&mut self) {
        self.zero = None;
        self.turned.reset();
        self.reference_changed = true;
        self.zero_average = Some(ZeroAverage::default());
    }

    /// Take the zero reference of all six errors: the mean of the frames since
    /// [`Measure::start_zero`] when they are more than the live window holds, else the live
    /// mean. `stitch` is where PSD2's stitch stands, kept with the zero.
    ///
    /// Its covariance is the frames' noise over their number alone. PSD2's stitch error at
    /// the zero is not in it: every later frame states the stitch's variance from the same
    /// reference (the tracker's, taken with the zero), and the part up to the zero is common
    /// to the zero and the frame, so it cancels in what the frame reads against the zero.
    /// Counted in both, the storm's roll was stated 0.41″ (standard) where the captures were
    /// 0.18″ RMS off the truth: the stage's 0.2 µm beyond its map, twice.
    pub fn set_zero(&mut self, stitch: Option<StitchAnchor>) -> Option<Errors6> {
        self.zero = None;
        let average = self.zero_average.take();
        let live = self.live()?;
        let (e, n) = match average {
            Some(a) if a.n > live.frames => (a.sum / a.n as f64, a.n),
            _ => (live.errors.to_vector(), self.samples.len()),
        };
        let cov = self.frame_cov / n.max(1) as f64;
        self.zero = Some(Zero {
            errors: e,
            cov,
            stitch,
        });
        if let Some(at) = self.position() {
            self.turned.revisit.set_zero(at);
        }
        self.reference_changed = true;
        Some(Errors6::from_vector(&e))
    }

    /// The six errors `other` reads from the newest frame's spots (no zero reference), when a
    /// frame was decoupled; `None` also when `other` cannot decouple it.
    pub fn read_with(&self, other: &Decoupler) -> Option<Errors6> {
        let (r, travel, follower) = self.last_input?;
        other.decouple(&r, travel, follower).ok().map(|e| e.errors)
    }

    /// Shift the zero reference by `by` (internal units): frames read `by` less than they
    /// did. The run's judge found the reference moved by as much (`run::judge`).
    pub fn shift_zero(&mut self, by: Errors6) {
        let by = by.to_vector();
        match self.zero.as_mut() {
            Some(z) => z.errors += by,
            None => {
                self.zero = Some(Zero {
                    errors: by,
                    cov: Matrix6::zeros(),
                    stitch: None,
                })
            }
        }
        self.samples.clear();
        // A return to the zero half averaged reads against the zero in force from here on.
        self.turned.revisit.restart();
        self.reference_changed = true;
    }

    /// Forget the zero reference.
    pub fn clear_zero(&mut self) {
        self.zero = None;
        self.turned.reset();
        self.reference_changed = true;
    }

    /// The decoupling in use.
    pub fn decoupler(&self) -> &Decoupler {
        &self.decoupler
    }

    /// Decouple with `decoupler` from now on (an accepted calibration). The averaging window
    /// restarts and the zero reference is forgotten: both were in the old decoupling's terms.
    pub fn set_decoupler(&mut self, decoupler: Decoupler) {
        self.decoupler = decoupler;
        self.beta = BetaCache::default();
        self.samples.clear();
        self.zero = None;
        self.zero_average = self.zero_average.map(|_| ZeroAverage::default());
        self.turned.reset();
        self.reference_changed = true;
    }

    /// Feed one frame with PSD2's stitched position. Invalid frames (a PSD without its spot)
    /// and frames without a valid stitch are skipped: never averaged in. Returns the frame's
    /// estimate when it was used.
    pub fn handle_frame(
        &mut self,
        frame: &Frame,
        stitch: &Stitch,
        now: Instant,
    ) -> Result<Option<FrameSample>, DecoupleError> {
        while let Some(s) = self.samples.front() {
            if now.saturating_duration_since(s.at) > self.window {
                self.samples.pop_front();
            } else {
                break;
            }
        }
        let Some(mut r) = frame.readings() else {
            return Ok(None);
        };
        let follower = stitch.follower_mm;
        let travel = self.nominal.unwrap_or(follower + r[2]);
        // The spots as they are, for judging a calibration: every frame with its spots, the
        // stitch valid or not (a hexapod run breaks it), without the stitch's vertical steps.
        self.last_input = Some((r, travel, follower));
        if !stitch.valid {
            return Ok(None);
        }
        r[3] += stitch.vertical_mm;
        let var = [0.0, 0.0, stitch.variance[0], stitch.variance[1], 0.0, 0.0];
        let (est, stitch_cov) =
            self.decoupler
                .decouple_cached(&r, travel, follower, &var, &mut self.beta)?;
        self.frame_cov = est.cov;
        let layout = self.decoupler.layout();
        let mut read = self.turned.undo(layout, travel, est.errors);
        if let Some(k) = self.turned.watch.push(frame.stamp(), travel, &read) {
            // The frames since the knock read through a turn not taken out yet: dropped.
            self.turned.add(k, layout, travel);
            read = self.turned.undo(layout, travel, est.errors);
            self.restart();
            self.turned.revisit.restart();
            self.reference_changed = true;
        }
        // Pitch, yaw, dx and dz relative to the zero, for the check of each return to it.
        let order = [3, 5, 0, 2];
        let (rel, zero_sd) = match &self.zero {
            Some(z) => (
                read.to_vector() - z.errors,
                order.map(|k| z.cov[(k, k)].sqrt()),
            ),
            None => (read.to_vector(), [0.0; 4]),
        };
        let at = travel + read.dy;
        let agreed = self.turned.revisit.agreed_us();
        if let Some(k) = self
            .turned
            .revisit
            .push(frame.stamp(), at, order.map(|k| rel[k]), zero_sd)
        {
            // Found back at the zero: the frames of this stay read through it too.
            self.turned.add(k, self.decoupler.layout(), travel);
            read = self
                .turned
                .undo(self.decoupler.layout(), travel, est.errors);
            self.restart();
            self.turned.watch.reset();
        }
        if self.turned.revisit.agreed_us() != agreed && self.zero.is_some() {
            self.reference_changed = true;
        }
        if let Some(a) = self.turned.revisit.agreement() {
            self.turned.bound(a);
        }
        let turned_var = self.turned_var(travel);
        if let Some(a) = self.zero_average.as_mut() {
            a.sum += read.to_vector();
            a.n += 1;
        }
        self.samples.push_back(Sample {
            at: now,
            errors: read.to_vector(),
            travel,
            follower,
            stitch_var: stitch.variance,
        });
        // Relative to the zero reference, as the live errors: its uncertainty is as
        // systematic as the stitching's.
        let (errors, zero_var) = match &self.zero {
            Some(z) => (
                Errors6::from_vector(&(read.to_vector() - z.errors)),
                std::array::from_fn(|k| z.cov[(k, k)]),
            ),
            None => (read, [0.0; 6]),
        };
        Ok(Some(FrameSample {
            at: now,
            unix_us: frame.unix_us,
            position_mm: travel + read.dy,
            nominal: self.nominal,
            errors,
            var: Errors6::from_array(std::array::from_fn(|k| est.cov[(k, k)])),
            stitch_var: Errors6::from_array(std::array::from_fn(|k| {
                stitch_cov[(k, k)] + zero_var[k] + turned_var[k] + self.calibration_var[k]
            })),
            turns_var: self
                .turned
                .pending()
                .then(|| Errors6::from_array(turned_var)),
            material_c: None,
            air_c: None,
        }))
    }

    /// The variance the turns found add to each error at `travel`.
    fn turned_var(&self, travel: f64) -> [f64; 6] {
        let zero_travel = self.turned.revisit.state().map_or(0.0, |z| z.position_mm);
        self.turned
            .var_at(self.decoupler.layout(), travel, zero_travel)
    }

    /// Covariance of the window's mean: noise / n plus the stitching variance through β.
    fn window_cov(&self) -> Option<Matrix6<f64>> {
        self.cov_of_mean(self.samples.len())
    }

    /// Covariance of a mean of `n` frames like the newest: noise / n plus the stitching
    /// variance through β.
    fn cov_of_mean(&self, n: usize) -> Option<Matrix6<f64>> {
        let last = self.samples.back()?;
        let n = n.max(1) as f64;
        let var = [0.0, 0.0, last.stitch_var[0], last.stitch_var[1], 0.0, 0.0];
        let stitch = self
            .decoupler
            .propagate(&var, last.travel, last.follower)
            .ok()?;
        Some(self.frame_cov / n + stitch)
    }

    /// The live six errors, when the window holds any frame.
    pub fn live(&self) -> Option<LiveErrors> {
        let last = self.samples.back()?;
        let n = self.samples.len();
        let mean = self
            .samples
            .iter()
            .fold(Vector6::zeros(), |acc, s| acc + s.errors)
            / n as f64;
        let mut cov = self.window_cov()?;
        let mut e = mean;
        let turned = self.turned_var(last.travel);
        for (k, v) in turned.iter().enumerate() {
            cov[(k, k)] += v + self.calibration_var[k];
        }
        if let Some(z) = &self.zero {
            e -= z.errors;
            cov += z.cov;
        }
        let errors = Errors6::from_vector(&e);
        Some(LiveErrors {
            errors,
            sd: crate::decouple::sd_of(&cov),
            frames: n,
            travel_mm: last.travel,
            nominal: self.nominal,
            position_mm: last.travel + mean[1],
            zeroed: self.zero.is_some(),
        })
    }
}

#[cfg(test)]
mod tests;
