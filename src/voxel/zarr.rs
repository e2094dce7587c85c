//! Voxel tiles as a Zarr v3 store (`voxels.zarr`), one chunk per tile, written atomically.
//!
//! Layout (Zarr v3 core specification; CF conventions so that `xarray.open_zarr` gives named
//! dimensions, coordinates and the CRS):
//!
//! ```text
//! voxels.zarr/zarr.json                 group: CRS (crs_wkt, epsg), origin, voxel size, units,
//!                                       the processing configuration, the grid (attributes)
//! voxels.zarr/intensity_sum/            int64 [z, y, x], CF scale_factor = intensity quantum
//! voxels.zarr/sample_count/             uint32: bins deposited
//! voxels.zarr/intensity_max/            float32: largest bin (NaN: none)
//! voxels.zarr/pulse_count/              uint32: pulses whose beam passed through
//! voxels.zarr/{x,y,z}/                  float64 voxel centres, metres
//! voxels.zarr/spatial_ref/              0-d CF grid mapping holding the WKT
//! voxels.zarr/fwlidar_state/tiles/TX_TY the tile's watermark record (resume; see below)
//! ```
//!
//! Every data array has chunk shape `[levels, T, T]`: a chunk is a tile, chunk key
//! `c/0/ROW/COL` (`ROW`, `COL` counted from the store's south-west tile). Codecs: `bytes`
//! (little endian) then `gzip` (level 1): a tile is mostly empty air.
//!
//! **Crash safety.** A tile's four chunks are written under `KEY.pending` and synced; then its
//! record `fwlidar_state/tiles/TX_TY` is replaced atomically by `{watermark, pending: true}`
//! (the commit point); then the pending chunks are renamed into place and the record rewritten
//! with `pending: false`. Opening a store completes any committed tile whose renames were cut
//! short and deletes pending chunks that were never committed, so every tile is either its old
//! or its new content, never a mix. The **watermark** is the sequence number of the first pulse
//! not yet in the tile: a tile holds exactly the deposits of pulses numbered below it (pulses
//! reach the voxeliser in order), so a rerun of the same input skips, tile by tile, what is
//! already there, and ends with the same bits as an uninterrupted run.

use std::fs::{self, File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use flate2::Compression;
use flate2::read::GzDecoder;
use flate2::write::GzEncoder;
use serde_json::{Value, json};

use super::grid::Grid;
use super::tile::TileData;

/// Names of the data arrays, in the order their chunks are written.
pub const ARRAYS: [&str; 4] = [
    "intensity_sum",
    "sample_count",
    "intensity_max",
    "pulse_count",
];

/// Errors of the tile store; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A file of the store is not what this program writes.
    #[error("{path}: {what}")]
    Invalid {
        /// The file.
        path: String,
        /// What is wrong, naming the field.
        what: String,
    },
    /// The store holds another grid or another run's tiles; nothing was changed.
    #[error(
        "{path}: {what}; nothing was changed (choose another output, or combine stores with `fwlidar merge`)"
    )]
    Mismatch {
        /// The store.
        path: String,
        /// What differs.
        what: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.display().to_string(),
        source,
    }
}

fn invalid(path: &Path, what: impl Into<String>) -> StoreError {
    StoreError::Invalid {
        path: path.display().to_string(),
        what: what.into(),
    }
}

/// What the store records about its contents besides the grid.
#[derive(Clone, Debug, PartialEq)]
pub struct StoreInfo {
    /// The output CRS as OGC WKT, when known.
    pub crs_wkt: Option<String>,
    /// Its EPSG code, when known.
    pub epsg: Option<u32>,
    /// Units of the deposited intensity (`V`, or the calibrated backscatter's).
    pub intensity_units: String,
    /// Identifies the run that writes the store (input and configuration); a rerun resumes only
    /// a store with the same identity. Empty for merged stores.
    pub run_key: String,
    /// The processing configuration (TOML text), recorded as an attribute.
    pub configuration: String,
}

/// Per tile: the watermark and whether a commit is incomplete.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRecord {
    /// First pulse sequence number not in the tile.
    pub watermark: u64,
    /// The tile's chunks are being renamed into place.
    pub pending: bool,
}

