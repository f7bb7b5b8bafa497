//! The uncertainty budget of a measured axis, per ISO/TR 230-9: for every DOF and every point
//! (target and approach direction, and the bidirectional mean) each contributor's standard
//! uncertainty as its own named term, combined in quadrature (the contributors are taken as
//! uncorrelated with one another), expanded with a coverage factor k = 2:
//!
//! `u_c = √(Σ u_i²)`, `U = k·u_c`, k = 2 (about 95 % coverage for a near-normal combination).
//!
//! The terms (standard uncertainties, internal units; L = |P − P_ref| is the distance from the
//! zero reference, where the head was zeroed and every term that grows with travel is zero):
//!
//! | term | formula | from |
//! |---|---|---|
//! | PSD noise | `√(Σ_j sd_j²/f_j) / n` | each capture's frame scatter sd over its f frames, n runs |
//! | repeatability | `s/√n` | the run-to-run scatter s (ISO 230-2's s) of the n runs |
//! | calibration | `u_cal` per DOF | the calibration record: `√(max(0, h² − b²) + √(2/N)·b²)`, h the hold-out RMS over N poses, each the mean of many frames (a bench's dwell), b the Cramér–Rao bound of such a mean: what the fit adds beyond noise, and what N poses cannot rule out |
//! | follower map | `√((S_x·u_along)² + (S_y·u_vert)²)` | the follower's own errors at the point ([`FollowerInput`]), through PSD2's sensitivities S |
//! | follower map, this set-up's bend | `S_y·u_bend` | an instrument's stored map re-used on this set-up: the bend the rail takes from this machine's bed, fitted to a level's stations here (`follower::reuse`); zero for a map made on this set-up, whose vertical holds it |
//! | stitching | `√(mean_j(S_x²·v_x,j + S_y²·v_y,j))` | the overlap handovers' accumulated variance v at each capture (a random walk) |
//! | misalignment | `L·(1 − cos φ)/√12` (dy only) | φ the beam's angle to the travel, from the measured straightness slopes: the cosine error lies between 0 and L(1 − cos φ) (rectangular) |
//! | thermal, temperature | `α·u(T)·L` (dy only) | the material temperature sensor's standard uncertainty u(T) |
//! | thermal, coefficient | `u(α)·|ΔT|·L` (dy only) | the expansion coefficient's uncertainty and the mean departure ΔT from 20 °C |
//! | environmental variation | `E_VE/(2√3)` | the drift check (ISO 230-2: the head reading the carriage at rest for the test's duration), E_VE its range, rectangular |
//!
//! The PSD noise is also in the repeatability (the scatter of the runs contains the noise of
//! each run's mean): both are kept, on the safe side, and the noise term is small (frames are
//! averaged). Instrument terms that repeat in every run (calibration, follower, stitching) are
//! taken as fully correlated over the runs: they do not shrink with n. For the bidirectional
//! mean they are the mean of the two directions' terms, and the scatter terms combine as
//! `√(s↑²/n + s↓²/n)/2`.

use super::AxisEvaluation;
use crate::run::{Capture, Direction};
use crate::track::{HandoverKind, HandoverRecord};
use crate::units::{DOF_NAMES, DOF_TO_USER, DOF_UNITS};
use serde::Serialize;
use std::collections::BTreeMap;

/// The coverage factor of every expanded uncertainty here.
pub const K: f64 = 2.0;

/// The contributors, in the order of every `terms` array.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Component {
    Noise,
    Repeatability,
    Calibration,
    Follower,
    Bend,
    Stitching,
    Misalignment,
    ThermalTemperature,
    ThermalCoefficient,
    Environment,
}

/// How many components.
pub const COMPONENTS: usize = 10;

impl Component {
    pub const ALL: [Component; COMPONENTS] = [
        Component::Noise,
        Component::Repeatability,
        Component::Calibration,
        Component::Follower,
        Component::Bend,
        Component::Stitching,
        Component::Misalignment,
        Component::ThermalTemperature,
        Component::ThermalCoefficient,
        Component::Environment,
    ];

    /// Index in `terms` arrays.
    pub fn index(self) -> usize {
        self as usize
    }

