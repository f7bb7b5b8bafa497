//! The Align screen's state and keys: follower jog, home, stop and fault reset; zero; and the
//! beam alignment over a span of travel (stations read at both ends, target readings where a
//! spot is off its PSD, the service's advice: the check, the screw turns, the beam angle).

use super::*;

/// One PSD's spot at a station as the service read it (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StationSpot {
    pub x: f64,
    pub y: f64,
    /// Read from the alignment target (the spot was off the PSD).
    pub from_target: bool,
}

/// A station read with the carriage at rest.
#[derive(Clone, Debug, PartialEq)]
pub struct StationView {
    pub at_mm: f64,
    pub spots: [Option<StationSpot>; 3],
}

impl StationView {
    fn from_json(v: &serde_json::Value) -> Option<StationView> {
        let at_mm = v["at_mm"].as_f64()?;
        let spots = std::array::from_fn(|k| {
            let s = &v["spots"][k];
            Some(StationSpot {
                x: s["x"].as_f64()?,
                y: s["y"].as_f64()?,
                from_target: s["from"].as_str() == Some("target"),
            })
        });
        Some(StationView { at_mm, spots })
    }
}

/// The service's advice, as its reply says it.
#[derive(Clone, Debug, PartialEq)]
pub struct AdviceView {
    pub passed: bool,
    /// The check over the span, in words.
    pub check: String,
    /// What the check would be after the turns.
    pub after: String,
    /// "turn the yaw screw 1.35 turns clockwise", one per screw.
    pub turns: Vec<String>,
    /// The beam's angle to the travel (yaw, pitch), when PSD3 was read at both ends.
    pub misalignment_urad: Option<[f64; 2]>,
    pub span_mm: (f64, f64),
}

impl AdviceView {
    fn from_json(v: &serde_json::Value, span_mm: (f64, f64)) -> AdviceView {
        let m = &v["misalignment_urad"];
        AdviceView {
            passed: v["passed"].as_bool() == Some(true),
            check: v["check"].as_str().unwrap_or_default().to_string(),
            after: v["after"].as_str().unwrap_or_default().to_string(),
            turns: v["turns"]
                .as_array()
                .map(|a| {
                    a.iter()
                        .filter_map(|t| t["text"].as_str().map(str::to_string))
                        .collect()
                })
                .unwrap_or_default(),
            misalignment_urad: m[0].as_f64().zip(m[1].as_f64()).map(|(y, p)| [y, p]),
            span_mm,
        }
    }
}

/// The newest alignment the store holds for the plan's axis, as `align_stored` says it.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum StoredAlignment {
    /// Not asked since the console (or the service) started, or a newer one was stored.
    #[default]
    Unknown,
    /// The axis has none (or the service could not say).
    None,
    Found {
        unix_us: i64,
        advice: AdviceView,
    },
}

impl StoredAlignment {
    fn from_json(v: &serde_json::Value) -> StoredAlignment {
        let span = v["from_mm"].as_f64().zip(v["to_mm"].as_f64());
        match (v["unix_us"].as_i64(), span) {
            (Some(unix_us), Some(span)) => StoredAlignment::Found {
                unix_us,
                advice: AdviceView::from_json(v, span),
            },
            _ => StoredAlignment::None,
        }
    }
}

/// The alignment procedure's state on the Align screen.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AlignProc {
    /// The span typed (`s`); `None`: the Measure plan's start and end.
    pub span: Option<(f64, f64)>,
    /// The stations read since the last clear, in reading order (one per position).
    pub stations: Vec<StationView>,
    pub advice: Option<AdviceView>,
    /// The newest stored alignment of the plan's axis: shown while there is no advice.
    pub stored: StoredAlignment,
}

/// Parse the span typed: "FROM TO" in mm, FROM below TO.
pub fn parse_span(text: &str) -> Result<(f64, f64), String> {
    let nums: Vec<f64> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("span \"{text}\": type two positions in mm, e.g. 0 400"))?;
    match nums[..] {
        [a, b] if a < b => Ok((a, b)),
        [a, b] => Err(format!(
            "span {a}–{b} mm: the near end must be below the far end"
        )),
        _ => Err(format!(
            "span \"{text}\": type two positions in mm, e.g. 0 400"
        )),
    }
}

