//! The follower's stop-and-go self-calibration on the virtual-time lab, through the lab's
//! public interface only (the carriage, the clock, the service's tracker).
//!
//! The plan and the collection are the product's own (`follower::selfcal`, which the service
//! runs as a part program): the carriage comes to the start through the lead-in point, then
//! steps over the span and rests; the tracker (overlap strategy, `average_frames` per side)
//! hands over while the spot is fixed in space; each stop's displacement, along and vertical,
//! with its variance, is read from the stitch's increments as the tracker's handover record
//! (the lab keeps the records to itself) and goes to the collector, which keeps the optical
//! steps for `follower::build`.

use super::lab::{Lab, LabError};
use crate::follower::selfcal::{Collector, Plan, Spec};
use crate::follower::{FollowerMap, Step, VerticalReference};
use crate::track::{HandoverKind, HandoverRecord};
use std::sync::Arc;
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
        let s = Spec::default();
        CalSpec {
            from_mm: s.from_mm,
            to_mm: s.to_mm,
            step_mm: s.step_mm,
            passes: s.passes,
            average_frames: 1000,
            probe_every: s.probe_every,
        }
    }
}

impl CalSpec {
    /// The procedure's plan of stops.
    pub fn spec(&self) -> Spec {
        Spec {
            from_mm: self.from_mm,
            to_mm: self.to_mm,
            step_mm: self.step_mm,
            passes: self.passes,
            probe_every: self.probe_every,
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
    let plan = Plan::new(spec.spec())
        .map_err(|e| LabError::Setup(super::SimError::Input(e.to_string())))?;
    let saved = *lab.pipeline.tracker.settings();
    let result = passes(lab, plan, spec.average_frames, &mut progress);
    lab.pipeline.tracker.set_settings(saved);
    result
}

fn passes(
    lab: &mut Lab,
    plan: Plan,
    average_frames: usize,
    progress: &mut impl FnMut(usize, usize),
) -> Result<CalRun, LabError> {
    let base = *lab.pipeline.tracker.settings();
    let mut c = Collector::new(plan, lab.now());
    // To the start through the lead-in point, followed as the tracker usually follows (in
    // the overlap strategy); then every stop a handover, with the procedure's settings.
    lab.pipeline
        .tracker
        .set_settings(c.tracking(&base, average_frames));
    for x in c.plan().approach() {
        lab.move_carriage(x)?;
        settle(lab)?;
    }
    c.arm();
    lab.pipeline
        .tracker
        .set_settings(c.tracking(&base, average_frames));
    let stops = c.plan().stops().to_vec();
    for (i, &x) in stops.iter().enumerate() {
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
        let variance = [
            after.variance[0] - before.variance[0],
            after.variance[1] - before.variance[1],
        ];
        c.handle_record(&HandoverRecord {
            unix_us: 0,
            kind: if variance[0] > OPTICAL_VAR_LIMIT {
                HandoverKind::Encoder
            } else {
                HandoverKind::Overlap
            },
            before: [0.0; 2],
            after: [0.0; 2],
            n_before: 0,
            n_after: 0,
            frame_sd: [0.0; 2],
            encoder_before: from,
            encoder_after: to,
            delta: [
                after.follower_mm - before.follower_mm,
                after.vertical_mm - before.vertical_mm,
            ],
            variance,
        });
        if i % 20 == 0 {
            progress(i, stops.len());
        }
    }
    Ok(CalRun {
        steps: c.steps().to_vec(),
        skipped: c.progress().skipped,
        machine_time: c.elapsed(lab.now()),
    })
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

/// The outside reference of the vertical map: a precision electronic level on the carriage,
/// read at stations along the span beside the head's roll. A level reads roll against
/// gravity, so at each station the difference of the head's roll and the level's is the
/// follower's vertical error there (1.38″ per µm) up to a constant: the stations fix the
/// map's line, which no handover can see, and pin the random walk of the steps between them.
/// The twin's level reads the axis' true roll with `sd_rad` of noise per reading (a level of
/// 1 µrad resolution and repeatability, 0.2″).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelSpec {
    /// Standard deviation of one reading (rad).
    pub sd_rad: f64,
    /// Readings at each station, each beside one window of the head's live roll.
    pub readings: usize,
    /// Stations at most this far apart over the span, both ends included (mm; at least 2
    /// stations).
    pub station_mm: f64,
}

impl Default for LevelSpec {
    fn default() -> Self {
        LevelSpec {
            sd_rad: 1e-6,
            readings: 20,
            station_mm: 100.0,
        }
    }
}

impl LevelSpec {
    /// The stations over `span` (mm): evenly spaced, both ends included.
    pub fn stations(&self, span: (f64, f64)) -> Vec<f64> {
        crate::follower::level::stations(span, self.station_mm)
    }
}

/// The head's roll minus the level's at one station (mean over the readings, rad), the
/// variance of that mean (rad², `follower::level::excess`: the head's noise and the level's,
/// not the stitch's: the map's error at the station is what is measured), and the encoder
/// there (mm).
struct StationReading {
    excess: f64,
    var_excess: f64,
    encoder: f64,
}

fn read_station(
    lab: &mut Lab,
    level: &LevelSpec,
    window: Duration,
    rng: &mut super::Rng,
) -> Result<StationReading, LabError> {
    let n = level.readings.max(2);
    let (mut head, mut read) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        // Each reading a fresh window of the head's live mean.
        lab.advance(window + Duration::from_millis(50))?;
        let live = lab
            .pipeline
            .measure
            .live()
            .ok_or_else(|| LabError::BringUp {
                what: "level reference",
                why: "the head gave no live roll".into(),
            })?;
        head.push(live.errors.ey);
        read.push(lab.truth().errors.ey + rng.gauss(level.sd_rad));
    }
    let (excess, var_excess) =
        crate::follower::level::excess(&head, &read, level.sd_rad).map_err(|e| {
            LabError::BringUp {
                what: "level reference",
                why: e.to_string(),
            }
        })?;
    Ok(StationReading {
        excess,
        var_excess,
        encoder: encoder(lab)?,
    })
}

/// The roll's sensitivity to PSD2's Y (rad per mm) where the head reads now, at carriage
/// position `travel_mm` (`follower::level::roll_per_y2`).
fn roll_per_y2(
    lab: &Lab,
    decoupler: &crate::decouple::Decoupler,
    travel_mm: f64,
) -> Result<f64, LabError> {
    let bad = |why: String| LabError::BringUp {
        what: "level reference",
        why,
    };
    let frame = lab
        .pipeline
        .last_frame
        .and_then(|f| f.readings())
        .ok_or_else(|| bad("no frame with all three spots".into()))?;
    let stitch = lab.pipeline.tracker.stitch();
    crate::follower::level::roll_per_y2(
        decoupler,
        &frame,
        travel_mm,
        stitch.follower_mm,
        stitch.vertical_mm,
    )
    .map_err(|e| bad(e.to_string()))
}

/// Read the level's stations over `span` (`LevelSpec`): with `map` applied in tracking (its
/// own reference left out), zero the head at the span's start and read its roll beside the
/// level's at every station. Each station gives the follower's true vertical there up to a
/// common constant: the map's vertical minus what the head read beyond the level, through the
/// roll's sensitivity to PSD2's Y (`decoupler`; `window` is the head's live window). The
/// tracker is left with `map` as it was.
pub fn reference_level(
    lab: &mut Lab,
    map: &FollowerMap,
    span: (f64, f64),
    level: &LevelSpec,
    decoupler: &crate::decouple::Decoupler,
    window: Duration,
) -> Result<VerticalReference, LabError> {
    let mut rng = super::Rng::new(lab.plant.spec.seed).fork(17);
    let mut free = map.clone();
    free.vertical_line = None;
    free.vertical_reference = None;
    let free = Arc::new(free);
    lab.pipeline.tracker.set_map(Some(free.clone()));
    let at = level.stations(span);
    let mut stations = Vec::with_capacity(at.len());
    let mut moved = 0.0f64;
    for (k, &x) in at.iter().enumerate() {
        lab.move_carriage(x)?;
        if k == 0 {
            lab.zero(x, window)?;
        }
        let r = read_station(lab, level, window, &mut rng)?;
        let g = roll_per_y2(lab, decoupler, x)?;
        let m = free.correction(r.encoder, crate::follower::Direction::Up)[1];
        moved = moved.max((x - at[0]).abs());
        stations.push(crate::follower::level::station(
            r.encoder,
            m,
            r.excess,
            r.var_excess,
            g,
        ));
    }
    lab.pipeline.tracker.set_map(Some(Arc::new(map.clone())));
    if stations.len() < 2 || moved < 1.0 {
        return Err(LabError::BringUp {
            what: "level reference",
            why: format!(
                "{} stations over {moved:.1} mm: the span is too short for a level's reference",
                stations.len()
            ),
        });
    }
    Ok(VerticalReference {
        source: format!(
            "a level ({:.2}″ a reading, {} readings at each of {} stations {:.0} to {:.0} mm)",
            level.sd_rad / crate::units::RAD_PER_ARCSEC,
            level.readings,
            stations.len(),
            span.0,
            span.1,
        ),
        stations,
    })
}

/// How to map a follower on the lab: the stop-and-go passes, the fit, the certificate (the
/// twin's own when `None`) and the level for the vertical line (none: the line is left out).
#[derive(Clone, Debug)]
pub struct Mapping {
    pub cal: CalSpec,
    pub settings: crate::follower::MapSettings,
    pub certificate: Option<crate::follower::Certificate>,
    pub level: Option<LevelSpec>,
    /// The instrument's map made on another set-up (issue 26): checked on this one by the
    /// level's stations and re-used, instead of the stop-and-go passes.
    pub reuse: Option<Box<TwinMap>>,
}

impl Mapping {
    /// The default procedure over `span` (mm): four passes of 1000 frames a side, the twin's
    /// certificate, the level.
    pub fn over(span: (f64, f64)) -> Mapping {
        Mapping {
            cal: CalSpec {
                from_mm: span.0,
                to_mm: span.1,
                ..CalSpec::default()
            },
            settings: crate::follower::MapSettings::default(),
            certificate: None,
            level: Some(LevelSpec::default()),
            reuse: None,
        }
    }
}

/// Map the follower of the lab's twin (brought up) and put the map in use in its tracker:
/// the self-calibration, the map from its steps and the certificate, the level's line.
/// `decoupler` and `window` as for [`reference_line`].
pub fn map_on_lab(
    lab: &mut Lab,
    m: &Mapping,
    decoupler: &crate::decouple::Decoupler,
    window: Duration,
    progress: impl FnMut(usize, usize),
) -> Result<TwinMap, MapTwinError> {
    if let Some(stored) = &m.reuse {
        let level = m.level.as_ref().ok_or(MapTwinError::NoLevel)?;
        let span = (m.cal.from_mm, m.cal.to_mm);
        return reuse_on_lab(lab, stored, span, level, decoupler, window);
    }
    let started = lab.now();
    let seed = lab.plant.spec.seed;
    let run = self_calibrate(lab, &m.cal, progress)?;
    let (certificate, certificate_text) = match &m.certificate {
        Some(c) => (c.clone(), None),
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
    let mut map = crate::follower::build(&run.steps, Some(&certificate), &m.settings)?;
    if let Some(level) = &m.level {
        // The level's stations read with the steps' map in tracking, then the vertical fitted
        // again with them.
        let span = (m.cal.from_mm, m.cal.to_mm);
        let reference = reference_level(lab, &map, span, level, decoupler, window)?;
        map = crate::follower::build_referenced(
            &run.steps,
            Some(&certificate),
            &m.settings,
            Some(&reference),
        )?;
    }
    let machine_time = lab.now() - started;
    if let Some(s) = map.self_calibration.as_mut() {
        s.machine_time_s = Some(machine_time.as_secs_f64());
    }
    lab.pipeline.tracker.set_map(Some(Arc::new(map.clone())));
    Ok(TwinMap {
        map,
        run,
        certificate,
        certificate_text,
        machine_time,
    })
}

/// Re-use the instrument's map `stored` (made on another set-up) on the lab's twin: with it
/// in tracking, the level's stations over `span` (carriage, mm), the check
/// (`follower::reuse`), and the map re-referenced by this set-up's bend put in use. The
/// machine time is the stations'.
pub fn reuse_on_lab(
    lab: &mut Lab,
    stored: &TwinMap,
    span: (f64, f64),
    level: &LevelSpec,
    decoupler: &crate::decouple::Decoupler,
    window: Duration,
) -> Result<TwinMap, MapTwinError> {
    let started = lab.now();
    let reference = reference_level(lab, &stored.map, span, level, decoupler, window)?;
    let (map, _) = crate::follower::reuse::reuse(
        &stored.map,
        &reference,
        &crate::follower::ReuseSettings::default(),
    )?;
    let machine_time = lab.now() - started;
    lab.pipeline.tracker.set_map(Some(Arc::new(map.clone())));
    Ok(TwinMap {
        map,
        run: CalRun {
            steps: Vec::new(),
            skipped: 0,
            machine_time: Duration::ZERO,
        },
        certificate: stored.certificate.clone(),
        certificate_text: stored.certificate_text.clone(),
        machine_time,
    })
}

/// Why mapping the twin's follower failed.
#[derive(Debug, thiserror::Error)]
pub enum MapTwinError {
    #[error(transparent)]
    Lab(#[from] LabError),
    #[error(transparent)]
    Map(#[from] crate::follower::MapError),
    #[error("the instrument's stored map cannot be used on this set-up: {0}")]
    Reuse(#[from] crate::follower::ReuseError),
    #[error("re-using a stored map needs a level for its check on this set-up")]
    NoLevel,
}

/// What mapping the twin's follower gave.
#[derive(Clone, Debug)]
pub struct TwinMap {
    pub map: crate::follower::FollowerMap,
    pub run: CalRun,
    /// The certificate the map was built with (kept with it in the store).
    pub certificate: crate::follower::Certificate,
    /// The twin's certificate (CSV) when it was the one used.
    pub certificate_text: Option<String>,
    /// Machine time of the whole mapping (passes and level).
    pub machine_time: Duration,
}

/// Map the follower of a twin (`plant`, the reference head decoupled by its nominal layout):
/// bring the lab up and run [`map_on_lab`] over `cal`'s span, with `certificate`, or with
/// the twin's own certificate (its noise drawn from `plant.seed`) when `None`, and the level
/// when `level` is given.
pub fn map_twin(
    plant: super::plant::PlantSpec,
    cal: &CalSpec,
    certificate: Option<crate::follower::Certificate>,
    settings: &crate::follower::MapSettings,
    level: Option<LevelSpec>,
    progress: impl FnMut(usize, usize),
) -> Result<TwinMap, MapTwinError> {
    let spec = super::lab::LabSpec::standard(plant, None)?;
    let mut lab = Lab::new(&spec)?;
    lab.bring_up()?;
    let m = Mapping {
        cal: *cal,
        settings: *settings,
        certificate,
        level,
        reuse: None,
    };
    map_on_lab(&mut lab, &m, &spec.decoupler, spec.live_window, progress)
}

/// The plant seed of an instrument's own bench (its bend there drawn from it).
const BENCH_SEED: u64 = 0x00be_7c4a;

/// Map an instrument once on its own bench (issue 26), as its maker or the first machine
/// would: the follower `follower` (with its `instrument_seed`) set up on a bench of
/// `length_mm`, aligned, with the reference head set to its nominal layout (no installation
/// errors: the nominal decoupling is exact); the whole mapping
/// ([`map_twin`]: the passes of `cal`, the certificate, the level). The machine's own set-up
/// then only checks it ([`reuse_on_lab`]).
pub fn map_instrument(
    follower: super::follower::FollowerSpec,
    length_mm: f64,
    cal: &CalSpec,
    progress: impl FnMut(usize, usize),
) -> Result<TwinMap, MapTwinError> {
    let plant = super::plant::PlantSpec {
        seed: BENCH_SEED ^ follower.instrument_seed.unwrap_or(0),
        axis: super::axis::AxisSpec {
            length_mm,
            ..super::axis::AxisSpec::default()
        },
        follower,
        install: super::InstallSpec {
            offset_mm: 0.0,
            tilt_deg: 0.0,
            gain_error: 0.0,
        },
        ..super::plant::PlantSpec::default()
    };
    map_twin(
        plant,
        cal,
        None,
        &crate::follower::MapSettings::default(),
        Some(LevelSpec::default()),
        progress,
    )
}
