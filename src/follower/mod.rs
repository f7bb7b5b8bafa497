//! The follower stage's error map (DESIGN §4): where PSD2 really is, along the follower's axis
//! and vertically, as a function of the follower's encoder position and the direction it last
//! moved in, so that encoder tracking can correct for the stage's own errors.
//!
//! Each term has one source, recorded in the map:
//! - **long-wavelength positioning** (the length reference): the encoder's calibration
//!   certificate ([`certificate`], CSV, format in that module), never PSD2, whose gain is known
//!   to ~6e-5 only (60 µm over a metre of stitched steps);
//! - **screw-periodic term and reversal**: the stop-and-go self-calibration, which sees them
//!   well in PSD2's along-axis jump at each handover. The fit carries a smooth long-wavelength
//!   nuisance (Legendre polynomials over the travel) that absorbs PSD2's gain and the long
//!   shape, so neither sets the scale; the certificate's rows have the fitted periodic term
//!   and reversal taken out before they are interpolated (a 10 mm certificate aliases a 5 mm
//!   lead);
//! - **vertical straightness** (the roll channel): the stop-and-go self-calibration alone. At
//!   each handover the carriage rests and the spot is fixed in space, so PSD2's vertical jump
//!   (the difference of means taken just before and just after the step: beam drift over a
//!   second does not enter) is the follower's vertical step. Every step of every pass is an
//!   observation of `v(to) − v(from)` plus a slope times its length; a weighted least-squares
//!   solution over the visited positions gives the map and its standard uncertainty per
//!   point (a random walk tied down at both ends, shrunk by the number of passes). The map is
//!   the straightness relative to the end-point line over the calibrated travel: the line —
//!   the follower's inclination to PSD2's u axis — reads the same at a handover as PSD2's
//!   in-plane tilt, which the head's model already carries, so no handover can measure it.
//!   A level on the carriage gives what the steps cannot: read beside the head's roll at
//!   stations along the travel (`LevelStation`, every 100 mm or so), each station is the
//!   follower's true vertical there up to one common constant. Fitted together with the
//!   steps ([`build_referenced`]), the stations fix the line and pin the steps' random walk
//!   between them: over 2 m the vertical's u falls from about 0.25 µm mid-travel (steps and
//!   a line from the two ends) to under 0.1 µm.
//!
//! Sans-I/O: [`build`] takes the steps (from the tracker's handover records or the lab) and an
//! optional certificate and returns the map; [`FollowerMap::correction`] is what the tracker
//! applies; [`FollowerMap::point`] gives, per position and PSD2 axis, the correction, its
//! standard uncertainty and its source (for uncertainty budgets and reports).

pub mod certificate;
mod fit;
pub mod level;
pub mod reuse;
pub mod selfcal;
mod stored;

pub use certificate::{Certificate, CertificateError, CertificatePoint};
pub use reuse::{Reuse, ReuseError, ReuseSettings};
pub use stored::{STEP_COLUMNS, StoredMap, StoredSteps};

use crate::track::{HandoverKind, HandoverRecord, StageCorrection};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The direction the follower last moved in (as a direction of approach).
pub use crate::run::Direction;

/// Where a term of the map comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    /// The encoder's calibration certificate.
    Certificate,
    /// The stop-and-go self-calibration (PSD2 at each handover).
    SelfCalibration,
    /// Not mapped: the term is taken as zero.
    None,
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Source::Certificate => "certificate",
            Source::SelfCalibration => "self-calibration",
            Source::None => "not mapped",
        })
    }
}

/// Which source each term came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Sources {
    pub long: Source,
    pub periodic: Source,
    pub reversal: Source,
    pub vertical: Source,
}

/// Why a map could not be built or read.
#[derive(Debug, Error)]
pub enum MapError {
    #[error(transparent)]
    Certificate(#[from] CertificateError),
    #[error(
        "the self-calibration has {found} usable steps; it needs at least {needed} over the follower's travel"
    )]
    TooFewSteps { found: usize, needed: usize },
    #[error("the self-calibration's {what} fit is singular: {hint}")]
    Singular { what: &'static str, hint: String },
    #[error("neither a certificate nor a self-calibration: nothing to map")]
    Empty,
    #[error("{file}: {problem}")]
    File { file: String, problem: String },
}

