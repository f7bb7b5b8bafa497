//! Drawing: pure functions of the [`App`] into a ratatui `Frame`, one file per screen. The
//! frame is a tab bar, the screen, and a status bar (message, link, role); overlays (help,
//! confirmation) go on top. Layouts work from 80×24 and use the room at 160×48 and above.

mod align;
mod calibrate;
mod chart;
mod events;
mod live;
mod machine;
mod measure;
mod psd;
mod publish;
mod results;
mod trends;

use super::app::{
    Access, App, Confirm, GLOBAL_KEYS, Input, InputFor, Level, LinkState, Overlay, Screen,
};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::style::{Color, Modifier, Style};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Block, Clear, Paragraph, Wrap};

/// Styles, with or without colour (`NO_COLOR`): without, only modifiers mark things.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Theme {
    pub color: bool,
}

impl Theme {
    fn fg(&self, c: Color) -> Style {
        if self.color {
            Style::new().fg(c)
        } else {
            Style::new()
        }
    }
    /// Normal, healthy state.
    pub fn ok(&self) -> Style {
        self.fg(Color::Green)
    }
    pub fn warn(&self) -> Style {
        if self.color {
            Style::new().fg(Color::Yellow)
        } else {
            Style::new().add_modifier(Modifier::BOLD)
        }
    }
    pub fn bad(&self) -> Style {
        if self.color {
            Style::new().fg(Color::Red).add_modifier(Modifier::BOLD)
        } else {
            Style::new().add_modifier(Modifier::BOLD | Modifier::REVERSED)
        }
    }
    pub fn accent(&self) -> Style {
        self.fg(Color::Cyan).add_modifier(Modifier::BOLD)
    }
    pub fn dim(&self) -> Style {
        if self.color {
            Style::new().fg(Color::DarkGray)
        } else {
            Style::new().add_modifier(Modifier::DIM)
        }
    }
    pub fn selected(&self) -> Style {
        Style::new().add_modifier(Modifier::REVERSED)
    }
    pub fn bold(&self) -> Style {
        Style::new().add_modifier(Modifier::BOLD)
    }
    /// Colour for canvas shapes.
    pub fn shape(&self, c: Color) -> Color {
        if self.color { c } else { Color::Reset }
    }
    pub fn level(&self, l: Level) -> Style {
        match l {
            Level::Info => Style::new(),
            Level::Warn => self.warn(),
            Level::Error => self.bad(),
        }
    }
}

/// Wide layouts from this many columns.
pub const WIDE: u16 = 120;
/// Tall layouts from this many rows.
pub const TALL: u16 = 36;

/// Draw the whole console.
pub fn render(frame: &mut Frame, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let [tabs, body, status] = Layout::vertical([
        Constraint::Length(1),
        Constraint::Min(1),
        Constraint::Length(status_rows(app, frame.area().width)),
    ])
    .areas(frame.area());
    render_tabs(frame, tabs, app, theme);
    let body = banner(frame, body, app, theme);
    match app.screen {
        Screen::Live => live::render(frame, body, app),
        Screen::Align => align::render(frame, body, app),
        Screen::Calibrate => calibrate::render(frame, body, app),
        Screen::Measure => measure::render(frame, body, app),
        Screen::Results if app.trends.shown => trends::render(frame, body, app),
        Screen::Results => results::render(frame, body, app),
        Screen::Publish => publish::render(frame, body, app),
        Screen::Events => events::render(frame, body, app),
        Screen::Machine => machine::render(frame, body, app),
    }
    render_status(frame, status, app, theme);
    match &app.overlay {
        Overlay::None => {}
        Overlay::Help => render_help(frame, app, theme),
        Overlay::Confirm(c) => render_confirm(frame, c, app, theme),
        Overlay::Input(i) => render_input(frame, i, app.input_fresh, theme),
    }
}

