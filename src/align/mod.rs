//! Beam alignment: the head's mount on the machine ([`mount`]) corrected from spot readings at
//! the near and far ends of the travel, and the check that every spot stays on its PSD, with a
//! margin, over a plan's whole travel (DESIGN §4).
//!
//! Sans-I/O: a [`Station`] is what the PSDs (or, where a spot is off its PSD, the alignment
//! target in front of it) showed with the carriage at rest at one position; [`advise`] turns
//! the stations into the screw turns that centre the spots, the residual misalignment and the
//! verdict. Whoever moves the carriage and reads the PSDs (the service, the lab) calls it.
//!
//! Readings are linear in the carriage position to first order (the mount is a constant angle
//! and a straightness slope in the head's frame), so two stations predict every spot over the
//! travel between them, and the spots' extremes lie at the ends. PSD2's X follows the
//! follower, which keeps it centred; its Y is checked like the others.

pub mod knock;
pub mod mount;
pub mod revisit;

pub use knock::{Knock, KnockSettings, KnockWatch, Step};
pub use mount::{Mount, MountGeometry, Screw};
pub use revisit::{Agreement, Revisit, RevisitSettings, RevisitState};

use crate::optics::{Layout, Pose, Spot};
use crate::units::Errors6;
use nalgebra::{DMatrix, DVector};
use thiserror::Error;

/// Why no advice could be given.
#[derive(Debug, Error, PartialEq)]
pub enum AlignError {
    #[error("no station to align from: read the spots with the carriage at the near end first")]
    NoStation,
    #[error(
        "no spot to align from: read the spots on the alignment targets where a PSD shows none, or bring the beam onto the targets by eye"
    )]
    NoReadings,
    #[error("alignment settings: {0}")]
    Settings(String),
}

/// Where a spot reading came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SpotSource {
    /// The PSD itself (a mean of frames: µm).
    Psd,
    /// The alignment target in front of the PSD, read by eye (the spot is off the PSD).
    Target,
}

/// One spot at a station (mm, in the PSD's X, Y).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observed {
    pub x: f64,
    pub y: f64,
    pub source: SpotSource,
}

impl Observed {
    pub fn psd(s: Spot) -> Observed {
        Observed {
            x: s.x,
            y: s.y,
            source: SpotSource::Psd,
        }
    }
}

/// The spots with the carriage at rest at one position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Station {
    /// Nominal carriage position (mm).
    pub travel_mm: f64,
    /// Per PSD: the spot, or `None` when neither the PSD nor its target shows one.
    pub spots: [Option<Observed>; 3],
}

/// Alignment settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignSettings {
    pub geometry: MountGeometry,
    /// How far inside its active area every spot must stay (mm).
    pub margin_mm: f64,
    /// The largest angle of the beam to the travel the check passes (rad): the cosine error
    /// it leaves is L·θ²/2 (200 µrad: 0.02 µm per metre).
    pub max_angle_rad: f64,
}

impl Default for AlignSettings {
    fn default() -> Self {
        AlignSettings {
            geometry: MountGeometry::default(),
            margin_mm: 1.0,
            max_angle_rad: 200e-6,
        }
    }
}

/// How much more the corner cube's slope over the travel weighs than a spot's position.
const PARALLEL_WEIGHT: f64 = 5.0;

/// A reading channel the alignment uses: PSD index (0..3) and axis (0 = X, 1 = Y).
const CHANNELS: [(usize, usize); 5] = [(0, 0), (0, 1), (1, 1), (2, 0), (2, 1)];

fn channel_name(psd: usize, axis: usize) -> String {
    format!("{}{}", if axis == 0 { 'X' } else { 'Y' }, psd + 1)
}

/// A spot that leaves (or would leave) its margin.
#[derive(Clone, Debug, PartialEq)]
pub struct Leave {
    /// PSD index (0..3).
    pub psd: usize,
    /// What happens there, in words (`X1 reaches 4.12 mm at 1000 mm (limit ±3.50 mm)`, `no
    /// spot at 0 mm`).
    pub what: String,
}

