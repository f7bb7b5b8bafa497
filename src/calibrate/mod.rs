//! Calibration of the head from known poses (DESIGN §3): the paper's linear β with an offset
//! (`linear`), and the model-based fit of installation errors (`model`), each judged on poses
//! held out of the fit; saved to and loaded from a TOML file (`file`).
//!
//! The poses must cover the operating window (positioning over the whole follower window):
//! a linear β fitted over a small window leaves µm-level bias when used over a large one.
//! For the model to hold over the travel, the poses must also span the travel (hexapod at
//! several positions along a calibration bench): from one position the parameters that set
//! the beams' directions relative to the travel are seen only over the hexapod's ±2 mm, far
//! too short a lever to extrapolate to hundreds of millimetres (`axiscomp demo --bench-mm 0`
//! shows it).
//!
//! Poses taken on the axis under test itself (the hexapod on the carriage, DESIGN §3) differ
//! between positions along the travel by what the calibration cannot know: the carriage's own
//! six errors there (what the run will measure) and the follower's own positioning and
//! vertical errors (PSD2's offset along X2 and Y2). With `station_offsets` each position
//! (each distinct travel and follower pair, a *station*) after the first gets its own unknown
//! offset: six DOFs in the model fit (the two PSD2 offsets act on X2 and Y2 as dy and a
//! roll/straightness pair do, so six DOFs span them), six reading offsets in the linear fit;
//! the hold-outs are judged against the pose plus its station's offset. The first station's
//! offset is the installation's (as with one position). What stations cannot give is the
//! beams' direction relative to the travel: it is a straightness slope, which the offsets take.

pub mod file;
pub mod linear;
pub mod model;
pub mod plausible;
pub mod poses;

pub use file::CalibrationFile;
pub use linear::{LINEAR_RCOND, LinearFit, fit_linear, fit_linear_stations};
pub use model::{ModelFit, ModelFitOptions, fit_model, fit_model_stations};
pub use poses::{PoseSample, parse_pose_csv, write_pose_csv};

use crate::decouple::{self, DecoupleError, Decoupler, Method, SolveOptions, Source};
use crate::optics::{Installation, Layout, Pose};
use crate::units::{DOF_NAMES, DOF_TO_USER, DOF_UNITS, Errors6, MM_PER_UM, READING_NAMES};
use crate::util::csv::CsvError;
use nalgebra::Vector6;
use std::fmt;
use thiserror::Error;

/// Why a calibration failed.
#[derive(Debug, Error)]
pub enum CalError {
    #[error(transparent)]
    Csv(#[from] CsvError),
    #[error("{0}")]
    Input(String),
    #[error("{n} poses are too few: this fit needs at least {needed}")]
    TooFewPoses { n: usize, needed: usize },
    #[error(
        "the pose set does not determine β (rank {rank} of {needed}): {weakest} is not excited; add poses that move it"
    )]
    LowRank {
        rank: usize,
        needed: usize,
        weakest: String,
    },
    #[error("model fit failed: {problem}")]
    ModelFit { problem: String },
    #[error("decoupling during calibration failed: {0}")]
    Decouple(#[from] DecoupleError),
    #[error("calibration file {path}: {problem}")]
    File { path: String, problem: String },
    #[error("internal: {0}")]
    Internal(&'static str),
}

/// Split a pose set: every `every`-th pose (the last of each group) is held out of the fit.
pub fn split_holdout(samples: &[PoseSample], every: usize) -> (Vec<PoseSample>, Vec<PoseSample>) {
    let every = every.max(2);
    let mut fit = Vec::new();
    let mut hold = Vec::new();
    for (i, s) in samples.iter().enumerate() {
        if i % every == every - 1 {
            hold.push(*s);
        } else {
            fit.push(*s);
        }
    }
    (fit, hold)
}

/// RMS per DOF (internal units) of decoupled minus known errors over `samples`.
pub fn holdout_rms(dec: &Decoupler, samples: &[PoseSample]) -> Result<[f64; 6], CalError> {
    holdout_rms_at(dec, samples, &[])
}

/// The stations of a pose set: each distinct (travel, follower) pair in order of first
/// appearance, and each sample's station.
#[derive(Clone, Debug, PartialEq)]
pub struct Stations {
    pub at: Vec<(f64, f64)>,
    pub of: Vec<usize>,
}

impl Stations {
    /// The stations of `samples`; all one station unless `separate`.
    pub fn of(samples: &[PoseSample], separate: bool) -> Stations {
        let mut at: Vec<(f64, f64)> = Vec::new();
        let of = samples
            .iter()
            .map(|s| {
                let key = (s.pose.travel, s.pose.follower);
                if !separate {
                    if at.is_empty() {
                        at.push(key);
                    }
                    return 0;
                }
                match at.iter().position(|k| *k == key) {
                    Some(i) => i,
                    None => {
                        at.push(key);
                        at.len() - 1
                    }
                }
            })
            .collect();
        Stations { at, of }
    }

    pub fn len(&self) -> usize {
        self.at.len()
    }

    pub fn is_empty(&self) -> bool {
        self.at.is_empty()
    }
}

/// One station's fitted offset (zero at the first station).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StationOffset {
    pub travel_mm: f64,
    pub follower_mm: f64,
    /// Six-DOF offset of the model fit (internal units), when the model was fitted.
    pub errors: Option<Errors6>,
    /// Reading offset of the linear fit (mm).
    pub readings: Vector6<f64>,
}

