//! The voxel-tile sink (`[voxels] enabled = true`): deposits every pulse's return bins into
//! the voxel grid (`crate::voxel::voxelise`), closes tiles as the flight leaves them and writes
//! them to `voxels.zarr` (`crate::voxel::zarr`).
//!
//! The store is created at the first pulse with geometry: that is when the output CRS is known
//! for a capture georeferenced into the UTM zone of its first fix, and where the automatic
//! extent is centred. Rerunning with the same output resumes a store the same run left behind
//! (killed, or complete): tile by tile, deposits already in it are skipped. While the run writes,
//! the store's arrays span the whole extent; `finish` fits them to the tiles written.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use crate::geo::dem::Dem;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::{Pulse, SegmentKind};
use crate::sink::SinkReport;
use crate::voxel::grid::{Grid, Placer, VoxelConfig};
use crate::voxel::tiles::TileSet;
use crate::voxel::tiles::TileStats;
use crate::voxel::voxelise::{DepositParams, DepositStats, deposit_pulse};
use crate::voxel::zarr::{StoreError, StoreInfo, ZarrStore};

/// Where the automatic extent is centred when `pulse` is the first with geometry: the middle of
/// its first return segment (x, y in the output CRS, m); `None` without a finite position.
pub fn extent_centre(pulse: &Pulse) -> Option<[f64; 2]> {
    let g = pulse.geometry?;
    let t = pulse
        .segments
        .iter()
        .find(|s| s.kind == SegmentKind::Return)
        .map(|s| s.start_ns + s.len as f64 * pulse.sample_ns / 2.0)
        .unwrap_or(0.0);
    let c = [
        g.anchor[0] + t * g.direction[0],
        g.anchor[1] + t * g.direction[1],
    ];
    c.iter().all(|v| v.is_finite()).then_some(c)
}

/// Where the output CRS comes from.
#[derive(Clone, Debug)]
pub enum CrsSource {
    /// Known before the run (the input states it, or the configuration names it): OGC WKT or
    /// `EPSG:<code>`; `None` when nobody knows.
    Known(Option<String>),
    /// Decided by the georeferencing during the run (the UTM zone of the first fix).
    Decided(Arc<OnceLock<String>>),
}

/// The voxel sink's report (`summary.json` → `sinks.voxels`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct VoxelReport {
    /// The store.
    pub store: String,
    /// What was deposited and skipped.
    pub deposits: DepositStats,
    /// The tiles' lifecycle and the store's writes (after the first pulse with geometry).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tiles: Option<VoxelTilesReport>,
    /// The grid.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grid: Option<VoxelGridReport>,
    /// What the store's arrays span.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub arrays: Option<VoxelArraysReport>,
    /// Pulses per tile, for the QC map (the daemon only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage: Option<CoverageReport>,
}

/// The tiles' lifecycle and what the store wrote.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct VoxelTilesReport {
    /// Tiles opened, closed, merged, peaks.
    #[serde(flatten)]
    pub lifecycle: TileStats,
    /// Tiles written.
    pub written: u64,
    /// Bytes through the compressor.
    pub bytes_written: u64,
    /// Bytes stored.
    pub bytes_stored: u64,
    /// Chunk files written.
    pub chunks_written: u64,
    /// Inner chunks encoded.
    pub inner_chunks_written: u64,
    /// Tiles in the store.
    pub in_store: u64,
    /// Commits of an earlier run completed when the store was opened.
    pub recovered_commits: u64,
}

/// The voxel grid.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct VoxelGridReport {
    /// Its CRS's EPSG code.
    pub epsg: Option<u32>,
    /// Voxel size x, y, z, m.
    pub voxel_size_m: [f64; 3],
    /// Height levels.
    pub levels: u32,
    /// Levels per height chunk.
    pub chunk_levels: u32,
    /// Columns per tile side.
    pub tile_columns: u32,
    /// South-west corner of the extent, m.
    pub extent_origin_m: [f64; 2],
    /// Tiles across the extent.
    pub tiles: [u32; 2],
    /// Heights: `absolute` or `above_dem`.
    pub height: &'static str,
    /// Units of the deposited intensity.
    pub intensity_units: String,
}

/// What the store's arrays span.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct VoxelArraysReport {
    /// First tile.
    pub tile_min: [i64; 2],
    /// Tiles spanned.
    pub tiles: [u32; 2],
    /// Fitted to the tiles written (the run ended).
    pub fitted: bool,
    /// The arrays' shape (levels, rows, columns).
    pub shape: [u64; 3],
    /// Origin of the arrays, m.
    pub origin_m: [f64; 2],
}

/// Pulses per tile (the daemon's QC map).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct CoverageReport {
    /// Tile size, m.
    pub tile_m: [f64; 2],
    /// Grid origin, m.
    pub origin_m: [f64; 2],
    /// Each tile: column, row, pulses, open (1) or closed (0).
    pub cells: Vec<[i64; 4]>,
    /// Highest canopy height per tile, m (none without metrics).
    pub canopy_max_m: Vec<Option<f32>>,
}