impl std::fmt::Display for Leave {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PSD{}: {}", self.psd + 1, self.what)
    }
}

/// The spots over a span of travel, judged against the margin.
#[derive(Clone, Debug, PartialEq)]
pub struct Check {
    /// The span judged (mm).
    pub span_mm: (f64, f64),
    /// The smallest distance of any spot from its PSD's edge over the span (mm; negative:
    /// off the PSD), when every PSD was read at two positions.
    pub least_clearance_mm: Option<f64>,
    /// Every spot that leaves its margin.
    pub leaves: Vec<Leave>,
}

impl Check {
    pub fn passed(&self) -> bool {
        self.leaves.is_empty() && self.least_clearance_mm.is_some()
    }

    /// Whether it passed over a span that holds `span` (mm).
    pub fn covers(&self, span: (f64, f64)) -> bool {
        self.passed() && self.span_mm.0 <= span.0 + 1e-6 && self.span_mm.1 >= span.1 - 1e-6
    }
}

/// A station from the frames read at rest at `at_mm`: each PSD's mean spot, where it had one
/// in at least nine frames of ten (else `None`: its target is read instead).
pub fn mean_station<'a>(
    at_mm: f64,
    frames: impl Iterator<Item = &'a [Option<Spot>; 3]> + Clone,
) -> Station {
    let n = frames.clone().count();
    let spots = std::array::from_fn(|k| {
        let valid: Vec<Spot> = frames.clone().filter_map(|f| f[k]).collect();
        (!valid.is_empty() && valid.len() * 10 >= n * 9).then(|| {
            let m = valid.len() as f64;
            Observed::psd(Spot {
                x: valid.iter().map(|s| s.x).sum::<f64>() / m,
                y: valid.iter().map(|s| s.y).sum::<f64>() / m,
            })
        })
    });
    Station {
        travel_mm: at_mm,
        spots,
    }
}

impl std::fmt::Display for Check {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (a, b) = self.span_mm;
        if self.passed() {
            return write!(
                f,
                "every spot stays on its PSD from {a:.0} to {b:.0} mm, at least {:.2} mm inside the edge",
                self.least_clearance_mm.unwrap_or_default()
            );
        }
        let what: Vec<String> = self.leaves.iter().map(Leave::to_string).collect();
        if what.is_empty() {
            write!(
                f,
                "the spots were not read at both ends of {a:.0}–{b:.0} mm"
            )
        } else {
            write!(f, "{}", what.join("; "))
        }
    }
}

/// One screw to turn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Turn {
    pub screw: Screw,
    /// Turns, clockwise positive.
    pub turns: f64,
}

impl std::fmt::Display for Turn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.turns.abs();
        let dir = if self.turns >= 0.0 {
            "clockwise"
        } else {
            "anticlockwise"
        };
        let unit = if (n - 1.0).abs() < 0.005 {
            "turn"
        } else {
            "turns"
        };
        write!(f, "turn the {} screw {n:.2} {unit} {dir}", self.screw)
    }
}

/// What to do.
#[derive(Clone, Debug, PartialEq)]
pub struct Advice {
    /// The mount correction that centres the spots (rad, mm).
    pub correction: Mount,
    /// The screws to turn for it (those that need at least 0.01 turn).
    pub turns: Vec<Turn>,
    /// The beam's angle to the travel (yaw, pitch in µrad), from the corner cube's spot at
    /// two positions: the slope an ISO 230-1 straightness line removes.
    pub misalignment_urad: Option<[f64; 2]>,
    /// The spots as they are now, over the span.
    pub now: Check,
    /// The spots expected after the turns, over the span.
    pub after: Check,
}

