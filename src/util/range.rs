//! Range checks for numbers read from input (configuration files, maps, plans, CSVs, control
//! requests): each number has one accepted range in its unit, and a value outside it (NaN,
//! ±inf, or a value no machine has) is refused with the range in words, before it can reach
//! a `Duration`, an allocation or a drive. Callers put the key (or the column and line) in
//! front and wrap the problem in their own error type.

use std::fmt::Display;
use std::time::Duration;

/// The accepted range of one number: `min..=max` in `unit`, and optionally 0 besides it with
/// a meaning ("off", "not specified").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    pub min: f64,
    pub max: f64,
    /// The unit as the user writes it ("Hz", "mm", "µm"); empty for a plain number.
    pub unit: &'static str,
    /// What 0 means when it is accepted outside `min..=max`.
    pub zero: Option<&'static str>,
    /// Negative values are accepted too, by their magnitude (a gain that inverts an axis).
    pub either_sign: bool,
}

/// A position along a machine axis, or a span's end (mm): ±10 m, the longest axes built.
pub const POSITION_MM: Range = Range::symmetric(10_000.0, "mm");

/// A feed of the carriage (mm/min): up to 100 m/min, as fast as linear motors go.
pub const FEED_MM_MIN: Range = Range::new(1.0, 100_000.0, "mm/min");

impl Range {
    pub const fn new(min: f64, max: f64, unit: &'static str) -> Range {
        Range {
            min,
            max,
            unit,
            zero: None,
            either_sign: false,
        }
    }

    /// `-max..=max`.
    pub const fn symmetric(max: f64, unit: &'static str) -> Range {
        Range::new(-max, max, unit)
    }

    /// The same range with 0 accepted besides it, meaning `meaning`.
    pub const fn or_zero(self, meaning: &'static str) -> Range {
        Range {
            zero: Some(meaning),
            ..self
        }
    }

    /// The same range for either sign: `-max..=-min` too.
    pub const fn either_sign(self) -> Range {
        Range {
            either_sign: true,
            ..self
        }
    }

    /// Whether `v` is accepted.
    pub fn contains(&self, v: f64) -> bool {
        let m = if self.either_sign { v.abs() } else { v };
        (self.min..=self.max).contains(&m) || (self.zero.is_some() && v == 0.0)
    }

    /// `v` when accepted, else the problem in words: "1e300 Hz is out of range: use 0.1 to
    /// 100 Hz".
    pub fn check(&self, v: f64) -> Result<f64, String> {
        if self.contains(v) {
            Ok(v)
        } else {
            Err(self.problem(v))
        }
    }

    /// Why `v` is refused.
    pub fn problem(&self, v: f64) -> String {
        if v.is_nan() {
            format!("nan is not a number: use {}", self.describe())
        } else {
            format!(
                "{} is out of range: use {}",
                with_unit(num(v), self.unit),
                self.describe()
            )
        }
    }

    /// The range in words: "0.1 to 100 Hz", "0 (off) or 5 to 100 µm", "-10 to -0.1 or 0.1
    /// to 10 mm/V".
    pub fn describe(&self) -> String {
        let mut span = format!("{} to {}", num(self.min), num(self.max));
        if self.either_sign {
            span = format!("{} to {} or {span}", num(-self.max), num(-self.min));
        }
        let span = with_unit(span, self.unit);
        match self.zero {
            Some(meaning) => format!("0 ({meaning}) or {span}"),
            None => span,
        }
    }

    /// `v` (in units of `secs_per_unit` seconds: 3600 for hours) as a duration, when accepted.
    pub fn duration(&self, v: f64, secs_per_unit: f64) -> Result<Duration, String> {
        let v = self.check(v)?;
        Duration::try_from_secs_f64(v * secs_per_unit).map_err(|_| self.problem(v))
    }

    /// The period of a rate `hz` in this range (which must exclude 0).
    pub fn period(&self, hz: f64) -> Result<Duration, String> {
        let hz = self.check(hz)?;
        Duration::try_from_secs_f64(1.0 / hz).map_err(|_| self.problem(hz))
    }
}

/// An integer (a count, an id, milliseconds) within `min..=max`, or the problem in words:
/// "0 ms is out of range: use 1 to 60000 ms".
pub fn int<T: PartialOrd + Display + Copy>(v: T, min: T, max: T, unit: &str) -> Result<T, String> {
    if v >= min && v <= max {
        Ok(v)
    } else {
        Err(format!(
            "{} is out of range: use {}",
            with_unit(v.to_string(), unit),
            with_unit(format!("{min} to {max}"), unit)
        ))
    }
}

