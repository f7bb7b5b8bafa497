//! Calibrating with the hexapod in the loop from the service (the console's Calibrate
//! screen): `hexapod_start` runs [`crate::hexapod::session`] — the same session as
//! `axiscomp calibrate run` — on a task of its own, reading the head from the service's own
//! acquisition; `hexapod_status` follows it (pose i of N, machine time, time left, the
//! controller's error in its own words); `hexapod_stop` halts the platform and ends the run
//! before the next pose. Every pose is stored as it is taken in the run directory, so starting
//! again with the same plan resumes at the next pose (after a controller fault, a stop, a
//! crash). The fitted calibration then waits for accept or reject like any other.
//!
//! A plan at several positions along the travel runs when the service drives the twin's CNC
//! (`[cnc] mode = "twin"`): [`ServiceBench`] moves the carriage there through the twin's
//! control socket and the follower through the service's own drive. With a CNC the service
//! does not drive, such a plan is refused before any move.

use super::{Ctx, Procedure, Reply, Who};
use crate::acquire::Frame;
use crate::canopen::DriveHandle;
use crate::config::CncMode;
use crate::hexapod::bench::Bench;
use crate::hexapod::config::HexapodSettings;
use crate::hexapod::plan::{PlanSpec, PosePlan};
use crate::hexapod::procedure::{PoseStore, ProcedureError};
use crate::hexapod::session::{self, SessionEvent};
use crate::optics::Layout;
use crate::service::api::HexapodView as RunView;
use crate::service::api::Request;
use crate::service::api::hexapod::{DEFAULT_POSES, MAX_POSES, MIN_POSES};
use crate::service::calibration::{Pending, Summary};
use crate::units::DOF_TO_USER;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{broadcast, watch};

/// The service's bench: the twin's carriage through its control socket (none with a CNC the
/// service does not drive), the follower through the service's drive.
pub struct ServiceBench {
    twin: Option<SocketAddr>,
    drive: DriveHandle,
}

impl ServiceBench {
    pub fn new(cnc: &CncMode, drive: DriveHandle) -> ServiceBench {
        let twin = match cnc {
            CncMode::Twin(a) => Some(*a),
            CncMode::Manual => None,
        };
        ServiceBench { twin, drive }
    }
}

impl Bench for ServiceBench {
    fn moves(&self) -> bool {
        self.twin.is_some()
    }

    async fn go_to(&mut self, travel_mm: f64, follower_mm: f64) -> Result<(), String> {
        let addr = self
            .twin
            .ok_or("the service does not drive this CNC ([cnc] mode is manual)")?;
        let r = crate::service::cnc::twin_request(
            addr,
            serde_json::json!({"cmd": "move", "mm": travel_mm}),
        )
        .await?;
        // The twin answers a wait within its request timeout: sleep through the move first.
        let secs = r["duration_s"].as_f64().unwrap_or(0.0);
        if secs.is_finite() && secs > 0.0 {
            tokio::time::sleep(Duration::from_secs_f64(secs)).await;
        }
        crate::service::cnc::twin_request(addr, serde_json::json!({"cmd": "wait"})).await?;
        self.drive
            .move_to(follower_mm)
            .await
            .map_err(|e| format!("the follower to {follower_mm} mm: {e}"))
    }
}

/// Every n-th pose is held out of the fit to judge it.
const HOLDOUT_EVERY: usize = 5;

/// The service's hexapod runs: at most one at a time.
#[derive(Debug)]
pub struct HexapodRuns {
    settings: HexapodSettings,
    layout: Layout,
    state_dir: PathBuf,
    view: Arc<Mutex<RunView>>,
    stop: Option<watch::Sender<bool>>,
    /// A finished run's calibration, for the core to make pending.
    finished: Arc<Mutex<Option<Pending>>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The plan a start request asks for: the file on the service's host, or `poses` generated.
pub fn plan_for(plan: Option<&str>, poses: Option<usize>) -> Result<PosePlan, String> {
    match plan.filter(|p| !p.trim().is_empty()) {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| {
                format!("plan {path}: cannot read it ({e}); give a CSV on the service's host")
            })?;
            PosePlan::parse(&text, path).map_err(|e| e.to_string())
        }
        None => {
            let n = poses.unwrap_or(DEFAULT_POSES);
            if n < MIN_POSES {
                return Err(format!("{n} poses: give at least {MIN_POSES}"));
            }
            crate::util::range::int_field("poses", Some(n), MIN_POSES, MAX_POSES)?;
            Ok(PosePlan::generate(&PlanSpec {
                poses: n,
                ..PlanSpec::default()
            }))
        }
    }
}

