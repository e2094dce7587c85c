//! The points tree reconstruction starts from: the hyper point cloud a replay writes
//! (`hyper_points.las`, LAS 1.4 point format 6, `sink::hyper_points`), every sample of every
//! return segment above a floor, at its georeferenced position, with its processed signal (V) in
//! the extra dimension `signal`.
//!
//! A small reader of point format 6 (and 7, 8: the same first 30 bytes) with Extra Bytes: the
//! waveform LAS reader (`format::las_read`) reads formats 4, 5, 9 and 10 and refuses point-only
//! files, and this needs nothing else. It never panics and never allocates by a size read from
//! the file before checking it against the file's length; errors name the file and the field.

use std::path::Path;

use crate::trees::TreesError;

/// One waveform sample above the floor, at its georeferenced position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TreePoint {
    /// X, Y, Z in the file's CRS units (m in a projected CRS).
    pub xyz: [f64; 3],
    /// Processed signal of the sample, V above the baseline.
    pub signal: f32,
    /// GPS time of the pulse, s (all samples of one pulse share it).
    pub gps_time: f64,
}

/// The points of a file and its CRS.
#[derive(Clone, Debug, Default)]
pub struct PointSet {
    /// The points, in file order.
    pub points: Vec<TreePoint>,
    /// The CRS as OGC WKT, when the file declares one.
    pub crs_wkt: Option<String>,
}

fn bad(path: &Path, field: &str, why: impl std::fmt::Display) -> TreesError {
    TreesError::Points {
        path: path.display().to_string(),
        field: field.to_string(),
        why: why.to_string(),
    }
}

fn le_u16(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(b.get(at..at + 2)?.try_into().ok()?))
}
fn le_u32(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?))
}
fn le_i32(b: &[u8], at: usize) -> Option<i32> {
    Some(i32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?))
}
fn le_u64(b: &[u8], at: usize) -> Option<u64> {
    Some(u64::from_le_bytes(b.get(at..at + 8)?.try_into().ok()?))
}
fn le_f64(b: &[u8], at: usize) -> Option<f64> {
    Some(f64::from_le_bytes(b.get(at..at + 8)?.try_into().ok()?))
}

/// Bytes per value of an Extra Bytes `data_type` (1..=10); `None` for undocumented types.
fn extra_size(data_type: u8) -> Option<usize> {
    match data_type {
        1 | 2 => Some(1),
        3 | 4 => Some(2),
        5 | 6 | 9 => Some(4),
        7 | 8 | 10 => Some(8),
        _ => None,
    }
}

/// Reads `path` (a LAS 1.4 file of point format 6, 7 or 8 with an Extra Bytes dimension named
/// `signal` of type float or double, as `hyper_points.las`).
pub fn read_hyper_points(path: &Path) -> Result<PointSet, TreesError> {
    let meta = std::fs::metadata(path).map_err(|e| bad(path, "file", e))?;
    if !meta.is_file() {
        return Err(bad(path, "file", "not a regular file"));
    }
    let bytes = std::fs::read(path).map_err(|e| bad(path, "file", e))?;
    parse_hyper_points(path, &bytes)
}

/// [`read_hyper_points`] on the file's bytes (`path` names it in errors).
pub fn parse_hyper_points(path: &Path, b: &[u8]) -> Result<PointSet, TreesError> {
    let h = parse_header(path, b)?;
    let vlrs = read_vlrs(path, b, &h)?;
    let (sig_at, sig_size) = signal_layout(path, vlrs.signal, h.record_len)?;
    let available = b.len().saturating_sub(h.point_offset) / h.record_len;
    if (available as u64) < h.count {
        return Err(bad(
            path,
            "number of point records",
            format!(
                "{} points declared, the file holds {available} (cut off? `fwlidar repair` rebuilds the header)",
                h.count
            ),
        ));
    }
    Ok(PointSet {
        points: read_points(b, &h, sig_at, sig_size),
        crs_wkt: vlrs.wkt,
    })
}

/// What the reader needs of a LAS 1.4 header.
struct Header {
    /// Bytes of the header: where the VLRs start.
    header_size: usize,
    /// Where the point records start, bytes.
    point_offset: usize,
    /// Number of VLRs.
    n_vlrs: u32,
    /// Bytes of the format's standard fields (where the extra bytes start).
    base: usize,
    /// Bytes per point record.
    record_len: usize,
    /// Scale factors of X, Y, Z (finite, > 0).
    scale: [f64; 3],
    /// Offsets of X, Y, Z (finite).
    offset: [f64; 3],
    /// Number of point records declared.
    count: u64,
}

/// The file ends inside the header, at `field`.
fn short(path: &Path, field: &str) -> TreesError {
    bad(path, field, "the file ends inside the header")
}