/// An open store.
pub struct ZarrStore {
    root: PathBuf,
    grid: Grid,
    info: StoreInfo,
    /// Reused encode/decode buffers.
    raw: Vec<u8>,
    packed: Vec<u8>,
    /// Committed tiles and their watermarks.
    records: std::collections::HashMap<[i64; 2], u64>,
    /// Tiles written (for the summary).
    pub tiles_written: u64,
    /// Bytes of uncompressed tile data written.
    pub bytes_written: u64,
    /// Committed tiles whose renames a previous run left unfinished, completed on open.
    pub recovered_commits: u64,
    /// Uncommitted pending chunks of a previous run, deleted on open.
    pub discarded_pending: u64,
}

fn dtype(name: &str) -> (&'static str, Value) {
    match name {
        "intensity_sum" => ("int64", json!(0)),
        "sample_count" | "pulse_count" => ("uint32", json!(0)),
        _ => ("float32", json!("NaN")),
    }
}

fn write_file_synced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut f = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .open(path)
        .map_err(io(path))?;
    f.write_all(bytes).map_err(io(path))?;
    f.sync_all().map_err(io(path))
}

/// Writes `path` atomically: `path.partial`, sync, rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    write_file_synced(&tmp, bytes)?;
    fs::rename(&tmp, path).map_err(io(path))
}

fn sync_dir(path: &Path) {
    // Makes the renames durable; not every platform can open a directory, so best effort.
    if let Ok(d) = File::open(path) {
        let _ = d.sync_all();
    }
}

impl ZarrStore {
    /// The store's folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The grid.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// What the store records.
    pub fn info(&self) -> &StoreInfo {
        &self.info
    }

    /// A store at `root` with nothing read or written yet.
    fn at(root: &Path, grid: Grid, info: StoreInfo) -> Self {
        ZarrStore {
            root: root.to_path_buf(),
            grid,
            info,
            raw: Vec::new(),
            packed: Vec::new(),
            records: Default::default(),
            tiles_written: 0,
            bytes_written: 0,
            recovered_commits: 0,
            discarded_pending: 0,
        }
    }

    /// Every tile of the store with its accumulators, in tile order (tests, small stores: one
    /// tile's memory each).
    pub fn read_all(&mut self) -> Result<Vec<([i64; 2], TileData)>, StoreError> {
        let n = self.grid.tile_voxels();
        let mut out = Vec::new();
        for t in self.tiles() {
            let mut d = TileData::new(n);
            self.read_tile(t, &mut d)?;
            out.push((t, d));
        }
        Ok(out)
    }