fn render_input(frame: &mut Frame, input: &Input, selected: bool, theme: Theme) {
    let (title, about) = match &input.purpose {
        InputFor::PublishAxis { table_id, axis } => (
            " Publish? ".to_string(),
            vec![
                Line::raw(format!(
                    "Table {table_id} changes the compensation axis {axis} applies."
                )),
                Line::raw(format!(
                    "Type the axis name \"{axis}\" and Enter to publish."
                )),
            ],
        ),
        InputFor::PosePath => (
            " Fit a pose set ".to_string(),
            vec![Line::raw(
                "Path of the pose-set CSV on the service's host (axiscomp calibrate simulate writes one):",
            )],
        ),
        InputFor::HexapodPlan => (
            " Calibrate with the hexapod ".to_string(),
            vec![Line::raw(
                "Plan CSV on the service's host (x_mm,y_mm,z_mm,u_deg,v_deg,w_deg[,travel_mm,follower_mm]); empty: 200 poses over the operating window:",
            )],
        ),
        InputFor::ProgramPath => (
            " Save the part program ".to_string(),
            vec![Line::raw(
                "File to write the plan's program to (on this host):",
            )],
        ),
        InputFor::AlignSpan => (
            " Alignment span ".to_string(),
            vec![Line::raw(
                "The travel to align over: near and far end in mm (e.g. 0 400):",
            )],
        ),
        InputFor::AlignTarget => (
            " Target reading ".to_string(),
            vec![Line::raw(
                "The PSD with no spot and what its target shows, X and Y in mm (e.g. 2 1.5 -0.5):",
            )],
        ),
        InputFor::MachineRecord => (
            " A new machine ".to_string(),
            vec![Line::raw(
                "Path of the machine's record (TOML: name, chain, travels, tool, the squares' certificates) on the service's host:",
            )],
        ),
        InputFor::CertificatePath => (
            " Import the follower's certificate ".to_string(),
            vec![Line::raw(
                "Path of the certificate CSV on the service's host (position_mm,error_um,direction,uncertainty_um):",
            )],
        ),
        InputFor::Mapping => (
            " Map the follower ".to_string(),
            vec![Line::raw(
                "The span in mm, then passes and frames a side (e.g. 0 400 2 500):",
            )],
        ),
        InputFor::LevelReading => (
            " The level's reading ".to_string(),
            vec![Line::raw(
                "What the level reads at this station, in arcsec (e.g. -1.25):",
            )],
        ),
    };
    let mut lines = about;
    lines.push(Line::raw(""));
    // The end of a long line stays in view.
    let w = 64usize;
    let chars: Vec<char> = input.text.chars().collect();
    let shown: String = chars[chars.len().saturating_sub(w)..].iter().collect();
    // A suggestion is shown selected: typing replaces it.
    let selected = selected && !shown.is_empty();
    lines.push(Line::from(vec![
        Span::styled("> ", theme.accent()),
        if selected {
            Span::styled(shown, theme.selected())
        } else {
            Span::raw(shown)
        },
        Span::styled("█", theme.dim()),
    ]));
    let footer = Line::styled(
        if selected {
            "typing replaces it, Enter takes it, Esc cancels"
        } else {
            "Enter takes it, Ctrl-U clears, Esc cancels"
        },
        theme.dim(),
    );
    warning_popup(frame, title, lines, footer, 72, theme);
}

/// A centred, bordered popup in the warning colour over whatever is below it.
fn warning_popup<'a>(
    frame: &mut Frame,
    title: impl Into<Line<'a>>,
    lines: Vec<Line<'a>>,
    footer: Line<'a>,
    width: u16,
    theme: Theme,
) {
    let screen = frame.area();
    let width = width.min(screen.width);
    let inner_w = width.saturating_sub(2).max(1) as usize;
    // Rows the body takes once wrapped (word wrapping may take a row more per line than the
    // width suggests; one spare row covers the usual case).
    let body_rows: usize = lines
        .iter()
        .map(|l| l.width().max(1).div_ceil(inner_w))
        .sum::<usize>()
        + 1;
    let height = (body_rows as u16 + 3).min(screen.height);
    let area = centred(screen, width, height);
    frame.render_widget(Clear, area);
    let block = Block::bordered().title(title).border_style(theme.warn());
    let inner = block.inner(area);
    frame.render_widget(block, area);
    // The footer (the keys that answer the popup) always has the last row.
    let [body, foot] = Layout::vertical([Constraint::Min(0), Constraint::Length(1)]).areas(inner);
    frame.render_widget(Paragraph::new(lines).wrap(Wrap { trim: false }), body);
    frame.render_widget(Paragraph::new(footer), foot);
}

