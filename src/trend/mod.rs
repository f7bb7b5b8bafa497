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
//! for the one shift it is tuned to and worse for others. A point far above the mean alarms
//! by itself too (Lucas and Saccucci 1990's combined Shewhart-EWMA): a fast change is seen at
//! once. **Upward only:** every figure charted is a range or a deviation, larger is worse, and
//! a figure getting better calls for no maintenance; the widths are the one-sided ones with the
//! two-sided rates of L = 3 and a 3.5 σ point: L = 2.8 and 3.3 σ (a 2 σ-per-check drift seen
//! within 3 checks on 92 machines of 100 against 89 two-sided, at the same false-alarm rate).
//!
//! **Limits from the machine's own history:** `μ0` and `σ` are the mean and the standard
//! deviation of the first `baseline` points (the axis as commissioned), then of every point
//! since that gave no signal: the history grows with each check in control (a self-starting
//! chart, after Hawkins 1987). The limits are widened by the mean's own uncertainty (`σ²/m`
//! added to the EWMA's variance, m the points learned from), with σ not below `sigma_floor`
//! (the figure's stated standard uncertainty, when the caller knows it). Why the growing
//! history: σ from 8 points is uncertain by a quarter, and a machine whose first checks
//! happened to scatter little would cry wolf for ever (the twin's seed 11: σ of M from its
//! first 8 checks 0.029 µm against 0.046 µm over 200, and 25 of 200 stable checks outside
//! limits learned from the 8 alone). A drift is seen in the few checks after its onset, before
//! its points can move the history: a point is learned only once the checks after it have
//! raised no alarm that stood (an alarm that cleared by itself was the scatter).
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
    /// The upper limit's width in standard deviations of the EWMA (L); the lower limit is
    /// drawn, a figure below it does not alarm.
    pub width: f64,
    /// A single point this many σ above the history's mean alarms at once (the Shewhart rule
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
            width: 2.8,
            point_width: 3.3,
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
    /// The mean of the history the last limits were learned from, and the σ they assume.
    pub mean: f64,
    pub sigma: f64,
    /// The EWMA after each point.
    pub ewma: Vec<f64>,
    /// The limits (lower, upper) at each point.
    pub limits: Vec<(f64, f64)>,
    /// Whether each point signals: judged (after the baseline), its EWMA outside its limits or
    /// itself `point_width` σ from the mean.
    pub signals: Vec<bool>,
    /// The first point that signals: the drift alarm.
    pub alarm: Option<usize>,
    /// The values the limits were learned from at the end: the baseline and every later
    /// point settled without an alarm that stood (all but the newest few).
    pub history: Vec<f64>,
}

/// The limits' centre and scale, learned from a machine's history.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Baseline {
    /// The mean of the points learned from, and the σ the limits assume.
    pub mean: f64,
    pub sigma: f64,
    /// How many points it was learned from.
    pub points: usize,
    /// Whether σ is the floor (known, not estimated from the points).
    pub floored: bool,
}

impl Baseline {
    /// From the first `s.baseline` of `points` (at least one more must follow to chart).
    pub fn learn(points: &[Point], s: &Settings) -> Result<Baseline, TrendError> {
        check(points, s)?;
        if points.len() <= s.baseline {
            return Err(TrendError::TooFew {
                have: points.len(),
                need: s.baseline + 1,
                baseline: s.baseline,
            });
        }
        let base: Vec<f64> = points[..s.baseline].iter().map(|p| p.value).collect();
        Ok(Baseline::of(&base, s.sigma_floor))
    }