/// One follower step seen at a handover with the carriage at rest: the encoder before and
/// after (mm) and PSD2's displacement measured optically (mm: along, vertical) with its
/// variance (mm²).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Step {
    pub from_mm: f64,
    pub to_mm: f64,
    pub along_mm: f64,
    pub vertical_mm: f64,
    pub variance: [f64; 2],
}

impl Step {
    /// An optical (overlap) handover as a step; encoder-kind ones measure nothing.
    pub fn from_record(r: &HandoverRecord) -> Option<Step> {
        (r.kind == HandoverKind::Overlap && r.encoder_after != r.encoder_before).then_some(Step {
            from_mm: r.encoder_before,
            to_mm: r.encoder_after,
            along_mm: r.delta[0],
            vertical_mm: r.delta[1],
            variance: r.variance,
        })
    }

    fn direction(&self) -> Direction {
        if self.to_mm >= self.from_mm {
            Direction::Up
        } else {
            Direction::Down
        }
    }
}

/// Settings of the map's fit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapSettings {
    /// The follower's screw lead (mm): the period of its periodic error.
    pub lead_mm: f64,
    /// Degree of the long-wavelength nuisance in the along-axis fit.
    pub long_degree: usize,
    /// Visited positions closer than this are one point of the vertical map (mm).
    pub merge_mm: f64,
}

impl Default for MapSettings {
    fn default() -> Self {
        MapSettings {
            lead_mm: 5.0,
            long_degree: 12,
            merge_mm: 0.5,
        }
    }
}

/// The screw-periodic term `sin·sin(2πx/lead) + cos·cos(2πx/lead)` (mm) and its covariance.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Periodic {
    pub lead_mm: f64,
    pub sin_mm: f64,
    pub cos_mm: f64,
    /// Covariance of (sin, cos) (mm²).
    pub cov_mm2: [[f64; 2]; 2],
}

impl Periodic {
    fn basis(&self, x: f64) -> [f64; 2] {
        let a = 2.0 * std::f64::consts::PI * x / self.lead_mm;
        [a.sin(), a.cos()]
    }

    /// The term at `x` (mm) and its standard uncertainty.
    pub fn at(&self, x: f64) -> (f64, f64) {
        let b = self.basis(x);
        let c = self.cov_mm2;
        let var = b[0] * b[0] * c[0][0] + 2.0 * b[0] * b[1] * c[0][1] + b[1] * b[1] * c[1][1];
        (self.sin_mm * b[0] + self.cos_mm * b[1], var.max(0.0).sqrt())
    }

    /// The variance of the term's difference between `a` and `b` (mm²): its coefficients'
    /// errors are the same at both.
    pub fn difference_variance(&self, a: f64, b: f64) -> f64 {
        let (ba, bb) = (self.basis(a), self.basis(b));
        let d = [ba[0] - bb[0], ba[1] - bb[1]];
        let c = self.cov_mm2;
        (d[0] * d[0] * c[0][0] + 2.0 * d[0] * d[1] * c[0][1] + d[1] * d[1] * c[1][1]).max(0.0)
    }

    /// Its amplitude (mm).
    pub fn amplitude(&self) -> f64 {
        self.sin_mm.hypot(self.cos_mm)
    }
}

/// A value and its standard uncertainty (mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value_mm: f64,
    pub u_mm: f64,
}

/// What the self-calibration was.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelfCalibration {
    pub steps: usize,
    /// Direction changes seen (each measures the reversal).
    pub reversals: usize,
    /// Reduced χ² of the along-axis and vertical fits (their uncertainties are scaled up by
    /// its root when it exceeds 1).
    pub chi2_along: f64,
    pub chi2_vertical: f64,
    /// Machine time the passes took (s), when known.
    pub machine_time_s: Option<f64>,
    /// The along-axis steps' stated standard deviation, their RMS (mm); zero in a map stored
    /// before it was kept.
    #[serde(default)]
    pub step_sd_along_mm: f64,
}

