//! A survey campaign: many flight lines replayed with one configuration into one CRS and one
//! voxel grid, each line's store written on its own, then merged exactly into one mosaic
//! (`docs/campaign.md`).
//!
//! - this file: the campaign file (`[campaign]`: captures or globs, run configuration, output
//!   folder, EPSG code) and the plan made from it (`fwlidar campaign plan`);
//! - `local.rs`: running the plan with N processes on one machine and merging the line stores
//!   as a tree (`fwlidar campaign run --local N`).
//!
//! The mosaic is byte-identical whatever the number of processes, the order lines finish in
//! and the shape of the merge tree: voxel accumulators are integers (`crate::voxel::merge`) and
//! every merge writes the campaign's metadata, not its inputs' names.

pub mod local;
pub mod slurm;

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::config::RunConfig;
use crate::core::config_error::ConfigErrors;
use crate::core::validate::{Validate, Validator, field, index};
use crate::source::shard::Shard;

/// A campaign file: one `[campaign]` table.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CampaignFile {
    /// The campaign.
    pub campaign: Campaign,
}

/// What a campaign is made of. Relative paths start at the campaign file's folder.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Campaign {
    /// Name (letters, digits, `-`, `_`, `.`): in the reports and the Slurm jobs' names.
    pub name: String,
    /// The flight lines: capture files (or any file `replay` reads), or glob patterns
    /// (`lines/*.fwcap`). Each line's store is named after its file's stem, which must be
    /// unique.
    pub captures: Vec<String>,
    /// Run configuration of every line (default: the embedded one). `voxels.enabled` must be
    /// true: the mosaic is the voxel store.
    #[serde(default)]
    pub config: Option<String>,
    /// Changes to it, as `replay --set` takes them.
    #[serde(default)]
    pub set: Vec<String>,
    /// The campaign folder: `lines/<stem>/` per line, `mosaic.zarr`, `campaign.json`.
    pub out: String,
    /// EPSG code of the CRS every line is projected into (`georeference.output_epsg`), so that
    /// lines in two UTM zones still share one grid.
    pub epsg: u32,
    /// A capture larger than this many GB is replayed as `ceil(size / shard_gb)` shards
    /// (`replay --shard i/n`, contiguous pulse ranges), each a task of its own: for lines too
    /// long for one node's time limit. Default: never split.
    #[serde(default)]
    pub shard_gb: Option<f64>,
    /// Whether the merge also writes the forest-metrics rasters of the mosaic (`rasters/`, as
    /// `fwlidar metrics` does). Default true.
    #[serde(default = "yes")]
    pub metrics: bool,
    /// Cell of the canopy height model, m (default: the voxel column).
    #[serde(default)]
    pub chm_cell_m: Option<f64>,
    /// Cell of the metrics raster, m (default: `chm_cell_m`).
    #[serde(default)]
    pub profile_cell_m: Option<f64>,
}

fn yes() -> bool {
    true
}

impl Validate for CampaignFile {
    fn validate(&self, path: &str, v: &mut Validator) {
        let c = &self.campaign;
        let p = field(path, "campaign");
        v.require(
            !c.name.is_empty()
                && c.name
                    .chars()
                    .all(|ch| ch.is_ascii_alphanumeric() || "-_.".contains(ch)),
            field(&p, "name"),
            format!("must be letters, digits, '-', '_' or '.', got {:?}", c.name),
        );
        v.require(
            !c.captures.is_empty(),
            field(&p, "captures"),
            "must name at least one capture or pattern",
        );
        for (i, s) in c.captures.iter().enumerate() {
            v.require(
                !s.trim().is_empty(),
                index(&field(&p, "captures"), i),
                "is empty",
            );
        }
        v.require(!c.out.is_empty(), field(&p, "out"), "must name a folder");
        v.require(
            c.epsg > 0,
            field(&p, "epsg"),
            "must be an EPSG code, e.g. 32736",
        );
        if let Some(g) = c.shard_gb {
            v.require(
                g.is_finite() && g > 0.0,
                field(&p, "shard_gb"),
                format!("must be a size in GB above 0, got {g}"),
            );
        }
        for (name, cell) in [
            ("chm_cell_m", c.chm_cell_m),
            ("profile_cell_m", c.profile_cell_m),
        ] {
            if let Some(m) = cell {
                v.require(
                    m.is_finite() && m > 0.0,
                    field(&p, name),
                    format!("must be a cell size in metres above 0, got {m}"),
                );
            }
        }
    }
}

