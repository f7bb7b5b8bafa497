//! `axiscomp demo --trend`: a year of short checks on the twin (issue 30, [`ageing`]). The
//! head calibrated and the axis commissioned as the single-axis demo does it; then a short
//! check (every other target of the commissioning plan, 2 bidirectional runs) every week while the screw wears from a day on,
//! every figure trended against limits learned from the first checks, E's drift alarmed and
//! forecast to the acceptance tolerance, a composed table proposed and published a month
//! ahead; and the same machine without wear checked as often, for its false alarms. Judged by
//! the twin's truth: the day E would have crossed its tolerance had nothing been published.
//!
//! `summary.json`: `{"seed", "trend": {"figure": "E", "unit": "µm", "tolerance", "checks",
//! "interval_days", "onset_day", "drift_um_per_half_year", "alarm_check", "alarm_day",
//! "checks_to_alarm", "false_alarms", "judged", "forecast_made_day", "forecast_days",
//! "forecast_low_days", "forecast_high_days", "true_crossing_days", "forecast_error_of_lead",
//! "proposal": {"from_check", "after_check", "sequences", "next_check", "next_value",
//! "next_ewma", "limits", "within_limits"}, "check_machine_time_s"}, "stable": [{"figure", "unit",
//! "machine", "checks", "judged", "false_alarms"}], "checks": [{"day", "wear_um", "table",
//! "E", "E_truth", "signal"}]}`: check indices from 0, days since commissioning; the
//! forecast is the one made at the last check at least 30 days before the true crossing, its
//! error as a fraction of the days it looked ahead.

use super::demo::{Args, DEMO_E_UM, Setup, set_up};
use anyhow::{Context, Result};
use axiscomp::sim::ageing::{
    CheckRecord, DRIFT, Drift, E, FIGURES, WEAR_MOVES, Year, YearSpec, YearStep, check_plan, unit,
    year,
};
use axiscomp::trend::Settings;
use axiscomp::util::progress::Progress;
use serde_json::json;

/// Half a year (days): the drift's rate is given per half year, as the issue states it.
const HALF_YEAR_DAYS: f64 = 182.5;

/// How far ahead (days) a proposal is published, and the forecast judged.
const NOTICE_DAYS: f64 = 30.0;

/// Refuse settings that cannot make a year, before the head is calibrated.
fn check_args(a: &Args) -> Result<(), super::InputError> {
    let need = Settings::default().baseline + 1;
    let bad = |flag: &str, problem: String| Err(super::InputError(format!("--{flag}: {problem}")));
    if a.checks < need {
        return bad(
            "checks",
            format!(
                "{} checks cannot chart a trend: give at least {need} (8 to learn the limits from, and one to judge)",
                a.checks
            ),
        );
    }
    if a.stable_checks < need {
        return bad(
            "stable-checks",
            format!(
                "{} checks cannot chart a trend: give at least {need}",
                a.stable_checks
            ),
        );
    }
    if !(a.interval_days > 0.0 && a.interval_days <= 365.0) {
        return bad(
            "interval-days",
            format!(
                "{} is not a time between checks: give more than 0 and at most 365 days",
                a.interval_days
            ),
        );
    }
    if !(a.onset_day >= 0.0 && a.onset_day.is_finite()) {
        return bad(
            "onset-day",
            format!(
                "{} is not a day since commissioning: give 0 or more",
                a.onset_day
            ),
        );
    }
    if !(a.drift_um >= 0.0 && a.drift_um <= 100.0) {
        return bad(
            "drift-um",
            format!(
                "{} µm is not a wear the twin can take: give 0 to 100 µm",
                a.drift_um
            ),
        );
    }
    Ok(())
}

