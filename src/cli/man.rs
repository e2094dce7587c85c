//! `fwlidar man --out DIR`: manual pages generated from the command line's own definition
//! (clap): `fwlidar.1` and one page per subcommand, `fwlidar-<command>.1`. Like the other
//! commands that write files, it never writes over one: if any page already exists in DIR it
//! names them and writes nothing.

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::CommandFactory;

use crate::cli::{Cli, Failure};

/// Arguments of `fwlidar man`.
#[derive(Debug, clap::Args)]
pub struct ManArgs {
    /// Folder to write the pages into (created if missing), e.g. `~/.local/share/man/man1`;
    /// read one with `man -l DIR/fwlidar.1`.
    #[arg(long, short)]
    pub out: PathBuf,
}

/// The manual pages, as (file name, roff text): `fwlidar.1` first, then `fwlidar-<command>.1`
/// for each subcommand in the order of `fwlidar --help`.
pub fn pages() -> Result<Vec<(String, Vec<u8>)>, std::io::Error> {
    let mut cmd = Cli::command();
    // Building names each subcommand `fwlidar-<command>` (its page's title and file name),
    // gives it the usage `fwlidar <command>`, and propagates the global options into it.
    cmd.build();
    let source = format!(
        "fwlidar {}",
        cmd.get_version().unwrap_or(env!("CARGO_PKG_VERSION"))
    );
    let subcommands = cmd
        .get_subcommands()
        .filter(|s| s.get_name() != "help")
        .cloned();
    let mut pages = Vec::new();
    for page in std::iter::once(cmd.clone()).chain(subcommands) {
        let man = clap_mangen::Man::new(page).source(source.clone());
        let mut roff = Vec::new();
        man.render(&mut roff)?;
        pages.push((man.get_filename(), roff));
    }
    Ok(pages)
}

/// Runs `fwlidar man`: refuses (exit 2) when a page would be written over; otherwise writes
/// every page and lists them.
pub fn run(args: ManArgs) -> Result<(), Failure> {
    let pages = pages().map_err(|e| Failure::job(format!("cannot render the pages: {e}")))?;
    let target = |name: &str| -> PathBuf { args.out.join(name) };
    let existing: Vec<String> = pages
        .iter()
        .map(|(name, _)| target(name))
        .filter(|p| p.exists())
        .map(|p| p.display().to_string())
        .collect();
    if !existing.is_empty() {
        return Err(Failure::usage(format!(
            "{} already exist(s); manual pages are never written over (remove them or choose \
             another --out); nothing written",
            existing.join(", ")
        )));
    }
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", args.out.display())))?;
    for (name, roff) in &pages {
        write_new(&target(name), roff)?;
    }
    println!(
        "wrote {} manual pages into {} (fwlidar.1, fwlidar-<command>.1)",
        pages.len(),
        args.out.display()
    );
    Ok(())
}

/// Writes `bytes` to a file that must not exist yet (created exclusively, so a file that
/// appears after the check above is not written over either).
fn write_new(path: &Path, bytes: &[u8]) -> Result<(), Failure> {
    let fail = |e: std::io::Error| Failure::job(format!("cannot write {}: {e}", path.display()));
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(fail)?;
    f.write_all(bytes).and_then(|()| f.sync_all()).map_err(fail)
}
