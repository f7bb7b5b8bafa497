//! The replies to the console's requests, each applied to the state of the screen that asked.

use super::*;

impl App {
    /// The reply to request `id`; it may ask for more (the result of a run that finished).
    pub fn handle_reply(
        &mut self,
        id: u64,
        result: Result<serde_json::Value, ClientError>,
        now: Instant,
    ) -> Vec<Action> {
        self.now = now;
        let Some(pending) = self.pending.remove(&id) else {
            return Vec::new();
        };
        if matches!(
            pending,
            Pending::Machine
                | Pending::MachineAttach(_)
                | Pending::MachineDetach(_)
                | Pending::MachineNew
        ) && !result.as_ref().is_err_and(ClientError::is_role_refusal)
        {
            return self.machine_reply(&pending, result.map_err(|e| e.to_string()));
        }
        let v = match result {
            Ok(v) => v,
            Err(e) => {
                if e.is_role_refusal() {
                    match pending {
                        Pending::Publish(_) => self.publish.publishing = None,
                        Pending::Generate(_) => self.publish.generating = None,
                        Pending::Fit => self.calibrate.fitting = false,
                        Pending::MachineAttach(_) => self.machine.attaching = None,
                        _ => {}
                    }
                    self.access = Access::Viewer;
                    self.say(Level::Warn, format!("read-only (viewer): {e}"));
                    self.log(Level::Error, format!("✗ {e}"));
                } else {
                    match pending {
                        Pending::RunStatus | Pending::RunResult(ResultFor::Live) => {}
                        Pending::RunResult(_) => {
                            self.results.error = Some(e.to_string());
                            self.say(Level::Error, e.to_string());
                        }
                        Pending::Trend => {
                            self.trends.error = Some(format!("trends: {e}"));
                            self.say(Level::Error, format!("trends: {e}"));
                        }
                        Pending::Tables => {
                            self.publish.listed = true;
                            self.say(Level::Error, format!("table list: {e}"));
                        }
                        Pending::TableStatus => self.publish.status = Some(Err(e.to_string())),
                        Pending::Publish(table_id) => {
                            self.publish.publishing = None;
                            self.publish.outcome = Some(Err(e.to_string()));
                            self.log(Level::Error, format!("✗ publish table {table_id}: {e}"));
                            self.say(Level::Error, format!("publish failed: {e}"));
                            return self.reload_publish();
                        }
                        Pending::Generate(run) => {
                            self.publish.generating = None;
                            self.log(Level::Error, format!("✗ generate from run {run}: {e}"));
                            self.say(Level::Error, e.to_string());
                        }
                        Pending::Calibration => {
                            self.calibrate.loaded = true;
                            self.calibrate.error = Some(e.to_string());
                        }
                        Pending::HexapodStatus => self.calibrate.error = Some(e.to_string()),
                        // Asked once: a service that cannot say leaves the screen as it was.
                        Pending::AlignStored => {
                            self.align.stored = StoredAlignment::None;
                            self.log(Level::Warn, format!("stored alignment: {e}"));
                        }
                        Pending::Fit
                        | Pending::CalAccept
                        | Pending::CalReject
                        | Pending::HexapodStart
                        | Pending::HexapodStop => {
                            if pending == Pending::Fit {
                                self.calibrate.fitting = false;
                            }
                            self.calibrate.error = Some(e.to_string());
                            self.log(Level::Error, format!("✗ {e}"));
                            self.say(Level::Error, e.to_string());
                        }
                        _ => {
                            self.say(Level::Error, e.to_string());
                            self.log(Level::Error, format!("✗ {e}"));
                        }
                    }
                }
                return Vec::new();
            }
        };
        if self.access == Access::Unknown && !pending.is_read() {
            // An operator request went through.
            self.access = Access::Operator;
        }
        match pending {
            Pending::Tables => {
                match serde_json::from_value::<Vec<TableView>>(v["tables"].clone()) {
                    Ok(tables) => {
                        let keep = self.publish.selected_table().map(|t| t.id);
                        let p = &mut self.publish;
                        p.tables = tables;
                        p.map = v["map"].as_str().map(str::to_string);
                        p.selected = keep
                            .and_then(|id| p.tables.iter().position(|t| t.id == id))
                            .unwrap_or(0);
                    }
                    Err(e) => self.say(Level::Error, format!("bad table list: {e}")),
                }
                self.publish.listed = true;
            }
            Pending::TableStatus => {
                self.publish.status = Some(
                    serde_json::from_value::<StatusView>(v)
                        .map_err(|e| format!("bad table status from the service: {e}")),
                );
            }
            Pending::Generate(run) => {
                self.publish.generating = None;
                let ids: Vec<String> = v["tables"]
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .map(|t| {
                                format!(
                                    "{} {}",
                                    t["id"].as_i64().unwrap_or(0),
                                    t["name"].as_str().unwrap_or("?")
                                )
                            })
                            .collect()
                    })
                    .unwrap_or_default();
                // Issue 15: say when they are the active tables plus the run's residual.
                let composed = v["tables"].as_array().is_some_and(|a| {
                    a.iter().any(|t| {
                        t["composition"]
                            .as_str()
                            .is_some_and(|c| c.starts_with("composed"))
                    })
                });
                let text = format!(
                    "run {run}: tables {} generated{}",
                    ids.join(", "),
                    if composed {
                        ", composed: the active tables plus the residual"
                    } else {
                        ""
                    }
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                // The newest first: select the first generated.
                self.publish.selected = 0;
                return self.reload_publish();
            }
            Pending::Publish(table_id) => {
                self.publish.publishing = None;
                let outcome = serde_json::from_value::<PublishView>(v)
                    .map_err(|e| format!("bad publish reply from the service: {e}"));
                let (level, text) = match &outcome {
                    Ok(p) if p.result == "committed" => (
                        Level::Info,
                        format!("table {table_id} committed as sequence {}", p.sequence),
                    ),
                    Ok(p) => (
                        Level::Error,
                        format!("table {table_id} {}: {}", p.result, p.message),
                    ),
                    Err(e) => (Level::Error, e.clone()),
                };
                self.log(
                    level,
                    format!("{} {text}", if level == Level::Info { "✓" } else { "✗" }),
                );
                self.say(level, text);
                self.publish.outcome = Some(outcome);
                return self.reload_publish();
            }
            Pending::Calibration => self.apply_calibration(&v),
            Pending::HexapodStatus => return self.apply_hexapod_status(v),
            Pending::HexapodStart => {
                let text = format!(
                    "hexapod run started: {} poses, {} stored already ({})",
                    v["poses"].as_u64().unwrap_or(0),
                    v["stored"].as_u64().unwrap_or(0),
                    v["out"].as_str().unwrap_or("")
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                // Follow it now.
                self.calibrate.last_hexapod_status = None;
                return self.calibrate_need_hexapod();
            }
            Pending::HexapodStop => {
                let text = format!(
                    "stopping the hexapod at pose {} of {}: u resumes",
                    v["done"].as_u64().unwrap_or(0),
                    v["total"].as_u64().unwrap_or(0)
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            Pending::Fit => {
                self.calibrate.fitting = false;
                self.calibrate.error = None;
                match serde_json::from_value::<CalSummary>(v["pending"].clone()) {
                    Ok(c) => {
                        let text = format!(
                            "fitted {} poses ({}): judge it, then a accepts or x rejects",
                            c.poses, c.decoupling
                        );
                        self.log(Level::Info, format!("✓ {text}"));
                        self.say(Level::Info, text);
                        self.calibrate.pending = Some(c);
                    }
                    Err(e) => self.say(Level::Error, format!("bad fit reply: {e}")),
                }
            }
            Pending::CalAccept => {
                let text = format!(
                    "calibration {} in use ({}); the zero was cleared: take it again (screen 2, z)",
                    v["calibration_id"].as_i64().unwrap_or(0),
                    v["decoupling"].as_str().unwrap_or("?")
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            Pending::CalReject => {
                self.calibrate.pending = None;
                self.log(Level::Info, "✓ calibration rejected");
                self.say(Level::Info, "calibration rejected");
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            Pending::RunStart(plan) => {
                let run_id = v["run_id"].as_i64().unwrap_or(0);
                let expected = v["captures_expected"].as_u64().map(|n| n as usize);
                let mut r = RunProgress::new(run_id, 0, now);
                r.expected = expected;
                r.program = v["program"].as_str().map(str::to_string);
                r.plan = Some(*plan);
                self.run = Some(r);
                let cnc = v["cnc"].as_str().unwrap_or("");
                let text = format!(
                    "run {run_id} started: {} captures; {cnc}",
                    expected.map(|e| e.to_string()).unwrap_or("?".into())
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            Pending::RunStatus => return self.apply_run_status(&v, now),
            Pending::Runs => self.apply_runs(v),
            Pending::Trend => self.apply_trend(v),
            Pending::Audit => {
                match serde_json::from_value::<Vec<AuditView>>(v["entries"].clone()) {
                    Ok(entries) => self.audit = Some(entries),
                    Err(e) => {
                        self.say(Level::Error, format!("bad audit log from the service: {e}"))
                    }
                }
            }
            Pending::RunResult(to) => self.apply_result(to, v),
            Pending::RunAbort => {
                let text = match v["aborted"].as_i64() {
                    Some(id) => format!("run {id} aborted (its captures stay stored)"),
                    None => "run aborted".into(),
                };
                if let Some(r) = self.run.as_mut() {
                    r.state = "aborted".into();
                }
                self.results.listed = false;
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            Pending::AlignRead => self.apply_align_station(&v, false),
            Pending::AlignTarget => self.apply_align_station(&v, true),
            Pending::AlignAdvice(span) => self.apply_align_advice(&v, span),
            Pending::AlignStored => self.apply_align_stored(&v),
            Pending::AlignClear => {
                self.align.stations.clear();
                self.align.advice = None;
                self.log(Level::Info, "✓ stations cleared");
                self.say(Level::Info, "stations cleared: read both ends again (n, f)");
            }
            Pending::Certificate => self.apply_certificate(&v),
            Pending::MapStart => self.apply_mapping_started(&v),
            p @ (Pending::LevelStart | Pending::LevelStop | Pending::LevelReading) => {
                self.apply_level(&p, &v)
            }
            Pending::MapStop => {
                let text = v["error"]
                    .as_str()
                    .unwrap_or("follower mapping stopped")
                    .to_string();
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            // Answered by `machine_reply` above.
            Pending::Machine
            | Pending::MachineAttach(_)
            | Pending::MachineDetach(_)
            | Pending::MachineNew => {}
            Pending::Other(what) => {
                let text = format!("{what} done{}", answer_words(&v));
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
        }
        Vec::new()
    }

    /// The outcome of an [`Action::Save`].
    pub fn handle_saved(&mut self, path: &str, result: Result<(), String>) {
        match result {
            Ok(()) => {
                self.log(Level::Info, format!("✓ part program saved to {path}"));
                self.say(Level::Info, format!("part program saved to {path}"));
                self.saved = Some(Ok(path.to_string()));
            }
            Err(e) => {
                let text = format!("part program not saved to {path}: {e}");
                self.log(Level::Error, format!("✗ {text}"));
                self.say(Level::Error, text.clone());
                self.saved = Some(Err(text));
            }
        }
    }
}

/// The service's answer to a zero, a cleared zero or a follower move, in words after "done"
/// (the console printed `zero here done: {"offsets":[0.0171208…`): the offsets the zero took,
/// the follower's position; nothing for an answer with nothing to say.
fn answer_words(v: &serde_json::Value) -> String {
    if let Some(o) = v["offsets"].as_array().filter(|o| o.len() == 6) {
        let parts: Vec<String> = o
            .iter()
            .zip(crate::units::DOF_NAMES)
            .enumerate()
            .map(|(k, (x, name))| match x.as_f64() {
                Some(x) if k < 3 => format!("{name} {x:+.2} µm"),
                Some(x) => format!("{name} {x:+.2}″"),
                None => format!("{name} unknown"),
            })
            .collect();
        return format!(": offsets {}", parts.join(", "));
    }
    if let Some(p) = v["position_mm"].as_f64() {
        return format!(": the follower at {p:.3} mm");
    }
    String::new()
}

#[cfg(test)]
mod answer_tests {
    use super::answer_words;
    use serde_json::json;

    #[test]
    fn answers_are_words() {
        assert_eq!(
            answer_words(
                &json!({"zeroed": true, "offsets": [0.0171208, -1.25, 0.0, 0.41, -0.005, 2.0]})
            ),
            ": offsets dx +0.02 µm, dy -1.25 µm, dz +0.00 µm, ex +0.41″, ey -0.01″, ez +2.00″"
        );
        assert_eq!(answer_words(&json!({"zeroed": false})), "");
        assert_eq!(
            answer_words(&json!({"position_mm": 12.34567})),
            ": the follower at 12.346 mm"
        );
        assert_eq!(answer_words(&serde_json::Value::Null), "");
    }
}