    /// Creates the store at `root`, or opens the one there when it was written by the same run
    /// on the same grid (a resumed run): committed but unfinished tiles are completed and
    /// uncommitted chunks removed. Another grid or run is refused without changing anything.
    pub fn create_or_open(root: &Path, grid: Grid, info: StoreInfo) -> Result<Self, StoreError> {
        let meta = root.join("zarr.json");
        if meta.exists() {
            let mut s = ZarrStore::open(root)?;
            if let Err(what) = s.grid.compatible(&grid) {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!("the store's grid differs from this run's: {what}"),
                });
            }
            if s.grid.tile_min != grid.tile_min || s.grid.tiles != grid.tiles {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!(
                        "the store covers tiles {:?} + {:?}, this run {:?} + {:?}",
                        s.grid.tile_min, s.grid.tiles, grid.tile_min, grid.tiles
                    ),
                });
            }
            if s.info.run_key != info.run_key {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!(
                        "the store was written by another run ({}), not this one ({})",
                        s.info.run_key, info.run_key
                    ),
                });
            }
            s.info = info;
            return Ok(s);
        }
        if root.exists() && fs::read_dir(root).map_err(io(root))?.next().is_some() {
            return Err(StoreError::Mismatch {
                path: root.display().to_string(),
                what: "the folder exists, is not empty and is not a voxel store".into(),
            });
        }
        let s = ZarrStore::at(root, grid, info);
        s.write_metadata()?;
        Ok(s)
    }

    /// Opens an existing store (for `merge`, reading, resuming), finishing interrupted commits.
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        let meta = root.join("zarr.json");
        let text = fs::read(&meta).map_err(io(&meta))?;
        let v: Value =
            serde_json::from_slice(&text).map_err(|e| invalid(&meta, format!("not JSON: {e}")))?;
        let attrs = v
            .get("attributes")
            .ok_or_else(|| invalid(&meta, "no `attributes`"))?;
        let fw = attrs
            .get("fwlidar")
            .ok_or_else(|| invalid(&meta, "no `attributes.fwlidar`: not a fwlidar voxel store"))?;
        let grid: Grid = serde_json::from_value(fw.get("grid").cloned().unwrap_or(Value::Null))
            .map_err(|e| invalid(&meta, format!("attributes.fwlidar.grid: {e}")))?;
        let s = |k: &str| attrs.get(k).and_then(|x| x.as_str()).map(str::to_string);
        let info = StoreInfo {
            crs_wkt: s("crs_wkt"),
            epsg: attrs
                .get("epsg")
                .and_then(|x| x.as_u64())
                .and_then(|x| u32::try_from(x).ok()),
            intensity_units: s("intensity_units").unwrap_or_default(),
            run_key: fw
                .get("run_key")
                .and_then(|x| x.as_str())
                .unwrap_or_default()
                .to_string(),
            configuration: s("configuration").unwrap_or_default(),
        };
        let mut store = ZarrStore::at(root, grid, info);
        store.recover()?;
        Ok(store)
    }

    fn state_dir(&self) -> PathBuf {
        self.root.join("fwlidar_state").join("tiles")
    }

    fn record_path(&self, tile: [i64; 2]) -> PathBuf {
        self.state_dir().join(format!("{}_{}", tile[0], tile[1]))
    }

    /// Path of a tile's chunk of `array`.
    pub fn chunk_path(&self, array: &str, tile: [i64; 2]) -> PathBuf {
        let [row, col] = self.grid.chunk_of(tile);
        self.root
            .join(array)
            .join("c")
            .join("0")
            .join(row.to_string())
            .join(col.to_string())
    }

    fn pending_path(&self, array: &str, tile: [i64; 2]) -> PathBuf {
        let mut p = self.chunk_path(array, tile).into_os_string();
        p.push(".pending");
        PathBuf::from(p)
    }

    fn read_record(path: &Path) -> Result<TileRecord, StoreError> {
        let text = fs::read(path).map_err(io(path))?;
        let v: Value = serde_json::from_slice(&text)
            .map_err(|e| invalid(path, format!("tile record is not JSON: {e}")))?;
        Ok(TileRecord {
            watermark: v
                .get("watermark")
                .and_then(|x| x.as_u64())
                .ok_or_else(|| invalid(path, "tile record has no `watermark`"))?,
            pending: v.get("pending").and_then(|x| x.as_bool()).unwrap_or(false),
        })
    }

    fn parse_tile_name(name: &str) -> Option<[i64; 2]> {
        let (a, b) = name.split_once('_')?;
        Some([a.parse().ok()?, b.parse().ok()?])
    }

    /// Completes committed tiles, discards uncommitted chunks, loads the watermarks.
    fn recover(&mut self) -> Result<(), StoreError> {
        let dir = self.state_dir();
        if dir.exists() {
            for entry in fs::read_dir(&dir).map_err(io(&dir))? {
                let entry = entry.map_err(io(&dir))?;
                let name = entry.file_name().to_string_lossy().to_string();
                if name.ends_with(".partial") {
                    let _ = fs::remove_file(entry.path());
                    continue;
                }
                let Some(tile) = Self::parse_tile_name(&name) else {
                    continue;
                };
                let rec = Self::read_record(&entry.path())?;
                if rec.pending {
                    for a in ARRAYS {
                        let p = self.pending_path(a, tile);
                        if p.exists() {
                            let c = self.chunk_path(a, tile);
                            fs::rename(&p, &c).map_err(io(&c))?;
                        }
                    }
                    write_atomic(
                        &entry.path(),
                        json!({"watermark": rec.watermark, "pending": false})
                            .to_string()
                            .as_bytes(),
                    )?;
                    self.recovered_commits += 1;
                }
                self.records.insert(tile, rec.watermark);
            }
        }
        // Pending chunks no record committed: an interrupted first step; the old chunk stays.
        for a in ARRAYS {
            let base = self.root.join(a).join("c");
            if base.exists() {
                self.discarded_pending += remove_pending(&base)?;
            }
        }
        Ok(())
    }

    /// Watermark of a tile already in the store.
    pub fn watermark(&self, tile: [i64; 2]) -> Option<u64> {
        self.records.get(&tile).copied()
    }

    /// Tiles in the store.
    pub fn tiles(&self) -> Vec<[i64; 2]> {
        let mut t: Vec<_> = self.records.keys().copied().collect();
        t.sort();
        t
    }

    /// Reads a tile into `into` (which must have the grid's tile size); false when the store has
    /// no such tile (`into` is then cleared).
    pub fn read_tile(&mut self, tile: [i64; 2], into: &mut TileData) -> Result<bool, StoreError> {
        into.clear();
        if !self.records.contains_key(&tile) {
            return Ok(false);
        }
        let n = self.grid.tile_voxels();
        for a in ARRAYS {
            let path = self.chunk_path(a, tile);
            if !path.exists() {
                continue; // all fill value
            }
            let f = File::open(&path).map_err(io(&path))?;
            self.raw.clear();
            GzDecoder::new(f)
                .read_to_end(&mut self.raw)
                .map_err(|e| invalid(&path, format!("chunk does not decompress: {e}")))?;
            let width = if a == "intensity_sum" { 8 } else { 4 };
            if self.raw.len() != n * width {
                return Err(invalid(
                    &path,
                    format!(
                        "chunk holds {} bytes, a tile of {n} voxels needs {}",
                        self.raw.len(),
                        n * width
                    ),
                ));
            }
            let order = DiskOrder::of(&self.grid);
            let raw = &self.raw;
            match a {
                "intensity_sum" => order.read(raw, &mut into.sum_q, i64::from_le_bytes),
                "sample_count" => order.read(raw, &mut into.samples, u32::from_le_bytes),
                "pulse_count" => order.read(raw, &mut into.pulses, u32::from_le_bytes),
                _ => order.read(raw, &mut into.max, f32::from_le_bytes),
            }
        }
        Ok(true)
    }

    /// A second handle on the same store for a writer thread: it writes tiles with
    /// [`write_tile`](Self::write_tile) exactly as this one would; this one learns of each commit
    /// through [`note_committed`](Self::note_committed). Its own records are not consulted.
    pub fn tile_writer(&self) -> ZarrStore {
        ZarrStore::at(&self.root, self.grid.clone(), self.info.clone())
    }

    /// Records a tile committed by a [`tile_writer`](Self::tile_writer) handle.
    pub fn note_committed(&mut self, tile: [i64; 2], watermark: u64) {
        self.records.insert(tile, watermark);
        self.tiles_written += 1;
        self.bytes_written += self.grid.tile_voxels() as u64 * 20;
    }

    /// Writes a tile with its watermark (see the module documentation for the protocol).
    pub fn write_tile(
        &mut self,
        tile: [i64; 2],
        data: &TileData,
        watermark: u64,
    ) -> Result<(), StoreError> {
        for a in ARRAYS {
            self.raw.clear();
            let order = DiskOrder::of(&self.grid);
            match a {
                "intensity_sum" => order.write(&data.sum_q, &mut self.raw, i64::to_le_bytes),
                "sample_count" => order.write(&data.samples, &mut self.raw, u32::to_le_bytes),
                "pulse_count" => order.write(&data.pulses, &mut self.raw, u32::to_le_bytes),
                _ => order.write(&data.max, &mut self.raw, f32::to_le_bytes),
            }
            self.bytes_written += self.raw.len() as u64;
            self.packed.clear();
            let mut enc = GzEncoder::new(std::mem::take(&mut self.packed), Compression::new(1));
            let path = self.pending_path(a, tile);
            enc.write_all(&self.raw).map_err(io(&path))?;
            self.packed = enc.finish().map_err(io(&path))?;
            let dir = path.parent().unwrap_or(&self.root).to_path_buf();
            fs::create_dir_all(&dir).map_err(io(&dir))?;
            write_file_synced(&path, &self.packed)?;
        }
        let state = self.state_dir();
        fs::create_dir_all(&state).map_err(io(&state))?;
        let record = self.record_path(tile);
        write_atomic(
            &record,
            json!({"watermark": watermark, "pending": true})
                .to_string()
                .as_bytes(),
        )?;
        for a in ARRAYS {
            let (p, c) = (self.pending_path(a, tile), self.chunk_path(a, tile));
            fs::rename(&p, &c).map_err(io(&c))?;
        }
        write_atomic(
            &record,
            json!({"watermark": watermark, "pending": false})
                .to_string()
                .as_bytes(),
        )?;
        sync_dir(&state);
        self.records.insert(tile, watermark);
        self.tiles_written += 1;
        Ok(())
    }

    /// Rewrites the metadata documents (group, arrays, coordinates).
    fn write_metadata(&self) -> Result<(), StoreError> {
        let g = &self.grid;
        fs::create_dir_all(&self.root).map_err(io(&self.root))?;
        let shape = g.shape();
        let t = g.tile_columns as u64;
        let extent = g.extent_origin();
        let tm = g.tile_m();
        let group = json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {
                "Conventions": "CF-1.10",
                "title": "fwlidar voxel tiles: calibrated full-waveform intensity per voxel",
                "crs_wkt": self.info.crs_wkt,
                "epsg": self.info.epsg,
                "origin_m": [extent[0], extent[1], g.z_bottom_m],
                "tile_grid_origin_m": g.origin_m,
                "voxel_size_m": g.voxel_size_m,
                "tile_size_m": tm,
                "tile_columns": g.tile_columns,
                "height": g.height.name(),
                "intensity_units": self.info.intensity_units,
                "intensity_quantum": g.intensity_quantum,
                "configuration": self.info.configuration,
                "fwlidar": {
                    "version": env!("CARGO_PKG_VERSION"),
                    "grid": g,
                    "run_key": self.info.run_key,
                },
            },
        });
        write_atomic(&self.root.join("zarr.json"), group.to_string().as_bytes())?;
        // The resume records live in a group of their own so that Zarr readers see a node.
        let state = self.root.join("fwlidar_state");
        fs::create_dir_all(&state).map_err(io(&state))?;
        write_atomic(
            &state.join("zarr.json"),
            json!({
                "zarr_format": 3,
                "node_type": "group",
                "attributes": {"description": "fwlidar resume records: tiles/TX_TY holds the watermark of each tile (first pulse sequence number not in it)"},
            })
            .to_string()
            .as_bytes(),
        )?;
        let (height_name, height_long) = match g.height {
            super::grid::HeightMode::Absolute => ("height", "height of the voxel centre (CRS z)"),
            super::grid::HeightMode::AboveDem => (
                "height_above_ground",
                "height of the voxel centre above the DEM",
            ),
        };
        let units = &self.info.intensity_units;
        for a in ARRAYS {
            let (dt, fill) = dtype(a);
            let mut attrs = json!({
                "grid_mapping": "spatial_ref",
                "coordinates": "spatial_ref",
            });
            let m = attrs.as_object_mut().expect("object");
            match a {
                "intensity_sum" => {
                    m.insert("long_name".into(), json!("sum of deposited intensity"));
                    m.insert("units".into(), json!(units));
                    m.insert("scale_factor".into(), json!(g.intensity_quantum));
                }
                "sample_count" => {
                    m.insert("long_name".into(), json!("waveform bins deposited"));
                    m.insert("units".into(), json!("1"));
                }
                "intensity_max" => {
                    m.insert("long_name".into(), json!("largest deposited intensity"));
                    m.insert("units".into(), json!(units));
                }
                _ => {
                    m.insert(
                        "long_name".into(),
                        json!("pulses whose beam passed through the voxel"),
                    );
                    m.insert("units".into(), json!("1"));
                }
            }
            self.write_array_meta(
                a,
                json!(shape),
                dt,
                fill,
                json!([shape[0], t, t]),
                json!(["z", "y", "x"]),
                attrs,
            )?;
        }
        // Coordinates: voxel centres.
        let e = g.extent_origin();
        let xs: Vec<f64> = (0..shape[2])
            .map(|i| e[0] + (i as f64 + 0.5) * g.voxel_size_m[0])
            .collect();
        let ys: Vec<f64> = (0..shape[1])
            .map(|j| e[1] + (j as f64 + 0.5) * g.voxel_size_m[1])
            .collect();
        let zs: Vec<f64> = (0..shape[0])
            .map(|k| g.z_bottom_m + (k as f64 + 0.5) * g.voxel_size_m[2])
            .collect();
        for (name, vals, attrs) in [
            (
                "x",
                xs,
                json!({"standard_name": "projection_x_coordinate", "long_name": "easting of the voxel centre", "units": "m", "axis": "X"}),
            ),
            (
                "y",
                ys,
                json!({"standard_name": "projection_y_coordinate", "long_name": "northing of the voxel centre", "units": "m", "axis": "Y"}),
            ),
            (
                "z",
                zs,
                json!({"standard_name": height_name, "long_name": height_long, "units": "m", "axis": "Z", "positive": "up"}),
            ),
        ] {
            self.write_array_meta(
                name,
                json!([vals.len()]),
                "float64",
                json!("NaN"),
                json!([vals.len().max(1)]),
                json!([name]),
                attrs,
            )?;
            let mut raw = Vec::with_capacity(vals.len() * 8);
            for v in &vals {
                raw.extend_from_slice(&v.to_le_bytes());
            }
            let mut enc = GzEncoder::new(Vec::new(), Compression::new(1));
            let path = self.root.join(name).join("c").join("0");
            enc.write_all(&raw).map_err(io(&path))?;
            let packed = enc.finish().map_err(io(&path))?;
            fs::create_dir_all(path.parent().unwrap_or(&self.root)).map_err(io(&path))?;
            write_atomic(&path, &packed)?;
        }
        // CF grid mapping: a 0-d variable carrying the CRS.
        let mut sr = json!({"long_name": "coordinate reference system"});
        if let Some(w) = &self.info.crs_wkt {
            sr["crs_wkt"] = json!(w);
            sr["spatial_ref"] = json!(w);
        }
        if let Some(code) = self.info.epsg {
            sr["epsg_code"] = json!(format!("EPSG:{code}"));
        }
        self.write_array_meta(
            "spatial_ref",
            json!([]),
            "int32",
            json!(0),
            json!([]),
            json!([]),
            sr,
        )?;
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn write_array_meta(
        &self,
        name: &str,
        shape: Value,
        data_type: &str,
        fill: Value,
        chunk: Value,
        dims: Value,
        attrs: Value,
    ) -> Result<(), StoreError> {
        let dir = self.root.join(name);
        fs::create_dir_all(&dir).map_err(io(&dir))?;
        let codecs = if data_type == "int32" && shape == json!([]) {
            json!([{"name": "bytes", "configuration": {"endian": "little"}}])
        } else {
            json!([
                {"name": "bytes", "configuration": {"endian": "little"}},
                {"name": "gzip", "configuration": {"level": 1}}
            ])
        };
        let meta = json!({
            "zarr_format": 3,
            "node_type": "array",
            "shape": shape,
            "data_type": data_type,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunk}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": fill,
            "codecs": codecs,
            "attributes": attrs,
            "dimension_names": dims,
        });
        write_atomic(&dir.join("zarr.json"), meta.to_string().as_bytes())
    }
}

