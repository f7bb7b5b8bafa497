//! The twin's configuration file (`axiscomp sim --config configs/sim.toml`), in two stages:
//! what the file says (`RawSimConfig`, unknown keys refused) and the validated `TwinSpec`.
//! Errors name the file and the key.

use super::axis::AxisSpec;
use super::drive::TwinDriveConfig;
use super::plant::{FollowerSpec, PlantSpec};
use super::twin::{TwinCan, TwinSpec};
use super::{InstallSpec, SimError};
use crate::acquire::IoMap;
use crate::canopen::Scaling;
use crate::optics::Layout;
use crate::util::range::{POSITION_MM, Range};
use serde::Deserialize;
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSimConfig {
    twin: RawTwin,
    io: RawIo,
    can: RawCan,
    drive: RawDrive,
    control: RawControl,
    #[serde(default)]
    plc: Option<RawPlc>,
    /// The twin hexapod's controller, read by `sim::hexapod_servers::spec_from_config`.
    #[serde(default)]
    #[serde(rename = "hexapod")]
    _hexapod: Option<toml::Value>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPlc {
    listen: String,
    map: String,
}

/// The twin's PLC (`[plc]`): where it listens and the CNC map it serves.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinPlcSpec {
    pub bind: SocketAddr,
    pub map: crate::plc::CncMap,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTwin {
    seed: u64,
    layout: String,
    axis: RawAxis,
    head: RawHead,
    follower: RawFollower,
    carriage: RawCarriage,
    #[serde(default)]
    level: Option<RawLevel>,
}

/// `[twin.level]`: the twin's electronic level on the carriage (the control socket's `level`).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLevel {
    /// One reading's standard deviation (µrad).
    sd_urad: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawAxis {
    length_mm: f64,
    positioning_um: f64,
    periodic_um: f64,
    lead_mm: f64,
    backlash_um: f64,
    straightness_um: f64,
    pitch_yaw_arcsec: f64,
    roll_arcsec: f64,
    thermal_um_per_m_per_h: f64,
    /// Ageing (issue 15): see `sim::axis::Wear`.
    #[serde(default)]
    wear_positioning_um: f64,
    #[serde(default)]
    wear_backlash_um: f64,
    #[serde(default)]
    wear_thermal_um: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHead {
    install_offset_mm: f64,
    install_tilt_deg: f64,
    /// How far from aligned the head is mounted on the axis (± each; 0: exactly).
    #[serde(default)]
    mount_angle_deg: f64,
    #[serde(default)]
    mount_offset_mm: f64,
    gain_error: f64,
    noise_um: f64,
    beam_drift_urad_per_sqrt_s: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFollower {
    positioning_um: f64,
    straightness_um: f64,
    #[serde(default = "default_follower_periodic_um")]
    periodic_um: f64,
    #[serde(default = "default_follower_lead_mm")]
    lead_mm: f64,
    #[serde(default = "default_follower_reversal_um")]
    reversal_um: f64,
    start_mm: f64,
    /// The instrument's identity (its own shapes, the same on every machine).
    #[serde(default)]
    instrument_seed: Option<u64>,
    /// Peak of this set-up's vertical bend of the rail (µm).
    #[serde(default)]
    bend_um: f64,
}

fn default_follower_periodic_um() -> f64 {
    FollowerSpec::default().periodic_um
}
fn default_follower_lead_mm() -> f64 {
    FollowerSpec::default().lead_mm
}
fn default_follower_reversal_um() -> f64 {
    FollowerSpec::default().reversal_um
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCarriage {
    feed_mm_s: f64,
    accel_mm_s2: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIo {
    listen: String,
    map: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCan {
    transport: String,
    #[serde(default)]
    local: String,
    #[serde(default)]
    remote: String,
    #[serde(default)]
    group: String,
    #[serde(default)]
    port: u16,
    #[serde(default)]
    iface: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDrive {
    node_id: u8,
    feed_mm: f64,
    shaft_revolutions: u32,
    encoder_increments: u32,
    motor_revolutions: u32,
    gear_ratio: f64,
    heartbeat_ms: u16,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawControl {
    listen: String,
}

/// The twin's layout and spec from a file.
pub fn load(path: &Path) -> Result<(Layout, TwinSpec), SimError> {
    load_all(path).map(|(l, s, _)| (l, s))
}

/// The twin's layout, spec and PLC (when the file has `[plc]`) from a file.
pub fn load_all(path: &Path) -> Result<(Layout, TwinSpec, Option<TwinPlcSpec>), SimError> {
    let label = path.display().to_string();
    let text = std::fs::read_to_string(path)
        .map_err(|e| SimError::Input(format!("twin config {label}: cannot read it: {e}")))?;
    parse_all(&text, &label)
}

/// Parse twin configuration text; `label` names it in errors.
pub fn parse(text: &str, label: &str) -> Result<(Layout, TwinSpec), SimError> {
    parse_all(text, label).map(|(l, s, _)| (l, s))
}

/// [`parse`], with the twin's PLC.
pub fn parse_all(
    text: &str,
    label: &str,
) -> Result<(Layout, TwinSpec, Option<TwinPlcSpec>), SimError> {
    let raw: RawSimConfig = toml::from_str(text).map_err(|e| {
        SimError::Input(format!(
            "twin config {label}: {}; see configs/sim.toml for every key",
            crate::util::toml_error_line(text, &e)
        ))
    })?;
    let bad = |key: &str, problem: String| {
        SimError::Input(format!("twin config {label}: {key}: {problem}"))
    };
    let addr = |key: &str, s: &str| -> Result<SocketAddr, SimError> {
        s.parse()
            .map_err(|_| bad(key, format!("\"{s}\" is not an address: write IP:port")))
    };
    let rng = |key: &str, v: f64, r: Range| r.check(v).map_err(|p| bad(key, p));
    // The twin's errors, as large as a worn or badly built machine's and no larger.
    let um = |max: f64| Range::new(0.0, max, "µm");
    let arcsec = Range::new(0.0, 3600.0, "arcsec");
    let wear = um(super::twin::WEAR_MAX_UM);
    let lead = Range::new(0.1, 100.0, "mm");
    // A head mounted and built within 10 mm and 10° of its design.
    let (mm10, deg10) = (
        Range::new(0.0, 10.0, "mm"),
        Range::new(0.0, 10.0, "degrees"),
    );
    let t = &raw.twin;
    let layout = match t.layout.as_str() {
        "builtin" | "builtin:reference" => Layout::reference(),
        p => Layout::load(Path::new(p)).map_err(|e| bad("twin.layout", e.to_string()))?,
    };
    let a = &t.axis;
    rng(
        "twin.axis.length_mm",
        a.length_mm,
        Range::new(1.0, 10_000.0, "mm"),
    )?;
    let h = &t.head;
    let plant = PlantSpec {
        seed: t.seed,
        axis: AxisSpec {
            length_mm: a.length_mm,
            positioning_um: rng("twin.axis.positioning_um", a.positioning_um, um(10_000.0))?,
            periodic_um: rng("twin.axis.periodic_um", a.periodic_um, um(1000.0))?,
            lead_mm: rng("twin.axis.lead_mm", a.lead_mm, lead)?,
            backlash_um: rng("twin.axis.backlash_um", a.backlash_um, um(1000.0))?,
            straightness_um: rng("twin.axis.straightness_um", a.straightness_um, um(10_000.0))?,
            pitch_yaw_arcsec: rng("twin.axis.pitch_yaw_arcsec", a.pitch_yaw_arcsec, arcsec)?,
            roll_arcsec: rng("twin.axis.roll_arcsec", a.roll_arcsec, arcsec)?,
            thermal_um_per_m_per_h: rng(
                "twin.axis.thermal_um_per_m_per_h",
                a.thermal_um_per_m_per_h,
                Range::symmetric(1000.0, "µm/m/h"),
            )?,
            wear: super::axis::Wear {
                positioning_um: rng("twin.axis.wear_positioning_um", a.wear_positioning_um, wear)?,
                backlash_um: rng("twin.axis.wear_backlash_um", a.wear_backlash_um, wear)?,
                thermal_um: rng("twin.axis.wear_thermal_um", a.wear_thermal_um, wear)?,
            },
        },
        install: InstallSpec {
            offset_mm: rng("twin.head.install_offset_mm", h.install_offset_mm, mm10)?,
            tilt_deg: rng("twin.head.install_tilt_deg", h.install_tilt_deg, deg10)?,
            gain_error: rng(
                "twin.head.gain_error",
                h.gain_error,
                Range::new(0.0, 0.5, ""),
            )?,
        },
        mount: super::plant::MountSpec {
            angle_deg: rng("twin.head.mount_angle_deg", h.mount_angle_deg, deg10)?,
            offset_mm: rng("twin.head.mount_offset_mm", h.mount_offset_mm, mm10)?,
        },
        noise_mm: rng("twin.head.noise_um", h.noise_um, um(1000.0))? * 1e-3,
        beam_drift_rad_per_sqrt_s: rng(
            "twin.head.beam_drift_urad_per_sqrt_s",
            h.beam_drift_urad_per_sqrt_s,
            Range::new(0.0, 1000.0, "µrad/√s"),
        )? * 1e-6,
        follower: FollowerSpec {
            positioning_um: rng(
                "twin.follower.positioning_um",
                t.follower.positioning_um,
                um(1000.0),
            )?,
            straightness_um: rng(
                "twin.follower.straightness_um",
                t.follower.straightness_um,
                um(1000.0),
            )?,
            periodic_um: rng(
                "twin.follower.periodic_um",
                t.follower.periodic_um,
                um(1000.0),
            )?,
            lead_mm: rng("twin.follower.lead_mm", t.follower.lead_mm, lead)?,
            reversal_um: rng(
                "twin.follower.reversal_um",
                t.follower.reversal_um,
                um(1000.0),
            )?,
            instrument_seed: t.follower.instrument_seed,
            bend_um: rng("twin.follower.bend_um", t.follower.bend_um, um(1000.0))?,
            rail_mm: None,
            kink: None,
        },
        feed: rng(
            "twin.carriage.feed_mm_s",
            t.carriage.feed_mm_s,
            Range::new(0.1, 2000.0, "mm/s"),
        )?,
        accel: rng(
            "twin.carriage.accel_mm_s2",
            t.carriage.accel_mm_s2,
            Range::new(1.0, 1e6, "mm/s²"),
        )?,
        level_sd_rad: match &t.level {
            Some(l) => {
                rng(
                    "twin.level.sd_urad",
                    l.sd_urad,
                    Range::new(0.0, 1000.0, "µrad"),
                )? * 1e-6
            }
            None => PlantSpec::default().level_sd_rad,
        },
        ..PlantSpec::default()
    };
    let io_map = match raw.io.map.as_str() {
        "builtin" | "builtin:generic" => IoMap::generic(),
        p => IoMap::load(Path::new(p)),
    }
    .map_err(|e| bad("io.map", e.to_string()))?;
    let c = &raw.can;
    let can = match c.transport.as_str() {
        "cannelloni" => TwinCan::Cannelloni {
            local: addr("can.local", &c.local)?,
            remote: addr("can.remote", &c.remote)?,
        },
        "pycan" => TwinCan::PyCan {
            group: c
                .group
                .parse()
                .map_err(|_| bad("can.group", format!("\"{}\" is not an IPv4 group", c.group)))?,
            port: c.port,
            iface: c.iface.parse().map_err(|_| {
                bad(
                    "can.iface",
                    format!("\"{}\" is not an IPv4 address", c.iface),
                )
            })?,
        },
        other => {
            return Err(bad(
                "can.transport",
                format!("\"{other}\": the twin speaks cannelloni or pycan"),
            ));
        }
    };
    let d = &raw.drive;
    rng("drive.feed_mm", d.feed_mm, Range::new(0.01, 1000.0, "mm"))?;
    rng(
        "drive.gear_ratio",
        d.gear_ratio,
        Range::new(0.001, 1000.0, ""),
    )?;
    rng("twin.follower.start_mm", t.follower.start_mm, POSITION_MM)?;
    let drive = TwinDriveConfig {
        node_id: d.node_id,
        scaling: Scaling {
            feed_mm: d.feed_mm,
            shaft_revolutions: d.shaft_revolutions,
            encoder_increments: d.encoder_increments,
            motor_revolutions: d.motor_revolutions,
            gear_ratio: d.gear_ratio,
        },
        start_mm: t.follower.start_mm,
        default_heartbeat_ms: d.heartbeat_ms,
        tick: Duration::from_millis(2),
        ..TwinDriveConfig::default()
    };
    if !(1..=127).contains(&drive.node_id) {
        return Err(bad(
            "drive.node_id",
            format!("{} is not a CANopen node id (1 to 127)", drive.node_id),
        ));
    }
    let plc = match &raw.plc {
        Some(p) => Some(TwinPlcSpec {
            bind: addr("plc.listen", &p.listen)?,
            map: match p.map.as_str() {
                "builtin" | "builtin:generic" => crate::plc::CncMap::generic(),
                f => crate::plc::CncMap::load(Path::new(f)),
            }
            .map_err(|e| bad("plc.map", e.to_string()))?,
        }),
        None => None,
    };
    Ok((
        layout,
        TwinSpec {
            plant,
            io_bind: addr("io.listen", &raw.io.listen)?,
            io_map,
            can,
            drive,
            control: Some(addr("control.listen", &raw.control.listen)?),
        },
        plc,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_sim_config_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/sim.toml");
        let (_, spec, plc) = load_all(&path).unwrap();
        assert_eq!(spec.plant.axis.length_mm, 1000.0);
        let plc = plc.expect("[plc]");
        assert_eq!(plc.bind, "127.0.0.1:5502".parse().unwrap());
        assert_eq!(plc.map, crate::plc::CncMap::generic().unwrap());
        assert!(matches!(spec.can, TwinCan::Cannelloni { .. }));
    }

    #[test]
    fn errors_name_file_and_key() {
        let text =
            std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/sim.toml"))
                .unwrap();
        let e = parse(
            &text.replace("noise_um = 1.0", "noise_um = -1.0"),
            "sim.toml",
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("sim.toml: twin.head.noise_um"),
            "{e}"
        );
        let e = parse(
            &text.replace("[control]", "[control]\ncolour = 1"),
            "sim.toml",
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("in [control]: unknown key `colour`"),
            "{e}"
        );
        let e = parse(
            &text.replace("transport = \"cannelloni\"", "transport = \"usb\""),
            "sim.toml",
        )
        .unwrap_err();
        assert!(e.to_string().contains("can.transport"), "{e}");
        let e = parse(
            &text.replace(
                "listen = \"127.0.0.1:5502\"\nmap = \"builtin:generic\"",
                "listen = \"127.0.0.1:5502\"\nmap = \"no-such.toml\"",
            ),
            "sim.toml",
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("sim.toml: plc.map") && e.to_string().contains("no-such.toml"),
            "{e}"
        );
    }
}
