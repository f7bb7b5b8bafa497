//! Trends of an axis's figures over its runs (issue 30): control limits learned from the
//! machine's own history, a drift alarm, and a forecast of when a figure crosses its tolerance,
//! with an interval. Sans-I/O: the points in, the chart and the forecast out; `axiscomp trend`
//! reads the points from the store.
//!
//! **Method: an EWMA chart** (Roberts 1959; Montgomery, *Introduction to Statistical Quality
//! Control*, §9.2) on the figure: `z_i = λ x_i + (1 − λ) z_{i−1}` from `z_0 = μ0`, with limits
//! `μ0 ± L σ √(λ/(2 − λ) · (1 − (1 − λ)^{2i}))`. Why EWMA: wear moves a figure slowly and for
//! good, and an EWMA sees a sustained shift of 1 σ in about 10 checks and of 2 σ in about 4, where
//! a Shewhart chart (each point alone against 3 σ) needs about 44 and 6, at the same false-alarm
//! rate (λ = 0.2, L = 3: about one false signal in 500 points with σ known). CUSUM does as well
//! for the one shift it is tuned to and worse for others. A point 3.5 σ from the mean alarms
//! by itself too (Lucas and Saccucci 1990's combined Shewhart-EWMA): a fast change is seen at
//! once, and a stable machine gives such a point once in about 2000 checks.
//!
//! **Limits from the machine's own history:** `μ0` and `σ` are the mean and the standard
//! deviation of the first `baseline` points (the axis as commissioned; the limits widened by
//! the mean's own uncertainty, `σ²/baseline` added to the EWMA's variance), with σ not below
//! `sigma_floor` (the figure's stated standard uncertainty, when the caller knows it: a short
//! baseline can happen to scatter little, and limits drawn from it would cry wolf).
//!
//! **Forecast:** a straight line fitted by least squares to the last `window` points, the day
//! it reaches the tolerance, and a 95 % interval for that day by the delta method on the line's
//! intercept and slope (Student's t on n − 2 degrees of freedom). A figure that does not grow
//! has no crossing.

use thiserror::Error;

/// One figure of one run or check: when (days since any fixed origin), and its value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point {
    pub days: f64,
    pub value: f64,
}

/// How a trend is judged.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Settings {
    /// The first points, whose mean and scatter set the limits.
    pub baseline: usize,
    /// The EWMA's weight of the newest point (0 < λ ≤ 1).
    pub lambda: f64,
    /// The limits' width in standard deviations of the EWMA (L).
    pub width: f64,
    /// A single point this many σ from the baseline's mean alarms at once (the Shewhart rule
    /// beside the EWMA, for a fast change the EWMA would take a few checks to see).
    pub point_width: f64,
    /// The points the forecast's line is fitted to (the newest), at least 3.
    pub window: usize,
    /// The least σ the limits assume (the figure's unit): its stated standard uncertainty.
    pub sigma_floor: f64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            baseline: 8,
            lambda: 0.2,
            width: 3.0,
            point_width: 3.5,
            window: 8,
            sigma_floor: 0.0,
        }
    }
}

/// Why a trend cannot be drawn.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum TrendError {
    #[error(
        "{have} points: a trend needs at least {need} (a baseline of {baseline} to learn the limits from, and one more)"
    )]
    TooFew {
        have: usize,
        need: usize,
        baseline: usize,
    },
    #[error("point {index} is not a number (day {days}, value {value})")]
    NotFinite { index: usize, days: f64, value: f64 },
    #[error(
        "point {index} (day {days:.2}) is before the point ahead of it: give the points in time order"
    )]
    Unordered { index: usize, days: f64 },
    #[error("{0}")]
    Settings(String),
}

/// The EWMA chart of a figure.
#[derive(Clone, Debug, PartialEq)]
pub struct Chart {
    /// The baseline's mean and the σ the limits assume.
    pub mean: f64,
    pub sigma: f64,
    /// The EWMA after each point.
    pub ewma: Vec<f64>,
    /// The limits (lower, upper) at each point.
    pub limits: Vec<(f64, f64)>,
    /// The first point after the baseline whose EWMA is outside its limits, or that is itself
    /// `point_width` σ from the mean: the drift alarm.
    pub alarm: Option<usize>,
}