fn render_tabs(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    let mut spans = Vec::new();
    // Eight screens fit 80 columns with one space between them, not two.
    let wide: usize = Screen::ALL.iter().map(|s| s.title().len() + 4).sum();
    let pad = if wide <= area.width as usize { " " } else { "" };
    for s in Screen::ALL {
        let label = format!(" {} {}{pad}", s.index() + 1, s.title());
        spans.push(if s == app.screen {
            Span::styled(label, theme.selected().add_modifier(Modifier::BOLD))
        } else {
            Span::raw(label)
        });
    }
    let used: usize = spans.iter().map(|s| s.width()).sum();
    let name = " axiscomp console";
    if (area.width as usize) >= used + name.len() {
        spans.push(Span::styled(
            format!("{name:>w$}", w = area.width as usize - used),
            theme.accent(),
        ));
    }
    frame.render_widget(Line::from(spans), area);
}

/// A one-line warning above the screen when the link is down or the data stale; returns the
/// rest of the area.
fn banner(frame: &mut Frame, area: Rect, app: &App, theme: Theme) -> Rect {
    let text = match (&app.link, app.snapshot.is_some()) {
        (LinkState::Up, true) if !app.stale() => return area,
        (LinkState::Up, _) => "waiting for snapshots from the service".to_string(),
        (LinkState::Connecting, _) => format!("connecting to {}", app.opts.socket),
        (LinkState::Down { error, retry_in }, has) => format!(
            "{}no service: {error}; retrying in {:.1} s",
            if has { "last known values; " } else { "" },
            retry_in.as_secs_f64()
        ),
    };
    let [top, rest] = Layout::vertical([Constraint::Length(1), Constraint::Min(0)]).areas(area);
    frame.render_widget(Paragraph::new(Span::styled(text, theme.bad())), top);
    rest
}

/// The most rows the status bar takes for a long message: the rest stays the screen's.
const STATUS_MAX_ROWS: u16 = 3;

/// The status bar's right side: who and the link, two blanks apart from the message.
fn status_right(app: &App, theme: Theme) -> Line<'static> {
    let link = match &app.link {
        LinkState::Up => Span::styled("● connected", theme.ok()),
        LinkState::Connecting => Span::styled("○ connecting", theme.warn()),
        LinkState::Down { .. } => Span::styled("○ no service", theme.bad()),
    };
    let who = match (app.access, &app.user) {
        (Access::Viewer, _) => Span::styled("read-only (viewer)", theme.warn()),
        (Access::Operator, Some(u)) => Span::raw(format!("operator {u}")),
        (Access::Operator, None) => Span::raw("operator"),
        (Access::Unknown, Some(u)) => Span::raw(u.clone()),
        (Access::Unknown, None) => Span::raw(""),
    };
    // Two blanks keep a long message apart from who and the link.
    Line::from(vec![
        Span::raw("  "),
        who,
        Span::raw("  "),
        link,
        Span::raw(" "),
    ])
}

/// The status bar's message: the last one, or the keys that always work.
fn status_left(app: &App, theme: Theme) -> Line<'static> {
    match &app.message {
        Some(m) => Line::from(Span::styled(format!(" {}", m.text), theme.level(m.level))),
        // The screens' keys from their number, so that a new screen cannot leave it behind.
        None => Line::from(Span::styled(
            format!(" ? help  q quit  1–{}/Tab screens", Screen::ALL.len()),
            theme.dim(),
        )),
    }
}

/// Rows the status bar needs at `width` columns: a message too long for one row (a refusal
/// with its reason, a file the service cannot read) wraps onto up to [`STATUS_MAX_ROWS`]
/// rows rather than losing its end at 80 columns.
fn status_rows(app: &App, width: u16) -> u16 {
    let theme = Theme { color: false };
    let room = width.saturating_sub(status_right(app, theme).width() as u16);
    let text: String = status_left(app, theme)
        .spans
        .iter()
        .map(|s| s.content.as_ref())
        .collect();
    wrapped_rows(&text, room).clamp(1, STATUS_MAX_ROWS)
}