/// Between the in-memory order of a tile (`(j·T + i)·L + k`, columns contiguous) and the
/// chunk's `[z, y, x]` order (`(k·T + j)·T + i`).
#[derive(Clone, Copy)]
struct DiskOrder {
    side: usize,
    levels: usize,
}

impl DiskOrder {
    fn of(grid: &Grid) -> Self {
        DiskOrder {
            side: grid.tile_columns as usize,
            levels: grid.levels as usize,
        }
    }

    /// Appends `mem` to `out` in chunk order, little endian.
    fn write<T: Copy, const N: usize>(self, mem: &[T], out: &mut Vec<u8>, enc: fn(T) -> [u8; N]) {
        let (t, l) = (self.side, self.levels);
        out.reserve(mem.len() * N);
        for k in 0..l {
            for col in 0..t * t {
                out.extend_from_slice(&enc(mem[col * l + k]));
            }
        }
    }

    /// Fills `mem` from chunk-order bytes `raw` (of the right length).
    fn read<T: Copy, const N: usize>(self, raw: &[u8], mem: &mut [T], dec: fn([u8; N]) -> T) {
        let (t, l) = (self.side, self.levels);
        for (n, b) in raw.chunks_exact(N).enumerate() {
            let (k, col) = (n / (t * t), n % (t * t));
            if let (Some(d), Ok(bytes)) = (mem.get_mut(col * l + k), b.try_into()) {
                *d = dec(bytes);
            }
        }
    }
}