/// A request's field `name`, when given, within `r`; the problem names the field:
/// `"hz": 1e-300 Hz is out of range: use 0.1 to 100 Hz`.
pub fn field(name: &str, v: Option<f64>, r: Range) -> Result<(), String> {
    match v {
        Some(v) => r.check(v).map(drop).map_err(|p| format!("\"{name}\": {p}")),
        None => Ok(()),
    }
}

/// A request's integer field `name`, when given, within `min..=max`, like [`field`].
pub fn int_field<T: PartialOrd + Display + Copy>(
    name: &str,
    v: Option<T>,
    min: T,
    max: T,
) -> Result<(), String> {
    match v {
        Some(v) => int(v, min, max, "")
            .map(drop)
            .map_err(|p| format!("\"{name}\": {p}")),
        None => Ok(()),
    }
}

fn with_unit(s: String, unit: &str) -> String {
    if unit.is_empty() {
        s
    } else {
        format!("{s} {unit}")
    }
}

/// A number for a message: as written when short (0.1, 8760, -0), in exponent form when it
/// would be long (1e300, 5e-324), `nan`, `inf`, `-inf`.
pub fn num(v: f64) -> String {
    if v.is_nan() {
        "nan".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf" } else { "-inf" }.into()
    } else if v == 0.0 || (1e-4..1e9).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_say_the_value_and_the_range_in_words() {
        let hz = Range::new(0.1, 100.0, "Hz");
        assert_eq!(hz.check(10.0), Ok(10.0));
        for (v, msg) in [
            (1e-300, "1e-300 Hz is out of range: use 0.1 to 100 Hz"),
            (1e300, "1e300 Hz is out of range: use 0.1 to 100 Hz"),
            (f64::INFINITY, "inf Hz is out of range: use 0.1 to 100 Hz"),
            (
                f64::NEG_INFINITY,
                "-inf Hz is out of range: use 0.1 to 100 Hz",
            ),
            (f64::NAN, "nan is not a number: use 0.1 to 100 Hz"),
            (-1.0, "-1 Hz is out of range: use 0.1 to 100 Hz"),
            (5e-324, "5e-324 Hz is out of range: use 0.1 to 100 Hz"),
            (-0.0, "-0 Hz is out of range: use 0.1 to 100 Hz"),
        ] {
            assert_eq!(hz.check(v), Err(msg.to_string()), "{v}");
        }
        let um = Range::new(5.0, 100.0, "µm").or_zero("none");
        assert_eq!((um.check(0.0), um.check(-0.0)), (Ok(0.0), Ok(-0.0)));
        assert_eq!(
            um.check(1.0).unwrap_err(),
            "1 µm is out of range: use 0 (none) or 5 to 100 µm"
        );
        let gain = Range::new(0.1, 10.0, "mm/V").either_sign();
        assert_eq!((gain.check(-2.0), gain.check(0.5)), (Ok(-2.0), Ok(0.5)));
        assert_eq!(
            gain.check(-1e300).unwrap_err(),
            "-1e300 mm/V is out of range: use -10 to -0.1 or 0.1 to 10 mm/V"
        );
        assert_eq!(
            Range::new(2.0, 1e6, "").check(1e12).unwrap_err(),
            "1e12 is out of range: use 2 to 1000000"
        );
        assert_eq!(
            int(0u64, 1, 60_000, "ms").unwrap_err(),
            "0 ms is out of range: use 1 to 60000 ms"
        );
        assert_eq!(
            int(u64::MAX, 1, 10, ""),
            Err(format!("{} is out of range: use 1 to 10", u64::MAX))
        );
        assert_eq!(int(-3i64, -5, 5, "mm"), Ok(-3));
    }

    #[test]
    fn durations_never_panic() {
        let h = Range::new(0.1, 8760.0, "h");
        assert_eq!(h.duration(24.0, 3600.0), Ok(Duration::from_secs(86_400)));
        assert!(h.duration(1e300, 3600.0).is_err());
        assert!(h.duration(f64::NAN, 3600.0).is_err());
        let hz = Range::new(0.1, 100.0, "Hz");
        assert_eq!(hz.period(10.0), Ok(Duration::from_millis(100)));
        assert!(hz.period(1e-300).is_err() && hz.period(0.0).is_err());
    }
}