impl SelfCalibration {
    /// What the stage repeats to along its axis beyond its map (mm, standard deviation), as
    /// its self-calibration saw it; `None` when the steps' noise was not kept. A step is the
    /// difference of two positions, each off its map by σ, on top of its stated noise s:
    /// its residuals scatter as s² + 2σ², so σ² = (χ²_red − 1)·s²/2, with χ²_red taken at
    /// its upper 95 % bound for the steps there were (+2·√(2/steps)): a fit that agrees with
    /// its noise still cannot rule out that much.
    ///
    /// Along only: the vertical steps' χ² does not see what the vertical map misses (a storm
    /// on seed 12 read roll up to 0.56″ off the truth, 0.4 µm of the follower's vertical, where
    /// the map stated at most 0.07 µm and its χ² 0.95), so the vertical keeps its stated figure.
    pub fn unmapped_sd_mm(&self) -> Option<f64> {
        let s = self.step_sd_along_mm;
        if self.steps == 0 || !(s > 0.0 && s.is_finite()) {
            return None;
        }
        let bound = 2.0 * (2.0 / self.steps as f64).sqrt();
        Some(((self.chi2_along + bound - 1.0).max(0.0) * s * s / 2.0).sqrt())
    }
}

/// The variance of a tabulated curve's difference between `a` and `b`, its points' errors
/// independent with standard uncertainties `u` (mm²): what the two share of a point cancels.
fn difference_of_points(positions: &[f64], u: &[f64], a: f64, b: f64) -> f64 {
    let n = positions.len().min(u.len());
    if n == 0 {
        return 0.0;
    }
    let mut w = std::collections::BTreeMap::new();
    for (i, x) in fit::weights(&positions[..n], a) {
        *w.entry(i).or_insert(0.0) += x;
    }
    for (i, x) in fit::weights(&positions[..n], b) {
        *w.entry(i).or_insert(0.0) -= x;
    }
    w.iter().map(|(&i, x)| x * x * u[i] * u[i]).sum()
}

/// The follower's error map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FollowerMap {
    pub sources: Sources,
    /// The certificate's file name, when one was imported.
    pub certificate_name: Option<String>,
    pub self_calibration: Option<SelfCalibration>,
    /// Long-wavelength along-axis error per direction (mm) at `long_positions_mm`, with its
    /// standard uncertainty: the certificate with the periodic term and the reversal out.
    pub long_positions_mm: Vec<f64>,
    pub long_up_mm: Vec<f64>,
    pub long_down_mm: Vec<f64>,
    pub long_u_mm: Vec<f64>,
    pub periodic: Option<Periodic>,
    /// Reversal: PSD2's position after a down move minus after an up move, at the same
    /// encoder position (mm).
    pub reversal: Option<Estimate>,
    /// The certificate's own mean reversal (mm), a cross-check of the self-calibration's.
    pub certificate_reversal_mm: Option<f64>,
    /// Vertical straightness (mm, PSD2 above the end-point line) at `vertical_positions_mm`,
    /// zero at both ends, with its standard uncertainty; with a level's stations
    /// (`vertical_reference`), PSD2's whole vertical relative to the first position.
    pub vertical_positions_mm: Vec<f64>,
    pub vertical_mm: Vec<f64>,
    pub vertical_u_mm: Vec<f64>,
    /// PSD2's vertical jump per mm of follower step the end-point line took (mm/mm): PSD2's
    /// in-plane tilt and the follower's inclination together (not applied).
    pub vertical_slope: f64,
    /// The vertical map's line from an outside reference (the self-calibration cannot see
    /// it): applied on top of the straightness, with its uncertainty. `None`: the vertical
    /// map is relative to its end-point line, and the line is an unmapped error.
    #[serde(default)]
    pub vertical_line: Option<VerticalLine>,
    /// A level's stations the vertical map was fitted with (its line and shape, not only the
    /// steps'): then `vertical_mm` is the whole vertical and no line is added.
    #[serde(default)]
    pub vertical_reference: Option<VerticalReference>,
    /// The instrument's stored map re-used on this set-up: what its check found (the bend
    /// is in the vertical, its uncertainty in the vertical's).
    #[serde(default)]
    pub reuse: Option<Reuse>,
}

