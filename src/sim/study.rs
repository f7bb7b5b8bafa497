//! A calibration study on the twin: a head with installation errors, calibrated from hexapod
//! poses, then judged on independent hold-out poses against the twin's truth. The demo prints
//! it; the tests assert on it.

use super::{Hexapod, InstallSpec, PoseWindow, Rng, TwinHead};
use crate::calibrate::{self, CalError, CalibrateOptions, Calibration, PoseSample};
use crate::decouple::{self, Decoupler, Linear, Method, SolveOptions, Source};
use crate::optics::{Layout, Pose};
use crate::units::Errors6;
use crate::util::progress::Progress;
use nalgebra::Vector6;
use thiserror::Error;

/// What to simulate.
#[derive(Clone, Debug, PartialEq)]
pub struct StudySpec {
    pub seed: u64,
    pub install: InstallSpec,
    /// PSD noise per axis (mm).
    pub noise_mm: f64,
    /// Calibration poses.
    pub poses: usize,
    pub window: PoseWindow,
    /// Independent hold-out poses (same window, travel uniform in `holdout_travel`).
    pub holdout: usize,
    pub holdout_travel: (f64, f64),
    /// Frames averaged per hold-out pose for the calibration's own error (a bench dwells at
    /// each pose: `hexapod::procedure` averages 50).
    pub holdout_frames: usize,
    pub calibrate: CalibrateOptions,
}

impl Default for StudySpec {
    fn default() -> Self {
        StudySpec {
            seed: 2026,
            install: InstallSpec {
                gain_error: 0.01,
                ..InstallSpec::default()
            },
            noise_mm: 1e-3,
            poses: 200,
            window: PoseWindow {
                travels: vec![0.0, 100.0, 200.0],
                ..PoseWindow::default()
            },
            holdout: 1000,
            holdout_travel: (0.0, 200.0),
            holdout_frames: 50,
            calibrate: CalibrateOptions::default(),
        }
    }
}

/// Hold-out RMS error per DOF (internal units) of each way of decoupling, and the bound.
#[derive(Clone, Debug)]
pub struct StudyResult {
    pub head: TwinHead,
    pub calibration: Calibration,
    pub calibration_poses: usize,
    pub skipped: usize,
    pub holdout_poses: usize,
    /// Simulated β at D = 0, no offset: the paper's form.
    pub simulated_no_offset: Errors6,
    /// Simulated β at D = 0 with a zero reference read at the home pose.
    pub simulated_zero_ref: Errors6,
    /// The calibrated linear β and offset.
    pub linear: Errors6,
    /// The calibrated model with Gauss–Newton.
    pub model: Option<Errors6>,
    /// Cramér–Rao bound of the true head, RMS over the hold-out poses.
    pub crlb: Errors6,
    /// The calibrated model on the same poses, each read as the mean of
    /// `averaged_frames` frames, and the bound of such a mean: single frames hide a model
    /// error below a fifth of their noise; means show it (what `calibration_u` needs).
    pub model_averaged: Option<Errors6>,
    pub crlb_averaged: Errors6,
    pub averaged_frames: usize,
}

impl StudyResult {
    /// The calibration's own standard uncertainty per DOF (internal units), from the hold-out
    /// poses read as means of many frames (as a bench dwells): what the model's error h adds to
    /// the bound b of such a mean, h² − b², and what N hold-out poses cannot rule out: the mean
    /// of N squared errors is known to √(2/N)·b², so `u² = max(0, h² − b²) + √(2/N)·b²`.
    /// (Single frames would do the same sum with b five to ten times larger: their noise hides
    /// the model's error, and the allowance for it dominates.)
    pub fn calibration_u(&self) -> Option<([f64; 6], String)> {
        let (h, b) = (
            self.model_averaged.as_ref()?.to_array(),
            self.crlb_averaged.to_array(),
        );
        Some((
            crate::evaluate::uncertainty::calibration_u(&h, &b, self.holdout_poses),
            format!(
                "the model calibration's hold-out error h beyond the Cramér–Rao bound b, √(max(0, h² − b²) + √(2/N)·b²), N = {} poses, each the mean of {} frames",
                self.holdout_poses, self.averaged_frames
            ),
        ))
    }
}