    /// What a user reads.
    pub fn name(self) -> &'static str {
        match self {
            Component::Noise => "PSD noise",
            Component::Repeatability => "repeatability",
            Component::Calibration => "calibration",
            Component::Follower => "follower map",
            Component::Bend => "follower map, this set-up's bend",
            Component::Stitching => "stitching",
            Component::Misalignment => "misalignment",
            Component::ThermalTemperature => "thermal, temperature",
            Component::ThermalCoefficient => "thermal, coefficient",
            Component::Environment => "environmental variation",
        }
    }

    /// Its formula, as the report states it.
    pub fn formula(self) -> &'static str {
        match self {
            Component::Noise => "√(Σ sd²/frames)/n",
            Component::Repeatability => "s/√n",
            Component::Calibration => "√(max(0, h² − b²) + √(2/N)·b²)",
            Component::Follower => "S·u(follower) at the point",
            Component::Bend => "S·u(bend) at the point",
            Component::Stitching => "S·√(Σ overlap handover variances)",
            Component::Misalignment => "L·(1 − cos φ)/√12",
            Component::ThermalTemperature => "α·u(T)·L",
            Component::ThermalCoefficient => "u(α)·|ΔT|·L",
            Component::Environment => "E_VE/(2√3)",
        }
    }
}

/// Standard uncertainties (mm) of the follower stage's own errors at one position: along its
/// axis (PSD2's X: positioning) and vertical (PSD2's Y: roll, 1.38″ per µm); and apart from
/// the vertical, what this set-up's bend adds to it (a re-used map's check).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FollowerU {
    pub along_mm: f64,
    pub vertical_mm: f64,
    pub bend_mm: f64,
}

/// What is known of the follower's own errors. A follower error map replaces the
/// specification with its per-position uncertainties.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub enum FollowerInput {
    /// Nothing stated: the term is zero and the budget says so.
    Unstated,
    /// The stage's specification: errors within ±`positioning_mm` along and
    /// ±`straightness_mm` vertically, anywhere (rectangular: u = a/√3).
    Specification {
        positioning_mm: f64,
        straightness_mm: f64,
    },
    /// A map's standard uncertainty per encoder position (linear between, held beyond the
    /// ends), with where it came from (certificate, self-calibration, date). `bend_mm`: the
    /// part of the vertical's that this set-up's bend adds, kept apart (empty: none, the map
    /// was made on this set-up).
    Map {
        source: String,
        positions_mm: Vec<f64>,
        along_mm: Vec<f64>,
        vertical_mm: Vec<f64>,
        bend_mm: Vec<f64>,
    },
}

impl FollowerInput {
    /// The standard uncertainties at encoder position `mm`.
    pub fn at(&self, mm: f64) -> FollowerU {
        match self {
            FollowerInput::Unstated => FollowerU::default(),
            FollowerInput::Specification {
                positioning_mm,
                straightness_mm,
            } => FollowerU {
                along_mm: positioning_mm.abs() / 3f64.sqrt(),
                vertical_mm: straightness_mm.abs() / 3f64.sqrt(),
                bend_mm: 0.0,
            },
            FollowerInput::Map {
                positions_mm,
                along_mm,
                vertical_mm,
                bend_mm,
                ..
            } => FollowerU {
                along_mm: crate::util::interpolate(positions_mm, along_mm, mm),
                vertical_mm: crate::util::interpolate(positions_mm, vertical_mm, mm),
                bend_mm: crate::util::interpolate(positions_mm, bend_mm, mm),
            },
        }
    }

    /// From a follower error map in use: its standard uncertainties every `step_mm` over its
    /// span, in carriage coordinates (the encoder reads `encoder_offset_mm` more than the
    /// carriage's nominal position), each combined in quadrature with the map's uncertainty
    /// at `reference_mm`: a measured error is relative to the zero reference, so it carries
    /// the map's error at the point and at the reference. The bend of a re-used map comes out
    /// of the vertical into `bend_mm` (in quadrature: the map's vertical u holds it so).
    pub fn of_map(
        map: &crate::follower::FollowerMap,
        encoder_offset_mm: f64,
        reference_mm: f64,
        step_mm: f64,
        source: String,
    ) -> FollowerInput {
        use crate::follower::Direction;
        let u = |x: f64| {
            let (up, down) = (map.point(x, Direction::Up), map.point(x, Direction::Down));
            let (vertical, bend) = (up.vertical_u_um * 1e-3, map.bend_u_mm(x));
            (
                up.along_u_um.max(down.along_u_um) * 1e-3,
                (vertical * vertical - bend * bend).max(0.0).sqrt(),
                bend,
            )
        };
        let (lo, hi) = map.span();
        if !(lo.is_finite() && hi.is_finite() && step_mm > 0.0) {
            return FollowerInput::Unstated;
        }
        let (ra, rv, rb) = u(reference_mm + encoder_offset_mm);
        let n = ((hi - lo) / step_mm).ceil() as usize;
        let (mut positions_mm, mut along_mm, mut vertical_mm) = (vec![], vec![], vec![]);
        let mut bend_mm = vec![];
        for k in 0..=n {
            let x = (lo + k as f64 * step_mm).min(hi);
            let (a, v, b) = u(x);
            positions_mm.push(x - encoder_offset_mm);
            along_mm.push(a.hypot(ra));
            vertical_mm.push(v.hypot(rv));
            bend_mm.push(b.hypot(rb));
        }
        if map.reuse.is_none() {
            bend_mm.clear();
        }
        FollowerInput::Map {
            source,
            positions_mm,
            along_mm,
            vertical_mm,
            bend_mm,
        }
    }