/// The sink.
pub struct VoxelTilesSink {
    cfg: VoxelConfig,
    root: PathBuf,
    crs: CrsSource,
    info: StoreInfo,
    dem: Option<Arc<Dem>>,
    divergence_mrad: Option<f64>,
    tiles: Option<TileSet>,
    params: Option<DepositParams>,
    stats: DepositStats,
    next_seq: u64,
    finished: bool,
    /// Take the grid of a store already there (a survey continued by the daemon).
    continue_store: bool,
    /// Per tile by footprint centre (the QC coverage map), when tracked: the pulses, and the
    /// highest canopy height (RH100, m) of those with forest metrics (NaN: none).
    coverage: Option<std::collections::HashMap<[i64; 2], (u64, f32)>>,
    /// Write closed tiles on a writer thread, this many waiting at most (0: on this thread).
    writer_queue: usize,
}

/// The voxel store failed (the error names the file).
#[derive(Debug, thiserror::Error)]
#[error("voxel tiles: {0}")]
pub struct VoxelStoreError(#[from] pub StoreError);

fn store_err(e: StoreError) -> SinkError {
    SinkError::output(VoxelStoreError(e))
}

impl VoxelTilesSink {
    /// A sink writing `dir/voxels.zarr`. `info` carries the intensity units, the run identity
    /// and the configuration text (its CRS fields are filled from `crs`); `dem` is needed for
    /// heights above ground; `divergence_mrad` (the sensor's) for the footprint spread unless
    /// the configuration gives one.
    pub fn create(
        dir: &Path,
        cfg: VoxelConfig,
        crs: CrsSource,
        info: StoreInfo,
        dem: Option<Arc<Dem>>,
        divergence_mrad: Option<f64>,
    ) -> Result<Self, SinkError> {
        Ok(VoxelTilesSink {
            root: dir.join("voxels.zarr"),
            divergence_mrad: cfg.beam_divergence_mrad.or(divergence_mrad),
            cfg,
            crs,
            info,
            dem,
            tiles: None,
            params: None,
            stats: DepositStats::default(),
            next_seq: 0,
            finished: false,
            continue_store: false,
            coverage: None,
            writer_queue: 0,
        })
    }

    /// Writes closed tiles on a thread of their own, at most `queue` waiting, so that the
    /// deposits do not wait for compression and fsyncs (the daemon's latency; the store ends up
    /// the same).
    pub fn with_tile_writer(mut self, queue: usize) -> Self {
        self.writer_queue = queue;
        self
    }

    /// Continues a store left by an earlier run of the same survey: its grid is taken as it is
    /// (the automatic extent was centred on that run's first pulse) and the run must be the
    /// same (`StoreInfo::run_key`). For the daemon, whose restarts continue one survey; the
    /// pulses' `seq` must continue too (`RunControl::seq_base`).
    pub fn continuing(mut self) -> Self {
        self.continue_store = true;
        self
    }

    /// Counts pulses per tile (footprint centre) for the report's `coverage` (the QC map).
    pub fn with_coverage(mut self) -> Self {
        self.coverage = Some(std::collections::HashMap::new());
        self
    }

    /// What was deposited and skipped so far.
    pub fn stats(&self) -> &DepositStats {
        &self.stats
    }

    /// The open tile set (after the first pulse with geometry).
    pub fn tiles(&self) -> Option<&TileSet> {
        self.tiles.as_ref()
    }

    fn start(&mut self, pulse: &Pulse) -> Result<(), SinkError> {
        let Some(first) = extent_centre(pulse) else {
            return Ok(());
        };
        let crs = match &self.crs {
            CrsSource::Known(c) => c.clone(),
            CrsSource::Decided(cell) => cell.get().cloned(),
        };
        let mut info = self.info.clone();
        info.epsg = crs.as_deref().and_then(crate::geo::crs::epsg_of);
        info.crs_wkt = crs.filter(|c| !c.starts_with("EPSG:"));
        let mut grid = Grid::new(&self.cfg, first);
        if self.continue_store && self.root.join("zarr.json").exists() {
            let existing = ZarrStore::open(&self.root).map_err(store_err)?;
            grid = existing.grid().clone();
            tracing::info!(
                store = %self.root.display(),
                tiles = existing.tiles().len(),
                "continuing the survey's voxel store on its grid"
            );
        }
        if self.cfg.extent_m.is_none() {
            tracing::info!(
                "voxel store: tiles may lie in a {} km square centred on the first pulse \
                 ({:.1}, {:.1}); only those holding data are written",
                self.cfg.auto_extent_m / 1e3,
                first[0],
                first[1]
            );
        }
        let store = ZarrStore::create_or_open_grouped(
            &self.root,
            grid.clone(),
            info,
            self.cfg.layout_choice(),
        )
        .map_err(store_err)?;
        if store.recovered_commits > 0 || store.discarded_pending > 0 || !store.tiles().is_empty() {
            tracing::info!(
                tiles = store.tiles().len(),
                recovered = store.recovered_commits,
                discarded = store.discarded_pending,
                "resuming the voxel store {}",
                self.root.display()
            );
        }
        self.params = Some(DepositParams {
            placer: Placer::new(&grid),
            height: grid.height,
            dem: self.dem.clone(),
            inv_quantum: 1.0 / grid.intensity_quantum,
            footprint_divergence_rad: if self.cfg.footprint {
                self.divergence_mrad.map(|d| d * 1e-3)
            } else {
                None
            },
        });
        let wkt = store.info().crs_wkt.clone();
        let mut tiles = TileSet::new(store, self.cfg.max_open_tiles, self.cfg.close_after_s)
            .with_memory_budget((self.cfg.max_open_mib as usize).saturating_mul(1 << 20));
        if self.writer_queue > 0 {
            tiles = tiles.with_writer_threads(self.writer_queue, self.cfg.writer_threads());
        }
        if self.cfg.las {
            let dir = self
                .root
                .parent()
                .unwrap_or(Path::new("."))
                .join("voxels_las");
            std::fs::create_dir_all(&dir).map_err(|source| SinkError::Io {
                path: dir.display().to_string(),
                source,
            })?;
            tiles = tiles.with_las(dir, wkt);
        }
        self.tiles = Some(tiles);
        Ok(())
    }
}

impl PulseSink for VoxelTilesSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "voxels"
    }

    fn write(&mut self, pulse: &Pulse) -> Result<(), SinkError> {
        if self.tiles.is_none() {
            self.start(pulse)?;
        }
        self.next_seq = pulse.seq + 1;
        let (Some(tiles), Some(params)) = (self.tiles.as_mut(), self.params.as_ref()) else {
            // No store yet: the pulse has no usable geometry; count it.
            deposit_counts_only(pulse, &mut self.stats);
            return Ok(());
        };
        tiles
            .close_idle(pulse.seq, pulse.gps_time)
            .map_err(store_err)?;
        if let Some(cov) = self.coverage.as_mut()
            && let Some(c) = footprint_centre(pulse)
        {
            let g = tiles.grid();
            let tm = g.tile_m();
            let t = [
                ((c[0] - g.origin_m[0]) / tm[0]).floor() as i64,
                ((c[1] - g.origin_m[1]) / tm[1]).floor() as i64,
            ];
            let e = cov.entry(t).or_insert((0, f32::NAN));
            e.0 += 1;
            if let Some(m) = pulse
                .metrics
                .as_ref()
                .filter(|m| m.status == crate::pulse::waveform_metrics::MetricsStatus::Ok)
                && m.canopy_height.is_finite()
            {
                // f32::max keeps the number when the other side is NaN.
                e.1 = e.1.max(m.canopy_height);
            }
        }
        deposit_pulse(pulse, tiles, params, &mut self.stats).map_err(store_err)
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        Ok(())
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        if self.finished {
            return Ok(());
        }
        self.finished = true;
        if let Some(t) = self.tiles.as_mut() {
            t.close_all(self.next_seq).map_err(store_err)?;
        }
        Ok(())
    }

    fn report(&self) -> SinkReport {
        let mut r = VoxelReport {
            store: self.root.display().to_string(),
            deposits: self.stats.clone(),
            ..VoxelReport::default()
        };
        if let Some(t) = &self.tiles {
            let s = t.store();
            let g = t.grid();
            r.tiles = Some(VoxelTilesReport {
                lifecycle: t.stats().clone(),
                written: s.tiles_written,
                bytes_written: s.bytes_written,
                bytes_stored: s.bytes_stored,
                chunks_written: s.chunks_written,
                inner_chunks_written: s.inner_chunks_written,
                in_store: s.tiles().len() as u64,
                recovered_commits: s.recovered_commits,
            });
            r.grid = Some(VoxelGridReport {
                epsg: s.info().epsg,
                voxel_size_m: g.voxel_size_m,
                levels: g.levels,
                chunk_levels: g.chunk_levels(),
                tile_columns: g.tile_columns,
                extent_origin_m: g.extent_origin(),
                tiles: g.tiles,
                height: g.height.name(),
                intensity_units: s.info().intensity_units.clone(),
            });
            // What the store's arrays span: the bounding box of the tiles written once the run
            // ended (`fitted`), the whole extent while it writes.
            let span = s.span();
            r.arrays = Some(VoxelArraysReport {
                tile_min: span.tile_min,
                tiles: span.tiles,
                fitted: span.fitted,
                shape: span.shape(g),
                origin_m: span.origin_m(g),
            });
            r.coverage = self.coverage.as_ref().map(|cov| {
                let open: std::collections::HashSet<[i64; 2]> =
                    t.open_tiles().into_iter().collect();
                let mut cells: Vec<([i64; 4], f32)> = cov
                    .iter()
                    .map(|(k, (n, h))| ([k[0], k[1], *n as i64, open.contains(k) as i64], *h))
                    .collect();
                cells.sort_unstable_by_key(|c| c.0);
                CoverageReport {
                    tile_m: g.tile_m(),
                    origin_m: g.origin_m,
                    // Canopy height per cell, in the cells' order (none: no pulse with metrics).
                    canopy_max_m: cells
                        .iter()
                        .map(|c| c.1.is_finite().then_some(c.1))
                        .collect(),
                    cells: cells.into_iter().map(|c| c.0).collect(),
                }
            });
        }
        SinkReport::Voxels(Box::new(r))
    }
}