impl HexapodRuns {
    pub fn new(settings: HexapodSettings, layout: Layout, state_dir: &Path) -> HexapodRuns {
        HexapodRuns {
            settings,
            layout,
            state_dir: state_dir.to_path_buf(),
            view: Arc::new(Mutex::new(RunView::idle())),
            stop: None,
            finished: Arc::new(Mutex::new(None)),
        }
    }

    /// Where the run is.
    pub fn status(&self) -> serde_json::Value {
        serde_json::to_value(&*lock(&self.view)).unwrap_or_default()
    }

    /// Whether a run is under way.
    pub fn active(&self) -> bool {
        lock(&self.view).active()
    }

    /// A finished run's calibration, once.
    pub fn take_finished(&self) -> Option<Pending> {
        lock(&self.finished).take()
    }

    /// Start (or resume) a run; everything the request can get wrong is refused here, before
    /// the hexapod moves.
    pub fn start(
        &mut self,
        plan: Option<String>,
        poses: Option<usize>,
        out: Option<String>,
        frames: broadcast::Receiver<Frame>,
        bench: ServiceBench,
    ) -> Result<serde_json::Value, String> {
        if self.active() {
            return Err("a hexapod run is under way: stop it (or wait) first".into());
        }
        session::driver(&self.settings)?;
        let pose_plan = plan_for(plan.as_deref(), poses)?;
        pose_plan
            .check(&self.settings.workspace)
            .and_then(|()| match bench.moves() {
                true => Ok(()),
                false => pose_plan.station().map(|_| ()),
            })
            .map_err(|e| e.to_string())?;
        let out = out
            .filter(|o| !o.trim().is_empty())
            .map(PathBuf::from)
            .unwrap_or_else(|| self.state_dir.join("hexapod-run"));
        let stored = PoseStore::open(&out, &pose_plan)
            .map_err(|e| e.to_string())?
            .poses
            .len();
        let total = pose_plan.poses.len();
        let (stop_tx, stop_rx) = watch::channel(false);
        self.stop = Some(stop_tx);
        *lock(&self.view) = RunView {
            state: "running".into(),
            controller: self.settings.driver.map(|d| d.name()).unwrap_or("").into(),
            plan: plan.clone().unwrap_or_default(),
            poses: total,
            stations: pose_plan.stations().len(),
            out: out.display().to_string(),
            done: stored,
            total,
            resumed_from: stored,
            ..RunView::default()
        };
        let (hx, layout) = (self.settings.clone(), self.layout.clone());
        let (view, finished) = (self.view.clone(), self.finished.clone());
        let dir = out.clone();
        tokio::spawn(async move {
            let (mut frames, mut bench) = (frames, bench);
            let ev_view = view.clone();
            let r = session::run(
                &hx,
                &mut frames,
                &mut bench,
                &pose_plan,
                &dir,
                &layout,
                HOLDOUT_EVERY,
                &stop_rx,
                &mut |e| {
                    let mut v = lock(&ev_view);
                    match e {
                        SessionEvent::Resuming { stored, .. } => v.resumed_from = stored,
                        SessionEvent::Connected { controller, id } => {
                            v.controller = format!("{controller} ({id})")
                        }
                        SessionEvent::Pose(p) => {
                            v.done = p.done;
                            v.machine_s = p.machine.as_secs_f64();
                            v.elapsed_s = p.elapsed.as_secs_f64();
                            v.eta_s = p.eta.map(|d| d.as_secs_f64());
                            v.reconnects = p.reconnects;
                        }
                        SessionEvent::Fitting { iteration } => {
                            v.state = "fitting".into();
                            v.eta_s = None;
                            v.fit_iteration = iteration;
                        }
                    }
                },
            )
            .await;
            let mut v = lock(&view);
            match r {
                Ok(o) => {
                    let j = &o.judgement;
                    let user = |a: [f64; 6]| -> [f64; 6] {
                        std::array::from_fn(|k| a[k] * DOF_TO_USER[k])
                    };
                    v.state = "done".into();
                    v.done = v.total;
                    v.machine_s = o.report.machine.as_secs_f64();
                    v.elapsed_s = o.report.wall.as_secs_f64();
                    v.eta_s = None;
                    v.holdout_poses = j.holdout_poses;
                    v.holdout_frames = j.frames;
                    v.untraceable = j.untraceable;
                    v.holdout_rms = Some(user(j.holdout_rms));
                    v.crlb = Some(user(j.crlb));
                    v.ratio = Some(j.ratio());
                    v.calibration_file = o.calibration_file.display().to_string();
                    let source = o.calibration_file.display().to_string();
                    match j.calibration.decoupler(&layout) {
                        Ok(decoupler) => {
                            *lock(&finished) = Some(Pending {
                                summary: Summary::of(&j.calibration, &source),
                                calibration: j.calibration.clone(),
                                decoupler,
                            })
                        }
                        Err(e) => {
                            v.state = "failed".into();
                            v.error = Some(format!("the fitted calibration: {e}"));
                        }
                    }
                }
                Err(e) => {
                    v.state = match e {
                        ProcedureError::Stopped { .. } => "stopped",
                        _ => "failed",
                    }
                    .into();
                    v.eta_s = None;
                    v.error = Some(e.to_string());
                    tracing::warn!(error = %e, "hexapod calibration run ended");
                }
            }
        });
        tracing::info!(poses = total, stored, out = %out.display(), "hexapod calibration run started");
        Ok(serde_json::json!({
            "poses": total,
            "stored": stored,
            "out": out.display().to_string(),
        }))
    }

