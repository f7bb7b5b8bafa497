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

use super::{Ctx, Procedure, Reply, Who};
use crate::config::CncMode;
use crate::follower::selfcal::{Collector, Plan, Spec, Taken, Timing, long_degree};
use crate::follower::{Certificate, MapSettings};
use crate::run::Dialect;
use crate::service::api::{MappingRequest, MappingView, Request, Snapshot};
use crate::service::cnc::{CncDriver, CncNews};
use crate::service::pipeline::{Output, Pipeline};
use crate::store::FollowerMapRecord;
use crate::track::{HandoverRecord, TrackSettings};
use serde::{Deserialize, Serialize};
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

/// The map stored (or not): how the mapping ended, and the replies owed.
struct Stored {
    how: String,
    elapsed_s: f64,
    record: Result<FollowerMapRecord, String>,
    reply: Option<Reply>,
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
    /// When the twin's CNC said its program was done.
    cnc_done_at: Option<Instant>,
}

/// The service's follower mapping: at most one at a time, and the last one's outcome.
pub struct FollowerMapping {
    cfg: MappingConfig,
    active: Option<Active>,
    view: Option<MappingView>,
    cnc: CncDriver,
    /// The map is being stored, or the zero taken again with it: the mapping still holds
    /// the machine (and is "finishing").
    storing: bool,
    zeroing: bool,
    /// The reply owed to `follower_map_finish`, sent once the mapping is done.
    owed: Option<Reply>,
    tx: mpsc::Sender<Stored>,
    rx: mpsc::Receiver<Stored>,
    /// Found interrupted at start: tell (an alarm) and stop the twin's program, once.
    interrupted: bool,
    /// The last start refused, and when (µs since the epoch): the status says it (a refused
    /// start left it saying only that no mapping ran since the service started).
    refused: Option<(String, i64)>,
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

impl FollowerMapping {
    /// Idle; a marker left by a mapping the service did not finish says it was interrupted.
    pub fn new(cfg: MappingConfig) -> FollowerMapping {
        let (tx, rx) = mpsc::channel(4);
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
            cnc: CncDriver::new(cfg.cnc.clone()),
            cfg,
            active: None,
            view,
            storing: false,
            zeroing: false,
            owed: None,
            tx,
            rx,
            interrupted,
            refused: None,
        }
    }

    /// Whether a mapping is under way.
    pub fn active(&self) -> bool {
        self.active.is_some()
    }

    /// The mapping as the snapshot shows it (none before the first since the start).
    pub fn view(&self) -> Option<MappingView> {
        self.view.clone()
    }