    /// Where the term comes from, for the report.
    pub fn describe(&self) -> String {
        match self {
            FollowerInput::Unstated => "not stated: no follower map or specification".into(),
            FollowerInput::Specification {
                positioning_mm,
                straightness_mm,
            } => format!(
                "the follower's specification, ±{:.1} µm positioning and ±{:.1} µm vertical straightness (rectangular, u = a/√3; no error map)",
                positioning_mm * 1e3,
                straightness_mm * 1e3
            ),
            FollowerInput::Map { source, .. } => format!("follower error map: {source}"),
        }
    }
}

/// The temperature terms' inputs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ThermalInput {
    /// Expansion coefficient of the axis' scale (1/K; steel 11.5e-6).
    pub alpha_per_k: f64,
    /// Its standard uncertainty (1/K).
    pub u_alpha_per_k: f64,
    /// Standard uncertainty of the material temperature measurement (K).
    pub u_temperature_k: f64,
    /// Mean material temperature minus 20 °C during the test (K).
    pub delta_t_k: f64,
}

/// Everything the budget needs beside the captures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BudgetInputs {
    /// Where the head was zeroed (mm): L is measured from here.
    pub reference_mm: f64,
    /// |∂e_k/∂X2| and |∂e_k/∂Y2| (internal units per mm of PSD2 reading), from β⁻¹
    /// ([`psd2_sensitivity`]).
    pub psd2_sensitivity: [[f64; 2]; 6],
    pub follower: FollowerInput,
    /// Per DOF (internal units), with where it came from; `None`: no calibration record.
    pub calibration: Option<([f64; 6], String)>,
    pub thermal: Option<ThermalInput>,
    /// The drift check's range E_VE per DOF (internal units); `None`: not done.
    pub drift_range: Option<[f64; 6]>,
}

/// One capture with the overlap-stitching variance it carried ([along, vertical], mm²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StitchedCapture {
    pub capture: Capture,
    pub overlap_var: [f64; 2],
}

/// Each capture's overlap-stitching variance: the sum of the overlap handovers before it
/// (`handovers` of its run, after the zero reference). Encoder handovers carry the follower's
/// own errors, which are the follower term's, not a random walk.
pub fn stitched(captures: &[Capture], handovers: &[HandoverRecord]) -> Vec<StitchedCapture> {
    captures
        .iter()
        .map(|c| {
            let mut v = [0.0; 2];
            for h in handovers
                .iter()
                .filter(|h| h.kind == HandoverKind::Overlap && h.unix_us <= c.unix_us)
            {
                v[0] += h.variance[0];
                v[1] += h.variance[1];
            }
            StitchedCapture {
                capture: *c,
                overlap_var: v,
            }
        })
        .collect()
}

/// PSD2's sensitivities from a decoupler at `travel` (follower at the same place): the square
/// roots of the diagonal of β⁻¹·diag(1 mm²)·β⁻ᵀ for X2 and for Y2.
pub fn psd2_sensitivity(
    decoupler: &crate::decouple::Decoupler,
    travel: f64,
) -> Result<[[f64; 2]; 6], crate::decouple::DecoupleError> {
    let x = decoupler.propagate(&[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], travel, travel)?;
    let y = decoupler.propagate(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], travel, travel)?;
    Ok(std::array::from_fn(|k| {
        [x[(k, k)].max(0.0).sqrt(), y[(k, k)].max(0.0).sqrt()]
    }))
}

/// One DOF's budget at one point.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PointBudget {
    pub dof: usize,
    pub target_index: u32,
    pub position_mm: f64,
    /// The approach direction, or `None` for the bidirectional mean.
    pub direction: Option<Direction>,
    /// Standard uncertainty of each component (internal units), in [`Component::ALL`] order.
    pub terms: [f64; COMPONENTS],
    /// Combined standard uncertainty and expanded uncertainty (k = 2).
    pub combined: f64,
    pub expanded: f64,
}

/// The budget of a measured axis.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Budget {
    pub k: f64,
    pub inputs: BudgetInputs,
    /// Per DOF, target and direction (up, down, mean).
    pub points: Vec<PointBudget>,
    /// Where a term comes from, in words, when the inputs alone cannot say it (a stored
    /// run's term "not recorded", a calibration's term "not stated" and why): replaces
    /// [`Budget::sources`]' own wording for that component.
    pub notes: Vec<(Component, String)>,
}

