//! The follower's stop-and-go self-calibration run by the service (issue 14): the plan of
//! `follower::selfcal` as a part program in the configured dialect (written to the state
//! directory; with `[cnc] mode = "twin"` sent to the twin's CNC), the tracker's handover
//! records collected as the CNC steps the carriage, and at the end the map — built with the
//! certificate given, or the one kept with the map in use — stored with its source and date,
//! put in use in the tracker and the zero taken again.
//!
//! Control requests (operators; `follower_map_status` for viewers): `follower_map_start`
//! (span — the axis' last alignment unless given —, step, passes, frames a side, lead),
//! `follower_map_status`, `follower_map_stop` (nothing is stored), `follower_map_finish`
//! (build now from the steps so far). The mapping ends by itself when the twin's CNC reports
//! its program done, or, with a CNC the service does not drive, once every planned stop was
//! seen. A measurement run and a hexapod run refuse to start under it and it under them.
//!
//! The tracker runs with the procedure's settings from the start (overlap, its averaging, an
//! edge beyond one step) and gets the service's own back when the mapping ends, however it
//! ends. A mapping is not resumed after a service restart: a marker in the state directory
//! says at the next start that it was interrupted (no map stored, the map in use unchanged).

use super::follower::FollowerMapView;
use super::pipeline::Pipeline;
use crate::config::CncMode;
use crate::follower::selfcal::{Collector, Plan, Spec, Taken, Timing, long_degree};
use crate::follower::{Certificate, MapSettings};
use crate::run::Dialect;
use crate::store::Store;
use crate::track::{HandoverRecord, TrackSettings};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// Frames averaged a side by default (the demo's four passes take 1000).
pub const DEFAULT_FRAMES: usize = 1000;
/// The carriage's feed between stops by default (mm/min).
pub const DEFAULT_FEED_MM_MIN: f64 = 2000.0;
/// The acceleration the time estimate assumes for the carriage (mm/s²).
const ACCEL_MM_S2: f64 = 500.0;
/// The marker of a mapping under way, in the state directory.
const MARKER: &str = "follower-mapping.json";

/// `follower_map_start`: every field optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MappingRequest {
    /// The span (mm); default: the axis' last alignment.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to_mm: Option<f64>,
    /// The carriage's step between stops (mm, default 3.75).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_mm: Option<f64>,
    /// Passes over the span, alternately up and down (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub passes: Option<usize>,
    /// Frames averaged each side of a handover (default 1000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<usize>,
    /// The follower's screw lead (mm, default 5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lead_mm: Option<f64>,
    /// A back-and-forth probe every this many stops (default 13; 0: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probe_every: Option<usize>,
    /// The carriage's feed (mm/min, default 2000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_mm_min: Option<f64>,
    /// The machine axis (default X): its alignment, the program's axis letter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<String>,
    /// The program's dialect (default: the configured one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dialect: Option<String>,
    /// A certificate CSV on the service's host (default: the one kept with the map in use).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub certificate: Option<String>,
}

impl MappingRequest {
    /// Every number given within its range (`start` and the plan check how they fit
    /// together), or the first that is not, named.
    pub fn check(&self) -> Result<(), String> {
        use crate::follower::selfcal::{MAX_STEP_MM, MIN_STEP_MM};
        use crate::util::range::{Range, field, int_field};
        check_span_and_feed(self.from_mm, self.to_mm, self.feed_mm_min)?;
        let step = Range::new(MIN_STEP_MM, MAX_STEP_MM, "mm");
        field("step_mm", self.step_mm, step)?;
        field("lead_mm", self.lead_mm, Range::new(0.1, 100.0, "mm"))?;
        int_field("passes", self.passes, 1, 100)?;
        int_field("frames", self.frames, 10, 100_000)?;
        int_field("probe_every", self.probe_every, 0, 1000)
    }
}

