//! The Align screen's follower error map (issue 14): import the encoder's certificate (`i`, a
//! path on the service's host), map the follower by the stop-and-go self-calibration (`m`:
//! the span, passes and frames typed, then asked; `m` again stops it), its progress from the
//! snapshots, and the summary of the map made. `v` switches the lower panel between the beam
//! alignment and the follower map (at 80×24 they take turns; a mapping started shows its own).

use super::*;
use crate::service::api::CertificateImport;
use crate::service::api::{MappingRequest, MappingView};

/// The lower panel of the Align screen (at 80×24 one at a time).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AlignPanel {
    #[default]
    Beam,
    Follower,
}

/// The follower map's state on the Align screen.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FollowerPanel {
    pub panel: AlignPanel,
    /// The last certificate imported from this console: its map's title and summary.
    pub imported: Option<(String, Vec<String>)>,
    /// A mapping was under way in the last snapshot.
    was_active: bool,
    /// Level stations were under way in the last snapshot.
    pub(super) level_was_active: bool,
}

/// Default passes and frames a side offered for a mapping (the service's defaults).
const PASSES: usize = 4;
const FRAMES: usize = 1000;

/// Parse the mapping typed: "FROM TO [PASSES [FRAMES]]" (mm, then counts).
pub fn parse_mapping(text: &str) -> Result<MappingRequest, String> {
    let bad = || {
        format!(
            "mapping \"{text}\": type the span in mm, then passes and frames a side if not {PASSES} and {FRAMES}, e.g. 0 400 2 500"
        )
    };
    let parts: Vec<&str> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .collect();
    if !(2..=4).contains(&parts.len()) {
        return Err(bad());
    }
    let mm = |t: &str| t.parse::<f64>().ok().filter(|v| v.is_finite());
    let count = |t: &str| t.parse::<usize>().ok().filter(|n| *n > 0);
    let (Some(from), Some(to)) = (mm(parts[0]), mm(parts[1])) else {
        return Err(bad());
    };
    if from >= to {
        return Err(format!(
            "span {from}–{to} mm: the near end must be below the far end"
        ));
    }
    let passes = match parts.get(2) {
        Some(t) => Some(count(t).ok_or_else(bad)?),
        None => None,
    };
    let frames = match parts.get(3) {
        Some(t) => Some(count(t).ok_or_else(bad)?),
        None => None,
    };
    Ok(MappingRequest {
        from_mm: Some(from),
        to_mm: Some(to),
        passes,
        frames,
        ..MappingRequest::default()
    })
}

impl App {
    /// The follower mapping as the last snapshot shows it.
    pub fn mapping(&self) -> Option<&MappingView> {
        self.snapshot
            .as_ref()
            .and_then(|s| s.follower_mapping.as_ref())
    }

    /// A mapping is under way (as far as the service last said).
    pub fn mapping_active(&self) -> bool {
        self.mapping().is_some_and(MappingView::active)
    }

    /// A snapshot came: a mapping that just started shows its panel; one that just ended
    /// says how.
    pub(super) fn observe_mapping(&mut self) {
        let active = self.mapping_active();
        let was = std::mem::replace(&mut self.follower.was_active, active);
        if active && !was {
            self.follower.panel = AlignPanel::Follower;
        }
        if was
            && !active
            && let Some(m) = self.mapping().cloned()
        {
            let text = match (m.state.as_str(), m.map_id) {
                ("done", Some(id)) => format!(
                    "follower mapped: map {id} in use ({} steps), the zero taken again",
                    m.steps_kept
                ),
                (s, _) => format!(
                    "follower mapping {s}: {}",
                    m.error.as_deref().unwrap_or("no map stored")
                ),
            };
            let level = if m.state == "done" {
                Level::Info
            } else {
                Level::Warn
            };
            self.log(level, text.clone());
            self.say(level, text);
        }
    }

