//! The core's own requests: the zero reference and the nominal, the stitching strategy, the
//! follower (moves and the error map in use), the head's calibration, and what the store
//! holds (runs, a run's result, the audit log: read off the loop, answered from there).

use super::Core;
use crate::service::api::Request;
use crate::service::procedure::{Reply, Who};
use crate::store::{QueueError, Store};
use std::path::PathBuf;
use std::sync::Arc;

impl Core {
    pub(super) fn own_request(&mut self, req: Request, who: &Who, reply: Reply) {
        match req {
            Request::Status | Request::Subscribe { .. } => {
                reply.send(Err("status and subscribe are answered by the socket".into()))
            }
            Request::TableList { .. }
            | Request::TableGenerate { .. }
            | Request::TablePublish { .. }
            | Request::TableStatus => reply.send(Err(
                "internal: table requests are answered by the tables task".into(),
            )),
            Request::Nominal { mm } => {
                if mm.is_some_and(|x| !x.is_finite()) {
                    return reply.send(Err("nominal must be a finite number of mm or null".into()));
                }
                if self.pipeline.run_progress().is_some() {
                    return reply.send(Err("a run is under way: it sets the nominal".into()));
                }
                self.pipeline.measure.set_nominal(mm);
                reply.send(Ok(serde_json::json!({"nominal_mm": mm})));
            }
            Request::Strategy { strategy } => {
                self.pipeline.tracker.set_strategy(strategy);
                reply.send(Ok(serde_json::json!({"strategy": strategy})));
            }
            Request::ClearZero => {
                self.pipeline.measure.clear_zero();
                reply.send(Ok(serde_json::json!({"zeroed": false})));
            }
            Request::Zero => {
                if !self.pipeline.begin_zero(
                    crate::util::clock::now(),
                    self.env.settings.head.zero_window,
                ) {
                    return reply.send(Err(
                        "the follower's position is not known yet: is the drive up?".into(),
                    ));
                }
                // A zero asked for again answers the one before with this one.
                if let Some(old) = self.zero_reply.replace(reply) {
                    old.send(Err("a newer zero request replaced this one".into()));
                }
            }
            Request::FollowerMap { id } => self.follower_map_request(id, reply),
            Request::FollowerCertificate(req) => {
                self.store_then(move |s| crate::service::follower::import_on(s, req), reply)
            }
            Request::Runs { limit } => self.read(
                move |s| {
                    crate::service::results::runs(s, limit.unwrap_or(50))
                        .map(|v| serde_json::json!({ "runs": v }))
                },
                reply,
            ),
            Request::Audit { limit } => self.read(
                move |s| {
                    crate::service::results::audit(s, limit.unwrap_or(50))
                        .map(|v| serde_json::json!({ "entries": v }))
                },
                reply,
            ),
            Request::RunResult { run_id } => self.read(
                move |s| {
                    crate::service::results::run_result(s, run_id).and_then(|r| {
                        serde_json::to_value(r).map_err(|e| format!("run result: {e}"))
                    })
                },
                reply,
            ),
            Request::RunFlags { run_id } => self.read(
                move |s| {
                    let run = crate::store::RunId(run_id);
                    s.run(run).map_err(|e| e.to_string())?;
                    let flags = s.capture_flags(run).map_err(|e| e.to_string())?;
                    let events = s.run_events(run).map_err(|e| e.to_string())?;
                    let restated = s.restatements(run).map_err(|e| e.to_string())?;
                    Ok(serde_json::json!({
                        "run_id": run_id,
                        "flags": flags.iter().map(crate::service::results::flag_view).collect::<Vec<_>>(),
                        "events": events,
                        "restated": restated,
                    }))
                },
                reply,
            ),
            Request::RunExclude {
                run_id,
                flag,
                reason,
            } => {
                let user = who.user.clone();
                match self.store.try_call(move |s| {
                    s.exclude_flag(
                        crate::store::RunId(run_id),
                        flag,
                        &user,
                        &reason,
                        crate::util::clock::unix_us(),
                    )
                    .map_err(|e| e.to_string())?;
                    Ok(serde_json::json!({
                        "run_id": run_id,
                        "excluded": flag,
                        "open": s.open_flags(crate::store::RunId(run_id)).map_err(|e| e.to_string())?,
                    }))
                }) {
                    Ok(done) => {
                        tokio::spawn(async move {
                            reply.send(match done.await {
                                Ok(r) => r,
                                Err(e) => Err(e.to_string()),
                            })
                        });
                    }
                    Err(e) => reply.send(Err(e.to_string())),
                }
            }
            Request::Trend { axis } => {
                let acceptance = self.env.settings.acceptance.clone();
                self.read(
                    move |s| {
                        use crate::service::trends::AxisTrends;
                        let axis = match axis {
                            Some(a) => a,
                            None => AxisTrends::newest_axis(s)?.ok_or(
                                "no finished run in the store to trend: measure an axis first",
                            )?,
                        };
                        AxisTrends::read(s, &axis, &acceptance, &Default::default())
                            .map(|t| t.to_json())
                    },
                    reply,
                )
            }
            Request::Machines => self.read(
                |s| {
                    crate::service::machine::list(s).map(|v| serde_json::json!({ "machines": v }))
                },
                reply,
            ),
            Request::Machine { id } => self.read(
                move |s| json(crate::service::machine::view(s, id)?),
                reply,
            ),
            Request::MachineNew {
                record,
                path,
                origin,
            } => self.read(
                move |s| {
                    let (record, origin) = match path {
                        Some(p) => (
                            crate::service::machine::read_record(&p)?,
                            origin.unwrap_or(p),
                        ),
                        None => (
                            record,
                            origin.unwrap_or_else(|| "sent to the service".into()),
                        ),
                    };
                    json(crate::service::machine::create(s, &record, &origin)?)
                },
                reply,
            ),
            Request::MachineAttach { id, setup, run_id } => self.read(
                move |s| json(crate::service::machine::attach(s, id, setup, run_id)?),
                reply,
            ),
            Request::MachineDetach { id, setup } => self.read(
                move |s| json(crate::service::machine::detach(s, id, setup)?),
                reply,
            ),
            Request::Calibration => reply.send(Ok(self.calibrations.status())),
            Request::CalibrationFit { poses } => self.calibration_fit(poses, reply),
            Request::CalibrationAccept { force } => self.calibration_accept(force, reply),
            Request::CalibrationReject => reply.send(self.calibrations.reject()),
            Request::Follower { action, mm } => self.follower_request(action, mm, who, reply),
            // Every other request is a procedure's.
            other => {
                let v = serde_json::to_value(&other).unwrap_or_default();
                reply.send(Err(format!(
                    "internal: no one takes the request {}",
                    v["cmd"].as_str().unwrap_or("?")
                )))
            }
        }
    }