/// Parse a target reading typed: "PSD X Y" (PSD 1..3, X and Y in mm).
pub fn parse_target(text: &str) -> Result<(usize, f64, f64), String> {
    let bad = || {
        format!(
            "target \"{text}\": type the PSD (1–3) and what its target shows, X and Y in mm, e.g. 2 1.5 -0.5"
        )
    };
    let parts: Vec<&str> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .collect();
    let [p, x, y] = parts[..] else {
        return Err(bad());
    };
    let digits = match p.get(..3) {
        Some(pre) if pre.eq_ignore_ascii_case("psd") => &p[3..],
        _ => p,
    };
    let psd = digits
        .parse::<usize>()
        .ok()
        .filter(|k| (1..=3).contains(k))
        .ok_or_else(bad)?;
    let num = |t: &str| t.parse::<f64>().ok().filter(|v| v.is_finite());
    match (num(x), num(y)) {
        (Some(x), Some(y)) => Ok((psd, x, y)),
        _ => Err(bad()),
    }
}

impl App {
    /// The span the alignment covers (mm): typed, or the Measure plan's travel (its end targets
    /// and the overrun: what the pre-run check asks for).
    pub fn align_span(&self) -> (f64, f64) {
        self.align
            .span
            .unwrap_or_else(|| match self.plan.checked() {
                Ok(plan) => plan.travel_mm(),
                Err(_) => (self.plan.spec.start_mm, self.plan.spec.end_mm),
            })
    }

    fn align_read(&mut self, at_mm: f64, end: &str) -> Vec<Action> {
        if !self.may_operate("reading a station") {
            return Vec::new();
        }
        self.log(Level::Info, format!("→ read the {end} end at {at_mm} mm"));
        vec![self.send(
            Request::AlignRead { at_mm: Some(at_mm) },
            Pending::AlignRead,
        )]
    }

    pub(super) fn apply_align_station(&mut self, v: &serde_json::Value, target: bool) {
        let Some(st) = StationView::from_json(v) else {
            self.say(Level::Error, "the service's station reply has no position");
            return;
        };
        let missing: Vec<String> = (0..3)
            .filter(|k| st.spots[*k].is_none())
            .map(|k| format!("PSD{}", k + 1))
            .collect();
        let at = st.at_mm;
        self.align.stations.retain(|s| (s.at_mm - at).abs() > 1.0);
        self.align.stations.push(st);
        if missing.is_empty() {
            let what = if target {
                "target reading taken"
            } else {
                "read"
            };
            self.say(Level::Info, format!("station at {at:.1} mm {what}"));
        } else {
            self.say(
                Level::Warn,
                format!(
                    "station at {at:.1} mm: no spot on {}: type what the target shows (t)",
                    missing.join(", ")
                ),
            );
        }
    }

    pub(super) fn apply_align_advice(&mut self, v: &serde_json::Value, span: (f64, f64)) {
        let a = AdviceView::from_json(v, span);
        if a.passed {
            self.say(Level::Info, format!("check passed: {}", a.check));
            self.log(Level::Info, format!("alignment check passed: {}", a.check));
        } else if a.turns.is_empty() {
            self.say(Level::Warn, format!("check not passed: {}", a.check));
        } else {
            self.say(
                Level::Info,
                format!("{}, then read both ends again", a.turns.join(", ")),
            );
        }
        self.align.advice = Some(a);
        // The advice was stored: the stored one is this one now.
        self.align.stored = StoredAlignment::Unknown;
    }

    /// The stored alignment's reply.
    pub(super) fn apply_align_stored(&mut self, v: &serde_json::Value) {
        self.align.stored = StoredAlignment::from_json(v);
    }

    /// On the Align screen, the stored alignment of the plan's axis once (again after a
    /// reconnect or a new advice).
    pub(super) fn align_need_stored(&mut self) -> Vec<Action> {
        if self.screen != Screen::Align
            || self.align.stored != StoredAlignment::Unknown
            || self.waiting(&Pending::AlignStored)
        {
            return Vec::new();
        }
        vec![self.send(
            Request::AlignStored {
                axis: Some(self.plan.spec.axis.clone()),
            },
            Pending::AlignStored,
        )]
    }

