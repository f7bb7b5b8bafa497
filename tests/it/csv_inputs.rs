//! The CSV files a lab brings, read by the one reader (`util::csv`): each fixture under
//! `tests/fixtures/csv/` in its `,` form and its `;` form (quoted, reordered, decimal commas)
//! reads to the same values, and the bad ones are refused naming the file, the line and the
//! column (issue 29, must-show 2).

use axiscomp::follower::{Certificate, Direction};
use axiscomp::hexapod::plan::PosePlan;
use std::path::PathBuf;

fn fixture(name: &str) -> (String, String) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/csv")
        .join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (text, name.to_string())
}

fn certificate(name: &str) -> Result<Certificate, String> {
    let (text, name) = fixture(name);
    Certificate::parse(&text, &name).map_err(|e| e.to_string())
}

fn plan(name: &str) -> Result<PosePlan, String> {
    let (text, name) = fixture(name);
    PosePlan::parse(&text, &name).map_err(|e| e.to_string())
}

#[test]
fn a_certificate_reads_the_same_from_either_form() {
    let comma = certificate("certificate.csv").unwrap();
    let semi = certificate("certificate-semicolon.csv").unwrap();
    assert_eq!((comma.up.len(), comma.down.len()), (3, 3));
    // The values, written by hand in the fixture (µm there, mm here).
    let want_up = [(0.0, 0.0, 0.10), (20.0, 0.35, 0.10), (40.0, 0.62, 0.12)];
    let want_down = [(0.0, 0.05, 0.10), (20.0, 0.41, 0.10), (40.0, 0.70, 0.12)];
    for c in [&comma, &semi] {
        for (points, want) in [(&c.up, want_up), (&c.down, want_down)] {
            for (p, (x, e, u)) in points.iter().zip(want) {
                assert_eq!(p.position_mm, x);
                assert!(
                    (p.error_mm - e * 1e-3).abs() < 1e-15,
                    "{} {}",
                    c.name,
                    p.error_mm
                );
                assert!((p.uncertainty_mm - u * 1e-3).abs() < 1e-15);
            }
        }
        assert!(c.bidirectional());
    }
    assert_eq!(comma.at(10.0, Direction::Up), semi.at(10.0, Direction::Up));
}

#[test]
fn bad_certificates_are_refused_naming_file_line_and_column() {
    assert_eq!(
        certificate("certificate-bad-decimal.csv").unwrap_err(),
        "certificate-bad-decimal.csv line 6, column uncertainty_um: \"0.10\" has a decimal point, and this file's decimals follow a comma (a ; file): write 0,10 or put # decimal = . above the header"
    );
    assert_eq!(
        certificate("certificate-bad-direction.csv").unwrap_err(),
        "certificate-bad-direction.csv line 6, column direction: \"up\" is neither + nor -"
    );
}

#[test]
fn a_pose_plan_reads_the_same_from_either_form() {
    let comma = plan("pose-plan.csv").unwrap();
    let semi = plan("pose-plan-semicolon.csv").unwrap();
    assert_eq!(comma.poses.len(), 6);
    assert_eq!(comma.poses, semi.poses);
    // Pose 6, written by hand in the fixture: v -0.015°, w 0.01°.
    assert_eq!(comma.poses[5].pose.0, [0.0, 0.0, 0.0, 0.0, -0.015, 0.01]);
    assert_eq!(comma.poses[1].pose.0[0], 0.5);
}

#[test]
fn bad_pose_plans_are_refused_naming_file_line_and_column() {
    assert_eq!(
        plan("pose-plan-bad.csv").unwrap_err(),
        "pose-plan-bad.csv line 3: 5 fields, the header has 6"
    );
    assert_eq!(
        plan("pose-plan-bad-range.csv").unwrap_err(),
        "pose-plan-bad-range.csv line 3, column w_deg: 200 degrees is out of range: use -180 to 180 degrees"
    );
}
