//! `axiscomp follower level`: a level's stations along the follower's map on the running
//! service (`service::follower_level`), thin over the control API: start them and follow them
//! to the refitted map (with `--check`: to the map in use checked on this set-up), or
//! `--status`, `--stop`, `--finish` them, or type the level's reading
//! at the station being read (`--reading ARCSEC`, `[follower] level = "manual"`). Exit codes:
//! 2 for a refused request, 1 for anything else.

use super::client::{Leave, duration_words, follow, refused, runtime, socket_path};
use anyhow::Result;
use axiscomp::service::api::LevelRequest;
use axiscomp::service::api::Request;
use axiscomp::service::control::Client;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct LevelArgs {
    /// The running service's control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The service's configuration, for its control socket (default:
    /// /etc/axiscomp/axiscomp.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the level stations are, then exit.
    #[arg(long, conflicts_with_all = ["stop", "finish", "reading"])]
    pub status: bool,
    /// Stop the level stations: nothing is stored, the map in use is unchanged.
    #[arg(long, conflicts_with_all = ["finish", "reading"])]
    pub stop: bool,
    /// Fit the map now with the stations taken (two at least).
    #[arg(long, conflicts_with = "reading")]
    pub finish: bool,
    /// The level's reading at the station being read (arcsec), with a level read by hand.
    #[arg(long, allow_negative_numbers = true, value_name = "ARCSEC")]
    pub reading: Option<f64>,
    /// Start the stations and return at once (follow them with --status).
    #[arg(long)]
    pub detach: bool,
    /// The stations' near end, the carriage's position (mm; default: the map's span).
    #[arg(long, allow_negative_numbers = true)]
    pub from_mm: Option<f64>,
    /// The stations' far end (mm; default: the map's span).
    #[arg(long, allow_negative_numbers = true)]
    pub to_mm: Option<f64>,
    /// Stations at most this far apart, both ends included (mm; default 100).
    #[arg(long)]
    pub station_mm: Option<f64>,
    /// Readings of the head (and of the twin's level) at each station (default 20).
    #[arg(long)]
    pub readings: Option<usize>,
    /// The carriage's feed between stations (mm/min; default 2000).
    #[arg(long)]
    pub feed_mm_min: Option<f64>,
    /// The program's axis letter (default X).
    #[arg(long)]
    pub axis: Option<String>,
    /// The program's dialect: iso, siemens, heidenhain or linuxcnc (default: the
    /// configuration's).
    #[arg(long)]
    pub dialect: Option<String>,
    /// Check the map in use on this set-up (the instrument's map from its bench) instead of
    /// fitting it again: re-used with this set-up's smooth bend when the stations fit it,
    /// refused with the span to map again when they do not (six stations at least).
    #[arg(long, conflicts_with_all = ["status", "stop", "finish", "reading"])]
    pub check: bool,
}

fn num(v: &serde_json::Value, k: &str) -> String {
    v[k].as_f64()
        .map(|x| format!("{x:.2}"))
        .unwrap_or_else(|| "–".into())
}

/// The stations' progress on one line.
fn progress_line(v: &serde_json::Value) -> String {
    let n = v["stations"].as_array().map_or(0, Vec::len);
    let mut line = format!(
        "{}: {} of {n} stations taken, {}",
        v["state"].as_str().unwrap_or("?"),
        v["taken"].as_u64().unwrap_or(0),
        duration_words(v["elapsed_s"].as_f64().unwrap_or(0.0))
    );
    if let Some(p) = v["prompt"].as_str().filter(|p| !p.is_empty()) {
        line.push_str("; ");
        line.push_str(p);
    }
    line
}

