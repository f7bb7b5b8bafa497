//! `[hexapod]`: the calibration hexapod's controller and how the calibration run takes its
//! poses (first stage `RawHexapod`, validated `HexapodSettings`; errors name the key, and
//! `config` adds the file that set it).

use super::driver::Timeouts;
use super::procedure::RunOptions;
use super::{Driver, HexPose, Workspace};
use crate::util::range::{self, Range};
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

/// `n` numbers, the `k`-th (`x`, `y`, `z`, `u`, `v`, `w`) within `range(k)`.
fn six(
    err: &dyn Fn(&'static str, String) -> HexapodConfigError,
    key: &'static str,
    v: &[f64],
    n: usize,
    range: impl Fn(usize) -> Range,
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
    for (k, x) in v.iter().enumerate() {
        range(k)
            .check(*x)
            .map_err(|p| err(key, format!("{} = {p}", super::AXES[k].to_lowercase())))?;
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
    // Positions within a metre of the controller's origin, angles within a half turn; a
    // half-range of the workspace up to a metre or a right angle.
    let (mm, deg) = (
        Range::symmetric(1000.0, "mm"),
        Range::symmetric(180.0, "degrees"),
    );
    let pivot = six(&err, "pivot_mm", &raw.pivot_mm, 3, |_| mm)?;
    let work = six(&err, "work", &raw.work, 6, |k| if k < 3 { mm } else { deg })?;
    let ws = six(&err, "workspace", &raw.workspace, 6, |k| {
        if k < 3 {
            Range::new(0.001, 1000.0, "mm")
        } else {
            Range::new(0.001, 90.0, "degrees")
        }
    })?;
    let speed = Range::new(0.001, 1000.0, "mm/s").or_zero("the controller's");
    speed
        .check(raw.speed_mm_s)
        .map_err(|p| err("speed_mm_s", p))?;
    if raw.frames < 2 {
        return Err(err(
            "frames",
            format!("{}: average at least 2 frames per pose", raw.frames),
        ));
    }
    range::int(raw.frames, 2, 100_000, "").map_err(|p| err("frames", p))?;
    Range::new(0.001, 1000.0, "µm")
        .check(raw.stable_um)
        .map_err(|p| err("stable_um", p))?;
    if raw.timeout_ms < 10 {
        return Err(err(
            "timeout_ms",
            format!("{} ms is too short: give at least 10 ms", raw.timeout_ms),
        ));
    }
    let ms = |key: &'static str, v: u64, min: u64, max: u64| {
        range::int(v, min, max, "ms")
            .map(Duration::from_millis)
            .map_err(|p| err(key, p))
    };
    let reply = ms("timeout_ms", raw.timeout_ms, 10, 600_000)?;
    let settle = ms("settle_ms", raw.settle_ms, 0, 60_000)?;
    let motion = range::int(raw.motion_timeout_s, 1, 86_400, "s")
        .map(Duration::from_secs)
        .map_err(|p| err("motion_timeout_s", p))?;
    Ok(HexapodSettings {
        driver,
        address,
        group: raw.group.trim().to_string(),
        workspace: Workspace::symmetric(std::array::from_fn(|k| ws[k])),
        speed_mm_s: raw.speed_mm_s,
        timeouts: Timeouts {
            reply,
            motion,
            ..Timeouts::default()
        },
        run: RunOptions {
            pivot: [pivot[0], pivot[1], pivot[2]],
            work: HexPose(std::array::from_fn(|k| work[k])),
            settle,
            frames: raw.frames as usize,
            stable_um: raw.stable_um,
            ..RunOptions::default()
        },
    })
}