/// One station of a level along the follower's travel: the follower's true vertical there
/// (mm) up to a constant common to all stations — the head's roll read beside a level's,
/// turned into PSD2's vertical — and its variance (mm²).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelStation {
    /// The follower's encoder position at the station (mm).
    pub position_mm: f64,
    pub value_mm: f64,
    pub variance_mm2: f64,
}

/// The level's stations a vertical map was fitted with, and what they were.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VerticalReference {
    pub stations: Vec<LevelStation>,
    /// The instrument and how it was read.
    pub source: String,
}

/// The follower's vertical line (its inclination to the head's model of its axis) from an
/// outside reference: `slope·(x − origin)` is added to the vertical map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VerticalLine {
    /// Encoder position where the line is zero (the vertical map's first point, mm).
    pub origin_mm: f64,
    /// The line's slope (mm/mm) and its standard uncertainty.
    pub slope: f64,
    pub u_slope: f64,
    /// Where it came from (the instrument and what it read).
    pub source: String,
}

/// The map at one position and direction, per PSD2 axis: the correction (PSD2's true position
/// minus the encoder's, µm), its standard uncertainty (µm) and its source.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MapPoint {
    pub position_mm: f64,
    pub direction: Direction,
    pub along_um: f64,
    pub along_u_um: f64,
    /// The along-axis source: the certificate when it gave the long-wavelength shape (the
    /// periodic term and reversal from the self-calibration are in `sources`).
    pub along_source: Source,
    pub vertical_um: f64,
    pub vertical_u_um: f64,
    pub vertical_source: Source,
}

/// What the tracker applies: the map's own [`FollowerMap::correction`] and
/// [`FollowerMap::difference_variance`].
impl StageCorrection for FollowerMap {
    fn correction(&self, x: f64, dir: Direction) -> [f64; 2] {
        FollowerMap::correction(self, x, dir)
    }

    fn difference_variance(&self, a: f64, b: f64, dir_a: Direction, dir_b: Direction) -> [f64; 2] {
        FollowerMap::difference_variance(self, a, b, dir_a, dir_b)
    }

    fn unmapped_sd(&self) -> Option<f64> {
        self.self_calibration
            .as_ref()
            .and_then(SelfCalibration::unmapped_sd_mm)
    }
}

impl FollowerMap {
    /// PSD2's true position minus the encoder's (mm: along the follower's axis, vertical) at
    /// encoder position `x` after a motion in `dir`. Only differences between two positions
    /// mean anything (the tracker uses them so).
    pub fn correction(&self, x: f64, dir: Direction) -> [f64; 2] {
        let p = self.point_mm(x, dir);
        [p.0, p.2]
    }

    /// (along, u along, vertical, u vertical) in mm.
    fn point_mm(&self, x: f64, dir: Direction) -> (f64, f64, f64, f64) {
        let interp = |v: &[f64]| crate::util::interpolate(&self.long_positions_mm, v, x);
        let (mut along, mut var) = (0.0, 0.0);
        if !self.long_positions_mm.is_empty() {
            along += interp(match dir {
                Direction::Up => &self.long_up_mm,
                Direction::Down => &self.long_down_mm,
            });
            var += interp(&self.long_u_mm).powi(2);
        }
        if let Some(p) = &self.periodic {
            let (v, u) = p.at(x);
            along += v;
            var += u * u;
        }
        if let Some(r) = &self.reversal {
            along += match dir {
                Direction::Up => -r.value_mm / 2.0,
                Direction::Down => r.value_mm / 2.0,
            };
            var += (r.u_mm / 2.0).powi(2);
        }
        let vp = &self.vertical_positions_mm;
        let (mut v, mut vu) = if vp.is_empty() {
            (0.0, 0.0)
        } else {
            (
                crate::util::interpolate(vp, &self.vertical_mm, x),
                crate::util::interpolate(vp, &self.vertical_u_mm, x),
            )
        };
        if let (Some(l), None) = (&self.vertical_line, &self.vertical_reference) {
            v += l.slope * (x - l.origin_mm);
            vu = vu.hypot(l.u_slope * (x - l.origin_mm));
        }
        (along, var.sqrt(), v, vu)
    }