/// The header of LAS file `b`: signature, version 1.4, point format 6, 7 or 8 with records
/// long enough for it, finite scale factors (> 0) and offsets.
fn parse_header(path: &Path, b: &[u8]) -> Result<Header, TreesError> {
    if b.get(0..4) != Some(b"LASF".as_slice()) {
        return Err(bad(path, "file signature", "not a LAS file (no \"LASF\")"));
    }
    let short = |field: &str| short(path, field);
    let (major, minor) = (b.get(24).copied(), b.get(25).copied());
    if major != Some(1) || minor.is_none_or(|m| m < 4) {
        return Err(bad(
            path,
            "version",
            format!(
                "LAS {}.{}; the hyper point cloud is LAS 1.4",
                major.unwrap_or(0),
                minor.unwrap_or(0)
            ),
        ));
    }
    let header_size = le_u16(b, 94).ok_or_else(|| short("header size"))? as usize;
    let point_offset = le_u32(b, 96).ok_or_else(|| short("offset to point data"))? as usize;
    let n_vlrs = le_u32(b, 100).ok_or_else(|| short("number of VLRs"))?;
    let format = b.get(104).copied().ok_or_else(|| short("point format"))? & 0x3f;
    let record_len = le_u16(b, 105).ok_or_else(|| short("point record length"))? as usize;
    let scale = [131, 139, 147].map(|o| le_f64(b, o));
    let offset = [155, 163, 171].map(|o| le_f64(b, o));
    let count = le_u64(b, 247).ok_or_else(|| short("number of point records"))?;
    if !(6..=8).contains(&format) {
        return Err(bad(
            path,
            "point format",
            format!("point format {format}; a hyper point cloud is format 6 (7 and 8 read too)"),
        ));
    }
    let base = match format {
        6 => 30,
        7 => 36,
        _ => 38,
    };
    if record_len < base {
        return Err(bad(
            path,
            "point record length",
            format!("{record_len} bytes, less than format {format}'s {base}"),
        ));
    }
    let (Some(sx), Some(sy), Some(sz)) = (scale[0], scale[1], scale[2]) else {
        return Err(short("scale factors"));
    };
    let (Some(ox), Some(oy), Some(oz)) = (offset[0], offset[1], offset[2]) else {
        return Err(short("offsets"));
    };
    if ![sx, sy, sz].iter().all(|s| s.is_finite() && *s > 0.0)
        || ![ox, oy, oz].iter().all(|o| o.is_finite())
    {
        return Err(bad(path, "scale factors", "not finite and positive"));
    }
    Ok(Header {
        header_size,
        point_offset,
        n_vlrs,
        base,
        record_len,
        scale: [sx, sy, sz],
        offset: [ox, oy, oz],
        count,
    })
}

/// What the VLRs hold for the reader.
struct Vlrs {
    /// The CRS as OGC WKT (LASF_Projection / 2112).
    wkt: Option<String>,
    /// The `signal` extra dimension: its byte in a record and its data type.
    signal: Option<(usize, u8)>,
}

/// Reads the header's VLRs: the CRS (LASF_Projection / 2112) and the Extra Bytes
/// (LASF_Spec / 4).
fn read_vlrs(path: &Path, b: &[u8], h: &Header) -> Result<Vlrs, TreesError> {
    let mut at = h.header_size;
    let mut vlrs = Vlrs {
        wkt: None,
        signal: None,
    };
    for i in 0..h.n_vlrs {
        let field = format!("VLR {i}");
        let head = b.get(at..at + 54).ok_or_else(|| short(path, &field))?;
        let user = String::from_utf8_lossy(&head[2..18])
            .trim_end_matches('\0')
            .to_string();
        let id = u16::from_le_bytes([head[18], head[19]]);
        let len = u16::from_le_bytes([head[20], head[21]]) as usize;
        let data = b
            .get(at + 54..at + 54 + len)
            .ok_or_else(|| bad(path, &field, "its data run past the end of the file"))?;
        if user == "LASF_Projection" && id == 2112 {
            vlrs.wkt = Some(
                String::from_utf8_lossy(data)
                    .trim_end_matches('\0')
                    .to_string(),
            );
        } else if user == "LASF_Spec" && id == 4 {
            extra_bytes(path, data, h.base, &mut vlrs.signal)?;
        }
        at += 54 + len;
    }
    Ok(vlrs)
}

/// Walks the Extra Bytes descriptors in `data` (192 bytes each; the extra bytes start at byte
/// `base` of a record): `signal` gets the byte and data type of a dimension named `signal`.
fn extra_bytes(
    path: &Path,
    data: &[u8],
    base: usize,
    signal: &mut Option<(usize, u8)>,
) -> Result<(), TreesError> {
    let mut pos = 0usize;
    for d in data.chunks_exact(192) {
        let ty = d[2];
        let name = String::from_utf8_lossy(&d[4..36])
            .trim_end_matches('\0')
            .to_string();
        let size = if ty == 0 {
            d[3] as usize // undocumented extra bytes: options hold the count
        } else {
            extra_size(ty).ok_or_else(|| {
                bad(
                    path,
                    "extra bytes",
                    format!("dimension {name:?} has data type {ty}"),
                )
            })?
        };
        if name == "signal" {
            *signal = Some((base + pos, ty));
        }
        pos += size;
    }
    Ok(())
}

