//! The calibration run with the hexapod in the loop (DESIGN §3): the plan is checked against
//! the workspace before the first move; the hexapod is initialised and given its pivot and
//! work frame; at each pose it moves, reports in position and its reached pose, settles, and
//! a stable window of frames is averaged. Every pose is stored as it is taken (the frames
//! first, then the pose line that commits them, flushed to disk), so a run that stops — a
//! controller error, a crash — resumes at the next pose. A dropped link is reconnected and
//! the pose taken again. Then the linear and model fits and the hold-out judgement.
//!
//! The judgement: the poses held out of the fit (every `holdout_every`-th) are decoupled
//! frame by frame with the new calibration against the reached poses; the RMS per DOF is
//! compared with the Cramér–Rao bound of single frames (the calibrated model's Jacobian at
//! each held-out pose, the frame noise measured at the poses). Averaging many frames per pose
//! keeps the calibration's own error well below one frame's noise.
//!
//! Stations: the plan's poses may stand at several positions along the travel (DESIGN §3:
//! the follower window along the travel). Before the first pose at a station — and at the
//! first pose after a resume — the bench (`super::bench`) brings the carriage and the
//! follower there (a plan at one position runs where they are). The fit gives each station after the first its own offset (the carriage's
//! and the follower's own errors there, `calibrate::Stations`), and the judgement compares
//! each held-out frame with the reached pose plus its station's offset. A held-out frame the
//! calibrated model cannot decouple (a spot near a PSD's edge, a trace that fails) is left
//! out and counted; more than `MAX_UNTRACEABLE` of them refuses the judgement.

use super::bench::Bench;
use super::plan::{PlanError, PosePlan};
use super::{HexPose, Hexapod, HexapodError, Workspace};
use crate::calibrate::{
    self, CalError, CalibrateOptions, Calibration, PoseSample, StationOffset, add_errors,
};
use crate::decouple;
use crate::optics::{Layout, Pose};
use crate::units::{MM_PER_UM, readings_from_um, readings_to_um};
use nalgebra::Vector6;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why the run stopped.
#[derive(Debug, Error)]
pub enum ProcedureError {
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(
        "pose {index} of {total}: {source}; the poses taken so far are stored: run again to resume"
    )]
    Hexapod {
        index: usize,
        total: usize,
        source: HexapodError,
    },
    #[error("pose {index}: {problem}")]
    Frames { index: usize, problem: String },
    #[error("{path}: {problem}")]
    Store { path: String, problem: String },
    #[error(transparent)]
    Calibrate(#[from] CalError),
    #[error(
        "stopped by the operator before pose {index} of {total}; the poses taken so far are stored: start again to resume"
    )]
    Stopped { index: usize, total: usize },
    #[error(
        "pose {index} of {total}: the carriage and the follower did not reach travel {travel_mm} mm and {follower_mm} mm ({problem}); the poses taken so far are stored: run again to resume"
    )]
    Bench {
        index: usize,
        total: usize,
        travel_mm: f64,
        follower_mm: f64,
        problem: String,
    },
    #[error(
        "{untraceable} of {frames} held-out frames cannot be decoupled with the new calibration (first at pose {first_pose}: {first}), more than {limit_percent:.0} %: the fit does not hold over the plan's window; check the PSDs' spots at the plan's extremes or narrow the plan"
    )]
    Untraceable {
        untraceable: usize,
        frames: usize,
        first_pose: usize,
        first: String,
        limit_percent: f64,
    },
}

/// The largest share of held-out frames the judgement leaves out as untraceable.
pub const MAX_UNTRACEABLE: f64 = 0.02;

/// The operator's stop: once `true`, the run halts the hexapod and ends before the next pose.
pub type StopSignal = tokio::sync::watch::Receiver<bool>;

/// A stop signal that never fires.
pub fn never_stop() -> StopSignal {
    tokio::sync::watch::channel(false).1
}

/// A source of PSD frames: the readings (mm) of the next frame, `None` when it is invalid
/// (a PSD without its spot); only frames taken at or after `since` count.
pub trait FrameSource: Send {
    fn next_frame(
        &mut self,
        since: Instant,
    ) -> impl std::future::Future<Output = Result<Option<Vector6<f64>>, String>> + Send;
}