    /// `follower_map_status`.
    pub fn status(&self) -> serde_json::Value {
        let mut v = match &self.view {
            Some(v) => serde_json::to_value(v).unwrap_or_default(),
            None => serde_json::json!({"state": "idle"}),
        };
        if let (Some((reason, unix_us)), Some(o)) = (&self.refused, v.as_object_mut()) {
            o.insert(
                "last_refused".into(),
                serde_json::json!({"reason": reason, "unix_us": unix_us}),
            );
        }
        v
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

    /// `follower_map_start`: the plan, its program written (and sent to the twin's CNC),
    /// the collection started. (The core refuses it while another procedure holds the
    /// machine.)
    fn start(&mut self, req: MappingRequest, who: &str, reply: Reply, ctx: &mut Ctx) {
        let r = self.prepare(req, who, ctx);
        match r {
            Ok((file, text, dialect, axis, view)) => {
                self.cnc
                    .deliver(file, text, dialect, &axis, Some((reply, view)))
            }
            Err(e) => {
                self.refused = Some((e.clone(), crate::store::now_us()));
                reply.send(Err(e))
            }
        }
    }

    /// Everything a start checks and sets up: the program's file and text, its dialect and
    /// axis, and the answer.
    fn prepare(
        &mut self,
        req: MappingRequest,
        who: &str,
        ctx: &mut Ctx,
    ) -> Result<(PathBuf, String, Dialect, String, serde_json::Value), String> {
        if self.active.is_some() || self.storing || self.zeroing {
            return Err("a follower mapping is under way: stop it (follower_map_stop) or let it finish first".into());
        }
        let axis = req.axis.clone().unwrap_or_else(|| "X".into());
        let (from_mm, to_mm) = match (req.from_mm, req.to_mm) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => match ctx.cached.alignments.get(&axis) {
                Some(a) => (a.alignment.from_mm, a.alignment.to_mm),
                None => {
                    return Err(format!(
                        "axis {axis} has no beam alignment to take the span from: give from_mm and to_mm, or align the head first"
                    ));
                }
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
        if self.cnc.twin().is_some() && !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc) {
            return Err("the twin's CNC runs iso or linuxcnc programs".into());
        }
        let (certificate, cert_text) = match &req.certificate {
            Some(path) => {
                let c = crate::service::follower::read_certificate(path)?;
                let t = format!("{} (given)", c.name);
                (CertificateFrom::Given(c), t)
            }
            None => {
                let kept = ctx
                    .cached
                    .follower_map
                    .as_ref()
                    .and_then(|r| r.certificate.as_ref().map(|c| c.name.clone()));
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
        let dir = self.cnc_dir();
        let (file, cnc) = self
            .cnc
            .program_file(&dir, &format!("mapping-{started_us}"), dialect)?;
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
        let collector = Collector::new(plan, now);
        // The overlap strategy from now on (the approach's records arm the collection).
        ctx.pipeline
            .tracker
            .set_settings(collector.tracking(&base, frames));
        let progress = collector.progress();
        let view = MappingView {
            state: "approaching".into(),
            axis: axis.clone(),
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
            cnc_done_at: None,
        });
        let answer = serde_json::to_value(view).unwrap_or_default();
        Ok((file, text, dialect, axis, answer))
    }

    /// A handover record of the tracker: one stop (or the approach), and the tracker's
    /// settings for what comes next.
    fn handle_record(&mut self, r: &HandoverRecord, pipeline: &mut Pipeline) {
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
    fn advance(&mut self, ctx: &mut Ctx) {
        let now = ctx.now;
        if std::mem::take(&mut self.interrupted) {
            let text = self
                .view
                .as_ref()
                .and_then(|v| v.error.clone())
                .unwrap_or_default();
            ctx.pipeline.alarms.raise("mapping-interrupted", text);
            self.cnc.stop();
        }
        while let Ok(st) = self.rx.try_recv() {
            self.stored(st, ctx);
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
                            "the twin's CNC did not take the program ({e}): nothing was mapped, the map in use is unchanged"
                        ),
                        ctx,
                    );
                }
                CncNews::Taken => {}
                CncNews::Ended => {
                    if let Some(a) = self.active.as_mut()
                        && a.cnc_done_at.is_none()
                    {
                        tracing::info!("follower mapping: the twin's CNC ended the program");
                        a.cnc_done_at = Some(now);
                    }
                }
            }
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let grace = Duration::from_secs_f64(a.timing.dwell_s(a.collector.plan().spec().step_mm))
            + Duration::from_secs(2);
        let end = match a.cnc_done_at {
            Some(t) => a.collector.all_seen() || now.saturating_duration_since(t) >= grace,
            None => self.cnc.twin().is_none() && a.collector.all_seen(),
        };
        if let Some(v) = self.view.as_mut()
            && a.cnc_done_at.is_some()
        {
            v.state = "finishing".into();
        }
        self.refresh(now);
        if end {
            self.finish_with(now, "the program ended", None, ctx);
        }
    }