/// Where `signal` is in a record of `record_len` bytes and its size (4: float, 8: double);
/// refused when absent, of another type or past the record's end.
fn signal_layout(
    path: &Path,
    signal: Option<(usize, u8)>,
    record_len: usize,
) -> Result<(usize, usize), TreesError> {
    let Some((sig_at, sig_ty)) = signal else {
        return Err(bad(
            path,
            "extra bytes",
            "no dimension named \"signal\" (write it with `output.hyper_points = true`)",
        ));
    };
    let sig_size = if sig_ty == 9 {
        4
    } else if sig_ty == 10 {
        8
    } else {
        return Err(bad(
            path,
            "extra bytes",
            format!("\"signal\" has data type {sig_ty}, not float (9) or double (10)"),
        ));
    };
    if sig_at + sig_size > record_len {
        return Err(bad(
            path,
            "point record length",
            format!("{record_len} bytes cannot hold \"signal\" at byte {sig_at}"),
        ));
    }
    Ok((sig_at, sig_size))
}

/// The header's `count` point records of `b` (checked to be in the file), scaled and offset
/// to the CRS's units, with their signal (`sig_size` bytes at `sig_at`); records whose signal
/// is not finite are left out.
fn read_points(b: &[u8], h: &Header, sig_at: usize, sig_size: usize) -> Vec<TreePoint> {
    let (point_offset, record_len) = (h.point_offset, h.record_len);
    let ([sx, sy, sz], [ox, oy, oz]) = (h.scale, h.offset);
    let mut points = Vec::with_capacity(h.count as usize);
    for k in 0..h.count as usize {
        let r = &b[point_offset + k * record_len..point_offset + (k + 1) * record_len];
        let (Some(x), Some(y), Some(z)) = (le_i32(r, 0), le_i32(r, 4), le_i32(r, 8)) else {
            unreachable!("a record holds at least 30 bytes")
        };
        let gps_time = le_f64(r, 22).unwrap_or(f64::NAN);
        let s = if sig_size == 4 {
            f32::from_le_bytes([r[sig_at], r[sig_at + 1], r[sig_at + 2], r[sig_at + 3]])
        } else {
            le_f64(r, sig_at).unwrap_or(f64::NAN) as f32
        };
        if !s.is_finite() {
            continue;
        }
        points.push(TreePoint {
            xyz: [
                ox + sx * f64::from(x),
                oy + sy * f64::from(y),
                oz + sz * f64::from(z),
            ],
            signal: s,
            gps_time,
        });
    }
    points
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::las_points::{PointSix, write_point_cloud};
    use crate::format::las_write::ExtraDim;

    fn written(n: usize) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("h.las");
        let extra = [
            ExtraDim::f32("signal", "processed signal (V)"),
            ExtraDim::f32("backscatter", "b").with_no_data(),
        ];
        let pts = (0..n).map(|i| {
            (
                PointSix {
                    xyz: [500_000.0 + i as f64 * 0.25, 7_000_000.0, 10.0 + i as f64],
                    gps_time: 100.0 + i as f64,
                    ..Default::default()
                },
                [0.5 + i as f64, f64::NAN],
            )
        });
        write_point_cloud(&path, Some("PROJCS[\"x\"]"), &extra, pts).unwrap();
        (dir, path)
    }

    #[test]
    fn reads_what_the_point_cloud_writer_wrote() {
        let (_d, path) = written(5);
        let set = read_hyper_points(&path).unwrap();
        assert_eq!(set.points.len(), 5);
        assert_eq!(set.crs_wkt.as_deref(), Some("PROJCS[\"x\"]"));
        let p = set.points[3];
        assert!((p.xyz[0] - 500_000.75).abs() < 1e-3);
        assert!((p.xyz[2] - 13.0).abs() < 1e-3);
        assert_eq!(p.signal, 3.5);
        assert_eq!(p.gps_time, 103.0);
    }

    #[test]
    fn a_cut_file_names_the_point_count_and_never_panics() {
        let (_d, path) = written(20);
        let bytes = std::fs::read(&path).unwrap();
        let e = parse_hyper_points(&path, &bytes[..bytes.len() - 10]).unwrap_err();
        assert!(e.to_string().contains("number of point records"), "{e}");
        // Every prefix and a sweep of single-byte corruptions: an error or points, never a panic.
        for cut in 0..bytes.len() {
            let _ = parse_hyper_points(&path, &bytes[..cut]);
        }
        for i in 0..bytes.len().min(600) {
            let mut b = bytes.clone();
            b[i] ^= 0xff;
            let _ = parse_hyper_points(&path, &b);
        }
    }

    #[test]
    fn a_file_without_signal_is_refused_naming_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.las");
        write_point_cloud(&path, None, &[], [(PointSix::default(), [0.0f64; 0])]).unwrap();
        let e = read_hyper_points(&path).unwrap_err().to_string();
        assert!(e.contains("p.las") && e.contains("signal"), "{e}");
    }
}