pub fn run(a: &Args) -> Result<()> {
    check_args(a)?;
    let Setup { spec, .. } = set_up(a)?;
    let check = check_plan(&spec.plan)?;
    spec.lab
        .check_plan(&check)
        .map_err(|e| super::InputError(e.to_string()))?;
    let drift = Drift {
        onset_day: a.onset_day,
        um_per_day: a.drift_um / HALF_YEAR_DAYS,
    };
    let y = YearSpec {
        check,
        checks: a.checks,
        interval_days: a.interval_days,
        drift: Some(drift),
        tolerance_e_um: DEMO_E_UM,
        notice_days: NOTICE_DAYS,
        trend: Settings::default(),
    };
    let targets: Vec<String> = y.check.targets.iter().map(|t| format!("{t:.0}")).collect();
    println!(
        "\n== 3. a year of short checks: the axis commissioned, then {} checks every {} days ({} targets at {} mm, {} bidirectional runs each); the screw wears from day {:.0}, {:.1} µm mid-travel every half year",
        y.checks,
        y.interval_days,
        y.check.targets.len(),
        targets.join(", "),
        y.check.spec.runs,
        drift.onset_day,
        a.drift_um
    );
    println!(
        "limits learned from the first {} checks (EWMA, λ {}, ±{} σ; a single point beyond {} σ); E forecast to its tolerance of {:.1} µm; a composed table proposed at E's alarm and published {} days ahead of the forecast crossing",
        y.trend.baseline,
        y.trend.lambda,
        y.trend.width,
        y.trend.point_width,
        y.tolerance_e_um,
        NOTICE_DAYS
    );
    let wall = std::time::Instant::now();
    let drifting = year(&spec, &y, |s| tell(&s))?;
    println!(
        "\n== 4. the same machine without wear: {} checks, for false alarms",
        a.stable_checks
    );
    let mut bar: Option<Progress> = None;
    let stable = year(
        &spec,
        &YearSpec {
            checks: a.stable_checks,
            drift: None,
            ..y.clone()
        },
        |s| {
            if let YearStep::Checked(i, _) = s {
                bar.get_or_insert_with(|| Progress::new("checks", a.stable_checks as u64))
                    .set(i as u64 + 1);
            }
        },
    )?;
    if let Some(b) = bar.take() {
        b.finish("done");
    }
    let summary = summarise(a, &y, &drifting, &stable);
    print_summary(&summary);
    println!("({:.0} s here)", wall.elapsed().as_secs_f64());
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let path = a.out.join("summary.json");
    std::fs::write(
        &path,
        format!("{}\n", serde_json::to_string_pretty(&summary)?),
    )
    .with_context(|| format!("writing {}", path.display()))?;
    println!("summary: {}", path.display());
    Ok(())
}

/// One line per check of the drifting machine, and the alarm, proposal and publication.
fn tell(s: &YearStep) {
    match s {
        YearStep::Commissioning(_) => {}
        YearStep::Checked(i, c) => {
            let forecast = c
                .forecast
                .and_then(|f| f.crossing)
                .map(|x| {
                    format!(
                        "; reaches {:.1} µm on day {:.0} ({:.0}–{:.0})",
                        DEMO_E_UM, x.day, x.low, x.high
                    )
                })
                .unwrap_or_default();
            let signal = if c.signals[DRIFT] || c.signals[E] {
                " ← alarm"
            } else {
                ""
            };
            let drift = if c.measured[DRIFT].is_finite() {
                format!(
                    "drift {:.2} µm (truth {:.2}), ",
                    c.measured[DRIFT], c.truth[DRIFT]
                )
            } else {
                String::new()
            };
            println!(
                "check {i:>3}, day {:>3.0}: {drift}E {:.2} µm (truth {:.2}), wear {:.2} µm, table {}{forecast}{signal}",
                c.day, c.measured[E], c.truth[E], c.wear_um, c.table
            );
        }
        YearStep::Proposed(i) => println!(
            "  positioning drifts: a composed table proposed from check {i} (the table in force plus the check's residual), re-composed from each check until published"
        ),
        YearStep::Published(p) => {
            let seqs: Vec<String> = p.published.iter().map(|t| t.sequence.to_string()).collect();
            println!(
                "  the forecast gives E less than {NOTICE_DAYS:.0} days: the proposal from check {} published after check {} (sequences {}), accepted and active",
                p.from_check,
                p.after_check,
                seqs.join(", ")
            );
        }
    }
}

