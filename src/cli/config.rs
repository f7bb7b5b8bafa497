//! `axiscomp config`: the configuration's reference and its documented example, as the
//! binary carries them (no repository needed on the machine).

use anyhow::Result;
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Every key with its built-in default, environment variable and meaning (Markdown: the
    /// guide's configuration reference).
    Reference,
    /// The documented example configuration (configs/axiscomp.toml), to copy to
    /// /etc/axiscomp/axiscomp.toml and edit.
    Example,
}

pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Reference => print!("{}", axiscomp::config::reference::markdown()?),
        Command::Example => print!("{}", axiscomp::config::reference::EXAMPLE),
    }
    Ok(())
}
