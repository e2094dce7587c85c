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
        /// Stores per merge of the merge tree, 2 or more (default: every store in one merge,
        /// the fastest on one node; a tree pays one more pass over the tiles per level).
        #[arg(long)]
        fan_in: Option<usize>,
    },
    /// Write the Slurm jobs into `<out>/slurm/` — an array job with one task per line not yet
    /// done, and a merge job after it (`--dependency=afterok`) — and submit them with sbatch.
    Submit {
        /// The campaign file.
        file: PathBuf,
        /// `#SBATCH --partition` (default: the cluster's).
        #[arg(long)]
        partition: Option<String>,
        /// `#SBATCH --time` of a line task.
        #[arg(long, default_value = "04:00:00")]
        time: String,
        /// `#SBATCH --time` of the merge job.
        #[arg(long, default_value = "04:00:00")]
        merge_time: String,
        /// `#SBATCH --cpus-per-task`.
        #[arg(long, default_value_t = 2)]
        cpus: usize,
        /// `#SBATCH --mem` of a line task, MB (default: the tile budget's model, in the script).
        #[arg(long)]
        mem_mb: Option<u64>,
        /// Stores per merge of the merge tree, 2 or more (default: every store in one merge,
        /// the fastest on one node; a tree pays one more pass over the tiles per level).
        #[arg(long)]
        fan_in: Option<usize>,
        /// Nodes the merge is spread over: G > 1 adds an array job of G group merges (each the
        /// stores of neighbouring lines, on a node of its own) between the lines and the last
        /// merge, which then merges the G group stores.
        #[arg(long, default_value_t = 1)]
        merge_nodes: usize,
        /// Write the scripts and print the sbatch commands without running them.
        #[arg(long)]
        dry_run: bool,
    },
    /// One line of the plan (what a Slurm array task runs): its replay, unless done.
    Task {
        /// The campaign file.
        file: PathBuf,
        /// The task's number in the plan (`$SLURM_ARRAY_TASK_ID`).
        #[arg(long)]
        index: usize,
    },
    /// The merge job: every task's store merged into `mosaic.zarr`, then the metrics rasters
    /// and `campaign.json`. Refused while a task is not done. With `--groups G`, the G group
    /// stores (merging those not there yet); with `--group g` too, only that group (a task of
    /// the merge groups' array).
    Merge {
        /// The campaign file.
        file: PathBuf,
        /// Merge groups (2 or more; `submit --merge-nodes`): the tasks cut into G runs of
        /// neighbouring lines, each merged on its own first.
        #[arg(long, default_value_t = 1)]
        groups: usize,
        /// Merge only this group (0-based; `$SLURM_ARRAY_TASK_ID`) into `merge/`, then stop.
        #[arg(long)]
        group: Option<usize>,
        /// Merges at once.
        #[arg(long, default_value_t = 1)]
        processes: usize,
        /// Stores per merge of the merge tree, 2 or more (default: every store in one merge,
        /// the fastest on one node; a tree pays one more pass over the tiles per level).
        #[arg(long)]
        fan_in: Option<usize>,
    },
}

fn failure(e: CampaignError) -> Failure {
    match e {
        CampaignError::Run(m) => Failure::job(m),
        other => Failure::usage(other),
    }
}

fn exe() -> Result<PathBuf, Failure> {
    std::env::current_exe()
        .map_err(|e| Failure::job(format!("cannot find the fwlidar executable: {e}")))
}

/// `--fan-in`: 2 or more; `None` becomes 0, every store in one merge.
fn check_fan_in(fan_in: Option<usize>) -> Result<usize, Failure> {
    match fan_in {
        Some(k) if k < 2 => Err(Failure::usage(format!(
            "--fan-in must be at least 2 (got {k}); leave it out to merge every store at once"
        ))),
        k => Ok(k.unwrap_or(0)),
    }
}

