//! The Results screen's trends view (`t`): every figure of the axis's finished runs and checks
//! over time, as the service's `trend` request gives them (`service::trends`, what `axiscomp
//! trend` prints): each figure's newest value against its control limits, the drift alarm and
//! what it calls for, and the forecast against its tolerance; the figure highlighted charted.

use super::*;
use serde::Deserialize;

/// One run's value of a figure, with the EWMA and the limits after it.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct TrendPoint {
    pub run_id: i64,
    pub unix_us: i64,
    pub value: f64,
    pub ewma: Option<f64>,
    pub limits: Option<[f64; 2]>,
}

/// The forecast of a figure against its tolerance.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct ForecastView {
    pub slope_per_day: f64,
    pub points: usize,
    pub crossing_unix_us: Option<i64>,
    pub crossing_low_unix_us: Option<i64>,
    pub crossing_high_unix_us: Option<i64>,
}

/// One figure's trend.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct FigureTrend {
    pub dof: String,
    pub name: String,
    pub unit: String,
    pub points: Vec<TrendPoint>,
    pub mean: Option<f64>,
    pub sigma: Option<f64>,
    pub alarm_run: Option<i64>,
    pub remedy: Option<String>,
    pub no_limits: Option<String>,
    pub tolerance: Option<f64>,
    pub forecast: Option<ForecastView>,
}

impl FigureTrend {
    pub fn label(&self) -> String {
        format!("{} {}", self.dof, self.name)
    }
}

/// An axis's trends.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct AxisTrend {
    pub axis: String,
    pub runs: Vec<i64>,
    pub compensation: String,
    pub runs_under_other_tables: usize,
    pub figures: Vec<FigureTrend>,
}

/// The trends view's state.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrendsView {
    /// The Results screen shows the trends, not the runs.
    pub shown: bool,
    pub trend: Option<AxisTrend>,
    /// The figure highlighted.
    pub selected: usize,
    /// Why the last `trend` failed.
    pub error: Option<String>,
}

impl TrendsView {
    /// The figure highlighted.
    pub fn figure(&self) -> Option<&FigureTrend> {
        self.trend.as_ref()?.figures.get(self.selected)
    }
}

impl App {
    pub(super) fn apply_trend(&mut self, v: serde_json::Value) {
        match serde_json::from_value::<AxisTrend>(v) {
            Ok(t) => {
                let keep = self.trends.figure().map(FigureTrend::label);
                // Keep the figure highlighted; else the first one in alarm; else E.
                self.trends.selected = keep
                    .and_then(|k| t.figures.iter().position(|f| f.label() == k))
                    .or_else(|| t.figures.iter().position(|f| f.alarm_run.is_some()))
                    .or_else(|| {
                        t.figures
                            .iter()
                            .position(|f| f.dof == "dy" && f.name.starts_with("E "))
                    })
                    .unwrap_or(0);
                self.trends.error = None;
                self.trends.trend = Some(t);
            }
            Err(e) => self.say(Level::Error, format!("bad trend from the service: {e}")),
        }
    }

    /// The trends of the newest run's axis, asked for.
    pub(super) fn load_trend(&mut self) -> Action {
        self.send(Request::Trend { axis: None }, Pending::Trend)
    }

    /// Keys while the trends view shows.
    pub(super) fn trends_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let n = self.trends.trend.as_ref().map_or(0, |t| t.figures.len());
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) if n > 0 => self.trends.selected = (self.trends.selected + n - 1) % n,
            (KeyCode::Down, _) if n > 0 => self.trends.selected = (self.trends.selected + 1) % n,
            (_, Some('t')) => self.trends.shown = false,
            (_, Some('r')) => return vec![self.load_trend()],
            _ => {}
        }
        Vec::new()
    }
}
