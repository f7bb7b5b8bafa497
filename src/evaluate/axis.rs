//! All six DOFs of one axis from the same captures: ISO 230-2 for positioning (dy), ISO 230-1
//! straightness for dx and dz, angular ranges for pitch (ex), roll (ey) and yaw (ez), per-point
//! expanded uncertainty, and thermal normalisation of positioning to 20 °C.

use super::group::{Directions, Grouped, Keyed, group};
use super::iso230_1::{Angular, DirectionalStraightness, Straightness};
use super::iso230_2::{self, Iso230_2};
use super::{EvalError, mean_sd, range};
use crate::run::{Capture, Direction};
use crate::units::Errors6;
use serde::Serialize;

/// ISO 1 reference temperature (°C).
pub const REFERENCE_C: f64 = 20.0;

/// Thermal normalisation settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ThermalConfig {
    /// Expansion coefficient of the axis's scale (the part whose length sets the position: the
    /// ball screw or the linear scale), µm/(m·K). Steel ≈ 11.5.
    pub alpha_um_per_m_k: f64,
    /// Position (mm) at which the expansion is zero: where the scale is fixed, usually the
    /// reference point.
    pub reference_mm: f64,
}

/// Evaluation options.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct EvalOptions {
    /// Normalise positioning to 20 °C when the captures carry a material temperature.
    pub thermal: Option<ThermalConfig>,
}

/// What thermal normalisation did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThermalReport {
    pub applied: bool,
    /// Why it was or was not applied, for the report.
    pub note: String,
    pub mean_material_c: Option<f64>,
    /// Largest |correction| applied to a positioning deviation (mm).
    pub max_correction_mm: f64,
}

/// One DOF's mean profile over the runs (internal units), with expanded uncertainties (k = 2).
///
/// Uncertainty model. Each capture carries a standard uncertainty u (frame noise of its mean,
/// stitching and the decoupling covariance). Part of u is systematic at a target — the
/// decoupling covariance repeats identically in every run — and we cannot split it from the
/// rest, so the instrument term of the mean over n runs is taken as fully correlated: ū, the
/// mean of the u's (the upper bound; it does not shrink with n). The machine's run-to-run
/// scatter enters as the standard deviation of the mean, s/√n. Independent, so
/// `U = 2·√(ū² + s²/n)`. For the bidirectional mean (x̄↑ + x̄↓)/2 the instrument terms are again
/// correlated and the scatter terms independent: `U = 2·√(((ū↑ + ū↓)/2)² + (s↑²/n + s↓²/n)/4)`.
/// The scatter s already contains the instrument's random part, so U is slightly pessimistic;
/// that is the safe side for an acceptance figure.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DofProfile {
    /// 0..6 in `Errors6` order.
    pub dof: usize,
    pub up: Option<Vec<f64>>,
    pub down: Option<Vec<f64>>,
    /// (up + down)/2, or the one direction present.
    pub mean: Vec<f64>,
    pub u_up: Option<Vec<f64>>,
    pub u_down: Option<Vec<f64>>,
    pub u_mean: Vec<f64>,
}

impl DofProfile {
    /// The profile of one direction, if present.
    pub fn direction(&self, d: Direction) -> Option<&[f64]> {
        match d {
            Direction::Up => self.up.as_deref(),
            Direction::Down => self.down.as_deref(),
        }
    }
}

/// The evaluation of an axis from its captures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AxisEvaluation {
    pub directions: Directions,
    pub runs: Vec<u32>,
    pub target_indices: Vec<u32>,
    pub positions_mm: Vec<f64>,
    /// ISO 230-2 of dy (after thermal normalisation, if applied).
    pub positioning: Iso230_2,
    /// Per DOF, in `Errors6` order (dy thermally normalised like `positioning`).
    pub profiles: Vec<DofProfile>,
    /// Horizontal straightness (dx).
    pub straightness_x: DirectionalStraightness,
    /// Vertical straightness (dz).
    pub straightness_z: DirectionalStraightness,
    pub pitch: Angular,
    pub roll: Angular,
    pub yaw: Angular,
    pub thermal: ThermalReport,
}