impl StationOffset {
    /// The offset of the station at (travel, follower) in `offsets`, if it is one of them.
    pub fn find(offsets: &[StationOffset], travel: f64, follower: f64) -> Option<&StationOffset> {
        offsets
            .iter()
            .find(|o| o.travel_mm == travel && o.follower_mm == follower)
    }
}

/// `errors + offset`, DOF by DOF (the carriage's error and the hexapod's pose add, as the
/// twin adds them).
pub fn add_errors(a: &Errors6, b: &Errors6) -> Errors6 {
    let (a, b) = (a.to_array(), b.to_array());
    Errors6::from_array(std::array::from_fn(|k| a[k] + b[k]))
}

/// The known errors at a sample with its station's offset, and the readings with the linear
/// offset removed (for the linear decoupler, `linear`).
fn with_station(
    s: &PoseSample,
    offsets: &[StationOffset],
    linear: bool,
) -> (Errors6, Vector6<f64>) {
    match StationOffset::find(offsets, s.pose.travel, s.pose.follower) {
        None => (s.pose.errors, s.readings),
        Some(o) if linear => (s.pose.errors, s.readings - o.readings),
        Some(o) => (
            o.errors
                .map(|e| add_errors(&s.pose.errors, &e))
                .unwrap_or(s.pose.errors),
            s.readings,
        ),
    }
}

/// `holdout_rms` with each sample judged against its station's offset (`offsets`; none: the
/// poses as they are).
pub fn holdout_rms_at(
    dec: &Decoupler,
    samples: &[PoseSample],
    offsets: &[StationOffset],
) -> Result<[f64; 6], CalError> {
    let linear = matches!(dec.source, Source::Linear { .. });
    let mut ss = [0.0; 6];
    for s in samples {
        let (truth, readings) = with_station(s, offsets, linear);
        let est = dec.decouple(&readings, s.pose.travel, s.pose.follower)?;
        let d = est.errors.to_array();
        let t = truth.to_array();
        for k in 0..6 {
            ss[k] += (d[k] - t[k]).powi(2);
        }
    }
    let n = samples.len().max(1) as f64;
    Ok(ss.map(|x| (x / n).sqrt()))
}

/// The model-based part of a calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelPart {
    pub install: Installation,
    /// Nominal layout with `install` applied.
    pub layout: Layout,
    pub iterations: u32,
    pub converged: bool,
    pub fitted_params: usize,
    pub well_determined: usize,
    /// Residual RMS per reading channel (mm).
    pub residual_rms: [f64; 6],
    /// Hold-out RMS per DOF (internal units).
    pub holdout_rms: Option<[f64; 6]>,
}

/// A complete calibration: what the file holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    pub created: String,
    pub layout_name: String,
    pub layout_hash: String,
    pub poses: usize,
    pub fit_poses: usize,
    pub holdout_poses: usize,
    pub travel_range: (f64, f64),
    /// Reading noise per channel (mm), from the fit residuals; used for every covariance.
    pub sigma_mm: [f64; 6],
    pub linear: LinearFit,
    /// Hold-out RMS per DOF of the linear fit (internal units).
    pub linear_holdout_rms: Option<[f64; 6]>,
    pub model: Option<ModelPart>,
}

/// What to fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Hold out every n-th pose (0: hold out none).
    pub holdout_every: usize,
    /// Also fit the installation errors (model-based calibration).
    pub model: bool,
    pub model_options: ModelFitOptions,
    /// Give each position along the travel after the first its own offset (poses taken on
    /// the axis under test, whose errors there are unknown); off for a bench whose positions
    /// are exact.
    pub station_offsets: bool,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            holdout_every: 5,
            model: true,
            model_options: ModelFitOptions::default(),
            station_offsets: false,
        }
    }
}

/// Lower bound on a channel's noise estimate (mm), so a noise-free pose set still gives a
/// usable covariance.
const SIGMA_FLOOR_MM: f64 = 1e-6;