    /// From `values` (at least 2), σ not below `sigma_floor`.
    pub fn of(values: &[f64], sigma_floor: f64) -> Baseline {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let sd = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        Baseline {
            mean,
            sigma: sd.max(sigma_floor),
            points: values.len(),
            floored: sigma_floor >= sd,
        }
    }
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
            "point_width {} must be a positive number of standard deviations (3.3 is usual)",
            s.point_width
        )));
    }
    if !(s.width > 0.0 && s.width.is_finite()) {
        return Err(TrendError::Settings(format!(
            "width {} must be a positive number of standard deviations (2.8 is usual)",
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

/// The EWMA chart of `points` (in time order), its limits learned from its first
/// `s.baseline` points and every later one in control.
pub fn chart(points: &[Point], s: &Settings) -> Result<Chart, TrendError> {
    Baseline::learn(points, s)?;
    Ok(run(Vec::new(), points, s.baseline, s))
}

/// The EWMA chart of `points` against a history learned before (`history`: the values of the
/// points in control, as [`Chart::history`] gives them), every point judged, the EWMA starting
/// from the history's mean. After a new table has brought an axis back to how it was
/// commissioned, its checks are charted against its commissioned history again. `history`
/// needs at least 2 values (else nothing signals); `points` are taken as [`chart`] checked
/// them.
pub fn follow(history: &[f64], points: &[Point], s: &Settings) -> Chart {
    run(history.to_vec(), points, 0, s)
}

/// A point joins the history once this many later points have been judged, at a point that
/// gives no signal: the first points of a drift (still inside the limits) wait while the drift
/// is seen, which an EWMA does within a few checks, and are never learned while its alarm
/// stands; the points of an alarm that cleared by itself (the scatter) are learned when it
/// clears. Learning each point inside the limits at once let 2 σ-per-check drifts into the
/// history (18 of 100 machines seen later than their 3rd check); learning only the points
/// inside the limits kept limits drawn from a few quiet first checks narrow (10 false alarms
/// in 200 checks on one stable machine in 100).
const SETTLE: usize = 3;

/// The quantile of Student's t on `dof` degrees with the normal's tail beyond `z`: the
/// Cornish–Fisher expansion to 1/dof² (Abramowitz and Stegun 26.7.5): a little narrow at few
/// degrees (5.86 against the exact 6.16 at 7 degrees for z = 3.5, 4.42 against 4.53 for z =
/// 3), within 0.3 % from 20.
fn student_width(z: f64, dof: f64) -> f64 {
    if dof.is_infinite() {
        return z;
    }
    if dof.is_nan() || dof < 1.0 {
        return f64::INFINITY;
    }
    let (z3, z5) = (z.powi(3), z.powi(5));
    z + (z3 + z) / (4.0 * dof) + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * dof * dof)
}

/// Before point `i` is judged: when the point before it gave no signal, every point with
/// [`SETTLE`] points judged after it joins the history (`learned`: those before it have).
fn settle(
    history: &mut Vec<f64>,
    learned: &mut usize,
    points: &[Point],
    signals: &[bool],
    i: usize,
    unjudged: usize,
) {
    if i <= unjudged || signals.get(i - 1).copied().unwrap_or(true) {
        return;
    }
    while *learned + SETTLE < i {
        history.push(points[*learned].value);
        *learned += 1;
    }
}

/// The chart: the first `unjudged` points join the history at once (the baseline); each later
/// one is judged against the history before it, and joins it once settled ([`SETTLE`]).
fn run(mut history: Vec<f64>, points: &[Point], unjudged: usize, s: &Settings) -> Chart {
    history.extend(points.iter().take(unjudged).map(|p| p.value));
    let (lambda, width) = (s.lambda, s.width);
    let start = (history.len() >= 2).then(|| Baseline::of(&history, s.sigma_floor));
    let mut z = start.map_or(f64::NAN, |b| b.mean);
    let mut ewma = Vec::with_capacity(points.len());
    let mut limits = Vec::with_capacity(points.len());
    let mut signals: Vec<bool> = Vec::with_capacity(points.len());
    let mut b = start;
    // The points before this one are in the history (or were the baseline).
    let mut learned = unjudged;
    for (i, p) in points.iter().enumerate() {
        settle(&mut history, &mut learned, points, &signals, i, unjudged);
        if i >= unjudged && history.len() >= 2 {
            b = Some(Baseline::of(&history, s.sigma_floor));
        }
        let Some(base) = b else {
            ewma.push(f64::NAN);
            limits.push((f64::NAN, f64::NAN));
            signals.push(false);
            continue;
        };
        let (mean, sigma, n) = (base.mean, base.sigma, base.points as f64);
        z = lambda * p.value + (1.0 - lambda) * z;
        let k = (i + 1) as i32;
        // The EWMA's variance about the true mean, plus the history mean's own (σ²/m): with
        // a baseline of 8, leaving it out put 4.7 % of a stable machine's checks outside.
        // σ estimated from n points (not the floor): each width is the one Student's t on
        // n − 1 degrees gives the same tail as the normal's (σ from 8 points put 1 point in
        // 100 beyond 3.5 of its σ, not 1 in 2000).
        let dof = if base.floored { f64::INFINITY } else { n - 1.0 };
        let half = student_width(width, dof)
            * sigma
            * (lambda / (2.0 - lambda) * (1.0 - (1.0 - lambda).powi(2 * k)) + 1.0 / n).sqrt();
        ewma.push(z);
        limits.push((mean - half, mean + half));
        let point = student_width(s.point_width, dof) * sigma * (1.0 + 1.0 / n).sqrt();
        // Upward only: every figure here is a range or a deviation, larger is worse.
        let beyond = z > mean + half || p.value - mean > point;
        signals.push(i >= unjudged && beyond);
    }
    settle(
        &mut history,
        &mut learned,
        points,
        &signals,
        points.len(),
        unjudged,
    );
    let last = (history.len() >= 2).then(|| Baseline::of(&history, s.sigma_floor));
    let alarm = signals.iter().position(|&b| b);
    Chart {
        mean: last.map_or(f64::NAN, |b| b.mean),
        sigma: last.map_or(f64::NAN, |b| b.sigma),
        ewma,
        limits,
        signals,
        alarm,
        history,
    }
}

/// When the fitted line reaches the tolerance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Forecast {
    /// The line's slope (the figure's unit per day) and its standard uncertainty.
    pub slope_per_day: f64,
    pub slope_u: f64,
    /// The points the line was fitted to (the newest), and the newest's day: no crossing is
    /// forecast before it.
    pub points: usize,
    pub made_day: f64,
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

impl Forecast {
    /// The crossing's interval widened for the figure's own uncertainty `u` (standard, the
    /// figure's unit), which the points share and their scatter cannot show (a head that reads
    /// a range 0.2 µm low reads it low at every check: the line, and its crossing, lie late by
    /// 0.2 µm over the slope). Added in quadrature to the fit's, at k = 2.
    pub fn with_level_u(mut self, u: f64) -> Forecast {
        if let Some(c) = self.crossing.as_mut()
            && u > 0.0
            && self.slope_per_day > 0.0
        {
            let shift = 2.0 * u / self.slope_per_day;
            let widen = |half: f64| (half * half + shift * shift).sqrt();
            c.low = (c.day - widen(c.day - c.low)).max(self.made_day);
            c.high = c.day + widen(c.high - c.day);
        }
        self
    }
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
        made_day: last,
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
        // Baseline 1, 3 (mean 2, sd √2) under a floor of 1.5 (σ known: no widening for its
        // estimate), then 2 and 8.
        let s = Settings {
            baseline: 2,
            lambda: 0.5,
            width: 2.0,
            point_width: 100.0,
            sigma_floor: 1.5,
            ..Settings::default()
        };
        let c = chart(&series(&[1.0, 3.0, 2.0, 8.0]), &s).unwrap();
        // z: 0.5·1 + 0.5·2 = 1.5; 0.5·3 + 0.75 = 2.25; 1 + 1.125 = 2.125; 4 + 1.0625 = 5.0625.
        let want = [1.5, 2.25, 2.125, 5.0625];
        for (z, w) in c.ewma.iter().zip(want) {
            assert!((z - w).abs() < 1e-12, "{:?}", c.ewma);
        }
        // Limits at point 3: 2 ± 2·1.5·√(0.5/1.5·(1 − 0.5⁶) + 1/2); at point 4 the same
        // history (point 3 joins it only once 3 more are judged): 2 ± 3·√(1/3·(1 − 0.5⁸) + 1/2)
        // = 2 ± 2.737.
        let half = |k: i32| 3.0 * (1.0 / 3.0 * (1.0 - 0.5f64.powi(2 * k)) + 0.5).sqrt();
        assert!((c.limits[2].1 - (2.0 + half(3))).abs() < 1e-12);
        assert!((c.limits[3].1 - (2.0 + half(4))).abs() < 1e-12);
        // 5.0625 is above 4.737: the alarm at the fourth point, not in the baseline.
        assert_eq!(c.alarm, Some(3));
        assert!(c.out_now());
        assert_eq!(c.history, vec![1.0, 3.0]);
        // A higher floor widens the limits: no alarm with σ = 2 (2 + 3.65 at point 4).
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

    /// A point joins the history once 3 later points are judged at a point in control; those
    /// of an alarm that stands do not.
    #[test]
    fn the_history_grows_with_settled_points_only() {
        let s = Settings {
            baseline: 2,
            sigma_floor: 1.0,
            ..Settings::default()
        };
        // Baseline 1, 3; then 2, 2, 2, 2, 2: at the last, points 3 and 4 have 3 judged after
        // them.
        let c = chart(&series(&[1.0, 3.0, 2.0, 2.0, 2.0, 2.0, 2.0]), &s).unwrap();
        assert_eq!(c.history, vec![1.0, 3.0, 2.0, 2.0]);
        // A step of 20 σ that stands: none of its points, nor the three before it, is learned.
        let mut v = vec![1.0, 3.0, 2.0, 2.0, 2.0, 2.0];
        v.extend([22.0; 6]);
        let c = chart(&series(&v), &s).unwrap();
        assert_eq!(c.alarm, Some(6));
        assert_eq!(c.history, vec![1.0, 3.0, 2.0]);
    }

    /// Student's t widths against the exact quantiles (by numerical integration of its
    /// density): the same tail as the normal's beyond 3 and 3.5.
    #[test]
    fn student_widths_are_near_the_exact_quantiles() {
        for (dof, z, exact, within) in [
            (7.0, 3.0, 4.530, 0.03),
            (7.0, 3.5, 6.155, 0.05),
            (11.0, 3.0, 3.850, 0.01),
            (11.0, 3.5, 4.909, 0.015),
            (20.0, 3.0, 3.422, 0.003),
            (20.0, 3.5, 4.177, 0.003),
        ] {
            let w = student_width(z, dof);
            assert!(
                (w / exact - 1.0).abs() <= within,
                "{dof} degrees, z {z}: {w} against {exact}"
            );
        }
        assert_eq!(student_width(3.0, f64::INFINITY), 3.0);
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
        // No floor: the limits come from the machines' own checks alone, the first 8 of
        // which scatter as little as 0.56 σ on one machine in 20 (χ² on 7 degrees). At most
        // 0.5 % of the checks outside the limits (0.23 %), and at most 2 machines in 100 with
        // more than 1 % of their checks raising an alarm (2, with 3; 12 of 1000 machines).
        let (mut out, mut checks, mut worst, mut over2) = (0usize, 0usize, 0usize, 0usize);
        for seed in 0..100 {
            let mut rng = Rng::new(9000 + seed);
            let v: Vec<f64> = (0..208).map(|_| 5.0 + rng.gauss(0.3)).collect();
            let c = chart(&series(&v), &Settings::default()).unwrap();
            let alarms = (8..208)
                .filter(|&i| c.signals[i] && !c.signals[i - 1])
                .count();
            worst = worst.max(alarms);
            over2 += usize::from(alarms > 2);
            checks += 200;
            out += c.signals.iter().filter(|&&x| x).count();
        }
        let rate = out as f64 / checks as f64;
        assert!(
            rate <= 0.005 && over2 <= 2,
            "{out} of {checks} checks out of the limits; {over2} machines with more than 2 alarms in 200 checks (the most {worst})"
        );
    }

    /// A drift of `per_check_sd` σ per check from check 12 on, on 100 machines, σ learned
    /// from their own checks: how many see it within 3 checks of its onset, and how many
    /// alarm before it.
    fn drift_seen(per_check_sd: f64) -> (usize, usize) {
        let (mut within3, mut early) = (0, 0);
        for seed in 0..100 {
            let mut rng = Rng::new(7000 + seed);
            let sd = 0.4;
            let per_check = per_check_sd * sd;
            let v: Vec<f64> = (0..24)
                .map(|i| {
                    let drift = per_check * (i as f64 - 11.0).max(0.0);
                    5.0 + drift + rng.gauss(sd)
                })
                .collect();
            let c = chart(&series(&v), &Settings::default()).unwrap();
            let alarm = c.alarm.unwrap_or(usize::MAX);
            // Onset after check 11: checks 12, 13, 14 are the first three.
            early += usize::from(alarm < 12);
            within3 += usize::from((12..=14).contains(&alarm));
            assert!(alarm <= 17, "seed {seed}: alarm at {alarm}");
        }
        (within3, early)
    }

    /// A wear of 5 µm in 6 months checked monthly against 0.33 µm of scatter (2.5 σ per
    /// check) is seen within 3 checks of its onset on at least 95 machines of 100 (98), and
    /// never before it on 99; against 0.4 µm (2 σ per check), on at least 85 (92): the price
    /// of limits that widen for σ learned from a few checks (without the widening, 98 with 2 σ
    /// per check, and 4 stable machines in 100 with 3 false alarms in 200 checks).
    #[test]
    fn a_drift_is_seen_within_three_checks() {
        let (within3, early) = drift_seen(2.5);
        assert!(
            within3 >= 95 && early <= 1,
            "2.5 σ per check: within 3: {within3}, early: {early}"
        );
        let (within3, early) = drift_seen(2.0);
        assert!(
            within3 >= 85 && early <= 1,
            "2 σ per check: within 3: {within3}, early: {early}"
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
        // 8 σ: beyond the point rule's 3.3 σ widened for σ from 8 points (5.5 σ).
        v.push(base.mean + 8.0 * base.sigma);
        let c = chart(&series(&v), &Settings::default()).unwrap();
        assert_eq!(c.alarm, Some(8));
        assert!(!c.out_now(), "the EWMA alone is still inside: {:?}", c.ewma);
    }

    /// The figure's own uncertainty widens the crossing's interval by 2u over the slope, in
    /// quadrature; never before the newest point.
    #[test]
    fn a_stated_uncertainty_widens_the_crossing() {
        // 2 + 0.05·t through day 45 (10 points, exactly): the crossing of 7 on day 100, an
        // interval of zero width from the fit.
        let line: Vec<Point> = (0..10)
            .map(|i| Point {
                days: 5.0 * i as f64,
                value: 2.0 + 0.25 * i as f64,
            })
            .collect();
        let f = forecast(&line, 7.0, 8).unwrap().with_level_u(0.5);
        let c = f.crossing.unwrap();
        // 2·0.5/0.05 = 20 days either side; the low end no earlier than day 45.
        assert!(
            (c.high - 120.0).abs() < 1e-6 && (c.low - 80.0).abs() < 1e-6,
            "{c:?}"
        );
        let f = forecast(&line, 7.0, 8).unwrap().with_level_u(2.0);
        let c = f.crossing.unwrap();
        assert!((c.high - 180.0).abs() < 1e-6 && c.low == 45.0, "{c:?}");
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