/// A request's span and the carriage's feed, when given (`follower_map_start`,
/// `follower_level_start`).
pub(super) fn check_span_and_feed(
    from_mm: Option<f64>,
    to_mm: Option<f64>,
    feed_mm_min: Option<f64>,
) -> Result<(), String> {
    use crate::util::range::{FEED_MM_MIN, POSITION_MM, field};
    field("from_mm", from_mm, POSITION_MM)?;
    field("to_mm", to_mm, POSITION_MM)?;
    field("feed_mm_min", feed_mm_min, FEED_MM_MIN)
}

/// The mapping as `follower_map_status` and the snapshot show it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MappingView {
    /// "approaching" (before the start), "mapping", "finishing", "done", "stopped",
    /// "failed", "interrupted" (by a service restart).
    pub state: String,
    pub axis: String,
    pub from_mm: f64,
    pub to_mm: f64,
    pub step_mm: f64,
    pub passes: usize,
    pub frames: usize,
    pub stops_done: usize,
    pub stops_planned: usize,
    pub steps_kept: usize,
    pub skipped: usize,
    /// Kept steps whose move is not the plan's (another program on the CNC, a stop missed).
    pub out_of_plan: usize,
    /// Machine time since the start, and left by the plan (s).
    pub elapsed_s: f64,
    pub left_s: f64,
    pub dwell_s: f64,
    /// What the dwell is made of, in words.
    pub dwell: String,
    /// The part program's file, and where it went.
    pub program: String,
    pub cnc: String,
    /// The certificate the map is built with, in words.
    pub certificate: String,
    pub started: String,
    pub started_by: String,
    /// Why it stopped, failed or was interrupted.
    pub error: Option<String>,
    /// The map stored, and its summary (`FollowerMap::summary`), once done.
    pub map_id: Option<i64>,
    pub summary: Vec<String>,
}

impl MappingView {
    /// Whether a mapping is under way.
    pub fn active(&self) -> bool {
        matches!(self.state.as_str(), "approaching" | "mapping" | "finishing")
    }
}

/// What the service knows that sets the mapping's timing and where its program goes.
#[derive(Clone, Debug)]
pub struct MappingConfig {
    pub cnc: CncMode,
    pub dialect: Dialect,
    pub state_dir: PathBuf,
    /// PSD frames per second (0: as fast as the module answers, taken as 200).
    pub frame_rate_hz: f64,
    pub follower_velocity_mm_s: f64,
    pub follower_accel_mm_s2: f64,
    pub sync: Duration,
}

/// Where the certificate comes from.
#[derive(Clone, Debug)]
enum CertificateFrom {
    /// Given with the start request (a file on the service's host).
    Given(Certificate),
    /// The one kept with the map in use when the mapping ends.
    InUse,
}

/// Results of the mapping's own asynchronous work (the twin's CNC).
#[derive(Debug)]
enum Event {
    /// The program was (or was not) taken by the twin; its program count after.
    Delivered(Result<u32, String>),
    /// The twin CNC's state.
    Cnc(serde_json::Value),
}

/// A mapping under way.
#[derive(Debug)]
struct Active {
    collector: Collector,
    timing: Timing,
    frames: usize,
    settings: MapSettings,
    certificate: CertificateFrom,
    /// The service's own tracking settings, restored at the end.
    base: TrackSettings,
    twin_programs_at_send: Option<u32>,
    /// When the twin's CNC said its program was done.
    cnc_done_at: Option<Instant>,
    last_cnc_poll: Option<Instant>,
}

/// The service's follower mapping: at most one at a time, and the last one's outcome.
#[derive(Debug)]
pub struct FollowerMapping {
    cfg: MappingConfig,
    active: Option<Active>,
    view: Option<MappingView>,
    tx: mpsc::UnboundedSender<Event>,
    rx: mpsc::UnboundedReceiver<Event>,
    /// Found interrupted at start: tell (an alarm) and stop the twin's program, once.
    interrupted: bool,
}

