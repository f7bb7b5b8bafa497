//! Issue 30's year of short checks on the twin (`sim::ageing`), small: a 200 mm axis
//! commissioned in the virtual-time lab, checked weekly while its screw wears, judged by the
//! twin's truth. The full year on a 1 m axis is `axiscomp demo --trend`, swept over seeds by
//! `tests/interop/trend_sweep.sh` in `.ci/run`.

use axiscomp::sim::ageing::{DRIFT, Drift, E, Year, YearSpec, check_plan, year};
use axiscomp::sim::closed_loop::LoopSpec;
use axiscomp::trend::Settings;

/// A 200 mm axis commissioned with 9 targets and 2 runs, checked at 5 of them.
fn spec(seed: u64) -> LoopSpec {
    crate::lab::square_loop(seed, 200.0, 9, 2)
}

/// `checks` weekly checks; the screw wears from day 60 (after check 8) by `um_per_week` at
/// its peak; E's tolerance 1.5 µm.
fn year_spec(full: &LoopSpec, checks: usize, um_per_week: f64, notice_days: f64) -> YearSpec {
    YearSpec {
        check: check_plan(&full.plan).expect("check plan"),
        checks,
        interval_days: 7.0,
        drift: Some(Drift {
            onset_day: 60.0,
            um_per_day: um_per_week / 7.0,
        }),
        tolerance_e_um: 1.5,
        notice_days,
        trend: Settings::default(),
    }
}

fn first_alarm(y: &Year) -> usize {
    y.alarm.expect("a drift alarm")
}

/// Wear of 0.3 µm a week: the drift alarm within 3 checks of the onset (checks 9, 10, 11 are
/// the first three after day 60) and none before; a composed table proposed, published when
/// the forecast gives the tolerance a month, and the check in the same break back within the
/// commissioned limits, by the head and by the twin's truth.
#[test]
fn a_wearing_axis_is_seen_proposed_for_and_brought_back() {
    let full = spec(30);
    let y = year(&full, &year_spec(&full, 14, 0.3, 30.0), |_| {}).expect("the year");
    let alarm = first_alarm(&y);
    assert!((9..=11).contains(&alarm), "alarm at check {alarm}");
    assert!(
        y.checks[..9]
            .iter()
            .all(|c| !c.signals[DRIFT] && !c.signals[E])
    );
    let p = y.publication.as_ref().expect("a composed table published");
    assert!(p.after_check >= alarm);
    let check = &y.checks[p.after_check + 1];
    let before = &y.checks[p.after_check];
    // The check in the same break: the same day, the same wear, the new table.
    assert_eq!(check.day, before.day);
    assert_eq!(check.wear_um, before.wear_um);
    assert!(check.table > before.table);
    assert!(!check.signals[E] && !check.signals[DRIFT], "{check:?}");
    // The truth agrees: E back to within 0.2 µm of the axis as commissioned checked it.
    let commissioned = y.checks[..8].iter().map(|c| c.truth[E]).sum::<f64>() / 8.0;
    assert!(
        (check.truth[E] - commissioned).abs() < 0.2,
        "E by the truth: {} after the table, {commissioned} as commissioned",
        check.truth[E]
    );
}

/// Wear of 0.1 µm a week and nothing published (no notice): the day the twin's truth says E
/// would cross its tolerance, worked out at a check from its wear, is the day the later
/// checks' truth crosses it; and the forecast made at least two weeks before it, from 8
/// checks of the drift, is within ±20 % of the days it looked ahead.
#[test]
fn the_true_crossing_and_the_forecast_agree_with_the_checks_that_follow() {
    let full = spec(31);
    let y = year(&full, &year_spec(&full, 26, 0.1, 0.0), |_| {}).expect("the year");
    assert!(y.publication.is_none());
    let crossed = y
        .checks
        .iter()
        .position(|c| c.truth[E] >= 1.5)
        .expect("E crosses 1.5 µm within the year");
    let at = y.checks[crossed - 2].true_crossing_day.expect("a crossing");
    assert!(
        y.checks[crossed - 1].day < at && at <= y.checks[crossed].day,
        "crossing worked out for day {at}, checks cross between day {} and {}",
        y.checks[crossed - 1].day,
        y.checks[crossed].day
    );
    let (made, c) = y
        .checks
        .iter()
        .rev()
        .filter_map(|c| Some((c, c.true_crossing_day?)))
        .find(|(c, t)| t - c.day >= 14.0)
        .expect("a check two weeks or more before the crossing");
    let f = made
        .forecast
        .and_then(|f| f.crossing)
        .expect("a forecast crossing");
    let lead = c - made.day;
    assert!(
        (f.day - c).abs() <= 0.2 * lead,
        "forecast day {:.1} on day {:.0}, true {c:.1}",
        f.day,
        made.day
    );
}