/// Why a campaign cannot be planned or run.
#[derive(Debug, thiserror::Error)]
pub enum CampaignError {
    /// The campaign file is malformed.
    #[error("{0}")]
    File(#[from] ConfigErrors),
    /// A field names something that is not there or cannot be read.
    #[error("{file}: {field}: {why}")]
    Field {
        /// The campaign file.
        file: String,
        /// The field at fault.
        field: String,
        /// What is wrong.
        why: String,
    },
    /// A line or the merge failed.
    #[error("{0}")]
    Run(String),
}

/// One task: a flight line (or one shard of it) replayed into its own store.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Task {
    /// Number in the plan (0-based; the Slurm array index).
    pub id: usize,
    /// The task's name: the line's (its file's stem), `<line>.shard<i>of<n>` for a shard.
    pub name: String,
    /// The shard of the line, when the line is split (`Campaign::shard_gb`).
    pub shard: Option<Shard>,
    /// The capture.
    pub capture: PathBuf,
    /// Its size, bytes.
    pub bytes: u64,
    /// The folder its replay writes (`lines/<name>`).
    pub out: PathBuf,
    /// Already done (a finished replay left `done.json`).
    pub done: bool,
}

/// A checked campaign: its tasks and the configuration every line runs with.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The campaign file.
    pub file: PathBuf,
    /// The campaign.
    pub campaign: Campaign,
    /// The campaign folder.
    pub out: PathBuf,
    /// One task per line, by name.
    pub tasks: Vec<Task>,
    /// The run configuration of every line, with the campaign's CRS.
    pub config: RunConfig,
    /// Its TOML text (written as `run.toml` in the campaign folder and recorded in the mosaic).
    pub config_text: String,
    /// The captures, in task order.
    pub captures: Vec<PathBuf>,
    /// The mosaic's run key: that of one `fwlidar replay` of every capture in this order with
    /// `run.toml`, the store the mosaic equals byte for byte.
    pub run_key: String,
}

/// Name of the marker a finished line's replay leaves in its folder.
pub const DONE: &str = "done.json";

/// Reads and checks the campaign file `path`: every capture pattern matches, every capture
/// opens, line names are unique, the configuration loads with voxels on, and the CRS is the
/// campaign's. Errors name the file and the field.
pub fn plan(path: &Path) -> Result<Plan, CampaignError> {
    let file: CampaignFile = crate::core::toml_load::load_file_with(path, &[] as &[&str])?;
    let c = file.campaign;
    let base = path.parent().unwrap_or(Path::new("."));
    let at = |f: String, why: String| CampaignError::Field {
        file: path.display().to_string(),
        field: f,
        why,
    };
    let mut captures: Vec<PathBuf> = Vec::new();
    for (i, pat) in c.captures.iter().enumerate() {
        let f = format!("campaign.captures[{i}]");
        let full = base.join(pat);
        let text = full.to_string_lossy().to_string();
        let matched: Vec<PathBuf> = if pat.contains(['*', '?', '[']) {
            glob::glob(&text)
                .map_err(|e| at(f.clone(), format!("bad pattern {pat:?}: {e}")))?
                .filter_map(Result::ok)
                .filter(|p| p.is_file())
                .collect()
        } else {
            vec![full.clone()]
        };
        if matched.is_empty() {
            return Err(at(f, format!("{pat:?} matches no file")));
        }
        for m in matched {
            if !m.is_file() {
                return Err(at(f.clone(), format!("{}: no such file", m.display())));
            }
            crate::source::open_file(&m).map_err(|e| at(f.clone(), e.to_string()))?;
            captures.push(m);
        }
    }
    captures.sort();
    captures.dedup();
    let out = base.join(&c.out);
    let mut tasks: Vec<Task> = Vec::new();
    for cap in captures {
        let name = cap
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        if let Some(t) = tasks.iter().find(|t| t.name == name) {
            return Err(at(
                "campaign.captures".into(),
                format!(
                    "{} and {} are both line {name:?}: line names (file stems) must be unique",
                    t.capture.display(),
                    cap.display()
                ),
            ));
        }
        let bytes = std::fs::metadata(&cap).map(|m| m.len()).unwrap_or(0);
        let shards = match c.shard_gb {
            Some(g) => ((bytes as f64 / (g * 1e9)).ceil() as u32).max(1),
            None => 1,
        };
        for index in 1..=shards {
            let (task_name, shard) = if shards == 1 {
                (name.clone(), None)
            } else {
                (
                    format!("{name}.shard{index}of{shards}"),
                    Some(Shard {
                        index,
                        count: shards,
                    }),
                )
            };
            let dir = out.join("lines").join(&task_name);
            tasks.push(Task {
                id: 0,
                bytes: bytes / u64::from(shards),
                done: dir.join(DONE).is_file(),
                out: dir,
                name: task_name,
                shard,
                capture: cap.clone(),
            });
        }
    }
    // By line, then shard (names sort `line.shard10of12` after `line.shard9of12` this way).
    tasks.sort_by(|a, b| {
        (&a.capture, a.shard.map(|s| s.index)).cmp(&(&b.capture, b.shard.map(|s| s.index)))
    });
    for (i, t) in tasks.iter_mut().enumerate() {
        t.id = i;
    }
    let config_path = c.config.as_ref().map(|p| base.join(p));
    let mut config = crate::config::load_run_config_with(config_path.as_deref(), &c.set)?;
    if !config.voxels.enabled {
        return Err(at(
            "campaign.config".into(),
            "voxels.enabled is false: the campaign's mosaic is the voxel store".into(),
        ));
    }
    match config.georeference.output_epsg {
        Some(e) if e != c.epsg => {
            return Err(at(
                "campaign.epsg".into(),
                format!(
                    "{} but the run configuration's georeference.output_epsg is {e}",
                    c.epsg
                ),
            ));
        }
        _ => config.georeference.output_epsg = Some(c.epsg),
    }
    // Every line writes where `--out` tells it; the folder named here is never used.
    config.output.dir = "out".into();
    // One grid for every line: unless the configuration bounds it, the extent is the square a
    // replay would centre on its first pulse, centred on the first line's.
    if config.voxels.extent_m.is_none() {
        let first = &tasks[0].capture;
        // Quietly: the readers' "capture header" lines belong to the replays, not the plan.
        let quiet = tracing::subscriber::NoSubscriber::default();
        let centre = tracing::subscriber::with_default(quiet, || first_position(first, &config));
        let centre = centre.map_err(|why| {
            at(
                "campaign.captures".into(),
                format!("{}: cannot place the grid: {why}", first.display()),
            )
        })?;
        let h = config.voxels.auto_extent_m / 2.0;
        let c = [centre[0].round(), centre[1].round()];
        config.voxels.extent_m = Some([c[0] - h, c[1] - h, c[0] + h, c[1] + h]);
    }
    let config_text =
        toml::to_string(&config).map_err(|e| at("campaign.config".into(), e.to_string()))?;
    let mut captures: Vec<PathBuf> = tasks.iter().map(|t| t.capture.clone()).collect();
    captures.dedup();
    let run_key = crate::run::outputs::replay_run_key(&captures, None, &config);
    Ok(Plan {
        file: path.to_path_buf(),
        campaign: c,
        out,
        tasks,
        config,
        config_text,
        captures,
        run_key,
    })
}

