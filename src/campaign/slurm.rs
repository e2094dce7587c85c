//! The campaign on a Slurm cluster (`fwlidar campaign submit`): an `sbatch --array` job with one
//! task per flight line not yet done (`fwlidar campaign task FILE --index I`) and a merge job
//! that starts when every array task has succeeded (`--dependency=afterok`) and runs
//! `fwlidar campaign merge FILE`. The scripts are written to `<out>/slurm/` and are meant to be
//! read and edited: the `#SBATCH` lines a user changes are at the top, with the memory model.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::campaign::{CampaignError, Plan};

/// Resources of the jobs.
#[derive(Clone, Debug, PartialEq)]
pub struct SlurmOptions {
    /// `--partition` (none: the cluster's default).
    pub partition: Option<String>,
    /// `--time` of a line task, `HH:MM:SS` or what `sbatch` takes.
    pub line_time: String,
    /// `--time` of the merge job.
    pub merge_time: String,
    /// CPUs per line task (the replay's workers follow).
    pub cpus: usize,
    /// Memory per line task, MB (default: [`line_memory_mb`]).
    pub mem_mb: Option<u64>,
    /// Stores per merge in the merge job's tree (0: all in one merge).
    pub fan_in: usize,
    /// Nodes the merge is spread over: more than 1 adds an array job of that many group merges
    /// before the last merge.
    pub merge_nodes: usize,
    /// The `fwlidar` executable on the cluster's nodes.
    pub exe: PathBuf,
}

/// Memory a line's replay needs, MB, from the tile budget of its configuration: the open voxel
/// tiles (`max_open_tiles`, each at most `ceil(levels / chunk_levels)` height chunks of
/// 20 bytes × columns² × chunk levels; a survey-line tile holds 4–6, so 6 are counted) plus
/// 1 GB for the process, its pulse pools and queues and the written tiles' buffers.
pub fn line_memory_mb(plan: &Plan) -> u64 {
    let v = &plan.config.voxels;
    let chunk_bytes =
        20 * u64::from(v.tile_columns) * u64::from(v.tile_columns) * u64::from(v.chunk_levels);
    let tiles = v.max_open_tiles as u64;
    1024 + (tiles * 6 * chunk_bytes).div_ceil(1 << 20)
}

