//! `axiscomp console`: the commissioning and maintenance terminal UI (DESIGN §8), a ratatui
//! app over the control API and nothing else — no measurement logic of its own.
//!
//! - `client`: the control-API client (snapshot stream and requests, reconnecting);
//! - `app`: the state, sans-I/O (keys, snapshots and replies in; requests out);
//! - `ui`: one pure `render` per screen;
//! - `term`: terminal set-up and restore (also on panic).
//!
//! Live, Align, Calibrate (fit a pose set, judge, accept or reject), Measure (plan, part
//! program, start/abort, progress, live plot), Results (stored runs, six charts, ISO figures,
//! before/after), Publish (tables, the PLC's against them, generate, publish with the axis
//! name typed) and Events. Viewers get a read-only console;
//! `NO_COLOR` turns colours off; 80×24 is the smallest layout.

pub mod app;
pub mod client;
pub mod term;
pub mod ui;

use app::{Action, App, AppOptions};
use client::{Client, ClientOptions};
use crossterm::event::Event;
use futures_util::{Stream, StreamExt};
use ratatui::Terminal;
use ratatui::backend::Backend;
use std::path::PathBuf;
use std::time::Duration;
use thiserror::Error;

/// What the console is started with.
#[derive(Clone, Debug)]
pub struct Options {
    pub socket: PathBuf,
    /// Follower jog step on the Align screen (mm).
    pub jog_step_mm: f64,
    /// Snapshot rate asked of the service.
    pub hz: f64,
    /// Colours (see [`color_from_env`]).
    pub color: bool,
}

/// How often the screen is redrawn (and time-driven state advances).
pub const DRAW_EVERY: Duration = Duration::from_millis(100);

/// Why the console stopped with an error.
#[derive(Debug, Error)]
pub enum ConsoleError {
    #[error(transparent)]
    Term(#[from] term::TermError),
    #[error("drawing: {0}")]
    Draw(String),
    #[error("reading the keyboard: {0}")]
    Input(std::io::Error),
    #[error("signal handler: {0}")]
    Signal(std::io::Error),
    #[error("jog step {0} mm: use a positive number up to 10")]
    JogStep(f64),
}

/// Colours unless `NO_COLOR` is set to something (https://no-color.org).
pub fn color_from_env() -> bool {
    std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

/// Run the console on this terminal until the operator quits, the terminal goes away
/// (SIGHUP) or SIGTERM.
pub async fn run(opts: Options) -> Result<(), ConsoleError> {
    if !(opts.jog_step_mm > 0.0 && opts.jog_step_mm <= 10.0) {
        return Err(ConsoleError::JogStep(opts.jog_step_mm));
    }
    use tokio::signal::unix::{SignalKind, signal};
    let mut term_sig = signal(SignalKind::terminate()).map_err(ConsoleError::Signal)?;
    let mut hup = signal(SignalKind::hangup()).map_err(ConsoleError::Signal)?;
    let mut guard = term::TerminalGuard::enter()?;
    let mut client = Client::spawn(ClientOptions {
        hz: opts.hz,
        ..ClientOptions::new(opts.socket.clone())
    });
    let mut app = App::new(
        AppOptions {
            socket: opts.socket.display().to_string(),
            jog_step_mm: opts.jog_step_mm,
            color: opts.color,
        },
        crate::util::clock::now(),
    );
    let keys = crossterm::event::EventStream::new();
    tokio::select! {
        r = drive(&mut guard.terminal, &mut app, keys, &mut client, DRAW_EVERY) => r,
        _ = term_sig.recv() => Ok(()),
        _ = hup.recv() => Ok(()),
    }
}

fn draw<B: Backend>(terminal: &mut Terminal<B>, app: &App) -> Result<(), ConsoleError> {
    terminal
        .draw(|f| ui::render(f, app))
        .map(|_| ())
        .map_err(|e| ConsoleError::Draw(e.to_string()))
}

/// The event loop: keys, the client's events and a draw tick in; actions out. Generic over
/// the backend and the key stream so it runs on a `TestBackend` too. Returns on quit, or
/// when the key stream ends.
pub async fn drive<B, K>(
    terminal: &mut Terminal<B>,
    app: &mut App,
    mut keys: K,
    client: &mut Client,
    draw_every: Duration,
) -> Result<(), ConsoleError>
where
    B: Backend,
    K: Stream<Item = std::io::Result<Event>> + Unpin,
{
    let mut tick = tokio::time::interval(draw_every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        let actions = tokio::select! {
            _ = tick.tick() => {
                let a = app.tick(crate::util::clock::now());
                draw(terminal, app)?;
                a
            }
            key = keys.next() => match key {
                Some(Ok(Event::Key(k))) => {
                    let a = app.handle_key(k);
                    draw(terminal, app)?;
                    a
                }
                Some(Ok(Event::Resize(..))) => {
                    draw(terminal, app)?;
                    Vec::new()
                }
                Some(Ok(_)) => Vec::new(),
                Some(Err(e)) => return Err(ConsoleError::Input(e)),
                None => return Ok(()),
            },
            ev = client.events.recv() => match ev {
                Some(ev) => app.handle_link_event(ev, crate::util::clock::now()),
                None => return Ok(()),
            },
        };
        for action in actions {
            match action {
                Action::Quit => return Ok(()),
                Action::Send { id, request } => {
                    if let Err(e) = client.send(id, request).await {
                        app.handle_reply(id, Err(e), crate::util::clock::now());
                    }
                }
                Action::Save { path, text } => {
                    let r = tokio::fs::write(&path, text)
                        .await
                        .map_err(|e| e.to_string());
                    app.handle_saved(&path, r);
                }
            }
        }
    }
}