/// Rows `text` takes wrapped at word boundaries to `width` columns (a word longer than a row
/// is broken), as the status bar's paragraph wraps it.
fn wrapped_rows(text: &str, width: u16) -> u16 {
    let width = usize::from(width.max(1));
    let (mut rows, mut used) = (1usize, 0usize);
    for word in text.split(' ') {
        let w = Span::raw(word).width();
        if used > 0 && used + 1 + w <= width {
            used += 1 + w;
            continue;
        }
        if used > 0 {
            rows += 1;
        }
        // On a row of its own; a word longer than a row is broken across rows.
        rows += w.saturating_sub(1) / width;
        used = w - w.saturating_sub(1) / width * width;
    }
    u16::try_from(rows).unwrap_or(u16::MAX)
}

fn render_status(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    let right = status_right(app, theme);
    let rw = right.width() as u16;
    let [left_area, right_area] =
        Layout::horizontal([Constraint::Min(0), Constraint::Length(rw)]).areas(area);
    let [right_area, _] =
        Layout::vertical([Constraint::Length(1), Constraint::Min(0)]).areas(right_area);
    frame.render_widget(
        Paragraph::new(status_left(app, theme)).wrap(Wrap { trim: false }),
        left_area,
    );
    frame.render_widget(right, right_area);
}

/// A centred rectangle of at most `w`×`h` inside `area`.
fn centred(area: Rect, w: u16, h: u16) -> Rect {
    area.centered(
        Constraint::Length(w.min(area.width)),
        Constraint::Length(h.min(area.height)),
    )
}

fn key_lines<'a>(keys: &[(&'a str, &'a str)], theme: Theme) -> Vec<Line<'a>> {
    keys.iter()
        .map(|(k, what)| {
            Line::from(vec![
                Span::styled(format!("  {k:<12}"), theme.bold()),
                Span::raw(*what),
            ])
        })
        .collect()
}

fn render_help(frame: &mut Frame, app: &App, theme: Theme) {
    let keys = super::app::screen_keys(app.screen);
    let mut lines = vec![Line::styled(
        format!("{} screen", app.screen.title()),
        theme.accent(),
    )];
    if keys.is_empty() {
        lines.push(Line::styled("  (no keys of its own)", theme.dim()));
    } else {
        lines.extend(key_lines(keys, theme));
    }
    if app.read_only() && !keys.is_empty() {
        lines.push(Line::styled(
            "  read-only (viewer): keys that change anything are disabled",
            theme.warn(),
        ));
    }
    lines.push(Line::styled("Every screen", theme.accent()));
    lines.extend(key_lines(GLOBAL_KEYS, theme));
    lines.push(Line::styled("any key closes this help", theme.dim()));
    let h = lines.len() as u16 + 2;
    let area = centred(frame.area(), 64, h);
    frame.render_widget(Clear, area);
    frame.render_widget(
        Paragraph::new(lines).block(Block::bordered().title(" Help ")),
        area,
    );
}