/// The calibration's standard uncertainty per DOF from its hold-out: `h` the hold-out RMS
/// error over `n` poses, `b` the Cramér–Rao bound of one such pose's reading (both per DOF,
/// any one unit per DOF). What the fit's error adds to the noise, `h² − b²`, and what `n`
/// poses cannot rule out (the mean of `n` squared errors is known to `√(2/n)·b²`):
/// `u² = max(0, h² − b²) + √(2/n)·b²`.
pub fn calibration_u(h: &[f64; 6], b: &[f64; 6], n: usize) -> [f64; 6] {
    let resolution = (2.0 / n.max(1) as f64).sqrt();
    std::array::from_fn(|k| {
        let b2 = b[k] * b[k];
        ((h[k] * h[k] - b2).max(0.0) + resolution * b2).sqrt()
    })
}

impl Budget {
    /// The point of `dof` at target `index` in `direction` (`None`: the mean).
    pub fn point(
        &self,
        dof: usize,
        index: u32,
        direction: Option<Direction>,
    ) -> Option<&PointBudget> {
        self.points
            .iter()
            .find(|p| p.dof == dof && p.target_index == index && p.direction == direction)
    }

    /// The largest value of each term and of U over one DOF's points.
    pub fn largest(&self, dof: usize) -> ([f64; COMPONENTS], f64, f64) {
        let mut terms = [0.0f64; COMPONENTS];
        let (mut uc, mut big) = (0.0f64, 0.0f64);
        for p in self.points.iter().filter(|p| p.dof == dof) {
            for (t, v) in terms.iter_mut().zip(p.terms) {
                *t = t.max(v);
            }
            uc = uc.max(p.combined);
            big = big.max(p.expanded);
        }
        (terms, uc, big)
    }

    /// The budget with `words` as the source of `component` (see [`Budget::notes`]).
    pub fn with_source(mut self, component: Component, words: String) -> Budget {
        self.notes.retain(|(c, _)| *c != component);
        self.notes.push((component, words));
        self
    }

    /// The words given for `component`'s source, if any.
    fn note(&self, component: Component) -> Option<&str> {
        self.notes
            .iter()
            .find(|(c, _)| *c == component)
            .map(|(_, w)| w.as_str())
    }

    /// Whether `component` was stated (false: its term is zero because nothing is known).
    pub fn stated(&self, component: Component) -> bool {
        let i = &self.inputs;
        match component {
            Component::Calibration => i.calibration.is_some(),
            Component::Follower | Component::Bend => i.follower != FollowerInput::Unstated,
            Component::ThermalTemperature | Component::ThermalCoefficient => i.thermal.is_some(),
            Component::Environment => i.drift_range.is_some(),
            _ => true,
        }
    }

    /// Where each term comes from (one line per component).
    pub fn sources(&self) -> [String; COMPONENTS] {
        let i = &self.inputs;
        Component::ALL.map(|c| match c {
            c if self.note(c).is_some() => self.note(c).unwrap_or_default().to_string(),
            Component::Noise => "each capture's frame scatter over its frames".into(),
            Component::Repeatability => "the runs' scatter s (ISO 230-2)".into(),
            Component::Calibration => match &i.calibration {
                Some((_, s)) => s.clone(),
                None => "not stated: no calibration record with the run".into(),
            },
            Component::Follower => i.follower.describe(),
            Component::Bend => match &i.follower {
                FollowerInput::Map { bend_mm, .. } if !bend_mm.is_empty() => {
                    "the bend this machine's bed gives the instrument's re-used map, fitted to a level's stations on this set-up".into()
                }
                FollowerInput::Map { .. } => {
                    "none apart: the follower map was made on this set-up, its vertical holds the bend".into()
                }
                FollowerInput::Specification { .. } => "in the follower's specification".into(),
                FollowerInput::Unstated => "not stated: no follower map or specification".into(),
            },
            Component::Stitching => "overlap handovers since the zero (random walk)".into(),
            Component::Misalignment => {
                "φ from the least-squares straightness slopes (positioning only)".into()
            }
            Component::ThermalTemperature | Component::ThermalCoefficient => match &i.thermal {
                Some(t) => format!(
                    "α = {:.2} µm/(m·K) ± {:.2}, u(T) = {:.2} K, ΔT = {:+.2} K (positioning only)",
                    t.alpha_per_k * 1e6,
                    t.u_alpha_per_k * 1e6,
                    t.u_temperature_k,
                    t.delta_t_k
                ),
                None => "not stated: no material temperature sensor configured".into(),
            },
            Component::Environment => match &i.drift_range {
                Some(_) => "the drift check at the reference (range E_VE)".into(),
                None => "not stated: no drift check".into(),
            },
        })
    }

