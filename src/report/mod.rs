//! Plots and run reports (DESIGN §5 `report`, §8 Results).
//!
//! Input is this module's own small types — a `Series` per approach direction, `Figure`s for
//! the figure tables, a `RunMeta` — so that reporting does not depend on how the evaluation
//! computes them; the evaluation's output is converted into these. Series values are in the
//! crate's internal units (mm, rad) and are converted to µm / arcsec here, at the edge (DESIGN
//! §1); figures are display-ready (a value in the unit named beside it).
//!
//! Output:
//! - plots (`plot`): each error against position, per direction, mean with a ±2s band; the six
//!   errors of a run on one sheet; a before/after comparison. SVG and PNG, drawn by the one
//!   chart code the PDF's charts use too (`chart`; PNG rasterised by tiny-skia with the
//!   built-in DejaVu Sans: no system fonts or libraries);
//! - `write_run_report`: a directory with a self-contained HTML report (inline SVG, inline
//!   style, no scripts, no external resources), a Markdown report that references the PNGs by
//!   relative path, and the SVG and PNG files.

pub mod acceptance;
pub mod budget;
pub mod chart;
pub mod doc;
mod html;
pub mod layout;
mod markdown;
pub mod pdf;
pub mod plot;
mod raster;
pub mod render;
pub mod runs;
pub mod settings;
pub mod source;
pub(crate) mod text;
#[cfg(test)]
mod xml_check;

use crate::run::{Capture, Direction};
use crate::store::RunRecord;
use crate::units::{DOF_MEANING, DOF_NAMES, DOF_TO_USER, DOF_UNITS};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a plot or report could not be made.
#[derive(Debug, Error)]
pub enum ReportError {
    #[error("report input: {what}: {problem}")]
    Input { what: String, problem: String },
    #[error("plot {what}: drawing failed ({detail})")]
    Plot { what: String, detail: String },
    #[error("the acceptance PDF: {0}")]
    Pdf(#[from] pdf::PdfError),
    #[error(
        "report {path}: cannot write it ({source}); check that the directory is writable and \
         the disk is not full"
    )]
    Write {
        path: String,
        source: std::io::Error,
    },
}

/// One of the six errors (DESIGN §1 order).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Dof {
    Dx,
    Dy,
    Dz,
    Ex,
    Ey,
    Ez,
}

impl Dof {
    /// All six, in `Errors6` order.
    pub const ALL: [Dof; 6] = [Dof::Dx, Dof::Dy, Dof::Dz, Dof::Ex, Dof::Ey, Dof::Ez];

    /// Index in `Errors6` order.
    pub fn index(self) -> usize {
        self as usize
    }
    /// "dx" … "ez".
    pub fn name(self) -> &'static str {
        DOF_NAMES[self.index()]
    }
    /// "horizontal straightness" … "yaw".
    pub fn meaning(self) -> &'static str {
        DOF_MEANING[self.index()]
    }
    /// "µm" or "arcsec".
    pub fn unit(self) -> &'static str {
        DOF_UNITS[self.index()]
    }
    /// An internal value (mm or rad) in the user unit.
    pub fn to_user(self, internal: f64) -> f64 {
        internal * DOF_TO_USER[self.index()]
    }
    /// "dy — positioning".
    pub fn title(self) -> String {
        format!("{} — {}", self.name(), self.meaning())
    }
}

/// One error of one direction against position: per target, the mean over the runs and the
/// standard deviation s (ISO 230-2). Values in internal units (mm, rad); every vector has one
/// entry per position. Positions need not be sorted.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    pub direction: Direction,
    pub positions_mm: Vec<f64>,
    pub mean: Vec<f64>,
    pub s: Vec<f64>,
    /// Number of runs averaged at each position.
    pub n: Vec<u32>,
    /// Standard uncertainty of the measurement at each position, when known (the captures' u).
    pub u: Option<Vec<f64>>,
}

