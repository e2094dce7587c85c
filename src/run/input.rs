//! The input of a run: the source opened and georeferenced per `[georeference]`, the DEM, and
//! where the georeferencing puts the output CRS it decides.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use super::RunError;
use crate::config::RunConfig;
use crate::geo::dem::Dem;
use crate::source::DynSource;
use crate::source::georeferencing::GeoreferencingSource;
use crate::source::shard::Shard;

/// The opened input: the source (georeferenced per `[georeference]`), the DEM, and the cell
/// where the georeferencing puts the output CRS it decides (the UTM zone of the first fix) when
/// it wraps the source.
pub struct Input {
    /// The source the runner reads.
    pub source: Box<DynSource>,
    /// The run's DEM (`[georeference] dem`), opened.
    pub dem: Option<Arc<Dem>>,
    /// Where the georeferencing puts the CRS it decides, when it runs.
    pub decided_crs: Option<Arc<OnceLock<String>>>,
}

impl Input {
    /// Wraps an opened `source` (e.g. the daemon's live source) in the georeferencing per
    /// `[georeference]`, with the DEM it names. The output CRS is the DEM's own unless the
    /// configuration names one.
    pub fn georeferenced(source: Box<DynSource>, config: &RunConfig) -> Result<Input, RunError> {
        let dem = open_dem(config)?;
        let (source, decided_crs) = georeference_with(source, config, dem.clone())?;
        Ok(Input {
            source,
            dem,
            decided_crs,
        })
    }

    /// Opens the input files (only the shard's pulses of them when `shard` is given), wraps each
    /// in the georeferencing (its own trajectory), and chains them when there are several.
    pub fn open_files(
        paths: &[PathBuf],
        shard: Option<Shard>,
        config: &RunConfig,
    ) -> Result<Input, RunError> {
        let dem = open_dem(config)?;
        let several = paths.len() > 1;
        if several
            && config.georeference.enabled
            && config.georeference.output_epsg.is_none()
            && dem.as_ref().and_then(|d| d.epsg).is_none()
        {
            return Err(RunError::usage(
                "several inputs are replayed into one CRS, and the configuration names none \
                 (each line would get the UTM zone of its own first fix): set [georeference] \
                 output_epsg, e.g. --set georeference.output_epsg=32736",
            ));
        }
        let ranges = match shard {
            None => None,
            Some(s) => Some(shard_ranges(paths, s)?),
        };
        let mut sources = Vec::new();
        let mut decided = None;
        for (k, path) in paths.iter().enumerate() {
            let mut source = crate::source::open_file(path).map_err(RunError::job)?;
            if let Some(r) = &ranges {
                let (lo, hi) = r[k];
                if lo == hi && several {
                    continue; // none of this input's pulses is in the shard
                }
                source = Box::new(crate::source::shard::ShardSource::new(source, lo, hi));
            }
            let (source, cell) = georeference_with(source, config, dem.clone())?;
            decided = decided.or(cell);
            sources.push((path.display().to_string(), source));
        }
        let source: Box<DynSource> = if sources.len() == 1 {
            sources.pop().map(|(_, s)| s).expect("one source")
        } else {
            Box::new(crate::source::chain::ChainSource::new(sources).map_err(RunError::usage)?)
        };
        Ok(Input {
            source,
            dem,
            decided_crs: decided,
        })
    }
}

/// The shard's pulse range over the inputs in sequence, as each input's share of it (pulse
/// numbers within that input).
fn shard_ranges(paths: &[PathBuf], s: Shard) -> Result<Vec<(u64, u64)>, RunError> {
    let counts = paths
        .iter()
        .map(|p| crate::source::shard::count_pulses(p))
        .collect::<Result<Vec<u64>, String>>()
        .map_err(RunError::job)?;
    let total: u64 = counts.iter().sum();
    let (lo, hi) = s.range(total);
    if lo == hi {
        return Err(RunError::usage(format!(
            "--shard {s}: the input holds {total} pulses, so shard {s} holds none; give fewer \
             shards than pulses"
        )));
    }
    let mut offset = 0;
    let mut r = Vec::new();
    for c in counts {
        r.push((
            lo.clamp(offset, offset + c) - offset,
            hi.clamp(offset, offset + c) - offset,
        ));
        offset += c;
    }
    tracing::info!(shard = %s, first_pulse = lo, end_pulse = hi, "replaying one shard");
    Ok(r)
}

/// The DEM `[georeference] dem` names, opened.
pub fn open_dem(config: &RunConfig) -> Result<Option<Arc<Dem>>, RunError> {
    match &config.georeference.dem {
        Some(path) => Ok(Some(Arc::new(
            Dem::open(Path::new(path)).map_err(RunError::job)?,
        ))),
        None => Ok(None),
    }
}

/// The georeferenced source and its decided-CRS cell (the source itself when `[georeference]`
/// is off).
type Georeferenced = (Box<DynSource>, Option<Arc<OnceLock<String>>>);

/// Wraps `source` in the georeferencing with the DEM already open.
fn georeference_with(
    source: Box<DynSource>,
    config: &RunConfig,
    dem: Option<Arc<Dem>>,
) -> Result<Georeferenced, RunError> {
    if !config.georeference.enabled {
        return Ok((source, None));
    }
    let mut geo_cfg = config.georeference.clone();
    // Register to the ground in the DEM's own CRS unless an output CRS is named (a named one
    // that differs from the DEM's was refused when the configuration was loaded).
    if geo_cfg.output_epsg.is_none()
        && let Some(code) = dem.as_ref().and_then(|d| d.epsg)
    {
        geo_cfg.output_epsg = Some(code);
    }
    let mut g = GeoreferencingSource::new(source, geo_cfg)
        .map_err(RunError::usage)?
        .with_earliest_date(config.navigation.earliest_days());
    if let (Some(d), Some(path)) = (&dem, &config.georeference.dem) {
        g = g.with_dem(d.clone(), path.clone());
    }
    let decided = g.decided_crs();
    Ok((Box::new(g), Some(decided)))
}
