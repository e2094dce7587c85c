//! A complete LAS 1.4 point file of point data record format 6 with extra dimensions, written
//! atomically (`NAME.partial`, synced, renamed over `NAME`): the reusable writer for point
//! outputs other than the returns sink (e.g. each closed voxel tile's occupied voxels).
//!
//! ```no_run
//! use fwlidar::format::las_points::{PointSix, write_point_cloud};
//! use fwlidar::format::las_write::ExtraDim;
//! let extra = [ExtraDim::f32("density", "returns per voxel (count)")];
//! let pts = (0..10).map(|i| {
//!     let p = PointSix { xyz: [500_000.0 + f64::from(i), 6_650_000.0, 12.5], ..Default::default() };
//!     (p, [f64::from(i)])
//! });
//! let summary = write_point_cloud(std::path::Path::new("tile.las"), Some("PROJCS[...]"), &extra, pts)?;
//! assert_eq!(summary.points, 10);
//! # Ok::<(), fwlidar::format::las_points::LasFileError>(())
//! ```
//!
//! Coordinates are stored with scale [`SCALE`] (1 mm) and an offset taken from the first point
//! (rounded down to a multiple of 1000 CRS units); the header states the WKT CRS (global
//! encoding bit 4, required for format 6) when one is given, the Extra Bytes VLR when `extra` is
//! not empty, point count, per-return counts and bounds. Same header fields as the returns
//! output (`docs/formats.md`, "Returns as LAS 1.4 (output)").

use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

use crate::core::atomic_file::{AtomicFile, WriteError};
use crate::format::las_write::{
    self as lw, ExtraDim, HEADER_SIZE, Header, LasWriteError, PF6_SIZE, PointRecord6,
};

/// Scale of the stored X, Y, Z (CRS units per count).
pub const SCALE: f64 = 0.001;
/// The offset is the first point's position rounded down to a multiple of this.
pub const OFFSET_STEP: f64 = 1000.0;

/// One point of a format 6 file: position in CRS units and the core attributes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointSix {
    /// X, Y, Z in CRS units (stored to [`SCALE`]).
    pub xyz: [f64; 3],
    /// Intensity (16 bits, the caller's scaling).
    pub intensity: u16,
    /// Return number, 1..=15. Default 1.
    pub return_number: u8,
    /// Number of returns of the pulse, 1..=15. Default 1.
    pub number_of_returns: u8,
    /// Classification (0: never classified). Default 0.
    pub classification: u8,
    /// Scan angle, degrees (NaN: 0 is written). Default NaN.
    pub scan_angle_deg: f32,
    /// GPS time, s. Default 0.
    pub gps_time: f64,
}

impl Default for PointSix {
    fn default() -> Self {
        PointSix {
            xyz: [0.0; 3],
            intensity: 0,
            return_number: 1,
            number_of_returns: 1,
            classification: 0,
            scan_angle_deg: f32::NAN,
            gps_time: 0.0,
        }
    }
}

/// What [`write_point_cloud`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloudSummary {
    /// Point records.
    pub points: u64,
    /// Smallest X, Y, Z as stored (0 when there is no point).
    pub min: [f64; 3],
    /// Largest X, Y, Z as stored.
    pub max: [f64; 3],
    /// Points by return number 1..=15.
    pub by_return: [u64; 15],
}

/// A LAS point file that could not be written: an I/O error, or data the file cannot hold. Both
/// name the file.
#[derive(Debug, thiserror::Error)]
pub enum LasFileError {
    /// Writing failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file being written.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The data cannot be represented in the LAS file being written.
    #[error("cannot write {path}: {source}")]
    Las {
        /// The file being written.
        path: String,
        /// What cannot be represented.
        source: LasWriteError,
    },
}

impl From<WriteError> for LasFileError {
    fn from(e: WriteError) -> Self {
        LasFileError::Io {
            path: e.path,
            source: e.source,
        }
    }
}