impl Advice {
    /// The advice in a few lines of words.
    pub fn describe(&self) -> String {
        let mut out = String::new();
        match self.misalignment_urad {
            Some([y, p]) => out.push_str(&format!(
                "beam to travel: yaw {y:+.0} µrad, pitch {p:+.0} µrad\n"
            )),
            None => out.push_str("beam to travel: not known yet (read the spots at both ends)\n"),
        }
        if self.now.passed() {
            out.push_str(&format!("check passed: {}\n", self.now));
        } else {
            out.push_str(&format!("check not passed: {}\n", self.now));
        }
        if self.turns.is_empty() {
            out.push_str("no screw to turn\n");
        } else {
            for t in &self.turns {
                out.push_str(&format!("{t}\n"));
            }
            out.push_str(&format!("then: {}\n", self.after));
        }
        out
    }
}

/// The readings the alignment uses at one station, with their channel, where read.
fn readings(st: &Station) -> Vec<((usize, usize), f64)> {
    CHANNELS
        .iter()
        .filter_map(|&(k, a)| {
            let o = st.spots[k]?;
            Some(((k, a), if a == 0 { o.x } else { o.y }))
        })
        .collect()
}

/// The five alignment channels' readings at `travel` for a mount, on `layout` (geometry only).
fn model(layout: &Layout, g: &MountGeometry, m: &Mount, travel: f64) -> Option<[f64; 5]> {
    let e = m.head_pose(
        g.pivot(),
        layout.c,
        layout.travel_axis,
        travel,
        &Errors6::ZERO,
    );
    let r = layout.forward_unbounded(&Pose::new(e, travel, travel));
    let mut out = [0.0; 5];
    for (i, &(k, a)) in CHANNELS.iter().enumerate() {
        let s = r.psd[k].ok()?;
        out[i] = if a == 0 { s.x } else { s.y };
    }
    Some(out)
}

/// d(channel)/d(mount parameter) at `travel`: 5 × 4, by central differences.
fn jacobian(layout: &Layout, g: &MountGeometry, travel: f64) -> Result<[[f64; 4]; 5], AlignError> {
    let steps = [1e-4, 1e-4, 0.05, 0.05];
    let mut j = [[0.0; 4]; 5];
    for (p, s) in Screw::ALL.into_iter().zip(steps) {
        let hi = Mount::default().adjusted(p, s);
        let lo = Mount::default().adjusted(p, -s);
        let (Some(a), Some(b)) = (model(layout, g, &hi, travel), model(layout, g, &lo, travel))
        else {
            return Err(AlignError::Settings(format!(
                "the layout cannot be traced at {travel:.0} mm"
            )));
        };
        for c in 0..5 {
            j[c][p as usize] = (a[c] - b[c]) / (2.0 * s);
        }
    }
    Ok(j)
}

fn channel_index(ch: (usize, usize)) -> usize {
    CHANNELS.iter().position(|&c| c == ch).unwrap_or(0)
}