/// Why the study could not run.
#[derive(Debug, Error)]
pub enum StudyError {
    #[error(transparent)]
    Sim(#[from] super::SimError),
    #[error(transparent)]
    Calibrate(#[from] CalError),
    #[error(transparent)]
    Decouple(#[from] decouple::DecoupleError),
}

fn rms(acc: &[f64; 6], n: usize) -> Errors6 {
    Errors6::from_array(acc.map(|x| (x / n.max(1) as f64).sqrt()))
}

/// Run the study on a head drawn from `spec` (its seed, installation errors and noise).
/// `show` turns progress bars on.
pub fn run_study(layout: &Layout, spec: &StudySpec, show: bool) -> Result<StudyResult, StudyError> {
    let root = Rng::new(spec.seed);
    let head = TwinHead::random(layout, &spec.install, spec.noise_mm, &mut root.fork(1))?;
    study_head(head, layout, spec, show)
}

/// Run the study on `head` (e.g. the one a plant carries); `spec`'s seed draws the poses and
/// noise, its installation and noise settings are not used.
pub fn study_head(
    head: TwinHead,
    layout: &Layout,
    spec: &StudySpec,
    show: bool,
) -> Result<StudyResult, StudyError> {
    let root = Rng::new(spec.seed);
    let poses = spec.window.draw(spec.poses, &mut root.fork(2));
    let mut p = bar(show, "hexapod calibration poses", poses.len());
    let (samples, skipped) = Hexapod::default().acquire(&head, &poses, &mut root.fork(3), &mut p);
    p.finish(&format!("{} poses", samples.len()));

    let mut p = bar(
        show,
        "calibration fit",
        spec.calibrate.model_options.max_iter as usize,
    );
    let cal = calibrate::calibrate(&samples, layout, &spec.calibrate, &mut |it, _| {
        p.set(it as u64)
    })?;
    p.finish("done");

    // Independent hold-out poses, at travels the calibration never saw.
    let mut rng = root.fork(4);
    let h = spec.window.half_range.to_array();
    let mut hold = Vec::with_capacity(spec.holdout);
    let mut p = bar(show, "hold-out poses", spec.holdout);
    let mut tries = 0;
    while hold.len() < spec.holdout && tries < 10 * spec.holdout.max(1) {
        tries += 1;
        let e = Errors6::from_array(std::array::from_fn(|k| rng.uniform(-h[k], h[k])));
        let d = rng.uniform(spec.holdout_travel.0, spec.holdout_travel.1);
        let pose = Pose::new(e, d, d);
        if let Some(r) = head.read(&pose, &mut rng).vector() {
            hold.push(PoseSample { pose, readings: r });
            p.inc();
        }
    }
    p.finish(&format!("{} poses", hold.len()));
    // The same poses read as means of `frames` frames: the noise of a mean is σ/√frames.
    let frames = spec.holdout_frames.max(1);
    let mut arng = root.fork(6);
    let mut averaged = Vec::with_capacity(hold.len());
    for s in &hold {
        let mut r = head.exact(&s.pose);
        for spot in r.psd.iter_mut().flatten() {
            spot.x += arng.gauss(spec.noise_mm / (frames as f64).sqrt());
            spot.y += arng.gauss(spec.noise_mm / (frames as f64).sqrt());
        }
        if let Some(readings) = r.vector() {
            averaged.push(PoseSample {
                pose: s.pose,
                readings,
            });
        }
    }

    let sigma = [spec.noise_mm.max(1e-9); 6];
    let beta0 = decouple::jacobian(layout, &Pose::default())?;
    let linear_source = |offset: Vector6<f64>| -> Result<Decoupler, StudyError> {
        Ok(Decoupler {
            source: Source::Linear {
                linear: Box::new(Linear::new(beta0, offset, &sigma)?),
                nominal: layout.clone(),
                ref_travel: 0.0,
                ref_follower: 0.0,
            },
            method: Method::Linear,
            sigma_mm: sigma,
            options: SolveOptions::default(),
        })
    };
    // Zero reference: the mean of 100 frames at the home pose.
    let mut zero = Vector6::zeros();
    let mut zrng = root.fork(5);
    let mut nz = 0;
    for _ in 0..100 {
        if let Some(r) = head.read(&Pose::default(), &mut zrng).vector() {
            zero += r;
            nz += 1;
        }
    }
    let zero = zero / nz.max(1) as f64;
    let dec_paper = linear_source(Vector6::zeros())?;
    let dec_zero = linear_source(zero)?;
    let dec_linear = Decoupler {
        source: Source::Linear {
            linear: Box::new(cal.linear.linear(&cal.sigma_mm)?),
            nominal: layout.clone(),
            ref_travel: cal.linear.ref_travel,
            ref_follower: cal.linear.ref_follower,
        },
        method: Method::Linear,
        sigma_mm: cal.sigma_mm,
        options: SolveOptions::default(),
    };
    let dec_model = cal
        .model
        .as_ref()
        .map(|_| cal.decoupler(layout))
        .transpose()?;

    let mut acc = [[0.0; 6]; 4];
    let mut var = [0.0; 6];
    for s in &hold {
        let truth = s.pose.errors.to_array();
        let decs: [Option<&Decoupler>; 4] = [
            Some(&dec_paper),
            Some(&dec_zero),
            Some(&dec_linear),
            dec_model.as_ref(),
        ];
        for (a, d) in acc.iter_mut().zip(decs) {
            if let Some(d) = d {
                let est = d.decouple(&s.readings, s.pose.travel, s.pose.follower)?;
                let e = est.errors.to_array();
                for k in 0..6 {
                    a[k] += (e[k] - truth[k]).powi(2);
                }
            }
        }
        let j = decouple::jacobian(&head.truth, &s.pose)?;
        if let Some(c) = decouple::covariance(&j, &sigma) {
            for k in 0..6 {
                var[k] += c[(k, k)];
            }
        }
    }
    let n = hold.len();
    let model_averaged = match &dec_model {
        Some(d) => Some(Errors6::from_array(calibrate::holdout_rms(d, &averaged)?)),
        None => None,
    };
    let crlb = rms(&var, n);
    Ok(StudyResult {
        calibration_poses: samples.len(),
        skipped,
        holdout_poses: n,
        simulated_no_offset: rms(&acc[0], n),
        simulated_zero_ref: rms(&acc[1], n),
        linear: rms(&acc[2], n),
        model: dec_model.as_ref().map(|_| rms(&acc[3], n)),
        crlb,
        model_averaged,
        crlb_averaged: Errors6::from_array(crlb.to_array().map(|b| b / (frames as f64).sqrt())),
        averaged_frames: frames,
        head,
        calibration: cal,
    })
}

fn bar(show: bool, label: &str, total: usize) -> Progress {
    if show {
        Progress::new(label, total as u64)
    } else {
        Progress::hidden()
    }
}
