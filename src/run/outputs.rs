//! The outputs of a run: the sinks replay writes into its output folder, the sinks the
//! on-board daemon writes as it flies, and the identity of a run's voxel store.

use std::path::{Path, PathBuf};

use super::RunError;
use super::input::Input;
use crate::config::{RunConfig, WaveformFormat};
use crate::core::facts::SourceFacts;
use crate::sink::DynSink;
use crate::sink::hyper_points::HyperPointSink;
use crate::sink::las_wave::{LasWaveOptions, LasWaveSink};
use crate::sink::metrics_rasters::{MetricsRastersSink, RasterCrs, RasterSettings};
use crate::sink::pulse_metrics_csv::PulseMetricsCsvSink;
use crate::sink::returns_csv::ReturnsCsvSink;
use crate::sink::voxel_tiles::{CrsSource, VoxelTilesSink};
use crate::sink::waveform_csv::WaveformCsvSink;
use crate::sink::waveform_npy::WaveformNpySink;
use crate::source::shard::Shard;
use crate::stages::Chain;
use crate::voxel::zarr::StoreInfo;

/// Closed voxel tiles waiting for the tile writer threads at most (then the sink waits).
const TILE_WRITER_QUEUE: usize = 32;

/// Identifies a replay for resuming its voxel store (`StoreInfo::run_key`): each input's file
/// name and size, a checksum of the configuration (apart from the output folder), and the shard.
/// A campaign's mosaic carries the key of one replay of all its lines in sequence, the store it
/// equals (`crate::campaign`).
pub fn replay_run_key(inputs: &[PathBuf], shard: Option<Shard>, config: &RunConfig) -> String {
    let mut c = config.clone();
    c.output.dir.clear();
    let text = toml::to_string(&c).unwrap_or_default();
    let files: Vec<String> = inputs
        .iter()
        .map(|p| {
            let size = std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default();
            format!("{name} ({size} bytes)")
        })
        .collect();
    format!(
        "{}, configuration crc32c {:08x}{}",
        files.join(", "),
        crc32c::crc32c(text.as_bytes()),
        shard.map(|s| format!(", shard {s}")).unwrap_or_default()
    )
}

/// Whether replay's outputs write the discrete returns (`returns.csv`, `returns.las`) when the
/// chain finds them: what [`replay_sinks`] asks of `[output]` (`stages::RunContext`).
pub fn replay_writes_returns(config: &RunConfig) -> bool {
    config.output.returns || config.output.las
}

/// Whether the daemon's outputs write the discrete returns (the segment's LAS files) when the
/// chain finds them: what [`daemon_sinks`] asks of `[output]`.
pub fn daemon_writes_returns(config: &RunConfig) -> bool {
    config.output.las
}

/// What replay writes into `out_dir`: the outputs `[output]` and `[voxels]` ask for, each only
/// when the chain produces what it holds (returns after a decompose stage, metrics after a
/// metrics stage). `input_path` is the first input (a GEDI granule adds `shot_number` to
/// `pulse_metrics.csv`); `run_key` identifies the voxel store ([`replay_run_key`]).
pub fn replay_sinks(
    config: &RunConfig,
    chain: &Chain,
    input: &Input,
    input_path: &Path,
    run_key: &str,
    out_dir: &Path,
) -> Result<Vec<Box<DynSink>>, RunError> {
    let out = &config.output;
    let facts = input.source.facts();
    let products = chain.products();
    let mut sinks: Vec<Box<DynSink>> = Vec::new();
    if out.waveforms {
        sinks.push(match out.waveform_format {
            WaveformFormat::Npy => {
                Box::new(WaveformNpySink::create(out_dir).map_err(RunError::job)?)
            }
            WaveformFormat::Csv => {
                Box::new(WaveformCsvSink::create(out_dir).map_err(RunError::job)?)
            }
        });
    }
    if out.returns && products.returns {
        sinks.push(Box::new(
            ReturnsCsvSink::create_with_dem(out_dir, input.dem.clone()).map_err(RunError::job)?,
        ));
    }
    if out.las && products.returns {
        sinks.push(replay_las_sink(config, &facts, input, out_dir)?);
    }
    if out.hyper_points {
        sinks.push(Box::new(
            HyperPointSink::create(
                out_dir,
                out.hyper_threshold_v.unwrap_or(f32::INFINITY),
                las_options(&facts).crs_wkt.as_deref(),
                out.las_flush_s,
            )
            .map_err(RunError::job)?,
        ));
    }
    if out.metrics
        && let Some(m) = chain.metrics_config()
    {
        sinks.push(Box::new(
            PulseMetricsCsvSink::create(
                out_dir,
                is_hdf5(input_path),
                m.profile_bins,
                m.profile_bin_m,
                input.dem.clone(),
            )
            .map_err(RunError::job)?,
        ));
    }
    if out.rasters && products.metrics {
        sinks.push(Box::new(metrics_rasters_sink(
            config, &facts, input, out_dir,
        )));
    }
    if config.voxels.enabled {
        let info = store_info(chain, run_key.to_string(), config);
        sinks.push(voxel_sink(
            config,
            input,
            &facts,
            info,
            out_dir,
            VoxelUse::Replay,
        )?);
    }
    Ok(sinks)
}

