//! Running a campaign's plan on one machine (`fwlidar campaign run FILE --local N`): each line
//! replayed by a `fwlidar replay` process (N at a time) into `lines/<name>/`, then the line
//! stores merged as a tree (`fan_in` stores per merge, the merges of a level in parallel) into
//! `mosaic.zarr`, and `campaign.json` (what each line did, wall and CPU time per line, the
//! merge). Resumable: a line whose folder holds `done.json` is not replayed again; a line folder
//! without it (a killed replay) is cleared and replayed.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::campaign::{CampaignError, DONE, Plan, Task};
use crate::voxel::merge::{MergeMeta, merge_stores};

/// How to run the plan here.
#[derive(Clone, Debug)]
pub struct LocalOptions {
    /// Replays (and merges) at once.
    pub processes: usize,
    /// Stores per merge in the merge tree (2 or more).
    pub fan_in: usize,
    /// The `fwlidar` executable the replays run.
    pub exe: PathBuf,
}

/// What one line did.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LineReport {
    /// Line name.
    pub name: String,
    /// The capture.
    pub capture: String,
    /// Replayed by this run (false: done before and skipped).
    pub ran: bool,
    /// Wall time of its replay, s.
    pub wall_s: f64,
    /// CPU time (user + system) of its replay, s.
    pub cpu_s: f64,
    /// Pulses read and written, and dropped, from its `summary.json`.
    pub pulses_in: u64,
    /// Pulses out.
    pub pulses_out: u64,
    /// Pulses dropped (every reason).
    pub dropped: u64,
    /// Damage the source reported (bytes skipped, records rejected), from `summary.json`.
    pub source: serde_json::Value,
    /// Tiles in its voxel store.
    #[serde(default)]
    pub tiles: u64,
    /// Bytes of its voxel store's chunks.
    #[serde(default)]
    pub store_bytes: u64,
    /// Samples that fell outside the campaign's grid extent (not deposited; see
    /// `docs/campaign.md`, "One grid").
    #[serde(default)]
    pub bins_outside_grid: u64,
}

/// The merge tree.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MergeReport {
    /// Stores per merge.
    pub fan_in: usize,
    /// Levels of merges.
    pub levels: usize,
    /// Merges made.
    pub merges: usize,
    /// Tiles of the mosaic.
    pub tiles: usize,
    /// Tiles the merges copied as their chunk files were (one input held them), over all
    /// levels.
    pub tiles_copied: u64,
    /// Wall time of the whole tree, s (without the group merges).
    pub wall_s: f64,
    /// Merge groups whose stores were merged last (1: none, the task stores were).
    pub groups: usize,
    /// Of those, merged by this merge job (the others by the groups' array tasks).
    pub groups_merged_here: usize,
}

/// `campaign.json`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct CampaignReport {
    /// Campaign name.
    pub campaign: String,
    /// Lines, by name.
    pub lines: Vec<LineReport>,
    /// The merge tree.
    pub merge: MergeReport,
    /// The mosaic.
    pub mosaic: String,
    /// Wall time of this run, s.
    pub wall_s: f64,
    /// Processes at once.
    pub processes: usize,
    /// The mosaic's forest-metrics rasters (`rasters/`), when the campaign asks for them.
    pub metrics: Option<serde_json::Value>,
}

/// A running replay.
struct Running {
    task: Task,
    child: Child,
    started: Instant,
}

/// CPU time (user + system, s) of a finished child reaped with `wait4`, and its exit status;
/// `None` while it runs.
#[cfg(unix)]
fn reap(child: &Child) -> Option<(bool, f64)> {
    let mut status = 0;
    // SAFETY: zeroed rusage is a valid out-parameter; wait4 writes it for our own child.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: the pid is our child's, not yet reaped (we reap it only here).
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, libc::WNOHANG, &mut usage) };
    if pid <= 0 {
        return None;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    let ok = libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0;
    Some((ok, tv(usage.ru_utime) + tv(usage.ru_stime)))
}

fn io(what: &str, p: &Path, e: std::io::Error) -> CampaignError {
    CampaignError::Run(format!("cannot {what} {}: {e}", p.display()))
}