    /// The Align screen's follower map keys (`None`: not one of them).
    pub(super) fn follower_map_key(&mut self, c: char) -> Option<Vec<Action>> {
        Some(match c {
            'v' => {
                self.follower.panel = match self.follower.panel {
                    AlignPanel::Beam => AlignPanel::Follower,
                    AlignPanel::Follower => AlignPanel::Beam,
                };
                Vec::new()
            }
            'i' => {
                if !self.may_operate("importing a certificate") {
                    return Some(Vec::new());
                }
                self.follower.panel = AlignPanel::Follower;
                self.overlay = Overlay::Input(Input {
                    purpose: InputFor::CertificatePath,
                    text: String::new(),
                });
                Vec::new()
            }
            'm' if self.mapping_active() => {
                if !self.may_operate("stopping the follower mapping") {
                    return Some(Vec::new());
                }
                self.overlay = Overlay::Confirm(Confirm::MapStop);
                Vec::new()
            }
            'm' => {
                if !self.may_operate("mapping the follower") {
                    return Some(Vec::new());
                }
                if self.run_active() {
                    self.say(
                        Level::Warn,
                        "a run is under way: map the follower when it has ended",
                    );
                    return Some(Vec::new());
                }
                self.follower.panel = AlignPanel::Follower;
                let (from, to) = self.align_span();
                self.overlay = Overlay::Input(Input {
                    purpose: InputFor::Mapping,
                    text: format!("{from} {to} {PASSES} {FRAMES}"),
                });
                Vec::new()
            }
            _ => return None,
        })
    }

    /// A certificate path or a mapping typed into the input box.
    pub(super) fn follower_map_input(&mut self, purpose: &InputFor, text: &str) -> Vec<Action> {
        match purpose {
            InputFor::CertificatePath => {
                if text.is_empty() {
                    self.say(
                        Level::Warn,
                        "type the path of the certificate CSV on the service's host",
                    );
                    return Vec::new();
                }
                self.overlay = Overlay::None;
                self.log(Level::Info, format!("→ import the certificate {text}"));
                vec![self.send(
                    Request::FollowerCertificate(CertificateImport {
                        path: Some(text.to_string()),
                        ..CertificateImport::default()
                    }),
                    Pending::Certificate,
                )]
            }
            InputFor::Mapping => match parse_mapping(text) {
                Ok(req) => {
                    self.overlay = Overlay::Confirm(Confirm::MapStart(req));
                    Vec::new()
                }
                Err(e) => {
                    self.say(Level::Warn, e);
                    Vec::new()
                }
            },
            _ => Vec::new(),
        }
    }

    /// A mapping start or stop confirmed.
    pub(super) fn follower_map_confirmed(&mut self, c: Confirm) -> Vec<Action> {
        match c {
            Confirm::MapStart(req) => {
                self.log(
                    Level::Info,
                    format!(
                        "→ map the follower over {}–{} mm",
                        req.from_mm.unwrap_or(f64::NAN),
                        req.to_mm.unwrap_or(f64::NAN)
                    ),
                );
                vec![self.send(Request::FollowerMapStart(req), Pending::MapStart)]
            }
            Confirm::MapStop => {
                self.log(Level::Info, "→ stop the follower mapping");
                vec![self.send(Request::FollowerMapStop, Pending::MapStop)]
            }
            _ => Vec::new(),
        }
    }

    /// The reply to a certificate import: the map made, in use.
    pub(super) fn apply_certificate(&mut self, v: &serde_json::Value) {
        let id = v["id"].as_i64().unwrap_or(0);
        let name = v["name"].as_str().unwrap_or("?").to_string();
        let summary = v["summary"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|l| l.as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default();
        self.follower.imported = Some((format!("map {id} ({name})"), summary));
        let text = if v["in_use"].as_bool() == Some(true) {
            format!("certificate imported: map {id} in use; take the zero again (z)")
        } else {
            format!("certificate imported: map {id} stored, not in use")
        };
        self.log(Level::Info, format!("✓ {text}"));
        self.say(Level::Info, text);
    }

    /// The reply to a mapping start: where its program went.
    pub(super) fn apply_mapping_started(&mut self, v: &serde_json::Value) {
        let text = format!(
            "follower mapping started: {} stops, dwell {:.1} s; {}",
            v["stops_planned"].as_u64().unwrap_or(0),
            v["dwell_s"].as_f64().unwrap_or(0.0),
            v["cnc"].as_str().unwrap_or("")
        );
        self.follower.panel = AlignPanel::Follower;
        self.log(Level::Info, format!("✓ {text}"));
        self.say(Level::Info, text);
    }
}