fn remove_pending(dir: &Path) -> Result<u64, StoreError> {
    let mut n = 0;
    for entry in fs::read_dir(dir).map_err(io(dir))? {
        let entry = entry.map_err(io(dir))?;
        let p = entry.path();
        if entry.file_type().map_err(io(&p))?.is_dir() {
            n += remove_pending(&p)?;
        } else if p.extension().is_some_and(|e| e == "pending") {
            fs::remove_file(&p).map_err(io(&p))?;
            n += 1;
        }
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel::grid::VoxelConfig;

    fn grid() -> Grid {
        Grid::new(
            &VoxelConfig {
                extent_m: Some([0.0, 0.0, 16.0, 8.0]),
                z_range_m: [0.0, 0.6],
                tile_columns: 8,
                ..VoxelConfig::default()
            },
            [0.0, 0.0],
        )
    }

    fn info(key: &str) -> StoreInfo {
        StoreInfo {
            crs_wkt: None,
            epsg: Some(32736),
            intensity_units: "V".into(),
            run_key: key.into(),
            configuration: String::new(),
        }
    }

    fn sample(n: usize, seed: u32) -> TileData {
        let mut t = TileData::new(n);
        for i in 0..n {
            if (i as u32 ^ seed).is_multiple_of(3) {
                t.deposit(i, i as i64 * 1000 - 7, i as f32 * 0.5);
                t.pass(i);
            }
        }
        t
    }

    #[test]
    fn a_tile_written_reads_back_identically_and_survives_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let t = sample(n, 1);
        s.write_tile([1, 0], &t, 42).unwrap();
        let mut back = TileData::new(n);
        assert!(s.read_tile([1, 0], &mut back).unwrap());
        assert_eq!(back.sum_q, t.sum_q);
        assert!(!s.read_tile([0, 0], &mut back).unwrap());
        let mut s2 = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        assert_eq!(s2.watermark([1, 0]), Some(42));
        assert!(s2.read_tile([1, 0], &mut back).unwrap());
        assert_eq!(back.sum_q, t.sum_q);
        assert_eq!(back.samples, t.samples);
        assert_eq!(back.pulses, t.pulses);
        assert!(
            back.max
                .iter()
                .zip(&t.max)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        // Another run or grid: refused, nothing changed.
        let e = ZarrStore::create_or_open(&root, g.clone(), info("b"))
            .err()
            .unwrap();
        assert!(e.to_string().contains("another run"), "{e}");
        let mut g2 = g.clone();
        g2.levels += 1;
        let e = ZarrStore::create_or_open(&root, g2, info("a"))
            .err()
            .unwrap();
        assert!(e.to_string().contains("height ranges differ"), "{e}");
    }

    #[test]
    fn interrupted_commits_complete_and_uncommitted_chunks_vanish() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let old = sample(n, 1);
        s.write_tile([0, 0], &old, 10).unwrap();
        // A crash after the commit record, before the renames: the new content must win.
        let new = sample(n, 2);
        s.write_tile([1, 0], &new, 5).unwrap();
        let rec = s.record_path([1, 0]);
        for a in ARRAYS {
            fs::rename(s.chunk_path(a, [1, 0]), s.pending_path(a, [1, 0])).unwrap();
        }
        fs::write(&rec, br#"{"watermark": 20, "pending": true}"#).unwrap();
        // A crash before the commit record: pending chunks of tile (0,0) must be discarded.
        for a in ARRAYS {
            fs::write(s.pending_path(a, [0, 0]), b"garbage").unwrap();
        }
        let mut s2 = ZarrStore::open(&root).unwrap();
        assert_eq!(s2.recovered_commits, 1);
        assert_eq!(s2.discarded_pending, 4);
        assert_eq!(s2.watermark([1, 0]), Some(20));
        let mut back = TileData::new(n);
        s2.read_tile([1, 0], &mut back).unwrap();
        assert_eq!(back.sum_q, new.sum_q);
        s2.read_tile([0, 0], &mut back).unwrap();
        assert_eq!(back.sum_q, old.sum_q);
        assert_eq!(s2.watermark([0, 0]), Some(10));
    }

    #[test]
    fn a_corrupt_chunk_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g, info("a")).unwrap();
        s.write_tile([0, 0], &sample(n, 1), 1).unwrap();
        let p = s.chunk_path("sample_count", [0, 0]);
        fs::write(&p, b"not gzip").unwrap();
        let mut back = TileData::new(n);
        let e = s.read_tile([0, 0], &mut back).unwrap_err().to_string();
        assert!(
            e.contains("sample_count") && e.contains("decompress"),
            "{e}"
        );
    }
}