impl FrameSource for tokio::sync::broadcast::Receiver<crate::acquire::Frame> {
    async fn next_frame(&mut self, since: Instant) -> Result<Option<Vector6<f64>>, String> {
        use tokio::sync::broadcast::error::RecvError;
        loop {
            match self.recv().await {
                Ok(f) if f.at >= since => return Ok(f.readings()),
                Ok(_) | Err(RecvError::Lagged(_)) => continue,
                Err(RecvError::Closed) => return Err("the acquisition stopped".into()),
            }
        }
    }
}

/// How each pose is taken.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOptions {
    /// Pivot point (mm, platform frame) and work coordinate system.
    pub pivot: [f64; 3],
    pub work: HexPose,
    /// Wait after "in position" before averaging.
    pub settle: Duration,
    /// Frames averaged per pose.
    pub frames: usize,
    /// A window is stable when the means of its halves agree within this (µm) on every
    /// channel; else it is taken again (at most 5 times).
    pub stable_um: f64,
    /// Reconnect attempts after a dropped link (1 s apart).
    pub reconnects: u32,
    /// Longest wait for one frame.
    pub frame_timeout: Duration,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            pivot: [0.0; 3],
            work: HexPose::default(),
            settle: Duration::from_millis(200),
            frames: 50,
            stable_um: 2.0,
            reconnects: 10,
            frame_timeout: Duration::from_secs(2),
        }
    }
}

/// One stored pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StoredPose {
    pub index: usize,
    pub commanded: HexPose,
    pub reached: HexPose,
    /// Mean readings and their per-frame standard deviation (mm).
    pub mean: Vector6<f64>,
    pub sd: Vector6<f64>,
    pub frames: usize,
    pub travel_mm: f64,
    pub follower_mm: f64,
}

impl StoredPose {
    pub fn sample(&self) -> PoseSample {
        PoseSample {
            pose: Pose::new(self.reached.to_errors(), self.travel_mm, self.follower_mm),
            readings: self.mean,
        }
    }
}

const RUN_FILE: &str = "run.csv";
const FRAMES_FILE: &str = "frames.csv";

/// The run's files in a directory: `run.csv` (one line per pose taken) and `frames.csv`
/// (every averaged frame, for the judgement).
pub struct PoseStore {
    pub dir: PathBuf,
    pub poses: Vec<StoredPose>,
    plan: String,
}

fn store_err(path: &Path, e: impl std::fmt::Display) -> ProcedureError {
    ProcedureError::Store {
        path: path.display().to_string(),
        problem: e.to_string(),
    }
}

fn append(path: &Path, text: &str) -> Result<(), ProcedureError> {
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| store_err(path, e))?;
    f.write_all(text.as_bytes())
        .and_then(|_| f.sync_data())
        .map_err(|e| store_err(path, e))
}

fn um(v: &Vector6<f64>) -> String {
    readings_to_um(v)
        .iter()
        .map(|x| format!("{x:.5}"))
        .collect::<Vec<_>>()
        .join(",")
}

fn pose6(p: &HexPose) -> String {
    p.0.iter()
        .map(|x| format!("{x:.9}"))
        .collect::<Vec<_>>()
        .join(",")
}

