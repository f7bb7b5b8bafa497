//! Beam alignment in the service (sans-I/O): the PSDs' recent spots, the stations an operator
//! reads with the carriage at rest (`align_read`, with the alignment target's reading where a
//! spot is off its PSD: `align_target`), and the advice over a span of travel
//! (`align_advice`): the screw turns, the residual beam angle, the check. The control task
//! answers the requests; [`crate::align`] does the geometry.

use crate::acquire::Frame;
use crate::align::{AlignSettings, Observed, SpotSource, Station};
use crate::config::AlignConfig;
use crate::optics::{Layout, Spot};
use crate::store::{AlignmentRecord, NewAlignment};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// A station is the mean of the spots over this long.
pub const STATION_WINDOW: Duration = Duration::from_millis(500);

/// The alignment's state.
#[derive(Debug)]
pub struct AlignState {
    recent: VecDeque<(Instant, [Option<Spot>; 3])>,
    stations: Vec<Station>,
    pub config: AlignConfig,
}

impl Default for AlignState {
    fn default() -> Self {
        AlignState::new(AlignConfig {
            settings: AlignSettings::default(),
            check_before_run: true,
            valid_for: Duration::from_secs(24 * 3600),
        })
    }
}

impl AlignState {
    pub fn new(config: AlignConfig) -> AlignState {
        AlignState {
            recent: VecDeque::new(),
            stations: Vec::new(),
            config,
        }
    }

    /// A frame from the I/O module.
    pub fn handle_frame(&mut self, f: &Frame) {
        self.recent.push_back((f.at, f.spots));
        while let Some((t, _)) = self.recent.front() {
            if f.at.saturating_duration_since(*t) > STATION_WINDOW {
                self.recent.pop_front();
            } else {
                break;
            }
        }
    }

    /// Read a station at `at_mm`: each PSD's mean spot over the window, when it saw one in
    /// nine frames of ten. A station at the same position (±1 mm) replaces the earlier one.
    pub fn read(&mut self, at_mm: f64) -> Result<Station, String> {
        if !at_mm.is_finite() {
            return Err("at_mm must be a finite position (mm)".into());
        }
        if self.recent.is_empty() {
            return Err("no frames from the I/O module: is the link up?".into());
        }
        let st = crate::align::mean_station(at_mm, self.recent.iter().map(|(_, s)| s));
        self.stations.retain(|s| (s.travel_mm - at_mm).abs() > 1.0);
        self.stations.push(st);
        Ok(st)
    }

    /// What the alignment target in front of PSD `psd` (1..3) shows at the last station read.
    pub fn target(&mut self, psd: usize, x: f64, y: f64) -> Result<Station, String> {
        if !(1..=3).contains(&psd) {
            return Err(format!("psd {psd}: use 1, 2 or 3"));
        }
        if !(x.is_finite() && y.is_finite()) {
            return Err("the target's x and y must be numbers (mm)".into());
        }
        let st = self
            .stations
            .last_mut()
            .ok_or("read a station first (align_read), then what its targets show")?;
        st.spots[psd - 1] = Some(Observed {
            x,
            y,
            source: SpotSource::Target,
        });
        Ok(*st)
    }

    /// Forget the stations (after turning screws, read both ends again).
    pub fn clear(&mut self) {
        self.stations.clear();
    }

    /// The advice over `span` (mm) from the stations read, as the control API answers it, and
    /// the record to store for `axis` (the pre-run check reads the newest). The stations stay
    /// until `clear`: after turning screws, clear and read both ends again.
    pub fn advise_for(
        &self,
        layout: &Layout,
        axis: &str,
        span: (f64, f64),
    ) -> Result<(NewAlignment, serde_json::Value), String> {
        let (a, mut v) = self.advise(layout, span)?;
        // Without a residual angle (one station) nothing passed: record 0.
        let [yaw, pitch] = a.misalignment_urad.unwrap_or([0.0; 2]);
        v["axis"] = serde_json::json!(axis);
        let rec = NewAlignment {
            axis: axis.to_string(),
            from_mm: span.0,
            to_mm: span.1,
            passed: a.now.passed(),
            yaw_rad: yaw * 1e-6,
            pitch_rad: pitch * 1e-6,
            check: a.now.to_string(),
            advice: v.clone(),
        };
        Ok((rec, v))
    }

