//! Calibrating the head from the service (the console's Calibrate screen).
//!
//! A pose set — the CSV `axiscomp calibrate simulate` writes, or a hexapod run exported in
//! that format (poses and the six readings at each) — on the service's host is fitted on a
//! blocking thread (the model fit takes from tenths of a second to seconds). The result waits
//! as *pending* for the operator to judge by its residuals, condition number and hold-out
//! errors; accepting stores it and switches the live decoupler to it (the zero reference is
//! cleared: it belongs to the old decoupling); rejecting drops it. No hexapod is driven from
//! here: the poses come from the file.

use crate::calibrate::plausible::{self, Limits};
use crate::calibrate::{self, CalError, CalibrateOptions, Calibration, CalibrationFile};
use crate::decouple::Decoupler;
use crate::evaluate::recorded::{RecordedCalibration, Stated};
use crate::optics::Layout;
use crate::store::CalibrationId;
use crate::units::{DOF_TO_USER, Errors6};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a fit did not give a calibration.
#[derive(Debug, Error)]
pub enum CalibrationError {
    #[error(
        "pose set {path}: cannot read it ({source}); give a path on the service's host that \
         the service user can read"
    )]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("pose set {path}: {source}")]
    Fit {
        path: String,
        #[source]
        source: CalError,
    },
    #[error("the fit's thread ended abnormally: {0}")]
    Thread(String),
}

/// A fitted calibration waiting for the operator.
#[derive(Clone, Debug)]
pub struct Pending {
    pub calibration: Calibration,
    pub decoupler: Decoupler,
    pub summary: Summary,
}

/// What the operator judges a calibration by (readings in µm, DOFs in µm / arcsec); the
/// `calibration` and `calibration_fit` replies, which the console reads back.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Summary {
    pub source: String,
    pub created: String,
    pub poses: usize,
    pub fit_poses: usize,
    pub holdout_poses: usize,
    pub travel_mm: (f64, f64),
    /// Per reading channel X1 Y1 X2 Y2 X3 Y3: the noise estimate and the residual RMS of the
    /// linear and (when fitted) the model fit.
    pub noise_um: [f64; 6],
    pub linear_residual_um: [f64; 6],
    pub model_residual_um: Option<[f64; 6]>,
    /// Rank of the linear fit (of 7) and the condition number of β.
    pub rank: usize,
    pub condition_number: f64,
    /// Hold-out RMS per DOF of the linear and the model fit.
    pub linear_holdout: Option<[f64; 6]>,
    pub model_holdout: Option<[f64; 6]>,
    /// The model fit: iterations, converged, parameters fitted and well determined.
    pub model_iterations: Option<u32>,
    pub model_converged: Option<bool>,
    pub model_params: Option<(usize, usize)>,
    /// The decoupling accepting it gives: "model" or "linear".
    pub decoupling: String,
    /// What the calibration reads from the head's spots when it was judged (µm / arcsec).
    pub here: Option<[f64; 6]>,
    /// Why it looks implausible for this head (`calibrate::plausible`); accepting it then
    /// needs the override.
    pub concerns: Vec<String>,
}

impl Summary {
    /// The summary of `c`, read from `source`.
    pub fn of(c: &Calibration, source: &str) -> Summary {
        let um = |v: [f64; 6]| v.map(|x| x * 1000.0);
        let user = |v: [f64; 6]| std::array::from_fn(|k| v[k] * DOF_TO_USER[k]);
        let m = c.model.as_ref();
        Summary {
            source: source.to_string(),
            created: c.created.clone(),
            poses: c.poses,
            fit_poses: c.fit_poses,
            holdout_poses: c.holdout_poses,
            travel_mm: c.travel_range,
            noise_um: um(c.sigma_mm),
            linear_residual_um: um(c.linear.residual_rms),
            model_residual_um: m.map(|m| um(m.residual_rms)),
            rank: c.linear.rank,
            condition_number: c.linear.condition_number,
            linear_holdout: c.linear_holdout_rms.map(user),
            model_holdout: m.and_then(|m| m.holdout_rms).map(user),
            model_iterations: m.map(|m| m.iterations),
            model_converged: m.map(|m| m.converged),
            model_params: m.map(|m| (m.fitted_params, m.well_determined)),
            decoupling: if m.is_some() { "model" } else { "linear" }.into(),
            here: None,
            concerns: Vec::new(),
        }
    }
}