fn start(task: &Task, run_toml: &Path, exe: &Path) -> Result<Running, CampaignError> {
    // Group merges of an earlier attempt no longer hold this task's store: gone.
    if let Some(campaign) = task.out.parent().and_then(Path::parent) {
        let _ = std::fs::remove_dir_all(campaign.join("merge"));
    }
    if task.out.exists() {
        std::fs::remove_dir_all(&task.out).map_err(|e| io("clear", &task.out, e))?;
    }
    std::fs::create_dir_all(&task.out).map_err(|e| io("create", &task.out, e))?;
    let log = task.out.with_extension("log");
    let log_file = std::fs::File::create(&log).map_err(|e| io("create", &log, e))?;
    let err_file = log_file.try_clone().map_err(|e| io("open", &log, e))?;
    let mut cmd = Command::new(exe);
    cmd.arg("replay")
        .arg(&task.capture)
        .arg("--out")
        .arg(&task.out)
        .arg("--config")
        .arg(run_toml)
        .arg("--no-progress");
    if let Some(shard) = task.shard {
        cmd.arg("--shard").arg(shard.to_string());
    }
    let child = cmd
        .stdin(Stdio::null())
        .stdout(log_file)
        .stderr(err_file)
        .spawn()
        .map_err(|e| io("start", exe, e))?;
    Ok(Running {
        task: task.clone(),
        child,
        started: Instant::now(),
    })
}