/// The screw turns that centre the spots at the stations, the misalignment and the checks
/// over `span` (mm), from the head's nominal `layout`.
pub fn advise(
    layout: &Layout,
    settings: &AlignSettings,
    stations: &[Station],
    span: (f64, f64),
) -> Result<Advice, AlignError> {
    settings.geometry.validate().map_err(AlignError::Settings)?;
    if stations.is_empty() {
        return Err(AlignError::NoStation);
    }
    let g = &settings.geometry;
    // Rows: every reading at every station; columns scaled so that 1 mrad and 1 mm weigh alike.
    let scale = [1e-3, 1e-3, 1.0, 1.0];
    let mut rows: Vec<([f64; 4], f64)> = Vec::new();
    let mut jac = Vec::with_capacity(stations.len());
    for st in stations {
        let j = jacobian(layout, g, st.travel_mm)?;
        for (ch, v) in readings(st) {
            let row = j[channel_index(ch)];
            rows.push((std::array::from_fn(|i| row[i] * scale[i]), v));
        }
        jac.push(j);
    }
    // Parallelism first: the corner cube's spot must not walk over the travel (its slope is
    // the beam's angle to the travel, and the cosine error grows with its square), so the
    // slope of X3 and Y3 between the outermost stations is asked to vanish with a heavy
    // weight; the other readings then centre what a mount can centre.
    if let Some((i0, i1)) = outermost(stations)
        && let (Some(p0), Some(p1)) = (stations[i0].spots[2], stations[i1].spots[2])
    {
        for (a, v0, v1) in [(0, p0.x, p1.x), (1, p0.y, p1.y)] {
            let c = channel_index((2, a));
            let row: [f64; 4] = std::array::from_fn(|i| {
                PARALLEL_WEIGHT * (jac[i1][c][i] - jac[i0][c][i]) * scale[i]
            });
            rows.push((row, PARALLEL_WEIGHT * (v1 - v0)));
        }
    }
    if rows.is_empty() {
        // With fewer than four readings the correction is the smallest one that centres
        // those seen; the next round sees more.
        return Err(AlignError::NoReadings);
    }
    let a = DMatrix::from_fn(rows.len(), 4, |r, c| rows[r].0[c]);
    let b = DVector::from_iterator(rows.len(), rows.iter().map(|r| -r.1));
    let svd = a.svd(true, true);
    let x = svd
        .solve(&b, 1e-9)
        .map_err(|e| AlignError::Settings(e.to_string()))?;
    let correction = Mount::from_array(std::array::from_fn(|i| x[i] * scale[i]));
    let turns = Screw::ALL
        .into_iter()
        .map(|s| Turn {
            screw: s,
            turns: g.turns(s, correction.get(s)),
        })
        .filter(|t| t.turns.abs() >= 0.01)
        .collect();
    // The stations as they would read after the correction (first order).
    let after: Vec<Station> = stations
        .iter()
        .zip(&jac)
        .map(|(st, j)| {
            let mut s = *st;
            for (k, o) in s.spots.iter_mut().enumerate() {
                if let Some(o) = o.as_mut() {
                    for (a, v) in [(0, &mut o.x), (1, &mut o.y)] {
                        if CHANNELS.contains(&(k, a)) {
                            let row = j[channel_index((k, a))];
                            let c = correction.to_array();
                            *v += (0..4).map(|i| row[i] * c[i]).sum::<f64>();
                        }
                    }
                }
            }
            s
        })
        .collect();
    let half = psd_half(layout);
    let misalignment_urad = misalignment(stations, &jac);
    let mut now = check(stations, span, &half, settings.margin_mm);
    if let Some([y, p]) = misalignment_urad {
        let worst = y.abs().max(p.abs());
        let limit = settings.max_angle_rad * 1e6;
        if worst > limit {
            let len = span.1 - span.0;
            now.leaves.push(Leave {
                psd: 2,
                what: format!(
                    "the beam runs {worst:.0} µrad off the travel (at most {limit:.0} µrad: a cosine error of {:.2} µm over {len:.0} mm)",
                    len * (worst * 1e-6).powi(2) / 2.0 * 1e3
                ),
            });
        }
    }
    Ok(Advice {
        correction,
        turns,
        misalignment_urad,
        now,
        after: check(&after, span, &half, settings.margin_mm),
    })
}

/// The PSDs' active half-sizes (mm), in reading order.
fn psd_half(layout: &Layout) -> [f64; 3] {
    std::array::from_fn(|k| {
        layout
            .paths
            .get(k)
            .and_then(|p| p.steps.last())
            .and_then(|s| layout.elements.get(s.element))
            .map(|e| match e.aperture {
                crate::optics::layout::Aperture::Square { half } => half,
                crate::optics::layout::Aperture::Circle { radius } => radius,
            })
            .unwrap_or(4.5)
    })
}