    /// End the mapping on a failure: nothing stored, the tracker's settings back.
    fn fail(&mut self, msg: String, ctx: &mut Ctx) {
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
    fn stop(&mut self, who: &str, ctx: &mut Ctx) -> Result<serde_json::Value, String> {
        let Some(a) = self.active.take() else {
            return Err("no follower mapping is under way".into());
        };
        ctx.pipeline.tracker.set_settings(a.base);
        self.cnc.stop();
        self.cnc.forget();
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
    /// `follower_map_finish`: build the map now from the steps so far; the reply once it is
    /// stored.
    fn finish(&mut self, who: &str, reply: Reply, ctx: &mut Ctx) {
        if self.active.is_none() {
            return reply.send(Err("no follower mapping is under way".into()));
        }
        self.cnc.stop();
        self.cnc.forget();
        self.finish_with(ctx.now, &format!("finished by {who}"), Some(reply), ctx);
    }

    /// Where the mapping's programs go.
    fn cnc_dir(&self) -> PathBuf {
        self.cfg.state_dir.join("follower-maps")
    }

    fn remove_marker(&self) {
        let _ = std::fs::remove_file(self.cfg.state_dir.join(MARKER));
    }

    /// Build the map and store it (off the loop); the tracker gets its settings back either
    /// way. The map is put in use when the store has it (`stored`).
    fn finish_with(&mut self, now: Instant, how: &str, reply: Option<Reply>, ctx: &mut Ctx) {
        let Some(a) = self.active.take() else {
            if let Some(r) = reply {
                r.send(Err("no follower mapping is under way".into()));
            }
            return;
        };
        self.remove_marker();
        ctx.pipeline.tracker.set_settings(a.base);
        let elapsed_s = a.collector.elapsed(now).as_secs_f64();
        let built = build_map(&a, now, ctx.cached.follower_map.as_ref());
        let (stored, name) = match built {
            Ok(b) => b,
            Err(e) => {
                return self.stored(
                    Stored {
                        how: how.to_string(),
                        elapsed_s,
                        record: Err(e),
                        reply,
                    },
                    ctx,
                );
            }
        };
        let tx = self.tx.clone();
        let how = how.to_string();
        let job = ctx.store.try_call(move |s| {
            let id = s.insert_stored_follower_map(&stored, &name, true)?;
            s.follower_map(id)
        });
        match job {
            Ok(done) => {
                self.storing = true;
                if let Some(v) = self.view.as_mut() {
                    v.state = "finishing".into();
                }
                tokio::spawn(async move {
                    let record = match done.await {
                        Ok(Ok(r)) => Ok(r),
                        Ok(Err(e)) => Err(format!("the map was not stored: {e}")),
                        Err(e) => Err(format!("the map was not stored: {e}")),
                    };
                    let _ = tx
                        .send(Stored {
                            how,
                            elapsed_s,
                            record,
                            reply,
                        })
                        .await;
                });
            }
            Err(e) => self.stored(
                Stored {
                    how,
                    elapsed_s,
                    record: Err(format!("the map was not stored: {e}")),
                    reply,
                },
                ctx,
            ),
        }
    }

    /// The map stored: in use in the tracker, in the cache and the snapshot, the zero taken
    /// again; or why there is none.
    fn stored(&mut self, st: Stored, ctx: &mut Ctx) {
        self.storing = false;
        let Some(v) = self.view.as_mut() else {
            return;
        };
        v.elapsed_s = st.elapsed_s;
        v.left_s = 0.0;
        match st.record {
            Ok(rec) => {
                ctx.pipeline
                    .tracker
                    .set_map(Some(Arc::new(rec.map.clone())));
                *ctx.shown = Some(crate::service::follower::view(&rec));
                // The stitch has moved on by the follower's steps: the zero again, here. The
                // mapping is done once it is taken.
                let zero = ctx.pipeline.begin_zero(ctx.now, ctx.zero_window());
                self.zeroing = zero;
                v.state = if zero { "finishing" } else { "done" }.into();
                v.map_id = Some(rec.id);
                v.summary = rec.map.summary();
                v.error = (!zero).then(|| {
                    "the zero could not be taken again (the follower's position is not known): take it before measuring".to_string()
                });
                tracing::info!(
                    id = rec.id,
                    "follower mapping {}: map stored and in use, the zero taken again",
                    st.how
                );
                ctx.cached.follower_map = Some(rec);
            }
            Err(e) => {
                let msg = format!(
                    "{}, but no map was built: {e}; the map in use is unchanged",
                    st.how
                );
                ctx.pipeline.alarms.raise("mapping-failed", msg.clone());
                v.state = "failed".into();
                v.error = Some(msg);
            }
        }
        self.owed = st.reply;
        self.answer_owed();
    }

    /// The reply owed to `follower_map_finish`, once the mapping is done (or failed).
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

/// The map from the collected steps and the certificate (given, or the one kept with the
/// map in use), as it is stored (with its steps: a level's stations fit them again later),
/// and its name.
fn build_map(
    a: &Active,
    now: Instant,
    in_use: Option<&FollowerMapRecord>,
) -> Result<(crate::follower::StoredMap, String), String> {
    let certificate = match &a.certificate {
        CertificateFrom::Given(c) => Some(c.clone()),
        CertificateFrom::InUse => in_use.and_then(|r| r.certificate.clone()),
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
    let stored = crate::follower::StoredMap {
        map,
        certificate,
        steps: Some(crate::follower::StoredSteps {
            settings: a.settings,
            steps: a.collector.steps().to_vec(),
        }),
    };
    Ok((stored, name))
}

impl Procedure for FollowerMapping {
    fn name(&self) -> &'static str {
        "the follower mapping"
    }

    fn takes(&self, req: &Request) -> bool {
        matches!(
            req,
            Request::FollowerMapStart(_)
                | Request::FollowerMapStatus
                | Request::FollowerMapStop
                | Request::FollowerMapFinish
        )
    }

    fn starts(&self, req: &Request) -> bool {
        matches!(req, Request::FollowerMapStart(_))
    }

    fn holds_machine(&self) -> bool {
        self.active.is_some() || self.storing || self.zeroing
    }

    fn busy(&self, what: &str) -> String {
        format!(
            "the follower mapping is under way (its part program moves the carriage): stop it with follower_map_stop (axiscomp follower map --stop, or m on the console's Align screen) or let it finish, then {what}"
        )
    }

    fn request(&mut self, req: Request, who: &Who, reply: Reply, ctx: &mut Ctx) {
        match req {
            Request::FollowerMapStart(m) => self.start(m, &who.user, reply, ctx),
            Request::FollowerMapStatus => reply.send(Ok(self.status())),
            Request::FollowerMapStop => reply.send(self.stop(&who.user, ctx)),
            Request::FollowerMapFinish => self.finish(&who.user, reply, ctx),
            _ => reply.send(Err("internal: not a follower mapping request".into())),
        }
    }

    fn on_output(&mut self, out: &Output, ctx: &mut Ctx) {
        if let Output::Handover(r) = out {
            self.handle_record(r, ctx.pipeline);
        }
    }

    fn tick(&mut self, ctx: &mut Ctx) {
        self.advance(ctx);
    }

    fn show(&self, snap: &mut Snapshot, _pipeline: &Pipeline) {
        snap.follower_mapping = self.view();
    }
}
