//! Machine time: how long each phase of a measurement keeps the machine from making parts
//! (issue 26). The lab's simulated clock measures every phase it runs (the follower's
//! bring-up, the alignment's traverses, the follower's map with its level stations, each ISO
//! 230-2 pass with its zero, drift check and make-up passes); publishing is real Modbus TCP
//! on loopback and is measured on the wall clock. What the lab does not simulate is counted at
//! a stated assumption: the technician turning the mount's screws after each alignment round
//! that did not pass ([`TECHNICIAN_S_PER_ROUND`]).

use std::time::Duration;

/// The technician's time to turn the mount's four screws as advised, per alignment round
/// that did not pass (s): an assumption, stated wherever the figure is shown.
pub const TECHNICIAN_S_PER_ROUND: f64 = 120.0;

/// The machine time of each phase of a measurement on the twin.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MachineTime {
    /// The follower drive's bring-up and homing.
    pub bring_up: Duration,
    /// The alignment's traverses and readings (the technician's turns not included).
    pub align: Duration,
    /// Alignment rounds after which the technician turned the screws.
    pub align_turns: usize,
    /// The follower's self-calibration passes and level stations; or, with the instrument's
    /// map re-used, its check on this set-up (the level's stations).
    pub follower_map: Duration,
    pub map_reused: bool,
    /// The first ISO 230-2 pass: to the reference, the zero, the drift check, the cycle and
    /// its make-up passes.
    pub before: Duration,
    /// The tables into the PLC.
    pub publish: Duration,
    /// The verification pass on the compensated axis, as `before`.
    pub after: Duration,
}

impl MachineTime {
    /// The alignment with the technician's assumed turns (s).
    pub fn align_s(&self) -> f64 {
        self.align.as_secs_f64() + TECHNICIAN_S_PER_ROUND * self.align_turns as f64
    }

    /// Every phase in order, with its name (s).
    pub fn phases(&self) -> [(&'static str, f64); 6] {
        [
            ("bring_up", self.bring_up.as_secs_f64()),
            ("align", self.align_s()),
            ("follower_map", self.follower_map.as_secs_f64()),
            ("before", self.before.as_secs_f64()),
            ("publish", self.publish.as_secs_f64()),
            ("after", self.after.as_secs_f64()),
        ]
    }

    /// The whole measurement (s): the sum of the phases.
    pub fn total_s(&self) -> f64 {
        self.phases().iter().map(|(_, s)| s).sum()
    }

    /// `{"bring_up", "align", "follower_map", "before", "publish", "after", "total",
    /// "assumptions": {...}}` in seconds.
    pub fn to_json(&self) -> serde_json::Value {
        let mut m = serde_json::Map::new();
        for (name, s) in self.phases() {
            m.insert(name.into(), serde_json::json!(s));
        }
        m.insert("total".into(), serde_json::json!(self.total_s()));
        m.insert(
            "assumptions".into(),
            serde_json::json!({
                "technician_s_per_round": TECHNICIAN_S_PER_ROUND,
                "align_rounds_turned": self.align_turns,
                "follower_map_reused": self.map_reused,
            }),
        );
        serde_json::Value::Object(m)
    }

    /// The phases as lines of words (minutes), the assumption said.
    pub fn lines(&self) -> Vec<String> {
        let words = |name: &str| match name {
            "bring_up" => "the follower's bring-up and homing".to_string(),
            "align" => format!(
                "alignment ({} technician's turns at {:.0} min each, assumed)",
                self.align_turns,
                TECHNICIAN_S_PER_ROUND / 60.0
            ),
            "follower_map" if self.map_reused => {
                "the follower map's check on this set-up (level stations)".to_string()
            }
            "follower_map" => "the follower's map and level stations".to_string(),
            "before" => "ISO 230-2 run (zero, drift check, cycle, make-up)".to_string(),
            "publish" => "tables into the PLC".to_string(),
            "after" => "verification run".to_string(),
            other => other.to_string(),
        };
        let mut out: Vec<String> = self
            .phases()
            .iter()
            .map(|(name, s)| format!("  {:<58} {:>7.1} min", words(name), s / 60.0))
            .collect();
        out.push(format!(
            "  {:<58} {:>7.1} min",
            "total",
            self.total_s() / 60.0
        ));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_total_is_the_phases_with_the_technicians_turns() {
        let t = MachineTime {
            bring_up: Duration::from_secs(10),
            align: Duration::from_secs(30),
            align_turns: 2,
            follower_map: Duration::from_secs(600),
            map_reused: false,
            before: Duration::from_secs(340),
            publish: Duration::from_millis(500),
            after: Duration::from_secs(341),
        };
        assert_eq!(t.align_s(), 30.0 + 2.0 * TECHNICIAN_S_PER_ROUND);
        let want = 10.0 + 270.0 + 600.0 + 340.0 + 0.5 + 341.0;
        assert!((t.total_s() - want).abs() < 1e-9);
        let j = t.to_json();
        assert_eq!(j["align"], 270.0);
        assert_eq!(j["total"], want);
        assert_eq!(j["assumptions"]["align_rounds_turned"], 2);
        let lines = t.lines();
        assert_eq!(lines.len(), 7);
        assert!(lines[1].contains("2 technician's turns at 2 min each, assumed"));
        assert!(
            lines[6].ends_with(&format!("{:.1} min", want / 60.0)),
            "{}",
            lines[6]
        );
    }
}