/// The marker's content: enough to say what was interrupted.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Marker {
    axis: String,
    from_mm: f64,
    to_mm: f64,
    started: String,
    started_by: String,
}

fn twin_addr(cnc: &CncMode) -> Option<SocketAddr> {
    match cnc {
        CncMode::Twin(a) => Some(*a),
        CncMode::Manual => None,
    }
}

/// What else moves the machine now: a measurement run (its id), a hexapod run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Busy {
    pub run: Option<i64>,
    pub hexapod: bool,
}

impl Busy {
    /// Why a mapping cannot start now, naming what runs and how to end it.
    fn refusal(self) -> Option<String> {
        match (self.run, self.hexapod) {
            (Some(id), _) => Some(format!(
                "measurement run {id} is under way (it moves the carriage): abort it with run_abort or let it finish, then map the follower"
            )),
            (None, true) => Some("a hexapod calibration run is under way (it moves the head): stop it with hexapod_stop or let it finish, then map the follower".into()),
            (None, false) => None,
        }
    }
}

/// The collection's context in the core: the tracker and alarms, the store, the map view.
pub(super) struct Ctx<'a> {
    pub pipeline: &'a mut Pipeline,
    pub store: &'a mut Store,
    pub shown: &'a mut Option<FollowerMapView>,
    pub zero_window: Duration,
    /// PSD frames per second over the last second.
    pub frames_per_s: f64,
}

impl FollowerMapping {
    /// Idle; a marker left by a mapping the service did not finish says it was interrupted.
    pub fn new(cfg: MappingConfig) -> FollowerMapping {
        let (tx, rx) = mpsc::unbounded_channel();
        let marker = cfg.state_dir.join(MARKER);
        let mut view = None;
        let mut interrupted = false;
        if let Ok(text) = std::fs::read_to_string(&marker) {
            let m: Option<Marker> = serde_json::from_str(&text).ok();
            let what = m
                .as_ref()
                .map(|m| {
                    format!(
                        "the follower mapping over {} {:.1} to {:.1} mm started {} by {}",
                        m.axis, m.from_mm, m.to_mm, m.started, m.started_by
                    )
                })
                .unwrap_or_else(|| "a follower mapping".into());
            view = Some(MappingView {
                state: "interrupted".into(),
                error: Some(format!(
                    "{what} was interrupted by a service restart: its steps are lost, no map was stored and the map in use is unchanged; stop its part program on the CNC if it still runs, then start the mapping again"
                )),
                ..MappingView::default()
            });
            interrupted = true;
            let _ = std::fs::remove_file(&marker);
        }
        FollowerMapping {
            cfg,
            active: None,
            view,
            tx,
            rx,
            interrupted,
        }
    }

    /// Whether a mapping is under way.
    pub fn active(&self) -> bool {
        self.active.is_some()
    }

    /// Why a run or a hexapod run cannot start now (`None`: it may).
    pub fn refusal(&self, what: &str) -> Option<String> {
        self.active.as_ref().map(|_| {
            format!(
                "the follower mapping is under way (its part program moves the carriage): stop it with follower_map_stop (axiscomp follower map --stop, or m on the console's Align screen) or let it finish, then {what}"
            )
        })
    }

    /// The mapping as the snapshot shows it (none before the first since the start).
    pub fn view(&self) -> Option<MappingView> {
        self.view.clone()
    }

    /// `follower_map_status`.
    pub fn status(&self) -> serde_json::Value {
        match &self.view {
            Some(v) => serde_json::to_value(v).unwrap_or_default(),
            None => serde_json::json!({"state": "idle"}),
        }
    }