impl PoseStore {
    /// Open (or start) the run in `dir` for `plan`: a run file of another plan is refused.
    pub fn open(dir: &Path, plan: &PosePlan) -> Result<PoseStore, ProcedureError> {
        std::fs::create_dir_all(dir).map_err(|e| store_err(dir, e))?;
        let fp = plan.fingerprint();
        let path = dir.join(RUN_FILE);
        let mut store = PoseStore {
            dir: dir.to_path_buf(),
            poses: Vec::new(),
            plan: fp.clone(),
        };
        match std::fs::read_to_string(&path) {
            Ok(text) => store.load(&text, &path)?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let mut head = format!(
                    "# axiscomp hexapod calibration run\n# plan {fp} ({} poses)\nindex",
                    plan.poses.len()
                );
                for c in ["x_mm", "y_mm", "z_mm", "u_deg", "v_deg", "w_deg"] {
                    let _ = write!(head, ",{c}");
                }
                for c in ["x_mm", "y_mm", "z_mm", "u_deg", "v_deg", "w_deg"] {
                    let _ = write!(head, ",reached_{c}");
                }
                for c in calibrate::poses::READING_COLUMNS {
                    let _ = write!(head, ",{c}");
                }
                for c in calibrate::poses::READING_COLUMNS {
                    let _ = write!(head, ",sd_{c}");
                }
                head.push_str(",frames,travel_mm,follower_mm\n");
                append(&path, &head)?;
                append(
                    &dir.join(FRAMES_FILE),
                    "index,X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n",
                )?;
            }
            Err(e) => return Err(store_err(&path, e)),
        }
        Ok(store)
    }

    fn load(&mut self, text: &str, path: &Path) -> Result<(), ProcedureError> {
        let mut plan_ok = false;
        for (ln, line) in text.lines().enumerate() {
            if let Some(rest) = line.strip_prefix("# plan ") {
                plan_ok = rest.split_whitespace().next() == Some(self.plan.as_str());
                if !plan_ok {
                    return Err(store_err(
                        path,
                        "was taken with another plan: give the same plan to resume, or another --out directory to start anew",
                    ));
                }
                continue;
            }
            if line.starts_with('#') || line.starts_with("index") || line.trim().is_empty() {
                continue;
            }
            let v: Vec<f64> = line
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| store_err(path, format!("line {}: not a pose line", ln + 1)))?;
            if v.len() != 28 {
                // A line cut short by a crash: the pose is taken again.
                continue;
            }
            let six = |o: usize| -> [f64; 6] { std::array::from_fn(|k| v[o + k]) };
            self.poses.push(StoredPose {
                index: v[0] as usize,
                commanded: HexPose(six(1)),
                reached: HexPose(six(7)),
                mean: readings_from_um(six(13)),
                sd: readings_from_um(six(19)),
                frames: v[25] as usize,
                travel_mm: v[26],
                follower_mm: v[27],
            });
        }
        if !plan_ok {
            return Err(store_err(
                path,
                "has no plan line: not a run file of axiscomp",
            ));
        }
        Ok(())
    }

    /// The next pose to take (0-based), after those stored.
    pub fn next_index(&self) -> usize {
        self.poses.last().map(|p| p.index).unwrap_or(0)
    }

    /// Store one pose: its frames, then the line that commits them.
    pub fn push(&mut self, p: StoredPose, frames: &[Vector6<f64>]) -> Result<(), ProcedureError> {
        let mut f = String::new();
        for r in frames {
            let _ = writeln!(f, "{},{}", p.index, um(r));
        }
        append(&self.dir.join(FRAMES_FILE), &f)?;
        let line = format!(
            "{},{},{},{},{},{},{},{}\n",
            p.index,
            pose6(&p.commanded),
            pose6(&p.reached),
            um(&p.mean),
            um(&p.sd),
            p.frames,
            p.travel_mm,
            p.follower_mm
        );
        append(&self.dir.join(RUN_FILE), &line)?;
        self.poses.push(p);
        Ok(())
    }

    /// The frames of the committed poses, by pose index (1-based).
    pub fn frames(&self) -> Result<Vec<(usize, Vector6<f64>)>, ProcedureError> {
        let path = self.dir.join(FRAMES_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| store_err(&path, e))?;
        let committed: std::collections::BTreeSet<usize> =
            self.poses.iter().map(|p| p.index).collect();
        let mut out = Vec::new();
        for line in text.lines().skip(1) {
            let v: Vec<f64> = line
                .split(',')
                .filter_map(|x| x.trim().parse().ok())
                .collect();
            if v.len() == 7 && committed.contains(&(v[0] as usize)) {
                out.push((
                    v[0] as usize,
                    readings_from_um(std::array::from_fn(|k| v[k + 1])),
                ));
            }
        }
        Ok(out)
    }
}

/// Where the run is, for progress displays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunProgress {
    pub done: usize,
    pub total: usize,
    /// Time left at this session's pace.
    pub eta: Option<Duration>,
    pub reconnects: u32,
    /// Machine time (moves, settling, averaging) and wall time of this session so far.
    pub machine: Duration,
    pub elapsed: Duration,
}

/// What a run did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunReport {
    /// Poses taken in this session, and stored before it (resumed).
    pub taken: usize,
    pub resumed_from: usize,
    /// Time the hexapod and the head were busy (moves, settling, averaging), and the whole.
    pub machine: Duration,
    pub wall: Duration,
    pub reconnects: u32,
}