/// Of `figure` among the checks `range` of `y`: how many were judged (after the baseline),
/// how many signalled, and in how many alarms (a signal after a check that gave none: an
/// alarm stands until the figure is back, as the service raises it once).
fn signals(y: &Year, figure: usize, range: std::ops::Range<usize>) -> (usize, usize, usize) {
    let charted = y
        .chart(figure, y.checks.len(), &Settings::default())
        .is_some();
    let judged = range
        .clone()
        .filter(|&i| charted && i >= Settings::default().baseline)
        .count();
    let out = range
        .clone()
        .filter(|&i| y.checks[i].signals[figure])
        .count();
    let alarms = range
        .filter(|&i| y.checks[i].signals[figure] && (i == 0 || !y.checks[i - 1].signals[figure]))
        .count();
    (judged, out, alarms)
}

fn summarise(a: &Args, y: &YearSpec, drifting: &Year, stable: &Year) -> serde_json::Value {
    let onset = y.drift.map_or(f64::INFINITY, |d| d.onset_day);
    let first_after = drifting
        .checks
        .iter()
        .position(|c| c.day > onset)
        .unwrap_or(drifting.checks.len());
    let (judged, checks_out, false_alarms) = signals(drifting, DRIFT, 0..first_after);
    // The forecast judged: made at the last check, under the commissioned table, at least
    // NOTICE_DAYS before the day E would truly have crossed.
    let judged_forecast = drifting
        .checks
        .iter()
        .enumerate()
        .rev()
        .filter(|(_, c)| c.table == drifting.checks[0].table)
        .find_map(|(i, c)| {
            let t = c.true_crossing_day?;
            (t - c.day >= NOTICE_DAYS).then_some((i, c, t))
        });
    let forecast = judged_forecast.map(|(i, c, t)| {
        let x = c.forecast.and_then(|f| f.crossing);
        json!({
            "check": i,
            "made_day": c.day,
            "days": x.map(|x| x.day),
            "low_days": x.map(|x| x.low),
            "high_days": x.map(|x| x.high),
            "true_days": t,
            "error_of_lead": x.map(|x| (x.day - t) / (t - c.day)),
        })
    });
    let get = |k: &str| {
        forecast
            .as_ref()
            .map_or(serde_json::Value::Null, |f| f[k].clone())
    };
    let proposal = drifting.publication.as_ref().map(|p| {
        let next = p.after_check + 1;
        let chart = drifting.chart(E, next, &y.trend);
        let limits = chart.as_ref().and_then(|c| c.limits.last().copied());
        let ewma = chart.as_ref().and_then(|c| c.ewma.last().copied());
        let value = drifting.checks.get(next).map(|c| c.measured[E]);
        json!({
            "from_check": p.from_check,
            "after_check": p.after_check,
            "sequences": p.published.iter().map(|t| t.sequence).collect::<Vec<_>>(),
            "next_check": next,
            "next_value": value,
            "next_ewma": ewma,
            "limits": limits.map(|(lo, hi)| [lo, hi]),
            "within_limits": drifting.checks.get(next).map(|c| !c.signals[E]),
        })
    });
    let mean_s = drifting
        .checks
        .iter()
        .map(|c| c.machine_time.as_secs_f64())
        .sum::<f64>()
        / drifting.checks.len().max(1) as f64;
    let stable_rows: Vec<serde_json::Value> = (0..FIGURES.len())
        .flat_map(|k| {
            let mut rows = vec![(stable, "stable", 0..stable.checks.len())];
            if !WEAR_MOVES.contains(&k) {
                rows.push((drifting, "drifting", 0..drifting.checks.len()));
            }
            rows.into_iter().map(move |(y, machine, range)| {
                let checks = range.len();
                let (judged, out, alarms) = signals(y, k, range);
                json!({
                    "figure": FIGURES[k],
                    "unit": unit(k),
                    "machine": machine,
                    "checks": checks,
                    "judged": judged,
                    "false_alarms": alarms,
                    "checks_out": out,
                })
            })
        })
        .collect();
    json!({
        "seed": a.seed,
        "trend": {
            "figure": FIGURES[DRIFT],
            "unit": unit(DRIFT),
            "forecast_figure": FIGURES[E],
            "tolerance": y.tolerance_e_um,
            "checks": drifting.checks.len(),
            "interval_days": y.interval_days,
            "onset_day": onset,
            "drift_um_per_half_year": a.drift_um,
            "alarm_check": drifting.alarm,
            "alarm_day": drifting.alarm.map(|i| drifting.checks[i].day),
            "checks_to_alarm": drifting.alarm.map(|i| i as i64 - first_after as i64 + 1),
            "false_alarms": false_alarms,
            "checks_out": checks_out,
            "judged": judged,
            "forecast_made_day": get("made_day"),
            "forecast_days": get("days"),
            "forecast_low_days": get("low_days"),
            "forecast_high_days": get("high_days"),
            "true_crossing_days": get("true_days"),
            "forecast_error_of_lead": get("error_of_lead"),
            "proposal": proposal,
            "check_machine_time_s": mean_s,
        },
        "stable": stable_rows,
        "checks": drifting.checks.iter().map(check_json).collect::<Vec<_>>(),
        "stable_checks": stable.checks.iter().map(check_json).collect::<Vec<_>>(),
    })
}