/// The mount's angles from the slope of PSD3's spot between the outermost stations.
fn misalignment(stations: &[Station], jac: &[[[f64; 4]; 5]]) -> Option<[f64; 2]> {
    let (i0, i1) = outermost(stations)?;
    let (s0, s1) = (&stations[i0], &stations[i1]);
    let dd = s1.travel_mm - s0.travel_mm;
    let (p0, p1) = (s0.spots[2]?, s1.spots[2]?);
    if p0.source != SpotSource::Psd || p1.source != SpotSource::Psd {
        return None;
    }
    // Slope of X3 and Y3 per mm against the model's slope per unit yaw and pitch.
    let ds = |a: usize, p: usize| {
        (jac[i1][channel_index((2, a))][p] - jac[i0][channel_index((2, a))][p]) / dd
    };
    let m = nalgebra::Matrix2::new(ds(0, 0), ds(0, 1), ds(1, 0), ds(1, 1));
    let v = nalgebra::Vector2::new((p1.x - p0.x) / dd, (p1.y - p0.y) / dd);
    let ang = m.try_inverse()? * v;
    Some([ang[0] * 1e6, ang[1] * 1e6])
}

/// The stations nearest the two ends of the travel (indices), when they differ by 1 mm or more.
fn outermost(stations: &[Station]) -> Option<(usize, usize)> {
    let lo = (0..stations.len())
        .min_by(|&a, &b| stations[a].travel_mm.total_cmp(&stations[b].travel_mm))?;
    let hi = (0..stations.len())
        .max_by(|&a, &b| stations[a].travel_mm.total_cmp(&stations[b].travel_mm))?;
    (stations[hi].travel_mm - stations[lo].travel_mm >= 1.0).then_some((lo, hi))
}

