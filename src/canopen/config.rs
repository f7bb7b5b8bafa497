//! Configuration of the follower drive link, in two stages (DESIGN §11): `DriveConfig` holds
//! the raw values with defaults (a later step fills it from the TOML config), and
//! [`DriveConfig::validate`] turns it into `DriveSettings` with the node id checked and the
//! mm ↔ position-unit scaling worked out. Errors quote the key and the bad value and say what
//! is allowed.
//!
//! Positions: the drive's position values (0x607A target, 0x6064 actual) are taken to be in
//! encoder increments, and mm are converted with `counts_per_mm` derived from the feed constant
//! (0x6092: feed per shaft revolutions), the gear ratio and the position encoder resolution
//! (0x608F: increments per motor revolution). Velocities are position units per second and
//! accelerations position units per second², as CiA 402 defines them with unit factors of 1.

use canopen_rs::NodeId;
use std::time::Duration;
use thiserror::Error;

/// Why a configuration was refused.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ConfigError {
    #[error(
        "canopen.node_id = {0}: a CANopen node id is 1 to 127; set the follower drive's node id"
    )]
    NodeId(u8),
    #[error("canopen.{key} = {value}: {why}")]
    Invalid {
        key: &'static str,
        value: String,
        why: &'static str,
    },
}

/// mm ↔ encoder increments (0x6092 feed constant, 0x608F encoder resolution, gear ratio).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scaling {
    /// Feed constant 0x6092:01 expressed in mm: travel per `shaft_revolutions`.
    pub feed_mm: f64,
    /// Feed constant 0x6092:02: driving shaft revolutions for `feed_mm`.
    pub shaft_revolutions: u32,
    /// Position encoder resolution 0x608F:01: increments per `motor_revolutions`.
    pub encoder_increments: u32,
    /// Position encoder resolution 0x608F:02.
    pub motor_revolutions: u32,
    /// Gear ratio (0x6091:01 / 0x6091:02): motor revolutions per shaft revolution.
    pub gear_ratio: f64,
}

impl Default for Scaling {
    /// A 5 mm lead screw, direct drive, 17-bit encoder: 26 214.4 increments per mm.
    fn default() -> Self {
        Scaling {
            feed_mm: 5.0,
            shaft_revolutions: 1,
            encoder_increments: 131_072,
            motor_revolutions: 1,
            gear_ratio: 1.0,
        }
    }
}

impl Scaling {
    /// Encoder increments per mm of travel (not validated: see `DriveConfig::validate`).
    pub fn counts_per_mm(&self) -> f64 {
        self.encoder_increments as f64 / self.motor_revolutions as f64
            * self.gear_ratio
            * self.shaft_revolutions as f64
            / self.feed_mm
    }

    fn validate(&self) -> Result<f64, ConfigError> {
        positive("scaling.feed_mm", self.feed_mm)?;
        positive("scaling.gear_ratio", self.gear_ratio)?;
        for (key, v) in [
            ("scaling.shaft_revolutions", self.shaft_revolutions),
            ("scaling.encoder_increments", self.encoder_increments),
            ("scaling.motor_revolutions", self.motor_revolutions),
        ] {
            if v == 0 {
                return Err(ConfigError::Invalid {
                    key,
                    value: "0".into(),
                    why: "must be at least 1",
                });
            }
        }
        let c = self.counts_per_mm();
        if !(c.is_finite() && c > 0.0) {
            return Err(ConfigError::Invalid {
                key: "scaling",
                value: format!("{c} increments/mm"),
                why: "the derived increments per mm must be finite and > 0",
            });
        }
        Ok(c)
    }
}