/// Evaluate captures (any order). Refuses incomplete or inconsistent data (see `group`), and
/// non-finite errors or uncertainties, naming target, run and direction.
pub fn evaluate_captures(
    captures: &[Capture],
    opts: &EvalOptions,
) -> Result<AxisEvaluation, EvalError> {
    let keyed: Vec<Keyed<Capture>> = captures
        .iter()
        .map(|c| Keyed {
            target_index: c.target_index,
            target_mm: c.target_mm,
            run: c.run,
            direction: c.direction,
            line: None,
            value: *c,
        })
        .collect();
    let g = group(&keyed)?;
    for c in captures {
        for (what, v) in [("errors", c.errors), ("u", c.u)] {
            if let Some((k, x)) = v
                .to_array()
                .into_iter()
                .enumerate()
                .find(|(_, x)| !x.is_finite())
            {
                return Err(EvalError::NotFinite {
                    target: c.target_index,
                    run: c.run,
                    direction: c.direction.sign(),
                    at: String::new(),
                    what: format!("{what}.{}", crate::units::DOF_NAMES[k]),
                    value: x,
                });
            }
        }
        if let Some(t) = c.material_c
            && !t.is_finite()
        {
            return Err(EvalError::NotFinite {
                target: c.target_index,
                run: c.run,
                direction: c.direction.sign(),
                at: String::new(),
                what: "the material temperature".into(),
                value: t,
            });
        }
    }
    let (g, thermal) = normalise(g, opts.thermal)?;

    let positions: Vec<f64> = g.targets.iter().map(|t| t.position_mm).collect();
    let dy = Grouped {
        targets: g
            .targets
            .iter()
            .map(|t| super::group::Target {
                index: t.index,
                position_mm: t.position_mm,
                up: t.up.iter().map(|c| c.errors.dy).collect(),
                down: t.down.iter().map(|c| c.errors.dy).collect(),
            })
            .collect(),
        runs: g.runs.clone(),
        directions: g.directions,
    };
    let positioning = iso230_2::from_grouped(&dy);
    let profiles: Vec<DofProfile> = (0..6).map(|k| profile(&g, k)).collect();
    let straight = |k: usize| -> Result<DirectionalStraightness, EvalError> {
        let p = &profiles[k];
        let of = |v: &[f64]| Straightness::of(&positions, v);
        Ok(DirectionalStraightness {
            up: p.up.as_deref().and_then(of),
            down: p.down.as_deref().and_then(of),
            // `group` guarantees ≥ 2 targets at increasing positions, so the lines exist.
            mean: of(&p.mean).ok_or(EvalError::TooFewTargets {
                found: positions.len(),
            })?,
        })
    };
    let angular = |k: usize| {
        let p = &profiles[k];
        Angular {
            up: p.up.as_ref().map(|v| range(v.iter().copied())),
            down: p.down.as_ref().map(|v| range(v.iter().copied())),
            mean: range(p.mean.iter().copied()),
        }
    };
    Ok(AxisEvaluation {
        directions: g.directions,
        runs: g.runs.clone(),
        target_indices: g.targets.iter().map(|t| t.index).collect(),
        positions_mm: positions.clone(),
        positioning,
        straightness_x: straight(0)?,
        straightness_z: straight(2)?,
        pitch: angular(3),
        roll: angular(4),
        yaw: angular(5),
        profiles,
        thermal,
    })
}

