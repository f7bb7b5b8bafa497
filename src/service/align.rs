//! Beam alignment in the service (sans-I/O): the PSDs' recent spots, the stations an operator
//! reads with the carriage at rest (`align_read`, with the alignment target's reading where a
//! spot is off its PSD: `align_target`), and the advice over a span of travel
//! (`align_advice`): the screw turns, the residual beam angle, the check. The control task
//! answers the requests; [`crate::align`] does the geometry.

use crate::acquire::Frame;
use crate::align::{AlignSettings, Observed, SpotSource, Station, advise};
use crate::optics::{Layout, Spot};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// A station is the mean of the spots over this long.
pub const STATION_WINDOW: Duration = Duration::from_millis(500);

/// The alignment's state.
#[derive(Debug, Default)]
pub struct AlignState {
    recent: VecDeque<(Instant, [Option<Spot>; 3])>,
    stations: Vec<Station>,
    pub settings: AlignSettings,
}

impl AlignState {
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

    /// The advice over `span` (mm) from the stations read, as JSON for the control API (the
    /// stations stay until `clear`: after turning screws, clear and read both ends again).
    pub fn advice(&self, layout: &Layout, span: (f64, f64)) -> Result<serde_json::Value, String> {
        if !(span.0.is_finite() && span.1.is_finite() && span.0 < span.1) {
            return Err(format!(
                "from_mm {} must be below to_mm {} (mm)",
                span.0, span.1
            ));
        }
        let a = advise(layout, &self.settings, &self.stations, span).map_err(|e| e.to_string())?;
        let passed = a.now.passed();
        let turns: Vec<serde_json::Value> = a
            .turns
            .iter()
            .map(|t| serde_json::json!({"screw": t.screw.name(), "turns": t.turns, "text": t.to_string()}))
            .collect();
        Ok(serde_json::json!({
            "passed": passed,
            "check": a.now.to_string(),
            "after": a.after.to_string(),
            "turns": turns,
            "misalignment_urad": a.misalignment_urad,
            "stations": self.stations.len(),
            "text": a.describe(),
        }))
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
        let t0 = Instant::now();
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
}