    /// The frame rate the dwell assumes (Hz), and why: the configured rate (at 0, as fast as
    /// the module answers: 200 assumed), or the rate the frames come at now when that is
    /// lower (a loaded host, a slow module) — a window of frames takes as long as they take.
    fn frame_rate(&self, now_hz: f64) -> (f64, Option<String>) {
        let configured = if self.cfg.frame_rate_hz > 0.0 {
            self.cfg.frame_rate_hz
        } else {
            200.0
        };
        if now_hz.is_finite() && now_hz >= 10.0 && now_hz < 0.95 * configured {
            let why = format!(
                "frames come at {now_hz:.0} Hz now, not the {configured:.0} Hz configured: the dwell assumes {now_hz:.0} Hz"
            );
            (now_hz, Some(why))
        } else {
            (configured, None)
        }
    }

    fn timing(
        &self,
        rate_hz: f64,
        frames: usize,
        feed_mm_min: f64,
        base: &TrackSettings,
    ) -> Timing {
        Timing {
            frame_rate_hz: rate_hz,
            average_frames: frames,
            rest: base.rest_time,
            settle: base.settle,
            follower_velocity_mm_s: self.cfg.follower_velocity_mm_s,
            follower_accel_mm_s2: self.cfg.follower_accel_mm_s2,
            sync: self.cfg.sync,
            feed_mm_min,
            accel_mm_s2: ACCEL_MM_S2,
        }
    }

