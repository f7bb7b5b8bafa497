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

use crate::acquire::Frame;
use crate::decouple::{BetaCache, DecoupleError, Decoupler};
use crate::run::FrameSample;
use crate::track::Stitch;
use crate::units::Errors6;
use nalgebra::{Matrix6, Vector6};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

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
        }
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
        self.zero_average = Some(ZeroAverage::default());
    }

    /// Take the zero reference of all six errors: the mean of the frames since
    /// [`Measure::start_zero`] when they are more than the live window holds, else the live
    /// mean.
    pub fn set_zero(&mut self) -> Option<Errors6> {
        self.zero = None;
        let average = self.zero_average.take();
        let live = self.live()?;
        let (e, cov) = match average {
            Some(a) if a.n > live.frames => {
                let cov = self.cov_of_mean(a.n)?;
                (a.sum / a.n as f64, cov)
            }
            _ => (live.errors.to_vector(), self.window_cov()?),
        };
        self.zero = Some(Zero { errors: e, cov });
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
                })
            }
        }
        self.samples.clear();
    }

    /// Forget the zero reference.
    pub fn clear_zero(&mut self) {
        self.zero = None;
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
        if let Some(a) = self.zero_average.as_mut() {
            a.sum += est.errors.to_vector();
            a.n += 1;
        }
        self.samples.push_back(Sample {
            at: now,
            errors: est.errors.to_vector(),
            travel,
            follower,
            stitch_var: stitch.variance,
        });
        // Relative to the zero reference, as the live errors: its uncertainty is as
        // systematic as the stitching's.
        let (errors, zero_var) = match &self.zero {
            Some(z) => (
                Errors6::from_vector(&(est.errors.to_vector() - z.errors)),
                std::array::from_fn(|k| z.cov[(k, k)]),
            ),
            None => (est.errors, [0.0; 6]),
        };
        Ok(Some(FrameSample {
            at: now,
            unix_us: frame.unix_us,
            position_mm: travel + est.errors.dy,
            nominal: self.nominal,
            errors,
            var: Errors6::from_array(std::array::from_fn(|k| est.cov[(k, k)])),
            stitch_var: Errors6::from_array(std::array::from_fn(|k| {
                stitch_cov[(k, k)] + zero_var[k]
            })),
            material_c: None,
            air_c: None,
        }))
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
mod tests {
    use super::*;
    use crate::decouple::{Method, SolveOptions, Source};
    use crate::optics::{Layout, Pose, Spot};
    use crate::sim::Rng;
    use crate::track::Strategy;

    fn frame_at(layout: &Layout, pose: &Pose, rng: &mut Rng, t: Instant, noise: f64) -> Frame {
        let r = layout.forward(pose).vector().unwrap();
        let spots = std::array::from_fn(|k| {
            Some(Spot {
                x: r[2 * k] + rng.gauss(noise),
                y: r[2 * k + 1] + rng.gauss(noise),
            })
        });
        Frame {
            seq: 0,
            at: t,
            unix_us: 0,
            spots,
            sums: [5.0; 3],
        }
    }

    fn stitch(follower: f64, var: f64) -> Stitch {
        Stitch {
            follower_mm: follower,
            vertical_mm: 0.0,
            variance: [var, 0.0],
            handovers: 0,
            strategy: Strategy::Overlap,
            valid: true,
        }
    }

    #[test]
    fn live_mean_matches_truth_within_stated_sd() {
        let layout = Layout::reference();
        let dec = Decoupler {
            source: Source::Simulated(layout.clone()),
            method: Method::Nonlinear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        let mut m = Measure::new(dec, Duration::from_millis(250));
        m.set_nominal(Some(100.0));
        let truth = Errors6::from_user([12.0, -7.0, 4.0, 3.0, -2.0, 5.0]);
        let pose = Pose::new(truth, 100.0, 99.2);
        let mut rng = Rng::new(4);
        let t0 = crate::util::clock::now();
        let mut worst: f64 = 0.0;
        for trial in 0..24 {
            for i in 0..125 {
                let t = t0 + Duration::from_millis(2 * (i + 125 * trial));
                let f = frame_at(&layout, &pose, &mut rng, t, 1e-3);
                assert!(m.handle_frame(&f, &stitch(99.2, 0.0), t).unwrap().is_some());
            }
            let live = m.live().unwrap();
            assert_eq!(live.frames, 125);
            let (e, sd, tr) = (live.errors.to_array(), live.sd.to_array(), truth.to_array());
            for k in 0..6 {
                worst = worst.max((e[k] - tr[k]).abs() / sd[k]);
            }
            m.restart();
        }
        // 144 normal deviates: the largest should be well under 4.5 sd.
        assert!(worst < 4.5 && worst > 1.0, "worst {worst}");
    }

    #[test]
    fn stitch_variance_enters_positioning_and_invalid_frames_are_skipped() {
        let layout = Layout::reference();
        let dec = Decoupler {
            source: Source::Simulated(layout.clone()),
            method: Method::Linear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        let mut m = Measure::new(dec, Duration::from_millis(250));
        let t = crate::util::clock::now();
        // At D = 0, where the design's bound for dy (1.2137 µm at σ = 1 µm) applies.
        let pose = Pose::new(Errors6::ZERO, 0.0, 0.0);
        let mut rng = Rng::new(1);
        let f = frame_at(&layout, &pose, &mut rng, t, 0.0);
        m.handle_frame(&f, &stitch(0.0, (2e-3_f64).powi(2)), t)
            .unwrap();
        let live = m.live().unwrap();
        // dy's sd: frame noise (1.2137 µm for one frame) and 2 µm of stitching, in quadrature.
        let sd_dy = live.sd.to_user()[1];
        assert!(
            (sd_dy - (1.2137_f64.powi(2) + 4.0).sqrt()).abs() < 1e-3,
            "{sd_dy}"
        );
        assert!(live.nominal.is_none());
        assert!(live.position_mm.abs() < 1e-9);
        let mut blocked = f;
        blocked.spots[2] = None;
        assert!(
            m.handle_frame(&blocked, &stitch(0.0, 0.0), t)
                .unwrap()
                .is_none()
        );
        let mut broken = stitch(0.0, 0.0);
        broken.valid = false;
        assert!(m.handle_frame(&f, &broken, t).unwrap().is_none());
        assert_eq!(m.live().unwrap().frames, 1);
        assert!(m.set_zero().is_some());
        assert!(m.live().unwrap().zeroed);
    }

    /// A zero reference averages every frame since it was asked for, not the live window's
    /// last quarter second: with 1000 frames its noise is √(1000/125) ≈ 2.8 times less, and
    /// its stated covariance says so.
    #[test]
    fn the_zero_averages_every_frame_since_it_was_asked_for() {
        let layout = Layout::reference();
        let dec = Decoupler {
            source: Source::Simulated(layout.clone()),
            method: Method::Linear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        let mut m = Measure::new(dec, Duration::from_millis(250));
        m.set_nominal(Some(0.0));
        let pose = Pose::new(Errors6::ZERO, 0.0, 0.0);
        let mut rng = Rng::new(9);
        let t0 = crate::util::clock::now();
        m.start_zero();
        let mut sum = Vector6::zeros();
        let mut last_window = VecDeque::new();
        for i in 0..1000u64 {
            let t = t0 + Duration::from_millis(2 * i);
            let f = frame_at(&layout, &pose, &mut rng, t, 1e-3);
            let e = m
                .handle_frame(&f, &stitch(0.0, 0.0), t)
                .unwrap()
                .unwrap()
                .errors
                .to_vector();
            sum += e;
            last_window.push_back(e);
            if last_window.len() > 125 {
                last_window.pop_front();
            }
        }
        let live = m.live().unwrap();
        assert_eq!(live.frames, 126);
        let z = m.set_zero().unwrap().to_vector();
        let mean = sum / 1000.0;
        assert!((z - mean).norm() < 1e-12, "{z} against {mean}");
        // The stated uncertainty of the zero: the frame covariance over 1000, so a live mean
        // of the next window reads its own noise and the zero's, 1/125 + 1/1000.
        let t = t0 + Duration::from_millis(2000);
        let f = frame_at(&layout, &pose, &mut rng, t, 1e-3);
        m.handle_frame(&f, &stitch(0.0, 0.0), t).unwrap();
        let sd = m.live().unwrap().sd.to_user();
        // One frame after the window moved on: 126 frames in it and the zero's 1000.
        let dy_frame = 1.2137;
        let want = dy_frame * (1.0 / 126.0 + 1.0 / 1000.0_f64).sqrt();
        assert!(
            (sd[1] - want).abs() < 2e-3,
            "dy sd {} µm, want {want}",
            sd[1]
        );
        // Without a zero asked for, the live window is the zero.
        m.clear_zero();
        let live = m.live().unwrap();
        let z = m.set_zero().unwrap();
        assert_eq!(z, live.errors);
    }
}