/// The stations as `follower_level_status` gives them.
fn print_status(v: &serde_json::Value) {
    if v["state"].as_str() == Some("idle") {
        println!("no level stations since the service started");
        return;
    }
    let what = if v["check_map"].as_bool() == Some(true) {
        "follower level stations, checking the map in use on this set-up,"
    } else {
        "follower level stations"
    };
    println!("{what} {}", progress_line(v));
    println!(
        "  axis {} {:.1} to {:.1} mm, a station every {} mm at most, {} readings each; the map in use then: {} ({}); started {} by {}",
        v["axis"].as_str().unwrap_or_default(),
        v["from_mm"].as_f64().unwrap_or(f64::NAN),
        v["to_mm"].as_f64().unwrap_or(f64::NAN),
        v["station_mm"].as_f64().unwrap_or(f64::NAN),
        v["readings"].as_u64().unwrap_or(0),
        v["map_from"].as_i64().unwrap_or(0),
        v["map_from_name"].as_str().unwrap_or_default(),
        v["started"].as_str().unwrap_or_default(),
        v["started_by"].as_str().unwrap_or_default()
    );
    for (k, what) in [
        ("instrument", "level: "),
        ("dwell", ""),
        ("program", "program: "),
        ("cnc", "CNC: "),
    ] {
        if let Some(t) = v[k].as_str().filter(|t| !t.is_empty()) {
            println!("  {what}{t}");
        }
    }
    for (k, s) in v["stations"].as_array().into_iter().flatten().enumerate() {
        println!(
            "  station {} at {:.1} mm: {}; head {}″, level {}″, vertical {} µm ± {} µm",
            k + 1,
            s["at_mm"].as_f64().unwrap_or(f64::NAN),
            s["state"].as_str().unwrap_or("?"),
            num(s, "head_arcsec"),
            num(s, "level_arcsec"),
            num(s, "value_um"),
            num(s, "u_um")
        );
    }
    if let Some(e) = v["error"].as_str() {
        println!("  {e}");
    }
    if let Some(id) = v["map_id"].as_i64() {
        println!(
            "  follower map {id}, in use (the vertical's u at mid-span {} µm with the steps alone, {} µm with the stations):",
            num(v, "u_mid_steps_um"),
            num(v, "u_mid_level_um")
        );
        for l in v["summary"].as_array().into_iter().flatten() {
            println!("    {}", l.as_str().unwrap_or_default());
        }
    }
}

/// How the stations end the command: done is success, anything else an error.
fn outcome(v: &serde_json::Value) -> Result<()> {
    match v["state"].as_str() {
        Some("done") => Ok(()),
        Some(s) => Err(anyhow::anyhow!(
            "the level stations {s}: {}",
            v["error"].as_str().unwrap_or("no map was stored")
        )),
        None => Err(anyhow::anyhow!("the service's reply has no state: {v}")),
    }
}

pub fn run(a: LevelArgs) -> Result<()> {
    let socket = socket_path(a.socket.as_deref(), a.config.as_deref())?;
    let req = LevelRequest {
        from_mm: a.from_mm,
        to_mm: a.to_mm,
        station_mm: a.station_mm,
        readings: a.readings,
        feed_mm_min: a.feed_mm_min,
        axis: a.axis.clone(),
        dialect: a.dialect.clone(),
        check_map: a.check,
    };
    runtime()?.block_on(async move {
        let mut c = Client::connect(&socket).await?;
        if a.status {
            let v = c.request(&Request::FollowerLevelStatus).await?;
            super::stdout_closes_quietly();
            print_status(&v);
            return Ok(());
        }
        if let Some(x) = a.reading {
            let r = Request::FollowerLevelReading {
                arcsec: serde_json::json!(x),
            };
            let v = c.request(&r).await.map_err(refused)?;
            println!(
                "the level's reading {x}″ taken at station {}",
                v["station"].as_u64().unwrap_or(0)
            );
            println!("  {}", progress_line(&v["view"]));
            return Ok(());
        }
        if a.stop || a.finish {
            let r = if a.stop {
                Request::FollowerLevelStop
            } else {
                Request::FollowerLevelFinish
            };
            let v = c.request(&r).await.map_err(refused)?;
            print_status(&v);
            return if a.stop { Ok(()) } else { outcome(&v) };
        }
        let mut leave = Leave::listen(
            "the level stations go on in the service; follow them with: axiscomp follower level \
             --status; stop them with: axiscomp follower level --stop"
                .into(),
        )?;
        let v = c
            .request(&Request::FollowerLevelStart(req))
            .await
            .map_err(refused)?;
        print_status(&v);
        if a.detach {
            println!("follow them with: axiscomp follower level --status");
            return Ok(());
        }
        if v["level"].as_str() == Some("manual") {
            println!(
                "at each station, type the level's reading from another terminal: axiscomp follower level --reading ARCSEC"
            );
        }
        let running =
            |v: &serde_json::Value| matches!(v["state"].as_str(), Some("stations" | "finishing"));
        let v = follow(
            &mut c,
            &Request::FollowerLevelStatus,
            progress_line,
            running,
            &mut leave,
        )
        .await?;
        print_status(&v);
        outcome(&v)
    })
}