    /// The pre-run check (issue 13): a run over `travel` (mm) of `axis` starts only when the
    /// newest alignment of the axis passed over a span that holds the travel, no longer ago than
    /// the configured validity. The error says what is missing and what to do.
    pub fn pre_run_check(
        &self,
        latest: Option<&AlignmentRecord>,
        axis: &str,
        travel: (f64, f64),
        now_us: i64,
    ) -> Result<(), String> {
        if !self.config.check_before_run {
            return Ok(());
        }
        let how = format!(
            "align the head over {:.1} to {:.1} mm first (`axiscomp align read` at both ends, \
             then `axiscomp align advice --from-mm {:.1} --to-mm {:.1} --axis {axis}`, or the \
             console's Align screen), or set align.check_before_run = false",
            travel.0, travel.1, travel.0, travel.1
        );
        let Some(rec) = latest else {
            return Err(format!("axis {axis} has no beam alignment: {how}"));
        };
        let a = &rec.alignment;
        if !a.passed {
            let turns: Vec<&str> = a.advice["turns"]
                .as_array()
                .map(|t| t.iter().filter_map(|t| t["text"].as_str()).collect())
                .unwrap_or_default();
            let adjust = if turns.is_empty() {
                String::new()
            } else {
                format!("; adjust: {}", turns.join(", "))
            };
            return Err(format!(
                "axis {axis}'s last alignment ({:.1} to {:.1} mm) did not pass: {}{adjust}; then {how}",
                a.from_mm, a.to_mm, a.check
            ));
        }
        if a.from_mm > travel.0 + 1e-6 || a.to_mm < travel.1 - 1e-6 {
            return Err(format!(
                "axis {axis} was aligned over {:.1} to {:.1} mm, the run travels {:.1} to {:.1} mm: {how}",
                a.from_mm, a.to_mm, travel.0, travel.1
            ));
        }
        let age_s = (now_us - rec.unix_us) as f64 * 1e-6;
        if age_s > self.config.valid_for.as_secs_f64() {
            return Err(format!(
                "axis {axis}'s alignment is {:.1} h old (align.valid_for_h is {:.1} h): {how}",
                age_s / 3600.0,
                self.config.valid_for.as_secs_f64() / 3600.0
            ));
        }
        Ok(())
    }

    /// The advice over `span` (mm) from the stations read, as JSON for the control API.
    pub fn advice(&self, layout: &Layout, span: (f64, f64)) -> Result<serde_json::Value, String> {
        self.advise(layout, span).map(|(_, v)| v)
    }

    /// The advice over `span` (mm), and as the control API answers it.
    fn advise(
        &self,
        layout: &Layout,
        span: (f64, f64),
    ) -> Result<(crate::align::Advice, serde_json::Value), String> {
        if !(span.0.is_finite() && span.1.is_finite() && span.0 < span.1) {
            return Err(format!(
                "from_mm {} must be below to_mm {} (mm)",
                span.0, span.1
            ));
        }
        let a = crate::align::advise(layout, &self.config.settings, &self.stations, span)
            .map_err(|e| e.to_string())?;
        let passed = a.now.passed();
        let turns: Vec<serde_json::Value> = a
            .turns
            .iter()
            .map(|t| serde_json::json!({"screw": t.screw.name(), "turns": t.turns, "text": t.to_string()}))
            .collect();
        let v = serde_json::json!({
            "passed": passed,
            "check": a.now.to_string(),
            "after": a.after.to_string(),
            "turns": turns,
            "misalignment_urad": a.misalignment_urad,
            "stations": self.stations.len(),
            "text": a.describe(),
        });
        Ok((a, v))
    }
}

