//! A level's stations along the follower's travel (DESIGN §4), as pure functions shared by
//! the service (`service::follower_level`) and the virtual-time lab (`sim::follower_cal`).
//!
//! A precision electronic level on the carriage reads the carriage's roll against gravity;
//! the head reads the same roll plus what the follower's vertical error, not taken out by the
//! map in tracking, puts into PSD2's Y (1.38″ per µm). At a station the carriage rests and
//! the head's roll, averaged over a few live windows, is read beside the level's: their
//! difference `e` is `g·(map − true vertical)` up to a constant common to all stations (the
//! zero, the level's own offset), g the roll's sensitivity to PSD2's Y (rad/mm). So
//! `value = map_vertical(encoder) − e/g` is the follower's true vertical at the station up to
//! that constant ([`LevelStation`]), with the variance of `e` from the readings' own scatter.

use super::LevelStation;
use crate::decouple::Decoupler;
use nalgebra::Vector6;
use thiserror::Error;

/// Why a station could not be read.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum LevelError {
    #[error(
        "the station has {head} readings of the head and {level} of the level: it needs two of the head and one of the level at least"
    )]
    TooFew { head: usize, level: usize },
    #[error("the head's reading could not be decoupled: {0}")]
    Decouple(String),
    #[error(
        "the roll does not depend on PSD2's Y ({0:e} rad/mm): the head cannot see the follower's vertical"
    )]
    Insensitive(f64),
}

/// The stations over `span` (mm): evenly spaced at most `station_mm` apart (1 mm at least),
/// both ends included.
pub fn stations(span: (f64, f64), station_mm: f64) -> Vec<f64> {
    let len = (span.1 - span.0).max(0.0);
    let n = ((len / station_mm.max(1.0)).ceil() as usize).max(1);
    (0..=n)
        .map(|k| span.0 + len * k as f64 / n as f64)
        .collect()
}

/// The head's roll minus the level's at a station (rad) and the variance of that mean
/// (rad²). `head` and `level` are the readings (rad); when they pair one to one (the twin's
/// level read with each window of the head) the difference's own scatter gives the variance,
/// never less than the level's stated `level_sd_rad` says; otherwise (a level read by hand,
/// once or a few times at the station) the head's mean and the level's mean, each with its
/// own variance (the level's at least its stated one).
pub fn excess(head: &[f64], level: &[f64], level_sd_rad: f64) -> Result<(f64, f64), LevelError> {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let scatter = |v: &[f64], m: f64| {
        if v.len() < 2 {
            0.0
        } else {
            v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64
        }
    };
    let sd2 = level_sd_rad * level_sd_rad;
    if head.len() < 2 || level.is_empty() {
        return Err(LevelError::TooFew {
            head: head.len(),
            level: level.len(),
        });
    }
    if head.len() == level.len() {
        let d: Vec<f64> = head.iter().zip(level).map(|(h, l)| h - l).collect();
        let m = mean(&d);
        let n = d.len() as f64;
        return Ok((m, scatter(&d, m).max(sd2) / n));
    }
    let (mh, ml) = (mean(head), mean(level));
    let var =
        scatter(head, mh) / head.len() as f64 + scatter(level, ml).max(sd2) / level.len() as f64;
    Ok((mh - ml, var))
}

/// The station at encoder position `encoder_mm`: the map's vertical applied in tracking there
/// (`map_vertical_mm`) less the excess `e` (rad, its variance `var`, rad²) through `g` (rad
/// per mm of PSD2's Y).
pub fn station(encoder_mm: f64, map_vertical_mm: f64, e: f64, var: f64, g: f64) -> LevelStation {
    LevelStation {
        position_mm: encoder_mm,
        value_mm: map_vertical_mm - e / g,
        variance_mm2: var / (g * g),
    }
}

/// The roll's sensitivity to PSD2's Y (rad per mm) where the head reads now: `readings` as
/// read (mm, PSD2's Y without the stitch's vertical), the carriage at `travel_mm`, PSD2 at
/// the stitch's `follower_mm` and `vertical_mm`; a forward difference of 1 µm through
/// `decoupler`.
pub fn roll_per_y2(
    decoupler: &Decoupler,
    readings: &Vector6<f64>,
    travel_mm: f64,
    follower_mm: f64,
    vertical_mm: f64,
) -> Result<f64, LevelError> {
    let mut r = *readings;
    r[3] += vertical_mm;
    let h = 1e-3;
    let e0 = decoupler
        .decouple(&r, travel_mm, follower_mm)
        .map_err(|e| LevelError::Decouple(e.to_string()))?;
    r[3] += h;
    let e1 = decoupler
        .decouple(&r, travel_mm, follower_mm)
        .map_err(|e| LevelError::Decouple(e.to_string()))?;
    let g = (e1.errors.ey - e0.errors.ey) / h;
    if !g.is_finite() || g.abs() < 1e-9 {
        return Err(LevelError::Insensitive(g));
    }
    Ok(g)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stations_span_evenly_with_both_ends() {
        assert_eq!(
            stations((0.0, 80.0), 20.0),
            vec![0.0, 20.0, 40.0, 60.0, 80.0]
        );
        assert_eq!(stations((10.0, 95.0), 40.0).len(), 4);
        assert_eq!(stations((5.0, 5.0), 100.0), vec![5.0, 5.0]);
    }

    #[test]
    fn paired_readings_take_their_scatter_unpaired_each_its_own() {
        // Paired: differences 1, 3 (mean 2, scatter 2): variance 2/2 = 1, above the level's.
        let (e, v) = excess(&[11.0, 13.0], &[10.0, 10.0], 0.1).unwrap();
        assert_eq!((e, v), (2.0, 1.0));
        // Paired with no scatter: the level's stated noise.
        let (_, v) = excess(&[1.0, 1.0, 1.0, 1.0], &[0.0; 4], 0.5).unwrap();
        assert!((v - 0.25 / 4.0).abs() < 1e-15);
        // One level reading by hand: the head's mean and its scatter, plus the level's.
        let (e, v) = excess(&[1.0, 3.0, 2.0], &[0.5], 0.2).unwrap();
        assert!((e - 1.5).abs() < 1e-15);
        assert!((v - (1.0 / 3.0 + 0.04)).abs() < 1e-12, "{v}");
        assert_eq!(
            excess(&[1.0], &[0.0], 0.1),
            Err(LevelError::TooFew { head: 1, level: 1 })
        );
        assert!(excess(&[1.0, 2.0], &[], 0.1).is_err());
    }

    #[test]
    fn a_station_is_the_map_less_the_excess_through_g() {
        let s = station(40.0, 2e-3, 1e-6, 4e-14, 2e-3);
        assert_eq!(s.position_mm, 40.0);
        assert!((s.value_mm - (2e-3 - 5e-4)).abs() < 1e-15);
        assert!((s.variance_mm2 - 1e-8).abs() < 1e-20);
    }
}