/// Homing (mode 6): 0x6098 method, 0x6099 speeds, 0x609A acceleration, 0x607C offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HomingConfig {
    /// 0x6098 homing method (CiA 402: 1..=35 and 37; 35/37 home on the current position).
    pub method: i8,
    /// 0x6099:01 speed during the search for the switch (mm/s).
    pub switch_speed_mm_s: f64,
    /// 0x6099:02 speed during the search for zero (mm/s).
    pub zero_speed_mm_s: f64,
    /// 0x609A homing acceleration (mm/s²).
    pub accel_mm_s2: f64,
    /// 0x607C home offset (mm).
    pub offset_mm: f64,
    /// How long homing may take.
    pub timeout: Duration,
}

impl Default for HomingConfig {
    fn default() -> Self {
        HomingConfig {
            method: 19,
            switch_speed_mm_s: 5.0,
            zero_speed_mm_s: 0.5,
            accel_mm_s2: 50.0,
            offset_mm: 0.0,
            timeout: Duration::from_secs(30),
        }
    }
}

/// Profile position (mode 1): 0x6081 velocity, 0x6083/0x6084 acceleration/deceleration,
/// 0x6085 quick-stop deceleration, 0x6067 position window, 0x6065 following-error window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProfileConfig {
    pub velocity_mm_s: f64,
    pub accel_mm_s2: f64,
    pub decel_mm_s2: f64,
    pub quick_stop_decel_mm_s2: f64,
    /// Target reached when within this distance (mm); also the master's position tolerance.
    pub position_window_mm: f64,
    pub following_error_window_mm: f64,
    /// Whether `move_to` sets "change set immediately" (bit 5); `set_target` always does.
    pub change_immediately: bool,
    /// Added to the profile's own duration when waiting for "target reached".
    pub move_timeout_margin: Duration,
}

impl Default for ProfileConfig {
    fn default() -> Self {
        ProfileConfig {
            velocity_mm_s: 10.0,
            accel_mm_s2: 100.0,
            decel_mm_s2: 100.0,
            quick_stop_decel_mm_s2: 500.0,
            position_window_mm: 0.001,
            following_error_window_mm: 0.5,
            change_immediately: false,
            move_timeout_margin: Duration::from_secs(2),
        }
    }
}

/// Travel limits of the follower (mm); the master refuses targets outside, and writes them
/// to the drive's software position limits (0x607D) when `write_to_drive`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TravelLimits {
    pub min_mm: f64,
    pub max_mm: f64,
    pub write_to_drive: bool,
}

impl Default for TravelLimits {
    fn default() -> Self {
        TravelLimits {
            min_mm: -25.0,
            max_mm: 25.0,
            write_to_drive: true,
        }
    }
}

/// Everything the master needs to know about the follower drive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveConfig {
    /// CANopen node id, 1..=127.
    pub node_id: u8,
    /// Producer heartbeat time written to the drive (0x1017), whole ms, 1..=65535 ms.
    pub heartbeat_period: Duration,
    /// Consumer time: the drive is lost when no heartbeat arrives for this long.
    pub heartbeat_timeout: Duration,
    /// Wait for each SDO response at most this long.
    pub sdo_timeout: Duration,
    /// SYNC period (RPDO1 goes out just before each SYNC, TPDO1 answers it).
    pub sync_period: Duration,
    /// SYNC period while the follower is quiet: in profile position, no command under way or
    /// queued, not following, its status unchanged for [`QUIET_AFTER`](super::master::QUIET_AFTER).
    /// A whole multiple of `sync_period`; equal to it to keep one rate. Any command or follow
    /// target, and any change the drive reports, brings back `sync_period` at once.
    pub quiet_sync_period: Duration,
    /// Wait at most this long for an NMT state, a power-state transition or a set-point
    /// acknowledge.
    pub state_timeout: Duration,
    /// Wait at most this long for the boot-up after a reset.
    pub boot_timeout: Duration,
    /// Quiet time after a boot-up before talking to the drive: a late boot-up (from power-on)
    /// or late SDO responses still in flight are absorbed, not mistaken for new ones.
    pub boot_settle: Duration,
    /// Reset communication (and wait for the boot-up) at the start of `configure`, so the
    /// drive starts from its default communication objects.
    pub reset_communication: bool,
    /// Refuse moves until the drive has been homed since it was configured.
    pub require_homing: bool,
    pub scaling: Scaling,
    pub homing: HomingConfig,
    pub profile: ProfileConfig,
    pub limits: TravelLimits,
    /// Following (cyclic synchronous position): the demand sent at a SYNC leads the follow
    /// target by the target's velocity times this many SYNC periods, making up for the drive's
    /// interpolation delay: 1 for a drive that reaches each demand at the next SYNC (as the
    /// twin does), 0 for one that applies it at once. 0..=4.
    pub csp_lead_periods: f64,
}

