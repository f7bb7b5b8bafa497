//! The terminal for the console's life: raw mode, the alternate screen, no cursor — and all of
//! it undone on exit, on error and on panic (the panic message then prints on a sane
//! terminal).

use ratatui::Terminal;
use ratatui::backend::CrosstermBackend;
use std::io::{self, IsTerminal, Stdout};
use thiserror::Error;

/// The console's terminal.
pub type Term = Terminal<CrosstermBackend<Stdout>>;

/// Why the terminal could not be set up.
#[derive(Debug, Error)]
pub enum TermError {
    #[error("the console needs a terminal: standard input and output must both be one")]
    NotATerminal,
    #[error("setting up the terminal: {0}")]
    Io(#[from] io::Error),
}

/// Holds the terminal in console mode; dropping it restores the terminal.
pub struct TerminalGuard {
    pub terminal: Term,
}

impl TerminalGuard {
    /// Enter console mode (and install the panic hook that leaves it).
    pub fn enter() -> Result<TerminalGuard, TermError> {
        if !io::stdout().is_terminal() || !io::stdin().is_terminal() {
            return Err(TermError::NotATerminal);
        }
        install_panic_hook();
        crossterm::terminal::enable_raw_mode()?;
        let setup = || -> io::Result<Term> {
            crossterm::execute!(
                io::stdout(),
                crossterm::terminal::EnterAlternateScreen,
                crossterm::cursor::Hide
            )?;
            let mut t = Terminal::new(CrosstermBackend::new(io::stdout()))?;
            t.clear()?;
            Ok(t)
        };
        match setup() {
            Ok(terminal) => Ok(TerminalGuard { terminal }),
            Err(e) => {
                let _ = restore();
                Err(e.into())
            }
        }
    }
}

impl Drop for TerminalGuard {
    fn drop(&mut self) {
        let _ = restore();
    }
}

/// Leave console mode (safe to call more than once).
pub fn restore() -> io::Result<()> {
    let raw = crossterm::terminal::disable_raw_mode();
    crossterm::execute!(
        io::stdout(),
        crossterm::terminal::LeaveAlternateScreen,
        crossterm::cursor::Show
    )?;
    raw
}

/// Restore the terminal before the default panic output.
fn install_panic_hook() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let _ = restore();
            previous(info);
        }));
    });
}