    /// Ask the run to stop: the platform halts, the run ends before the next pose.
    pub fn stop(&mut self) -> Result<serde_json::Value, String> {
        let mut v = lock(&self.view);
        if v.state != "running" {
            return Err("no hexapod run is moving".into());
        }
        if let Some(s) = &self.stop {
            let _ = s.send(true);
        }
        v.state = "stopping".into();
        Ok(serde_json::json!({"stopping": true, "done": v.done, "total": v.total}))
    }
}

impl Procedure for HexapodRuns {
    fn name(&self) -> &'static str {
        "the hexapod calibration run"
    }

    fn takes(&self, req: &Request) -> bool {
        matches!(
            req,
            Request::HexapodStart { .. } | Request::HexapodStatus | Request::HexapodStop
        )
    }

    fn starts(&self, req: &Request) -> bool {
        matches!(req, Request::HexapodStart { .. })
    }

    fn holds_machine(&self) -> bool {
        self.active()
    }

    /// Under a hexapod calibration the follower holds still: the poses' PSD2 readings are
    /// taken with it where it is.
    fn holds_follower(&self) -> bool {
        self.active()
    }

    fn busy(&self, what: &str) -> String {
        format!(
            "a hexapod calibration run is under way (it moves the head): stop it with hexapod_stop or let it finish, then {what}"
        )
    }

    fn request(&mut self, req: Request, _who: &Who, reply: Reply, ctx: &mut Ctx) {
        match req {
            Request::HexapodStart { plan, poses, out } => {
                let bench = ServiceBench::new(&ctx.env.cnc, ctx.drive.clone());
                let r = self.start(plan, poses, out, ctx.acquisition.subscribe(), bench);
                if r.is_ok() {
                    ctx.pipeline.invalidate_stitch(
                        "the hexapod moved the head: zero again before measuring",
                    );
                }
                reply.send(r);
            }
            Request::HexapodStatus => {
                // A run that reads "done" has its calibration waiting by the time anyone
                // asks (the tick that takes it may not have come yet).
                let status = self.status();
                self.take_fit(ctx);
                reply.send(Ok(status));
            }
            Request::HexapodStop => reply.send(self.stop()),
            _ => reply.send(Err("internal: not a hexapod request".into())),
        }
    }

    fn tick(&mut self, ctx: &mut Ctx) {
        self.take_fit(ctx);
    }
}

impl HexapodRuns {
    /// A finished run's calibration, made pending (once) for accept or reject.
    fn take_fit(&self, ctx: &mut Ctx) {
        if let Some(p) = self.take_finished() {
            let measure = &ctx.pipeline.measure;
            let _ = ctx.calibrations.fitted(Ok(p), |d| measure.read_with(d));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plans_from_a_file_or_generated_and_bad_input_named() {
        assert_eq!(plan_for(None, None).unwrap().poses.len(), DEFAULT_POSES);
        assert_eq!(plan_for(Some(" "), Some(40)).unwrap().poses.len(), 40);
        let e = plan_for(None, Some(5)).unwrap_err();
        assert_eq!(e, "5 poses: give at least 20");
        let e = plan_for(Some("/nonexistent/plan.csv"), None).unwrap_err();
        assert!(
            e.starts_with("plan /nonexistent/plan.csv: cannot read it"),
            "{e}"
        );
    }
}