    /// The Align screen's alignment keys (`None`: not one of them).
    fn align_proc_key(&mut self, c: char) -> Option<Vec<Action>> {
        let (from, to) = self.align_span();
        Some(match c {
            's' => {
                self.overlay = Overlay::Input(Input {
                    purpose: InputFor::AlignSpan,
                    text: format!("{from} {to}"),
                });
                Vec::new()
            }
            'n' => self.align_read(from, "near"),
            'f' => self.align_read(to, "far"),
            't' => {
                if !self.may_operate("typing a target reading") {
                    return Some(Vec::new());
                }
                if self.align.stations.is_empty() {
                    self.say(
                        Level::Warn,
                        "read a station first (n or f), then what its targets show",
                    );
                    return Some(Vec::new());
                }
                let psd = self
                    .align
                    .stations
                    .last()
                    .and_then(|s| s.spots.iter().position(Option::is_none))
                    .map(|k| format!("{} ", k + 1))
                    .unwrap_or_default();
                self.overlay = Overlay::Input(Input {
                    purpose: InputFor::AlignTarget,
                    text: psd,
                });
                // The PSD's number is a start to type on, not a suggestion to replace.
                self.input_fresh = false;
                Vec::new()
            }
            'a' => {
                if !self.may_operate("asking for the alignment advice") {
                    return Some(Vec::new());
                }
                self.log(
                    Level::Info,
                    format!("→ alignment advice over {from}–{to} mm"),
                );
                vec![self.send(
                    Request::AlignAdvice {
                        from_mm: from,
                        to_mm: to,
                        axis: Some(self.plan.spec.axis.clone()),
                    },
                    Pending::AlignAdvice((from, to)),
                )]
            }
            'e' => {
                if !self.may_operate("clearing the stations") {
                    return Some(Vec::new());
                }
                vec![self.send(Request::AlignClear, Pending::AlignClear)]
            }
            _ => return None,
        })
    }

    /// A span or a target reading typed into the input box.
    pub(super) fn align_input(&mut self, purpose: &InputFor, text: &str) -> Vec<Action> {
        match purpose {
            InputFor::AlignSpan => match parse_span(text) {
                Ok(span) => {
                    self.overlay = Overlay::None;
                    self.align.span = Some(span);
                    self.align.advice = None;
                    self.say(
                        Level::Info,
                        format!("alignment span {}–{} mm", span.0, span.1),
                    );
                    Vec::new()
                }
                Err(e) => {
                    self.say(Level::Warn, e);
                    Vec::new()
                }
            },
            InputFor::AlignTarget => match parse_target(text) {
                Ok((psd, x, y)) => {
                    self.overlay = Overlay::None;
                    self.log(
                        Level::Info,
                        format!("→ PSD{psd}'s target shows x {x} mm, y {y} mm"),
                    );
                    vec![self.send(Request::AlignTarget { psd, x, y }, Pending::AlignTarget)]
                }
                Err(e) => {
                    self.say(Level::Warn, e);
                    Vec::new()
                }
            },
            _ => Vec::new(),
        }
    }
}

impl App {
    pub(super) fn follower(
        &mut self,
        action: FollowerAction,
        mm: Option<f64>,
        what: String,
    ) -> Vec<Action> {
        if !self.may_operate(&what) {
            return Vec::new();
        }
        vec![self.send(Request::Follower { action, mm }, Pending::Other(what))]
    }

    pub(super) fn align_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let step = self.jog_step_mm;
        if let Some(out) = key_char(&key).and_then(|c| self.align_proc_key(c)) {
            return out;
        }
        if let Some(out) = key_char(&key).and_then(|c| self.follower_map_key(c)) {
            return out;
        }
        if let Some(out) = key_char(&key).and_then(|c| self.follower_level_key(c)) {
            return out;
        }
        match key_char(&key) {
            Some('h') => self.follower(FollowerAction::Home, None, "home the follower".into()),
            Some('j') => self.follower(
                FollowerAction::Jog,
                Some(-step),
                format!("jog the follower -{step} mm"),
            ),
            Some('k') => self.follower(
                FollowerAction::Jog,
                Some(step),
                format!("jog the follower +{step} mm"),
            ),
            Some('x') => self.follower(FollowerAction::Stop, None, "stop the follower".into()),
            Some('r') => self.follower(
                FollowerAction::FaultReset,
                None,
                "reset the follower's fault".into(),
            ),
            Some('z') => {
                if !self.may_operate("zero") {
                    return Vec::new();
                }
                vec![self.send(Request::Zero, Pending::Other("zero here".into()))]
            }
            Some('c') => {
                if !self.may_operate("clear zero") {
                    return Vec::new();
                }
                vec![self.send(Request::ClearZero, Pending::Other("clear the zero".into()))]
            }
            Some('+' | ']') => {
                self.jog_step_mm = (step * 10.0).min(10.0);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            Some('-' | '[') => {
                self.jog_step_mm = (step / 10.0).max(0.001);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            _ => Vec::new(),
        }
    }
}
