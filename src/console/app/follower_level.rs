//! The Align screen's level stations along the follower's map (issue 14,
//! `service::follower_level`): `l` starts them over the map in use's span (asked first); while
//! they are under way `l` types the level's reading at the station being read when the service
//! awaits it (a level read by hand), else asks to stop them; `L` always asks to stop them;
//! `u` checks the map in use on this set-up with the stations instead (`check_map`: the
//! instrument's map re-used with this set-up's bend, or refused with the span to map again).
//! Their progress and outcome come from the snapshots (`follower_map_lines`).

use super::*;
use crate::service::api::{LevelRequest, LevelView};

/// Parse the level's reading typed (arcsec): a finite number (the service checks its range).
pub fn parse_level_reading(text: &str) -> Result<f64, String> {
    text.trim()
        .trim_end_matches(['″', '"'])
        .trim()
        .parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| {
            format!("level reading \"{text}\": type the level's reading in arcsec, e.g. -1.25")
        })
}

impl App {
    /// The level stations as the last snapshot shows them.
    pub fn level(&self) -> Option<&LevelView> {
        self.snapshot
            .as_ref()
            .and_then(|s| s.follower_level.as_ref())
    }

    /// The level stations are under way (as far as the service last said).
    pub fn level_active(&self) -> bool {
        self.level().is_some_and(LevelView::active)
    }

    /// A snapshot came: stations that just started show the follower panel; ones that just
    /// ended say how.
    pub(super) fn observe_level(&mut self) {
        let active = self.level_active();
        let was = std::mem::replace(&mut self.follower.level_was_active, active);
        if active && !was {
            self.follower.panel = AlignPanel::Follower;
        }
        if was
            && !active
            && let Some(l) = self.level().cloned()
        {
            let (level, text) = match (l.state.as_str(), l.map_id) {
                ("done", Some(id)) => (
                    Level::Info,
                    format!(
                        "level stations done: map {id} in use ({} stations), the zero taken again",
                        l.taken
                    ),
                ),
                (s, _) => (
                    Level::Warn,
                    format!(
                        "level stations {s}: {}",
                        l.error.as_deref().unwrap_or("no map stored")
                    ),
                ),
            };
            self.log(level, text.clone());
            self.say(level, text);
        }
    }

    /// The level keys (`None`: not one of them).
    pub(super) fn follower_level_key(&mut self, c: char) -> Option<Vec<Action>> {
        match c {
            'L' if self.level_active() => {
                if self.may_operate("stopping the level stations") {
                    self.overlay = Overlay::Confirm(Confirm::LevelStop);
                }
            }
            'L' => self.say(Level::Warn, "no level stations are under way"),
            'l' if self.level().is_some_and(|l| l.awaiting_reading.is_some()) => {
                if self.may_operate("typing the level's reading") {
                    self.follower.panel = AlignPanel::Follower;
                    self.overlay = Overlay::Input(Input {
                        purpose: InputFor::LevelReading,
                        text: String::new(),
                    });
                }
            }
            'l' if self.level_active() => {
                if self.may_operate("stopping the level stations") {
                    self.overlay = Overlay::Confirm(Confirm::LevelStop);
                }
            }
            'l' => self.ask_level_start(Confirm::LevelStart, "reading the level at stations"),
            'u' if self.level_active() => {
                self.say(
                    Level::Warn,
                    "the level stations are under way: stop them (L) or let them finish first",
                );
            }
            'u' => self.ask_level_start(
                Confirm::LevelCheck,
                "checking the map in use on this set-up",
            ),
            _ => return None,
        }
        Some(Vec::new())
    }

    /// Ask to start the level stations (`confirm`: to fit the map again or to check it on
    /// this set-up), unless the operator may not or a run or the mapping is under way.
    fn ask_level_start(&mut self, confirm: Confirm, what: &str) {
        if !self.may_operate(what) {
            return;
        }
        if self.run_active() || self.mapping_active() {
            self.say(
                Level::Warn,
                "a run or the follower mapping is under way: read the level's stations when it has ended",
            );
            return;
        }
        self.follower.panel = AlignPanel::Follower;
        self.overlay = Overlay::Confirm(confirm);
    }

    /// The level's reading typed into the input box.
    pub(super) fn follower_level_input(&mut self, text: &str) -> Vec<Action> {
        match parse_level_reading(text) {
            Ok(x) => {
                self.overlay = Overlay::None;
                self.log(Level::Info, format!("→ the level reads {x}″"));
                vec![self.send(
                    Request::FollowerLevelReading {
                        arcsec: serde_json::json!(x),
                    },
                    Pending::LevelReading,
                )]
            }
            Err(e) => {
                self.say(Level::Warn, e);
                Vec::new()
            }
        }
    }

    /// A start or stop of the level stations confirmed.
    pub(super) fn follower_level_confirmed(&mut self, c: Confirm) -> Vec<Action> {
        match c {
            Confirm::LevelStart => {
                self.log(Level::Info, "→ read the level at stations");
                vec![self.send(
                    Request::FollowerLevelStart(LevelRequest::default()),
                    Pending::LevelStart,
                )]
            }
            Confirm::LevelCheck => {
                self.log(Level::Info, "→ check the map in use on this set-up");
                vec![self.send(
                    Request::FollowerLevelStart(LevelRequest {
                        check_map: true,
                        ..LevelRequest::default()
                    }),
                    Pending::LevelStart,
                )]
            }
            Confirm::LevelStop => {
                self.log(Level::Info, "→ stop the level stations");
                vec![self.send(Request::FollowerLevelStop, Pending::LevelStop)]
            }
            _ => Vec::new(),
        }
    }

    /// The reply to a level request: what it started, took or stopped.
    pub(super) fn apply_level(&mut self, pending: &Pending, v: &serde_json::Value) {
        let text = match pending {
            Pending::LevelStart => format!(
                "level stations started: {} stations, dwell {:.1} s; {}",
                v["stations"].as_array().map_or(0, Vec::len),
                v["dwell_s"].as_f64().unwrap_or(0.0),
                v["cnc"].as_str().unwrap_or("")
            ),
            Pending::LevelReading => format!(
                "the level's reading {}″ taken at station {}",
                v["arcsec"].as_f64().unwrap_or(f64::NAN),
                v["station"].as_u64().unwrap_or(0)
            ),
            _ => v["error"]
                .as_str()
                .unwrap_or("level stations stopped")
                .to_string(),
        };
        self.follower.panel = AlignPanel::Follower;
        self.log(Level::Info, format!("✓ {text}"));
        self.say(Level::Info, text);
    }
}