/// What a line's `summary.json` says that the campaign's report keeps: the pulses, the
/// input's report as it is, and the voxel store's size and misses.
#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct LineSummary {
    pulses_in: u64,
    pulses_out: u64,
    dropped_total: u64,
    /// The input's report, kept as written.
    source: serde_json::Value,
    sinks: LineSinks,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct LineSinks {
    voxels: LineVoxels,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct LineVoxels {
    tiles: LineTiles,
    deposits: LineDeposits,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct LineTiles {
    in_store: u64,
    bytes_stored: u64,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct LineDeposits {
    bins_outside_extent: u64,
}

fn line_report(task: &Task, ran: bool, wall_s: f64, cpu_s: f64) -> LineReport {
    let summary: LineSummary = std::fs::read_to_string(task.out.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    let voxels = &summary.sinks.voxels;
    LineReport {
        name: task.name.clone(),
        capture: task.capture.display().to_string(),
        ran,
        wall_s,
        cpu_s,
        pulses_in: summary.pulses_in,
        pulses_out: summary.pulses_out,
        dropped: summary.dropped_total,
        tiles: voxels.tiles.in_store,
        store_bytes: voxels.tiles.bytes_stored,
        bins_outside_grid: voxels.deposits.bins_outside_extent,
        source: summary.source,
    }
}

/// Replays the lines not yet done, `opts.processes` at a time; returns every line's report.
fn run_lines(plan: &Plan, opts: &LocalOptions) -> Result<Vec<LineReport>, CampaignError> {
    let run_toml = plan.out.join("run.toml");
    let mut reports: Vec<LineReport> = Vec::new();
    let mut waiting: Vec<&Task> = Vec::new();
    for t in &plan.tasks {
        match std::fs::read_to_string(t.out.join(DONE))
            .ok()
            .and_then(|s| serde_json::from_str::<LineReport>(&s).ok())
        {
            Some(mut r) => {
                r.ran = false;
                reports.push(r);
            }
            None => waiting.push(t),
        }
    }
    waiting.reverse();
    let total = waiting.len();
    let mut running: Vec<Running> = Vec::new();
    let mut failed: Vec<String> = Vec::new();
    while !waiting.is_empty() || !running.is_empty() {
        while running.len() < opts.processes.max(1)
            && let Some(t) = waiting.pop()
        {
            running.push(start(t, &run_toml, &opts.exe)?);
        }
        let mut k = 0;
        while k < running.len() {
            match reap(&running[k].child) {
                None => k += 1,
                Some((ok, cpu)) => {
                    let r = running.swap_remove(k);
                    let wall = r.started.elapsed().as_secs_f64();
                    if ok {
                        let rep = line_report(&r.task, true, wall, cpu);
                        let text = serde_json::to_string_pretty(&rep).unwrap_or_default();
                        let done = r.task.out.join(DONE);
                        std::fs::write(&done, text).map_err(|e| io("write", &done, e))?;
                        eprintln!(
                            "line {} done ({}/{total}): {:.1} s wall, {:.1} s CPU",
                            r.task.name,
                            total - waiting.len() - running.len(),
                            wall,
                            cpu
                        );
                        reports.push(rep);
                    } else {
                        eprintln!(
                            "line {} failed: see {}",
                            r.task.name,
                            r.task.out.with_extension("log").display()
                        );
                        failed.push(r.task.name.clone());
                    }
                }
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    if !failed.is_empty() {
        return Err(CampaignError::Run(format!(
            "{} line(s) failed: {}; their logs are lines/<name>.log; run again to retry them \
             (finished lines are kept)",
            failed.len(),
            failed.join(", ")
        )));
    }
    reports.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(reports)
}

/// Merges `stores` as a tree of `fan_in`-way merges (the merges of one level on up to
/// `processes` threads) into `mosaic`, every merge with the campaign's metadata. Returns the
/// report; intermediate stores (`merge/`) are removed.
pub fn merge_tree(
    stores: &[PathBuf],
    work: &Path,
    mosaic: &Path,
    meta: &MergeMeta,
    fan_in: usize,
    processes: usize,
) -> Result<MergeReport, CampaignError> {
    let started = Instant::now();
    // 0: every store in one merge (the fastest on one node, docs/performance.md).
    let fan_in = if fan_in == 0 { stores.len() } else { fan_in }.max(2);
    let mut level: Vec<PathBuf> = stores.to_vec();
    level.sort();
    if work.exists() {
        std::fs::remove_dir_all(work).map_err(|e| io("clear", work, e))?;
    }
    let (mut levels, mut merges, mut tiles, mut copied) = (0, 0, 0, 0);
    loop {
        let last = level.len() <= fan_in;
        let groups: Vec<Vec<PathBuf>> = level.chunks(fan_in).map(<[PathBuf]>::to_vec).collect();
        let outs: Vec<PathBuf> = if last {
            vec![mosaic.to_path_buf()]
        } else {
            (0..groups.len())
                .map(|k| work.join(format!("level{levels}_{k:04}.zarr")))
                .collect()
        };
        if !last {
            std::fs::create_dir_all(work).map_err(|e| io("create", work, e))?;
        }
        let results: Vec<Result<crate::voxel::merge::MergeSummary, String>> =
            std::thread::scope(|s| {
                let mut results = Vec::new();
                for (batch_g, batch_o) in groups
                    .chunks(processes.max(1))
                    .zip(outs.chunks(processes.max(1)))
                {
                    let handles: Vec<_> = batch_g
                        .iter()
                        .zip(batch_o)
                        .map(|(g, o)| s.spawn(move || merge_stores(g, o, meta, |_, _| {})))
                        .collect();
                    results.extend(handles.into_iter().map(|h| {
                        h.join()
                            .unwrap_or_else(|_| Err("a merge thread panicked".to_string()))
                    }));
                }
                results
            });
        for r in results {
            let s = r.map_err(CampaignError::Run)?;
            tiles = s.tiles;
            copied += s.tiles_copied;
            merges += 1;
        }
        levels += 1;
        if last {
            break;
        }
        level = outs;
    }
    if work.exists() {
        std::fs::remove_dir_all(work).map_err(|e| io("remove", work, e))?;
    }
    Ok(MergeReport {
        fan_in,
        levels,
        merges,
        tiles,
        tiles_copied: copied,
        wall_s: started.elapsed().as_secs_f64(),
        groups: 1,
        groups_merged_here: 0,
    })
}

/// Writes the campaign folder's `run.toml` (the configuration every line runs with), or checks
/// that the one there is the same: a folder holding lines run with another configuration is
/// refused.
pub fn prepare_folder(plan: &Plan) -> Result<(), CampaignError> {
    std::fs::create_dir_all(&plan.out).map_err(|e| io("create", &plan.out, e))?;
    let run_toml = plan.out.join("run.toml");
    match std::fs::read_to_string(&run_toml) {
        Ok(old) if old != plan.config_text => Err(CampaignError::Field {
            file: plan.file.display().to_string(),
            field: "campaign.config".into(),
            why: format!(
                "{} holds lines run with another configuration ({}); give the campaign a new \
                 `out` folder",
                plan.out.display(),
                run_toml.display()
            ),
        }),
        Ok(_) => Ok(()),
        Err(_) => {
            std::fs::write(&run_toml, &plan.config_text).map_err(|e| io("write", &run_toml, e))
        }
    }
}

/// Runs one task (a Slurm array task): its line's replay unless it is done. Returns its report.
pub fn run_task(plan: &Plan, index: usize, exe: &Path) -> Result<LineReport, CampaignError> {
    let task = plan.tasks.get(index).ok_or_else(|| {
        CampaignError::Run(format!(
            "task {index} does not exist: the plan has {} tasks (0..{})",
            plan.tasks.len(),
            plan.tasks.len()
        ))
    })?;
    prepare_folder(plan)?;
    if let Some(mut r) = std::fs::read_to_string(task.out.join(DONE))
        .ok()
        .and_then(|s| serde_json::from_str::<LineReport>(&s).ok())
    {
        r.ran = false;
        return Ok(r);
    }
    let r = start(task, &plan.out.join("run.toml"), exe)?;
    loop {
        if let Some((ok, cpu)) = reap(&r.child) {
            let wall = r.started.elapsed().as_secs_f64();
            if !ok {
                return Err(CampaignError::Run(format!(
                    "line {} failed: see {}",
                    task.name,
                    task.out.with_extension("log").display()
                )));
            }
            let rep = line_report(task, true, wall, cpu);
            let done = task.out.join(DONE);
            std::fs::write(
                &done,
                serde_json::to_string_pretty(&rep).unwrap_or_default(),
            )
            .map_err(|e| io("write", &done, e))?;
            return Ok(rep);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The tasks of merge group `group` (0-based) of `groups`: the plan's tasks in order cut into
/// `groups` contiguous runs of near-equal length, so that neighbouring lines (and a line's
/// shards), which share most of the tiles any two share, fall in one group.
pub fn group_tasks(plan: &Plan, group: usize, groups: usize) -> &[Task] {
    let n = plan.tasks.len();
    let at = |k: usize| n * k / groups.max(1);
    &plan.tasks[at(group)..at(group + 1)]
}

/// Where merge group `group` of `groups` is written.
pub fn group_store(plan: &Plan, group: usize, groups: usize) -> PathBuf {
    plan.out
        .join("merge")
        .join(format!("group{group}of{groups}.zarr"))
}

/// One merge group (a task of the merge groups' Slurm array, on a node of its own): the stores
/// of [`group_tasks`] merged into [`group_store`] with the campaign's metadata. `Ok(false)`
/// when that store is there already (a store appears only complete). Refused while a task of
/// the group is not done.
pub fn merge_group(plan: &Plan, group: usize, groups: usize) -> Result<bool, CampaignError> {
    if groups < 2 || group >= groups || groups > plan.tasks.len() {
        return Err(CampaignError::Run(format!(
            "merge group {group} of {groups} does not exist: groups must be 2..={} (the              tasks) and the group below them",
            plan.tasks.len()
        )));
    }
    let out = group_store(plan, group, groups);
    if out.exists() {
        return Ok(false);
    }
    let tasks = group_tasks(plan, group, groups);
    let missing: Vec<&str> = tasks
        .iter()
        .filter(|t| !t.out.join(DONE).is_file())
        .map(|t| t.name.as_str())
        .collect();
    if !missing.is_empty() {
        return Err(CampaignError::Run(format!(
            "merge group {group} of {groups}: task(s) not done: {}",
            missing.join(", ")
        )));
    }
    let dir = plan.out.join("merge");
    std::fs::create_dir_all(&dir).map_err(|e| io("create", &dir, e))?;
    let stores: Vec<PathBuf> = tasks.iter().map(|t| t.out.join("voxels.zarr")).collect();
    merge_stores(&stores, &out, &campaign_meta(plan), |_, _| {}).map_err(CampaignError::Run)?;
    Ok(true)
}

/// The metadata every merge of the campaign writes: those of one replay of every line in
/// sequence, the store the mosaic equals.
fn campaign_meta(plan: &Plan) -> MergeMeta {
    MergeMeta::Given {
        run_key: plan.run_key.clone(),
        configuration: plan.config_text.clone(),
    }
}

/// The merge job: every task must be done; merges their stores into `mosaic.zarr` (rebuilt) —
/// when `groups` > 1, first the merge groups not merged yet (each normally a task of the
/// merge groups' array on a node of its own), then the group stores — writes the metrics
/// rasters and `campaign.json`.
pub fn merge_campaign(
    plan: &Plan,
    processes: usize,
    fan_in: usize,
    groups: usize,
    lines_ran_now: &[String],
    started: Instant,
) -> Result<CampaignReport, CampaignError> {
    let mut lines = Vec::new();
    let mut missing = Vec::new();
    for t in &plan.tasks {
        match std::fs::read_to_string(t.out.join(DONE))
            .ok()
            .and_then(|s| serde_json::from_str::<LineReport>(&s).ok())
        {
            Some(mut r) => {
                r.ran = lines_ran_now.contains(&r.name);
                lines.push(r);
            }
            None => missing.push(t.name.clone()),
        }
    }
    if !missing.is_empty() {
        return Err(CampaignError::Run(format!(
            "{} line(s) not done: {}; run their tasks first (a killed task is run again by \
             resubmitting the campaign)",
            missing.len(),
            missing.join(", ")
        )));
    }
    let mut groups_merged_here = 0;
    let stores: Vec<PathBuf> = if groups > 1 {
        for g in 0..groups {
            if merge_group(plan, g, groups)? {
                groups_merged_here += 1;
            }
        }
        (0..groups).map(|g| group_store(plan, g, groups)).collect()
    } else {
        plan.tasks
            .iter()
            .map(|t| t.out.join("voxels.zarr"))
            .collect()
    };
    let mosaic = plan.out.join("mosaic.zarr");
    let partial = plan.out.join("mosaic.zarr.partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| io("clear", &partial, e))?;
    }
    let mut merge = merge_tree(
        &stores,
        &plan.out.join("merge").join("tree"),
        &partial,
        &campaign_meta(plan),
        fan_in,
        processes,
    )?;
    merge.groups = groups.max(1);
    merge.groups_merged_here = groups_merged_here;
    let dir = plan.out.join("merge");
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| io("remove", &dir, e))?;
    }
    if mosaic.exists() {
        std::fs::remove_dir_all(&mosaic).map_err(|e| io("replace", &mosaic, e))?;
    }
    std::fs::rename(&partial, &mosaic).map_err(|e| io("rename", &partial, e))?;
    let metrics = if plan.campaign.metrics {
        Some(mosaic_rasters(plan, &mosaic)?)
    } else {
        None
    };
    let report = CampaignReport {
        metrics,
        campaign: plan.campaign.name.clone(),
        lines,
        merge,
        mosaic: mosaic.display().to_string(),
        wall_s: started.elapsed().as_secs_f64(),
        processes,
    };
    let path = plan.out.join("campaign.json");
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&report).unwrap_or_default() + "\n",
    )
    .map_err(|e| io("write", &path, e))?;
    Ok(report)
}

/// The forest-metrics rasters of the mosaic into `<out>/rasters/` (rebuilt; as `fwlidar metrics
/// mosaic.zarr --out rasters` writes them): returns what was done, with its time.
fn mosaic_rasters(plan: &Plan, mosaic: &Path) -> Result<serde_json::Value, CampaignError> {
    use crate::forest::store_metrics::{
        DEFAULT_NOISE_FLOOR, DEFAULT_SMOOTHING_NS, StoreMetricsOptions, compute_store_metrics,
    };
    let started = Instant::now();
    let dir = plan.out.join("rasters");
    let partial = plan.out.join("rasters.partial");
    for d in [&partial, &dir] {
        if d.exists() {
            std::fs::remove_dir_all(d).map_err(|e| io("clear", d, e))?;
        }
    }
    std::fs::create_dir_all(&partial).map_err(|e| io("create", &partial, e))?;
    let opts = StoreMetricsOptions {
        cell_m: plan.campaign.chm_cell_m,
        profile_cell_m: plan.campaign.profile_cell_m,
        smoothing_ns: DEFAULT_SMOOTHING_NS,
        min_pulses: 1,
        noise_floor: DEFAULT_NOISE_FLOOR,
    };
    let report = compute_store_metrics(mosaic, &partial, &opts, &mut |_, _| {})
        .map_err(|e| CampaignError::Run(format!("metrics rasters of the mosaic: {e}")))?;
    let json = crate::forest::store_metrics::metrics_json(
        &report,
        mosaic,
        started.elapsed().as_secs_f64(),
    );
    let jpath = partial.join("metrics.json");
    std::fs::write(
        &jpath,
        serde_json::to_string_pretty(&json).unwrap_or_default() + "\n",
    )
    .map_err(|e| io("write", &jpath, e))?;
    std::fs::rename(&partial, &dir).map_err(|e| io("rename", &partial, e))?;
    Ok(json)
}

/// Runs `plan` here: the lines not done, then the merge tree into `mosaic.zarr` (rebuilt on
/// every run), then `campaign.json`.
pub fn run_local(plan: &Plan, opts: &LocalOptions) -> Result<CampaignReport, CampaignError> {
    let started = Instant::now();
    prepare_folder(plan)?;
    let lines = run_lines(plan, opts)?;
    let ran: Vec<String> = lines
        .iter()
        .filter(|l| l.ran)
        .map(|l| l.name.clone())
        .collect();
    merge_campaign(plan, opts.processes, opts.fan_in, 1, &ran, started)
}