/// Where the first georeferenced pulse of `capture` looks, in the configuration's output CRS
/// (x, y in m): the middle of its first return segment, as the voxel store places its automatic
/// extent.
fn first_position(capture: &Path, config: &RunConfig) -> Result<[f64; 2], String> {
    use crate::pipeline::ports::SourceEvent;
    let raw = crate::source::open_file(capture)?;
    let mut src: Box<crate::source::DynSource> = if config.georeference.enabled {
        Box::new(
            crate::source::georeferencing::GeoreferencingSource::new(
                raw,
                config.georeference.clone(),
            )?
            .with_earliest_date(config.navigation.earliest_days()),
        )
    } else {
        raw
    };
    let pool = crate::pulse::PulsePool::new(16);
    loop {
        match src.next(&pool).map_err(|e| e.to_string())? {
            SourceEvent::Pulse(p) => {
                if let Some(xy) = crate::sink::voxel_tiles::extent_centre(&p) {
                    return Ok(xy);
                }
                pool.give(p);
            }
            SourceEvent::End => return Err("no pulse of it has a position".into()),
            SourceEvent::Nav(_) | SourceEvent::Idle => {}
        }
    }
}

impl Plan {
    /// The plan as text: one line per task.
    pub fn describe(&self) -> String {
        use std::fmt::Write as _;
        let mut s = format!(
            "campaign {} ({}): {} lines in {} tasks into {} (EPSG {}), {} done\n",
            self.campaign.name,
            self.file.display(),
            self.captures.len(),
            self.tasks.len(),
            self.out.display(),
            self.campaign.epsg,
            self.tasks.iter().filter(|t| t.done).count()
        );
        for t in &self.tasks {
            let _ = writeln!(
                s,
                "  task {:>3}  {:<28} {:>10.1} MB  {}  -> {}",
                t.id,
                t.name,
                t.bytes as f64 / 1e6,
                if t.done { "done   " } else { "to run " },
                t.out.display()
            );
        }
        let _ = writeln!(
            s,
            "  then a merge of {} stores into {}{}",
            self.tasks.len(),
            self.out.join("mosaic.zarr").display(),
            if self.campaign.metrics {
                " and its metrics rasters into rasters/"
            } else {
                ""
            }
        );
        s
    }
}
