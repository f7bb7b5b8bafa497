//! The follower's stop-and-go self-calibration on the virtual-time lab, through the lab's
//! public interface only (the carriage, the clock, the service's tracker).
//!
//! The carriage steps `step_mm` at a time over the span and rests; the tracker (overlap
//! strategy, `average_frames` per side) hands over while the spot is fixed in space; each
//! handover's optical displacement, along and vertical, with its variance, is read from the
//! stitch's increments and becomes a [`Step`] of the follower from the encoder position
//! before to the one after. Passes alternate up and down; every `probe_every` stops the
//! carriage steps back and forth once, so the follower reverses (the reversal error) all
//! along the travel. The steps feed `follower::build`.

use super::lab::{Lab, LabError};
use crate::follower::Step;
use crate::track::Strategy;
use std::time::Duration;

/// How the self-calibration runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalSpec {
    /// The carriage's span (mm).
    pub from_mm: f64,
    pub to_mm: f64,
    /// The carriage's step (mm): under PSD2's half-width (4.5 mm) less a margin, and not a
    /// whole number of screw leads.
    pub step_mm: f64,
    /// Passes over the span, alternately up and down.
    pub passes: usize,
    /// Frames averaged on each side of a handover.
    pub average_frames: usize,
    /// A back-and-forth probe every this many stops (0: none).
    pub probe_every: usize,
}

impl Default for CalSpec {
    fn default() -> Self {
        CalSpec {
            from_mm: 0.0,
            to_mm: 1000.0,
            step_mm: 3.75,
            passes: 4,
            average_frames: 1000,
            probe_every: 13,
        }
    }
}

/// What the self-calibration gave.
#[derive(Clone, Debug, PartialEq)]
pub struct CalRun {
    pub steps: Vec<Step>,
    /// Stops whose displacement was not optical (the follower followed by its encoder): left
    /// out.
    pub skipped: usize,
    /// Machine time it took.
    pub machine_time: Duration,
}

/// An overlap step's variance is a few nm²; an encoder step's at least the encoder's (1 µm)².
const OPTICAL_VAR_LIMIT: f64 = 1e-8;

/// Run the stop-and-go self-calibration on `lab` (brought up). The tracker's settings are
/// restored afterwards; its stitch has moved on by the follower's steps (take the zero
/// again). `progress` hears (stop, stops) now and then.
pub fn self_calibrate(
    lab: &mut Lab,
    spec: &CalSpec,
    mut progress: impl FnMut(usize, usize),
) -> Result<CalRun, LabError> {
    let bad = |why: String| LabError::Setup(super::SimError::Input(why));
    if !(spec.step_mm > 0.5 && spec.step_mm <= 4.0) || spec.to_mm <= spec.from_mm + spec.step_mm {
        return Err(bad(format!(
            "self-calibration: a step of {} mm over {} to {} mm: give a step of 0.5 to 4 mm and a span of several steps",
            spec.step_mm, spec.from_mm, spec.to_mm
        )));
    }
    let saved = *lab.pipeline.tracker.settings();
    let mut s = saved;
    s.strategy = Strategy::Overlap;
    s.average_frames = spec.average_frames.max(10);
    s.edge_mm = s.edge_mm.max(spec.step_mm + 0.45);
    s.handover_mm = s.handover_mm.min(spec.step_mm * 0.5);
    lab.pipeline.tracker.set_settings(s);
    let result = passes(lab, spec, &mut progress);
    lab.pipeline.tracker.set_settings(saved);
    result
}

