//! A cubic spline through tabulated points, for resampling a measured profile finer than it
//! was measured (a machine's errors are smooth between the targets; a control interpolates
//! its table linearly, so the table it gets should already follow the curve).
//!
//! The interpolating cubic with continuous first and second derivatives, "not-a-knot" at the
//! ends (one cubic over the first two intervals and over the last two: exact for cubics, where
//! a "natural" spline's zero curvature at the ends is not). Fewer than four points: straight
//! lines between them.

/// A spline through `(x, y)`, `x` strictly increasing.
#[derive(Clone, Debug, PartialEq)]
pub struct Spline {
    x: Vec<f64>,
    y: Vec<f64>,
    /// Second derivatives at the knots.
    m: Vec<f64>,
}

impl Spline {
    /// `None` unless `x` and `y` have the same length (two or more), `x` strictly increasing
    /// and every value finite.
    pub fn new(x: &[f64], y: &[f64]) -> Option<Spline> {
        let n = x.len();
        let ok = n >= 2
            && y.len() == n
            && x.iter().chain(y).all(|v| v.is_finite())
            && x.windows(2).all(|w| w[1] > w[0]);
        if !ok {
            return None;
        }
        let mut m = vec![0.0; n];
        if n >= 4 {
            // The interior: h_{i-1}·m_{i-1} + 2(h_{i-1} + h_i)·m_i + h_i·m_{i+1} = 6·(d_i − d_{i-1});
            // not-a-knot at both ends (the third derivative continuous at the second and the
            // last-but-one knot) folds m_0 and m_{n-1} into the first and last rows. Tridiagonal,
            // by the Thomas algorithm.
            let h: Vec<f64> = x.windows(2).map(|w| w[1] - w[0]).collect();
            let d: Vec<f64> = (0..n - 1).map(|i| (y[i + 1] - y[i]) / h[i]).collect();
            let k = n - 2;
            let mut sub: Vec<f64> = (0..k).map(|j| h[j]).collect();
            let mut diag: Vec<f64> = (0..k).map(|j| 2.0 * (h[j] + h[j + 1])).collect();
            let mut sup: Vec<f64> = (0..k).map(|j| h[j + 1]).collect();
            let mut rhs: Vec<f64> = (0..k).map(|j| 6.0 * (d[j + 1] - d[j])).collect();
            let (h0, h1) = (h[0], h[1]);
            diag[0] = 3.0 * h0 + 2.0 * h1 + h0 * h0 / h1;
            sup[0] = h1 - h0 * h0 / h1;
            let (hp, hl) = (h[n - 3], h[n - 2]);
            sub[k - 1] = hp - hl * hl / hp;
            diag[k - 1] = 2.0 * hp + 3.0 * hl + hl * hl / hp;
            for j in 1..k {
                let w = sub[j] / diag[j - 1];
                diag[j] -= w * sup[j - 1];
                rhs[j] -= w * rhs[j - 1];
            }
            m[k] = rhs[k - 1] / diag[k - 1];
            for j in (0..k - 1).rev() {
                m[j + 1] = (rhs[j] - sup[j] * m[j + 2]) / diag[j];
            }
            m[0] = m[1] * (1.0 + h0 / h1) - m[2] * h0 / h1;
            m[n - 1] = m[n - 2] * (1.0 + hl / hp) - m[n - 3] * hl / hp;
        }
        Some(Spline {
            x: x.to_vec(),
            y: y.to_vec(),
            m,
        })
    }

    /// The value at `q`; beyond the ends, the end values held.
    pub fn at(&self, q: f64) -> f64 {
        let (x, y, m) = (&self.x, &self.y, &self.m);
        let last = x.len() - 1;
        if q <= x[0] {
            return y[0];
        }
        if q >= x[last] {
            return y[last];
        }
        let i = x.partition_point(|&v| v <= q).clamp(1, last) - 1;
        let h = x[i + 1] - x[i];
        let (a, b) = ((x[i + 1] - q) / h, (q - x[i]) / h);
        a * y[i]
            + b * y[i + 1]
            + ((a * a * a - a) * m[i] + (b * b * b - b) * m[i + 1]) * h * h / 6.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cubic is reproduced exactly, on uneven knots, between them and at the ends.
    #[test]
    fn a_cubic_is_reproduced_exactly() {
        let f = |x: f64| 0.3 - 1.2 * x + 0.05 * x * x - 0.002 * x * x * x;
        let x = [0.0, 1.0, 2.5, 3.0, 5.0, 6.5, 9.0, 10.0];
        let y: Vec<f64> = x.iter().map(|&v| f(v)).collect();
        let s = Spline::new(&x, &y).expect("spline");
        for i in 0..=100 {
            let q = i as f64 / 10.0;
            assert!(
                (s.at(q) - f(q)).abs() < 1e-12,
                "at {q}: {} vs {}",
                s.at(q),
                f(q)
            );
        }
    }

    /// A sine sampled 9 times a wavelength: the spline stays within 0.5 % of its amplitude
    /// between the knots (0.44 %; the interior's bound 5h⁴·max|f⁗|/384 is 0.3 %, the ends add
    /// a little), straight lines 6 % off.
    #[test]
    fn a_smooth_curve_is_followed_between_the_knots() {
        let f = |x: f64| (2.0 * std::f64::consts::PI * x / 90.0).sin();
        let x: Vec<f64> = (0..=50).map(|i| i as f64 * 10.0).collect();
        let y: Vec<f64> = x.iter().map(|&v| f(v)).collect();
        let s = Spline::new(&x, &y).expect("spline");
        let (mut spline, mut linear) = (0.0f64, 0.0f64);
        for i in 0..=5000 {
            let q = i as f64 * 0.1;
            spline = spline.max((s.at(q) - f(q)).abs());
            linear = linear.max((crate::util::interpolate(&x, &y, q) - f(q)).abs());
        }
        assert!(spline < 5e-3, "spline {spline}");
        assert!(linear > 0.05, "linear {linear}");
    }

    #[test]
    fn few_points_are_joined_by_lines_and_bad_input_is_refused() {
        let s = Spline::new(&[0.0, 2.0, 4.0], &[0.0, 2.0, 0.0]).expect("spline");
        assert_eq!(s.at(1.0), 1.0);
        assert_eq!(s.at(3.0), 1.0);
        assert_eq!(s.at(-1.0), 0.0);
        assert!(Spline::new(&[0.0, 0.0], &[1.0, 2.0]).is_none());
        assert!(Spline::new(&[0.0, 1.0], &[1.0]).is_none());
        assert!(Spline::new(&[0.0, 1.0], &[1.0, f64::NAN]).is_none());
    }
}