impl Chart {
    /// Whether the newest point's EWMA is outside its limits.
    pub fn out_now(&self) -> bool {
        match (self.ewma.last(), self.limits.last()) {
            (Some(z), Some(&(lo, hi))) => *z < lo || *z > hi,
            _ => false,
        }
    }
}

fn check(points: &[Point], s: &Settings) -> Result<(), TrendError> {
    if !(s.lambda > 0.0 && s.lambda <= 1.0) {
        return Err(TrendError::Settings(format!(
            "lambda {} is not a weight: give 0 < λ ≤ 1 (0.2 is usual)",
            s.lambda
        )));
    }
    if !(s.point_width > 0.0 && s.point_width.is_finite()) {
        return Err(TrendError::Settings(format!(
            "point_width {} must be a positive number of standard deviations (3.5 is usual)",
            s.point_width
        )));
    }
    if !(s.width > 0.0 && s.width.is_finite()) {
        return Err(TrendError::Settings(format!(
            "width {} must be a positive number of standard deviations (3 is usual)",
            s.width
        )));
    }
    if s.baseline < 2 {
        return Err(TrendError::Settings(format!(
            "a baseline of {} point cannot give a scatter: give at least 2 (8 is usual)",
            s.baseline
        )));
    }
    if !(s.sigma_floor >= 0.0 && s.sigma_floor.is_finite()) {
        return Err(TrendError::Settings(format!(
            "sigma_floor {} must be 0 or more",
            s.sigma_floor
        )));
    }
    for (index, p) in points.iter().enumerate() {
        if !(p.days.is_finite() && p.value.is_finite()) {
            return Err(TrendError::NotFinite {
                index,
                days: p.days,
                value: p.value,
            });
        }
        if index > 0 && p.days < points[index - 1].days {
            return Err(TrendError::Unordered {
                index,
                days: p.days,
            });
        }
    }
    Ok(())
}