    /// The coverage factor of the vertical map as a whole: every point within this many of
    /// its standard uncertainties at once, at 95 % (`util::simultaneous_k` over the points
    /// whose u is stated; `None` without a vertical map). A k = 2 interval holds one point at
    /// 95 %; a curve of a few hundred correlated points needs about 3.7 to hold them all.
    pub fn vertical_band_k(&self) -> Option<f64> {
        let n = self.vertical_u_mm.iter().filter(|&&u| u > 0.0).count();
        (n > 0).then(|| crate::util::simultaneous_k(n, 0.95))
    }

    /// The map at encoder position `x` (mm) after a motion in `dir`, in µm, with each PSD2
    /// axis' standard uncertainty and source.
    pub fn point(&self, x: f64, dir: Direction) -> MapPoint {
        let (a, au, v, vu) = self.point_mm(x, dir);
        MapPoint {
            position_mm: x,
            direction: dir,
            along_um: a * 1e3,
            along_u_um: au * 1e3,
            along_source: if self.sources.long != Source::None {
                self.sources.long
            } else {
                self.sources.periodic
            },
            vertical_um: v * 1e3,
            vertical_u_um: vu * 1e3,
            vertical_source: self.sources.vertical,
        }
    }

    /// What the map is made of, in words, for the budget's follower terms: "long-wavelength
    /// positioning from the certificate, …, its line and shape referenced by 12 level
    /// stations; the instrument's map re-used on this set-up (its bend: the bend's own term)".
    pub fn describe_sources(&self) -> String {
        let s = &self.sources;
        let mut out = format!(
            "long-wavelength positioning from the {}, screw-periodic and reversal from the {}, vertical straightness from the {}",
            s.long, s.periodic, s.vertical
        );
        match (&self.vertical_reference, &self.vertical_line) {
            (Some(r), _) => out.push_str(&format!(
                ", its line and shape referenced by {} level stations",
                r.stations.len()
            )),
            (None, Some(l)) => out.push_str(&format!(
                ", its line from a level ({:+.2} ± {:.2} µm/m)",
                l.slope * 1e6,
                l.u_slope * 1e6
            )),
            (None, None) => out.push_str(", its line not referenced"),
        }
        if self.reuse.is_some() {
            out.push_str(
                "; the instrument's map re-used on this set-up (its bend: the bend's own term)",
            );
        }
        out
    }

    /// The standard uncertainty (mm) this set-up's bend adds to the vertical at encoder
    /// position `x` (already inside [`FollowerMap::point`]'s vertical u): zero for a map made
    /// on this set-up, or one kept before the bend's u was stored per position.
    pub fn bend_u_mm(&self, x: f64) -> f64 {
        match &self.reuse {
            Some(r) if r.bend_u_mm.len() == self.vertical_positions_mm.len() => {
                crate::util::interpolate(&self.vertical_positions_mm, &r.bend_u_mm, x)
            }
            _ => 0.0,
        }
    }

    /// Variance (mm²: along, vertical) of the correction's difference between encoder
    /// positions `a` and `b`. Each tabulated curve (the long-wavelength term, the vertical)
    /// as points with independent errors, interpolated linearly: what two positions share of
    /// a point cancels, so a position against itself differs by nothing and two far apart by
    /// both their variances (for the vertical a bound: its random walk makes neighbours'
    /// errors alike). The screw-periodic term through its coefficients' covariance, a
    /// referenced line through its slope's, the reversal only between two directions.
    pub fn difference_variance(
        &self,
        a: f64,
        b: f64,
        dir_a: Direction,
        dir_b: Direction,
    ) -> [f64; 2] {
        let mut along = difference_of_points(&self.long_positions_mm, &self.long_u_mm, a, b);
        if let Some(p) = &self.periodic {
            along += p.difference_variance(a, b);
        }
        if let Some(r) = &self.reversal
            && dir_a != dir_b
        {
            along += r.u_mm * r.u_mm;
        }
        let mut vertical =
            difference_of_points(&self.vertical_positions_mm, &self.vertical_u_mm, a, b);
        if let (Some(l), None) = (&self.vertical_line, &self.vertical_reference) {
            vertical += (l.u_slope * (b - a)).powi(2);
        }
        [along, vertical]
    }