fn passes(
    lab: &mut Lab,
    spec: &CalSpec,
    progress: &mut impl FnMut(usize, usize),
) -> Result<CalRun, LabError> {
    let started = lab.now();
    let n = ((spec.to_mm - spec.from_mm) / spec.step_mm).floor() as usize;
    let mut targets = Vec::new();
    for p in 0..spec.passes {
        for k in 1..=n {
            let (x, back) = if p % 2 == 0 {
                let x = spec.from_mm + k as f64 * spec.step_mm;
                (x, x - spec.step_mm)
            } else {
                let x = spec.from_mm + (n - k) as f64 * spec.step_mm;
                (x, x + spec.step_mm)
            };
            targets.push(x);
            if spec.probe_every > 0 && k % spec.probe_every == 0 && k < n {
                targets.push(back);
                targets.push(x);
            }
        }
    }
    // To the start, followed by the encoder; then every stop a handover.
    lab.move_carriage(spec.from_mm)?;
    settle(lab)?;
    let mut run = CalRun {
        steps: Vec::new(),
        skipped: 0,
        machine_time: Duration::ZERO,
    };
    for (i, &x) in targets.iter().enumerate() {
        let before = lab.pipeline.tracker.stitch();
        let from = encoder(lab)?;
        lab.move_carriage(x)?;
        let h = before.handovers;
        lab.advance_until(
            "a follower handover at rest",
            Duration::from_secs(60),
            |lab| {
                let t = &lab.pipeline.tracker;
                t.stitch().handovers > h && !t.handing_over()
            },
        )?;
        settle(lab)?;
        let after = lab.pipeline.tracker.stitch();
        let to = encoder(lab)?;
        let var = [
            after.variance[0] - before.variance[0],
            after.variance[1] - before.variance[1],
        ];
        if var[0] > OPTICAL_VAR_LIMIT || to == from {
            run.skipped += 1;
        } else {
            run.steps.push(Step {
                from_mm: from,
                to_mm: to,
                along_mm: after.follower_mm - before.follower_mm,
                vertical_mm: after.vertical_mm - before.vertical_mm,
                variance: var,
            });
        }
        if i % 20 == 0 {
            progress(i, targets.len());
        }
    }
    run.machine_time = lab.now() - started;
    Ok(run)
}

/// Wait until no handover is under way or about to start (the spot centred, at rest).
fn settle(lab: &mut Lab) -> Result<(), LabError> {
    let edge = lab.pipeline.tracker.settings().handover_mm;
    lab.advance_until("the follower at rest", Duration::from_secs(60), |lab| {
        let t = &lab.pipeline.tracker;
        !t.handing_over()
            && t.at_rest(lab.now())
            && lab
                .pipeline
                .last_frame
                .and_then(|f| f.spots[1])
                .is_some_and(|s| s.x.abs() < edge)
    })
}

fn encoder(lab: &Lab) -> Result<f64, LabError> {
    lab.drive_status()
        .position_mm
        .ok_or_else(|| LabError::BringUp {
            what: "self-calibration",
            why: "the follower's position is not known".into(),
        })
}

/// Why mapping the twin's follower failed.
#[derive(Debug, thiserror::Error)]
pub enum MapTwinError {
    #[error(transparent)]
    Lab(#[from] LabError),
    #[error(transparent)]
    Map(#[from] crate::follower::MapError),
}

/// What mapping the twin's follower gave.
#[derive(Debug)]
pub struct TwinMap {
    pub map: crate::follower::FollowerMap,
    pub run: CalRun,
    /// The twin's certificate (CSV) when it was the one used.
    pub certificate_text: Option<String>,
}

/// Map the follower of a twin (`plant`, the reference head decoupled by its nominal layout):
/// bring the lab up, run the self-calibration over `cal`'s span, and build the map with
/// `certificate`, or with the twin's own certificate (its noise drawn from `plant.seed`) when
/// `None`.
pub fn map_twin(
    plant: super::plant::PlantSpec,
    cal: &CalSpec,
    certificate: Option<crate::follower::Certificate>,
    settings: &crate::follower::MapSettings,
    progress: impl FnMut(usize, usize),
) -> Result<TwinMap, MapTwinError> {
    let seed = plant.seed;
    let spec = super::lab::LabSpec::standard(plant, None)?;
    let mut lab = Lab::new(&spec)?;
    lab.bring_up()?;
    let run = self_calibrate(&mut lab, cal, progress)?;
    let (certificate, certificate_text) = match certificate {
        Some(c) => (c, None),
        None => {
            let text = lab
                .plant
                .follower
                .certificate(&mut super::Rng::new(seed).fork(16));
            let c = crate::follower::Certificate::parse(&text, "twin-certificate.csv")
                .map_err(crate::follower::MapError::from)?;
            (c, Some(text))
        }
    };
    let mut map = crate::follower::build(&run.steps, Some(&certificate), settings)?;
    if let Some(s) = map.self_calibration.as_mut() {
        s.machine_time_s = Some(run.machine_time.as_secs_f64());
    }
    Ok(TwinMap {
        map,
        run,
        certificate_text,
    })
}