/// Thermal normalisation of dy: `dy_20 = dy − α·(T − 20 °C)·(P − P_ref)`. At T > 20 °C a scale
/// that has grown puts the carriage further out than nominal by α·ΔT·(P − P_ref); at 20 °C that
/// part would not be there.
fn normalise(
    mut g: Grouped<Capture>,
    cfg: Option<ThermalConfig>,
) -> Result<(Grouped<Capture>, ThermalReport), EvalError> {
    let all: Vec<&Capture> = g
        .targets
        .iter()
        .flat_map(|t| t.up.iter().chain(&t.down))
        .collect();
    let with_t = all.iter().filter(|c| c.material_c.is_some()).count();
    let mean_t =
        (with_t > 0).then(|| all.iter().filter_map(|c| c.material_c).sum::<f64>() / with_t as f64);
    let not_applied = |note: &str| ThermalReport {
        applied: false,
        note: note.into(),
        mean_material_c: mean_t,
        max_correction_mm: 0.0,
    };
    let Some(cfg) = cfg else {
        let note = if with_t > 0 {
            "not applied: material temperature present but no expansion coefficient configured"
        } else {
            "not applied: not configured"
        };
        return Ok((g, not_applied(note)));
    };
    if !(cfg.alpha_um_per_m_k.is_finite() && cfg.reference_mm.is_finite()) {
        return Err(EvalError::Thermal(format!(
            "expansion coefficient {} µm/(m·K) and reference {} mm must be finite numbers",
            cfg.alpha_um_per_m_k, cfg.reference_mm
        )));
    }
    if with_t == 0 {
        return Ok((
            g,
            not_applied("not applied: no material temperature in the captures"),
        ));
    }
    if with_t < all.len() {
        let c = all.iter().find(|c| c.material_c.is_none()).copied();
        let which = c.map(|c| {
            format!(
                "target {}, run {}, direction {}",
                c.target_index,
                c.run,
                c.direction.sign()
            )
        });
        return Err(EvalError::Thermal(format!(
            "{} of {} captures have a material temperature; {} has none: give every capture one or none",
            with_t,
            all.len(),
            which.unwrap_or_default()
        )));
    }
    let alpha = cfg.alpha_um_per_m_k * 1e-6;
    let mut max_corr = 0.0f64;
    for t in &mut g.targets {
        let p = t.position_mm;
        for c in t.up.iter_mut().chain(t.down.iter_mut()) {
            let dt = c.material_c.unwrap_or(REFERENCE_C) - REFERENCE_C;
            let corr = alpha * dt * (p - cfg.reference_mm);
            c.errors.dy -= corr;
            max_corr = max_corr.max(corr.abs());
        }
    }
    Ok((
        g,
        ThermalReport {
            applied: true,
            note: format!(
                "applied: positioning normalised to 20 °C with α = {} µm/(m·K) about {} mm",
                cfg.alpha_um_per_m_k, cfg.reference_mm
            ),
            mean_material_c: mean_t,
            max_correction_mm: max_corr,
        },
    ))
}

/// Mean, scatter and instrument uncertainty of one direction at one target for DOF k.
struct Cell {
    mean: f64,
    var_of_mean: f64,
    u_instr: f64,
}

fn cell(caps: &[Capture], k: usize) -> Cell {
    let x: Vec<f64> = caps.iter().map(|c| c.errors.to_array()[k]).collect();
    let (mean, s) = mean_sd(&x);
    let n = x.len() as f64;
    let s = s.unwrap_or(0.0);
    Cell {
        mean,
        var_of_mean: s * s / n,
        u_instr: caps.iter().map(|c| c.u.to_array()[k].abs()).sum::<f64>() / n,
    }
}

fn profile(g: &Grouped<Capture>, k: usize) -> DofProfile {
    let dir = |d: Direction| -> Option<Vec<Cell>> {
        let cells: Vec<Cell> = g.targets.iter().map(|t| cell(t.values(d), k)).collect();
        (g.targets.iter().all(|t| !t.values(d).is_empty())).then_some(cells)
    };
    let up = dir(Direction::Up);
    let down = dir(Direction::Down);
    let expanded = |c: &Cell| 2.0 * (c.u_instr * c.u_instr + c.var_of_mean).sqrt();
    let (mean, u_mean): (Vec<f64>, Vec<f64>) = match (&up, &down) {
        (Some(u), Some(d)) => u
            .iter()
            .zip(d)
            .map(|(a, b)| {
                let ui = (a.u_instr + b.u_instr) / 2.0;
                (
                    (a.mean + b.mean) / 2.0,
                    2.0 * (ui * ui + (a.var_of_mean + b.var_of_mean) / 4.0).sqrt(),
                )
            })
            .unzip(),
        (Some(one), None) | (None, Some(one)) => one.iter().map(|c| (c.mean, expanded(c))).unzip(),
        // `group` guarantees at least one direction.
        (None, None) => (Vec::new(), Vec::new()),
    };
    DofProfile {
        dof: k,
        up: up.as_ref().map(|v| v.iter().map(|c| c.mean).collect()),
        down: down.as_ref().map(|v| v.iter().map(|c| c.mean).collect()),
        u_up: up.as_ref().map(|v| v.iter().map(expanded).collect()),
        u_down: down.as_ref().map(|v| v.iter().map(expanded).collect()),
        mean,
        u_mean,
    }
}