    /// A read of the store, answered from its queue (never on the loop).
    fn read(
        &self,
        f: impl FnOnce(&mut Store) -> Result<serde_json::Value, String> + Send + 'static,
        reply: Reply,
    ) {
        let store = self.store.clone();
        tokio::spawn(async move {
            reply.send(match store.call(f).await {
                Ok(r) => r,
                Err(e) => Err(e.to_string()),
            });
        });
    }

    /// Work on the store that changes the follower map in use: once done, the map (when one
    /// is now in use) goes to the tracker, the cache and the snapshot, and the answer out.
    fn store_then(
        &mut self,
        f: impl FnOnce(
            &mut Store,
        )
            -> Result<(serde_json::Value, Option<crate::store::FollowerMapRecord>), String>
        + Send
        + 'static,
        reply: Reply,
    ) {
        match self.store.try_call(f) {
            Ok(done) => self.later(done, move |core, r| match flatten(r) {
                Ok((v, in_use)) => {
                    if let Some(rec) = in_use {
                        core.pipeline
                            .tracker
                            .set_map(Some(Arc::new(rec.map.clone())));
                        core.follower_map = Some(crate::service::follower::view(&rec));
                        core.cached.follower_map = Some(rec);
                    }
                    reply.send(Ok(v));
                }
                Err(e) => reply.send(Err(e)),
            }),
            Err(e) => reply.send(Err(e.to_string())),
        }
    }