/// One figure of a figure table, display-ready: `value` is in `unit`.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    pub name: String,
    pub value: f64,
    pub unit: String,
}

/// What the report shows for one error: its series (one per direction) and figures.
#[derive(Clone, Debug, PartialEq)]
pub struct DofResult {
    pub dof: Dof,
    pub series: Vec<Series>,
    pub figures: Vec<Figure>,
    /// Its uncertainty budget, when one was made.
    pub budget: Option<BudgetTable>,
}

/// One term of an uncertainty budget, display-ready (`largest` in the DOF's user unit).
#[derive(Clone, Debug, PartialEq)]
pub struct BudgetTerm {
    pub name: String,
    pub formula: String,
    pub source: String,
    /// The largest standard uncertainty of this term over the points.
    pub largest: f64,
}

/// One error's uncertainty budget (ISO/TR 230-9), display-ready, in the DOF's user unit.
#[derive(Clone, Debug, PartialEq)]
pub struct BudgetTable {
    /// The coverage factor of the expanded uncertainties.
    pub k: f64,
    pub terms: Vec<BudgetTerm>,
    /// The largest combined standard uncertainty and expanded uncertainty over the points.
    pub largest_combined: f64,
    pub largest_expanded: f64,
    /// Every point of each approach direction (the bidirectional mean left out): each term,
    /// the combined and expanded uncertainty.
    pub points: Vec<BudgetPoint>,
}

/// One point of a budget, display-ready, in the DOF's user unit.
#[derive(Clone, Debug, PartialEq)]
pub struct BudgetPoint {
    pub position_mm: f64,
    pub direction: Direction,
    /// Each term's standard uncertainty, in [`BudgetTable::terms`]' order.
    pub terms: Vec<f64>,
    pub combined: f64,
    pub expanded: f64,
}

impl BudgetTable {
    /// The point at `position_mm` in `direction`, when stated.
    pub fn at(&self, position_mm: f64, direction: Direction) -> Option<&BudgetPoint> {
        self.points
            .iter()
            .find(|p| p.direction == direction && (p.position_mm - position_mm).abs() < 1e-9)
    }

    /// The expanded uncertainty at `position_mm` in `direction`, when stated.
    pub fn expanded_at(&self, position_mm: f64, direction: Direction) -> Option<f64> {
        self.at(position_mm, direction).map(|p| p.expanded)
    }
}

/// Two measurements of one error to compare (e.g. before and after compensation).
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    pub dof: Dof,
    pub before_label: String,
    pub before: Vec<Series>,
    pub after_label: String,
    pub after: Vec<Series>,
}

/// Temperatures at one moment (e.g. one capture's).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EnvSample {
    /// µs since the Unix epoch.
    pub unix_us: i64,
    pub material_c: Option<f64>,
    pub air_c: Option<f64>,
}

impl EnvSample {
    /// A capture's temperatures.
    pub fn of_capture(c: &Capture) -> EnvSample {
        EnvSample {
            unix_us: c.unix_us,
            material_c: c.material_c,
            air_c: c.air_c,
        }
    }
}

/// The run a report is about.
#[derive(Clone, Debug, PartialEq)]
pub struct RunMeta {
    pub run_id: i64,
    pub axis: String,
    /// The run's state ("finished", …).
    pub state: String,
    /// µs since the Unix epoch.
    pub created_us: i64,
    pub updated_us: i64,
    /// The plan as (item, value) rows.
    pub plan: Vec<(String, String)>,
    /// The configuration summary as (item, value) rows.
    pub config: Vec<(String, String)>,
    pub notes: String,
}

impl RunMeta {
    /// From a stored run: the plan's and configuration's top-level JSON entries become rows.
    pub fn from_record(r: &RunRecord) -> RunMeta {
        RunMeta {
            run_id: r.id.0,
            axis: r.axis.clone(),
            state: r.state.to_string(),
            created_us: r.created_us,
            updated_us: r.updated_us,
            plan: text::json_rows("plan", &r.plan),
            config: text::json_rows("config", &r.config),
            notes: r.notes.clone(),
        }
    }
}

