//! A level's stations along the follower's map, run by the service (issue 14, DESIGN §4).
//!
//! The stop-and-go self-calibration gives the follower's vertical only relative to an
//! end-point line, its noise a random walk between the ends. A precision electronic level on
//! the carriage, read beside the head's roll at stations along the travel, gives the
//! follower's true vertical at each station up to one common constant
//! (`follower::level`): fitted together with the self-calibration's steps kept with the map
//! in use (`follower::build_referenced`), the map's line is fixed and its random walk pinned
//! between the stations.
//!
//! Control requests (operators; `follower_level_status` for viewers): `follower_level_start`
//! (stations every `station_mm` over the map's span or `from_mm`..`to_mm`, `readings` of the
//! head at each), `follower_level_status`, `follower_level_reading` (`arcsec`: the level's
//! reading the operator reads at the current station, `[follower] level = "manual"`),
//! `follower_level_stop` (nothing stored), `follower_level_finish` (build now from the
//! stations taken, two at least).
//!
//! At each station the carriage rests: the service averages the head's roll over `readings`
//! fresh live windows and pairs it with the level's — the twin's level asked once a window
//! (`[follower] level = "twin"`, the twin's control socket `level`), or the operator's typed
//! reading. The carriage is moved by a part program with a dwell per station long enough for
//! the readings (`run::program::generate_stops`): with `[cnc] mode = "twin"` sent to the
//! twin's CNC, else written for the operator; either way a station is taken when the carriage
//! comes to rest within [`NEAR_MM`] of it. At the end the map is fitted again from the map in
//! use's stored steps and certificate with the stations, stored as a new map ("… + level at N
//! stations"), put in use and the zero taken again. A measurement run, a hexapod run and a
//! follower mapping refuse to start under it, and it under them. Not resumed after a
//! restart (nothing is stored until the end).
//!
//! With `check_map` (issue 26) the stations check the map in use on this set-up instead of
//! fitting it again (`follower::reuse`): no steps needed, six stations at least; a map that
//! fits is stored with the set-up's bend and put in use, one that does not is refused with
//! the span where the rail changed, nothing stored.

use super::{Ctx, Procedure, Reply, Who};
use crate::config::{CncMode, LevelSource};
use crate::follower::{FollowerMap, LevelStation, StoredMap, StoredSteps, VerticalReference};
use crate::run::Dialect;
use crate::service::api::follower::typed_reading;
use crate::service::api::{LevelRequest, LevelView, Request, Snapshot, StationView};
use crate::service::cnc::{CncDriver, CncNews};
use crate::service::pipeline::Pipeline;
use crate::store::FollowerMapRecord;
use crate::units::RAD_PER_ARCSEC;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// Stations at most this far apart by default (mm).
pub const DEFAULT_STATION_MM: f64 = 100.0;
/// Readings of the head (live windows) at each station by default.
pub const DEFAULT_READINGS: usize = 20;
/// A station is taken with the carriage at rest within this of it (mm).
pub const NEAR_MM: f64 = 1.0;
/// With the level read by hand, the dwell leaves this long to read it and type it (s).
const TYPING_S: f64 = 20.0;
/// The carriage's feed between stations by default (mm/min).
const DEFAULT_FEED_MM_MIN: f64 = 2000.0;
/// Each reading is a fresh live window: this much after the last one ended.
const READING_GAP: Duration = Duration::from_millis(50);

/// What the level stations need of the service's configuration.
#[derive(Clone, Debug)]
pub struct LevelConfig {
    pub source: LevelSource,
    /// One level reading's stated standard deviation (rad).
    pub level_sd_rad: f64,
    pub cnc: CncMode,
    pub dialect: Dialect,
    pub state_dir: PathBuf,
    /// PSD frames per second (0: as fast as the module answers, taken as 200).
    pub frame_rate_hz: f64,
    /// The head's live window (each reading one).
    pub live_window: Duration,
    pub sync: Duration,
}

/// Results of the stations' own asynchronous work.
#[derive(Debug)]
enum Event {
    /// The twin level's reading `k` (rad) of visit `visit`.
    Level {
        visit: u64,
        k: usize,
        roll: Result<f64, String>,
    },
    /// The map fitted with the stations stored (or not): how they ended, the missed
    /// stations, the reply owed.
    Stored(Box<Stored>),
}

/// The map fitted with the stations stored (or not).
#[derive(Debug)]
struct Stored {
    how: String,
    missed: Vec<String>,
    record: Result<FollowerMapRecord, String>,
    reply: Option<Reply>,
}

/// The head read at a station, waiting for the level (or being read).
#[derive(Debug)]
struct Reading {
    station: usize,
    visit: u64,
    head: Vec<f64>,
    /// The twin level's replies, by reading; the operator's typed readings (rad).
    level: Vec<Option<f64>>,
    typed: Vec<f64>,
    next_at: Instant,
    /// Once the head's readings are complete: the encoder, the map's vertical there and g.
    fixed: Option<(f64, f64, f64)>,
}

/// A station taken.
#[derive(Clone, Copy, Debug)]
struct Taken {
    station: LevelStation,
    head: f64,
    level: f64,
}

