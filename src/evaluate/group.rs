//! Validation and grouping of keyed measurements (captures or deviation rows) into targets ×
//! directions × runs. One place for the rules every evaluation shares, so the CLI and the
//! service refuse the same inputs with the same words.

use super::{EvalError, at_line};
use crate::run::Direction;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// One measurement with its key. `line` locates it in a file, when it came from one.
#[derive(Clone, Debug, PartialEq)]
pub struct Keyed<T> {
    pub target_index: u32,
    pub target_mm: f64,
    pub run: u32,
    pub direction: Direction,
    pub line: Option<usize>,
    pub value: T,
}

/// Which approach directions the data holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Directions {
    Both,
    UpOnly,
    DownOnly,
}

impl Directions {
    /// In words, for messages.
    pub fn words(self) -> &'static str {
        match self {
            Directions::Both => "both directions",
            Directions::UpOnly => "the increasing direction only",
            Directions::DownOnly => "the decreasing direction only",
        }
    }

    pub fn has_up(self) -> bool {
        self != Directions::DownOnly
    }
    pub fn has_down(self) -> bool {
        self != Directions::UpOnly
    }
}

/// One target: its nominal position and the values of every run, per direction, in run order
/// (empty for a direction the data does not hold).
#[derive(Clone, Debug, PartialEq)]
pub struct Target<T> {
    pub index: u32,
    pub position_mm: f64,
    pub up: Vec<T>,
    pub down: Vec<T>,
}

impl<T> Target<T> {
    pub fn values(&self, d: Direction) -> &[T] {
        match d {
            Direction::Up => &self.up,
            Direction::Down => &self.down,
        }
    }
}

/// Validated data: targets in increasing position, complete runs in each direction present.
#[derive(Clone, Debug, PartialEq)]
pub struct Grouped<T> {
    pub targets: Vec<Target<T>>,
    /// The run numbers, ascending (the same for every target and direction).
    pub runs: Vec<u32>,
    pub directions: Directions,
}

/// How many missing captures are listed by name before "… and N more".
const MISSING_LISTED: usize = 8;

