//! The check the CNC asks for (issue 30): a thin task over the sans-I/O check handshake
//! (`plc::check`). With push configured and a CNC map that has `[check]`, it reads the PLC's
//! check fields every second on a Modbus link of its own. A new request starts a short check
//! of the axis the head stands on: the plan of the newest full run of that axis (five runs or
//! more, so never a check's) with two bidirectional runs, at the same targets, so the check
//! reads what the tables in force left at the points they correct. It goes to the core as a
//! `run_start` from the PLC (audited like an operator's: a refusal is recorded with its
//! reason), is watched to its end, and answered with the state and what the axis's trends say
//! of it (`service::trends`): in control, still learning its limits, a drift, a figure beyond
//! tolerance, flags open, failed or refused.

use super::api::{Request, Role};
use super::control::Command;
use super::peer::Peer;
use super::shutdown::Shutdown;
use super::trends::{AxisTrends, Remedy, Verdict};
use crate::config::PlcPush;
use crate::modbus::Link;
use crate::modbus::codec::ReadRange;
use crate::plc::Image;
use crate::plc::check::{CheckHandshake, CheckResult, Next, Polled};
use crate::plc::map::CheckFields;
use crate::report::settings::AcceptanceSettings;
use crate::run::{Plan, PlanSpec};
use crate::store::{RunId, RunState, Store};
use std::path::PathBuf;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;

/// How often the PLC's check fields are read.
const READ_EVERY: Duration = Duration::from_secs(1);
/// The bidirectional runs of a check.
pub const CHECK_RUNS: u32 = 2;
/// The fewest runs a run must have had for a check to take its plan.
const FULL_RUNS: u32 = 5;

/// The check task's inputs.
pub struct Checks {
    pub fields: CheckFields,
    pub unit: u8,
    pub push: PlcPush,
    pub requests: mpsc::Sender<Command>,
    pub store_path: PathBuf,
    pub acceptance: AcceptanceSettings,
}

/// The plan of a check of the newest full run in `store`: its axis's plan with
/// [`CHECK_RUNS`] runs, and that run's id; `None` when no finished run has five runs or more.
pub fn check_plan(store: &Store) -> Result<Option<(PlanSpec, i64)>, String> {
    let mut runs = store.list_runs().map_err(|e| e.to_string())?;
    runs.sort_by_key(|r| std::cmp::Reverse((r.created_us, r.id.0)));
    for r in runs.iter().filter(|r| r.state == RunState::Finished) {
        let Ok(plan) = serde_json::from_value::<Plan>(r.plan.clone()) else {
            continue;
        };
        if plan.spec.runs >= FULL_RUNS {
            let spec = PlanSpec {
                runs: CHECK_RUNS,
                ..plan.spec
            };
            return Ok(Some((spec, r.id.0)));
        }
    }
    Ok(None)
}

/// What a check that is no longer running came to: from its stored state, its open flags and
/// the axis's trends.
pub fn judge(store: &Store, run: i64, acceptance: &AcceptanceSettings) -> (CheckResult, String) {
    let rec = match store.run(RunId(run)) {
        Ok(r) => r,
        Err(e) => {
            return (
                CheckResult::Failed,
                format!("run {run} cannot be read: {e}"),
            );
        }
    };
    if rec.state != RunState::Finished {
        return (
            CheckResult::Failed,
            format!("run {run} ended {}", rec.state.as_str()),
        );
    }
    let open = store
        .capture_flags(RunId(run))
        .map(|f| f.iter().filter(|f| f.open()).count())
        .unwrap_or(0);
    if open > 0 {
        return (
            CheckResult::Flags,
            format!("run {run} ended with {open} flagged captures open"),
        );
    }
    let trends = match AxisTrends::read(store, &rec.axis, acceptance, &Default::default()) {
        Ok(t) => t,
        Err(e) => return (CheckResult::Failed, format!("run {run}'s trends: {e}")),
    };
    match trends.verdict(run) {
        Verdict::InControl => (
            CheckResult::InControl,
            format!(
                "run {run}: every figure of axis {} within its limits",
                rec.axis
            ),
        ),
        Verdict::Learning => (
            CheckResult::Learning,
            format!(
                "run {run}: {} runs of axis {} under these tables, too few for control limits yet",
                trends.runs.ids.len(),
                rec.axis
            ),
        ),
        Verdict::Drift(f) => {
            let said: Vec<String> = f
                .iter()
                .map(|(label, r)| format!("{label} ({})", r.words()))
                .collect();
            // A drift no table reaches is a maintenance alarm; one a table reaches, a
            // composed table to propose.
            let result = if f.iter().all(|(_, r)| *r == Remedy::Table) {
                CheckResult::Drift
            } else {
                CheckResult::Maintenance
            };
            (result, format!("run {run}: drift in {}", said.join("; ")))
        }
        Verdict::Tolerance(f) => (
            CheckResult::Tolerance,
            format!("run {run}: beyond tolerance: {}", f.join(", ")),
        ),
        Verdict::NotTrended => (
            CheckResult::Failed,
            format!("run {run} is not in axis {}'s trends", rec.axis),
        ),
    }
}