/// Read and fit the pose set at `path` against `layout` (blocking: call off the event loop).
pub fn fit(path: &Path, layout: &Layout) -> Result<Pending, CalibrationError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| CalibrationError::Read {
        path: name.clone(),
        source,
    })?;
    let fit_err = |source| CalibrationError::Fit {
        path: name.clone(),
        source,
    };
    let samples = calibrate::parse_pose_csv(&text, &name).map_err(fit_err)?;
    let calibration = calibrate::calibrate(
        &samples,
        layout,
        &CalibrateOptions::default(),
        &mut |_, _| {},
    )
    .map_err(fit_err)?;
    let decoupler = calibration.decoupler(layout).map_err(fit_err)?;
    let summary = Summary::of(&calibration, &name);
    Ok(Pending {
        calibration,
        decoupler,
        summary,
    })
}

/// [`fit`] on Tokio's blocking pool.
pub async fn fit_async(path: PathBuf, layout: Layout) -> Result<Pending, CalibrationError> {
    tokio::task::spawn_blocking(move || fit(&path, &layout))
        .await
        .map_err(|e| CalibrationError::Thread(e.to_string()))?
}

/// The calibration file text of `c` (what the store keeps).
pub fn file_text(c: &Calibration, layout: &Layout) -> String {
    CalibrationFile::from_calibration(c, layout).to_toml()
}

fn no_pending() -> String {
    "no calibration is waiting: fit a pose set first".into()
}

/// The service's calibrations: the one in use and at most one waiting for the operator.
#[derive(Debug)]
pub struct Calibrations {
    layout: Layout,
    active_id: Option<CalibrationId>,
    active: Option<Summary>,
    /// The calibration in use's own term in a run's uncertainty budget.
    budget_term: Stated<RecordedCalibration>,
    pending: Option<Pending>,
    fitting: bool,
}

/// `c`'s own term in a run's uncertainty budget (`CalibrationFile::budget_term`), named by
/// `what` (its store id or file).
fn budget_term(
    c: &Calibration,
    layout: &Layout,
    id: Option<CalibrationId>,
    what: &str,
) -> Stated<RecordedCalibration> {
    match CalibrationFile::from_calibration(c, layout).budget_term() {
        Ok(t) => Stated::Stated(RecordedCalibration {
            id: id.map(|i| i.0),
            u_um_arcsec: t.u,
            source: format!("{what} (made {}): {}", c.created, t.words()),
        }),
        Err(why) => Stated::NotStated(format!("{what}: {why}")),
    }
}

impl Calibrations {
    /// In use: `configured` (the configuration's file, `source`), or the nominal layout.
    pub fn new(layout: Layout, configured: Option<&Calibration>, source: &str) -> Calibrations {
        let budget_term = match configured {
            Some(c) => budget_term(
                c,
                &layout,
                None,
                &format!("the configured calibration {source}"),
            ),
            None => Stated::NotStated(
                "no calibration: the head decouples with its layout's nominal model, whose own \
                 error is not known"
                    .into(),
            ),
        };
        Calibrations {
            layout,
            active_id: None,
            active: configured.map(|c| Summary::of(c, source)),
            budget_term,
            pending: None,
            fitting: false,
        }
    }

    /// The layout fits are made against.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// The stored calibration in use, when it came from the store.
    pub fn active_id(&self) -> Option<CalibrationId> {
        self.active_id
    }

    /// The calibration in use's own term in a run's uncertainty budget, or why there is none.
    pub fn budget_term(&self) -> &Stated<RecordedCalibration> {
        &self.budget_term
    }

    /// A fit may start (one at a time).
    pub fn begin_fit(&mut self) -> Result<(), String> {
        if self.fitting {
            return Err("a calibration fit is already running; wait for its result".into());
        }
        self.fitting = true;
        Ok(())
    }

    /// A fit ended: its result becomes the pending calibration (replacing an older one),
    /// judged with `read_here` (what a decoupler reads from the head's current spots).
    pub fn fitted(
        &mut self,
        r: Result<Pending, CalibrationError>,
        read_here: impl Fn(&Decoupler) -> Option<Errors6>,
    ) -> Result<serde_json::Value, String> {
        self.fitting = false;
        let mut p = r.map_err(|e| e.to_string())?;
        self.judge(&mut p, &read_here);
        let v = serde_json::json!({ "pending": p.summary });
        self.pending = Some(p);
        Ok(v)
    }

