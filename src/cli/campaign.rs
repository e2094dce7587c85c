//! `fwlidar campaign plan FILE` and `fwlidar campaign run FILE --local N`: a survey campaign's
//! flight lines replayed with one configuration and merged exactly into one mosaic
//! (`crate::campaign`, `docs/campaign.md`).

use std::path::PathBuf;

use crate::campaign::local::{LocalOptions, run_local};
use crate::campaign::{CampaignError, plan};
use crate::cli::Failure;

/// Arguments of `fwlidar campaign`.
#[derive(Debug, clap::Args)]
pub struct CampaignArgs {
    /// What to do.
    #[command(subcommand)]
    pub action: CampaignAction,
}

/// `fwlidar campaign` actions.
#[derive(Debug, clap::Subcommand)]
pub enum CampaignAction {
    /// Check a campaign file (every capture readable, one configuration, one CRS) and print
    /// its tasks: one per flight line, and the merge.
    Plan {
        /// The campaign file (TOML, `[campaign]`).
        file: PathBuf,
    },
    /// Run the plan on this machine: the lines not yet done with N processes at once, then the
    /// merge tree into `mosaic.zarr` and `campaign.json`.
    Run {
        /// The campaign file.
        file: PathBuf,
        /// Processes at once.
        #[arg(long, default_value_t = 1)]
        local: usize,
        /// Stores per merge in the merge tree (2 or more).
        #[arg(long, default_value_t = 4)]
        fan_in: usize,
    },
}

fn failure(e: CampaignError) -> Failure {
    match e {
        CampaignError::Run(m) => Failure::job(m),
        other => Failure::usage(other),
    }
}

/// Runs `fwlidar campaign`.
pub fn run(args: CampaignArgs) -> Result<(), Failure> {
    match args.action {
        CampaignAction::Plan { file } => {
            let p = plan(&file).map_err(failure)?;
            print!("{}", p.describe());
            Ok(())
        }
        CampaignAction::Run {
            file,
            local,
            fan_in,
        } => {
            if local == 0 || fan_in < 2 {
                return Err(Failure::usage(format!(
                    "--local must be at least 1 and --fan-in at least 2 (got {local} and {fan_in})"
                )));
            }
            let p = plan(&file).map_err(failure)?;
            eprint!("{}", p.describe());
            let exe = std::env::current_exe()
                .map_err(|e| Failure::job(format!("cannot find the fwlidar executable: {e}")))?;
            let r = run_local(
                &p,
                &LocalOptions {
                    processes: local,
                    fan_in,
                    exe,
                },
            )
            .map_err(failure)?;
            let ran = r.lines.iter().filter(|l| l.ran).count();
            println!(
                "campaign {}: {} lines ({} replayed now, {} done before), {} pulses in, {} \
                 dropped; merge of {} stores in {} levels ({} merges, fan-in {}) into {}: {} \
                 tiles; {:.1} s wall",
                r.campaign,
                r.lines.len(),
                ran,
                r.lines.len() - ran,
                r.lines.iter().map(|l| l.pulses_in).sum::<u64>(),
                r.lines.iter().map(|l| l.dropped).sum::<u64>(),
                r.lines.len(),
                r.merge.levels,
                r.merge.merges,
                r.merge.fan_in,
                r.mosaic,
                r.merge.tiles,
                r.wall_s
            );
            Ok(())
        }
    }
}