fn las_err(path: &Path, msg: String) -> LasFileError {
    LasFileError::Las {
        path: path.display().to_string(),
        source: LasWriteError::Unrepresentable(msg),
    }
}

/// Writes `points` (each with one value per `extra` dimension, in order; NaN becomes the
/// dimension's declared no-data value when it has one) as a LAS 1.4 point format 6 file at
/// `path`, atomically: the file appears complete or not at all (an existing file survives until
/// then). `crs_wkt`: the CRS as OGC WKT (VLR `LASF_Projection` / 2112), `None` for none. GPS times
/// are declared as GPS week seconds (global encoding bit 0 clear).
///
/// Errors name the file: a folder that cannot be written, a NUL in the WKT, a bad extra
/// dimension name, a point with a non-finite position or more than 2^31 mm from the offset, or
/// with a number of extra values other than `extra.len()` (index of the point given).
pub fn write_point_cloud<I, E>(
    path: &Path,
    crs_wkt: Option<&str>,
    extra: &[ExtraDim],
    points: I,
) -> Result<PointCloudSummary, LasFileError>
where
    I: IntoIterator<Item = (PointSix, E)>,
    E: AsRef<[f64]>,
{
    let mut w = PointCloudWriter::create(path, crs_wkt, extra)?;
    let r = points
        .into_iter()
        .try_for_each(|(p, e)| w.push(&p, e.as_ref()))
        .and_then(|_| w.finish());
    if r.is_err() {
        w.abandon();
    }
    r
}

/// A LAS 1.4 point format 6 file written point by point (the streaming form of
/// [`write_point_cloud`]): `NAME.partial` until [`PointCloudWriter::finish`] renames it into
/// place. Its header and VLRs are written provisionally at creation and again (in place) when
/// the first point fixes the offset, so a file cut off by a crash is a valid LAS file with a
/// stale point count that `fwlidar repair` completes. [`PointCloudWriter::push`] does not
/// allocate.
pub struct PointCloudWriter {
    path: std::path::PathBuf,
    file: AtomicFile,
    extra: Vec<ExtraDim>,
    vlrs: Vec<u8>,
    n_vlrs: u32,
    record_len: usize,
    rec: Vec<u8>,
    offset: Option<[f64; 3]>,
    min: [i32; 3],
    max: [i32; 3],
    by_return: [u64; 15],
    n: u64,
    done: bool,
}

impl PointCloudWriter {
    /// Starts `path` (as `path.partial`) with its provisional header and VLRs.
    pub fn create(
        path: &Path,
        crs_wkt: Option<&str>,
        extra: &[ExtraDim],
    ) -> Result<Self, LasFileError> {
        let mut vlrs = Vec::new();
        let mut n_vlrs = 0u32;
        if let Some(wkt) = crs_wkt {
            vlrs.extend(lw::wkt_vlr(wkt).map_err(|e| las_err(path, e.to_string()))?);
            n_vlrs += 1;
        }
        if !extra.is_empty() {
            vlrs.extend(
                lw::extra_bytes_vlr(extra, "fwlidar point attributes")
                    .map_err(|e| las_err(path, e.to_string()))?,
            );
            n_vlrs += 1;
        }
        let record_len = PF6_SIZE + lw::extra_bytes_len(extra);
        let file = AtomicFile::create(path)?;
        let mut w = PointCloudWriter {
            path: path.to_path_buf(),
            file,
            extra: extra.to_vec(),
            vlrs,
            n_vlrs,
            record_len,
            rec: vec![0u8; record_len],
            offset: None,
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            by_return: [0; 15],
            n: 0,
            done: false,
        };
        let pre = w.preamble();
        w.file.writer()?.write_all(&pre).map_err(|e| w.io_err(e))?;
        Ok(w)
    }

    fn io_err(&self, e: std::io::Error) -> LasFileError {
        LasFileError::Io {
            path: self.path.display().to_string(),
            source: e,
        }
    }

