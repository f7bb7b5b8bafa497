//! `[hexapod]`: the calibration hexapod's controller and how the calibration run takes its
//! poses (first stage `RawHexapod`, validated `HexapodSettings`; errors name the key, and
//! `config` adds the file that set it).

use super::driver::Timeouts;
use super::procedure::RunOptions;
use super::{Driver, HexPose, Workspace};
use serde::{Deserialize, Serialize};
use std::time::Duration;
use thiserror::Error;

/// `[hexapod]` as written.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawHexapod {
    /// "pi-gcs" (C-887), "newport-xps" (HXP) or "none".
    pub driver: String,
    /// host:port; empty for the controller's usual port on 127.0.0.1.
    pub address: String,
    /// The XPS positioner group.
    pub group: String,
    /// The pivot point (mm, platform frame): the head's reference point.
    pub pivot_mm: Vec<f64>,
    /// The work coordinate system (mm, degrees), relative to the controller's own.
    pub work: Vec<f64>,
    /// The usable workspace: ± per axis (mm, degrees).
    pub workspace: Vec<f64>,
    /// Linear speed (mm/s; GCS `VLS`, HXP actuator SGamma velocity); 0 keeps the controller's.
    pub speed_mm_s: f64,
    pub settle_ms: u64,
    pub frames: u64,
    pub stable_um: f64,
    pub timeout_ms: u64,
    pub motion_timeout_s: u64,
}

/// `[hexapod]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct HexapodSettings {
    /// None: no hexapod configured.
    pub driver: Option<Driver>,
    pub address: String,
    pub group: String,
    pub workspace: Workspace,
    pub speed_mm_s: f64,
    pub timeouts: Timeouts,
    pub run: RunOptions,
}

/// A `[hexapod]` key that is not valid: which, what is wrong and what to write instead.
#[derive(Clone, Debug, Error, PartialEq)]
#[error("hexapod.{key}: {problem}")]
pub struct HexapodConfigError {
    /// The key within `[hexapod]` (`driver`, `pivot_mm`, …).
    pub key: &'static str,
    pub problem: String,
}

impl HexapodConfigError {
    /// The key as the configuration names it (`hexapod.driver`).
    pub fn dotted_key(&self) -> String {
        format!("hexapod.{}", self.key)
    }
}

fn six(
    err: &dyn Fn(&'static str, String) -> HexapodConfigError,
    key: &'static str,
    v: &[f64],
    n: usize,
) -> Result<Vec<f64>, HexapodConfigError> {
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        return Err(err(
            key,
            format!(
                "give {n} finite numbers, e.g. [{}]",
                vec!["0"; n].join(", ")
            ),
        ));
    }
    Ok(v.to_vec())
}

/// Validate `[hexapod]`.
pub fn validate(raw: &RawHexapod) -> Result<HexapodSettings, HexapodConfigError> {
    let err = |key: &'static str, problem: String| HexapodConfigError { key, problem };
    let driver = match raw.driver.as_str() {
        "pi-gcs" => Some(Driver::PiGcs),
        "newport-xps" => Some(Driver::NewportXps),
        "none" | "" => None,
        other => {
            return Err(err(
                "driver",
                format!(
                    "\"{other}\": use \"pi-gcs\" (PI C-887), \"newport-xps\" (Newport HXP) or \"none\""
                ),
            ));
        }
    };
    let address = match (&driver, raw.address.trim()) {
        (Some(d), "") => format!("127.0.0.1:{}", d.default_port()),
        (_, a) => {
            if !a.is_empty()
                && a.rsplit_once(':')
                    .and_then(|(_, p)| p.parse::<u16>().ok())
                    .is_none()
            {
                return Err(err(
                    "address",
                    format!("\"{a}\" is not host:port, e.g. \"192.168.0.254:5001\""),
                ));
            }
            a.to_string()
        }
    };
    if raw.group.trim().is_empty() {
        return Err(err("group", "empty: the HXP's group is \"HEXAPOD\"".into()));
    }
    let pivot = six(&err, "pivot_mm", &raw.pivot_mm, 3)?;
    let work = six(&err, "work", &raw.work, 6)?;
    let ws = six(&err, "workspace", &raw.workspace, 6)?;
    if ws.iter().any(|x| *x <= 0.0) {
        return Err(err(
            "workspace",
            "every half-range must be positive (mm, degrees)".into(),
        ));
    }
    if !(raw.speed_mm_s.is_finite() && raw.speed_mm_s >= 0.0) {
        return Err(err(
            "speed_mm_s",
            format!(
                "{} must be zero (the controller's) or positive",
                raw.speed_mm_s
            ),
        ));
    }
    if raw.frames < 2 {
        return Err(err(
            "frames",
            format!("{}: average at least 2 frames per pose", raw.frames),
        ));
    }
    if !(raw.stable_um.is_finite() && raw.stable_um > 0.0) {
        return Err(err(
            "stable_um",
            format!("{} must be a positive number", raw.stable_um),
        ));
    }
    if raw.timeout_ms < 10 {
        return Err(err(
            "timeout_ms",
            format!("{} ms is too short: give at least 10 ms", raw.timeout_ms),
        ));
    }
    Ok(HexapodSettings {
        driver,
        address,
        group: raw.group.trim().to_string(),
        workspace: Workspace::symmetric(std::array::from_fn(|k| ws[k])),
        speed_mm_s: raw.speed_mm_s,
        timeouts: Timeouts {
            reply: Duration::from_millis(raw.timeout_ms),
            motion: Duration::from_secs(raw.motion_timeout_s.max(1)),
            ..Timeouts::default()
        },
        run: RunOptions {
            pivot: [pivot[0], pivot[1], pivot[2]],
            work: HexPose(std::array::from_fn(|k| work[k])),
            settle: Duration::from_millis(raw.settle_ms),
            frames: raw.frames as usize,
            stable_um: raw.stable_um,
            ..RunOptions::default()
        },
    })
}
