//! NASA GEDI Level 1B geolocated waveforms (HDF5), read with the pure-Rust `hdf5-reader` crate.
//!
//! What is read, per beam group `BEAMxxxx` (names and meanings from the GEDI L1B product's data
//! dictionary; facts only):
//!
//! - `shot_number` (u64), `delta_time` (s since the GEDI epoch, 2018-01-01T00:00:00 UTC as GPS
//!   seconds, `ancillary/master_time_epoch`);
//! - `rx_sample_start_index` (1-based index into the flat `rxwaveform`, f32 counts, 1 ns bins)
//!   and `rx_sample_count`; `tx_sample_start_index` / `tx_sample_count` into `txwaveform`;
//! - `noise_mean_corrected`, `noise_stddev_corrected` (counts);
//! - `stale_return_flag` (1: the return is stale, not this shot's);
//! - `geolocation/{latitude,longitude,elevation}_{bin0,lastbin}` (degrees, degrees, metres
//!   above the WGS84 ellipsoid) of the first and last received sample;
//!   `geolocation/local_beam_azimuth`, `local_beam_elevation` (radians);
//!   `geolocation/bounce_time_offset_bin0` (s: the one-way light time from the instrument to
//!   bin 0; × c it is the slant range, 412.6 km on the fixture's first shot, which matches
//!   `altitude_instrument − elevation_bin0` over the cosine of the off-nadir angle);
//!   `geolocation/digital_elevation_model` (m); `geolocation/degrade` (non-zero: degraded
//!   pointing or positioning).
//!
//! The per-shot records of one beam are read whole ([`GediL1b::read_beam`]); the waveforms of
//! a range of shots are read as one hyperslab of each flat array ([`GediL1b::read_waveforms`]),
//! so a full orbit (10⁵–10⁶ shots per beam, gigabytes of samples) streams in blocks. Every
//! dataset's element type is checked and converted (integer or float of any width), so a
//! product version that widens a field still reads; anything missing, mis-shaped or pointing
//! outside its array is an error naming the file, the dataset and the shot. Nothing panics on
//! a damaged file.

use std::ops::Range;
use std::path::{Path, PathBuf};

use hdf5_reader::{Datatype, Hdf5File};