#[derive(Debug)]
struct Active {
    source: FollowerMapRecord,
    /// The self-calibration's steps the stations are fitted with; none for a check of the
    /// map in use on this set-up (`LevelRequest::check_map`).
    steps: Option<StoredSteps>,
    /// The map the tracker applies (the map in use): its vertical is the stations' base.
    applied: Arc<FollowerMap>,
    stations: Vec<f64>,
    taken: Vec<Option<Taken>>,
    readings: usize,
    reading: Option<Reading>,
    visit: u64,
    started: Instant,
    grace: Duration,
    /// How the program moves the carriage, its dwell (s), and whether the missed stations
    /// were sent again.
    program: Program,
    dwell_s: f64,
    again: bool,
    /// The program ended with stations missed: waiting for the operator to finish with the
    /// stations taken or to stop (a map from fewer stations than planned is not put in use
    /// unasked).
    incomplete: bool,
    cnc_done_at: Option<Instant>,
}

/// How the stations' programs move the carriage.
#[derive(Clone, Debug)]
struct Program {
    axis: String,
    dialect: Dialect,
    feed: f64,
}

/// The service's level stations: at most one at a time, and the last one's outcome.
pub struct FollowerLevel {
    cfg: LevelConfig,
    active: Option<Active>,
    view: Option<LevelView>,
    cnc: CncDriver,
    /// The map fitted with the stations is being stored, or the zero taken again with it.
    storing: bool,
    zeroing: bool,
    /// The reply owed to `follower_level_finish`, sent once the stations are done.
    owed: Option<Reply>,
    tx: mpsc::Sender<Event>,
    rx: mpsc::Receiver<Event>,
}

fn arcsec(rad: f64) -> f64 {
    rad / RAD_PER_ARCSEC
}

/// The vertical's u at the middle of its span (µm).
fn u_mid_um(map: &FollowerMap) -> Option<f64> {
    let vp = &map.vertical_positions_mm;
    let (a, b) = (vp.first()?, vp.last()?);
    Some(crate::util::interpolate(vp, &map.vertical_u_mm, (a + b) / 2.0) * 1e3)
}

impl FollowerLevel {
    pub fn new(cfg: LevelConfig) -> FollowerLevel {
        let (tx, rx) = mpsc::channel(64);
        FollowerLevel {
            cnc: CncDriver::new(cfg.cnc.clone()),
            cfg,
            active: None,
            view: None,
            storing: false,
            zeroing: false,
            owed: None,
            tx,
            rx,
        }
    }

    /// Whether the stations are under way.
    pub fn active(&self) -> bool {
        self.active.is_some()
    }

    /// The stations as the snapshot shows them (none before the first since the start).
    pub fn view(&self) -> Option<LevelView> {
        self.view.clone()
    }

    /// `follower_level_status`.
    pub fn status(&self) -> serde_json::Value {
        match &self.view {
            Some(v) => serde_json::to_value(v).unwrap_or_default(),
            None => serde_json::json!({"state": "idle"}),
        }
    }

    fn instrument(&self) -> (String, String) {
        let sd = arcsec(self.cfg.level_sd_rad);
        match &self.cfg.source {
            LevelSource::Manual => (
                "manual".into(),
                format!("a level read by hand, each reading typed ({sd:.2}″ a reading stated)"),
            ),
            LevelSource::Twin(a) => (
                "twin".into(),
                format!(
                    "the twin's electronic level at {a} (a simulated instrument, {sd:.2}″ a reading stated)"
                ),
            ),
        }
    }

    /// The dwell at each station (s, rounded up to 0.1 s) and what it is made of.
    fn dwell(&self, readings: usize, frames_per_s: f64, ctx: &Ctx) -> (f64, String) {
        let t = ctx.pipeline.tracker.settings();
        let configured = if self.cfg.frame_rate_hz > 0.0 {
            self.cfg.frame_rate_hz
        } else {
            200.0
        };
        let rate = if frames_per_s.is_finite() && frames_per_s >= 10.0 {
            configured.min(frames_per_s)
        } else {
            configured
        };
        let rest = t.rest_time.as_secs_f64();
        let handover = 2.0 * t.average_frames as f64 / rate
            + t.settle.as_secs_f64()
            + 2.0 * self.cfg.sync.as_secs_f64()
            + 0.2;
        let window = (self.cfg.live_window + READING_GAP).as_secs_f64();
        let replies = 0.3;
        let typing = match self.cfg.source {
            LevelSource::Manual => TYPING_S,
            LevelSource::Twin(_) => 0.0,
        };
        let need = rest + handover + readings as f64 * window + replies;
        let dwell = (((need * 1.25 + 0.5) * 10.0).ceil() / 10.0) + typing;
        let text = format!(
            "dwell {dwell:.1} s at each station: rest detection {rest:.2} s + a re-centring handover {handover:.2} s ({} frames a side at {rate:.0} Hz) + {readings} readings of the head's {:.2} s window ({:.2} s) + the level's replies {replies:.1} s, with 25 % and 0.5 s of margin{}",
            t.average_frames,
            self.cfg.live_window.as_secs_f64(),
            readings as f64 * window,
            if typing > 0.0 {
                format!(", + {typing:.0} s to read the level and type its reading")
            } else {
                String::new()
            }
        );
        (dwell, text)
    }

    fn start(&mut self, req: LevelRequest, who: &str, reply: Reply, ctx: &mut Ctx) {
        match self.prepare(req, who, ctx) {
            Ok((file, text, dialect, axis, answer)) => {
                self.cnc
                    .deliver(file, text, dialect, &axis, Some((reply, answer)))
            }
            Err(e) => reply.send(Err(e)),
        }
    }