fn render_confirm(frame: &mut Frame, c: &Confirm, app: &App, theme: Theme) {
    let (title, lines) = match c {
        Confirm::Quit => (
            " Quit? ",
            vec![
                Line::raw("A run is under way. It goes on in the service;"),
                Line::raw("the console can be started again to follow it."),
            ],
        ),
        Confirm::StartRun(spec) => {
            let checked = app.plan.checked();
            let captures = checked
                .as_ref()
                .map(|p| p.capture_count().to_string())
                .unwrap_or_else(|_| "?".into());
            // The plan's motion and dwell: the least the run takes on the machine.
            let time = checked.as_ref().map_or_else(
                |_| "?".into(),
                |p| {
                    duration(std::time::Duration::from_secs_f64(
                        p.motion_time_s(crate::run::ETA_ACCEL_MM_S2).max(0.0),
                    ))
                },
            );
            (
                " Start the run? ",
                vec![
                    Line::raw(format!(
                        "Axis {}, {} to {} mm, {} targets, {} bidirectional runs",
                        spec.axis, spec.start_mm, spec.end_mm, spec.targets, spec.runs
                    )),
                    Line::raw(format!(
                        "{captures} captures; overrun {} mm, dwell {} s, feed {} mm/min.",
                        spec.overrun_mm, spec.dwell_s, spec.feed_mm_min
                    )),
                    Line::raw(format!(
                        "At least {time} of machine time (motion and dwell; make-up passes add to it)."
                    )),
                    Line::raw("The service writes the part program; the CNC moves the axis."),
                ],
            )
        }
        Confirm::Fit(path) => (
            " Fit the calibration? ",
            vec![
                Line::raw(format!("Fit the pose set {path} on the service's host.")),
                Line::raw(
                    "The result waits for you to accept or reject it; nothing changes until then.",
                ),
            ],
        ),
        Confirm::HexapodStart(plan) => (
            " Start the hexapod calibration? ",
            vec![
                Line::raw(if plan.is_empty() {
                    "The hexapod moves the head's moving module through 200 poses over the operating window.".to_string()
                } else {
                    format!("The hexapod moves the head's moving module through the plan {plan}.")
                }),
                Line::raw(
                    "Keep clear of the platform. The run resumes where it stopped; the fit then waits for you.",
                ),
            ],
        ),
        Confirm::Accept(force) => {
            let concerns = app
                .calibrate
                .pending
                .as_ref()
                .map(|p| p.concerns.clone())
                .unwrap_or_default();
            let what = app
                .calibrate
                .pending
                .as_ref()
                .map(|p| {
                    format!(
                        "{} ({} decoupling, {} poses)",
                        p.source, p.decoupling, p.poses
                    )
                })
                .unwrap_or_else(|| "the pending calibration".into());
            let mut lines = vec![
                Line::raw(format!("Store {what} and decouple with it from now on.")),
                Line::raw("The zero reference is cleared: take it again on screen 2."),
            ];
            if *force {
                lines.push(Line::styled(
                    "OVERRIDE: accepted over its concerns (the service judges it again now):",
                    theme.bad(),
                ));
                lines.extend(
                    concerns
                        .iter()
                        .map(|c| Line::styled(c.clone(), theme.warn())),
                );
            }
            (" Accept the calibration? ", lines)
        }
        Confirm::MapStart(m) => (
            " Map the follower? ",
            vec![
                Line::raw(format!(
                    "Stop-and-go over {}–{} mm in {} mm steps:",
                    m.from_mm.unwrap_or(f64::NAN),
                    m.to_mm.unwrap_or(f64::NAN),
                    m.step_mm.unwrap_or(3.75)
                )),
                Line::raw(format!(
                    "{} passes, {} frames a side.",
                    m.passes.unwrap_or(4),
                    m.frames.unwrap_or(1000)
                )),
                Line::raw(
                    "The part program goes to the CNC (load it on a CNC the service does not drive). At the end the map is stored and put in use, and the zero taken again.",
                ),
                Line::raw(
                    "The service plans the stops and says the machine time as it starts; the follower panel then shows the time left.",
                ),
            ],
        ),
        Confirm::MapStop => (
            " Stop the follower mapping? ",
            vec![Line::raw(
                "Its steps are discarded and nothing is stored; the map in use stays.",
            )],
        ),
        Confirm::LevelCheck => (
            " Check the map in use on this set-up? ",
            vec![
                Line::raw(
                    "A station every 100 mm over the map in use's span, 20 readings of the head and the level at each.",
                ),
                Line::raw(
                    "The stations are fitted as the map's vertical plus this set-up's smooth bend: a map that fits is stored with the bend, put in use, and the zero taken again; one that does not is refused with the span to map again, and the map in use stays.",
                ),
            ],
        ),
        Confirm::LevelStart => (
            " Read the level at stations? ",
            vec![
                Line::raw(
                    "A station every 100 mm over the map in use's span, 20 readings of the head and the level at each.",
                ),
                Line::raw(
                    "The part program goes to the CNC (load it on a CNC the service does not drive). At the end the map is fitted again with the stations, stored, put in use, and the zero taken again.",
                ),
            ],
        ),
        Confirm::LevelStop => (
            " Stop the level stations? ",
            vec![Line::raw(
                "The stations read are discarded and nothing is stored; the map in use stays.",
            )],
        ),
        Confirm::Detach { id, setup, runs } => (
            " Detach the set-up's run? ",
            vec![
                Line::raw(format!(
                    "Runs {} leave set-up {setup} of machine {id} and the set-ups after it; the squarenesses and the model made with them go too.",
                    runs.iter()
                        .map(i64::to_string)
                        .collect::<Vec<_>>()
                        .join(", ")
                )),
                Line::raw(format!(
                    "The runs stay stored; the plan goes on from set-up {setup}, where a run can be attached again."
                )),
            ],
        ),
        Confirm::AbortRun(id) => (
            " Abort the run? ",
            vec![Line::raw(format!(
                "Stop run {}; its captures stay stored.",
                id.map(|i| i.to_string()).unwrap_or_else(|| "?".into())
            ))],
        ),
    };
    let footer = Line::from(vec![
        Span::styled(" y ", theme.selected()),
        Span::raw(" yes    "),
        Span::styled(" n ", theme.selected()),
        Span::raw(" no"),
    ]);
    warning_popup(frame, title, lines, footer, 70, theme);
}