    /// Points written so far.
    pub fn points(&self) -> u64 {
        self.n
    }

    /// The header as it stands, then the VLRs.
    fn preamble(&self) -> Vec<u8> {
        let s = self.summary();
        let (year, day) = lw::year_and_day(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
        );
        let header = Header {
            global_encoding: lw::GLOBAL_WKT,
            system_identifier: "fwlidar".into(),
            generating_software: concat!("fwlidar ", env!("CARGO_PKG_VERSION")).into(),
            creation_day_of_year: day,
            creation_year: year,
            offset_to_point_data: (HEADER_SIZE + self.vlrs.len()) as u32,
            number_of_vlrs: self.n_vlrs,
            point_format: 6,
            point_record_length: self.record_len as u16,
            scale: [SCALE; 3],
            offset: self.offset.unwrap_or([0.0; 3]),
            max: s.max,
            min: s.min,
            start_of_waveform_data: 0,
            start_of_first_evlr: 0,
            number_of_evlrs: 0,
            number_of_points: s.points,
            points_by_return: s.by_return,
        };
        let mut b = header.encode().to_vec();
        b.extend_from_slice(&self.vlrs);
        b
    }

    /// What has been written so far.
    pub fn summary(&self) -> PointCloudSummary {
        let o = self.offset.unwrap_or([0.0; 3]);
        let n = self.n;
        let bound = |v: &[i32; 3]| -> [f64; 3] {
            if n == 0 {
                [0.0; 3]
            } else {
                std::array::from_fn(|k| o[k] + f64::from(v[k]) * SCALE)
            }
        };
        PointCloudSummary {
            points: n,
            min: bound(&self.min),
            max: bound(&self.max),
            by_return: self.by_return,
        }
    }

    /// Rewrites the header and VLRs in place and goes on at the end.
    fn rewrite_preamble(&mut self) -> Result<(), LasFileError> {
        let pre = self.preamble();
        let path = self.path.clone();
        let w = self.file.writer()?;
        w.seek(SeekFrom::Start(0))
            .and_then(|_| w.write_all(&pre))
            .and_then(|_| w.seek(SeekFrom::End(0)))
            .map(|_| ())
            .map_err(|e| LasFileError::Io {
                path: path.display().to_string(),
                source: e,
            })
    }

    /// Appends one point with its extra values (one per extra dimension).
    pub fn push(&mut self, p: &PointSix, values: &[f64]) -> Result<(), LasFileError> {
        let i = self.n;
        if values.len() != self.extra.len() {
            return Err(las_err(
                &self.path,
                format!(
                    "point {i}: {} extra values for {} extra dimensions",
                    values.len(),
                    self.extra.len()
                ),
            ));
        }
        if p.xyz.iter().any(|v| !v.is_finite()) {
            return Err(las_err(
                &self.path,
                format!("point {i}: position {:?} is not finite", p.xyz),
            ));
        }
        let o = match self.offset {
            Some(o) => o,
            None => {
                let o = p.xyz.map(|v| (v / OFFSET_STEP).floor() * OFFSET_STEP);
                self.offset = Some(o);
                self.rewrite_preamble()?;
                o
            }
        };
        let scaled: [f64; 3] = std::array::from_fn(|k| ((p.xyz[k] - o[k]) / SCALE).round());
        if scaled
            .iter()
            .any(|v| *v < f64::from(i32::MIN) || *v > f64::from(i32::MAX))
        {
            return Err(las_err(
                &self.path,
                format!(
                    "point {i}: position {:?} is more than 2^31 mm from the offset {o:?}",
                    p.xyz
                ),
            ));
        }
        let xyz = scaled.map(|v| v as i32);
        let rn = p.return_number.clamp(1, 15);
        let scan = f64::from(p.scan_angle_deg) / 0.006;
        PointRecord6 {
            xyz,
            intensity: p.intensity,
            return_number: rn,
            number_of_returns: p.number_of_returns.min(15),
            scanner_channel: 0,
            classification: p.classification,
            scan_angle: if scan.is_finite() {
                scan.round().clamp(-30000.0, 30000.0) as i16
            } else {
                0
            },
            gps_time: p.gps_time,
        }
        .encode_into(&mut self.rec);
        lw::encode_extras(&self.extra, values, &mut self.rec[PF6_SIZE..]);
        let path = &self.path;
        self.file
            .writer()?
            .write_all(&self.rec)
            .map_err(|e| LasFileError::Io {
                path: path.display().to_string(),
                source: e,
            })?;
        for (k, v) in xyz.into_iter().enumerate() {
            self.min[k] = self.min[k].min(v);
            self.max[k] = self.max[k].max(v);
        }
        self.by_return[usize::from(rn) - 1] += 1;
        self.n += 1;
        Ok(())
    }