    /// The span of encoder positions the map covers (mm).
    pub fn span(&self) -> (f64, f64) {
        let all = self
            .long_positions_mm
            .iter()
            .chain(&self.vertical_positions_mm)
            .copied();
        all.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        })
    }

    /// The map as TOML (every term; reads back with [`FollowerMap::from_toml`]).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# the map could not be written: {e}\n"))
    }

    /// Read a map written by [`FollowerMap::to_toml`]; `file` names it in errors.
    pub fn from_toml(text: &str, file: &str) -> Result<FollowerMap, MapError> {
        toml::from_str(text).map_err(|e| MapError::File {
            file: file.to_string(),
            problem: format!("not a follower map: {}", e.message()),
        })
    }

    /// The map as CSV every `step_mm` over its span: position, then per direction the
    /// along-axis correction, and the vertical, each with its standard uncertainty (µm).
    pub fn to_csv(&self, step_mm: f64) -> String {
        let mut out = String::from(
            "position_mm,along_up_um,along_down_um,along_u_um,vertical_um,vertical_u_um\n",
        );
        let (lo, hi) = self.span();
        if !(lo.is_finite() && hi.is_finite() && step_mm > 0.0) {
            return out;
        }
        let n = ((hi - lo) / step_mm).floor() as usize;
        for k in 0..=n {
            let x = lo + k as f64 * step_mm;
            let up = self.point(x, Direction::Up);
            let down = self.point(x, Direction::Down);
            out.push_str(&format!(
                "{x:.3},{:.3},{:.3},{:.3},{:.3},{:.3}\n",
                up.along_um,
                down.along_um,
                up.along_u_um.max(down.along_u_um),
                up.vertical_um,
                up.vertical_u_um
            ));
        }
        out
    }

    /// A few lines for people: each term, its source and size.
    pub fn summary(&self) -> Vec<String> {
        let mut out = Vec::new();
        let (lo, hi) = self.span();
        out.push(format!("span {lo:.1} to {hi:.1} mm"));
        let range = |v: &[f64]| {
            let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            (hi - lo) * 1e3
        };
        let max_u = |v: &[f64]| v.iter().copied().fold(0.0, f64::max) * 1e3;
        match &self.certificate_name {
            Some(n) if !self.long_positions_mm.is_empty() => out.push(format!(
                "long-wavelength positioning: {:.2} µm range, u ≤ {:.2} µm, from the certificate {n}",
                range(&self.long_up_mm),
                max_u(&self.long_u_mm)
            )),
            _ => out.push("long-wavelength positioning: not mapped (import a certificate)".into()),
        }
        match &self.periodic {
            Some(p) => out.push(format!(
                "screw-periodic ({:.2} mm lead): {:.3} µm amplitude, u {:.3} µm, from the self-calibration",
                p.lead_mm,
                p.amplitude() * 1e3,
                p.cov_mm2[0][0].max(p.cov_mm2[1][1]).sqrt() * 1e3
            )),
            None => out.push("screw-periodic: not mapped".into()),
        }
        match (&self.reversal, self.certificate_reversal_mm) {
            (Some(r), c) => out.push(format!(
                "reversal: {:.3} µm, u {:.3} µm, from the self-calibration{}",
                r.value_mm * 1e3,
                r.u_mm * 1e3,
                c.map(|c| format!(" (the certificate says {:.3} µm)", c * 1e3))
                    .unwrap_or_default()
            )),
            (None, Some(c)) => {
                out.push(format!("reversal: {:.3} µm, from the certificate", c * 1e3))
            }
            (None, None) => out.push("reversal: not mapped".into()),
        }
        let band = self
            .vertical_band_k()
            .map(|k| format!(" (the whole curve within {k:.2} u at once, 95 %)"))
            .unwrap_or_default();
        if self.vertical_mm.is_empty() {
            out.push("vertical straightness: not mapped (run the self-calibration)".into());
        } else if let Some(r) = &self.vertical_reference {
            out.push(format!(
                "vertical (to the first point): {:.2} µm range over {} points, u ≤ {:.2} µm{band}, from the self-calibration's steps and {} level stations ({})",
                range(&self.vertical_mm),
                self.vertical_mm.len(),
                max_u(&self.vertical_u_mm),
                r.stations.len(),
                r.source
            ));
        } else {
            out.push(format!(
                "vertical straightness (to the end-point line): {:.2} µm range over {} points, u ≤ {:.2} µm{band}, from the self-calibration; PSD2's jump took a line of {:.1} µm/m (PSD2's tilt and the follower's inclination), not applied",
                range(&self.vertical_mm),
                self.vertical_mm.len(),
                max_u(&self.vertical_u_mm),
                self.vertical_slope * 1e6
            ));
        }
        if let (Some(l), None) = (&self.vertical_line, &self.vertical_reference) {
            out.push(format!(
                "vertical line: {:+.2} µm/m, u {:.2} µm/m, from {}",
                l.slope * 1e6,
                l.u_slope * 1e6,
                l.source
            ));
        }
        if let Some(r) = &self.reuse {
            out.push(r.describe());
        }
        if let Some(s) = &self.self_calibration {
            out.push(format!(
                "self-calibration: {} steps, {} reversals, reduced χ² {:.2} along, {:.2} vertical{}",
                s.steps,
                s.reversals,
                s.chi2_along,
                s.chi2_vertical,
                s.machine_time_s
                    .map(|t| if self.reuse.is_some() {
                        format!(", {:.1} min on the set-up it was made on (not this one)", t / 60.0)
                    } else {
                        format!(", {:.1} min of machine time", t / 60.0)
                    })
                    .unwrap_or_default()
            ));
        }
        out
    }
}

