//! One PSD: its active area as a box, the spot in it, the spot's X/Y and the SUM as a bar.
//! Shared by the Live and Align screens.

use super::{Theme, bar, panel, signed};
use crate::service::api::snapshot::PsdView;
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::style::Color;
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::Paragraph;
use ratatui::widgets::canvas::{Canvas, Line as CLine, Rectangle};

/// Full scale of the SUM bar (V): PSD signal processors give up to 10 V.
pub const SUM_FULL_V: f64 = 10.0;

/// What each PSD sees (DESIGN §2), for the panel titles.
pub const ROLE: [&str; 3] = ["pitch/yaw", "follower", "straightness"];

/// Half-size used when the service does not say (µm).
const DEFAULT_HALF_UM: f64 = 5000.0;

/// Draw PSD `k` (0..3) into `area`.
pub fn render(frame: &mut Frame, area: Rect, k: usize, psd: Option<&PsdView>, theme: Theme) {
    let title = if area.width >= 24 {
        format!("PSD{} {}", k + 1, ROLE[k])
    } else {
        format!("PSD{}", k + 1)
    };
    let block = panel(&title);
    let inner = block.inner(area);
    frame.render_widget(block, area);
    let [plot, text] = Layout::vertical([Constraint::Min(1), Constraint::Length(2)]).areas(inner);
    let spot = psd.and_then(|p| p.spots_um[k]);
    let half = psd
        .map(|p| p.half_size_um[k])
        .filter(|h| *h > 0.0)
        .unwrap_or(DEFAULT_HALF_UM);
    let m = half * 1.15;
    let (box_color, spot_color, axis_color) = (
        theme.shape(Color::Gray),
        theme.shape(Color::Yellow),
        theme.shape(Color::DarkGray),
    );
    let canvas = Canvas::default()
        .marker(Marker::Braille)
        .x_bounds([-m, m])
        .y_bounds([-m, m])
        .paint(move |ctx| {
            ctx.draw(&Rectangle {
                x: -half,
                y: -half,
                width: 2.0 * half,
                height: 2.0 * half,
                color: box_color,
            });
            let c = half * 0.12;
            ctx.draw(&CLine::new(-c, 0.0, c, 0.0, axis_color));
            ctx.draw(&CLine::new(0.0, -c, 0.0, c, axis_color));
            if let Some([x, y]) = spot {
                ctx.print(
                    x.clamp(-half, half),
                    y.clamp(-half, half),
                    Span::styled("●", ratatui::style::Style::new().fg(spot_color)),
                );
            }
        });
    frame.render_widget(canvas, plot);
    let lines = match (psd, spot) {
        (None, _) => vec![Line::styled("no frame yet", theme.dim())],
        (Some(p), Some([x, y])) => vec![
            Line::raw(format!(
                "X{:>9} Y{:>9} µm",
                signed(Some(x), 1),
                signed(Some(y), 1)
            )),
            sum_line(p.sums_v[k], text.width, theme),
        ],
        (Some(p), None) => vec![
            Line::styled("no beam (SUM below threshold)", theme.bad()),
            sum_line(p.sums_v[k], text.width, theme),
        ],
    };
    frame.render_widget(Paragraph::new(lines), text);
}

fn sum_line(v: f64, width: u16, theme: Theme) -> Line<'static> {
    let value = format!(" {v:.2} V");
    let w = (width as usize).saturating_sub(4 + value.len()).min(30);
    Line::from(vec![
        Span::raw("SUM "),
        Span::styled(bar(v / SUM_FULL_V, w), theme.ok()),
        Span::raw(value),
    ])
}