    /// Everything a start checks and sets up: the program's file and text, its dialect and
    /// axis, and the answer.
    fn prepare(
        &mut self,
        req: LevelRequest,
        who: &str,
        ctx: &mut Ctx,
    ) -> Result<(PathBuf, String, Dialect, String, serde_json::Value), String> {
        if self.active.is_some() || self.storing || self.zeroing {
            return Err("the follower's level stations are under way: stop them (follower_level_stop) or let them finish first".into());
        }
        let rec = ctx
            .cached
            .follower_map
            .clone()
            .ok_or("map the follower first: no follower map is in use, and the level's stations are fitted with the self-calibration's steps (axiscomp follower map, or m on the console's Align screen)")?;
        // A check re-uses the map as it is: its steps are not fitted again.
        let steps = if req.check_map {
            None
        } else {
            rec.steps.clone()
        };
        if req.check_map && rec.map.vertical_positions_mm.len() < 2 {
            return Err(format!(
                "the map in use (map {}, {}) has no vertical map to check on this set-up: map the follower (axiscomp follower map, or m on the console's Align screen)",
                rec.id, rec.name
            ));
        }
        if steps.is_none() && !req.check_map {
            return Err(format!(
                "map the follower first: the map in use (map {}, {}) was stored without its self-calibration's steps ({}), so a level cannot be fitted with them; run the self-calibration (axiscomp follower map, or m on the console's Align screen), then the level's stations",
                rec.id,
                rec.name,
                if rec.map.self_calibration.is_some() {
                    "stored before the steps were kept with the map"
                } else {
                    "a certificate alone has none"
                }
            ));
        }
        let applied = ctx
            .pipeline
            .tracker
            .map()
            .cloned()
            .unwrap_or_else(|| Arc::new(rec.map.clone()));
        let live = ctx.pipeline.measure.live().filter(|_| ctx.pipeline.tracker.stitch().valid).ok_or(
            "the head reads no live roll: the beam must be on all three PSDs and the stitch referenced (take the zero) before the level's stations",
        )?;
        let encoder = ctx
            .pipeline
            .follower_state()
            .map(|f| f.position_mm)
            .ok_or("the follower's position is not known: is its drive up?")?;
        // The carriage's position for an encoder position, as the follower stands now.
        let offset = encoder - live.travel_mm;
        let (lo, hi) = rec.map.span();
        let vp = &rec.map.vertical_positions_mm;
        let (vlo, vhi) = match (vp.first(), vp.last()) {
            (Some(a), Some(b)) => (*a, *b),
            _ => (lo, hi),
        };
        let (from_mm, to_mm) = match (req.from_mm, req.to_mm) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => (
                ((vlo - offset) * 10.0).ceil() / 10.0,
                ((vhi - offset) * 10.0).floor() / 10.0,
            ),
            _ => return Err("give both from_mm and to_mm (or neither: the map's span)".into()),
        };
        if !(from_mm.is_finite() && to_mm.is_finite() && to_mm > from_mm) {
            return Err(format!(
                "from_mm {from_mm} and to_mm {to_mm}: give a span with the near end below the far end"
            ));
        }
        if from_mm + offset < vlo - NEAR_MM || to_mm + offset > vhi + NEAR_MM {
            return Err(format!(
                "the stations {from_mm:.1} to {to_mm:.1} mm reach beyond the map's span ({:.1} to {:.1} mm of the carriage, {vlo:.1} to {vhi:.1} mm of the follower's encoder): give a span within it, or map the follower over the span first",
                vlo - offset,
                vhi - offset
            ));
        }
        let station_mm = req.station_mm.unwrap_or(DEFAULT_STATION_MM);
        if !(station_mm.is_finite() && station_mm >= 1.0) {
            return Err(format!(
                "station_mm {station_mm}: give the stations' spacing, 1 mm or more"
            ));
        }
        let readings = req.readings.unwrap_or(DEFAULT_READINGS);
        if !(2..=1000).contains(&readings) {
            return Err(format!("readings {readings}: give 2 to 1000 a station"));
        }
        let feed = req.feed_mm_min.unwrap_or(DEFAULT_FEED_MM_MIN);
        if !(feed.is_finite() && feed > 0.0) {
            return Err(format!("feed_mm_min {feed}: give a positive feed"));
        }
        let axis = req.axis.clone().unwrap_or_else(|| "X".into());
        let dialect = match &req.dialect {
            Some(d) => Dialect::parse(d).ok_or_else(|| {
                format!("dialect \"{d}\": use iso, siemens, heidenhain or linuxcnc")
            })?,
            None => self.cfg.dialect,
        };
        if self.cnc.twin().is_some() && !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc) {
            return Err("the twin's CNC runs iso or linuxcnc programs".into());
        }
        let stations = crate::follower::level::stations((from_mm, to_mm), station_mm);
        let needed = crate::follower::ReuseSettings::default().stations_needed();
        if req.check_map && stations.len() < needed {
            return Err(format!(
                "station_mm {station_mm}: {} stations from {from_mm:.1} to {to_mm:.1} mm, and checking the map in use on this set-up needs {needed} at least (a smooth bend fitted, and stations to spare to judge it by); give a smaller spacing",
                stations.len()
            ));
        }
        let (dwell, dwell_text) = self.dwell(readings, ctx.frames_per_s, ctx);
        let started_us = crate::store::now_us();
        let started = crate::util::time::rfc3339(started_us.div_euclid(1_000_000));
        let title = format!(
            "axiscomp follower level stations{} {axis} {from_mm:.3} to {to_mm:.3} mm, {} stations, {readings} readings each, dwell {dwell:.1} s",
            if req.check_map {
                " (check of the map in use)"
            } else {
                ""
            },
            stations.len()
        );
        let n = stations.len();
        let stops: Vec<(f64, Option<String>)> = stations
            .iter()
            .enumerate()
            .map(|(k, &x)| (x, Some(format!("station {} of {n}", k + 1))))
            .collect();
        let prog = Program {
            axis: axis.clone(),
            dialect,
            feed,
        };
        let prog_axis = axis.clone();
        let (file, cnc, text) =
            self.program(&prog, &stops, dwell, &title, &format!("level-{started_us}"))?;
        let (level, instrument) = self.instrument();
        let view = LevelView {
            state: "stations".into(),
            check_map: req.check_map,
            level,
            instrument,
            axis,
            from_mm,
            to_mm,
            station_mm,
            readings,
            stations: stations
                .iter()
                .map(|&x| StationView {
                    at_mm: x,
                    state: "waiting".into(),
                    ..StationView::default()
                })
                .collect(),
            dwell_s: dwell,
            dwell: dwell_text,
            program: file.display().to_string(),
            cnc: cnc.clone(),
            map_from: rec.id,
            map_from_name: rec.name.clone(),
            started,
            started_by: who.to_string(),
            u_mid_steps_um: match &steps {
                Some(steps) => {
                    crate::follower::build(&steps.steps, rec.certificate.as_ref(), &steps.settings)
                        .ok()
                        .as_ref()
                        .and_then(u_mid_um)
                }
                None => u_mid_um(&rec.map),
            },
            ..LevelView::default()
        };
        tracing::info!(
            from_mm,
            to_mm,
            stations = n,
            dwell_s = dwell,
            check = req.check_map,
            program = %file.display(),
            "follower level stations started by {who}"
        );
        ctx.pipeline.alarms.clear("level-failed");
        self.view = Some(view);
        self.active = Some(Active {
            source: rec,
            steps,
            applied,
            taken: vec![None; n],
            stations,
            readings,
            reading: None,
            visit: 0,
            started: crate::util::clock::now(),
            grace: Duration::from_secs_f64(dwell) + Duration::from_secs(2),
            program: prog,
            dwell_s: dwell,
            again: false,
            incomplete: false,
            cnc_done_at: None,
        });
        self.refresh(crate::util::clock::now());
        Ok((file, text, dialect, prog_axis, self.status()))
    }

    /// The stations' part program: its file in the state directory (`name`), where it goes
    /// (in words) and its text.
    fn program(
        &self,
        p: &Program,
        stops: &[(f64, Option<String>)],
        dwell: f64,
        title: &str,
        name: &str,
    ) -> Result<(PathBuf, String, String), String> {
        let text =
            crate::run::program::generate_stops(&p.axis, stops, p.feed, dwell, title, p.dialect);
        let dir = self.cfg.state_dir.join("follower-maps");
        let (file, cnc) = self.cnc.program_file(&dir, name, p.dialect)?;
        let cnc = match self.cnc.twin() {
            Some(_) => cnc,
            None => "load the program on the CNC and start it (or bring the carriage to each station and let it rest)".into(),
        };
        Ok((file, cnc, text))
    }

    /// The twin's program ended with stations missed (a loaded host, a reading the carriage
    /// left): once, the missed ones again with twice the dwell. `false`: not sent (already
    /// done once, or the program could not be written).
    fn again(&mut self) -> bool {
        let Some(a) = self.active.as_ref().filter(|a| !a.again) else {
            return false;
        };
        let missed: Vec<(f64, Option<String>)> = a
            .stations
            .iter()
            .enumerate()
            .filter(|(k, _)| a.taken[*k].is_none())
            .map(|(k, &x)| (x, Some(format!("station {} again", k + 1))))
            .collect();
        let dwell = a.dwell_s * 2.0;
        let title = format!(
            "axiscomp follower level stations {}: {} missed stations again, dwell {dwell:.1} s",
            a.program.axis,
            missed.len()
        );
        let name = format!("level-again-{}", crate::store::now_us());
        let r = self.program(&a.program.clone(), &missed, dwell, &title, &name);
        let Some(a) = self.active.as_mut() else {
            return false;
        };
        a.again = true;
        let Ok((file, cnc, text)) = r else {
            return false;
        };
        let (dialect, axis) = (a.program.dialect, a.program.axis.clone());
        self.cnc.deliver(file.clone(), text, dialect, &axis, None);
        let Some(a) = self.active.as_mut() else {
            return false;
        };
        let at: Vec<String> = missed.iter().map(|(x, _)| format!("{x:.1}")).collect();
        tracing::warn!(
            "follower level: the stations at {} mm were missed; sent again with a dwell of {dwell:.1} s",
            at.join(", ")
        );
        a.dwell_s = dwell;
        a.grace = Duration::from_secs_f64(dwell) + Duration::from_secs(2);
        a.cnc_done_at = None;
        if let Some(v) = self.view.as_mut() {
            v.dwell_s = dwell;
            v.program = file.display().to_string();
            v.cnc = cnc;
            v.error = Some(format!(
                "the stations at {} mm were missed (the carriage did not rest there long enough): sent again with a dwell of {dwell:.1} s",
                at.join(", ")
            ));
        }
        true
    }

    /// `follower_level_reading`: the operator's reading at the station being read or waiting
    /// for it.
    fn typed(&mut self, v: &serde_json::Value, who: &str) -> Result<serde_json::Value, String> {
        let x = typed_reading(v)?;
        let Some(a) = self.active.as_mut() else {
            return Err(
                "no level stations are under way: start them first (follower_level_start)".into(),
            );
        };
        if matches!(self.cfg.source, LevelSource::Twin(_)) {
            return Err("the level is the twin's ([follower] level = \"twin\"): its readings are taken by the service".into());
        }
        let Some(r) = a.reading.as_mut() else {
            let next = a
                .taken
                .iter()
                .position(Option::is_none)
                .map(|k| format!(" (the next is at {:.1} mm)", a.stations[k]))
                .unwrap_or_default();
            return Err(format!(
                "no station is being read: bring the carriage to rest at a station{next}, then type the level's reading there"
            ));
        };
        r.typed.push(x * RAD_PER_ARCSEC);
        tracing::info!(
            station = r.station + 1,
            arcsec = x,
            "the level's reading typed by {who}"
        );
        let station = r.station;
        self.refresh(crate::util::clock::now());
        Ok(serde_json::json!({"station": station + 1, "arcsec": x, "view": self.status()}))
    }

    /// Each tick: the twin's CNC and level heard, the station at rest read, the end judged.
    fn advance(&mut self, ctx: &mut Ctx) {
        let now = ctx.now;
        while let Ok(e) = self.rx.try_recv() {
            if let Some(why) = self.handle_event(e, ctx) {
                self.fail(why, ctx);
                return;
            }
        }
        if self.zeroing && !ctx.pipeline.zero_pending() {
            self.zeroing = false;
            if let Some(v) = self.view.as_mut() {
                v.state = "done".into();
            }
            self.answer_owed();
        }
        for news in self.cnc.poll(now) {
            match news {
                CncNews::Refused(e) => {
                    return self.fail(
                        format!(
                            "the twin's CNC did not take the program ({e}): no station was read, the map in use is unchanged"
                        ),
                        ctx,
                    );
                }
                CncNews::Taken => {}
                CncNews::Ended => {
                    if let Some(a) = self.active.as_mut()
                        && a.cnc_done_at.is_none()
                    {
                        a.cnc_done_at = Some(now);
                    }
                }
            }
        }
        if self.active.is_none() {
            return;
        }
        if let Err(why) = self.read(now, ctx.pipeline)
            && let Some(v) = self.view.as_mut()
        {
            v.error = Some(why);
        }
        self.complete();
        self.refresh(now);
        let Some(a) = self.active.as_ref() else {
            return;
        };
        let all = a.taken.iter().all(Option::is_some);
        let ended = a
            .cnc_done_at
            .is_some_and(|t| now.saturating_duration_since(t) >= a.grace)
            && a.reading.is_none();
        if all {
            self.finish_with(now, "every station taken", None, ctx);
        } else if ended && !a.incomplete && !self.again() {
            self.incomplete();
        }
    }

    /// The station at rest: start it, take the head's next reading, ask the twin's level.
    fn read(&mut self, now: Instant, p: &mut Pipeline) -> Result<(), String> {
        let Some(a) = self.active.as_mut() else {
            return Ok(());
        };
        let still = p.tracker.stitch().valid && !p.tracker.handing_over() && p.tracker.at_rest(now);
        let live = p.measure.live().filter(|l| l.frames >= 10);
        let near = |k: usize| live.is_some_and(|l| (l.travel_mm - a.stations[k]).abs() <= NEAR_MM);
        let window = self.cfg.live_window + READING_GAP;
        match a.reading.as_mut() {
            // Its head's readings complete: it waits for the level, wherever the carriage is.
            Some(r) if r.fixed.is_some() => return Ok(()),
            Some(r) if !(still && near(r.station)) => {
                // The carriage left (or a handover began) before the readings were done: the
                // station is read again when it rests there.
                a.visit += 1;
                a.reading = None;
                return Ok(());
            }
            Some(_) => {}
            None => {
                if !still {
                    return Ok(());
                }
                let Some(k) = (0..a.stations.len()).find(|&k| a.taken[k].is_none() && near(k))
                else {
                    return Ok(());
                };
                a.visit += 1;
                a.reading = Some(Reading {
                    station: k,
                    visit: a.visit,
                    head: Vec::new(),
                    level: Vec::new(),
                    typed: Vec::new(),
                    next_at: now + window,
                    fixed: None,
                });
                return Ok(());
            }
        }
        let (Some(r), Some(l)) = (a.reading.as_mut(), live) else {
            return Ok(());
        };
        if now < r.next_at {
            return Ok(());
        }
        let k = r.head.len();
        r.head.push(l.errors.ey);
        r.level.push(None);
        // On the grid while the ticks keep up; never before a whole fresh window.
        r.next_at = (r.next_at + window).max(now + self.cfg.live_window);
        if let LevelSource::Twin(addr) = self.cfg.source {
            let (tx, visit) = (self.tx.clone(), r.visit);
            tokio::spawn(async move {
                let roll =
                    crate::service::cnc::twin_request(addr, serde_json::json!({"cmd": "level"}))
                        .await
                        .and_then(|v| {
                            v["level"]["roll_arcsec"]
                                .as_f64()
                                .map(|x| x * RAD_PER_ARCSEC)
                                .ok_or_else(|| format!("the twin's level answered {v}"))
                        });
                let _ = tx.send(Event::Level { visit, k, roll }).await;
            });
        }
        if r.head.len() < a.readings {
            return Ok(());
        }
        // The head's readings are complete: where the follower stands, the map there, g.
        let fail = |why: String| {
            format!(
                "station at {:.1} mm: {why}; it is read again when the carriage rests there",
                a.stations[r.station]
            )
        };
        let encoder = p
            .follower_state()
            .map(|f| f.position_mm)
            .ok_or_else(|| fail("the follower's position is not known".into()))?;
        let frame = p
            .last_frame
            .and_then(|f| f.readings())
            .ok_or_else(|| fail("no frame with all three spots".into()))?;
        let stitch = p.tracker.stitch();
        let g = crate::follower::level::roll_per_y2(
            p.measure.decoupler(),
            &frame,
            l.travel_mm,
            stitch.follower_mm,
            stitch.vertical_mm,
        )
        .map_err(|e| fail(e.to_string()))?;
        let m = a
            .applied
            .correction(encoder, crate::follower::Direction::Up)[1];
        r.fixed = Some((encoder, m, g));
        Ok(())
    }

    /// A station whose head and level are both read: taken.
    fn complete(&mut self) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some(r) = a.reading.as_ref() else {
            return;
        };
        let Some((encoder, m, g)) = r.fixed else {
            return;
        };
        let level: Vec<f64> = match self.cfg.source {
            LevelSource::Twin(_) => match r.level.iter().copied().collect::<Option<Vec<f64>>>() {
                Some(l) => l,
                None => return,
            },
            LevelSource::Manual if r.typed.is_empty() => return,
            LevelSource::Manual => r.typed.clone(),
        };
        match crate::follower::level::excess(&r.head, &level, self.cfg.level_sd_rad) {
            Ok((e, var)) => {
                let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
                let k = r.station;
                a.taken[k] = Some(Taken {
                    station: crate::follower::level::station(encoder, m, e, var, g),
                    head: mean(&r.head),
                    level: mean(&level),
                });
                tracing::info!(
                    station = k + 1,
                    at_mm = a.stations[k],
                    excess_arcsec = arcsec(e),
                    "level station taken"
                );
                a.reading = None;
            }
            Err(e) => {
                if let Some(v) = self.view.as_mut() {
                    v.error = Some(e.to_string());
                }
                a.reading = None;
            }
        }
    }

    fn refresh(&mut self, now: Instant) {
        let (Some(a), Some(v)) = (self.active.as_ref(), self.view.as_mut()) else {
            return;
        };
        v.elapsed_s = now.saturating_duration_since(a.started).as_secs_f64();
        v.taken = a.taken.iter().flatten().count();
        v.current = a.reading.as_ref().map(|r| r.station);
        let manual = matches!(self.cfg.source, LevelSource::Manual);
        v.awaiting_reading = a
            .reading
            .as_ref()
            .filter(|r| manual && r.typed.is_empty())
            .map(|r| r.station);
        for (k, s) in v.stations.iter_mut().enumerate() {
            s.readings = 0;
            match (&a.taken[k], a.reading.as_ref().filter(|r| r.station == k)) {
                (Some(t), _) => {
                    s.state = "taken".into();
                    s.readings = a.readings;
                    s.encoder_mm = Some(t.station.position_mm);
                    s.head_arcsec = Some(arcsec(t.head));
                    s.level_arcsec = Some(arcsec(t.level));
                    s.value_um = Some(t.station.value_mm * 1e3);
                    s.u_um = Some(t.station.variance_mm2.max(0.0).sqrt() * 1e3);
                }
                (None, Some(r)) => {
                    s.readings = r.head.len();
                    s.state = if r.fixed.is_some() {
                        "awaiting the level".into()
                    } else {
                        "reading".into()
                    };
                }
                (None, None) => s.state = "waiting".into(),
            }
        }
        let n = a.stations.len();
        v.prompt = match a.reading.as_ref() {
            Some(r) if manual && r.typed.is_empty() => format!(
                "station {} of {n} at {:.1} mm: read the level and type its reading (arcsec){}",
                r.station + 1,
                a.stations[r.station],
                if r.fixed.is_none() {
                    format!("; the head's readings {} of {}", r.head.len(), a.readings)
                } else {
                    String::new()
                }
            ),
            Some(r) => format!(
                "station {} of {n} at {:.1} mm: reading the head{} ({} of {})",
                r.station + 1,
                a.stations[r.station],
                if manual { "" } else { " and the level" },
                r.head.len(),
                a.readings
            ),
            None => match a.taken.iter().position(Option::is_none) {
                Some(k) if self.cnc.twin().is_some() => format!(
                    "the twin's CNC brings the carriage to the stations (next {:.1} mm)",
                    a.stations[k]
                ),
                Some(k) => format!(
                    "bring the carriage to rest at a station (next {:.1} mm, within {NEAR_MM} mm)",
                    a.stations[k]
                ),
                None => "every station taken".into(),
            },
        };
    }

    /// The outcome of the stations' asynchronous work; a failure to report.
    fn handle_event(&mut self, e: Event, ctx: &mut Ctx) -> Option<String> {
        match e {
            Event::Stored(st) => {
                let Stored {
                    how,
                    missed,
                    record,
                    reply,
                } = *st;
                self.stored(&how, &missed, record, reply, ctx);
                None
            }
            Event::Level { visit, k, roll } => {
                let a = self.active.as_mut()?;
                let r = a.reading.as_mut().filter(|r| r.visit == visit)?;
                match roll {
                    Ok(x) => {
                        if let Some(slot) = r.level.get_mut(k) {
                            *slot = Some(x);
                        }
                        None
                    }
                    Err(e) => Some(format!(
                        "the twin's level did not answer ({e}): nothing was stored, the map in use is unchanged"
                    )),
                }
            }
        }
    }

    /// End on a failure: nothing stored.
    fn fail(&mut self, msg: String, ctx: &mut Ctx) {
        if self.active.take().is_none() {
            return;
        }
        self.cnc.stop();
        self.cnc.forget();
        ctx.pipeline.alarms.raise("level-failed", msg.clone());
        if let Some(v) = self.view.as_mut() {
            v.state = "failed".into();
            v.error = Some(msg);
        }
    }

    /// `follower_level_stop`: nothing stored; the twin's program stopped.
    fn stop(&mut self, who: &str) -> Result<serde_json::Value, String> {
        let Some(a) = self.active.take() else {
            return Err("no level stations are under way".into());
        };
        self.cnc.stop();
        self.cnc.forget();
        if let Some(v) = self.view.as_mut() {
            v.state = "stopped".into();
            v.current = None;
            v.awaiting_reading = None;
            v.prompt = String::new();
            v.error = Some(format!(
                "stopped by {who} after {} of {} stations: nothing was stored and the map in use is unchanged",
                a.taken.iter().flatten().count(),
                a.stations.len()
            ));
        }
        tracing::info!("follower level stations stopped by {who}");
        Ok(self.status())
    }

    /// The program ended with stations missed: say which, and wait for the operator's
    /// finish (the stations taken) or stop (nothing stored).
    fn incomplete(&mut self) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        a.incomplete = true;
        let missed: Vec<String> = a
            .stations
            .iter()
            .zip(&a.taken)
            .filter(|(_, t)| t.is_none())
            .map(|(x, _)| format!("{x:.1}"))
            .collect();
        let taken = a.taken.iter().flatten().count();
        let msg = format!(
            "the program ended with the stations at {} mm not taken (the carriage did not rest there long enough): fit the map with the {taken} taken (axiscomp follower level --finish) or stop (axiscomp follower level --stop, nothing stored); the map in use is unchanged until then",
            missed.join(", ")
        );
        tracing::warn!("follower level: {msg}");
        if let Some(v) = self.view.as_mut() {
            v.state = "incomplete".into();
            v.current = None;
            v.error = Some(msg);
        }
    }

    /// `follower_level_finish`: fit the map now with the stations taken.
    fn finish(&mut self, who: &str, reply: Reply, ctx: &mut Ctx) {
        if self.active.is_none() {
            return reply.send(Err("no level stations are under way".into()));
        }
        self.cnc.stop();
        self.cnc.forget();
        self.finish_with(ctx.now, &format!("finished by {who}"), Some(reply), ctx);
    }

    /// Fit the map with the stations taken and store it (off the loop); it is put in use when
    /// the store has it (`stored`).
    fn finish_with(&mut self, now: Instant, how: &str, reply: Option<Reply>, ctx: &mut Ctx) {
        self.refresh(now);
        let Some(a) = self.active.take() else {
            if let Some(r) = reply {
                r.send(Err("no level stations are under way".into()));
            }
            return;
        };
        if let Some(v) = self.view.as_mut() {
            v.current = None;
            v.awaiting_reading = None;
            v.prompt = String::new();
        }
        let missed: Vec<String> = a
            .stations
            .iter()
            .zip(&a.taken)
            .filter(|(_, t)| t.is_none())
            .map(|(x, _)| format!("{x:.1}"))
            .collect();
        let (stored, name) = match self.fit(&a) {
            Ok(f) => f,
            Err(e) => return self.stored(how, &missed, Err(e), reply, ctx),
        };
        let (tx, how) = (self.tx.clone(), how.to_string());
        let job = ctx.store.try_call(move |s| {
            let id = s.insert_stored_follower_map(&stored, &name, true)?;
            s.follower_map(id)
        });
        match job {
            Ok(done) => {
                self.storing = true;
                tokio::spawn(async move {
                    let record = match done.await {
                        Ok(Ok(r)) => Ok(r),
                        Ok(Err(e)) => Err(format!("the map was not stored: {e}")),
                        Err(e) => Err(format!("the map was not stored: {e}")),
                    };
                    let _ = tx
                        .send(Event::Stored(Box::new(Stored {
                            how,
                            missed,
                            record,
                            reply,
                        })))
                        .await;
                });
            }
            Err(e) => self.stored(
                &how,
                &missed,
                Err(format!("the map was not stored: {e}")),
                reply,
                ctx,
            ),
        }
    }

    /// The map stored: in use in the tracker, the cache and the snapshot, the zero taken
    /// again; or why there is none.
    fn stored(
        &mut self,
        how: &str,
        missed: &[String],
        record: Result<FollowerMapRecord, String>,
        reply: Option<Reply>,
        ctx: &mut Ctx,
    ) {
        self.storing = false;
        if let Some(v) = self.view.as_mut() {
            match record {
                Ok(rec) => {
                    ctx.pipeline
                        .tracker
                        .set_map(Some(Arc::new(rec.map.clone())));
                    *ctx.shown = Some(crate::service::follower::view(&rec));
                    // The map in tracking changed: the zero again, here. The stations are done
                    // once it is taken.
                    let zero = ctx.pipeline.begin_zero(ctx.now, ctx.zero_window());
                    self.zeroing = zero;
                    v.state = if zero { "finishing" } else { "done" }.into();
                    v.map_id = Some(rec.id);
                    v.summary = rec.map.summary();
                    v.u_mid_level_um = u_mid_um(&rec.map);
                    let mut notes = Vec::new();
                    if !missed.is_empty() {
                        notes.push(format!(
                            "the stations at {} mm were not taken (the carriage did not rest there long enough)",
                            missed.join(", ")
                        ));
                    }
                    if !zero {
                        notes.push("the zero could not be taken again (the follower's position is not known): take it before measuring".to_string());
                    }
                    v.error = (!notes.is_empty()).then(|| notes.join("; "));
                    tracing::info!(
                        id = rec.id,
                        "follower level stations {how}: map stored and in use, the zero taken again"
                    );
                    ctx.cached.follower_map = Some(rec);
                }
                Err(e) => {
                    let msg =
                        format!("{how}, but no map was fitted: {e}; the map in use is unchanged");
                    ctx.pipeline.alarms.raise("level-failed", msg.clone());
                    v.state = "failed".into();
                    v.error = Some(msg);
                }
            }
        }
        self.owed = reply;
        self.answer_owed();
    }

    /// The reply owed to `follower_level_finish`, once the stations are done (or failed).
    fn answer_owed(&mut self) {
        if self.storing || self.zeroing {
            return;
        }
        if let Some(r) = self.owed.take() {
            let v = self.status();
            r.send(match v["state"].as_str() {
                Some("failed") => Err(v["error"].as_str().unwrap_or("failed").to_string()),
                _ => Ok(v),
            });
        }
    }

    /// The map fitted with the stations, as it is stored (with the same certificate and
    /// steps), and its name.
    fn fit(&self, a: &Active) -> Result<(StoredMap, String), String> {
        let mut stations: Vec<LevelStation> = a.taken.iter().flatten().map(|t| t.station).collect();
        if stations.len() < 2 {
            return Err(format!(
                "{} of {} stations were taken: the fit needs two at least",
                stations.len(),
                a.stations.len()
            ));
        }
        stations.sort_by(|x, y| x.position_mm.total_cmp(&y.position_mm));
        let n = stations.len();
        let (_, instrument) = self.instrument();
        let reference = VerticalReference {
            source: format!(
                "{instrument}; {} readings of the head at each of {n} stations {:.1} to {:.1} mm",
                a.readings,
                a.stations.first().copied().unwrap_or(0.0),
                a.stations.last().copied().unwrap_or(0.0)
            ),
            stations,
        };
        let base = a
            .source
            .name
            .split(" + level at ")
            .next()
            .and_then(|b| b.split(" + checked on a set-up at ").next())
            .unwrap_or(&a.source.name);
        let Some(s) = &a.steps else {
            // A check of the map in use on this set-up: re-used with the set-up's bend, or
            // refused with the span where the rail changed.
            let (map, check) = crate::follower::reuse::reuse(
                &a.source.map,
                &reference,
                &crate::follower::ReuseSettings::default(),
            )
            .map_err(|e| format!("the map in use does not fit this set-up: {e}"))?;
            tracing::info!(
                "the map in use checked on this set-up: {}",
                check.describe()
            );
            let stored = StoredMap {
                map,
                certificate: a.source.certificate.clone(),
                steps: a.source.steps.clone(),
            };
            return Ok((
                stored,
                format!("{base} + checked on a set-up at {n} stations"),
            ));
        };
        let cert = a.source.certificate.as_ref();
        let mut map =
            crate::follower::build_referenced(&s.steps, cert, &s.settings, Some(&reference))
                .map_err(|e| e.to_string())?;
        if let (Some(new), Some(old)) = (
            map.self_calibration.as_mut(),
            a.source.map.self_calibration.as_ref(),
        ) {
            new.machine_time_s = old.machine_time_s;
        }
        let name = format!("{base} + level at {n} stations");
        let stored = StoredMap {
            map,
            certificate: a.source.certificate.clone(),
            steps: Some(s.clone()),
        };
        Ok((stored, name))
    }
}