/// Build the map from the self-calibration's `steps` (in the order taken; may be empty) and
/// the encoder's `certificate` (may be absent); at least one of them.
pub fn build(
    steps: &[Step],
    certificate: Option<&Certificate>,
    settings: &MapSettings,
) -> Result<FollowerMap, MapError> {
    build_referenced(steps, certificate, settings, None)
}

/// [`build`] with a level's stations (at least two) for the vertical map: its line and shape
/// from the stations and the steps together (see `fit`).
pub fn build_referenced(
    steps: &[Step],
    certificate: Option<&Certificate>,
    settings: &MapSettings,
    reference: Option<&VerticalReference>,
) -> Result<FollowerMap, MapError> {
    if steps.is_empty() && certificate.is_none() {
        return Err(MapError::Empty);
    }
    let along = if steps.is_empty() {
        None
    } else {
        Some(fit::along(steps, settings)?)
    };
    let vertical = if steps.is_empty() {
        None
    } else {
        let stations = reference.map_or(&[][..], |r| &r.stations[..]);
        Some(fit::vertical(steps, stations, settings)?)
    };
    let periodic = along.as_ref().map(|a| a.periodic);
    let reversal = along.as_ref().and_then(|a| a.reversal);
    let mut map = FollowerMap {
        sources: Sources {
            long: if certificate.is_some() {
                Source::Certificate
            } else {
                Source::None
            },
            periodic: if periodic.is_some() {
                Source::SelfCalibration
            } else {
                Source::None
            },
            reversal: match (reversal, certificate) {
                (Some(_), _) => Source::SelfCalibration,
                (None, Some(c)) if c.bidirectional() => Source::Certificate,
                _ => Source::None,
            },
            vertical: if vertical.is_some() {
                Source::SelfCalibration
            } else {
                Source::None
            },
        },
        certificate_name: certificate.map(|c| c.name.clone()),
        self_calibration: along
            .as_ref()
            .zip(vertical.as_ref())
            .map(|(a, v)| SelfCalibration {
                steps: steps.len(),
                reversals: a.reversals,
                chi2_along: a.chi2,
                chi2_vertical: v.chi2,
                machine_time_s: None,
                step_sd_along_mm: (steps.iter().map(|s| s.variance[0]).sum::<f64>()
                    / steps.len() as f64)
                    .sqrt(),
            }),
        long_positions_mm: Vec::new(),
        long_up_mm: Vec::new(),
        long_down_mm: Vec::new(),
        long_u_mm: Vec::new(),
        periodic,
        reversal,
        certificate_reversal_mm: None,
        vertical_positions_mm: Vec::new(),
        vertical_mm: Vec::new(),
        vertical_u_mm: Vec::new(),
        vertical_slope: 0.0,
        vertical_line: None,
        vertical_reference: reference
            .filter(|r| r.stations.len() >= 2 && !steps.is_empty())
            .cloned(),
        reuse: None,
    };
    if let Some(v) = vertical {
        map.vertical_positions_mm = v.positions;
        map.vertical_mm = v.values;
        map.vertical_u_mm = v.u;
        map.vertical_slope = v.slope;
    }
    if let Some(c) = certificate {
        apply_certificate(&mut map, c);
    }
    Ok(map)
}