/// GEDI L1B reading failures; every message names the file, and the dataset where there is one.
#[derive(Debug, thiserror::Error)]
pub enum GediError {
    /// The file cannot be opened or is not HDF5.
    #[error("{file}: cannot read as HDF5: {reason}")]
    Open {
        /// The file.
        file: String,
        /// What the HDF5 reader said.
        reason: String,
    },
    /// No `BEAMxxxx` group: not a GEDI Level 1B (or 2A/2B) granule.
    #[error("{file}: not a GEDI granule: no BEAMxxxx group at the root")]
    NoBeams {
        /// The file.
        file: String,
    },
    /// A GEDI granule of another level (2A, 2B), or an HDF5 file with beams but no waveforms.
    #[error(
        "{file}: {what}: {beam}/rxwaveform is missing; fwlidar reads GEDI Level 1B \
         (GEDI01_B) granules, the geolocated waveforms"
    )]
    NotLevel1b {
        /// The file.
        file: String,
        /// What it is instead.
        what: String,
        /// The beam looked at.
        beam: String,
    },
    /// A dataset is missing, has an unusable type or shape, or cannot be decoded.
    #[error("{file}: {dataset}: {reason}")]
    Dataset {
        /// The file.
        file: String,
        /// Full path of the dataset (e.g. `BEAM0001/rx_sample_count`).
        dataset: String,
        /// What is wrong.
        reason: String,
    },
    /// One shot's record points outside its waveform array.
    #[error("{file}: {dataset}: shot {shot_number} (index {index}): {reason}")]
    Shot {
        /// The file.
        file: String,
        /// Full path of the offending dataset.
        dataset: String,
        /// The shot's `shot_number`.
        shot_number: u64,
        /// Its index in the beam.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

/// One shot's record (everything but its samples).
#[derive(Clone, Debug, PartialEq)]
pub struct GediShot {
    /// `shot_number`: orbit, beam, minor frame and shot index packed by the mission.
    pub shot_number: u64,
    /// `delta_time`, s since the GEDI epoch (GPS time 2018-01-01T00:00:00).
    pub delta_time_s: f64,
    /// First received sample in the beam's flat `rxwaveform`, 0-based.
    pub rx_start: u64,
    /// Received samples (1 ns each).
    pub rx_count: u32,
    /// First transmitted sample in the beam's flat `txwaveform`, 0-based.
    pub tx_start: u64,
    /// Transmitted samples.
    pub tx_count: u32,
    /// `noise_mean_corrected`, counts.
    pub noise_mean: f64,
    /// `noise_stddev_corrected`, counts.
    pub noise_stddev: f64,
    /// `stale_return_flag` set: the received waveform is not this shot's.
    pub stale: bool,
    /// First received sample: longitude (°), latitude (°), elevation (m, WGS84 ellipsoid).
    pub bin0: [f64; 3],
    /// Last received sample: longitude (°), latitude (°), elevation (m, WGS84 ellipsoid).
    pub lastbin: [f64; 3],
    /// `local_beam_azimuth`, radians (east of north).
    pub beam_azimuth_rad: f64,
    /// `local_beam_elevation`, radians (above the local horizon; π/2 = nadir-pointing beam).
    pub beam_elevation_rad: f64,
    /// `digital_elevation_model` at the shot, m (NaN or a fill value where absent).
    pub dem_m: f64,
    /// `bounce_time_offset_bin0`, s: one-way light time from the instrument to bin 0 (≈ 1.38 ms
    /// from the ISS).
    pub bounce_time_bin0_s: f64,
    /// `degrade` flag non-zero: pointing or positioning degraded.
    pub degraded: bool,
}

/// The records of one beam.
#[derive(Clone, Debug, PartialEq)]
pub struct GediBeam {
    /// Group name, e.g. `BEAM0101`.
    pub name: String,
    /// Every shot, in file order.
    pub shots: Vec<GediShot>,
}

/// An open GEDI L1B granule.
pub struct GediL1b {
    path: PathBuf,
    file: Hdf5File,
    beams: Vec<String>,
}

/// The HDF5 signature (first 8 bytes of a file whose superblock is at offset 0).
pub const HDF5_SIGNATURE: [u8; 8] = *b"\x89HDF\r\n\x1a\n";

impl GediL1b {
    /// Opens `path` and lists its beam groups (sorted by name).
    pub fn open(path: &Path) -> Result<Self, GediError> {
        let file_name = path.display().to_string();
        let file = Hdf5File::open(path).map_err(|e| GediError::Open {
            file: file_name.clone(),
            reason: e.to_string(),
        })?;
        Self::from_file(file, path.to_path_buf())
    }

    /// Opens a granule held in memory (`name` stands for the file in messages; fuzzing).
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Self, GediError> {
        let file = Hdf5File::from_bytes(bytes).map_err(|e| GediError::Open {
            file: name.to_string(),
            reason: e.to_string(),
        })?;
        Self::from_file(file, PathBuf::from(name))
    }

    fn from_file(file: Hdf5File, path: PathBuf) -> Result<Self, GediError> {
        let name = path.display().to_string();
        let root = file.root_group().map_err(|e| GediError::Open {
            file: name.clone(),
            reason: e.to_string(),
        })?;
        let groups = root.groups().map_err(|e| GediError::Open {
            file: name.clone(),
            reason: e.to_string(),
        })?;
        let mut beams: Vec<String> = groups
            .iter()
            .map(|g| g.name().to_string())
            .filter(|n| n.starts_with("BEAM"))
            .collect();
        beams.sort();
        if beams.is_empty() {
            return Err(GediError::NoBeams { file: name });
        }
        Ok(GediL1b { path, file, beams })
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Beam group names, sorted.
    pub fn beams(&self) -> &[String] {
        &self.beams
    }

    /// The GEDI epoch of `delta_time` as GPS seconds (`BEAMxxxx/ancillary/master_time_epoch`
    /// of the first beam).
    pub fn time_epoch_gps_s(&self) -> Result<f64, GediError> {
        let beam = &self.beams[0];
        let v = self.f64s(&format!("{beam}/ancillary/master_time_epoch"))?;
        v.first().copied().ok_or_else(|| GediError::Dataset {
            file: self.name(),
            dataset: format!("{beam}/ancillary/master_time_epoch"),
            reason: "empty".into(),
        })
    }

    /// Shots in `beam` (the length of its `shot_number`), without reading them.
    pub fn shot_count(&self, beam: &str) -> Result<u64, GediError> {
        self.len_of(&format!("{beam}/shot_number"))
    }

    /// Checks that the granule is a Level 1B one (its first beam has `rxwaveform`). A Level 2A
    /// or 2B granule of the same shots (which has beams too, but no waveforms) is named as such.
    pub fn check_level1b(&self) -> Result<(), GediError> {
        let beam = &self.beams[0];
        let has = |d: &str| self.file.dataset(&format!("{beam}/{d}")).is_ok();
        if has("rxwaveform") && has("txwaveform") {
            return Ok(());
        }
        let product = if has("rh") || has("elev_lowestmode") {
            "a GEDI Level 2A granule (elevations and relative heights, no waveforms)"
        } else if has("pai") || has("cover") {
            "a GEDI Level 2B granule (cover and plant area index, no waveforms)"
        } else {
            "not a GEDI Level 1B granule"
        };
        Err(GediError::NotLevel1b {
            file: self.name(),
            what: product.to_string(),
            beam: beam.clone(),
        })
    }

    /// Reads every shot record of `beam` and checks that each points inside its beam's
    /// waveform arrays.
    pub fn read_beam(&self, beam: &str) -> Result<GediBeam, GediError> {
        let path = |d: &str| format!("{beam}/{d}");
        let shot_number = self.u64s(&path("shot_number"))?;
        let n = shot_number.len();
        let f = |d: &str| -> Result<Vec<f64>, GediError> {
            let p = path(d);
            let v = self.f64s(&p)?;
            if v.len() != n {
                return Err(self.dataset_error(
                    &p,
                    format!("{} values for {n} shots (shot_number)", v.len()),
                ));
            }
            Ok(v)
        };
        let u = |d: &str| -> Result<Vec<u64>, GediError> {
            let p = path(d);
            let v = self.u64s(&p)?;
            if v.len() != n {
                return Err(self.dataset_error(
                    &p,
                    format!("{} values for {n} shots (shot_number)", v.len()),
                ));
            }
            Ok(v)
        };
        let delta_time = f("delta_time")?;
        let rx_start = u("rx_sample_start_index")?;
        let rx_count = u("rx_sample_count")?;
        let tx_start = u("tx_sample_start_index")?;
        let tx_count = u("tx_sample_count")?;
        let noise_mean = f("noise_mean_corrected")?;
        let noise_stddev = f("noise_stddev_corrected")?;
        let stale = u("stale_return_flag")?;
        let geo = |d: &str| f(&format!("geolocation/{d}"));
        let (lat0, lon0, el0) = (
            geo("latitude_bin0")?,
            geo("longitude_bin0")?,
            geo("elevation_bin0")?,
        );
        let (lat1, lon1, el1) = (
            geo("latitude_lastbin")?,
            geo("longitude_lastbin")?,
            geo("elevation_lastbin")?,
        );
        let azimuth = geo("local_beam_azimuth")?;
        let elevation = geo("local_beam_elevation")?;
        let dem = geo("digital_elevation_model")?;
        let bounce = geo("bounce_time_offset_bin0")?;
        let degrade = geo("degrade")?;
        let rx_len = self.len_of(&path("rxwaveform"))?;
        let tx_len = self.len_of(&path("txwaveform"))?;

        let mut shots = Vec::with_capacity(n);
        for i in 0..n {
            let check = |dataset: &str, start: u64, count: u64, len: u64| {
                let reason = if start == 0 {
                    Some("start index 0 (the index is 1-based)".to_string())
                } else if count > u64::from(u32::MAX) {
                    Some(format!("{count} samples"))
                } else if start - 1 + count > len {
                    Some(format!(
                        "samples {start}..{} (1-based) outside the {len} of the waveform array",
                        start - 1 + count
                    ))
                } else {
                    None
                };
                match reason {
                    Some(reason) => Err(GediError::Shot {
                        file: self.name(),
                        dataset: path(dataset),
                        shot_number: shot_number[i],
                        index: i,
                        reason,
                    }),
                    None => Ok(()),
                }
            };
            check("rx_sample_start_index", rx_start[i], rx_count[i], rx_len)?;
            check("tx_sample_start_index", tx_start[i], tx_count[i], tx_len)?;
            shots.push(GediShot {
                shot_number: shot_number[i],
                delta_time_s: delta_time[i],
                rx_start: rx_start[i] - 1,
                rx_count: rx_count[i] as u32,
                tx_start: tx_start[i] - 1,
                tx_count: tx_count[i] as u32,
                noise_mean: noise_mean[i],
                noise_stddev: noise_stddev[i],
                stale: stale[i] != 0,
                bin0: [lon0[i], lat0[i], el0[i]],
                lastbin: [lon1[i], lat1[i], el1[i]],
                beam_azimuth_rad: azimuth[i],
                beam_elevation_rad: elevation[i],
                dem_m: dem[i],
                bounce_time_bin0_s: bounce[i],
                degraded: degrade[i] != 0.0,
            });
        }
        Ok(GediBeam {
            name: beam.to_string(),
            shots,
        })
    }

    /// Reads the received and transmitted samples of `beam.shots[shots]` (counts) into `rx`
    /// and `tx` (cleared first), each shot's samples at `shot.rx_start − first.rx_start`
    /// (resp. tx): one hyperslab per array, from the block's first start to its last end.
    pub fn read_waveforms(
        &self,
        beam: &GediBeam,
        shots: Range<usize>,
        rx: &mut Vec<f32>,
        tx: &mut Vec<f32>,
    ) -> Result<(), GediError> {
        rx.clear();
        tx.clear();
        let Some(block) = beam.shots.get(shots) else {
            return Err(self.dataset_error(
                &format!("{}/shot_number", beam.name),
                "shot range outside the beam".into(),
            ));
        };
        if block.is_empty() {
            return Ok(());
        }
        let span = |start: fn(&GediShot) -> u64, count: fn(&GediShot) -> u32| {
            let lo = block.iter().map(start).min().unwrap_or(0);
            let hi = block
                .iter()
                .map(|s| start(s) + u64::from(count(s)))
                .max()
                .unwrap_or(0);
            lo..hi
        };
        let rx_span = span(|s| s.rx_start, |s| s.rx_count);
        let tx_span = span(|s| s.tx_start, |s| s.tx_count);
        self.read_f32_range(&format!("{}/rxwaveform", beam.name), rx_span, rx)?;
        self.read_f32_range(&format!("{}/txwaveform", beam.name), tx_span, tx)?;
        Ok(())
    }

    fn name(&self) -> String {
        self.path.display().to_string()
    }

    fn dataset_error(&self, dataset: &str, reason: String) -> GediError {
        GediError::Dataset {
            file: self.name(),
            dataset: dataset.to_string(),
            reason,
        }
    }

    fn dataset(&self, path: &str) -> Result<hdf5_reader::Dataset, GediError> {
        self.file
            .dataset(path)
            .map_err(|e| self.dataset_error(path, format!("missing or unreadable: {e}")))
    }

    /// Elements of a one-dimensional dataset.
    fn len_of(&self, path: &str) -> Result<u64, GediError> {
        let d = self.dataset(path)?;
        match d.shape() {
            [n] => Ok(*n),
            other => Err(self.dataset_error(path, format!("shape {other:?}, expected 1-D"))),
        }
    }

    fn read_f32_range(
        &self,
        path: &str,
        range: Range<u64>,
        out: &mut Vec<f32>,
    ) -> Result<(), GediError> {
        let d = self.dataset(path)?;
        if !matches!(d.dtype(), Datatype::FloatingPoint { size: 4, .. }) {
            return Err(self.dataset_error(path, format!("type {:?}, expected f32", d.dtype())));
        }
        let sel = hdf5_reader::SliceInfo {
            selections: vec![hdf5_reader::SliceInfoElem::Slice {
                start: range.start,
                end: range.end,
                step: 1,
            }],
        };
        let a = d
            .read_slice::<f32>(&sel)
            .map_err(|e| self.dataset_error(path, format!("cannot decode: {e}")))?;
        out.extend(a.iter().copied());
        Ok(())
    }

    /// A 1-D numeric dataset (any integer or float width) as f64.
    fn f64s(&self, path: &str) -> Result<Vec<f64>, GediError> {
        let d = self.dataset(path)?;
        let bad =
            |e: hdf5_reader::error::Error| self.dataset_error(path, format!("cannot decode: {e}"));
        let v: Vec<f64> = match d.dtype() {
            Datatype::FloatingPoint { size: 8, .. } => read::<f64>(&d).map_err(bad)?,
            Datatype::FloatingPoint { size: 4, .. } => {
                widen(read::<f32>(&d).map_err(bad)?, f64::from)
            }
            Datatype::FixedPoint { size, signed, .. } => {
                self.ints(&d, path, *size, *signed)?.into_iter().collect()
            }
            other => {
                return Err(self.dataset_error(path, format!("type {other:?}, expected numbers")));
            }
        };
        Ok(v)
    }

    /// A 1-D non-negative integer dataset as u64 (exact).
    fn u64s(&self, path: &str) -> Result<Vec<u64>, GediError> {
        let d = self.dataset(path)?;
        let bad =
            |e: hdf5_reader::error::Error| self.dataset_error(path, format!("cannot decode: {e}"));
        match d.dtype() {
            Datatype::FixedPoint {
                size: 8,
                signed: false,
                ..
            } => read::<u64>(&d).map_err(bad),
            Datatype::FixedPoint { size, signed, .. } => {
                let (size, signed) = (*size, *signed);
                let v = self.ints(&d, path, size, signed)?;
                v.into_iter()
                    .map(|x| {
                        if x >= 0.0 {
                            Ok(x as u64)
                        } else {
                            Err(self.dataset_error(path, format!("negative value {x}")))
                        }
                    })
                    .collect()
            }
            other => Err(self.dataset_error(path, format!("type {other:?}, expected integers"))),
        }
    }

    /// Integers of any width up to 32 bits (and signed 64) as f64, exactly.
    fn ints(
        &self,
        d: &hdf5_reader::Dataset,
        path: &str,
        size: u8,
        signed: bool,
    ) -> Result<Vec<f64>, GediError> {
        let bad =
            |e: hdf5_reader::error::Error| self.dataset_error(path, format!("cannot decode: {e}"));
        Ok(match (size, signed) {
            (1, false) => widen(read::<u8>(d).map_err(bad)?, f64::from),
            (1, true) => widen(read::<i8>(d).map_err(bad)?, f64::from),
            (2, false) => widen(read::<u16>(d).map_err(bad)?, f64::from),
            (2, true) => widen(read::<i16>(d).map_err(bad)?, f64::from),
            (4, false) => widen(read::<u32>(d).map_err(bad)?, f64::from),
            (4, true) => widen(read::<i32>(d).map_err(bad)?, f64::from),
            (8, true) => widen(read::<i64>(d).map_err(bad)?, |x| x as f64),
            (8, false) => widen(read::<u64>(d).map_err(bad)?, |x| x as f64),
            _ => {
                return Err(self.dataset_error(path, format!("{size}-byte integers")));
            }
        })
    }
}

fn read<T: hdf5_reader::H5Type + Copy>(
    d: &hdf5_reader::Dataset,
) -> Result<Vec<T>, hdf5_reader::error::Error> {
    Ok(d.read_array::<T>()?.iter().copied().collect())
}

fn widen<T: Copy>(v: Vec<T>, f: impl Fn(T) -> f64) -> Vec<f64> {
    v.into_iter().map(f).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> PathBuf {
        crate::fixtures::path("waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5")
    }

    #[test]
    fn the_fixture_reads_with_every_shot_inside_its_arrays() {
        let g = GediL1b::open(&fixture()).unwrap();
        assert_eq!(g.beams(), ["BEAM0001", "BEAM1011"]);
        let epoch = g.time_epoch_gps_s().unwrap();
        assert!((1.19e9..1.2e9).contains(&epoch), "{epoch}");
        for name in g.beams() {
            let beam = g.read_beam(name).unwrap();
            assert_eq!(beam.shots.len(), 16, "{name}");
            let (mut rx, mut tx) = (Vec::new(), Vec::new());
            g.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx)
                .unwrap();
            let total: u64 = beam.shots.iter().map(|s| u64::from(s.rx_count)).sum();
            assert_eq!(rx.len() as u64, total, "{name}: contiguous rx");
            for s in &beam.shots {
                assert_eq!(s.tx_count, 128);
                // Cerrado savanna, Brazil; bins ~1000 samples long, 0.15 m apart in range.
                assert!((-14.0..-13.0).contains(&s.bin0[1]), "{}", s.bin0[1]);
                assert!((-45.0..-43.0).contains(&s.bin0[0]), "{}", s.bin0[0]);
                let drop = s.bin0[2] - s.lastbin[2];
                let per_bin = drop / f64::from(s.rx_count - 1);
                assert!((0.14..0.16).contains(&per_bin), "{per_bin} m/bin");
                assert!(s.noise_stddev > 0.0 && s.noise_mean > 100.0);
            }
            // A block in the middle reads the same samples as the whole beam.
            let (mut rx2, mut tx2) = (Vec::new(), Vec::new());
            g.read_waveforms(&beam, 5..7, &mut rx2, &mut tx2).unwrap();
            let off = (beam.shots[5].rx_start - beam.shots[0].rx_start) as usize;
            assert_eq!(rx2[..], rx[off..off + rx2.len()]);
            assert_eq!(tx2.len(), 256);
        }
        let beam = g.read_beam("BEAM0001").unwrap();
        assert_eq!(beam.shots[0].shot_number, 19640119100108615);
        assert_eq!(beam.shots[1].rx_start, 760);
    }

    #[test]
    fn bad_input_names_the_file_and_the_dataset() {
        let e = GediL1b::from_bytes(b"not hdf5 at all", "x.h5")
            .err()
            .unwrap();
        assert!(
            e.to_string().starts_with("x.h5: cannot read as HDF5"),
            "{e}"
        );
        let g = GediL1b::open(&fixture()).unwrap();
        let e = g.read_beam("BEAM9999").unwrap_err().to_string();
        assert!(e.contains("BEAM9999/shot_number"), "{e}");
        let beam = g.read_beam("BEAM0001").unwrap();
        let (mut rx, mut tx) = (Vec::new(), Vec::new());
        let e = g
            .read_waveforms(&beam, 10..40, &mut rx, &mut tx)
            .unwrap_err();
        assert!(e.to_string().contains("shot range outside the beam"), "{e}");
        // A level 2 product has beams but no waveforms.
        let l2 = crate::fixtures::path("waveform/gedi/GEDI02_A_O01964_beams0001_1011.h5");
        let g2 = GediL1b::open(&l2).unwrap();
        let e = g2.read_beam("BEAM0001").unwrap_err().to_string();
        assert!(e.contains("GEDI02_A") && e.contains("BEAM0001/"), "{e}");
    }

    #[test]
    fn truncated_and_corrupted_files_are_errors_not_panics() {
        let bytes = std::fs::read(fixture()).unwrap();
        for cut in [8usize, 100, 1000, 5000, 50_000, 400_000, bytes.len() - 1] {
            let _ = GediL1b::from_bytes(&bytes[..cut], "cut.h5")
                .and_then(|g| g.read_beam("BEAM0001").map(|_| ()));
        }
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..40 {
            let mut b = bytes.clone();
            for _ in 0..16 {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let i = (state % b.len() as u64) as usize;
                b[i] ^= (state >> 40) as u8 | 1;
            }
            if let Ok(g) = GediL1b::from_bytes(&b, "flip.h5") {
                for name in g.beams().to_vec() {
                    if let Ok(beam) = g.read_beam(&name) {
                        let (mut rx, mut tx) = (Vec::new(), Vec::new());
                        let _ = g.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx);
                    }
                }
            }
        }
    }
}
