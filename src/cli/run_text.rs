//! What `axiscomp run start|status|abort|flags|exclude` print: the service's answer in words
//! (its JSON, as the control API serves it, with `--json`). A field the answer lacks is left
//! out, not printed as `null`.

use axiscomp::util::time::{rfc3339, span};
use serde_json::Value;
use std::time::Duration;

/// A duration in seconds, in words ("8 min 31 s").
fn secs(v: &Value) -> Option<String> {
    v.as_f64()
        .filter(|s| s.is_finite() && *s >= 0.0)
        .map(|s| span(Duration::from_secs_f64(s)))
}

fn count(v: &Value) -> u64 {
    v.as_u64().unwrap_or(0)
}

/// `run start`'s answer.
pub fn started(v: &Value) -> String {
    let mut out = format!(
        "run {} started: {} captures expected",
        v["run_id"],
        count(&v["captures_expected"])
    );
    if let Some(cnc) = v["cnc"].as_str() {
        out.push_str(&format!("\nprogram: {cnc}"));
    }
    if let Some(p) = v["program"].as_str() {
        out.push_str(&format!(" ({p})"));
    }
    for w in v["warnings"].as_array().into_iter().flatten() {
        if let Some(w) = w.as_str() {
            out.push_str(&format!("\nwarning: {w}"));
        }
    }
    out
}

/// `run status`'s answer: the active run's progress, or the newest stored run.
pub fn status(v: &Value) -> String {
    let state = v["state"].as_str().unwrap_or("unknown");
    if state == "none" {
        return "no run stored yet: start one with axiscomp run start".into();
    }
    if state != "running" {
        let mut out = format!(
            "run {} {state}: {} captures stored",
            v["run_id"],
            count(&v["captures"])
        );
        let (flagged, open) = (count(&v["flagged"]), count(&v["flags_open"]));
        if flagged > 0 {
            out.push_str(&format!(
                ", {flagged} flagged ({open} open: axiscomp run flags --run {})",
                v["run_id"]
            ));
        }
        if let Some(t) = secs(&v["machine_time_s"]) {
            out.push_str(&format!("; {t} of machine time"));
        }
        if let Some(n) = v["notes"].as_str().filter(|n| !n.is_empty()) {
            out.push_str(&format!("\nnotes: {n}"));
        }
        return out;
    }
    let mut out = format!(
        "run {} running{}: {} of {} captures",
        v["run_id"],
        if v["paused"].as_bool() == Some(true) {
            " (paused)"
        } else {
            ""
        },
        count(&v["captures"]),
        count(&v["expected"])
    );
    let (flagged, held) = (count(&v["flagged"]), count(&v["held"]));
    if flagged > 0 {
        out.push_str(&format!(", {flagged} flagged for a retake"));
    }
    if held > 0 {
        out.push_str(&format!(", {held} held"));
        if let Some(e) = v["unverified_since"].as_str() {
            out.push_str(&format!(" until a capture checks the reference after {e}"));
        }
    }
    if let Some(left) = secs(&v["left_s"]) {
        out.push_str(&format!("\nabout {left} of machine time left"));
        if let Some(so_far) = secs(&v["machine_s"]) {
            let since = if v["resumed"].as_bool() == Some(true) {
                "since the run was resumed"
            } else {
                "so far"
            };
            out.push_str(&format!(" ({so_far} {since})"));
        }
    }
    if let Some(p) = v["program"].as_str().filter(|p| !p.is_empty()) {
        out.push_str(&format!("\nprogram: {p}"));
    }
    out
}

/// `run abort`'s answer.
pub fn aborted(v: &Value) -> String {
    format!("run {} aborted: its captures stay stored", v["aborted"])
}