    /// `follower_map_start`: refused while a run or a hexapod run is `busy`; else the plan,
    /// its program written (and sent to the twin's CNC), the collection started.
    pub(super) fn start(
        &mut self,
        req: MappingRequest,
        who: &str,
        busy: Busy,
        ctx: Ctx<'_>,
    ) -> Result<serde_json::Value, String> {
        if self.active.is_some() {
            return Err("a follower mapping is under way: stop it (follower_map_stop) or let it finish first".into());
        }
        if let Some(why) = busy.refusal() {
            return Err(why);
        }
        let axis = req.axis.clone().unwrap_or_else(|| "X".into());
        let (from_mm, to_mm) = match (req.from_mm, req.to_mm) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => match ctx.store.latest_alignment(&axis) {
                Ok(Some(a)) => (a.alignment.from_mm, a.alignment.to_mm),
                Ok(None) => {
                    return Err(format!(
                        "axis {axis} has no beam alignment to take the span from: give from_mm and to_mm, or align the head first"
                    ));
                }
                Err(e) => return Err(format!("the alignments cannot be read: {e}")),
            },
            _ => {
                return Err(
                    "give both from_mm and to_mm (or neither: the axis' last alignment)".into(),
                );
            }
        };
        let d = Spec::default();
        let spec = Spec {
            from_mm,
            to_mm,
            step_mm: req.step_mm.unwrap_or(d.step_mm),
            passes: req.passes.unwrap_or(d.passes),
            probe_every: req.probe_every.unwrap_or(d.probe_every),
        };
        let plan = Plan::new(spec).map_err(|e| e.to_string())?;
        let lead_mm = req.lead_mm.unwrap_or(MapSettings::default().lead_mm);
        if !(lead_mm.is_finite() && lead_mm > 0.0) {
            return Err(format!("lead_mm {lead_mm}: give the screw's lead in mm"));
        }
        let cycles = spec.step_mm / lead_mm;
        if (cycles - cycles.round()).abs() < 0.05 {
            return Err(format!(
                "a step of {} mm is a whole number of {lead_mm} mm leads: the screw-periodic term cannot be seen; give another step",
                spec.step_mm
            ));
        }
        let settings = MapSettings {
            lead_mm,
            long_degree: long_degree(to_mm - from_mm),
            ..MapSettings::default()
        };
        plan.check_fit(&settings).map_err(|e| e.to_string())?;
        let frames = req.frames.unwrap_or(DEFAULT_FRAMES);
        if !(10..=100_000).contains(&frames) {
            return Err(format!("frames {frames}: give 10 to 100000 a side"));
        }
        let feed = req.feed_mm_min.unwrap_or(DEFAULT_FEED_MM_MIN);
        if !(feed.is_finite() && feed > 0.0) {
            return Err(format!("feed_mm_min {feed}: give a positive feed"));
        }
        let dialect = match &req.dialect {
            Some(d) => Dialect::parse(d).ok_or_else(|| {
                format!("dialect \"{d}\": use iso, siemens, heidenhain or linuxcnc")
            })?,
            None => self.cfg.dialect,
        };
        let twin = twin_addr(&self.cfg.cnc);
        if twin.is_some() && !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc) {
            return Err("the twin's CNC runs iso or linuxcnc programs".into());
        }
        let (certificate, cert_text) = match &req.certificate {
            Some(path) => {
                let c = super::follower::read_certificate(path)?;
                let t = format!("{} (given)", c.name);
                (CertificateFrom::Given(c), t)
            }
            None => {
                let kept = ctx
                    .store
                    .follower_map_in_use()
                    .ok()
                    .flatten()
                    .and_then(|r| r.certificate.map(|c| c.name));
                let t = match kept {
                    Some(n) => format!("{n} (kept with the map in use)"),
                    None => "none yet: the one kept with the map in use when the mapping ends (without one the long-wavelength positioning is not mapped)".into(),
                };
                (CertificateFrom::InUse, t)
            }
        };
        let base = *ctx.pipeline.tracker.settings();
        let (rate_hz, slow) = self.frame_rate(ctx.frames_per_s);
        let timing = self.timing(rate_hz, frames, feed, &base);
        let dwell = timing.dwell_s(spec.step_mm);
        let now = crate::util::clock::now();
        let started_us = crate::store::now_us();
        let started = crate::util::time::rfc3339(started_us.div_euclid(1_000_000));
        let title = format!(
            "axiscomp follower self-calibration {axis} {:.3} to {:.3} mm, step {} mm, {} passes, {} frames a side, dwell {dwell:.1} s",
            from_mm, to_mm, spec.step_mm, spec.passes, frames
        );
        let text = crate::run::program::generate_stops(
            &axis,
            &program_stops(&plan),
            feed,
            dwell,
            &title,
            dialect,
        );
        let dir = self.cfg.state_dir.join("follower-maps");
        let file = dir.join(format!("mapping-{started_us}.{}", dialect.extension()));
        std::fs::create_dir_all(&dir)
            .and_then(|()| std::fs::write(&file, &text))
            .map_err(|e| format!("cannot write the program {}: {e}", file.display()))?;
        let marker = Marker {
            axis: axis.clone(),
            from_mm,
            to_mm,
            started: started.clone(),
            started_by: who.to_string(),
        };
        if let Err(e) = serde_json::to_string(&marker)
            .map_err(|e| e.to_string())
            .and_then(|t| {
                std::fs::write(self.cfg.state_dir.join(MARKER), t).map_err(|e| e.to_string())
            })
        {
            tracing::warn!(
                "the follower mapping's marker was not written ({e}): a restart will not say it was interrupted"
            );
        }
        let cnc = match twin {
            Some(addr) => {
                let req = serde_json::json!({"cmd": "program", "dialect": if dialect == Dialect::LinuxCnc { "linuxcnc" } else { "iso" }, "axis": axis, "text": text});
                let tx = self.tx.clone();
                tokio::spawn(async move {
                    let r = match super::core::twin_request(addr, req).await {
                        Ok(_) => super::core::twin_request(addr, serde_json::json!({"cmd": "cnc"}))
                            .await
                            .map(|v| v["cnc"]["programs"].as_u64().unwrap_or(0) as u32),
                        Err(e) => Err(e),
                    };
                    let _ = tx.send(Event::Delivered(r));
                });
                format!("sent to the twin's CNC at {addr}")
            }
            None => "load the program on the CNC and start it".to_string(),
        };
        let collector = Collector::new(plan, now);
        // The overlap strategy from now on (the approach's records arm the collection).
        ctx.pipeline
            .tracker
            .set_settings(collector.tracking(&base, frames));
        let progress = collector.progress();
        let view = MappingView {
            state: "approaching".into(),
            axis,
            from_mm,
            to_mm,
            step_mm: spec.step_mm,
            passes: spec.passes,
            frames,
            stops_planned: progress.stops_planned,
            left_s: collector.left_s(&timing),
            dwell_s: dwell,
            dwell: match &slow {
                Some(why) => format!("{} ({why})", timing.dwell_text(spec.step_mm)),
                None => timing.dwell_text(spec.step_mm),
            },
            program: file.display().to_string(),
            cnc: cnc.clone(),
            certificate: cert_text,
            started,
            started_by: who.to_string(),
            ..MappingView::default()
        };
        tracing::info!(
            from_mm,
            to_mm,
            stops = progress.stops_planned,
            dwell_s = dwell,
            program = %file.display(),
            "follower mapping started by {who}"
        );
        ctx.pipeline.alarms.clear("mapping-interrupted");
        ctx.pipeline.alarms.clear("mapping-failed");
        self.view = Some(view.clone());
        self.active = Some(Active {
            collector,
            timing,
            frames,
            settings,
            certificate,
            base,
            twin_programs_at_send: None,
            cnc_done_at: None,
            last_cnc_poll: None,
        });
        Ok(serde_json::to_value(view).unwrap_or_default())
    }

    /// A handover record of the tracker: one stop (or the approach), and the tracker's
    /// settings for what comes next.
    pub(super) fn handle_record(&mut self, r: &HandoverRecord, pipeline: &mut Pipeline) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let taken = a.collector.handle_record(r);
        if taken == Taken::Armed {
            tracing::info!("follower mapping: the carriage is at the start, the stops count");
        }
        pipeline
            .tracker
            .set_settings(a.collector.tracking(&a.base, a.frames));
        self.refresh(crate::util::clock::now());
    }

    fn refresh(&mut self, now: Instant) {
        let (Some(a), Some(v)) = (self.active.as_ref(), self.view.as_mut()) else {
            return;
        };
        let p = a.collector.progress();
        if v.state == "approaching" && p.armed {
            v.state = "mapping".into();
        }
        v.stops_done = p.stops_seen.min(p.stops_planned);
        v.steps_kept = p.steps_kept;
        v.skipped = p.skipped;
        v.out_of_plan = p.out_of_plan;
        v.elapsed_s = a.collector.elapsed(now).as_secs_f64();
        v.left_s = a.collector.left_s(&a.timing);
    }

    /// Each tick: the twin's CNC watched, the end judged, the view refreshed.
    pub(super) fn tick(&mut self, now: Instant, ctx: Ctx<'_>) {
        if std::mem::take(&mut self.interrupted) {
            let text = self
                .view
                .as_ref()
                .and_then(|v| v.error.clone())
                .unwrap_or_default();
            ctx.pipeline.alarms.raise("mapping-interrupted", text);
            if let Some(addr) = twin_addr(&self.cfg.cnc) {
                tokio::spawn(async move {
                    let _ = super::core::twin_request(
                        addr,
                        serde_json::json!({"cmd": "cnc", "stop": true}),
                    )
                    .await;
                });
            }
        }
        while let Ok(e) = self.rx.try_recv() {
            if let Some(why) = self.handle_event(e, now) {
                self.fail(why, ctx);
                return;
            }
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if let Some(addr) = twin_addr(&self.cfg.cnc)
            && a.last_cnc_poll
                .is_none_or(|t| now.saturating_duration_since(t) >= Duration::from_secs(1))
        {
            a.last_cnc_poll = Some(now);
            let tx = self.tx.clone();
            tokio::spawn(async move {
                if let Ok(v) =
                    super::core::twin_request(addr, serde_json::json!({"cmd": "cnc"})).await
                {
                    let _ = tx.send(Event::Cnc(v));
                }
            });
        }
        let grace = Duration::from_secs_f64(a.timing.dwell_s(a.collector.plan().spec().step_mm))
            + Duration::from_secs(2);
        let end = match a.cnc_done_at {
            Some(t) => a.collector.all_seen() || now.saturating_duration_since(t) >= grace,
            None => twin_addr(&self.cfg.cnc).is_none() && a.collector.all_seen(),
        };
        if let Some(v) = self.view.as_mut()
            && a.cnc_done_at.is_some()
        {
            v.state = "finishing".into();
        }
        self.refresh(now);
        if end {
            self.finish_with(now, "the program ended", ctx);
        }
    }

    /// The outcome of the mapping's asynchronous work; a failure to report (the mapping
    /// cannot go on).
    fn handle_event(&mut self, e: Event, now: Instant) -> Option<String> {
        let a = self.active.as_mut()?;
        match e {
            Event::Delivered(Ok(n)) => a.twin_programs_at_send = Some(n),
            Event::Delivered(Err(e)) => {
                return Some(format!(
                    "the twin's CNC did not take the program ({e}): nothing was mapped, the map in use is unchanged"
                ));
            }
            Event::Cnc(v) => {
                let done = v["cnc"]["done"].as_bool().unwrap_or(false);
                let programs = v["cnc"]["programs"].as_u64().unwrap_or(0) as u32;
                if done && a.twin_programs_at_send == Some(programs) && a.cnc_done_at.is_none() {
                    tracing::info!("follower mapping: the twin's CNC ended the program");
                    a.cnc_done_at = Some(now);
                }
            }
        }
        None
    }

    /// End the mapping on a failure: nothing stored, the tracker's settings back.
    fn fail(&mut self, msg: String, ctx: Ctx<'_>) {
        let Some(a) = self.active.take() else {
            return;
        };
        self.remove_marker();
        ctx.pipeline.tracker.set_settings(a.base);
        ctx.pipeline.alarms.raise("mapping-failed", msg.clone());
        if let Some(v) = self.view.as_mut() {
            v.state = "failed".into();
            v.error = Some(msg);
        }
    }

    /// `follower_map_stop`: end the mapping, nothing stored; the twin's program stopped.
    pub(super) fn stop(&mut self, who: &str, ctx: Ctx<'_>) -> Result<serde_json::Value, String> {
        let Some(a) = self.active.take() else {
            return Err("no follower mapping is under way".into());
        };
        ctx.pipeline.tracker.set_settings(a.base);
        self.stop_twin_program();
        self.remove_marker();
        let p = a.collector.progress();
        if let Some(v) = self.view.as_mut() {
            v.state = "stopped".into();
            v.error = Some(format!(
                "stopped by {who} after {} of {} stops: its {} steps were not used, no map was stored and the map in use is unchanged",
                p.stops_seen.min(p.stops_planned),
                p.stops_planned,
                p.steps_kept
            ));
        }
        tracing::info!("follower mapping stopped by {who}");
        Ok(self.status())
    }

    /// `follower_map_finish`: build the map now from the steps so far.
    pub(super) fn finish(&mut self, who: &str, ctx: Ctx<'_>) -> Result<serde_json::Value, String> {
        if self.active.is_none() {
            return Err("no follower mapping is under way".into());
        }
        self.stop_twin_program();
        self.finish_with(
            crate::util::clock::now(),
            &format!("finished by {who}"),
            ctx,
        );
        let v = self.status();
        match v["state"].as_str() {
            Some("failed") => Err(v["error"].as_str().unwrap_or("failed").to_string()),
            _ => Ok(v),
        }
    }

    fn stop_twin_program(&self) {
        if let Some(addr) = twin_addr(&self.cfg.cnc) {
            tokio::spawn(async move {
                if let Err(e) =
                    super::core::twin_request(addr, serde_json::json!({"cmd": "cnc", "stop": true}))
                        .await
                {
                    tracing::warn!("the twin's CNC was not stopped: {e}");
                }
            });
        }
    }

    fn remove_marker(&self) {
        let _ = std::fs::remove_file(self.cfg.state_dir.join(MARKER));
    }

    /// Build, store and apply the map; the tracker gets its settings back either way.
    fn finish_with(&mut self, now: Instant, how: &str, ctx: Ctx<'_>) {
        let Some(a) = self.active.take() else {
            return;
        };
        self.remove_marker();
        ctx.pipeline.tracker.set_settings(a.base);
        let r = store_map(&a, now, ctx.store);
        let Some(v) = self.view.as_mut() else {
            return;
        };
        v.elapsed_s = a.collector.elapsed(now).as_secs_f64();
        v.left_s = 0.0;
        match r {
            Ok(rec) => {
                ctx.pipeline
                    .tracker
                    .set_map(Some(Arc::new(rec.map.clone())));
                *ctx.shown = Some(super::follower::view(&rec));
                // The stitch has moved on by the follower's steps: the zero again, here.
                let zero = ctx.pipeline.begin_zero(now, ctx.zero_window);
                v.state = "done".into();
                v.map_id = Some(rec.id);
                v.summary = rec.map.summary();
                v.error = (!zero).then(|| {
                    "the zero could not be taken again (the follower's position is not known): take it before measuring".to_string()
                });
                tracing::info!(
                    id = rec.id,
                    "follower mapping {how}: map stored and in use, the zero taken again"
                );
            }
            Err(e) => {
                let msg = format!("{how}, but no map was built: {e}; the map in use is unchanged");
                ctx.pipeline.alarms.raise("mapping-failed", msg.clone());
                v.state = "failed".into();
                v.error = Some(msg);
            }
        }
    }
}