    /// The budget in user units (µm, arcsec) for JSON: per DOF the terms with their formula,
    /// source and largest value, and every point.
    pub fn to_user_json(&self) -> serde_json::Value {
        let sources = self.sources();
        let dofs: Vec<serde_json::Value> = (0..6)
            .map(|k| {
                let s = DOF_TO_USER[k];
                let (terms, uc, big) = self.largest(k);
                let points: Vec<serde_json::Value> = self
                    .points
                    .iter()
                    .filter(|p| p.dof == k)
                    .map(|p| {
                        serde_json::json!({
                            "target_mm": p.position_mm,
                            "direction": p.direction.map_or("mean", |d| d.sign()),
                            "terms": Component::ALL.iter().map(|c| (c.name(), p.terms[c.index()] * s)).collect::<BTreeMap<_, _>>(),
                            "u": p.combined * s,
                            "U": p.expanded * s,
                        })
                    })
                    .collect();
                serde_json::json!({
                    "dof": DOF_NAMES[k],
                    "unit": DOF_UNITS[k],
                    "terms": Component::ALL.iter().map(|c| serde_json::json!({
                        "name": c.name(),
                        "formula": c.formula(),
                        "source": sources[c.index()],
                        "largest_u": terms[c.index()] * s,
                    })).collect::<Vec<_>>(),
                    "largest_u": uc * s,
                    "largest_U": big * s,
                    "points": points,
                })
            })
            .collect();
        serde_json::json!({
            "k": self.k,
            "u": "standard uncertainty per term and combined (u); U = k·u expanded",
            "dofs": dofs,
        })
    }
}

/// One direction at one target: what the terms are made of.
struct Cell {
    position: f64,
    var_of_mean: f64,
    noise: f64,
    stitch_var: [f64; 2],
}

fn cell(caps: &[&StitchedCapture], k: usize) -> Cell {
    let x: Vec<f64> = caps
        .iter()
        .map(|c| c.capture.errors.to_array()[k])
        .collect();
    let (_, s) = super::mean_sd(&x);
    let n = x.len().max(1) as f64;
    let s = s.unwrap_or(0.0);
    let noise_var: f64 = caps
        .iter()
        .map(|c| {
            let sd = c.capture.frame_sd.to_array()[k];
            sd * sd / c.capture.frames.max(1) as f64
        })
        .sum();
    let stitch_var = [0, 1].map(|a| caps.iter().map(|c| c.overlap_var[a]).sum::<f64>() / n);
    Cell {
        position: caps.first().map_or(0.0, |c| c.capture.target_mm),
        var_of_mean: s * s / n,
        noise: noise_var.sqrt() / n,
        stitch_var,
    }
}