/// Put the certificate's long-wavelength shape into `map` (its periodic term and reversal,
/// when the self-calibration gave them, taken out first: `correction` adds them), with the
/// certificate's own mean reversal as a cross-check.
fn apply_certificate(map: &mut FollowerMap, c: &Certificate) {
    let (periodic, reversal) = (map.periodic, map.reversal);
    map.long_positions_mm.clear();
    map.long_up_mm.clear();
    map.long_down_mm.clear();
    map.long_u_mm.clear();
    map.certificate_reversal_mm = None;
    let mut xs: Vec<f64> = c.up.iter().chain(&c.down).map(|p| p.position_mm).collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup();
    if c.bidirectional() {
        let revs: Vec<f64> = xs
            .iter()
            .map(|&x| c.at(x, Direction::Down).0 - c.at(x, Direction::Up).0)
            .collect();
        map.certificate_reversal_mm = Some(revs.iter().sum::<f64>() / revs.len() as f64);
    }
    for &x in &xs {
        let per = periodic.map_or(0.0, |p| p.at(x).0);
        let (eu, uu) = c.at(x, Direction::Up);
        let (ed, ud) = c.at(x, Direction::Down);
        let (up, down, u) = match reversal {
            // The self-calibration's reversal applies (`correction` adds it): the long
            // shape is the mean of the two directions with the reversal out.
            Some(r) => {
                let half = r.value_mm / 2.0;
                let (long, u) = if c.bidirectional() {
                    (((eu + half) + (ed - half)) / 2.0, uu.hypot(ud) / 2.0)
                } else if c.up.is_empty() {
                    (ed - half, ud)
                } else {
                    (eu + half, uu)
                };
                (long - per, long - per, u)
            }
            None => (eu - per, ed - per, uu.max(ud)),
        };
        map.long_positions_mm.push(x);
        map.long_up_mm.push(up);
        map.long_down_mm.push(down);
        map.long_u_mm.push(u);
    }
}

impl FollowerMap {
    /// This map with `certificate` as its length reference: the long-wavelength shape from
    /// the certificate (replacing any the map had), the self-calibration's terms (periodic,
    /// reversal, vertical, its line) kept. How a certificate imported after a
    /// self-calibration joins it (the steps are not kept, the fitted terms are).
    pub fn with_certificate(&self, certificate: &Certificate) -> FollowerMap {
        let mut map = self.clone();
        map.sources.long = Source::Certificate;
        map.sources.reversal = match (map.reversal, certificate.bidirectional()) {
            (Some(_), _) => Source::SelfCalibration,
            (None, true) => Source::Certificate,
            (None, false) => Source::None,
        };
        map.certificate_name = Some(certificate.name.clone());
        apply_certificate(&mut map, certificate);
        map
    }
}

/// A map as the store keeps it with the certificate it was built from (see
/// [`StoredMap`], which also keeps the self-calibration's steps).
pub fn stored_toml(map: &FollowerMap, certificate: Option<&Certificate>) -> String {
    StoredMap {
        map: map.clone(),
        certificate: certificate.cloned(),
        steps: None,
    }
    .to_toml()
}

/// Read a map written by [`stored_toml`] (or [`StoredMap::to_toml`], or
/// [`FollowerMap::to_toml`]): the map and its certificate, when it has one. `file` names it
/// in errors.
pub fn from_stored_toml(
    text: &str,
    file: &str,
) -> Result<(FollowerMap, Option<Certificate>), MapError> {
    StoredMap::from_toml(text, file).map(|s| (s.map, s.certificate))
}

#[cfg(test)]
mod tests;