impl Default for DriveConfig {
    fn default() -> Self {
        DriveConfig {
            node_id: 1,
            heartbeat_period: Duration::from_millis(100),
            heartbeat_timeout: Duration::from_millis(350),
            sdo_timeout: Duration::from_millis(500),
            sync_period: Duration::from_millis(10),
            quiet_sync_period: Duration::from_millis(100),
            state_timeout: Duration::from_secs(1),
            boot_timeout: Duration::from_secs(5),
            boot_settle: Duration::from_millis(100),
            reset_communication: true,
            require_homing: true,
            scaling: Scaling::default(),
            homing: HomingConfig::default(),
            profile: ProfileConfig::default(),
            limits: TravelLimits::default(),
            csp_lead_periods: 1.0,
        }
    }
}

fn positive(key: &'static str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(ConfigError::Invalid {
            key,
            value: v.to_string(),
            why: "must be a finite number > 0",
        })
    }
}

fn nonzero(key: &'static str, d: Duration) -> Result<(), ConfigError> {
    if d.is_zero() {
        Err(ConfigError::Invalid {
            key,
            value: crate::util::time::span(d),
            why: "must be longer than 0",
        })
    } else {
        Ok(())
    }
}

impl DriveConfig {
    /// Check every value and derive the scaling.
    pub fn validate(&self) -> Result<DriveSettings, ConfigError> {
        let node = NodeId::new(self.node_id).map_err(|_| ConfigError::NodeId(self.node_id))?;
        for (key, d) in [
            ("heartbeat_period", self.heartbeat_period),
            ("heartbeat_timeout", self.heartbeat_timeout),
            ("sdo_timeout", self.sdo_timeout),
            ("sync_period", self.sync_period),
            ("state_timeout", self.state_timeout),
            ("boot_timeout", self.boot_timeout),
            ("homing.timeout", self.homing.timeout),
        ] {
            nonzero(key, d)?;
        }
        let hb = self.heartbeat_period;
        if !hb.subsec_nanos().is_multiple_of(1_000_000) || hb.as_millis() > u16::MAX as u128 {
            return Err(ConfigError::Invalid {
                key: "heartbeat_period",
                value: crate::util::time::span(hb),
                why: "0x1017 holds whole milliseconds, 1 to 65535 ms",
            });
        }
        if self.heartbeat_timeout <= hb {
            return Err(ConfigError::Invalid {
                key: "heartbeat_timeout",
                value: crate::util::time::span(self.heartbeat_timeout),
                why: "must be longer than heartbeat_period (CiA 301: consumer time > producer time)",
            });
        }
        let (sync, quiet) = (self.sync_period, self.quiet_sync_period);
        if quiet < sync || !quiet.as_nanos().is_multiple_of(sync.as_nanos()) {
            return Err(ConfigError::Invalid {
                key: "quiet_sync_period",
                value: crate::util::time::span(quiet),
                why: "must be a whole multiple of the SYNC period (equal to it: one rate)",
            });
        }
        let counts_per_mm = self.scaling.validate()?;
        let s = DriveSettings {
            config: *self,
            node,
            counts_per_mm,
        };
        for (key, v) in [
            ("homing.switch_speed_mm_s", self.homing.switch_speed_mm_s),
            ("homing.zero_speed_mm_s", self.homing.zero_speed_mm_s),
            ("homing.accel_mm_s2", self.homing.accel_mm_s2),
            ("profile.velocity_mm_s", self.profile.velocity_mm_s),
            ("profile.accel_mm_s2", self.profile.accel_mm_s2),
            ("profile.decel_mm_s2", self.profile.decel_mm_s2),
            (
                "profile.quick_stop_decel_mm_s2",
                self.profile.quick_stop_decel_mm_s2,
            ),
            (
                "profile.position_window_mm",
                self.profile.position_window_mm,
            ),
            (
                "profile.following_error_window_mm",
                self.profile.following_error_window_mm,
            ),
        ] {
            positive(key, v)?;
            if s.unsigned_counts(v).is_none() {
                return Err(ConfigError::Invalid {
                    key,
                    value: v.to_string(),
                    why: "too large for a 32-bit drive parameter at this scaling",
                });
            }
        }
        if !(self.csp_lead_periods >= 0.0 && self.csp_lead_periods <= 4.0) {
            return Err(ConfigError::Invalid {
                key: "csp_lead_periods",
                value: self.csp_lead_periods.to_string(),
                why: "must be 0 to 4 SYNC periods",
            });
        }
        let l = &self.limits;
        if !(l.min_mm.is_finite() && l.max_mm.is_finite() && l.min_mm < l.max_mm) {
            return Err(ConfigError::Invalid {
                key: "limits",
                value: format!("{}..{}", l.min_mm, l.max_mm),
                why: "min_mm must be below max_mm, both finite",
            });
        }
        for (key, v) in [
            ("limits.min_mm", l.min_mm),
            ("limits.max_mm", l.max_mm),
            ("homing.offset_mm", self.homing.offset_mm),
        ] {
            if s.mm_to_counts(v).is_none() {
                return Err(ConfigError::Invalid {
                    key,
                    value: v.to_string(),
                    why: "outside the drive's 32-bit position range at this scaling",
                });
            }
        }
        Ok(s)
    }
}