    /// Hands the buffered points to the OS (the file stays under its temporary name).
    pub fn flush(&mut self) -> Result<(), LasFileError> {
        Ok(self.file.flush()?)
    }

    /// Writes the final header, syncs and renames the file into place. Idempotent.
    pub fn finish(&mut self) -> Result<PointCloudSummary, LasFileError> {
        if !self.done {
            let pre = self.preamble();
            let w = self.file.writer()?;
            let r = w.seek(SeekFrom::Start(0)).and_then(|_| w.write_all(&pre));
            r.map_err(|e| self.io_err(e))?;
            self.file.commit()?;
            self.done = true;
        }
        Ok(self.summary())
    }

    /// Gives up: removes the temporary file (the final name keeps what it had).
    pub fn abandon(self) {
        if !self.done {
            let mut tmp = self.path.as_os_str().to_os_string();
            tmp.push(".partial");
            drop(self.file);
            let _ = std::fs::remove_file(tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_header_vlrs_points_and_extras() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.las");
        let extra = [
            ExtraDim::f32("a", "first (V)"),
            ExtraDim::f32("b", "second").with_no_data(),
        ];
        let pts = (0..3).map(|i| {
            (
                PointSix {
                    xyz: [1500.25 + f64::from(i), 2000.0, -3.0],
                    return_number: 1 + i as u8,
                    number_of_returns: 3,
                    gps_time: f64::from(i),
                    ..Default::default()
                },
                [f64::from(i), if i == 1 { f64::NAN } else { 0.5 }],
            )
        });
        let s = write_point_cloud(&path, Some("GEOGCS[\"x\"]"), &extra, pts).unwrap();
        assert_eq!(s.points, 3);
        assert_eq!(s.by_return[..3], [1, 1, 1]);
        assert_eq!(s.min, [1500.25, 2000.0, -3.0]);
        let b = std::fs::read(&path).unwrap();
        assert_eq!(b[104], 6);
        assert_eq!(u16::from_le_bytes([b[105], b[106]]), 38);
        let off = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
        assert_eq!(b.len(), off + 3 * 38);
        let rec1 = &b[off + 38..off + 76];
        assert_eq!(f32::from_le_bytes(rec1[30..34].try_into().unwrap()), 1.0);
        assert_eq!(
            f32::from_le_bytes(rec1[34..38].try_into().unwrap()),
            -9999.0
        );
        assert!(!dir.path().join("t.las.partial").exists());
        let e =
            write_point_cloud(&path, None, &extra, [(PointSix::default(), vec![1.0])]).unwrap_err();
        assert!(
            e.to_string().contains("t.las") && e.to_string().contains("point 0"),
            "{e}"
        );
        assert_eq!(
            std::fs::read(&path).unwrap(),
            b,
            "the old file survives a failure"
        );
        assert!(
            !dir.path().join("t.las.partial").exists(),
            "no temporary left"
        );
    }
}