// ---------- formatting shared by the screens ----------

/// A signed value with fixed decimals, or "—".
pub fn signed(v: Option<f64>, decimals: usize) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{v:+.decimals$}"),
        _ => "—".into(),
    }
}

/// A bar of `width` cells filled to `frac` (0..=1).
pub fn bar(frac: f64, width: usize) -> String {
    let f = if frac.is_finite() {
        frac.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let full = (f * width as f64).round() as usize;
    format!("{}{}", "█".repeat(full), "░".repeat(width - full))
}

/// `1 h 02 min`, `3 min 05 s`, `42 s`.
pub fn duration(d: std::time::Duration) -> String {
    let s = d.as_secs();
    if s >= 3600 {
        format!("{} h {:02} min", s / 3600, (s % 3600) / 60)
    } else if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}

/// `HH:MM:SS` UTC of µs since the epoch.
pub fn clock_utc(unix_us: i64) -> String {
    let s = unix_us.div_euclid(1_000_000).rem_euclid(86_400);
    format!("{:02}:{:02}:{:02}", s / 3600, (s % 3600) / 60, s % 60)
}

/// "2026-11-25 17:39" (UTC) from µs since the epoch: the date a run or table is found by.
pub fn date_utc(unix_us: i64) -> String {
    let t = crate::store::iso_utc(unix_us);
    // "2026-11-25T17:39:03Z" → "2026-11-25 17:39".
    format!("{} {}", &t[..10], &t[11..16])
}

/// A titled, bordered block.
pub fn panel(title: &str) -> Block<'_> {
    Block::bordered().title(format!(" {title} "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats() {
        assert_eq!(signed(Some(1.234), 2), "+1.23");
        assert_eq!(signed(Some(-0.5), 1), "-0.5");
        assert_eq!(signed(None, 1), "—");
        assert_eq!(bar(0.5, 4), "██░░");
        assert_eq!(bar(f64::NAN, 2), "░░");
        assert_eq!(duration(std::time::Duration::from_secs(3725)), "1 h 02 min");
        assert_eq!(duration(std::time::Duration::from_secs(185)), "3 min 05 s");
        assert_eq!(clock_utc(1_700_000_000_000_000), "22:13:20");
    }

    #[test]
    fn a_message_wraps_at_word_boundaries_and_breaks_a_long_word() {
        assert_eq!(wrapped_rows("", 10), 1);
        assert_eq!(wrapped_rows("abc def", 7), 1);
        assert_eq!(wrapped_rows("abc def", 6), 2);
        assert_eq!(wrapped_rows("abcdefghij", 4), 3);
        assert_eq!(wrapped_rows("ab abcdefghij", 4), 4);
        assert_eq!(wrapped_rows("µµµ µµµ", 7), 1);
    }
}