    /// `follower_map`: the maps; with `id` (operators), stored map `id` put in use first.
    fn follower_map_request(&mut self, id: Option<i64>, reply: Reply) {
        self.store_then(move |s| crate::service::follower::request_on(s, id), reply);
    }

    /// Fit a pose set off the event loop; the reply goes out when the fit ends.
    fn calibration_fit(&mut self, poses: String, reply: Reply) {
        if let Some(h) = self.holder() {
            return reply.send(Err(h.busy("calibrate")));
        }
        if let Err(e) = self.calibrations.begin_fit() {
            return reply.send(Err(e));
        }
        let layout = self.calibrations.layout().clone();
        self.later(
            crate::service::calibration::fit_async(PathBuf::from(poses), layout),
            move |core, r| {
                let measure = &core.pipeline.measure;
                let v = core.calibrations.fitted(r, |d| measure.read_with(d));
                reply.send(v);
            },
        );
    }

    /// Store the waiting calibration and decouple with it (judged again on the current
    /// spots; with concerns only when `force`).
    fn calibration_accept(&mut self, force: bool, reply: Reply) {
        if let Some(h) = self.holder() {
            return reply.send(Err(
                h.busy("accept a calibration (a run's captures must keep one decoupling)")
            ));
        }
        let measure = &self.pipeline.measure;
        let p = match self
            .calibrations
            .take_for_accept(force, |d| measure.read_with(d))
        {
            Ok(p) => p,
            Err(e) => return reply.send(Err(e)),
        };
        let text =
            crate::service::calibration::file_text(&p.calibration, self.calibrations.layout());
        let job = self.store.try_call(move |s| s.insert_calibration(&text));
        let done = match job {
            Ok(d) => d,
            Err(e) => {
                self.calibrations.restore_pending(p);
                return reply.send(Err(format!(
                    "the calibration was not stored (it still waits): {e}"
                )));
            }
        };
        self.later(done, move |core, r| {
            let id = match flatten(r.map(|r| r.map_err(|e| e.to_string()))) {
                Ok(id) => id,
                Err(e) => {
                    core.calibrations.restore_pending(p);
                    return reply.send(Err(format!(
                        "the calibration was not stored (it still waits): {e}"
                    )));
                }
            };
            core.pipeline.measure.set_decoupler(p.decoupler.clone());
            let decoupling = p.summary.decoupling.clone();
            let overridden = p.summary.concerns.clone();
            if overridden.is_empty() {
                tracing::info!(calibration = id.0, %decoupling, "calibration accepted");
            } else {
                tracing::warn!(
                    calibration = id.0,
                    %decoupling,
                    concerns = %overridden.join("; "),
                    "calibration accepted over its concerns (override)"
                );
            }
            core.calibrations.accepted(id, p);
            core.pipeline
                .measure
                .set_calibration_u(core.calibrations.budget_term());
            reply.send(Ok(serde_json::json!({
                "calibration_id": id.0,
                "decoupling": decoupling,
                "overridden": overridden,
                "zero": "cleared: take the zero reference again",
            })));
        });
    }
}

/// A queued job's result and the job's own.
fn flatten<T>(r: Result<Result<T, String>, QueueError>) -> Result<T, String> {
    match r {
        Ok(r) => r,
        Err(e) => Err(e.to_string()),
    }
}

/// A view as the reply's JSON.
fn json(v: impl serde::Serialize) -> Result<serde_json::Value, String> {
    serde_json::to_value(v).map_err(|e| format!("internal: the reply does not serialise: {e}"))
}
