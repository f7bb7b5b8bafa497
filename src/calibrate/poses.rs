//! Pose sets: known six-DOF poses (from a hexapod or the twin) with the readings taken there.
//! CSV form (user units): `dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,X1_um,...,Y3_um`
//! with optional `travel_mm,follower_mm` columns; `#` lines carry metadata.

use super::CalError;
use crate::optics::Pose;
use crate::units::{Errors6, readings_from_um, readings_to_um};
use crate::util::csv::NumericCsv;
use crate::util::range::{POSITION_MM, Range};
use nalgebra::Vector6;
use std::fmt::Write as _;

/// Error columns in order.
pub const ERROR_COLUMNS: [&str; 6] = [
    "dx_um",
    "dy_um",
    "dz_um",
    "ex_arcsec",
    "ey_arcsec",
    "ez_arcsec",
];
/// Reading columns in order.
pub const READING_COLUMNS: [&str; 6] = ["X1_um", "Y1_um", "X2_um", "Y2_um", "X3_um", "Y3_um"];
/// Optional position columns.
pub const POSITION_COLUMNS: [&str; 2] = ["travel_mm", "follower_mm"];

/// A PSD reading (µm): ±100 mm, beyond any PSD's size.
pub const READING_UM: Range = Range::symmetric(100_000.0, "µm");

/// Every column's range: the pose within a hexapod's reach (±100 mm, ±10°), the readings
/// within [`READING_UM`], the positions along a machine axis.
pub fn column_ranges() -> Vec<(&'static str, Range)> {
    let (um, arcsec) = (
        Range::symmetric(100_000.0, "µm"),
        Range::symmetric(36_000.0, "arcsec"),
    );
    let errors = ERROR_COLUMNS
        .iter()
        .enumerate()
        .map(|(k, c)| (*c, if k < 3 { um } else { arcsec }));
    let readings = READING_COLUMNS.iter().map(|c| (*c, READING_UM));
    let positions = POSITION_COLUMNS.iter().map(|c| (*c, POSITION_MM));
    errors.chain(readings).chain(positions).collect()
}

/// One known pose and the readings taken there (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseSample {
    pub pose: Pose,
    pub readings: Vector6<f64>,
}

/// Parse a pose-set CSV. `source_name` names the input in errors.
pub fn parse_pose_csv(text: &str, source_name: &str) -> Result<Vec<PoseSample>, CalError> {
    let mut required: Vec<&str> = ERROR_COLUMNS.to_vec();
    required.extend_from_slice(&READING_COLUMNS);
    let csv = NumericCsv::parse(text, source_name, &required, &POSITION_COLUMNS)?;
    csv.check_ranges(&column_ranges())?;
    let ecol: Vec<usize> = ERROR_COLUMNS.iter().filter_map(|c| csv.col(c)).collect();
    let rcol: Vec<usize> = READING_COLUMNS.iter().filter_map(|c| csv.col(c)).collect();
    let (tcol, fcol) = (csv.col("travel_mm"), csv.col("follower_mm"));
    let mut out = Vec::with_capacity(csv.rows.len());
    for (_, row) in &csv.rows {
        let e = Errors6::from_user(std::array::from_fn(|k| row[ecol[k]]));
        let r = readings_from_um(std::array::from_fn(|k| row[rcol[k]]));
        let travel = tcol.map(|c| row[c]).unwrap_or(0.0);
        let follower = fcol.map(|c| row[c]).unwrap_or(0.0);
        out.push(PoseSample {
            pose: Pose::new(e, travel, follower),
            readings: r,
        });
    }
    if out.is_empty() {
        return Err(CalError::Input(format!(
            "{source_name}: no pose rows after the header"
        )));
    }
    Ok(out)
}

/// Write a pose set as CSV (with position columns), `comments` first as `#` lines.
pub fn write_pose_csv(samples: &[PoseSample], comments: &[String]) -> String {
    let mut s = String::new();
    for c in comments {
        let _ = writeln!(s, "# {c}");
    }
    let mut header: Vec<&str> = ERROR_COLUMNS.to_vec();
    header.extend_from_slice(&READING_COLUMNS);
    header.extend_from_slice(&POSITION_COLUMNS);
    let _ = writeln!(s, "{}", header.join(","));
    for p in samples {
        let e = p.pose.errors.to_user();
        let r = readings_to_um(&p.readings);
        let fields: Vec<String> = e
            .iter()
            .chain(r.iter())
            .map(|x| format!("{x:.6}"))
            .chain(
                [p.pose.travel, p.pose.follower]
                    .iter()
                    .map(|x| format!("{x:.6}")),
            )
            .collect();
        let _ = writeln!(s, "{}", fields.join(","));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let s = PoseSample {
            pose: Pose::new(
                Errors6::from_user([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
                10.0,
                9.5,
            ),
            readings: readings_from_um([7.0, 8.0, 9.0, 10.0, 11.0, 12.0]),
        };
        let text = write_pose_csv(&[s], &["seed 1".into()]);
        let back = parse_pose_csv(&text, "t.csv").unwrap();
        assert_eq!(back.len(), 1);
        assert!((back[0].readings - s.readings).amax() < 1e-12);
        assert!((back[0].pose.errors.to_user()[5] - 6.0).abs() < 1e-9);
        assert_eq!(back[0].pose.follower, 9.5);
    }

    #[test]
    fn position_columns_are_optional() {
        let text = "dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n0,0,0,0,0,0,1,2,3,4,5,6\n";
        let p = parse_pose_csv(text, "t").unwrap();
        assert_eq!(p[0].pose.travel, 0.0);
    }
}