/// The program's stops, the lead-in, the start and each pass named.
fn program_stops(plan: &Plan) -> Vec<(f64, Option<String>)> {
    let [lead, start] = plan.approach();
    let mut out = vec![
        (
            lead,
            Some("lead-in: the carriage comes to the start from above".to_string()),
        ),
        (
            start,
            Some("the start: the stops count from here".to_string()),
        ),
    ];
    let per_pass = plan.stops_per_pass().max(1);
    for (i, &x) in plan.stops().iter().enumerate() {
        let comment = (i % per_pass == 0).then(|| {
            let pass = i / per_pass + 1;
            format!(
                "pass {pass} ({})",
                if pass % 2 == 1 { "up" } else { "down" }
            )
        });
        out.push((x, comment));
    }
    out
}

/// The map from the collected steps and the certificate, stored and put in use.
fn store_map(
    a: &Active,
    now: Instant,
    store: &mut Store,
) -> Result<crate::store::FollowerMapRecord, String> {
    let certificate = match &a.certificate {
        CertificateFrom::Given(c) => Some(c.clone()),
        CertificateFrom::InUse => store
            .follower_map_in_use()
            .map_err(|e| format!("the map in use cannot be read for its certificate: {e}"))?
            .and_then(|r| r.certificate),
    };
    let map = a
        .collector
        .build(certificate.as_ref(), &a.settings, now)
        .map_err(|e| e.to_string())?;
    let s = a.collector.plan().spec();
    let name = format!(
        "self-calibration {:.1} to {:.1} mm, {} passes{}",
        s.from_mm,
        s.to_mm,
        s.passes,
        certificate
            .as_ref()
            .map(|c| format!(" + {}", c.name))
            .unwrap_or_default()
    );
    // The steps are kept with the map: a level's stations fit them again later.
    let stored = crate::follower::StoredMap {
        map,
        certificate,
        steps: Some(crate::follower::StoredSteps {
            settings: a.settings,
            steps: a.collector.steps().to_vec(),
        }),
    };
    let id = store
        .insert_stored_follower_map(&stored, &name, true)
        .map_err(|e| format!("the map was not stored: {e}"))?;
    store.follower_map(id).map_err(|e| e.to_string())
}