/// Everything a run report shows.
#[derive(Clone, Debug, PartialEq)]
pub struct RunReport {
    pub meta: RunMeta,
    /// One entry per error measured, each error at most once.
    pub dofs: Vec<DofResult>,
    /// Before/after comparisons, each error at most once.
    pub comparisons: Vec<Comparison>,
    pub environment: Vec<EnvSample>,
}

impl RunReport {
    /// Check every series and that no error appears twice (its files would collide).
    pub fn validate(&self) -> Result<(), ReportError> {
        let mut seen = Vec::new();
        for d in &self.dofs {
            if seen.contains(&d.dof) {
                return Err(input(d.dof.name(), "appears twice among the results"));
            }
            seen.push(d.dof);
            validate_series(d.dof, &d.series)?;
            for f in &d.figures {
                if !f.value.is_finite() {
                    return Err(input(
                        d.dof.name(),
                        &format!("figure {:?} is {}", f.name, f.value),
                    ));
                }
            }
        }
        let mut seen = Vec::new();
        for c in &self.comparisons {
            if seen.contains(&c.dof) {
                return Err(input(c.dof.name(), "appears twice among the comparisons"));
            }
            seen.push(c.dof);
            validate_series(c.dof, &c.before)?;
            validate_series(c.dof, &c.after)?;
        }
        Ok(())
    }
}

fn input(what: &str, problem: &str) -> ReportError {
    ReportError::Input {
        what: what.to_string(),
        problem: problem.to_string(),
    }
}

/// Every series of `dof`: equal lengths, at least one point, finite values, s and u ≥ 0.
pub fn validate_series(dof: Dof, series: &[Series]) -> Result<(), ReportError> {
    for s in series {
        let what = format!("{} {} series", dof.name(), text::arrow(s.direction));
        let len = s.positions_mm.len();
        let u_len = s.u.as_ref().map_or(len, Vec::len);
        if len == 0 {
            return Err(input(&what, "has no points"));
        }
        if s.mean.len() != len || s.s.len() != len || s.n.len() != len || u_len != len {
            return Err(input(
                &what,
                &format!(
                    "lengths differ: {len} positions, {} means, {} s, {} n, {u_len} u",
                    s.mean.len(),
                    s.s.len(),
                    s.n.len()
                ),
            ));
        }
        let u = s.u.as_deref().unwrap_or(&[]);
        for i in 0..len {
            let (x, m, sd) = (s.positions_mm[i], s.mean[i], s.s[i]);
            let ui = u.get(i).copied().unwrap_or(0.0);
            if !(x.is_finite() && m.is_finite() && sd.is_finite() && ui.is_finite())
                || sd < 0.0
                || ui < 0.0
            {
                return Err(input(
                    &what,
                    &format!("point {i} at {x} mm: mean {m}, s {sd}, u {ui} (finite, s and u ≥ 0)"),
                ));
            }
        }
    }
    Ok(())
}

