//! One calibration session with the hexapod in the loop, as `axiscomp calibrate run` and the
//! service's Calibrate screen both run it: connect to the controller, set its speed, take (or
//! resume) the plan's poses into the run directory, then fit and judge on held-out poses and
//! write `calibration.toml` and the pose set there. The procedure itself is `procedure`; this
//! is the one place that strings it together, so the command line and the service cannot
//! drift apart.

use super::bench::Bench;
use super::config::HexapodSettings;
use super::plan::PosePlan;
use super::procedure::{
    self, FrameSource, Judgement, PoseStore, ProcedureError, RunProgress, RunReport, StopSignal,
};
use super::{Driver, Hexapod};
use crate::calibrate::{CalibrateOptions, CalibrationFile};
use crate::optics::Layout;
use std::path::{Path, PathBuf};

/// What a session reports as it goes.
#[derive(Clone, Debug, PartialEq)]
pub enum SessionEvent {
    /// The run directory holds this many poses of the plan already (resuming).
    Resuming { stored: usize, total: usize },
    /// Connected: the controller's identification.
    Connected {
        controller: &'static str,
        id: String,
    },
    /// A pose was stored.
    Pose(RunProgress),
    /// Every pose is stored: the fits run (model-fit iteration).
    Fitting { iteration: u32 },
}

/// What a finished session gives.
#[derive(Clone, Debug)]
pub struct SessionOutcome {
    pub report: RunReport,
    pub judgement: Judgement,
    pub calibration_file: PathBuf,
    pub pose_file: PathBuf,
    pub controller: &'static str,
}

/// The configured driver, or why there is none.
pub fn driver(hx: &HexapodSettings) -> Result<Driver, String> {
    hx.driver.ok_or_else(|| {
        "[hexapod] driver is \"none\": set driver = \"pi-gcs\" or \"newport-xps\" and its address in the configuration".to_string()
    })
}

/// Run (or resume) `plan` into `out` with the head read from `frames`, the bench bringing
/// the carriage and the follower to each station, then fit and judge. The plan is checked
/// against the workspace (and, where the bench cannot move, for one station) before anything
/// connects.
#[allow(clippy::too_many_arguments)]
pub async fn run(
    hx: &HexapodSettings,
    frames: &mut impl FrameSource,
    bench: &mut impl Bench,
    plan: &PosePlan,
    out: &Path,
    layout: &Layout,
    holdout_every: usize,
    stop: &StopSignal,
    events: &mut (dyn FnMut(SessionEvent) + Send),
) -> Result<SessionOutcome, ProcedureError> {
    let kind = driver(hx).map_err(|problem| ProcedureError::Store {
        path: "[hexapod]".into(),
        problem,
    })?;
    plan.check(&hx.workspace)?;
    if !bench.moves() {
        plan.station()?;
    }
    let mut store = PoseStore::open(out, plan)?;
    if !store.poses.is_empty() {
        events(SessionEvent::Resuming {
            stored: store.poses.len(),
            total: plan.poses.len(),
        });
    }
    let (total, next) = (plan.poses.len(), store.next_index() + 1);
    let link = |e| ProcedureError::Hexapod {
        index: next,
        total,
        source: e,
    };
    let mut h = Hexapod::connect(kind, &hx.address, &hx.group, hx.timeouts)
        .await
        .map_err(link)?;
    let id = h.identify().await.map_err(link)?;
    events(SessionEvent::Connected {
        controller: kind.name(),
        id,
    });
    h.set_speed(hx.speed_mm_s).await.map_err(link)?;
    let report = procedure::run(
        &mut h,
        frames,
        bench,
        plan,
        &hx.workspace,
        &mut store,
        &hx.run,
        stop,
        &mut |p| events(SessionEvent::Pose(*p)),
    )
    .await?;
    // The fits take seconds: off the event loop.
    let opts = CalibrateOptions {
        holdout_every,
        ..CalibrateOptions::default()
    };
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let layout_owned = layout.clone();
    let fit = tokio::task::spawn_blocking(move || {
        let j = procedure::fit_and_judge(&store, &layout_owned, &opts, &mut |it, _| {
            let _ = tx.send(it);
        });
        (store, j)
    });
    tokio::pin!(fit);
    let (store, judgement) = loop {
        tokio::select! {
            r = &mut fit => break r.map_err(|e| ProcedureError::Store {
                path: out.display().to_string(),
                problem: format!("the fit's thread ended abnormally: {e}"),
            })?,
            Some(it) = rx.recv() => events(SessionEvent::Fitting { iteration: it }),
        }
    };
    let judgement = judgement?;
    let calibration_file = out.join("calibration.toml");
    CalibrationFile::from_calibration(&judgement.calibration, layout).save(&calibration_file)?;
    let pose_file = out.join("poses.csv");
    let text = procedure::pose_set_csv(
        &store,
        &[format!(
            "axiscomp hexapod calibration: {} poses with the {} at {}",
            store.poses.len(),
            kind.name(),
            hx.address
        )],
    );
    std::fs::write(&pose_file, text).map_err(|e| ProcedureError::Store {
        path: pose_file.display().to_string(),
        problem: e.to_string(),
    })?;
    Ok(SessionOutcome {
        report,
        judgement,
        calibration_file,
        pose_file,
        controller: kind.name(),
    })
}
