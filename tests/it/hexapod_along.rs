//! The hexapod calibration along the travel (DESIGN §3: the poses cover the follower window
//! at several positions): the procedure brings the twin's carriage and follower to each
//! station, the fit gives each station its own offset (the axis' and the follower's own
//! errors there), the held-out frames are judged against the bound at every station, a run
//! stopped mid-plan resumes at its station, and untraceable held-out frames are counted, not
//! fatal, until there are too many.

use crate::helpers::TempDir;
use crate::hexapod::{assert_within, driver, judge, rig, take_on};
use axiscomp::calibrate::{CalibrateOptions, calibrate_along};
use axiscomp::hexapod::Driver;
use axiscomp::hexapod::bench::Bench;
use axiscomp::hexapod::plan::{PlanSpec, PosePlan};
use axiscomp::hexapod::procedure::{PoseStore, ProcedureError};
use axiscomp::optics::Layout;
use axiscomp::sim::hexapod_servers::HexapodFault;
use axiscomp::sim::plant::Plant;
use axiscomp::units::DOF_NAMES;
use std::io::Write as _;
use std::sync::Arc;

/// The twin's carriage and follower moved directly on the plant; each visit is recorded.
struct PlantBench {
    plant: Arc<Plant>,
    visits: Vec<(f64, f64)>,
}

impl PlantBench {
    fn new(plant: &Arc<Plant>) -> PlantBench {
        PlantBench {
            plant: plant.clone(),
            visits: Vec::new(),
        }
    }
}

impl Bench for PlantBench {
    fn moves(&self) -> bool {
        true
    }

    async fn go_to(&mut self, travel_mm: f64, follower_mm: f64) -> Result<(), String> {
        self.plant
            .move_carriage(travel_mm, axiscomp::util::clock::now());
        let end = self.plant.carriage_move_end();
        tokio::time::sleep_until(tokio::time::Instant::from_std(end)).await;
        self.plant.set_follower_encoder(follower_mm);
        self.visits.push((travel_mm, follower_mm));
        Ok(())
    }
}

fn stations() -> Vec<(f64, f64)> {
    vec![(0.0, 0.0), (150.0, 150.0), (300.0, 300.0)]
}

/// 90 poses at three stations 150 mm apart: the carriage and the follower visit each once,
/// in order; every held-out DOF within 1.15× the single-frame bound; without the stations'
/// offsets the same poses do not fit. (The offsets themselves are the axis' and the
/// follower's errors there only up to what the beams' direction relative to the travel
/// trades with them, µm and arcsec over 300 mm that vary with the noise: the readings cannot
/// tell the two apart, so no test compares them with the twin's truth.)
#[tokio::test(start_paused = true)]
async fn the_procedure_calibrates_along_the_travel_with_an_offset_per_station() {
    let r = rig(9).await;
    let dir = TempDir::new("hexapod-along");
    let plan = PosePlan::generate(&PlanSpec {
        poses: 90,
        stations: stations(),
        ..PlanSpec::default()
    });
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::PiGcs).await;
    let mut bench = PlantBench::new(&r.plant);
    let report = take_on(&mut h, &r, &mut bench, &plan, &mut store, &mut |_| {})
        .await
        .expect("run");
    assert_eq!(report.taken, 90);
    let visited = bench.visits.clone();
    assert_eq!(visited, stations(), "each station once, in order");
    for (i, p) in store.poses.iter().enumerate() {
        assert_eq!((p.travel_mm, p.follower_mm), stations()[i * 3 / 90]);
    }

    let j = judge(&store).expect("fit");
    assert_eq!(j.holdout_poses, 18);
    assert_eq!((j.frames, j.untraceable), (18 * 20, 0));
    assert_within(&j, 1.15);
    assert_eq!(j.stations.len(), 3);
    for (s, at) in j.stations.iter().zip(&bench.visits) {
        assert_eq!((s.travel_mm, s.follower_mm), *at);
    }
    // The offsets are what makes the stations agree: the same poses fitted as if the
    // carriage and the follower were exact leave the held-out poses (frames averaged) far
    // off, the axis' own µm and arcsec.
    let samples: Vec<_> = store.poses.iter().map(|p| p.sample()).collect();
    let held_rms = |station_offsets| {
        let (cal, _) = calibrate_along(
            &samples,
            &Layout::reference(),
            &CalibrateOptions {
                station_offsets,
                ..CalibrateOptions::default()
            },
            &mut |_, _| {},
        )
        .expect("fit");
        cal.model.and_then(|m| m.holdout_rms).expect("hold-out")
    };
    let (with, without) = (held_rms(true), held_rms(false));
    // With them, the 20-frame means at their noise: the single-frame bound over √20 = 0.22×.
    for k in 0..6 {
        assert!(
            with[k] < 0.35 * j.crlb[k],
            "{}: {:.3e} against the bound {:.3e}",
            DOF_NAMES[k],
            with[k],
            j.crlb[k]
        );
    }
    let worst = (0..6).map(|k| without[k] / j.crlb[k]).fold(0.0, f64::max);
    assert!(worst > 3.0, "without offsets: {without:?}");

    // A held-out frame the calibration cannot decouple is left out and counted.
    let held = store.poses[4].index;
    let frames = dir.path("run").join("frames.csv");
    let garbage = format!("{held},1000000,0,0,0,0,0\n");
    append(&frames, &garbage);
    let again = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    let j1 = judge(&again).expect("one untraceable frame is skipped");
    assert_eq!((j1.frames, j1.untraceable), (360, 1));
    // The same judgement otherwise (the reopened store's poses are rounded as written).
    for (k, name) in DOF_NAMES.iter().enumerate() {
        let rel = (j1.holdout_rms[k] - j.holdout_rms[k]).abs() / j.holdout_rms[k];
        assert!(rel < 1e-4, "{name}: {rel}");
    }
    // More than 2 % of them refuses the judgement, saying why.
    append(&frames, &garbage.repeat(12));
    let again = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    let e = judge(&again).expect_err("too many");
    assert!(
        matches!(
            e,
            ProcedureError::Untraceable {
                untraceable: 13,
                frames: 373,
                ..
            }
        ),
        "{e}"
    );
    let text = e.to_string();
    assert!(
        text.starts_with(&format!(
            "13 of 373 held-out frames cannot be decoupled with the new calibration (first at pose {held}: "
        )),
        "{text}"
    );
    assert!(text.contains("more than 2 %"), "{text}");
}

