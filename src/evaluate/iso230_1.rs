//! ISO 230-1 straightness and angular errors of a linear axis.
//!
//! Straightness is the range (max − min) of the deviations from a reference line. Two lines:
//! least squares (the minimum-variance line through all points) and end point (through the
//! first and last). The line's slope is reported rather than discarded: for an optical head it
//! is mostly the beam's alignment to the travel, a setup figure, not a machine error (a slope in
//! µm/m of 1 is a misalignment of 1 µrad). Angular errors (pitch, roll, yaw) are the range of the
//! mean angles over the travel. Each is given per direction and for the bidirectional mean.

use super::range;
use serde::Serialize;

/// Which reference line straightness is taken from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum ReferenceLine {
    LeastSquares,
    EndPoint,
}

/// A reference line `value = intercept + slope · position` and the residuals from it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LineFit {
    pub method: ReferenceLine,
    /// mm per mm (dimensionless).
    pub slope: f64,
    /// Value of the line at position 0 (mm).
    pub intercept_mm: f64,
    /// Deviation minus line at every point (mm).
    pub residuals: Vec<f64>,
    /// Range of the residuals (mm).
    pub straightness: f64,
}

impl LineFit {
    /// The slope in µm/m (the user unit for beam alignment).
    pub fn slope_um_per_m(&self) -> f64 {
        self.slope * 1e6
    }
}

/// Fit the reference line to `values` at `positions`. `None` for fewer than 2 points or
/// positions that do not spread (the line is then undefined).
pub fn fit_line(positions: &[f64], values: &[f64], method: ReferenceLine) -> Option<LineFit> {
    let n = positions.len();
    if n < 2 || values.len() != n {
        return None;
    }
    let (slope, intercept) = match method {
        ReferenceLine::LeastSquares => {
            let pm = positions.iter().sum::<f64>() / n as f64;
            let vm = values.iter().sum::<f64>() / n as f64;
            let sxx: f64 = positions.iter().map(|p| (p - pm) * (p - pm)).sum();
            let sxy: f64 = positions
                .iter()
                .zip(values)
                .map(|(p, v)| (p - pm) * (v - vm))
                .sum();
            if sxx <= 0.0 {
                return None;
            }
            let b = sxy / sxx;
            (b, vm - b * pm)
        }
        ReferenceLine::EndPoint => {
            let dp = positions[n - 1] - positions[0];
            if dp == 0.0 {
                return None;
            }
            let b = (values[n - 1] - values[0]) / dp;
            (b, values[0] - b * positions[0])
        }
    };
    let residuals: Vec<f64> = positions
        .iter()
        .zip(values)
        .map(|(p, v)| v - (intercept + slope * p))
        .collect();
    Some(LineFit {
        method,
        slope,
        intercept_mm: intercept,
        straightness: range(residuals.iter().copied()),
        residuals,
    })
}

/// Straightness of one profile against both reference lines.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Straightness {
    pub least_squares: LineFit,
    pub end_point: LineFit,
}

impl Straightness {
    /// `None` where `fit_line` is undefined.
    pub fn of(positions: &[f64], values: &[f64]) -> Option<Straightness> {
        Some(Straightness {
            least_squares: fit_line(positions, values, ReferenceLine::LeastSquares)?,
            end_point: fit_line(positions, values, ReferenceLine::EndPoint)?,
        })
    }

    pub fn line(&self, method: ReferenceLine) -> &LineFit {
        match method {
            ReferenceLine::LeastSquares => &self.least_squares,
            ReferenceLine::EndPoint => &self.end_point,
        }
    }
}

/// Straightness per direction and of the bidirectional mean (the one direction's profile when
/// the data holds only one).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DirectionalStraightness {
    pub up: Option<Straightness>,
    pub down: Option<Straightness>,
    pub mean: Straightness,
}

/// Angular error (rad): range of the mean angles, per direction and of the bidirectional mean.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Angular {
    pub up: Option<f64>,
    pub down: Option<f64>,
    pub mean: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_by_hand() {
        // v = 1 + 0.5 p plus a bump of +1 at p = 2.
        let p = [0.0, 1.0, 2.0, 3.0, 4.0];
        let v = [1.0, 1.5, 3.0, 2.5, 3.0];
        let e = fit_line(&p, &v, ReferenceLine::EndPoint).unwrap();
        assert!((e.slope - 0.5).abs() < 1e-15 && (e.intercept_mm - 1.0).abs() < 1e-15);
        assert_eq!(e.residuals, vec![0.0, 0.0, 1.0, 0.0, 0.0]);
        assert_eq!(e.straightness, 1.0);
        // Least squares: p̄ = 2, v̄ = 2.2, Sxx = 10, Sxy = 5 → b = 0.5, a = 1.2.
        let l = fit_line(&p, &v, ReferenceLine::LeastSquares).unwrap();
        assert!((l.slope - 0.5).abs() < 1e-15 && (l.intercept_mm - 1.2).abs() < 1e-15);
        assert!((l.straightness - 1.0).abs() < 1e-15);
        assert!((l.slope_um_per_m() - 5e5).abs() < 1e-6);
        assert!(fit_line(&[1.0], &[1.0], ReferenceLine::EndPoint).is_none());
        assert!(fit_line(&[1.0, 1.0], &[1.0, 2.0], ReferenceLine::LeastSquares).is_none());
    }

    #[test]
    fn a_pure_tilt_has_no_straightness_and_its_slope_is_reported() {
        // A pure tilt has zero straightness on both lines.
        let p: Vec<f64> = (0..11).map(|k| k as f64 * 10.0).collect();
        let v: Vec<f64> = p.iter().map(|p| 0.003 + 2e-6 * p).collect();
        let s = Straightness::of(&p, &v).unwrap();
        assert!(s.least_squares.straightness < 1e-15);
        assert!(s.end_point.straightness < 1e-15);
        assert!((s.least_squares.slope_um_per_m() - 2.0).abs() < 1e-9);
    }
}