/// A capture with the given errors (internal units), for tests and benchmarks.
pub fn synthetic_capture(
    target_index: u32,
    target_mm: f64,
    run: u32,
    direction: Direction,
    errors: Errors6,
    u: Errors6,
) -> Capture {
    Capture {
        run,
        target_index,
        target_mm,
        direction,
        errors,
        frame_sd: Errors6::ZERO,
        u,
        frames: 1,
        material_c: None,
        air_c: None,
        unix_us: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 3 targets × 2 runs × both directions with every DOF a known function.
    fn captures() -> Vec<Capture> {
        let mut v = Vec::new();
        for t in 0..3u32 {
            let p = 100.0 * t as f64;
            for run in 1..=2u32 {
                for d in [Direction::Up, Direction::Down] {
                    let sgn = if d == Direction::Up { 1.0 } else { -1.0 };
                    let jitter = if run == 1 { -1e-4 } else { 1e-4 };
                    let e = Errors6::from_array([
                        // dx: tilt 1e-5 + bump 2 µm at the middle.
                        1e-5 * p + if t == 1 { 2e-3 } else { 0.0 },
                        // dy: ±1 µm reversal, ±0.1 µm run jitter.
                        sgn * 1e-3 + jitter,
                        0.0,
                        1e-5 * t as f64,
                        0.0,
                        -2e-5 * t as f64 * sgn,
                    ]);
                    let u = Errors6::from_array([3e-4; 6]);
                    v.push(synthetic_capture(t, p, run, d, e, u));
                }
            }
        }
        v
    }

    #[test]
    fn six_dofs_from_one_set() {
        let r = evaluate_captures(&captures(), &EvalOptions::default()).unwrap();
        assert_eq!(r.directions, Directions::Both);
        // Positioning: B_i = +2 µm everywhere, s = √2·0.1 µm (two runs ±0.1).
        assert!((r.positioning.axis.b.unwrap() - 2e-3).abs() < 1e-12);
        let s = (2.0f64).sqrt() * 1e-4;
        assert!((r.positioning.targets[0].s_up.unwrap() - s).abs() < 1e-12);
        // Straightness x: end points on the tilt, bump of 2 µm; slope 10 µm/m.
        let ep = &r.straightness_x.mean.end_point;
        assert!((ep.straightness - 2e-3).abs() < 1e-12);
        assert!((ep.slope_um_per_m() - 10.0).abs() < 1e-6);
        // Pitch: range 2e-5 rad in both directions; yaw cancels in the mean.
        assert!((r.pitch.mean - 2e-5).abs() < 1e-15);
        assert!((r.yaw.up.unwrap() - 4e-5).abs() < 1e-15);
        assert!(r.yaw.mean.abs() < 1e-15);
        // Uncertainty of dy, one direction: 2·√(u² + s²/n) with u = 0.3 µm, s²/n = 1e-8.
        let want = 2.0 * (9e-8f64 + s * s / 2.0).sqrt();
        assert!((r.profiles[1].u_up.as_ref().unwrap()[0] - want).abs() < 1e-15);
        // Bidirectional mean: 2·√(u² + (s²/n + s²/n)/4).
        let want = 2.0 * (9e-8f64 + (s * s / 2.0) / 2.0).sqrt();
        assert!((r.profiles[1].u_mean[0] - want).abs() < 1e-15);
        assert!(!r.thermal.applied);
    }

    #[test]
    fn thermal_normalisation() {
        let mut caps = captures();
        for c in &mut caps {
            c.material_c = Some(22.0);
        }
        let cfg = ThermalConfig {
            alpha_um_per_m_k: 11.5,
            reference_mm: 0.0,
        };
        let base = evaluate_captures(&caps, &EvalOptions::default()).unwrap();
        assert!(!base.thermal.applied);
        assert!(base.thermal.note.contains("no expansion coefficient"));
        let r = evaluate_captures(&caps, &EvalOptions { thermal: Some(cfg) }).unwrap();
        assert!(r.thermal.applied, "{}", r.thermal.note);
        // At 200 mm, 2 K: 11.5e-6 · 2 · 200 mm = 4.6 µm removed.
        let d = base.profiles[1].mean[2] - r.profiles[1].mean[2];
        assert!((d - 4.6e-3).abs() < 1e-12, "{d}");
        assert!((r.thermal.max_correction_mm - 4.6e-3).abs() < 1e-12);
        assert_eq!(r.profiles[1].mean[0], base.profiles[1].mean[0]);
        // Straightness is not touched.
        assert_eq!(r.profiles[0], base.profiles[0]);

        caps[3].material_c = None;
        let e = evaluate_captures(&caps, &EvalOptions { thermal: Some(cfg) }).unwrap_err();
        assert!(
            e.to_string().contains("target 0, run 2, direction -"),
            "{e}"
        );
    }

    #[test]
    fn non_finite_is_named() {
        let mut caps = captures();
        caps[5].errors.ez = f64::NAN;
        let e = evaluate_captures(&caps, &EvalOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("target 1, run 1, direction -: errors.ez is NaN"),
            "{e}"
        );
    }
}