/// Calibrate from a pose set: linear fit, optionally the model fit, both judged on held-out
/// poses. `on_iter` reports model-fit iterations.
pub fn calibrate(
    samples: &[PoseSample],
    nominal: &Layout,
    opts: &CalibrateOptions,
    on_iter: &mut dyn FnMut(u32, f64),
) -> Result<Calibration, CalError> {
    Ok(calibrate_along(samples, nominal, opts, on_iter)?.0)
}

/// `calibrate`, also giving each station's fitted offset (one, zero, without
/// `station_offsets`).
pub fn calibrate_along(
    samples: &[PoseSample],
    nominal: &Layout,
    opts: &CalibrateOptions,
    on_iter: &mut dyn FnMut(u32, f64),
) -> Result<(Calibration, Vec<StationOffset>), CalError> {
    let (fit_set, hold_set) = if opts.holdout_every == 0 {
        (samples.to_vec(), Vec::new())
    } else {
        split_holdout(samples, opts.holdout_every)
    };
    let stations = Stations::of(&fit_set, opts.station_offsets);
    let (linear, lin_offsets) = fit_linear_stations(&fit_set, nominal, &stations)?;
    let model = if opts.model {
        Some(fit_model_stations(
            &fit_set,
            nominal,
            &stations,
            &opts.model_options,
            on_iter,
        )?)
    } else {
        None
    };
    let offsets: Vec<StationOffset> = stations
        .at
        .iter()
        .enumerate()
        .map(|(i, &(travel_mm, follower_mm))| StationOffset {
            travel_mm,
            follower_mm,
            errors: model.as_ref().map(|m| m.station_errors[i]),
            readings: lin_offsets[i],
        })
        .collect();
    // Noise estimate from the best model's residuals, corrected for the fitted parameters.
    let extra = 6.0 * (stations.len().max(1) - 1) as f64;
    let (resid, params_per_channel) = match &model {
        Some(m) => (m.residual_rms, (m.params.len() as f64 + extra) / 6.0),
        None => (linear.residual_rms, 7.0 + extra / 6.0),
    };
    let n = fit_set.len() as f64;
    let dof_corr = (n / (n - params_per_channel).max(1.0)).sqrt();
    let sigma_mm = resid.map(|r| (r * dof_corr).max(SIGMA_FLOOR_MM));

    let lin_dec = Decoupler {
        source: Source::Linear {
            linear: Box::new(linear.linear(&sigma_mm)?),
            nominal: nominal.clone(),
            ref_travel: linear.ref_travel,
            ref_follower: linear.ref_follower,
        },
        method: Method::Linear,
        sigma_mm,
        options: SolveOptions::default(),
    };
    // A held-out pose at a station the fit did not see has no offset: it is judged as it is.
    let linear_holdout_rms = if hold_set.is_empty() {
        None
    } else {
        Some(holdout_rms_at(&lin_dec, &hold_set, &offsets)?)
    };
    let model = match model {
        Some(m) => {
            let dec = Decoupler {
                source: Source::Model(m.layout.clone()),
                method: Method::Nonlinear,
                sigma_mm,
                options: SolveOptions::default(),
            };
            let holdout = if hold_set.is_empty() {
                None
            } else {
                Some(holdout_rms_at(&dec, &hold_set, &offsets)?)
            };
            Some(ModelPart {
                install: m.install,
                layout: m.layout,
                iterations: m.iterations,
                converged: m.converged,
                fitted_params: m.params.len(),
                well_determined: m.well_determined,
                residual_rms: m.residual_rms,
                holdout_rms: holdout,
            })
        }
        None => None,
    };
    let tmin = samples
        .iter()
        .map(|s| s.pose.travel)
        .fold(f64::INFINITY, f64::min);
    let tmax = samples
        .iter()
        .map(|s| s.pose.travel)
        .fold(f64::NEG_INFINITY, f64::max);
    let cal = Calibration {
        created: crate::util::time::now_rfc3339(),
        layout_name: nominal.name.clone(),
        layout_hash: nominal.hash(),
        poses: samples.len(),
        fit_poses: fit_set.len(),
        holdout_poses: hold_set.len(),
        travel_range: (tmin, tmax),
        sigma_mm,
        linear,
        linear_holdout_rms,
        model,
    };
    Ok((cal, offsets))
}