/// Write the report of a run into `dir` (created when missing): `report.html`, `report.md`, and
/// per error `<dof>.svg`/`.png`, the six-error sheet `six.svg`/`.png`, and for each comparison
/// `compare-<dof>.svg`/`.png`. Existing files of these names are replaced. Returns the paths
/// written, in the order written.
pub fn write_run_report(dir: &Path, report: &RunReport) -> Result<Vec<PathBuf>, ReportError> {
    report.validate()?;
    create_dir(dir)?;
    let mut written = Vec::new();
    let mut write_text =
        |name: &str, body: &str| write_file(&mut written, dir, name, body.as_bytes());

    let mut svgs = html::Svgs::default();
    if !report.dofs.is_empty() {
        let title = text::six_title(&report.meta);
        let svg = plot::six_svg(&report.dofs, &title)?;
        write_text(text::SIX_SVG, &svg)?;
        svgs.six = Some(svg);
    }
    for d in &report.dofs {
        let svg = plot::dof_svg(d)?;
        write_text(&text::dof_file(d.dof, "svg"), &svg)?;
        svgs.dofs.push(svg);
    }
    for c in &report.comparisons {
        let svg = plot::comparison_svg(c)?;
        write_text(&text::comparison_file(c.dof, "svg"), &svg)?;
        svgs.comparisons.push(svg);
    }
    write_text(text::HTML_FILE, &html::render(report, &svgs))?;
    write_text(text::MARKDOWN_FILE, &markdown::render(report))?;

    if !report.dofs.is_empty() {
        let title = text::six_title(&report.meta);
        let path = dir.join(text::SIX_PNG);
        plot::six_png(&report.dofs, &title, &path)?;
        written.push(path);
    }
    for d in &report.dofs {
        let path = dir.join(text::dof_file(d.dof, "png"));
        plot::dof_png(d, &path)?;
        written.push(path);
    }
    for c in &report.comparisons {
        let path = dir.join(text::comparison_file(c.dof, "png"));
        plot::comparison_png(c, &path)?;
        written.push(path);
    }
    Ok(written)
}

fn create_dir(dir: &Path) -> Result<(), ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Write {
        path: dir.display().to_string(),
        source,
    })
}

/// Write `dir/name` and add its path to `written`.
fn write_file(
    written: &mut Vec<PathBuf>,
    dir: &Path,
    name: &str,
    body: &[u8],
) -> Result<(), ReportError> {
    let path = dir.join(name);
    std::fs::write(&path, body).map_err(|source| ReportError::Write {
        path: path.display().to_string(),
        source,
    })?;
    written.push(path);
    Ok(())
}

/// The formats of an acceptance report.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Format {
    Html,
    Markdown,
    Pdf,
}

impl Format {
    pub const ALL: [Format; 3] = [Format::Html, Format::Markdown, Format::Pdf];

    /// "html", "md" or "pdf".
    pub fn parse(s: &str) -> Option<Format> {
        match s {
            "html" => Some(Format::Html),
            "md" | "markdown" => Some(Format::Markdown),
            "pdf" => Some(Format::Pdf),
            _ => None,
        }
    }
}

/// Write an acceptance document into `dir` (created when missing): `acceptance.html`,
/// `acceptance.md` with its charts as `chart-<n>.svg`, and `acceptance.pdf`, as `formats`
/// ask. Returns the paths written.
pub fn write_acceptance(
    dir: &Path,
    doc: &doc::Document,
    formats: &[Format],
    generated_us: i64,
) -> Result<Vec<PathBuf>, ReportError> {
    create_dir(dir)?;
    let mut written = Vec::new();
    let mut write = |name: &str, body: &[u8]| write_file(&mut written, dir, name, body);
    for f in formats {
        match f {
            Format::Html => write("acceptance.html", render::html(doc).as_bytes())?,
            Format::Markdown => {
                write("acceptance.md", render::markdown(doc).as_bytes())?;
                for (name, svg) in render::chart_svgs(doc) {
                    write(&name, svg.as_bytes())?;
                }
            }
            Format::Pdf => {
                let secs = generated_us.div_euclid(1_000_000);
                let stamp: String = crate::util::time::rfc3339(secs)
                    .chars()
                    .filter(char::is_ascii_digit)
                    .collect();
                let info = pdf::Info {
                    title: doc.title.clone(),
                    subject: doc.subtitle.clone(),
                    creation_date: format!("D:{stamp}Z"),
                };
                write("acceptance.pdf", &layout::pdf(doc, &info)?)?;
            }
        }
    }
    Ok(written)
}

#[cfg(test)]
mod tests;