/// A validated configuration with its scaling worked out.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveSettings {
    config: DriveConfig,
    node: NodeId,
    counts_per_mm: f64,
}

impl DriveSettings {
    pub fn config(&self) -> &DriveConfig {
        &self.config
    }
    pub fn node(&self) -> NodeId {
        self.node
    }
    pub fn counts_per_mm(&self) -> f64 {
        self.counts_per_mm
    }
    /// A position in mm as drive increments; `None` if it does not fit an INTEGER32.
    pub fn mm_to_counts(&self, mm: f64) -> Option<i32> {
        let c = (mm * self.counts_per_mm).round();
        (c.is_finite() && c >= i32::MIN as f64 && c <= i32::MAX as f64).then_some(c as i32)
    }
    /// Drive increments as mm.
    pub fn counts_to_mm(&self, counts: i32) -> f64 {
        counts as f64 / self.counts_per_mm
    }
    /// A non-negative speed, acceleration or window in mm units as an UNSIGNED32 parameter.
    pub fn unsigned_counts(&self, v: f64) -> Option<u32> {
        let c = (v * self.counts_per_mm).round();
        (c.is_finite() && c >= 0.0 && c <= u32::MAX as f64).then_some(c as u32)
    }
    /// The producer heartbeat time in ms (validated to fit 0x1017).
    pub fn heartbeat_ms(&self) -> u16 {
        self.config.heartbeat_period.as_millis() as u16
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_validate_and_scale() {
        let s = DriveConfig::default().validate().unwrap();
        assert_eq!(s.node().raw(), 1);
        assert!((s.counts_per_mm() - 26_214.4).abs() < 1e-9);
        assert_eq!(s.mm_to_counts(1.0), Some(26_214));
        assert_eq!(s.mm_to_counts(-2.5), Some(-65_536));
        assert!((s.counts_to_mm(131_072) - 5.0).abs() < 1e-12);
        assert_eq!(s.unsigned_counts(10.0), Some(262_144));
        assert_eq!(s.heartbeat_ms(), 100);
        assert_eq!(s.mm_to_counts(1e9), None);
        assert_eq!(s.mm_to_counts(f64::NAN), None);
    }

    #[test]
    fn scaling_from_feed_constant_and_encoder() {
        // 10 mm per 2 shaft revolutions, 4000 increments per motor revolution, 3:1 gear.
        let sc = Scaling {
            feed_mm: 10.0,
            shaft_revolutions: 2,
            encoder_increments: 4000,
            motor_revolutions: 1,
            gear_ratio: 3.0,
        };
        // 4000 inc/motor rev × 3 motor rev/shaft rev × 2 shaft rev / 10 mm = 2400 inc/mm.
        assert_eq!(sc.counts_per_mm(), 2400.0);
    }

    /// Each invalid value is refused with its key and value quoted.
    #[test]
    fn invalid_values_are_refused() {
        let bad: Vec<(DriveConfig, &str)> = vec![
            (
                DriveConfig {
                    node_id: 0,
                    ..Default::default()
                },
                "canopen.node_id = 0",
            ),
            (
                DriveConfig {
                    node_id: 128,
                    ..Default::default()
                },
                "canopen.node_id = 128",
            ),
            (
                DriveConfig {
                    heartbeat_period: Duration::from_micros(1500),
                    ..Default::default()
                },
                "canopen.heartbeat_period = 1.5 ms",
            ),
            (
                DriveConfig {
                    heartbeat_period: Duration::from_secs(70),
                    heartbeat_timeout: Duration::from_secs(80),
                    ..Default::default()
                },
                "whole milliseconds",
            ),
            (
                DriveConfig {
                    heartbeat_timeout: Duration::from_millis(100),
                    ..Default::default()
                },
                "canopen.heartbeat_timeout = 100 ms",
            ),
            (
                DriveConfig {
                    sdo_timeout: Duration::ZERO,
                    ..Default::default()
                },
                "canopen.sdo_timeout = 0 ms",
            ),
            (
                DriveConfig {
                    scaling: Scaling {
                        feed_mm: 0.0,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                "canopen.scaling.feed_mm = 0",
            ),
            (
                DriveConfig {
                    scaling: Scaling {
                        encoder_increments: 0,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                "canopen.scaling.encoder_increments = 0",
            ),
            (
                DriveConfig {
                    scaling: Scaling {
                        gear_ratio: f64::NAN,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                "canopen.scaling.gear_ratio = NaN",
            ),
            (
                DriveConfig {
                    profile: ProfileConfig {
                        velocity_mm_s: -1.0,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                "canopen.profile.velocity_mm_s = -1",
            ),
            (
                DriveConfig {
                    profile: ProfileConfig {
                        accel_mm_s2: 1e12,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                "32-bit drive parameter",
            ),
            (
                DriveConfig {
                    limits: TravelLimits {
                        min_mm: 5.0,
                        max_mm: 5.0,
                        write_to_drive: true,
                    },
                    ..Default::default()
                },
                "canopen.limits = 5..5",
            ),
            (
                DriveConfig {
                    limits: TravelLimits {
                        min_mm: -1e6,
                        max_mm: 5.0,
                        write_to_drive: true,
                    },
                    ..Default::default()
                },
                "canopen.limits.min_mm = -1000000",
            ),
            (
                DriveConfig {
                    csp_lead_periods: f64::NAN,
                    ..Default::default()
                },
                "canopen.csp_lead_periods = NaN",
            ),
            (
                DriveConfig {
                    csp_lead_periods: 5.0,
                    ..Default::default()
                },
                "canopen.csp_lead_periods = 5: must be 0 to 4 SYNC periods",
            ),
        ];
        for (cfg, want) in bad {
            let e = cfg.validate().unwrap_err().to_string();
            assert!(e.contains(want), "{e:?} should contain {want:?}");
        }
    }
}