fn append(path: &std::path::Path, text: &str) {
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .expect("frames.csv");
    f.write_all(text.as_bytes()).expect("append");
}

/// A controller error at the second station stops the run; the resumed run goes back to
/// that station first (the carriage was moved away meanwhile), then the third, and every
/// pose is stored once at its own station.
#[tokio::test(start_paused = true)]
async fn a_run_stopped_at_a_station_resumes_there() {
    let r = rig(10).await;
    let dir = TempDir::new("hexapod-along-resume");
    let plan = PosePlan::generate(&PlanSpec {
        poses: 30,
        stations: stations(),
        ..PlanSpec::default()
    });
    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("store");
    let mut h = driver(&r.servers, Driver::NewportXps).await;
    let hx = r.servers.hexapod.clone();
    let mut bench = PlantBench::new(&r.plant);
    let e = take_on(&mut h, &r, &mut bench, &plan, &mut store, &mut |p| {
        if p.done == 14 {
            hx.inject(HexapodFault::Error(-17));
        }
    })
    .await
    .expect_err("controller error");
    assert!(
        e.to_string()
            .starts_with("pose 15 of 30: Newport HXP error -17"),
        "{e}"
    );
    let visited = bench.visits.clone();
    assert_eq!(visited, stations()[..2]);
    // Meanwhile the carriage goes elsewhere.
    r.plant.move_carriage(0.0, axiscomp::util::clock::now());
    r.plant.set_follower_encoder(0.0);

    let mut store = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    assert_eq!(store.next_index(), 14);
    let mut bench = PlantBench::new(&r.plant);
    let report = take_on(&mut h, &r, &mut bench, &plan, &mut store, &mut |_| {})
        .await
        .expect("resumed");
    assert_eq!((report.resumed_from, report.taken), (14, 16));
    let visited = bench.visits.clone();
    assert_eq!(visited, stations()[1..]);
    let again = PoseStore::open(&dir.path("run"), &plan).expect("reopen");
    let idx: Vec<usize> = again.poses.iter().map(|p| p.index).collect();
    assert_eq!(idx, (1..=30).collect::<Vec<_>>());
    for p in &again.poses {
        assert_eq!(
            (p.travel_mm, p.follower_mm),
            stations()[(p.index - 1) * 3 / 30]
        );
    }
}