/// Where the pulse's first return segment is halfway through, `[x, y]` in the output CRS.
fn footprint_centre(pulse: &Pulse) -> Option<[f64; 2]> {
    let g = pulse.geometry?;
    let t = pulse
        .segments
        .iter()
        .find(|s| s.kind == SegmentKind::Return)
        .map(|s| s.start_ns + s.len as f64 * pulse.sample_ns / 2.0)?;
    let c = [
        g.anchor[0] + t * g.direction[0],
        g.anchor[1] + t * g.direction[1],
    ];
    c.iter().all(|v| v.is_finite()).then_some(c)
}

/// Counts a pulse seen before the store exists (it had no usable geometry).
fn deposit_counts_only(pulse: &Pulse, stats: &mut DepositStats) {
    match pulse.geometry {
        None => stats.pulses_no_geometry += 1,
        Some(_) => stats.pulses_non_finite += 1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::PulseGeometry;
    use crate::voxel::tile::Dense;

    /// A nadir pulse over (x, y): 40 return bins from 10 m above z = 0 down to 2 m below, 1 V
    /// each except a 5 V echo at z = 0.
    fn pulse(seq: u64, t: f64, x: f64, y: f64) -> Pulse {
        let mut p = Pulse {
            seq,
            gps_time: t,
            sample_ns: 1.0,
            geometry: Some(PulseGeometry {
                anchor: [x, y, 10.0],
                direction: [0.0, 0.0, -0.15],
            }),
            ..Default::default()
        };
        p.push_segment(SegmentKind::Return, 0, 0.0, 0..80u16);
        p.signal = (0..80)
            .map(|i| if (66..=67).contains(&i) { 5.0 } else { 1.0 })
            .collect();
        p
    }

    fn cfg() -> VoxelConfig {
        VoxelConfig {
            enabled: true,
            extent_m: Some([0.0, 0.0, 64.0, 64.0]),
            z_range_m: [-1.5, 4.5],
            voxel_size_m: [1.0, 1.0, 0.3],
            tile_columns: 8,
            max_open_tiles: 4,
            close_after_s: 0.5,
            ..VoxelConfig::default()
        }
    }

    fn info() -> StoreInfo {
        StoreInfo {
            crs_wkt: None,
            epsg: None,
            intensity_units: "V".into(),
            run_key: "test".into(),
            configuration: String::new(),
        }
    }

    /// A sink writing into `dir` (EPSG:32736, no DEM).
    fn sink(dir: &Path, cfg: VoxelConfig) -> VoxelTilesSink {
        VoxelTilesSink::create(
            dir,
            cfg,
            CrsSource::Known(Some("EPSG:32736".into())),
            info(),
            None,
            None,
        )
        .unwrap()
    }

    fn run(dir: &Path, cfg: VoxelConfig, pulses: impl Iterator<Item = Pulse>) -> VoxelTilesSink {
        let mut s = sink(dir, cfg);
        for p in pulses {
            s.write(&p).unwrap();
        }
        s.finish().unwrap();
        s
    }

    /// A flight line eastwards over y = 4.5 then back westwards over y = 5.5, 10 pulses per
    /// metre, 1 s per 10 m.
    fn flight() -> impl Iterator<Item = Pulse> {
        let out = (0..600).map(|i| pulse(i, i as f64 * 0.01, 0.05 + i as f64 * 0.1, 4.5));
        let back =
            (0..600).map(|i| pulse(600 + i, 10.0 + i as f64 * 0.01, 59.95 - i as f64 * 0.1, 5.5));
        out.chain(back)
    }

    fn read_all(dir: &Path) -> Vec<([i64; 2], Dense)> {
        ZarrStore::open(&dir.join("voxels.zarr"))
            .unwrap()
            .read_all()
            .unwrap()
            .into_iter()
            .map(|(t, d)| (t, d.dense()))
            .collect()
    }

    /// Two stores' tiles hold the same sums, counts and maxima (bit for bit).
    fn assert_same_tiles(a: &Path, b: &Path) {
        let (a, b) = (read_all(a), read_all(b));
        assert_eq!(a.len(), b.len());
        let bits = |d: &Dense| d.max.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for ((ta, da), (tb, db)) in a.iter().zip(&b) {
            assert_eq!(ta, tb);
            assert_eq!(da.sum_q, db.sum_q, "tile {ta:?}");
            assert_eq!(da.samples, db.samples, "tile {ta:?}");
            assert_eq!(da.pulses, db.pulses, "tile {ta:?}");
            assert_eq!(bits(da), bits(db), "tile {ta:?}");
        }
    }

    #[test]
    fn bins_land_in_their_voxels_with_sums_counts_maxima_and_passes() {
        let dir = tempfile::tempdir().unwrap();
        let s = run(
            dir.path(),
            cfg(),
            [pulse(0, 0.0, 3.2, 2.7), pulse(1, 0.001, 3.4, 2.9)].into_iter(),
        );
        let st = s.stats();
        // Bins at z = 10 − 0.15 i: inside [-1.5, 4.5) for i in 37..=76 → 40 per pulse.
        assert_eq!(st.bins_deposited, 80);
        assert_eq!(st.bins_outside_heights, 80);
        let tiles = read_all(dir.path());
        assert_eq!(tiles.len(), 1);
        let (t, d) = &tiles[0];
        assert_eq!(*t, [0, 0]);
        // Column (3, 2); the echo at z = 0.1 and −0.05 is in level floor((z+1.5)/0.3) = 5 and
        // 4: bins 66 (z = 0.1) → level 5, 67 (z = −0.05) → level 4.
        let at = |k: usize| (2 * 8 + 3) * 20 + k;
        assert_eq!(d.max[at(5)], 5.0);
        assert_eq!(d.max[at(4)], 5.0);
        // Level 5 spans z in [0, 0.3): bins 64 (0.4)? no: z = 10 − 0.15·i for i = 65, 66 → 0.25,
        // 0.1 → two bins per pulse, one of 1 V and one of 5 V: sum 12 V over two pulses.
        assert_eq!(d.samples[at(5)], 4);
        assert_eq!(d.sum_q[at(5)], 12_000_000);
        assert_eq!(d.pulses[at(5)], 2, "each pulse passed once");
        assert_eq!(d.pulses[at(19)], 2);
        let next_column = (2 * 8 + 4) * 20 + 5;
        assert!(d.max[next_column].is_nan() && d.samples[next_column] == 0);
    }

    #[test]
    fn the_coverage_map_keeps_the_highest_canopy_per_tile() {
        use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
        let dir = tempfile::tempdir().unwrap();
        let mut s = VoxelTilesSink::create(
            dir.path(),
            cfg(),
            CrsSource::Known(Some("EPSG:32736".into())),
            info(),
            None,
            None,
        )
        .unwrap()
        .with_coverage();
        // Tile (0, 0): canopy 12 m and 17 m and a pulse without metrics; tile (1, 0): one
        // pulse without metrics.
        for (i, (x, h)) in [
            (3.2, Some(12.0f32)),
            (3.4, Some(17.0)),
            (3.6, None),
            (12.0, None),
        ]
        .into_iter()
        .enumerate()
        {
            let mut p = pulse(i as u64, i as f64 * 0.001, x, 2.7);
            p.metrics = h.map(|h| {
                let mut m = WaveformMetrics {
                    status: MetricsStatus::Ok,
                    ..Default::default()
                };
                m.canopy_height = h;
                m
            });
            s.write(&p).unwrap();
        }
        let r = serde_json::to_value(s.report()).unwrap();
        let cov = &r["coverage"];
        let head = |i: usize| -> Vec<i64> {
            (0..3)
                .map(|j| cov["cells"][i][j].as_i64().unwrap())
                .collect()
        };
        assert_eq!(head(0), [0, 0, 3], "{cov}");
        assert_eq!(cov["canopy_max_m"][0], 17.0, "{cov}");
        assert_eq!(head(1), [1, 0, 1], "{cov}");
        assert!(cov["canopy_max_m"][1].is_null(), "{cov}");
        s.finish().unwrap();
    }

    #[test]
    fn a_tile_writer_thread_writes_the_same_store() {
        let inline = tempfile::tempdir().unwrap();
        let a = run(inline.path(), cfg(), flight());
        let threaded = tempfile::tempdir().unwrap();
        let mut b = sink(threaded.path(), cfg()).with_tile_writer(1);
        for p in flight() {
            b.write(&p).unwrap();
        }
        b.finish().unwrap();
        // The same lifecycle (the return line reopens tiles, some still being written) and the
        // same store, bit for bit.
        let (sa, sb) = (a.tiles().unwrap(), b.tiles().unwrap());
        assert_eq!(
            (sa.stats().opened, sa.stats().closed, sa.stats().merged),
            (sb.stats().opened, sb.stats().closed, sb.stats().merged)
        );
        assert_eq!(sa.store().tiles_written, sb.store().tiles_written);
        assert_eq!(sa.store().tiles(), sb.store().tiles());
        assert_same_tiles(inline.path(), threaded.path());
    }

    #[test]
    fn tiles_close_behind_the_flight_and_a_second_line_merges_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let s = run(dir.path(), cfg(), flight());
        let ts = s.tiles().unwrap().stats().clone();
        // 60 m of line = 8 tiles (8 m each) out; back over the same tiles, of which the last
        // two are still open at the turn: 14 openings, 6 of them merged with the store.
        assert_eq!((ts.opened, ts.closed, ts.merged), (14, 14, 6), "{ts:?}");
        assert!(ts.peak_open <= 4);
        // Equal to one run with room for everything (no tile closed before the end).
        let dir2 = tempfile::tempdir().unwrap();
        let big = VoxelConfig {
            max_open_tiles: 1000,
            close_after_s: 1000.0,
            ..cfg()
        };
        let s2 = run(dir2.path(), big, flight());
        assert_eq!(s2.tiles().unwrap().stats().merged, 0);
        assert_same_tiles(dir.path(), dir2.path());
    }

    #[test]
    fn a_resumed_run_skips_what_the_store_holds_and_ends_identical() {
        let full = tempfile::tempdir().unwrap();
        run(full.path(), cfg(), flight());
        // A run that stops after 900 pulses without closing its open tiles (as kill -9 would),
        // then a rerun of everything into the same folder.
        let cut = tempfile::tempdir().unwrap();
        {
            let mut s = VoxelTilesSink::create(
                cut.path(),
                cfg(),
                CrsSource::Known(Some("EPSG:32736".into())),
                info(),
                None,
                None,
            )
            .unwrap();
            for p in flight().take(900) {
                s.write(&p).unwrap();
            }
            assert!(s.tiles().unwrap().store().tiles_written > 0);
            // Dropped without finish: open tiles are lost.
        }
        let s = run(cut.path(), cfg(), flight());
        assert!(s.stats().bins_resumed > 0);
        assert_same_tiles(full.path(), cut.path());
    }

    #[test]
    fn tiles_grouped_into_shards_hold_the_same_voxels_inline_threaded_and_resumed() {
        let plain = tempfile::tempdir().unwrap();
        run(plain.path(), cfg(), flight());
        let grouped = || VoxelConfig {
            shard_tiles: 2,
            shard_height_chunks: 1,
            ..cfg()
        };
        let inline = tempfile::tempdir().unwrap();
        let a = run(inline.path(), grouped(), flight());
        assert_same_tiles(plain.path(), inline.path());
        // 60 m of line in 16 m groups: a few files per array, written as the flight left them.
        let files = |d: &Path| store_files(d);
        let shards = files(inline.path())
            .into_keys()
            .filter(|k| k.contains("sample_count/c/"))
            .count();
        assert!((2..=5).contains(&shards), "{shards}");
        assert!(a.tiles().unwrap().stats().merged > 0);
        let threaded = tempfile::tempdir().unwrap();
        let mut b = sink(threaded.path(), grouped()).with_tile_writer(1);
        for p in flight() {
            b.write(&p).unwrap();
        }
        b.finish().unwrap();
        assert_same_tiles(plain.path(), threaded.path());
        let data = |d: &Path| {
            files(d)
                .into_iter()
                .filter(|(k, _)| k.contains("_count/c/") || k.contains("intensity_"))
                .collect::<Vec<_>>()
        };
        assert_eq!(data(inline.path()), data(threaded.path()));
        // Killed after 900 pulses, then run again into the same folder.
        let cut = tempfile::tempdir().unwrap();
        {
            let mut s = sink(cut.path(), grouped()).with_tile_writer(1);
            for p in flight().take(900) {
                s.write(&p).unwrap();
            }
        }
        let s = run(cut.path(), grouped(), flight());
        assert!(s.stats().bins_resumed > 0);
        assert_same_tiles(plain.path(), cut.path());
        assert_eq!(data(inline.path()), data(cut.path()));
    }

    #[test]
    fn pulses_without_or_with_broken_geometry_and_bins_outside_are_counted() {
        let dir = tempfile::tempdir().unwrap();
        let mut none = pulse(0, 0.0, 1.0, 1.0);
        none.geometry = None;
        let mut nan = pulse(1, 0.0, 1.0, 1.0);
        nan.geometry.as_mut().unwrap().anchor[0] = f64::NAN;
        let outside = pulse(2, 0.0, 100.0, 1.0);
        let s = run(dir.path(), cfg(), [none, nan, outside].into_iter());
        let st = s.stats();
        assert_eq!(st.pulses_no_geometry, 1);
        assert_eq!(st.pulses_non_finite, 1);
        assert_eq!(st.bins_outside_extent, 80);
        assert_eq!(st.bins_deposited, 0);
    }

    #[test]
    fn a_pulse_crossing_tiles_with_room_for_one_keeps_every_deposit() {
        // Slanted pulses crossing from tile (0, 0) into (1, 0) (8 m tiles) and on; with room for
        // one open tile, tiles close early between pulses but never under the pulse.
        let slanted = |seq: u64| {
            // Alternately from x = 6 and x = 14 m: each pulse reopens what the last one closed.
            let x = 6.0 + (seq % 2) as f64 * 8.0 + (seq / 2) as f64 * 0.05;
            let mut p = pulse(seq, seq as f64 * 0.001, x, 3.0);
            p.geometry.as_mut().unwrap().direction = [0.06, 0.0, -0.14];
            p
        };
        let tight = tempfile::tempdir().unwrap();
        let roomy = tempfile::tempdir().unwrap();
        let s1 = run(
            tight.path(),
            VoxelConfig {
                max_open_tiles: 1,
                ..cfg()
            },
            (0..40).map(slanted),
        );
        let s2 = run(roomy.path(), cfg(), (0..40).map(slanted));
        let st = s1.tiles().unwrap().stats();
        assert!(st.closed_early > 0 && st.merged > 0, "{st:?}");
        assert_eq!(st.peak_open, 2, "the bound gives way by one under a pulse");
        assert_eq!(s1.stats().bins_deposited, s2.stats().bins_deposited);
        assert_same_tiles(tight.path(), roomy.path());
    }

    #[test]
    fn a_memory_budget_closes_tiles_early_and_keeps_every_deposit() {
        // 8 m tiles of 128 × 128 columns (a tile's column map alone is 64 KiB a height chunk):
        // two passes over all 64 tiles, row by row, nothing closing by time or count; a
        // budget of 1 MiB holds about 16 of them.
        let wide = |max_open_mib| VoxelConfig {
            voxel_size_m: [0.0625, 0.0625, 0.3],
            tile_columns: 128,
            max_open_tiles: 64,
            max_open_mib,
            close_after_s: 1e6,
            ..cfg()
        };
        let passes = || {
            (0..2 * 64 * 4).map(|i: u64| {
                let tile = i % 64;
                let (tx, ty) = ((tile % 8) as f64, (tile / 8) as f64);
                let k = (i / 64) as f64;
                pulse(i, i as f64 * 0.001, tx * 8.0 + 1.0 + k, ty * 8.0 + 1.0 + k)
            })
        };
        let tight = tempfile::tempdir().unwrap();
        let roomy = tempfile::tempdir().unwrap();
        let s1 = run(tight.path(), wide(1), passes());
        let s2 = run(roomy.path(), wide(1024), passes());
        let (st, all) = (s1.tiles().unwrap().stats(), s2.tiles().unwrap().stats());
        assert!(st.closed_over_budget > 0 && st.merged > 0, "{st:?}");
        assert_eq!(st.closed_early, st.closed_over_budget, "{st:?}");
        assert!(st.peak_open < 32, "{st:?}");
        assert!(st.peak_open_bytes < 2 << 20, "{st:?}");
        assert_eq!((all.closed_early, all.peak_open), (0, 64), "{all:?}");
        assert!(all.peak_open_bytes > 3 << 20, "{all:?}");
        assert_eq!(s1.stats().bins_deposited, s2.stats().bins_deposited);
        assert_same_tiles(tight.path(), roomy.path());
    }

    #[test]
    fn calibrated_pulses_deposit_each_bin_times_its_own_factor() {
        let dir = tempfile::tempdir().unwrap();
        let mut p = pulse(0, 0.0, 3.2, 2.7);
        let cal = crate::pulse::Calibration {
            scale: 2.0,
            emission_ns: -30.0,
            metres_per_ns: 0.15,
            reference_range_m: 10.0,
            range_normalised: true,
        };
        p.calibration = Some(cal);
        let s = run(dir.path(), cfg(), [p].into_iter());
        assert_eq!(s.stats().bins_deposited, 40);
        let tiles = read_all(dir.path());
        let d = &tiles[0].1;
        // Level 5 of column (3, 2) holds bins 65 (1 V) and 66 (5 V).
        let at5 = (2 * 8 + 3) * 20 + 5;
        let want = 1.0 * cal.factor_at(65.0) + 5.0 * cal.factor_at(66.0);
        let got = d.sum_q[at5] as f64 * 1e-6;
        assert!((got - want as f64).abs() < 2e-6, "{got} vs {want}");
        assert_eq!(d.max[at5], 5.0 * cal.factor_at(66.0));
        // The factor grows with range: (96 · 0.15 / 10)² · 2 ≈ 4.1 at bin 66.
        assert!(d.max[at5] > 20.0);
    }

    #[test]
    fn footprint_spreads_a_bin_over_the_columns_it_covers_and_keeps_its_sum() {
        let dir = tempfile::tempdir().unwrap();
        let c = VoxelConfig {
            footprint: true,
            beam_divergence_mrad: Some(400.0), // 0.2 rad: 0.2 m radius per metre of range
            ..cfg()
        };
        // Range at the echo is 80 bins ·0.15 m ≈ 10 m → radius ≈ 1 m: several 1 m columns.
        let s = run(dir.path(), c, [pulse(0, 0.0, 4.5, 4.5)].into_iter());
        let tiles = read_all(dir.path());
        let total_q: i64 = tiles.iter().flat_map(|(_, d)| d.sum_q.iter()).sum();
        let columns_hit: std::collections::BTreeSet<usize> = tiles
            .iter()
            .flat_map(|(_, d)| {
                d.samples
                    .iter()
                    .enumerate()
                    .filter(|(_, n)| **n > 0)
                    .map(|(o, _)| o / 20)
            })
            .collect();
        assert!(columns_hit.len() >= 4, "{columns_hit:?}");
        // 38 bins of 1 V and 2 of 5 V in range: 48 V, up to rounding of the shares.
        assert!((total_q - 48_000_000).abs() < 1000, "{total_q}");
        assert_eq!(s.stats().bins_deposited, 40);
    }

    /// Every file of a store except the tile records (a file per tile, or the journal of grouped
    /// tiles: watermarks depend on when tiles closed).
    fn store_files(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
        fn walk(base: &Path, d: &Path, out: &mut std::collections::BTreeMap<String, Vec<u8>>) {
            for e in std::fs::read_dir(d).unwrap() {
                let p = e.unwrap().path();
                let rel = p.strip_prefix(base).unwrap().display().to_string();
                if p.is_dir() {
                    walk(base, &p, out);
                } else if !rel.starts_with("fwlidar_state/tiles/") && rel != "fwlidar_state/journal"
                {
                    out.insert(rel, std::fs::read(&p).unwrap());
                }
            }
        }
        let root = dir.join("voxels.zarr");
        let mut m = Default::default();
        walk(&root, &root, &mut m);
        m
    }

    #[test]
    fn a_continued_store_grows_beyond_its_fitted_arrays_and_ends_as_one_run() {
        // x 30..39 m, y 35 m: tiles (3..=4, 4) of 8 m; a file per tile fits them exactly, 16 × 16
        // tiles grouped into shard files widen the span down to the group's corner, (0, 0).
        let per_tile = VoxelConfig {
            shard_tiles: 0,
            ..cfg()
        };
        continued_store_grows(per_tile, ([3, 4], [2, 1]), 16);
        continued_store_grows(cfg(), ([0, 0], [5, 5]), 40);
    }

    fn continued_store_grows(cfg: VoxelConfig, first_span: ([i64; 2], [u32; 2]), columns: u64) {
        // The daemon's survey across a restart: a first run over the middle of the extent, a
        // second (continuing the store and the pulse numbers, writing on a writer thread) that
        // flies south-west and north-east of it.
        let first = || (0..300).map(|i| pulse(i, i as f64 * 0.01, 30.05 + i as f64 * 0.03, 35.0));
        let second = || {
            (0..300).map(|i| {
                let (x, y) = if i < 150 { (3.0, 2.0) } else { (60.0, 61.0) };
                pulse(
                    300 + i,
                    10.0 + i as f64 * 0.01,
                    x + (i % 10) as f64 * 0.2,
                    y,
                )
            })
        };
        let survey = tempfile::tempdir().unwrap();
        let continuing = |pulses: &mut dyn Iterator<Item = Pulse>| {
            let mut s = VoxelTilesSink::create(
                survey.path(),
                cfg.clone(),
                CrsSource::Known(Some("EPSG:32736".into())),
                info(),
                None,
                None,
            )
            .unwrap()
            .continuing()
            .with_tile_writer(1);
            for p in pulses {
                s.write(&p).unwrap();
            }
            s.finish().unwrap();
            s
        };
        let s = continuing(&mut first());
        let span = *s.tiles().unwrap().store().span();
        assert_eq!(
            (span.tile_min, span.tiles, span.fitted),
            (first_span.0, first_span.1, true)
        );
        assert_eq!(
            serde_json::to_value(s.report()).unwrap()["arrays"]["shape"],
            serde_json::json!([20, 8 * first_span.1[1], columns])
        );
        let s = continuing(&mut second());
        let span = *s.tiles().unwrap().store().span();
        assert_eq!((span.tile_min, span.tiles), ([0, 0], [8, 8]));
        // The same store, bit for bit, as one run of every pulse.
        let once = tempfile::tempdir().unwrap();
        let one = run(once.path(), cfg, first().chain(second()));
        assert_eq!(one.tiles().unwrap().store().span(), &span);
        assert_same_tiles(once.path(), survey.path());
        let (a, b) = (store_files(once.path()), store_files(survey.path()));
        assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
        for (k, v) in &a {
            assert!(b[k] == *v, "{k} differs");
        }
    }
}