fn abs(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

/// The array job's script for the tasks `ids`.
pub fn lines_script(plan: &Plan, ids: &[usize], o: &SlurmOptions) -> String {
    let mem = o.mem_mb.unwrap_or_else(|| line_memory_mb(plan));
    let v = &plan.config.voxels;
    let mut s = String::from("#!/bin/bash\n");
    let _ = writeln!(
        s,
        "# fwlidar campaign {:?}: one array task per flight line not yet done ({} of {}).\n\
         # Each task replays its line into {}/lines/<name>/ and leaves done.json there;\n\
         # resubmitting the campaign (`fwlidar campaign submit`) runs only the lines without it.\n\
         # docs/campaign.md explains every line. Change the #SBATCH lines for your cluster:\n\
         # memory model: 1024 MB + max_open_tiles ({}) x 6 height chunks x 20 B x {}^2 columns x\n\
         # {} levels = {} MB (give more for lines that cross many tiles at once).",
        plan.campaign.name,
        ids.len(),
        plan.tasks.len(),
        abs(&plan.out).display(),
        v.max_open_tiles,
        v.tile_columns,
        v.chunk_levels,
        line_memory_mb(plan)
    );
    sbatch_lines(&mut s, plan, o, "lines", &o.line_time, mem, "line_%a.log");
    let list: Vec<String> = ids.iter().map(usize::to_string).collect();
    let _ = writeln!(s, "#SBATCH --array={}", list.join(","));
    let _ = writeln!(
        s,
        "set -euo pipefail\nexec {:?} campaign task {:?} --index \"$SLURM_ARRAY_TASK_ID\"",
        o.exe.display().to_string(),
        abs(&plan.file).display().to_string()
    );
    s
}

/// The merge job's script.
pub fn merge_script(plan: &Plan, o: &SlurmOptions) -> String {
    let mut s = String::from("#!/bin/bash\n");
    let (shape, flag) = if o.fan_in == 0 {
        ("in one merge".to_string(), String::new())
    } else {
        (
            format!("as a tree of {}-way merges", o.fan_in),
            format!(" --fan-in {}", o.fan_in),
        )
    };
    let _ = writeln!(
        s,
        "# fwlidar campaign {:?}: merges the {} task stores {shape} into\n\
         # {}/mosaic.zarr (the bytes of one replay of every line in sequence), writes the\n\
         # forest-metrics rasters of it into rasters/ unless the campaign says metrics = false,\n\
         # and campaign.json. Submitted with --dependency=afterok on the lines' array job, so it\n\
         # starts only when every task succeeded. Memory: one tile per store at a time.",
        plan.campaign.name,
        plan.tasks.len(),
        abs(&plan.out).display()
    );
    sbatch_lines(&mut s, plan, o, "merge", &o.merge_time, 2048, "merge.log");
    let groups = if o.merge_nodes > 1 {
        format!(" --groups {}", o.merge_nodes)
    } else {
        String::new()
    };
    let _ = writeln!(
        s,
        "set -euo pipefail\nexec {:?} campaign merge {:?} --processes \"${{SLURM_CPUS_PER_TASK:-1}}\"{groups}{flag}",
        o.exe.display().to_string(),
        abs(&plan.file).display().to_string(),
    );
    s
}

/// The merge groups' array job (`--merge-nodes G`): task `g` merges the stores of the `g`-th
/// run of neighbouring lines into `merge/group<g>of<G>.zarr`, each on a node of its own.
pub fn groups_script(plan: &Plan, o: &SlurmOptions) -> String {
    let g = o.merge_nodes;
    let mut s = String::from("#!/bin/bash\n");
    let _ = writeln!(
        s,
        "# fwlidar campaign {:?}: the merge spread over {g} nodes. Array task g merges the\n\
         # stores of the g-th of {g} runs of neighbouring tasks (in plan order) into\n\
         # {}/merge/group<g>of{g}.zarr; the merge job after this array merges the {g} group\n\
         # stores (tiles only one group holds are copied as they are). Submitted with\n\
         # --dependency=afterok on the lines' array job.",
        plan.campaign.name,
        abs(&plan.out).display()
    );
    sbatch_lines(
        &mut s,
        plan,
        o,
        "groups",
        &o.merge_time,
        2048,
        "group_%a.log",
    );
    let _ = writeln!(s, "#SBATCH --array=0-{}", g - 1);
    let _ = writeln!(
        s,
        "set -euo pipefail\nexec {:?} campaign merge {:?} --groups {g} --group \"$SLURM_ARRAY_TASK_ID\"",
        o.exe.display().to_string(),
        abs(&plan.file).display().to_string(),
    );
    s
}

/// The `#SBATCH` lines both jobs share: name, partition, time, CPUs, memory (MB), log file.
fn sbatch_lines(
    s: &mut String,
    plan: &Plan,
    o: &SlurmOptions,
    job: &str,
    time: &str,
    mem_mb: u64,
    log: &str,
) {
    let _ = writeln!(s, "#SBATCH --job-name=fwlidar-{}-{job}", plan.campaign.name);
    if let Some(p) = &o.partition {
        let _ = writeln!(s, "#SBATCH --partition={p}");
    }
    let _ = writeln!(s, "#SBATCH --time={time}");
    let _ = writeln!(s, "#SBATCH --cpus-per-task={}", o.cpus);
    let _ = writeln!(s, "#SBATCH --mem={mem_mb}M");
    let _ = writeln!(
        s,
        "#SBATCH --output={}/slurm/{log}",
        abs(&plan.out).display()
    );
}

/// What `submit` wrote and did.
#[derive(Clone, Debug, PartialEq)]
pub struct Submitted {
    /// The array job's script (`None` when every line is done).
    pub lines_script: Option<PathBuf>,
    /// The merge groups' array job's script (`--merge-nodes` > 1).
    pub groups_script: Option<PathBuf>,
    /// The merge job's script.
    pub merge_script: PathBuf,
    /// The commands run (or to run, with `dry_run`).
    pub commands: Vec<String>,
    /// Job ids from `sbatch --parsable` (empty with `dry_run`).
    pub job_ids: Vec<String>,
}

fn sbatch(args: &[&str]) -> Result<String, CampaignError> {
    let o = Command::new("sbatch").args(args).output().map_err(|e| {
        CampaignError::Run(format!(
            "cannot run sbatch ({e}): is this a Slurm login node? `--dry-run` writes the \
             scripts only, `fwlidar campaign run --local N` runs here"
        ))
    })?;
    if !o.status.success() {
        return Err(CampaignError::Run(format!(
            "sbatch {} failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        )));
    }
    // --parsable prints "jobid" or "jobid;cluster".
    Ok(String::from_utf8_lossy(&o.stdout)
        .trim()
        .split(';')
        .next()
        .unwrap_or_default()
        .to_string())
}

/// Writes the scripts into `<out>/slurm/` and, unless `dry_run`, submits them.
pub fn submit(plan: &Plan, o: &SlurmOptions, dry_run: bool) -> Result<Submitted, CampaignError> {
    crate::campaign::local::prepare_folder(plan)?;
    let dir = plan.out.join("slurm");
    std::fs::create_dir_all(&dir)
        .map_err(|e| CampaignError::Run(format!("cannot create {}: {e}", dir.display())))?;
    let ids: Vec<usize> = plan
        .tasks
        .iter()
        .filter(|t| !t.done)
        .map(|t| t.id)
        .collect();
    let write = |name: &str, text: String| -> Result<PathBuf, CampaignError> {
        let p = dir.join(name);
        std::fs::write(&p, text)
            .map_err(|e| CampaignError::Run(format!("cannot write {}: {e}", p.display())))?;
        Ok(p)
    };
    let lines = if ids.is_empty() {
        // Every line is done: no array job; an earlier one's script would mislead.
        let old = dir.join("lines.sbatch");
        if old.exists() {
            std::fs::remove_file(&old)
                .map_err(|e| CampaignError::Run(format!("cannot remove {}: {e}", old.display())))?;
        }
        None
    } else {
        Some(write("lines.sbatch", lines_script(plan, &ids, o))?)
    };
    if o.merge_nodes > plan.tasks.len() {
        return Err(CampaignError::Run(format!(
            "--merge-nodes {} is more than the campaign's {} tasks",
            o.merge_nodes,
            plan.tasks.len()
        )));
    }
    let groups = if o.merge_nodes > 1 {
        Some(write("merge_groups.sbatch", groups_script(plan, o))?)
    } else {
        None
    };
    let merge = write("merge.sbatch", merge_script(plan, o))?;
    // The jobs in order, each after the one before succeeded.
    let chain: Vec<(&str, String)> = [
        lines.as_ref().map(|l| ("lines", l.display().to_string())),
        groups.as_ref().map(|g| ("groups", g.display().to_string())),
        Some(("merge", merge.display().to_string())),
    ]
    .into_iter()
    .flatten()
    .collect();
    let mut commands = Vec::new();
    let mut job_ids: Vec<String> = Vec::new();
    for (k, (_, script)) in chain.iter().enumerate() {
        match k {
            0 => commands.push(format!("sbatch --parsable {script}")),
            _ => commands.push(format!(
                "sbatch --parsable --dependency=afterok:<{} job> {script}",
                chain[k - 1].0
            )),
        }
        if !dry_run {
            let id = match job_ids.last() {
                None => sbatch(&["--parsable", script])?,
                Some(before) => {
                    let dep = format!("--dependency=afterok:{before}");
                    sbatch(&["--parsable", &dep, script])?
                }
            };
            job_ids.push(id);
        }
    }
    Ok(Submitted {
        lines_script: lines,
        groups_script: groups,
        merge_script: merge,
        commands,
        job_ids,
    })
}