/// A station as the control API answers it: per PSD the spot (mm) and where it was read.
pub fn station_json(st: &crate::align::Station) -> serde_json::Value {
    let spots: Vec<serde_json::Value> = st
        .spots
        .iter()
        .map(|s| match s {
            Some(o) => serde_json::json!({
                "x": o.x,
                "y": o.y,
                "from": match o.source {
                    crate::align::SpotSource::Psd => "psd",
                    crate::align::SpotSource::Target => "target",
                },
            }),
            None => serde_json::Value::Null,
        })
        .collect();
    serde_json::json!({"at_mm": st.travel_mm, "spots": spots})
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(at: Instant, spots: [Option<Spot>; 3]) -> Frame {
        Frame {
            seq: 0,
            at,
            unix_us: 0,
            spots,
            sums: [5.0; 3],
        }
    }

    #[test]
    fn a_station_is_the_mean_and_a_missing_spot_waits_for_its_target() {
        let t0 = crate::util::clock::now();
        let mut a = AlignState::default();
        assert!(a.read(0.0).unwrap_err().contains("no frames"));
        for i in 0..300 {
            let t = t0 + Duration::from_millis(2 * i);
            let x = if i % 2 == 0 { 0.1 } else { 0.3 };
            a.handle_frame(&frame(
                t,
                [
                    Some(Spot { x, y: -0.2 }),
                    Some(Spot { x: 0.0, y: 0.0 }),
                    None,
                ],
            ));
        }
        let st = a.read(0.0).unwrap();
        let s1 = st.spots[0].unwrap();
        // The last 0.5 s of frames, alternating 0.1 and 0.3 mm.
        assert!(
            (s1.x - 0.2).abs() < 1e-3 && (s1.y + 0.2).abs() < 1e-12,
            "{s1:?}"
        );
        assert!(st.spots[2].is_none());
        let st = a.target(3, 5.5, -1.0).unwrap();
        assert_eq!(st.spots[2].unwrap().source, SpotSource::Target);
        assert!(a.target(4, 0.0, 0.0).unwrap_err().contains("use 1, 2 or 3"));
        let layout = Layout::reference();
        let v = a.advice(&layout, (0.0, 1000.0)).unwrap();
        assert_eq!(v["passed"], false);
        assert!(v["check"].as_str().unwrap().contains("PSD3"), "{v}");
        assert!(a.advice(&layout, (5.0, 1.0)).unwrap_err().contains("below"));
    }

    /// The pre-run check against the alignments stored on disk: none, one that failed (its
    /// check and turns quoted), one over too short a span, one too old, one that covers.
    #[test]
    fn the_pre_run_check_reads_the_newest_alignment_of_the_axis() {
        let dir = std::env::temp_dir().join(format!("axiscomp-prerun-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let mut store = crate::store::Store::open(dir.join("store.sqlite")).unwrap();
        let a = AlignState::default();
        let now = crate::store::now_us();
        let travel = (-5.0, 1005.0);
        let e = a
            .pre_run_check(
                store.latest_alignment("X").unwrap().as_ref(),
                "X",
                travel,
                now,
            )
            .unwrap_err();
        assert!(
            e.contains("axis X has no beam alignment") && e.contains("-5.0 to 1005.0 mm"),
            "{e}"
        );
        let mut rec = NewAlignment {
            axis: "X".into(),
            from_mm: -5.0,
            to_mm: 1005.0,
            passed: false,
            yaw_rad: 3e-3,
            pitch_rad: 0.0,
            check: "PSD3 leaves its margin at 1005 mm (X3 4.6 mm)".into(),
            advice: serde_json::json!({"turns": [{"text": "turn the yaw screw 1.20 turns clockwise"}]}),
        };
        store.insert_alignment(&rec).unwrap();
        let e = a
            .pre_run_check(
                store.latest_alignment("X").unwrap().as_ref(),
                "X",
                travel,
                now,
            )
            .unwrap_err();
        assert!(
            e.contains("did not pass: PSD3 leaves its margin at 1005 mm")
                && e.contains("adjust: turn the yaw screw 1.20 turns clockwise"),
            "{e}"
        );
        // Another axis's alignment is not this one's.
        assert!(
            a.pre_run_check(
                store.latest_alignment("Y").unwrap().as_ref(),
                "Y",
                travel,
                now
            )
            .unwrap_err()
            .contains("axis Y has no")
        );
        rec.passed = true;
        rec.to_mm = 800.0;
        store.insert_alignment(&rec).unwrap();
        let e = a
            .pre_run_check(
                store.latest_alignment("X").unwrap().as_ref(),
                "X",
                travel,
                now,
            )
            .unwrap_err();
        assert!(
            e.contains("aligned over -5.0 to 800.0 mm, the run travels -5.0 to 1005.0 mm"),
            "{e}"
        );
        rec.to_mm = 1005.0;
        store.insert_alignment(&rec).unwrap();
        a.pre_run_check(
            store.latest_alignment("X").unwrap().as_ref(),
            "X",
            travel,
            now,
        )
        .unwrap();
        let day_later = now + 25 * 3_600_000_000;
        let e = a
            .pre_run_check(
                store.latest_alignment("X").unwrap().as_ref(),
                "X",
                travel,
                day_later,
            )
            .unwrap_err();
        assert!(
            e.contains("25.0 h old (align.valid_for_h is 24.0 h)"),
            "{e}"
        );
        let off = AlignState::new(AlignConfig {
            check_before_run: false,
            ..a.config.clone()
        });
        off.pre_run_check(None, "Z", travel, now).unwrap();
        let stored = store.latest_alignment("X").unwrap().unwrap();
        assert_eq!(stored.alignment, rec);
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
