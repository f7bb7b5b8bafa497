//! The pose plan of a hexapod calibration: which poses, in which order, at which bench
//! position (travel D) with the follower where (d). Generated to cover the operating window
//! (DESIGN §3: positioning over the whole follower window, the angles and straightnesses the
//! axis will show) with a Halton sequence, which fills the six-dimensional box evenly for any
//! number of poses; or read from a CSV file. Checked against the workspace before any move.

use super::{AXES, HexPose, Workspace};
use crate::units::Errors6;
use crate::util::csv::{CsvError, NumericCsv};
use crate::util::range::{POSITION_MM, Range};
use std::fmt::Write as _;
use thiserror::Error;

/// One pose of the plan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanPose {
    pub pose: HexPose,
    /// Where the hexapod stands along the travel (mm) and the follower (mm).
    pub travel_mm: f64,
    pub follower_mm: f64,
}

/// The poses in the order they are visited.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PosePlan {
    pub poses: Vec<PlanPose>,
}

/// What a generated plan covers.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanSpec {
    pub poses: usize,
    /// Half-range per DOF (internal units), centred on the home pose.
    pub half_range: Errors6,
    /// Bench positions (travel, follower) visited in turn.
    pub stations: Vec<(f64, f64)>,
}

impl Default for PlanSpec {
    /// 200 poses, ±100 µm straightness, ±2 mm positioning (the follower window), ±60″.
    fn default() -> Self {
        PlanSpec {
            poses: 200,
            half_range: Errors6::from_user([100.0, 2000.0, 100.0, 60.0, 60.0, 60.0]),
            stations: vec![(0.0, 0.0)],
        }
    }
}

#[derive(Clone, Debug, Error, PartialEq)]
pub enum PlanError {
    #[error(
        "pose {index} of the plan: {axis} = {value} is outside the hexapod's workspace ({min} to {max}); no pose was moved to: change the plan or [hexapod] workspace"
    )]
    OutsideWorkspace {
        index: usize,
        axis: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("the plan has no poses")]
    Empty,
    #[error(transparent)]
    Csv(#[from] CsvError),
    #[error(
        "pose {index} of the plan is at travel {travel_mm} mm with the follower at {follower_mm} mm, pose 1 at {first_travel_mm} mm and {first_follower_mm} mm: nothing here moves the carriage and the follower (the service does, with [cnc] mode = \"twin\"); give a plan at one position and bring the carriage and the follower there first"
    )]
    Stations {
        index: usize,
        travel_mm: f64,
        follower_mm: f64,
        first_travel_mm: f64,
        first_follower_mm: f64,
    },
}

/// The `i`-th element of the van der Corput sequence in `base`, in [0, 1).
fn radical_inverse(mut i: u64, base: u64) -> f64 {
    let mut f = 1.0;
    let mut r = 0.0;
    while i > 0 {
        f /= base as f64;
        r += f * (i % base) as f64;
        i /= base;
    }
    r
}

/// The range of column `k` of a plan file: a hexapod's reach (±1 m, a half turn), then the
/// positions along the axis.
fn column_range(k: usize) -> Range {
    match k {
        0..3 => Range::symmetric(1000.0, "mm"),
        3..6 => Range::symmetric(180.0, "degrees"),
        _ => POSITION_MM,
    }
}

/// The CSV columns of a plan file.
pub const PLAN_COLUMNS: [&str; 8] = [
    "x_mm",
    "y_mm",
    "z_mm",
    "u_deg",
    "v_deg",
    "w_deg",
    "travel_mm",
    "follower_mm",
];

impl PosePlan {
    /// A plan covering `spec`'s window: Halton points (bases 2, 3, 5, 7, 11, 13; the first
    /// point skipped, it is the corner), in one block per station.
    pub fn generate(spec: &PlanSpec) -> PosePlan {
        const BASES: [u64; 6] = [2, 3, 5, 7, 11, 13];
        let h = spec.half_range.to_array();
        let stations = if spec.stations.is_empty() {
            vec![(0.0, 0.0)]
        } else {
            spec.stations.clone()
        };
        let poses = (0..spec.poses)
            .map(|i| {
                let e = Errors6::from_array(std::array::from_fn(|k| {
                    h[k] * (2.0 * radical_inverse(i as u64 + 1, BASES[k]) - 1.0)
                }));
                // One block of consecutive poses per station: the carriage and the follower
                // move once per station.
                let (travel_mm, follower_mm) = stations[i * stations.len() / spec.poses];
                PlanPose {
                    pose: HexPose::from_errors(&e),
                    travel_mm,
                    follower_mm,
                }
            })
            .collect();
        PosePlan { poses }
    }