/// What the daemon writes as it flies: the survey's voxel store (continued across restarts,
/// with the QC coverage) and the segment's LAS files (`DIR/returns/<segment>/`, rotated every
/// minute unless `las_rotate_s` says otherwise) after a decompose stage.
pub fn daemon_sinks(
    config: &RunConfig,
    chain: &Chain,
    input: &Input,
    out_dir: &Path,
    segment_stem: &str,
) -> Result<Vec<Box<DynSink>>, RunError> {
    let facts = input.source.facts();
    let mut sinks: Vec<Box<DynSink>> = Vec::new();
    if config.voxels.enabled {
        let mut keyed = config.clone();
        keyed.output.dir.clear();
        keyed.daemon = Default::default();
        keyed.navigation = Default::default();
        let run_key = format!(
            "survey {}, configuration crc32c {:08x}",
            config.daemon.survey,
            crc32c::crc32c(toml::to_string(&keyed).unwrap_or_default().as_bytes())
        );
        let info = store_info(chain, run_key, config);
        sinks.push(voxel_sink(
            config,
            input,
            &facts,
            info,
            out_dir,
            VoxelUse::Daemon,
        )?);
    }
    if daemon_writes_returns(config) && chain.products().returns {
        let dir = out_dir.join("returns").join(segment_stem);
        std::fs::create_dir_all(&dir).map_err(|e| {
            RunError::job(format!("cannot create LAS folder {}: {e}", dir.display()))
        })?;
        let out = &config.output;
        sinks.push(Box::new(
            LasWaveSink::create(
                &dir,
                LasWaveOptions {
                    point_format: out.las_point_format,
                    rotate_s: if out.las_rotate_s > 0.0 {
                        out.las_rotate_s
                    } else {
                        60.0
                    },
                    flush_s: out.las_flush_s,
                    crs_wkt: facts.crs.clone().filter(|c| !c.starts_with("EPSG:")),
                    crs_decided: input.decided_crs.clone(),
                    ..LasWaveOptions::default()
                },
            )
            .map_err(RunError::job)?,
        ));
    }
    Ok(sinks)
}

/// The voxel store's identity: its intensity units (calibrated backscatter after a calibrate
/// stage, volts otherwise), the run key and the configuration it was made with.
fn store_info(chain: &Chain, run_key: String, config: &RunConfig) -> StoreInfo {
    StoreInfo {
        crs_wkt: None,
        epsg: None,
        intensity_units: if chain.products().calibrated {
            "calibrated backscatter (docs/calibration.md)"
        } else {
            "V"
        }
        .into(),
        run_key,
        configuration: toml::to_string(config).unwrap_or_default(),
    }
}

/// Who writes the voxel store: replay (a new store, or a resumed replay of the same inputs) or
/// the daemon (the survey's store, continued across restarts, with the QC coverage).
#[derive(Clone, Copy, PartialEq, Eq)]
enum VoxelUse {
    Replay,
    Daemon,
}