impl Procedure for FollowerLevel {
    fn name(&self) -> &'static str {
        "the follower's level stations"
    }

    fn takes(&self, req: &Request) -> bool {
        matches!(
            req,
            Request::FollowerLevelStart(_)
                | Request::FollowerLevelStatus
                | Request::FollowerLevelReading { .. }
                | Request::FollowerLevelStop
                | Request::FollowerLevelFinish
        )
    }

    fn starts(&self, req: &Request) -> bool {
        matches!(req, Request::FollowerLevelStart(_))
    }

    fn holds_machine(&self) -> bool {
        self.active.is_some() || self.storing || self.zeroing
    }

    fn busy(&self, what: &str) -> String {
        format!(
            "the follower's level stations are under way (the carriage rests at each): stop them with follower_level_stop (axiscomp follower level --stop, or l on the console's Align screen) or let them finish, then {what}"
        )
    }

    fn request(&mut self, req: Request, who: &Who, reply: Reply, ctx: &mut Ctx) {
        match req {
            Request::FollowerLevelStart(r) => self.start(r, &who.user, reply, ctx),
            Request::FollowerLevelStatus => reply.send(Ok(self.status())),
            Request::FollowerLevelReading { arcsec } => reply.send(self.typed(&arcsec, &who.user)),
            Request::FollowerLevelStop => reply.send(self.stop(&who.user)),
            Request::FollowerLevelFinish => self.finish(&who.user, reply, ctx),
            _ => reply.send(Err("internal: not a follower level request".into())),
        }
    }

    fn tick(&mut self, ctx: &mut Ctx) {
        self.advance(ctx);
    }

    fn show(&self, snap: &mut Snapshot, _pipeline: &Pipeline) {
        snap.follower_level = self.view();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_typed_reading_is_a_number_within_the_limit_and_errors_name_the_field() {
        assert_eq!(typed_reading(&serde_json::json!(1.25)), Ok(1.25));
        assert_eq!(typed_reading(&serde_json::json!(-999)), Ok(-999.0));
        let e = typed_reading(&serde_json::Value::Null).unwrap_err();
        assert!(e.contains("\"arcsec\""), "{e}");
        let e = typed_reading(&serde_json::json!("NaN")).unwrap_err();
        assert_eq!(
            e,
            "\"arcsec\" is \"NaN\": give the level's reading as a number of arcsec"
        );
        let e = typed_reading(&serde_json::json!(1000.5)).unwrap_err();
        assert_eq!(
            e,
            "\"arcsec\" is 1000.5: give the level's reading within ±1000″"
        );
    }
}