    /// Every pose inside `ws`, or the first that is not.
    pub fn check(&self, ws: &Workspace) -> Result<(), PlanError> {
        if self.poses.is_empty() {
            return Err(PlanError::Empty);
        }
        for (i, p) in self.poses.iter().enumerate() {
            if let Some((k, value)) = ws.outside(&p.pose) {
                return Err(PlanError::OutsideWorkspace {
                    index: i + 1,
                    axis: AXES[k],
                    value,
                    min: ws.min[k],
                    max: ws.max[k],
                });
            }
        }
        Ok(())
    }

    /// The positions (travel, follower) the plan visits, in order of first visit.
    pub fn stations(&self) -> Vec<(f64, f64)> {
        let mut at: Vec<(f64, f64)> = Vec::new();
        for p in &self.poses {
            if !at.contains(&(p.travel_mm, p.follower_mm)) {
                at.push((p.travel_mm, p.follower_mm));
            }
        }
        at
    }

    /// The one bench position (travel, follower) of every pose, or the first pose elsewhere:
    /// the carriage and the follower stay where the operator put them for the whole run.
    pub fn station(&self) -> Result<(f64, f64), PlanError> {
        let first = self.poses.first().ok_or(PlanError::Empty)?;
        let at = (first.travel_mm, first.follower_mm);
        match self
            .poses
            .iter()
            .position(|p| (p.travel_mm, p.follower_mm) != at)
        {
            None => Ok(at),
            Some(i) => Err(PlanError::Stations {
                index: i + 1,
                travel_mm: self.poses[i].travel_mm,
                follower_mm: self.poses[i].follower_mm,
                first_travel_mm: at.0,
                first_follower_mm: at.1,
            }),
        }
    }

    /// A short fingerprint of the plan (FNV-1a of its text), so a pose file is resumed only
    /// with the plan it was taken with.
    pub fn fingerprint(&self) -> String {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for b in self.to_csv().bytes() {
            h ^= b as u64;
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
        format!("{h:016x}")
    }

    /// The plan as CSV (the form `parse` reads).
    pub fn to_csv(&self) -> String {
        let mut s = format!("{}\n", PLAN_COLUMNS.join(","));
        for p in &self.poses {
            let v = p.pose.0;
            let _ = writeln!(
                s,
                "{:.7},{:.7},{:.7},{:.9},{:.9},{:.9},{},{}",
                v[0], v[1], v[2], v[3], v[4], v[5], p.travel_mm, p.follower_mm
            );
        }
        s
    }

    /// Read a plan: the header names the columns (`travel_mm`, `follower_mm` optional, 0 when
    /// absent); `#` lines and blank lines are skipped.
    pub fn parse(text: &str, source_name: &str) -> Result<PosePlan, PlanError> {
        if text.lines().all(|l| {
            let l = l.trim();
            l.is_empty() || l.starts_with('#')
        }) {
            return Err(PlanError::Empty);
        }
        let csv = NumericCsv::parse(text, source_name, &PLAN_COLUMNS[..6], &PLAN_COLUMNS[6..])?;
        let ranges: Vec<(&str, Range)> = PLAN_COLUMNS
            .iter()
            .enumerate()
            .map(|(k, c)| (*c, column_range(k)))
            .collect();
        csv.check_ranges(&ranges)?;
        let cols: [Option<usize>; 8] = std::array::from_fn(|k| csv.col(PLAN_COLUMNS[k]));
        let poses: Vec<PlanPose> = csv
            .rows
            .iter()
            .map(|(_, row)| {
                let v: [f64; 8] = std::array::from_fn(|k| cols[k].map_or(0.0, |c| row[c]));
                PlanPose {
                    pose: HexPose([v[0], v[1], v[2], v[3], v[4], v[5]]),
                    travel_mm: v[6],
                    follower_mm: v[7],
                }
            })
            .collect();
        if poses.is_empty() {
            return Err(PlanError::Empty);
        }
        Ok(PosePlan { poses })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_plan_covers_the_window_evenly() {
        let spec = PlanSpec::default();
        let plan = PosePlan::generate(&spec);
        assert_eq!(plan.poses.len(), 200);
        let h = HexPose::from_errors(&spec.half_range).0;
        for (k, &hk) in h.iter().enumerate() {
            let v: Vec<f64> = plan.poses.iter().map(|p| p.pose.0[k]).collect();
            let (lo, hi) = v
                .iter()
                .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(*x), b.max(*x)));
            // Within the window, reaching within 3 % of both ends.
            assert!(lo >= -hk && hi <= hk, "{k}");
            assert!(lo < -0.97 * hk && hi > 0.97 * hk, "{k}: {lo} .. {hi}");
            // Every tenth of the range is visited by 10 % of the poses, ±4.
            for b in 0..10 {
                let a = -hk + 0.2 * hk * b as f64;
                let n = v.iter().filter(|x| **x >= a && **x < a + 0.2 * hk).count();
                assert!((16..=24).contains(&n), "axis {k} bin {b}: {n}");
            }
        }
        assert_eq!(radical_inverse(1, 2), 0.5);
        assert_eq!(radical_inverse(3, 2), 0.75);
        assert!((radical_inverse(5, 3) - 7.0 / 9.0).abs() < 1e-15);
    }