/// The budget of every DOF at every target and direction of `eval`, from its captures with
/// their stitching variances.
pub fn budget(
    eval: &AxisEvaluation,
    captures: &[StitchedCapture],
    inputs: &BudgetInputs,
) -> Budget {
    let mut by_key: BTreeMap<(u32, Direction), Vec<&StitchedCapture>> = BTreeMap::new();
    for c in captures {
        by_key
            .entry((c.capture.target_index, c.capture.direction))
            .or_default()
            .push(c);
    }
    let slope =
        |s: &super::DirectionalStraightness| s.mean.line(super::ReferenceLine::LeastSquares).slope;
    let phi = slope(&eval.straightness_x)
        .hypot(slope(&eval.straightness_z))
        .atan();
    let mut points = Vec::new();
    for k in 0..6 {
        let sens = inputs.psd2_sensitivity[k];
        // The terms that repeat in every run, at a position.
        let systematic = |pos: f64, stitch_var: [f64; 2]| -> [f64; COMPONENTS] {
            let l = (pos - inputs.reference_mm).abs();
            let mut t = [0.0; COMPONENTS];
            t[Component::Calibration.index()] = inputs.calibration.as_ref().map_or(0.0, |c| c.0[k]);
            let f = inputs.follower.at(pos);
            t[Component::Follower.index()] = (sens[0] * f.along_mm).hypot(sens[1] * f.vertical_mm);
            t[Component::Bend.index()] = sens[1] * f.bend_mm;
            t[Component::Stitching.index()] =
                (sens[0] * sens[0] * stitch_var[0] + sens[1] * sens[1] * stitch_var[1]).sqrt();
            if k == 1 {
                // 1 − cos φ, computed without cancellation.
                let one_minus_cos = 2.0 * (phi / 2.0).sin().powi(2);
                t[Component::Misalignment.index()] = l * one_minus_cos / 12f64.sqrt();
                if let Some(th) = &inputs.thermal {
                    t[Component::ThermalTemperature.index()] =
                        th.alpha_per_k * th.u_temperature_k * l;
                    t[Component::ThermalCoefficient.index()] =
                        th.u_alpha_per_k * th.delta_t_k.abs() * l;
                }
            }
            t[Component::Environment.index()] = inputs
                .drift_range
                .map_or(0.0, |r| r[k].abs() / (2.0 * 3f64.sqrt()));
            t
        };
        let finish = |dof, target_index, position_mm, direction, terms: [f64; COMPONENTS]| {
            let combined = terms.iter().map(|t| t * t).sum::<f64>().sqrt();
            PointBudget {
                dof,
                target_index,
                position_mm,
                direction,
                terms,
                combined,
                expanded: K * combined,
            }
        };
        for (i, &ti) in eval.target_indices.iter().enumerate() {
            let cells: Vec<(Direction, Cell)> = [Direction::Up, Direction::Down]
                .into_iter()
                .filter_map(|d| by_key.get(&(ti, d)).map(|c| (d, cell(c, k))))
                .collect();
            let mut dir_terms = Vec::new();
            for (d, c) in &cells {
                let mut t = systematic(c.position, c.stitch_var);
                t[Component::Noise.index()] = c.noise;
                t[Component::Repeatability.index()] = c.var_of_mean.sqrt();
                dir_terms.push(t);
                points.push(finish(k, ti, eval.positions_mm[i], Some(*d), t));
            }
            // The bidirectional mean: correlated terms averaged, scatter terms in quadrature.
            if !cells.is_empty() {
                let m = cells.len() as f64;
                let mut t: [f64; COMPONENTS] =
                    std::array::from_fn(|j| dir_terms.iter().map(|t| t[j]).sum::<f64>() / m);
                t[Component::Noise.index()] = cells
                    .iter()
                    .map(|(_, c)| c.noise * c.noise)
                    .sum::<f64>()
                    .sqrt()
                    / m;
                t[Component::Repeatability.index()] =
                    cells.iter().map(|(_, c)| c.var_of_mean).sum::<f64>().sqrt() / m;
                points.push(finish(k, ti, eval.positions_mm[i], None, t));
            }
        }
    }
    Budget {
        k: K,
        inputs: inputs.clone(),
        points,
        notes: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evaluate::axis::synthetic_capture;
    use crate::evaluate::{EvalOptions, evaluate_captures};
    use crate::units::{Errors6, RAD_PER_ARCSEC};

    /// 3 targets at 0, 500 and 1000 mm × 2 runs × both directions; frame scatter 1 µm over
    /// 100 frames; a run-to-run difference of ±0.1 µm in dy; a straight line in dx of
    /// `slope` (the beam's misalignment).
    fn captures(slope: f64) -> Vec<StitchedCapture> {
        let mut v = Vec::new();
        for t in 0..3u32 {
            let p = 500.0 * t as f64;
            for run in 1..=2u32 {
                for d in [Direction::Up, Direction::Down] {
                    let jitter = if run == 1 { -1e-4 } else { 1e-4 };
                    let e = Errors6::from_array([slope * p, jitter, 0.0, 0.0, 0.0, 0.0]);
                    let mut c = synthetic_capture(t, p, run, d, e, Errors6::ZERO);
                    c.frame_sd = Errors6::from_array([1e-3; 6]);
                    c.frames = 100;
                    v.push(StitchedCapture {
                        capture: c,
                        overlap_var: [0.0; 2],
                    });
                }
            }
        }
        v
    }

    fn inputs() -> BudgetInputs {
        // X2 → dy 1:1; Y2 → roll 1/150 mm (rad per mm) and dz 0.291″/µm·… (any value).
        let mut s = [[0.0; 2]; 6];
        s[1][0] = 1.0;
        s[4][1] = 1.0 / 150.0;
        s[2][1] = 0.02;
        BudgetInputs {
            reference_mm: 0.0,
            psd2_sensitivity: s,
            follower: FollowerInput::Unstated,
            calibration: None,
            thermal: None,
            drift_range: None,
        }
    }

    fn run(caps: &[StitchedCapture], inputs: &BudgetInputs) -> Budget {
        let raw: Vec<Capture> = caps.iter().map(|c| c.capture).collect();
        let eval = evaluate_captures(&raw, &EvalOptions::default()).expect("evaluation");
        budget(&eval, caps, inputs)
    }

    /// Every point of `with` equals `base` except `component`, which is `want(point)`; and
    /// U = 2·√(Σ terms²) everywhere.
    fn only(
        base: &Budget,
        with: &Budget,
        component: Component,
        want: impl Fn(&PointBudget) -> f64,
    ) {
        assert_eq!(base.points.len(), with.points.len());
        let mut changed = 0;
        for (b, w) in base.points.iter().zip(&with.points) {
            for c in Component::ALL {
                let (x, y) = (b.terms[c.index()], w.terms[c.index()]);
                if c == component {
                    let want = want(w);
                    assert!(
                        (y - want).abs() <= 1e-12 * want.abs().max(1e-9),
                        "{}: dof {} target {} {:?}: {y:e}, want {want:e}",
                        c.name(),
                        w.dof,
                        w.target_index,
                        w.direction
                    );
                    changed += usize::from(y != x);
                } else {
                    assert_eq!(x, y, "{} changed with {}", c.name(), component.name());
                }
            }
            let sum: f64 = w.terms.iter().map(|t| t * t).sum();
            assert!((w.expanded - 2.0 * sum.sqrt()).abs() < 1e-15);
            // The component alone adds its term in quadrature to U/2.
            let extra = w.terms[component.index()] - b.terms[component.index()];
            if extra != 0.0 {
                let want_u2 = b.combined * b.combined - b.terms[component.index()].powi(2)
                    + w.terms[component.index()].powi(2);
                assert!((w.combined * w.combined - want_u2).abs() < 1e-18);
            }
        }
        assert!(changed > 0, "{} changed nothing", component.name());
    }

    #[test]
    fn noise_and_repeatability() {
        let b = run(&captures(0.0), &inputs());
        let p = b.point(1, 1, Some(Direction::Up)).expect("point");
        // Two captures of 1 µm frame scatter over 100 frames, mean of 2: √(2·1e-8)/2.
        let noise = (2.0f64 * 1e-6 / 100.0).sqrt() / 2.0;
        assert!((p.terms[Component::Noise.index()] - noise).abs() < 1e-15);
        // s = √2·0.1 µm over n = 2 runs.
        let s = 2f64.sqrt() * 1e-4;
        assert!((p.terms[Component::Repeatability.index()] - s / 2f64.sqrt()).abs() < 1e-15);
        let m = b.point(1, 1, None).expect("mean");
        let want = (2.0 * s * s / 2.0).sqrt() / 2.0;
        assert!((m.terms[Component::Repeatability.index()] - want).abs() < 1e-15);
        assert!((m.terms[Component::Noise.index()] - noise / 2f64.sqrt()).abs() < 1e-15);
        // Nothing else is stated.
        for c in &Component::ALL[2..] {
            assert_eq!(p.terms[c.index()], 0.0, "{}", c.name());
        }
    }

    /// ISO/TR 230-9's temperature terms on a 1000 mm steel axis: a 0.5 K standard uncertainty
    /// of the material temperature adds α·u(T)·L = 11.5e-6 · 0.5 · 1000 mm = 5.75 µm at the
    /// far end (half at 500 mm), to positioning only; α known to ±1 µm/(m·K) (rectangular,
    /// u = 0.577e-6) at ΔT = 2 K adds u(α)·ΔT·L = 1.155 µm at 1000 mm.
    #[test]
    fn each_component_alone_adds_its_own_term() {
        let caps = captures(0.0);
        let base = run(&caps, &inputs());

        let mut i = inputs();
        i.thermal = Some(ThermalInput {
            alpha_per_k: 11.5e-6,
            u_alpha_per_k: 0.0,
            u_temperature_k: 0.5,
            delta_t_k: 0.0,
        });
        let with = run(&caps, &i);
        only(&base, &with, Component::ThermalTemperature, |p| {
            if p.dof == 1 {
                11.5e-6 * 0.5 * p.position_mm
            } else {
                0.0
            }
        });
        let far = with.point(1, 2, Some(Direction::Up)).expect("far end");
        assert!((far.terms[Component::ThermalTemperature.index()] - 5.75e-3).abs() < 1e-12);

        let mut i = inputs();
        let u_alpha = 1e-6 / 3f64.sqrt();
        i.thermal = Some(ThermalInput {
            alpha_per_k: 11.5e-6,
            u_alpha_per_k: u_alpha,
            u_temperature_k: 0.0,
            delta_t_k: -2.0,
        });
        let with = run(&caps, &i);
        only(&base, &with, Component::ThermalCoefficient, |p| {
            if p.dof == 1 {
                u_alpha * 2.0 * p.position_mm
            } else {
                0.0
            }
        });

        // The follower's specification, ±4 µm along and ±2 µm vertical: a/√3 through PSD2.
        let mut i = inputs();
        i.follower = FollowerInput::Specification {
            positioning_mm: 4e-3,
            straightness_mm: 2e-3,
        };
        let with = run(&caps, &i);
        only(&base, &with, Component::Follower, |p| match p.dof {
            1 => 4e-3 / 3f64.sqrt(),
            4 => 2e-3 / 3f64.sqrt() / 150.0,
            2 => 2e-3 / 3f64.sqrt() * 0.02,
            _ => 0.0,
        });
        // 1.155 µm vertical is 1.59″ of roll.
        let roll = with.point(4, 0, Some(Direction::Up)).expect("roll").terms
            [Component::Follower.index()]
            / RAD_PER_ARCSEC;
        assert!((roll - 1.5876).abs() < 1e-3, "{roll}");

        // A follower map replaces the specification, point by point.
        let mut i = inputs();
        i.follower = FollowerInput::Map {
            source: "test".into(),
            positions_mm: vec![0.0, 1000.0],
            along_mm: vec![0.2e-3, 0.4e-3],
            vertical_mm: vec![0.0, 0.0],
            bend_mm: vec![],
        };
        let with = run(&caps, &i);
        only(&base, &with, Component::Follower, |p| {
            if p.dof == 1 {
                0.2e-3 * (1.0 + p.position_mm / 1000.0)
            } else {
                0.0
            }
        });
        // A re-used map's bend: its own term, through PSD2's vertical sensitivity alone.
        i.follower = FollowerInput::Map {
            source: "test".into(),
            positions_mm: vec![0.0, 1000.0],
            along_mm: vec![0.0, 0.0],
            vertical_mm: vec![0.0, 0.0],
            bend_mm: vec![0.1e-3, 0.3e-3],
        };
        let with = run(&caps, &i);
        only(&base, &with, Component::Bend, |p| {
            let b = 0.1e-3 + 0.2e-3 * p.position_mm / 1000.0;
            match p.dof {
                4 => b / 150.0,
                2 => b * 0.02,
                _ => 0.0,
            }
        });

        let cal = [1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6];
        let mut i = inputs();
        i.calibration = Some((cal, "test".into()));
        let with = run(&caps, &i);
        only(&base, &with, Component::Calibration, |p| cal[p.dof]);

        let drift = [1e-3, 2e-3, 0.0, 0.0, 5e-6, 0.0];
        let mut i = inputs();
        i.drift_range = Some(drift);
        let with = run(&caps, &i);
        only(&base, &with, Component::Environment, |p| {
            drift[p.dof] / (2.0 * 3f64.sqrt())
        });

        // Overlap stitching: 1 µm² along at every capture of target 2.
        let mut stitched = caps.clone();
        for c in stitched.iter_mut().filter(|c| c.capture.target_index == 2) {
            c.overlap_var = [1e-6, 0.0];
        }
        let with = run(&stitched, &inputs());
        only(&base, &with, Component::Stitching, |p| {
            if p.dof == 1 && p.target_index == 2 {
                1e-3
            } else {
                0.0
            }
        });
    }

    /// A beam 1 mrad off the travel (its dx slope): the cosine error at 1000 mm is
    /// 1000·(1 − cos 1e-3) = 0.5 µm, rectangular over [0, 0.5 µm]: u = 0.5/√12 µm.
    #[test]
    fn misalignment_from_the_measured_slope() {
        let base = run(&captures(0.0), &inputs());
        let with = run(&captures(1e-3), &inputs());
        for (b, w) in base.points.iter().zip(&with.points) {
            let l = w.position_mm;
            let want = if w.dof == 1 {
                l * (1.0 - 1e-3f64.atan().cos()) / 12f64.sqrt()
            } else {
                0.0
            };
            let got = w.terms[Component::Misalignment.index()];
            assert!((got - want).abs() < 1e-12, "{got:e} vs {want:e}");
            assert_eq!(b.terms[Component::Misalignment.index()], 0.0);
        }
        let far = with.point(1, 2, Some(Direction::Up)).expect("far");
        assert!(
            (far.terms[Component::Misalignment.index()] * 1e3 - 0.5 / 12f64.sqrt()).abs() < 1e-6
        );
    }

    #[test]
    fn stitched_sums_the_overlap_handovers_before_each_capture() {
        let rec = |unix_us, kind, v| HandoverRecord {
            unix_us,
            kind,
            before: [0.0; 2],
            after: [0.0; 2],
            n_before: 1,
            n_after: 1,
            frame_sd: [0.0; 2],
            encoder_before: 0.0,
            encoder_after: 0.0,
            delta: [0.0; 2],
            variance: [v, 2.0 * v],
        };
        let hs = [
            rec(10, HandoverKind::Overlap, 1.0),
            rec(20, HandoverKind::Encoder, 100.0),
            rec(30, HandoverKind::Overlap, 3.0),
        ];
        let mut caps = Vec::new();
        for at in [5, 25, 35] {
            let mut c = synthetic_capture(0, 0.0, 1, Direction::Up, Errors6::ZERO, Errors6::ZERO);
            c.unix_us = at;
            caps.push(c);
        }
        let s = stitched(&caps, &hs);
        let got: Vec<[f64; 2]> = s.iter().map(|c| c.overlap_var).collect();
        assert_eq!(got, vec![[0.0, 0.0], [1.0, 2.0], [4.0, 8.0]]);
    }
}