impl Calibration {
    /// The decoupler this calibration gives: the calibrated model with Gauss–Newton when the
    /// model was fitted, the linear β otherwise.
    pub fn decoupler(&self, nominal: &Layout) -> Result<Decoupler, CalError> {
        Ok(match &self.model {
            Some(m) => Decoupler {
                source: Source::Model(m.layout.clone()),
                method: Method::Nonlinear,
                sigma_mm: self.sigma_mm,
                options: SolveOptions::default(),
            },
            None => Decoupler {
                source: Source::Linear {
                    linear: Box::new(self.linear.linear(&self.sigma_mm)?),
                    nominal: nominal.clone(),
                    ref_travel: self.linear.ref_travel,
                    ref_follower: self.linear.ref_follower,
                },
                method: Method::Linear,
                sigma_mm: self.sigma_mm,
                options: SolveOptions::default(),
            },
        })
    }

    /// Cramér–Rao bound per DOF (internal units) of the calibrated head at the linear fit's
    /// reference position, with this calibration's noise.
    pub fn crlb(&self, nominal: &Layout) -> Result<Errors6, CalError> {
        let layout = self.model.as_ref().map(|m| &m.layout).unwrap_or(nominal);
        let pose = Pose::new(
            Errors6::ZERO,
            self.linear.ref_travel,
            self.linear.ref_follower,
        );
        let j = decouple::jacobian(layout, &pose)?;
        let cov = decouple::covariance(&j, &self.sigma_mm).ok_or(DecoupleError::Singular)?;
        Ok(decouple::sd_of(&cov))
    }

    /// The fit report as text, with the Cramér–Rao bound of `crlb` for comparison.
    pub fn report(&self, crlb: Option<&Errors6>) -> String {
        ReportView { cal: self, crlb }.to_string()
    }
}

struct ReportView<'a> {
    cal: &'a Calibration,
    crlb: Option<&'a Errors6>,
}

fn dof_row(f: &mut fmt::Formatter<'_>, label: &str, v: &[f64; 6]) -> fmt::Result {
    write!(f, "  {label:<24}")?;
    for k in 0..6 {
        write!(f, "{:>9.3}", v[k] * DOF_TO_USER[k])?;
    }
    writeln!(f)
}

fn channel_row(f: &mut fmt::Formatter<'_>, label: &str, v: &[f64; 6]) -> fmt::Result {
    write!(f, "  {label:<24}")?;
    for x in v {
        write!(f, "{:>9.3}", x / MM_PER_UM)?;
    }
    writeln!(f)
}

impl fmt::Display for ReportView<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = self.cal;
        writeln!(
            f,
            "calibration: {} poses ({} fitted, {} held out), travel {:.1} to {:.1} mm, layout {} ({})",
            c.poses,
            c.fit_poses,
            c.holdout_poses,
            c.travel_range.0,
            c.travel_range.1,
            c.layout_name,
            c.layout_hash
        )?;
        write!(f, "  {:<24}", "per reading (µm)")?;
        for n in READING_NAMES {
            write!(f, "{n:>9}")?;
        }
        writeln!(f)?;
        channel_row(f, "noise σ (from residuals)", &c.sigma_mm)?;
        channel_row(f, "linear fit residual RMS", &c.linear.residual_rms)?;
        if let Some(m) = &c.model {
            channel_row(f, "model fit residual RMS", &m.residual_rms)?;
        }
        writeln!(
            f,
            "linear β + offset (SVD, rcond {:.0e}): rank {} of 7, condition number of β {:.2} (µm/arcsec)",
            LINEAR_RCOND, c.linear.rank, c.linear.condition_number
        )?;
        if let Some(m) = &c.model {
            writeln!(
                f,
                "model-based (Levenberg–Marquardt): {} installation parameters, {} well determined, {} iterations, {}",
                m.fitted_params,
                m.well_determined,
                m.iterations,
                if m.converged {
                    "converged"
                } else {
                    "NOT converged"
                }
            )?;
        }
        write!(f, "  {:<24}", "per DOF")?;
        for k in 0..6 {
            write!(
                f,
                "{:>9}",
                format!("{} {}", DOF_NAMES[k], DOF_UNITS[k].replace("arcsec", "″"))
            )?;
        }
        writeln!(f)?;
        if let Some(h) = &c.linear_holdout_rms {
            dof_row(f, "hold-out RMS, linear β", h)?;
        }
        if let Some(h) = c.model.as_ref().and_then(|m| m.holdout_rms.as_ref()) {
            dof_row(f, "hold-out RMS, model", h)?;
        }
        if let Some(b) = self.crlb {
            dof_row(f, "Cramér–Rao bound", &b.to_array())?;
            if let Some(h) = c.model.as_ref().and_then(|m| m.holdout_rms.as_ref()) {
                write!(f, "  {:<24}", "model / bound")?;
                let b = b.to_array();
                for k in 0..6 {
                    write!(f, "{:>9.3}", h[k] / b[k])?;
                }
                writeln!(f)?;
            }
        }
        Ok(())
    }
}