    #[test]
    fn the_workspace_check_names_pose_and_axis() {
        let plan = PosePlan::generate(&PlanSpec::default());
        assert_eq!(
            plan.check(&Workspace::symmetric([1.0, 3.0, 1.0, 1.0, 1.0, 1.0])),
            Ok(())
        );
        match plan.check(&Workspace::symmetric([1.0, 1.5, 1.0, 1.0, 1.0, 1.0])) {
            Err(PlanError::OutsideWorkspace { axis, value, .. }) => {
                assert_eq!(axis, "Y");
                assert!(value.abs() > 1.5);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn csv_round_trip_and_bad_input() {
        let plan = PosePlan::generate(&PlanSpec {
            poses: 5,
            stations: vec![(0.0, 0.0), (100.0, 100.0)],
            ..PlanSpec::default()
        });
        let back = PosePlan::parse(&plan.to_csv(), "plan.csv").expect("parse");
        assert_eq!(back.poses.len(), 5);
        assert_eq!(back.poses[2].travel_mm, 0.0);
        assert_eq!(back.stations(), vec![(0.0, 0.0), (100.0, 100.0)]);
        assert_eq!(back.poses[3].travel_mm, 100.0);
        assert_eq!(
            back.station().expect_err("two stations").to_string(),
            "pose 4 of the plan is at travel 100 mm with the follower at 100 mm, pose 1 at 0 mm and 0 mm: nothing here moves the carriage and the follower (the service does, with [cnc] mode = \"twin\"); give a plan at one position and bring the carriage and the follower there first"
        );
        assert_eq!(
            PosePlan::generate(&PlanSpec::default()).station(),
            Ok((0.0, 0.0))
        );
        assert_eq!(back.fingerprint(), plan.fingerprint());
        let e = PosePlan::parse("x_mm,y_mm,z_mm,u_deg,v_deg,w_deg\n0,0,0,0,0,abc\n", "p.csv")
            .expect_err("bad");
        assert_eq!(
            e.to_string(),
            "p.csv line 2, column w_deg: \"abc\" is not a number"
        );
        let e = PosePlan::parse("x_mm,y_mm,z_mm,u_deg,v_deg,w_deg\n0,0,0,0,0,200\n", "p.csv")
            .expect_err("bad");
        assert_eq!(
            e.to_string(),
            "p.csv line 2, column w_deg: 200 degrees is out of range: use -180 to 180 degrees"
        );
        let e = PosePlan::parse("x_mm,y_mm,q\n", "p.csv").expect_err("bad");
        assert!(e.to_string().contains("unknown column \"q\""), "{e}");
    }
}