async fn average(
    frames: &mut impl FrameSource,
    opts: &RunOptions,
    index: usize,
) -> Result<(Vector6<f64>, Vector6<f64>, Vec<Vector6<f64>>), ProcedureError> {
    let n = opts.frames.max(2);
    let mut last = String::new();
    for _ in 0..5 {
        let since = crate::util::clock::now();
        let mut got = Vec::with_capacity(n);
        let mut invalid = 0;
        while got.len() < n {
            match tokio::time::timeout(opts.frame_timeout, frames.next_frame(since)).await {
                Err(_) => {
                    return Err(ProcedureError::Frames {
                        index,
                        problem: format!(
                            "no frame within {:.1} s: is the I/O module reachable?",
                            opts.frame_timeout.as_secs_f64()
                        ),
                    });
                }
                Ok(Err(e)) => return Err(ProcedureError::Frames { index, problem: e }),
                Ok(Ok(Some(r))) => got.push(r),
                Ok(Ok(None)) => {
                    invalid += 1;
                    if invalid > 10 * n {
                        return Err(ProcedureError::Frames {
                            index,
                            problem: "a PSD has no spot at this pose: is the beam blocked, or the pose outside the PSDs?".into(),
                        });
                    }
                }
            }
        }
        let mean = |s: &[Vector6<f64>]| s.iter().sum::<Vector6<f64>>() / s.len() as f64;
        let m = mean(&got);
        let (a, b) = got.split_at(n / 2);
        let drift = (mean(a) - mean(b)).abs().max() / MM_PER_UM;
        if drift <= opts.stable_um {
            let var = got
                .iter()
                .map(|r| (r - m).component_mul(&(r - m)))
                .sum::<Vector6<f64>>()
                / (n - 1) as f64;
            return Ok((m, var.map(f64::sqrt), got));
        }
        last = format!("the halves of the window differ by {drift:.2} µm");
    }
    Err(ProcedureError::Frames {
        index,
        problem: format!(
            "the readings do not settle ({last}, limit {} µm)",
            opts.stable_um
        ),
    })
}

