//! Calibrate and Publish: in the tab bar already, saying plainly which control-API
//! requests they wait for and what to use until then. Their shapes are the service's to
//! define; nothing here guesses them.

use super::{Theme, panel};
use crate::console::app::App;
use ratatui::Frame;
use ratatui::layout::Rect;
use ratatui::text::Line;
use ratatui::widgets::{Paragraph, Wrap};

fn page(frame: &mut Frame, area: Rect, app: &App, title: &str, lines: Vec<Line<'static>>) {
    let theme = Theme {
        color: app.opts.color,
    };
    let mut all = lines;
    all.insert(
        0,
        Line::styled(
            "Not in this console yet: the control API does not serve it.",
            theme.warn(),
        ),
    );
    frame.render_widget(
        Paragraph::new(all)
            .wrap(Wrap { trim: false })
            .block(panel(title)),
        area,
    );
}

fn waits(requests: &str) -> Line<'static> {
    Line::raw(format!("Waits for the control API's {requests}."))
}

pub fn calibrate(frame: &mut Frame, area: Rect, app: &App) {
    let dim = Theme {
        color: app.opts.color,
    }
    .dim();
    page(
        frame,
        area,
        app,
        "Calibrate",
        vec![
            Line::raw(""),
            waits("calibration requests (none yet)"),
            Line::raw(
                "It will walk through the pose set, the fit (β, offsets, installation) and its validation.",
            ),
            Line::raw(""),
            Line::styled("Until then, offline:", dim),
            Line::styled("  axiscomp calibrate simulate|fit …  (see --help)", dim),
            Line::styled(
                "  then set head.calibration in the configuration and restart the service",
                dim,
            ),
        ],
    );
}

pub fn publish(frame: &mut Frame, area: Rect, app: &App) {
    let dim = Theme {
        color: app.opts.color,
    }
    .dim();
    page(
        frame,
        area,
        app,
        "Publish",
        vec![
            Line::raw(""),
            waits("`table_generate`, `table_publish` and `table_status` requests"),
            Line::raw(
                "It will show the table, a diff against what the PLC holds, ask for the axis name to confirm, and follow the handshake.",
            ),
            Line::raw(""),
            Line::styled("Until then, a controller file from the store:", dim),
            Line::styled("  axiscomp export --run N --format FORMAT --out FILE", dim),
        ],
    );
}
