//! `fwlidar completions SHELL`: the shell completion script for fwlidar, generated from the
//! command line's own definition (clap), on standard output.

use std::io::Write;

use clap::CommandFactory;

use crate::cli::{Cli, Failure};

/// Arguments of `fwlidar completions`.
#[derive(Debug, clap::Args)]
pub struct CompletionsArgs {
    /// The shell to complete in. Install the script where the shell looks, e.g.
    /// `fwlidar completions bash > ~/.local/share/bash-completion/completions/fwlidar`,
    /// `fwlidar completions zsh > ~/.zfunc/_fwlidar`,
    /// `fwlidar completions fish > ~/.config/fish/completions/fwlidar.fish`.
    #[arg(value_enum)]
    pub shell: clap_complete::Shell,
}

/// The completion script for `shell`.
pub fn script(shell: clap_complete::Shell) -> Vec<u8> {
    let mut cmd = Cli::command();
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut cmd, "fwlidar", &mut script);
    script
}

/// Runs `fwlidar completions`: writes the script to standard output.
pub fn run(args: CompletionsArgs) -> Result<(), Failure> {
    let mut out = std::io::stdout().lock();
    out.write_all(&script(args.shell))
        .and_then(|()| out.flush())
        .map_err(|e| Failure::job(format!("cannot write the completion script: {e}")))
}