/// Resolves once the operator's stop is set.
async fn stopped(stop: &mut StopSignal) {
    while !*stop.borrow_and_update() {
        if stop.changed().await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// Run (or resume) the plan: workspace check first, then every pose not yet stored, the
/// bench bringing the carriage and the follower to each pose's station first.
/// (The controller, the frames, the bench, the plan and its limits, the store, how to take a
/// pose, the operator's stop and the progress report are each their own: no struct would
/// group them.)
#[allow(clippy::too_many_arguments)]
pub async fn run(
    hexapod: &mut Hexapod,
    frames: &mut impl FrameSource,
    bench: &mut impl Bench,
    plan: &PosePlan,
    workspace: &Workspace,
    store: &mut PoseStore,
    opts: &RunOptions,
    stop: &StopSignal,
    progress: &mut (dyn FnMut(&RunProgress) + Send),
) -> Result<RunReport, ProcedureError> {
    plan.check(workspace)?;
    // A plan at one position runs where the operator put the carriage and the follower, as
    // before stations existed; the bench moves them only between stations.
    let moving = plan.stations().len() > 1;
    if moving && !bench.moves() {
        plan.station()?;
    }
    let mut stop = stop.clone();
    let start = crate::util::clock::now();
    let total = plan.poses.len();
    let resumed_from = store.next_index();
    let fail = |index: usize, source: HexapodError| ProcedureError::Hexapod {
        index,
        total,
        source,
    };
    let mut reconnects = 0;
    let mut machine = Duration::ZERO;
    let mut prepared = false;
    let mut station: Option<(f64, f64)> = None;
    let mut i = resumed_from;
    while i < total {
        let index = i + 1;
        if *stop.borrow() {
            return Err(ProcedureError::Stopped { index, total });
        }
        let t0 = crate::util::clock::now();
        let here = (plan.poses[i].travel_mm, plan.poses[i].follower_mm);
        if moving && station != Some(here) {
            tracing::info!(
                pose = index,
                travel_mm = here.0,
                follower_mm = here.1,
                "hexapod calibration: to the next station"
            );
            let moved = tokio::select! {
                r = bench.go_to(here.0, here.1) => Some(r),
                () = stopped(&mut stop) => None,
            };
            match moved {
                None => return Err(ProcedureError::Stopped { index, total }),
                Some(Err(problem)) => {
                    return Err(ProcedureError::Bench {
                        index,
                        total,
                        travel_mm: here.0,
                        follower_mm: here.1,
                        problem,
                    });
                }
                Some(Ok(())) => station = Some(here),
            }
        }
        let step = async {
            if !prepared {
                hexapod.initialize().await?;
                hexapod.set_frames(opts.pivot, opts.work).await?;
            }
            hexapod.move_to(plan.poses[i].pose).await
        };
        let outcome = tokio::select! {
            r = step => Some(r),
            () = stopped(&mut stop) => None,
        };
        let Some(outcome) = outcome else {
            // Halt the platform where it is; this pose is taken again on resume.
            let _ = hexapod.stop().await;
            return Err(ProcedureError::Stopped { index, total });
        };
        let reached = match outcome {
            Ok(r) => r,
            Err(e) if e.is_link() && reconnects < opts.reconnects => {
                // Stop, reconnect, take this pose again.
                tracing::warn!(pose = index, error = %e, "hexapod link lost: reconnecting");
                reconnects += 1;
                prepared = false;
                tokio::time::sleep(Duration::from_secs(1)).await;
                if let Err(e) = hexapod.reconnect().await {
                    tracing::warn!(error = %e, "hexapod reconnect failed");
                }
                continue;
            }
            Err(e) => {
                let _ = hexapod.stop().await;
                return Err(fail(index, e));
            }
        };
        prepared = true;
        tokio::time::sleep(opts.settle).await;
        let (mean, sd, window) = average(frames, opts, index).await?;
        machine += crate::util::clock::since(t0);
        let p = &plan.poses[i];
        store.push(
            StoredPose {
                index,
                commanded: p.pose,
                reached,
                mean,
                sd,
                frames: window.len(),
                travel_mm: p.travel_mm,
                follower_mm: p.follower_mm,
            },
            &window,
        )?;
        i += 1;
        let done = i - resumed_from;
        let per = crate::util::clock::since(start).div_f64(done as f64);
        progress(&RunProgress {
            done: i,
            total,
            eta: Some(per.mul_f64((total - i) as f64)),
            reconnects,
            machine,
            elapsed: crate::util::clock::since(start),
        });
    }
    // Back to the zero pose, where the head measures: the last pose may stand millimetres
    // off, and the calibration is judged (and its plausibility read) at the head's home.
    if prepared {
        let home = tokio::select! {
            r = hexapod.move_to(HexPose::default()) => Some(r),
            () = stopped(&mut stop) => None,
        };
        match home {
            Some(Ok(_)) => tokio::time::sleep(opts.settle).await,
            Some(Err(e)) => tracing::warn!(
                error = %e,
                "the hexapod did not return to its zero pose after the last pose: move it there before accepting the calibration"
            ),
            None => {
                let _ = hexapod.stop().await;
            }
        }
    }
    Ok(RunReport {
        taken: total - resumed_from,
        resumed_from,
        machine,
        wall: crate::util::clock::since(start),
        reconnects,
    })
}

/// The fitted calibration and how it holds on the held-out poses.
#[derive(Clone, Debug)]
pub struct Judgement {
    pub calibration: Calibration,
    /// Each station's fitted offset (zero at the first; one station: just that).
    pub stations: Vec<StationOffset>,
    /// Frames decoupled, over how many held-out poses.
    pub frames: usize,
    pub holdout_poses: usize,
    /// Held-out frames the calibration could not decouple, left out of the RMS.
    pub untraceable: usize,
    /// Frame noise per channel (mm), pooled over the poses.
    pub sigma_frame_mm: [f64; 6],
    /// RMS per DOF (internal units) of single frames against the reached pose.
    pub holdout_rms: [f64; 6],
    /// The Cramér–Rao bound of one frame, RMS over the held-out poses.
    pub crlb: [f64; 6],
}

impl Judgement {
    pub fn ratio(&self) -> [f64; 6] {
        std::array::from_fn(|k| self.holdout_rms[k] / self.crlb[k])
    }
}

/// Fit the stored poses (linear and model, every `opts.holdout_every`-th held out, each
/// station after the first with its own offset) and judge the calibration frame by frame on
/// the held-out poses, each against its reached pose plus its station's offset.
pub fn fit_and_judge(
    store: &PoseStore,
    layout: &Layout,
    opts: &CalibrateOptions,
    on_iter: &mut dyn FnMut(u32, f64),
) -> Result<Judgement, ProcedureError> {
    let samples: Vec<PoseSample> = store.poses.iter().map(StoredPose::sample).collect();
    let opts = CalibrateOptions {
        station_offsets: true,
        ..*opts
    };
    let (cal, stations) = calibrate::calibrate_along(&samples, layout, &opts, on_iter)?;
    let dec = cal.decoupler(layout)?;
    let linear = cal.model.is_none();
    let every = opts.holdout_every.max(2);
    let held: std::collections::BTreeMap<usize, &StoredPose> = store
        .poses
        .iter()
        .enumerate()
        .filter(|(i, _)| opts.holdout_every > 0 && i % every == every - 1)
        .map(|(_, p)| (p.index, p))
        .collect();
    // The pose the head was at: the reached pose plus its station's offset (model), and the
    // station's reading offset (linear β).
    let at = |p: &StoredPose| -> (Pose, Vector6<f64>) {
        let s = p.sample();
        match StationOffset::find(&stations, s.pose.travel, s.pose.follower) {
            Some(o) if !linear => (
                Pose {
                    errors: o
                        .errors
                        .map(|e| add_errors(&s.pose.errors, &e))
                        .unwrap_or(s.pose.errors),
                    ..s.pose
                },
                Vector6::zeros(),
            ),
            Some(o) => (s.pose, o.readings),
            None => (s.pose, Vector6::zeros()),
        }
    };
    // Frame noise: pooled per-pose variance.
    let mut pooled = [0.0; 6];
    for p in &store.poses {
        for (acc, sd) in pooled.iter_mut().zip(p.sd.iter()) {
            *acc += sd * sd;
        }
    }
    let sigma: [f64; 6] = pooled.map(|v| (v / store.poses.len().max(1) as f64).sqrt().max(1e-9));
    let model_layout = cal.model.as_ref().map(|m| &m.layout).unwrap_or(layout);
    let mut var = [0.0; 6];
    for p in held.values() {
        let j = decouple::jacobian(model_layout, &at(p).0).map_err(CalError::from)?;
        let c = decouple::covariance(&j, &sigma)
            .ok_or(CalError::Decouple(decouple::DecoupleError::Singular))?;
        for k in 0..6 {
            var[k] += c[(k, k)];
        }
    }
    let crlb = var.map(|v| (v / held.len().max(1) as f64).sqrt());
    let mut ss = [0.0; 6];
    let (mut n, mut untraceable) = (0, 0);
    let mut first: Option<(usize, String)> = None;
    for (index, r) in store.frames()? {
        let Some(p) = held.get(&index) else {
            continue;
        };
        let (pose, offset) = at(p);
        match dec.decouple(&(r - offset), pose.travel, pose.follower) {
            Ok(est) => {
                let (e, t) = (est.errors.to_array(), pose.errors.to_array());
                for k in 0..6 {
                    ss[k] += (e[k] - t[k]).powi(2);
                }
                n += 1;
            }
            Err(e) => {
                untraceable += 1;
                first.get_or_insert((index, e.to_string()));
            }
        }
    }
    let frames = n + untraceable;
    if untraceable > 0 {
        tracing::warn!(
            untraceable,
            frames,
            "held-out frames the calibration cannot decouple are left out of the judgement"
        );
    }
    if let Some((first_pose, first)) =
        first.filter(|_| untraceable as f64 > MAX_UNTRACEABLE * frames as f64 || n == 0)
    {
        return Err(ProcedureError::Untraceable {
            untraceable,
            frames,
            first_pose,
            first,
            limit_percent: MAX_UNTRACEABLE * 100.0,
        });
    }
    Ok(Judgement {
        calibration: cal,
        stations,
        frames: n,
        holdout_poses: held.len(),
        untraceable,
        sigma_frame_mm: sigma,
        holdout_rms: ss.map(|x| (x / n.max(1) as f64).sqrt()),
        crlb,
    })
}

/// The stored poses as a pose-set CSV (`calibrate fit`, the service's Calibrate screen).
pub fn pose_set_csv(store: &PoseStore, comments: &[String]) -> String {
    let samples: Vec<PoseSample> = store.poses.iter().map(StoredPose::sample).collect();
    calibrate::write_pose_csv(&samples, comments)
}