fn check_json(c: &CheckRecord) -> serde_json::Value {
    json!({
        "day": c.day,
        "wear_um": c.wear_um,
        "table": c.table,
        "E": c.measured[E],
        "E_truth": c.truth[E],
        "drift": c.measured[DRIFT],
        "drift_truth": c.truth[DRIFT],
        "measured": c.measured.iter().map(|v| v.is_finite().then_some(*v)).collect::<Vec<_>>(),
        "truth": c.truth.iter().map(|v| v.is_finite().then_some(*v)).collect::<Vec<_>>(),
        "signals": FIGURES.iter().zip(c.signals).filter(|(_, s)| *s).map(|(f, _)| *f).collect::<Vec<_>>(),
    })
}

fn print_summary(s: &serde_json::Value) {
    let t = &s["trend"];
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    println!("\n== 5. judged by the twin's truth");
    match t["alarm_check"].as_u64() {
        Some(i) => println!(
            "drift alarm on positioning at check {i} (day {:.0}): the {} check after the wear began on day {:.0}",
            num(&t["alarm_day"]),
            ordinal(t["checks_to_alarm"].as_i64().unwrap_or(0)),
            num(&t["onset_day"])
        ),
        None => println!("no drift alarm on positioning"),
    }
    println!(
        "false alarms on positioning before the wear: {} ({} of {} checks judged outside)",
        t["false_alarms"], t["checks_out"], t["judged"]
    );
    if t["forecast_days"].is_number() {
        println!(
            "forecast on day {:.0}: E reaches {:.1} µm on day {:.0} (95 % {:.0}–{:.0}); the twin: day {:.0}, so {:+.0} % of the {:.0} days looked ahead",
            num(&t["forecast_made_day"]),
            num(&t["tolerance"]),
            num(&t["forecast_days"]),
            num(&t["forecast_low_days"]),
            num(&t["forecast_high_days"]),
            num(&t["true_crossing_days"]),
            100.0 * num(&t["forecast_error_of_lead"]),
            num(&t["true_crossing_days"]) - num(&t["forecast_made_day"])
        );
    } else {
        println!("no forecast {NOTICE_DAYS:.0} days or more ahead of the true crossing");
    }
    let p = &t["proposal"];
    if p.is_object() {
        let lim = &p["limits"];
        println!(
            "the composed table from check {} published after check {}; check {} in the same break: E {:.2} µm, its EWMA {:.2} µm {} the commissioned limits {:.2}–{:.2} µm",
            p["from_check"],
            p["after_check"],
            p["next_check"],
            num(&p["next_value"]),
            num(&p["next_ewma"]),
            if p["within_limits"].as_bool() == Some(true) {
                "back within"
            } else {
                "still outside"
            },
            num(&lim[0]),
            num(&lim[1])
        );
    } else {
        println!("no composed table published");
    }
    println!(
        "false alarms of each figure on the stable machine, and of those the wear does not move on the drifting one:"
    );
    for r in s["stable"].as_array().into_iter().flatten() {
        println!(
            "  {:<17} {:<8} machine: {} alarms, {} of {} checks judged outside",
            r["figure"].as_str().unwrap_or_default(),
            r["machine"].as_str().unwrap_or_default(),
            r["false_alarms"],
            r["checks_out"],
            r["judged"]
        );
    }
}

fn ordinal(n: i64) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}