/// The few lines a campaign run or merge ends with (the whole report is `campaign.json`).
fn print_report(r: &crate::campaign::local::CampaignReport) {
    let ran = r.lines.iter().filter(|l| l.ran).count();
    println!(
        "campaign {}: {} tasks ({} replayed now, {} done before), {} pulses in, {} dropped",
        r.campaign,
        r.lines.len(),
        ran,
        r.lines.len() - ran,
        r.lines.iter().map(|l| l.pulses_in).sum::<u64>(),
        r.lines.iter().map(|l| l.dropped).sum::<u64>(),
    );
    println!(
        "  merge of {} stores in {} levels ({} merges, fan-in {}) into {}: {} tiles, {:.1} s",
        r.lines.len(),
        r.merge.levels,
        r.merge.merges,
        r.merge.fan_in,
        r.mosaic,
        r.merge.tiles,
        r.merge.wall_s
    );
    if let Some(m) = r
        .metrics
        .as_ref()
        .and_then(|m| serde_json::from_value::<MetricsLine>(m.clone()).ok())
    {
        println!(
            "  metrics rasters: {} of {} cells with a canopy height, {:.1} s",
            m.cells_ok[0], m.cells[0], m.seconds
        );
    }
    let outside: Vec<String> = r
        .lines
        .iter()
        .filter(|l| l.bins_outside_grid > 0)
        .map(|l| format!("{} ({})", l.name, l.bins_outside_grid))
        .collect();
    if !outside.is_empty() {
        println!(
            "  warning: samples outside the campaign's grid were not deposited: {}; give \
             voxels.extent_m covering the campaign (docs/campaign.md, \"One grid\")",
            outside.join(", ")
        );
    }
    println!("  {:.1} s wall; report in campaign.json", r.wall_s);
}

/// Runs `fwlidar campaign`.
pub fn run(args: CampaignArgs) -> Result<(), Failure> {
    match args.action {
        CampaignAction::Submit {
            file,
            partition,
            time,
            merge_time,
            cpus,
            mem_mb,
            fan_in,
            merge_nodes,
            dry_run,
        } => {
            if cpus == 0 {
                return Err(Failure::usage("--cpus must be at least 1 (got 0)"));
            }
            let fan_in = check_fan_in(fan_in)?;
            let p = plan(&file).map_err(failure)?;
            let o = crate::campaign::slurm::SlurmOptions {
                partition,
                line_time: time,
                merge_time,
                cpus,
                mem_mb,
                fan_in,
                merge_nodes: merge_nodes.max(1),
                exe: exe()?,
            };
            let s = crate::campaign::slurm::submit(&p, &o, dry_run).map_err(failure)?;
            for script in [&s.lines_script, &s.groups_script].into_iter().flatten() {
                println!("wrote {}", script.display());
            }
            println!("wrote {}", s.merge_script.display());
            for c in &s.commands {
                println!(
                    "{}{c}",
                    if dry_run {
                        "to submit: "
                    } else {
                        "submitted: "
                    }
                );
            }
            if !s.job_ids.is_empty() {
                println!("jobs {}", s.job_ids.join(", "));
            }
            Ok(())
        }
        CampaignAction::Task { file, index } => {
            let p = plan(&file).map_err(failure)?;
            let r = crate::campaign::local::run_task(&p, index, &exe()?).map_err(failure)?;
            println!(
                "line {}: {} ({} pulses in, {} dropped, {:.1} s wall, {:.1} s CPU)",
                r.name,
                if r.ran { "replayed" } else { "already done" },
                r.pulses_in,
                r.dropped,
                r.wall_s,
                r.cpu_s
            );
            Ok(())
        }
        CampaignAction::Merge {
            file,
            groups,
            group,
            processes,
            fan_in,
        } => {
            if processes == 0 {
                return Err(Failure::usage("--processes must be at least 1 (got 0)"));
            }
            let fan_in = check_fan_in(fan_in)?;
            let p = plan(&file).map_err(failure)?;
            if let Some(g) = group {
                let t = std::time::Instant::now();
                let merged = crate::campaign::local::merge_group(&p, g, groups).map_err(failure)?;
                println!(
                    "merge group {g} of {groups} ({} tasks): {} {}",
                    crate::campaign::local::group_tasks(&p, g, groups).len(),
                    if merged {
                        format!("merged in {:.1} s into", t.elapsed().as_secs_f64())
                    } else {
                        "already merged in".to_string()
                    },
                    crate::campaign::local::group_store(&p, g, groups).display()
                );
                return Ok(());
            }
            let r = crate::campaign::local::merge_campaign(
                &p,
                processes,
                fan_in,
                groups,
                &[],
                std::time::Instant::now(),
            )
            .map_err(failure)?;
            print_report(&r);
            Ok(())
        }
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
            if local == 0 {
                return Err(Failure::usage("--local must be at least 1 (got 0)"));
            }
            let fan_in = check_fan_in(fan_in)?;
            let p = plan(&file).map_err(failure)?;
            eprint!("{}", p.describe());
            let exe = exe()?;
            let r = run_local(
                &p,
                &LocalOptions {
                    processes: local,
                    fan_in,
                    exe,
                },
            )
            .map_err(failure)?;
            print_report(&r);
            Ok(())
        }
    }
}

/// What the summary of a campaign shows of its mosaic's `rasters/metrics.json`: the cells with
/// a canopy height and all cells (canopy height model first), and the time taken.
#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct MetricsLine {
    cells_ok: [u64; 2],
    cells: [u64; 2],
    seconds: f64,
}
