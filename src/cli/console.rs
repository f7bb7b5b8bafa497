//! `axiscomp console`: the terminal UI over the running service.

use anyhow::{Context, Result};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The service's configuration (default: /etc/axiscomp/axiscomp.toml), for the socket.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Follower jog step on the Align screen (mm; [ and ] change it there).
    #[arg(long, default_value_t = 0.1)]
    pub jog_mm: f64,
    /// Snapshot rate asked of the service (per second).
    #[arg(long, default_value_t = 10.0)]
    pub hz: f64,
}

pub fn run(a: Args) -> Result<()> {
    let socket = match a.socket {
        Some(s) => s,
        None => {
            super::service::settings(a.config.as_deref())?
                .service
                .socket
        }
    };
    if !(a.jog_mm > 0.0 && a.jog_mm <= 10.0) {
        return Err(super::InputError(format!(
            "--jog-mm {}: use a positive number up to 10",
            a.jog_mm
        ))
        .into());
    }
    // The service refuses a subscription outside this range: say so before connecting.
    axiscomp::config::SNAPSHOT_HZ
        .check(a.hz)
        .map_err(|p| super::InputError(format!("--hz: {p}")))?;
    let opts = axiscomp::console::Options {
        socket,
        jog_step_mm: a.jog_mm,
        hz: a.hz,
        color: axiscomp::console::color_from_env(),
    };
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?
        .block_on(axiscomp::console::run(opts))?;
    Ok(())
}