/// Judge the spots over `span` from the outermost stations, each channel linear in travel.
pub fn check(stations: &[Station], span: (f64, f64), half: &[f64; 3], margin: f64) -> Check {
    let mut leaves = Vec::new();
    for st in stations {
        for k in 0..3 {
            match st.spots[k] {
                None => leaves.push(Leave {
                    psd: k,
                    what: format!("no spot at {:.0} mm", st.travel_mm),
                }),
                Some(o) if o.source == SpotSource::Target => leaves.push(Leave {
                    psd: k,
                    what: format!(
                        "the spot is off the PSD at {:.0} mm (target reads X {:+.1} mm, Y {:+.1} mm)",
                        st.travel_mm, o.x, o.y
                    ),
                }),
                Some(_) => {}
            }
        }
    }
    let mut least: Option<f64> = None;
    let ends = outermost(stations);
    if leaves.is_empty()
        && let Some((i0, i1)) = ends
    {
        let (s0, s1) = (&stations[i0], &stations[i1]);
        for &(k, a) in &CHANNELS {
            let (Some(o0), Some(o1)) = (s0.spots[k], s1.spots[k]) else {
                continue;
            };
            let (v0, v1) = if a == 0 { (o0.x, o1.x) } else { (o0.y, o1.y) };
            let at = |d: f64| v0 + (v1 - v0) * (d - s0.travel_mm) / (s1.travel_mm - s0.travel_mm);
            let limit = half[k] - margin;
            let mut worst: Option<(f64, f64)> = None;
            for d in [span.0, span.1] {
                let v = at(d);
                least = Some(least.map_or(half[k] - v.abs(), |l: f64| l.min(half[k] - v.abs())));
                if v.abs() > limit && worst.is_none_or(|(w, _)| v.abs() > w.abs()) {
                    worst = Some((v, d));
                }
            }
            if let Some((v, d)) = worst {
                leaves.push(Leave {
                    psd: k,
                    what: format!(
                        "{} reaches {v:+.2} mm at {d:.0} mm (limit ±{limit:.2} mm)",
                        channel_name(k, a)
                    ),
                });
            }
        }
    }
    Check {
        span_mm: span,
        least_clearance_mm: if ends.is_some() { least } else { None },
        leaves,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stations read from the nominal layout at a mount (noise-free; off-PSD spots on targets).
    fn read(layout: &Layout, g: &MountGeometry, m: &Mount, at: &[f64]) -> Vec<Station> {
        at.iter()
            .map(|&d| {
                let e = m.head_pose(g.pivot(), layout.c, layout.travel_axis, d, &Errors6::ZERO);
                let pose = Pose::new(e, d, d);
                let bounded = layout.forward(&pose);
                let free = layout.forward_unbounded(&pose);
                Station {
                    travel_mm: d,
                    spots: std::array::from_fn(|k| match (bounded.psd[k], free.psd[k]) {
                        (Ok(s), _) => Some(Observed::psd(s)),
                        (Err(_), Ok(s)) if s.x.abs() < 20.0 && s.y.abs() < 20.0 => Some(Observed {
                            x: (s.x * 2.0).round() / 2.0,
                            y: (s.y * 2.0).round() / 2.0,
                            source: SpotSource::Target,
                        }),
                        _ => None,
                    }),
                }
            })
            .collect()
    }

    #[test]
    fn a_misaligned_mount_is_found_and_corrected_in_a_few_turns() {
        let layout = Layout::reference();
        let s = AlignSettings::default();
        let g = s.geometry;
        let mut m = Mount {
            yaw: 4e-3,
            pitch: -3e-3,
            x: 1.5,
            z: -1.2,
        };
        let span = (0.0, 2000.0);
        let mut passed = false;
        for _ in 0..6 {
            let st = read(&layout, &g, &m, &[span.0, span.1]);
            let adv = advise(&layout, &s, &st, span).unwrap();
            if adv.now.passed() {
                passed = true;
                let [y, p] = adv.misalignment_urad.unwrap();
                // The slope the check saw is the mount's own angle (sign: the head's yaw).
                assert!(
                    (y.abs() - m.yaw.abs() * 1e6).abs() < 5.0,
                    "{y} vs {}",
                    m.yaw
                );
                assert!(
                    (p.abs() - m.pitch.abs() * 1e6).abs() < 5.0,
                    "{p} vs {}",
                    m.pitch
                );
                break;
            }
            // A technician turns each screw 3 % more than asked.
            for t in &adv.turns {
                m = m.adjusted(t.screw, g.amount(t.screw, t.turns * 1.03));
            }
        }
        assert!(passed, "mount left at {m:?}");
        assert!(m.yaw.abs() < 2e-4 && m.pitch.abs() < 2e-4, "{m:?}");
    }

    #[test]
    fn the_check_names_the_psd_the_position_and_the_limit() {
        let layout = Layout::reference();
        let s = AlignSettings::default();
        let m = Mount {
            yaw: 1.5e-3,
            ..Mount::default()
        };
        let st = read(&layout, &s.geometry, &m, &[0.0, 1000.0]);
        let adv = advise(&layout, &s, &st, (0.0, 1000.0)).unwrap();
        assert!(!adv.now.passed());
        let text = adv.now.to_string();
        assert!(
            text.contains("PSD3") && text.contains("at 1000 mm"),
            "{text}"
        );
        assert!(text.contains("limit ±3.50 mm"), "{text}");
        assert!(adv.after.passed(), "{}", adv.after);
        let y = adv.turns.iter().find(|t| t.screw == Screw::Yaw).unwrap();
        assert!((y.turns.abs() - 0.6).abs() < 0.02, "{}", y.turns);
        assert!(
            adv.describe().contains("turn the yaw screw 0.6"),
            "{}",
            adv.describe()
        );
    }

    #[test]
    fn no_station_and_too_few_readings_are_refused() {
        let layout = Layout::reference();
        let s = AlignSettings::default();
        assert_eq!(
            advise(&layout, &s, &[], (0.0, 1.0)).unwrap_err(),
            AlignError::NoStation
        );
        let st = Station {
            travel_mm: 0.0,
            spots: [None, None, None],
        };
        assert_eq!(
            advise(&layout, &s, &[st], (0.0, 1.0)).unwrap_err(),
            AlignError::NoReadings
        );
    }
}