    fn judge(&self, p: &mut Pending, read_here: &impl Fn(&Decoupler) -> Option<Errors6>) {
        let here = read_here(&p.decoupler);
        p.summary.here = here.map(Errors6::to_user);
        p.summary.concerns = plausible::concerns(
            &p.calibration,
            &self.layout,
            here.as_ref(),
            &Limits::default(),
        );
    }

    /// The pending calibration, judged again on the head's current spots, to accept: refused
    /// (it keeps waiting) when it has concerns and `force` is not set.
    pub fn take_for_accept(
        &mut self,
        force: bool,
        read_here: impl Fn(&Decoupler) -> Option<Errors6>,
    ) -> Result<Pending, String> {
        let mut p = self.pending.take().ok_or_else(no_pending)?;
        self.judge(&mut p, &read_here);
        if !force && !p.summary.concerns.is_empty() {
            let why = p.summary.concerns.join("; ");
            self.pending = Some(p);
            return Err(format!(
                "the calibration was not accepted (it still waits): {why}. Reject it and fit a pose set of this head, or accept it anyway with the override (console: A; control: {{\"cmd\":\"calibration_accept\",\"force\":true}})"
            ));
        }
        Ok(p)
    }

    /// Put a calibration taken for accepting back (it could not be stored).
    pub fn restore_pending(&mut self, p: Pending) {
        self.pending = Some(p);
    }

    /// The pending calibration.
    pub fn pending(&self) -> Result<&Pending, String> {
        self.pending.as_ref().ok_or_else(no_pending)
    }

    /// `p` was stored as `id` and is in use now.
    pub fn accepted(&mut self, id: CalibrationId, p: Pending) {
        self.budget_term = budget_term(
            &p.calibration,
            &self.layout,
            Some(id),
            &format!("calibration id {}", id.0),
        );
        self.active_id = Some(id);
        self.active = Some(p.summary);
    }

    /// Drop the pending calibration.
    pub fn reject(&mut self) -> Result<serde_json::Value, String> {
        match self.pending.take() {
            Some(p) => Ok(serde_json::json!({ "rejected": p.summary.source })),
            None => Err("no calibration is waiting to be rejected".into()),
        }
    }

    /// What is in use, what waits, whether a fit runs.
    pub fn status(&self) -> serde_json::Value {
        serde_json::json!({
            "active": self.active,
            "active_id": self.active_id.map(|i| i.0),
            "pending": self.pending.as_ref().map(|p| &p.summary),
            "fitting": self.fitting,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::write_pose_csv;
    use crate::sim::{Hexapod, InstallSpec, PoseWindow, Rng, TwinHead};
    use crate::util::progress::Progress;

    #[test]
    fn a_twin_pose_set_fits_and_a_bad_path_is_named() {
        let layout = Layout::reference();
        let rng = Rng::new(4);
        let head =
            TwinHead::random(&layout, &InstallSpec::default(), 1e-3, &mut rng.fork(1)).unwrap();
        let poses = PoseWindow::default().draw(60, &mut rng.fork(2));
        let (samples, _) =
            Hexapod::default().acquire(&head, &poses, &mut rng.fork(3), &mut Progress::hidden());
        let dir = std::env::temp_dir().join(format!("axiscomp-cal-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("poses.csv");
        std::fs::write(&path, write_pose_csv(&samples, &[])).unwrap();
        let p = fit(&path, &layout).unwrap();
        assert_eq!(p.summary.poses, samples.len());
        assert_eq!(p.summary.rank, 7);
        assert_eq!(p.summary.decoupling, "model");
        // The model fit's residuals are at the noise (1 µm), the linear fit's far above it.
        let m = p.summary.model_residual_um.unwrap();
        assert!(m.iter().all(|r| *r > 0.5 && *r < 2.0), "{m:?}");
        // The stored text parses back.
        let text = file_text(&p.calibration, &layout);
        assert!(CalibrationFile::parse(&text, "t").is_ok());

        let missing = dir.join("nope.csv");
        let e = fit(&missing, &layout).unwrap_err().to_string();
        assert!(e.contains("nope.csv") && e.contains("cannot read"), "{e}");
        std::fs::write(&path, "travel_mm,garbage\n1,2\n").unwrap();
        let e = fit(&path, &layout).unwrap_err().to_string();
        assert!(e.contains("poses.csv"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