/// `voxels.zarr`, in the CRS the input states or the georeferencing decides; closed tiles are
/// compressed and committed off the sink thread.
fn voxel_sink(
    config: &RunConfig,
    input: &Input,
    facts: &SourceFacts,
    info: StoreInfo,
    out_dir: &Path,
    user: VoxelUse,
) -> Result<Box<DynSink>, RunError> {
    let crs = match (facts.crs.clone(), input.decided_crs.clone()) {
        (Some(c), _) => CrsSource::Known(Some(c)),
        (None, Some(cell)) => CrsSource::Decided(cell),
        (None, None) => CrsSource::Known(None),
    };
    let mut sink = VoxelTilesSink::create(
        out_dir,
        config.voxels.clone(),
        crs,
        info,
        input.dem.clone(),
        facts.sensor.as_ref().map(|s| s.beam_divergence_mrad),
    )
    .map_err(RunError::job)?;
    if user == VoxelUse::Daemon {
        sink = sink.continuing().with_coverage();
    }
    Ok(Box::new(sink.with_tile_writer(TILE_WRITER_QUEUE)))
}

/// The metrics rasters, their tiles closed behind the flight by the voxel tiles' rule.
fn metrics_rasters_sink(
    config: &RunConfig,
    facts: &SourceFacts,
    input: &Input,
    out_dir: &Path,
) -> MetricsRastersSink {
    let out = &config.output;
    let crs = match (facts.crs.clone(), input.decided_crs.clone()) {
        (Some(c), _) => RasterCrs::Known(Some(c)),
        (None, Some(cell)) => RasterCrs::Decided(cell),
        (None, None) => RasterCrs::Known(None),
    };
    MetricsRastersSink::new(
        out_dir,
        RasterSettings {
            chm_cell_m: out.chm_cell_m,
            profile_cell_m: out.profile_cell_m,
            tile_m: out.raster_tile_m,
            close_after_s: config.voxels.close_after_s,
            max_open_tiles: config.voxels.max_open_tiles,
        },
        crs,
    )
}

/// Whether `path` is an HDF5 file (GEDI input: `pulse_metrics.csv` gains `shot_number`).
fn is_hdf5(path: &Path) -> bool {
    let mut head = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && head == *b"\x89HDF\r\n\x1a\n"
}

/// `returns.las` (or its rotated files), with the CRS and time base the input states, or the
/// CRS the georeferencing decides during the run.
fn replay_las_sink(
    config: &RunConfig,
    facts: &SourceFacts,
    input: &Input,
    out_dir: &Path,
) -> Result<Box<DynSink>, RunError> {
    if facts.crs.is_none() && input.decided_crs.is_none() {
        tracing::warn!(
            "returns.las will have no CRS record: the input states none before it is read \
             and no georeferencing decides it; set [georeference] output_epsg to name it"
        );
    }
    let out = &config.output;
    let sink = LasWaveSink::create(
        out_dir,
        LasWaveOptions {
            point_format: out.las_point_format,
            rotate_s: out.las_rotate_s,
            flush_s: out.las_flush_s,
            crs_decided: input.decided_crs.clone(),
            ..las_options(facts)
        },
    )
    .map_err(RunError::job)?;
    Ok(Box::new(sink))
}

/// The LAS output's CRS and time base from what the input states: its WKT when it gave one, or
/// the WKT of a WGS84 UTM zone named `EPSG:326zz`/`327zz` (other `EPSG:<code>`s cannot be
/// turned into the WKT LAS 1.4 requires without a CRS database, so the file then has no CRS
/// record and the summary of the input says which EPSG it was), and adjusted standard GPS time
/// when the input's times are in it.
fn las_options(facts: &SourceFacts) -> LasWaveOptions {
    LasWaveOptions {
        crs_wkt: facts
            .crs
            .as_deref()
            .and_then(|c| match c.strip_prefix("EPSG:") {
                // WGS84 UTM zones (GEDI input) are written from their parameters.
                Some(code) => code.parse().ok().and_then(crate::geo::crs::utm_wkt),
                None => Some(c.to_string()),
            }),
        adjusted_standard_gps_time: facts.time_base.as_deref() == Some("gps_adjusted_standard"),
        ..LasWaveOptions::default()
    }
}

/// Prepares the output folder: created when missing; an existing file of that name is refused.
pub fn prepare_out_dir(dir: &Path) -> Result<(), RunError> {
    if dir.exists() && !dir.is_dir() {
        return Err(RunError::job(format!(
            "output folder {} exists and is not a folder",
            dir.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| {
        RunError::job(format!(
            "cannot create output folder {}: {e}",
            dir.display()
        ))
    })
}