impl Checks {
    /// Read the PLC's check fields, each from its own register table.
    async fn read(&self, link: &Link) -> Result<Polled, String> {
        let mut img = Image::default();
        for f in Polled::reads(&self.fields) {
            let range = ReadRange::new(f.address, f.words()).map_err(|e| e.to_string())?;
            let v = link
                .read(f.kind, self.unit, range)
                .await
                .map_err(|e| e.to_string())?;
            img.put(f.kind, f.address, &v);
        }
        Ok(Polled::read(&self.fields, &img))
    }

    /// Send `request` to the service as the PLC and wait for the answer.
    async fn ask(&self, request: Request, plc_request: u32) -> Result<serde_json::Value, String> {
        let (tx, rx) = oneshot::channel();
        let peer = Peer {
            uid: 0,
            gid: 0,
            pid: None,
            user: format!("PLC check request {plc_request}"),
            role: Some(Role::Operator),
        };
        self.requests
            .send(Command {
                request,
                peer,
                reply: tx,
            })
            .await
            .map_err(|_| "the service is stopping".to_string())?;
        rx.await
            .map_err(|_| "the service dropped the request".to_string())?
    }

    /// Start the check for PLC request `n`: its run's id, or the result that refuses it.
    async fn start(&self, n: u32) -> Result<u32, CheckResult> {
        let path = self.store_path.clone();
        let plan = tokio::task::spawn_blocking(move || {
            Store::open(&path)
                .map_err(|e| e.to_string())
                .and_then(|s| check_plan(&s))
        })
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r);
        let (spec, from) = match plan {
            Ok(Some(p)) => p,
            Ok(None) => {
                tracing::warn!(
                    request = n,
                    "PLC check request refused: no finished run of {FULL_RUNS} runs or more to take the check's targets from; measure the axis first"
                );
                return Err(CheckResult::NoPlan);
            }
            Err(e) => {
                tracing::warn!(request = n, "PLC check request refused: the store: {e}");
                return Err(CheckResult::NotStarted);
            }
        };
        let notes = format!(
            "short check requested by the PLC (request {n}): the targets of run {from}, {CHECK_RUNS} bidirectional runs"
        );
        let axis = spec.axis.clone();
        let req = Request::RunStart {
            plan: spec,
            dialect: None,
            notes: Some(notes),
        };
        match self.ask(req, n).await {
            Ok(v) => {
                let run = v["run_id"].as_u64().and_then(|r| u32::try_from(r).ok());
                tracing::info!(request = n, run = run.unwrap_or(0), axis = %axis, "PLC check request: the check runs");
                Ok(run.unwrap_or(0))
            }
            Err(why) => {
                tracing::warn!(
                    request = n,
                    "PLC check request refused by the service: {why}"
                );
                Err(CheckResult::NotStarted)
            }
        }
    }

    /// The id of the run under way, when one is.
    async fn running(&self, n: u32) -> Option<i64> {
        let v = self.ask(Request::RunStatus, n).await.ok()?;
        (v["state"] == "running")
            .then(|| v["run_id"].as_i64().unwrap_or(0))
            .filter(|id| *id > 0)
    }

    /// What run `run` came to, once it no longer runs.
    async fn outcome(&self, run: u32) -> (CheckResult, String) {
        let path = self.store_path.clone();
        let acceptance = self.acceptance.clone();
        tokio::task::spawn_blocking(move || match Store::open(&path) {
            Ok(s) => judge(&s, i64::from(run), &acceptance),
            Err(e) => (CheckResult::Failed, format!("the store: {e}")),
        })
        .await
        .unwrap_or_else(|e| (CheckResult::Failed, e.to_string()))
    }

    /// Serve the handshake until the shutdown.
    pub async fn run(self, mut shutdown: Shutdown) {
        let link = Link::spawn(self.push.link.clone());
        let mut h = CheckHandshake::new(std::time::Instant::now(), READ_EVERY);
        let mut link_said = false;
        loop {
            let due = h.poll_timeout();
            let wait = due.saturating_duration_since(std::time::Instant::now());
            tokio::select! {
                _ = shutdown.recv() => break,
                _ = tokio::time::sleep_until(Instant::now() + wait) => {}
            }
            let now = std::time::Instant::now();
            match self.read(&link).await {
                Err(e) => {
                    if !link_said {
                        tracing::warn!(
                            "PLC check fields cannot be read at {}: {e}; read again every second",
                            link.addr()
                        );
                        link_said = true;
                    }
                    h.read_failed(now);
                }
                Ok(p) => {
                    link_said = false;
                    match h.handle_read(now, p) {
                        Next::Nothing => {}
                        Next::Start(n) => {
                            self.write_answers(&link, &mut h).await;
                            match self.start(n).await {
                                Ok(run) => h.started(n, run),
                                Err(r) => h.ended(n, r),
                            }
                        }
                        Next::Resume(n) => match self.running(n).await {
                            Some(id) => {
                                tracing::info!(
                                    request = n,
                                    run = id,
                                    "PLC check request answered busy before a restart: watching its run"
                                );
                                h.started(n, u32::try_from(id).unwrap_or(0));
                            }
                            None => h.ended(n, CheckResult::Interrupted),
                        },
                    }
                }
            }
            if let Some((n, run)) = h.current()
                && run != 0
                && self.running(n).await.is_none_or(|id| id != i64::from(run))
            {
                let (result, why) = self.outcome(run).await;
                tracing::info!(
                    request = n,
                    run,
                    code = result.code(),
                    "PLC check request done: {why}"
                );
                h.ended(n, result);
            }
            self.write_answers(&link, &mut h).await;
        }
    }

    /// Write the answers due, each field in order; one that fails is offered again.
    async fn write_answers(&self, link: &Link, h: &mut CheckHandshake) {
        while let Some(a) = h.poll_write() {
            let writes = match a.writes(&self.fields) {
                Ok(w) => w,
                Err(e) => {
                    tracing::warn!("PLC check answer cannot be encoded: {e}");
                    continue;
                }
            };
            for (address, regs) in writes {
                if let Err(e) = link
                    .write_multiple_registers(self.unit, address, &regs)
                    .await
                {
                    tracing::warn!(
                        "PLC check answer not written at {}: {e}; written again at the next read",
                        link.addr()
                    );
                    h.write_failed(a);
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_check_takes_the_newest_full_runs_plan_with_two_runs() {
        let dir = std::env::temp_dir().join(format!("axiscomp-checks-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("s.db");
        let _ = std::fs::remove_file(&path);
        let mut store = Store::open(&path).expect("store");
        assert_eq!(check_plan(&store).expect("reads"), None);
        let spec = |runs: u32| PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 200.0,
            targets: 6,
            runs,
            overrun_mm: 2.0,
            dwell_s: 1.5,
            feed_mm_min: 3000.0,
            lead_mm: 10.0,
            reference_mm: None,
        };
        let full = Plan::new(spec(5)).expect("plan");
        let mut add = |p: &Plan, state: RunState| {
            let id = store
                .create_run(&crate::store::NewRun {
                    axis: "X".into(),
                    plan: serde_json::to_value(p).expect("json"),
                    config: serde_json::json!({}),
                    calibration: None,
                    notes: String::new(),
                })
                .expect("run");
            store.set_run_state(id, RunState::Running).expect("running");
            store.set_run_state(id, state).expect("state");
            id
        };
        let first = add(&full, RunState::Finished);
        // A check (two runs) and a failed full run after it are not what a check is taken from.
        add(&Plan::new(spec(2)).expect("plan"), RunState::Finished);
        add(&full, RunState::Failed);
        let (s, from) = check_plan(&store).expect("reads").expect("a plan");
        assert_eq!(from, first.0);
        assert_eq!(s.runs, CHECK_RUNS);
        assert_eq!(Plan::new(s).expect("plan").targets, full.targets);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