/// `run flags`' answer: each flag with its state, then the events.
pub fn flags(v: &Value) -> String {
    let flags = v["flags"].as_array().cloned().unwrap_or_default();
    let mut out = match flags.len() {
        0 => format!("run {}: no flagged captures", v["run_id"]),
        1 => format!("run {}: 1 flagged capture", v["run_id"]),
        n => format!("run {}: {n} flagged captures", v["run_id"]),
    };
    for f in &flags {
        out.push_str(&format!(
            "\n  flag {}: run {}, target {} ({:.3} mm) {}: {}; {}",
            f["flag"],
            f["run"],
            f["target"],
            f["target_mm"].as_f64().unwrap_or(f64::NAN),
            f["direction"].as_str().unwrap_or("?"),
            f["state"].as_str().unwrap_or("?"),
            f["reason"].as_str().unwrap_or("")
        ));
    }
    let events = v["events"].as_array().cloned().unwrap_or_default();
    if !events.is_empty() {
        out.push_str(&format!(
            "\nevents that could move the reference ({}):",
            events.len()
        ));
        for e in &events {
            let at = e["unix_us"]
                .as_i64()
                .map(|us| rfc3339(us.div_euclid(1_000_000)))
                .unwrap_or_default();
            out.push_str(&format!(
                "\n  {at} {}: {}",
                e["kind"].as_str().unwrap_or("?"),
                e["detail"].as_str().unwrap_or("")
            ));
        }
    }
    let restated = v["restated"].as_array().map_or(0, Vec::len);
    if restated > 0 {
        out.push_str(&format!(
            "\n{restated} captures had their u stated again (--json lists them)"
        ));
    }
    out
}

/// `run exclude`'s answer.
pub fn excluded(v: &Value) -> String {
    let open = count(&v["open"]);
    format!(
        "flag {} of run {} excluded; {}",
        v["excluded"],
        v["run_id"],
        if open == 0 {
            "no flag is open: the run's tables can be generated".to_string()
        } else {
            format!("{open} flags still open")
        }
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_running_runs_status_is_words() {
        // The CLI printed {"left_s": 511.48212121212026, …}.
        let v = json!({
            "run_id": 3, "state": "running", "captures": 41, "expected": 110, "missing": 69,
            "flagged": 2, "held": 1, "unverified_since": "PSD2's stitch re-referenced",
            "program": "/var/lib/axiscomp/runs/3/program-1.ngc", "paused": false,
            "plan_s": 871.456313235, "left_s": 511.48212121212026, "machine_s": 360.2,
            "resumed": false
        });
        assert_eq!(
            status(&v),
            "run 3 running: 41 of 110 captures, 2 flagged for a retake, 1 held until a capture checks the reference after PSD2's stitch re-referenced\n\
             about 8 min 31 s of machine time left (6 min 00 s so far)\n\
             program: /var/lib/axiscomp/runs/3/program-1.ngc"
        );
    }

    #[test]
    fn stored_runs_starts_aborts_and_flags_are_words() {
        let v = json!({"run_id": 2, "state": "finished with flags", "captures": 110,
            "flagged": 3, "flags_open": 1, "notes": "", "machine_time_s": 1402.0});
        assert_eq!(
            status(&v),
            "run 2 finished with flags: 110 captures stored, 3 flagged (1 open: axiscomp run flags --run 2); 23 min 22 s of machine time"
        );
        assert_eq!(
            status(&json!({"state": "none"})),
            "no run stored yet: start one with axiscomp run start"
        );
        let v = json!({"run_id": 4, "captures_expected": 110, "warnings": ["fewer than five runs"],
            "cnc": "sent to the twin at 127.0.0.1:5020", "program": "/s/runs/4/program-0.ngc"});
        assert_eq!(
            started(&v),
            "run 4 started: 110 captures expected\nprogram: sent to the twin at 127.0.0.1:5020 (/s/runs/4/program-0.ngc)\nwarning: fewer than five runs"
        );
        assert_eq!(
            aborted(&json!({"aborted": 4})),
            "run 4 aborted: its captures stay stored"
        );
        let v = json!({"run_id": 2, "flags": [{"flag": 7, "run": 3, "target": 5,
            "target_mm": 399.721, "direction": "+", "errors_um_arcsec": [0, 0, 0, 0, 0, 0],
            "reason": "off the other 4 captures of its target and direction by dy +3.5 µm (limit 0.5)",
            "was_stored": false, "state": "retaken"}],
            "events": [{"unix_us": 1_700_000_000_000_000i64, "kind": "knock", "detail": "a knock turned the head"}],
            "restated": []});
        assert_eq!(
            flags(&v),
            "run 2: 1 flagged capture\n  flag 7: run 3, target 5 (399.721 mm) +: retaken; off the other 4 captures of its target and direction by dy +3.5 µm (limit 0.5)\n\
             events that could move the reference (1):\n  2023-11-14T22:13:20Z knock: a knock turned the head"
        );
        assert_eq!(
            excluded(&json!({"run_id": 2, "excluded": 7, "open": 0})),
            "flag 7 of run 2 excluded; no flag is open: the run's tables can be generated"
        );
    }
}