/// The EWMA chart of `points` (in time order) with limits from its first `s.baseline` points.
pub fn chart(points: &[Point], s: &Settings) -> Result<Chart, TrendError> {
    check(points, s)?;
    if points.len() <= s.baseline {
        return Err(TrendError::TooFew {
            have: points.len(),
            need: s.baseline + 1,
            baseline: s.baseline,
        });
    }
    let base: Vec<f64> = points[..s.baseline].iter().map(|p| p.value).collect();
    let n = base.len() as f64;
    let mean = base.iter().sum::<f64>() / n;
    let sd = (base.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let sigma = sd.max(s.sigma_floor);
    let (lambda, width) = (s.lambda, s.width);
    let mut z = mean;
    let mut ewma = Vec::with_capacity(points.len());
    let mut limits = Vec::with_capacity(points.len());
    let mut alarm = None;
    for (i, p) in points.iter().enumerate() {
        z = lambda * p.value + (1.0 - lambda) * z;
        let k = (i + 1) as i32;
        // The EWMA's variance about the true mean, plus the baseline mean's own (σ²/m): with
        // a baseline of 8, leaving it out put 4.7 % of a stable machine's checks outside.
        let half = width
            * sigma
            * (lambda / (2.0 - lambda) * (1.0 - (1.0 - lambda).powi(2 * k)) + 1.0 / n).sqrt();
        ewma.push(z);
        limits.push((mean - half, mean + half));
        let point = s.point_width * sigma * (1.0 + 1.0 / n).sqrt();
        let beyond = z < mean - half || z > mean + half || (p.value - mean).abs() > point;
        if alarm.is_none() && i >= s.baseline && beyond {
            alarm = Some(i);
        }
    }
    Ok(Chart {
        mean,
        sigma,
        ewma,
        limits,
        alarm,
    })
}

/// When the fitted line reaches the tolerance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Forecast {
    /// The line's slope (the figure's unit per day) and its standard uncertainty.
    pub slope_per_day: f64,
    pub slope_u: f64,
    /// The points the line was fitted to (the newest).
    pub points: usize,
    /// The day the line reaches the tolerance (days on the points' scale), with its 95 %
    /// interval; `None` when the line does not grow towards it.
    pub crossing: Option<Crossing>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing {
    pub day: f64,
    pub low: f64,
    pub high: f64,
}

/// Student's t at 97.5 % for `dof` degrees of freedom (1 to 30 tabulated; 1.96 beyond).
fn t975(dof: usize) -> f64 {
    const T: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    match dof {
        0 => f64::INFINITY,
        d if d <= 30 => T[d - 1],
        _ => 1.96,
    }
}

/// Runs closer together than this (days) give no forecast: a slope per day needs days.
pub const FORECAST_MIN_SPAN_DAYS: f64 = 1.0;

/// A crossing further ahead than this (days: a century) is none at all.
pub const FORECAST_HORIZON_DAYS: f64 = 36_525.0;

/// The line through the newest `window` points (at least 3, spanning at least
/// [`FORECAST_MIN_SPAN_DAYS`]) and the day it reaches `tolerance` (above the line's present
/// value, within [`FORECAST_HORIZON_DAYS`]), with a 95 % interval.
pub fn forecast(points: &[Point], tolerance: f64, window: usize) -> Option<Forecast> {
    let w = window.max(3).min(points.len());
    if w < 3 {
        return None;
    }
    let pts = &points[points.len() - w..];
    if pts[w - 1].days - pts[0].days < FORECAST_MIN_SPAN_DAYS {
        return None;
    }
    let n = w as f64;
    let tm = pts.iter().map(|p| p.days).sum::<f64>() / n;
    let ym = pts.iter().map(|p| p.value).sum::<f64>() / n;
    let sxx: f64 = pts.iter().map(|p| (p.days - tm).powi(2)).sum();
    if sxx <= 0.0 {
        return None;
    }
    let b = pts
        .iter()
        .map(|p| (p.days - tm) * (p.value - ym))
        .sum::<f64>()
        / sxx;
    let a = ym - b * tm;
    let rss: f64 = pts.iter().map(|p| (p.value - a - b * p.days).powi(2)).sum();
    let s2 = rss / (n - 2.0);
    let slope_u = (s2 / sxx).sqrt();
    let last = pts[w - 1].days;
    let ahead = (tolerance - a) / b;
    let reachable = b > 0.0 && tolerance > a + b * last && ahead - last <= FORECAST_HORIZON_DAYS;
    let crossing = reachable.then(|| {
        let day = ahead;
        // Delta method: the line's value at `day` is uncertain by s²(1/n + (day − t̄)²/Sxx);
        // divided by the slope, that is the day's.
        let u = (s2 * (1.0 / n + (day - tm).powi(2) / sxx)).sqrt() / b;
        let k = t975(w - 2);
        Crossing {
            day,
            low: (day - k * u).max(last),
            high: (day + k * u).min(last + FORECAST_HORIZON_DAYS),
        }
    });
    Some(Forecast {
        slope_per_day: b,
        slope_u,
        points: w,
        crossing,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::Rng;

    fn series(values: &[f64]) -> Vec<Point> {
        values
            .iter()
            .enumerate()
            .map(|(i, &value)| Point {
                days: i as f64,
                value,
            })
            .collect()
    }

    #[test]
    fn the_ewma_and_its_limits_are_the_textbook_ones() {
        // Baseline 1, 3 (mean 2, sd √2), then 2 and 8.
        let s = Settings {
            baseline: 2,
            lambda: 0.5,
            width: 2.0,
            point_width: 100.0,
            ..Settings::default()
        };
        let c = chart(&series(&[1.0, 3.0, 2.0, 8.0]), &s).unwrap();
        assert!((c.mean - 2.0).abs() < 1e-12 && (c.sigma - 2f64.sqrt()).abs() < 1e-12);
        // z: 0.5·1 + 0.5·2 = 1.5; 0.5·3 + 0.75 = 2.25; 1 + 1.125 = 2.125; 4 + 1.0625 = 5.0625.
        let want = [1.5, 2.25, 2.125, 5.0625];
        for (z, w) in c.ewma.iter().zip(want) {
            assert!((z - w).abs() < 1e-12, "{:?}", c.ewma);
        }
        // Limits at point 4: 2 ± 2·√2·√(0.5/1.5·(1 − 0.5⁸) + 1/2).
        let half = 2.0 * 2f64.sqrt() * (1.0 / 3.0 * (1.0 - 0.5f64.powi(8)) + 0.5).sqrt();
        assert!((c.limits[3].1 - (2.0 + half)).abs() < 1e-12);
        // 5.0625 is above 2 + 2.58: the alarm at the fourth point, not in the baseline.
        assert_eq!(c.alarm, Some(3));
        assert!(c.out_now());
        // A floor widens the limits: no alarm with σ ≥ 2.
        let floored = chart(
            &series(&[1.0, 3.0, 2.0, 8.0]),
            &Settings {
                sigma_floor: 2.0,
                ..s
            },
        )
        .unwrap();
        assert_eq!((floored.sigma, floored.alarm), (2.0, None));
    }

    #[test]
    fn bad_points_and_settings_are_refused_in_words() {
        let s = Settings::default();
        let e = chart(&series(&[1.0; 5]), &s).unwrap_err();
        assert_eq!(
            e.to_string(),
            "5 points: a trend needs at least 9 (a baseline of 8 to learn the limits from, and one more)"
        );
        let mut p = series(&[1.0; 10]);
        p[4].days = 2.5;
        assert!(
            chart(&p, &s)
                .unwrap_err()
                .to_string()
                .contains("point 4 (day 2.50) is before the point ahead of it")
        );
        p[4].days = 4.0;
        p[6].value = f64::NAN;
        assert!(matches!(
            chart(&p, &s),
            Err(TrendError::NotFinite { index: 6, .. })
        ));
        let e = chart(&series(&[1.0; 10]), &Settings { lambda: 0.0, ..s }).unwrap_err();
        assert!(e.to_string().contains("lambda 0 is not a weight"), "{e}");
    }

    /// A machine that does not drift: over 200 checks after its baseline, on 100 machines
    /// (seeds), the EWMA is outside its limits at no more than 1 % of the checks.
    #[test]
    fn a_stable_machine_rarely_alarms() {
        let (mut out, mut checks) = (0usize, 0usize);
        for seed in 0..100 {
            let mut rng = Rng::new(9000 + seed);
            let v: Vec<f64> = (0..208).map(|_| 5.0 + rng.gauss(0.3)).collect();
            let c = chart(
                &series(&v),
                &Settings {
                    // The figure's stated standard uncertainty.
                    sigma_floor: 0.3,
                    ..Settings::default()
                },
            )
            .unwrap();
            for i in 8..208 {
                checks += 1;
                let (lo, hi) = c.limits[i];
                out += usize::from(c.ewma[i] < lo || c.ewma[i] > hi);
            }
        }
        let rate = out as f64 / checks as f64;
        assert!(rate <= 0.01, "{out} of {checks} checks out of the limits");
    }

    /// A drift of 2 σ per check from check 12 on (a wear of 5 µm in 6 months, checked
    /// monthly, against 0.4 µm of scatter), on 100 machines: seen within 3 checks of its
    /// onset on at least 95 of them and within 5 on all, and never before it on 99.
    #[test]
    fn a_drift_is_seen_within_three_checks() {
        let (mut within3, mut early) = (0, 0);
        for seed in 0..100 {
            let mut rng = Rng::new(7000 + seed);
            let sd = 0.4;
            let per_check = 5.0 / 6.0;
            let v: Vec<f64> = (0..24)
                .map(|i| {
                    let drift = per_check * (i as f64 - 11.0).max(0.0);
                    5.0 + drift + rng.gauss(sd)
                })
                .collect();
            let c = chart(
                &series(&v),
                &Settings {
                    sigma_floor: sd,
                    ..Settings::default()
                },
            )
            .unwrap();
            let alarm = c.alarm.unwrap_or(usize::MAX);
            // Onset after check 11: checks 12, 13, 14 are the first three.
            early += usize::from(alarm < 12);
            within3 += usize::from((12..=14).contains(&alarm));
            assert!(alarm <= 16, "seed {seed}: alarm at {alarm}");
        }
        assert!(
            within3 >= 95 && early <= 1,
            "within 3: {within3}, early: {early}"
        );
    }

    /// One point far out (a crash, a loose gib) alarms at once by the point rule, where the
    /// EWMA alone would wait for more.
    #[test]
    fn a_single_large_change_alarms_at_once() {
        let mut rng = Rng::new(41);
        let mut v: Vec<f64> = (0..8).map(|_| 2.0 + rng.gauss(0.1)).collect();
        let base = chart(
            &series(&[v.clone(), vec![2.0]].concat()),
            &Settings::default(),
        )
        .unwrap();
        v.push(base.mean + 5.0 * base.sigma);
        let c = chart(&series(&v), &Settings::default()).unwrap();
        assert_eq!(c.alarm, Some(8));
        assert!(!c.out_now(), "the EWMA alone is still inside: {:?}", c.ewma);
    }

    #[test]
    fn the_forecast_finds_the_crossing_of_a_line_and_its_interval_covers_it() {
        // Exactly on a line: 2 + 0.05·t reaches 7 at day 100.
        let line: Vec<Point> = (0..10)
            .map(|i| Point {
                days: 5.0 * i as f64,
                value: 2.0 + 0.05 * 5.0 * i as f64,
            })
            .collect();
        let f = forecast(&line, 7.0, 8).unwrap();
        let c = f.crossing.unwrap();
        assert!((c.day - 100.0).abs() < 1e-9 && (c.high - c.low).abs() < 1e-6);
        assert!((f.slope_per_day - 0.05).abs() < 1e-12 && f.points == 8);
        // Falling or flat: no crossing.
        let falling: Vec<Point> = line
            .iter()
            .map(|p| Point {
                value: 10.0 - p.value,
                ..*p
            })
            .collect();
        assert!(forecast(&falling, 12.0, 8).unwrap().crossing.is_none());
        // Runs within a day of each other: no slope per day worth the name. A crossing a
        // thousand years out: none.
        let hours: Vec<Point> = line
            .iter()
            .map(|p| Point {
                days: p.days / 100.0,
                ..*p
            })
            .collect();
        assert!(forecast(&hours, 7.0, 8).is_none());
        let slow = forecast(&line, 2.0 + 0.05 * 400_000.0, 8).unwrap();
        assert!(slow.crossing.is_none() && slow.slope_per_day > 0.0);
        // With noise, 30 days ahead: the 95 % interval holds the true day on most seeds, and
        // the day itself is within ±20 % of the time left on most.
        let (mut covered, mut close, trials) = (0, 0, 400);
        for seed in 0..trials {
            let mut rng = Rng::new(500 + seed as u64);
            // Weekly checks for 10 weeks, 0.03 µm/day, 0.1 µm of scatter; tolerance at day 100.
            let pts: Vec<Point> = (0..10)
                .map(|i| {
                    let t = 7.0 * i as f64;
                    Point {
                        days: t,
                        value: 4.0 + 0.03 * t + rng.gauss(0.1),
                    }
                })
                .collect();
            let truth = (7.0 - 4.0) / 0.03;
            let f = forecast(&pts, 7.0, 10).unwrap();
            if let Some(c) = f.crossing {
                covered += usize::from(c.low <= truth && truth <= c.high);
                close += usize::from(((c.day - truth) / (truth - 63.0)).abs() <= 0.2);
            }
        }
        assert!(
            covered as f64 >= 0.92 * trials as f64,
            "covered {covered} of {trials}"
        );
        assert!(
            close as f64 >= 0.9 * trials as f64,
            "close {close} of {trials}"
        );
    }
}