/// Check and group. Rules: no duplicates; one position per target; every (target, run,
/// direction present) exists; at least 2 runs and 2 targets; positions increase with the index.
pub fn group<T: Clone>(items: &[Keyed<T>]) -> Result<Grouped<T>, EvalError> {
    if items.is_empty() {
        return Err(EvalError::Empty);
    }
    let mut positions: BTreeMap<u32, (f64, Option<usize>)> = BTreeMap::new();
    let mut seen: HashMap<(u32, u32, Direction), usize> = HashMap::new();
    let mut dirs = BTreeSet::new();
    let mut runs = BTreeSet::new();
    for (k, it) in items.iter().enumerate() {
        if !it.target_mm.is_finite() {
            return Err(EvalError::NotFinite {
                target: it.target_index,
                run: it.run,
                direction: it.direction.sign(),
                at: at_line(it.line),
                what: "the target position".into(),
                value: it.target_mm,
            });
        }
        match positions.get(&it.target_index) {
            Some(&(p, l)) if p != it.target_mm => {
                return Err(EvalError::TargetMoved {
                    target: it.target_index,
                    found: it.target_mm,
                    at: at_line(it.line),
                    first: p,
                    first_at: at_line(l),
                });
            }
            Some(_) => {}
            None => {
                positions.insert(it.target_index, (it.target_mm, it.line));
            }
        }
        if let Some(&first) = seen.get(&(it.target_index, it.run, it.direction)) {
            return Err(EvalError::Duplicate {
                target: it.target_index,
                run: it.run,
                direction: it.direction.sign(),
                lines: match (items[first].line, it.line) {
                    (Some(a), Some(b)) => format!(" (lines {a} and {b})"),
                    _ => String::new(),
                },
            });
        }
        seen.insert((it.target_index, it.run, it.direction), k);
        dirs.insert(it.direction);
        runs.insert(it.run);
    }
    let runs: Vec<u32> = runs.into_iter().collect();
    let run_list = runs
        .iter()
        .map(|r| r.to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let directions = match (
        dirs.contains(&Direction::Up),
        dirs.contains(&Direction::Down),
    ) {
        (true, true) => Directions::Both,
        (true, false) => Directions::UpOnly,
        _ => Directions::DownOnly,
    };
    let present: Vec<Direction> = [Direction::Up, Direction::Down]
        .into_iter()
        .filter(|d| dirs.contains(d))
        .collect();

    let mut missing = Vec::new();
    for (&t, &(p, _)) in &positions {
        for &d in &present {
            for &r in &runs {
                if !seen.contains_key(&(t, r, d)) {
                    missing.push(format!(
                        "target {t} ({p} mm) run {r} direction {}",
                        d.sign()
                    ));
                }
            }
        }
    }
    if !missing.is_empty() {
        let count = missing.len();
        let mut list = missing[..count.min(MISSING_LISTED)].join("; ");
        if count > MISSING_LISTED {
            list.push_str(&format!("; … and {} more", count - MISSING_LISTED));
        }
        return Err(EvalError::Missing {
            count,
            list,
            runs: run_list,
        });
    }
    if runs.len() < 2 {
        return Err(EvalError::TooFewRuns {
            found: runs.len(),
            runs: run_list,
        });
    }
    if positions.len() < 2 {
        return Err(EvalError::TooFewTargets {
            found: positions.len(),
        });
    }
    let ordered: Vec<(u32, f64)> = positions.iter().map(|(&t, &(p, _))| (t, p)).collect();
    for w in ordered.windows(2) {
        if w[1].1 <= w[0].1 {
            return Err(EvalError::NotIncreasing {
                earlier: w[0].0,
                earlier_mm: w[0].1,
                later: w[1].0,
                later_mm: w[1].1,
            });
        }
    }

    let run_pos: HashMap<u32, usize> = runs.iter().enumerate().map(|(k, &r)| (r, k)).collect();
    let tgt_pos: HashMap<u32, usize> = ordered
        .iter()
        .enumerate()
        .map(|(k, &(t, _))| (t, k))
        .collect();
    let mut slots: Vec<[Vec<Option<T>>; 2]> = ordered
        .iter()
        .map(|_| [vec![None; runs.len()], vec![None; runs.len()]])
        .collect();
    for it in items {
        let d = match it.direction {
            Direction::Up => 0,
            Direction::Down => 1,
        };
        slots[tgt_pos[&it.target_index]][d][run_pos[&it.run]] = Some(it.value.clone());
    }
    let targets = ordered
        .iter()
        .zip(slots)
        .map(|(&(index, position_mm), [up, down])| Target {
            index,
            position_mm,
            up: up.into_iter().flatten().collect(),
            down: down.into_iter().flatten().collect(),
        })
        .collect();
    Ok(Grouped {
        targets,
        runs,
        directions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k(t: u32, p: f64, r: u32, d: Direction, line: usize) -> Keyed<f64> {
        Keyed {
            target_index: t,
            target_mm: p,
            run: r,
            direction: d,
            line: Some(line),
            value: (t * 10 + r) as f64,
        }
    }

    fn full(dirs: &[Direction]) -> Vec<Keyed<f64>> {
        let mut v = Vec::new();
        let mut line = 2;
        for t in 0..3 {
            for r in 1..=3 {
                for &d in dirs {
                    v.push(k(t, t as f64 * 100.0, r, d, line));
                    line += 1;
                }
            }
        }
        v
    }

    #[test]
    fn groups_in_run_order_any_row_order() {
        let mut v = full(&[Direction::Up, Direction::Down]);
        v.reverse();
        let g = group(&v).unwrap();
        assert_eq!(g.directions, Directions::Both);
        assert_eq!(g.runs, vec![1, 2, 3]);
        assert_eq!(g.targets[2].position_mm, 200.0);
        assert_eq!(g.targets[2].up, vec![21.0, 22.0, 23.0]);
        assert_eq!(g.targets[0].down, vec![1.0, 2.0, 3.0]);
        let g = group(&full(&[Direction::Down])).unwrap();
        assert_eq!(g.directions, Directions::DownOnly);
        assert!(g.targets[0].up.is_empty());
    }

    #[test]
    fn refuses_with_target_run_direction_and_line() {
        let mut v = full(&[Direction::Up, Direction::Down]);
        v.retain(|x| !(x.target_index == 1 && x.run == 2 && x.direction == Direction::Down));
        let e = group(&v).unwrap_err().to_string();
        assert!(
            e.starts_with("1 capture(s) missing: target 1 (100 mm) run 2 direction -;"),
            "{e}"
        );
        assert!(e.contains("same runs (1, 2, 3)"), "{e}");

        let mut v = full(&[Direction::Up]);
        v.push(k(1, 100.0, 2, Direction::Up, 99));
        let e = group(&v).unwrap_err().to_string();
        assert_eq!(
            e,
            "target 1, run 2, direction + appears twice (lines 6 and 99): keep one"
        );

        let mut v = full(&[Direction::Up]);
        v[4].target_mm = 101.0;
        let e = group(&v).unwrap_err().to_string();
        assert!(
            e.contains("target 1 is at 101 mm (line 6) but at 100 mm (line 5)"),
            "{e}"
        );

        let v: Vec<_> = full(&[Direction::Up])
            .into_iter()
            .filter(|x| x.run == 1)
            .collect();
        assert!(matches!(
            group(&v),
            Err(EvalError::TooFewRuns { found: 1, .. })
        ));

        let v: Vec<_> = full(&[Direction::Up])
            .into_iter()
            .filter(|x| x.target_index == 0)
            .collect();
        assert!(matches!(
            group(&v),
            Err(EvalError::TooFewTargets { found: 1 })
        ));

        let mut v = full(&[Direction::Up]);
        for x in v.iter_mut().filter(|x| x.target_index == 2) {
            x.target_mm = 50.0;
        }
        let e = group(&v).unwrap_err().to_string();
        assert!(
            e.starts_with("target 2 (50 mm) is not beyond target 1 (100 mm)"),
            "{e}"
        );

        let mut v = full(&[Direction::Up]);
        v[0].target_mm = f64::NAN;
        let e = group(&v).unwrap_err().to_string();
        assert!(
            e.starts_with("target 0, run 1, direction + (line 2): the target position"),
            "{e}"
        );
        assert_eq!(group::<f64>(&[]), Err(EvalError::Empty));
    }
}
