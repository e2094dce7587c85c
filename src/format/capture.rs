//! The native capture container, version 1.0: constants, record kinds, errors, the skip report
//! and the writer's flush policy.
//!
//! A capture is one append-only file: a 16-byte preamble, then length-prefixed, CRC-32C
//! checksummed records (a sensor-description header, digitizer frames, raw navigation bytes).
//! All integers are little-endian. The byte layout, the resync algorithm and the versioning rules
//! are specified in `docs/formats.md`, section "Capture format v1.1"; the reader is in
//! [`super::capture_reader`], the writer in [`super::capture_writer`], the frame and nav payloads in
//! [`super::frame`].

use std::io;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::frame::FrameError;

/// The first 8 bytes of every capture file: `0x89 'F' 'W' 'L' 'C' 'A' 'P' '\n'`.
pub const MAGIC: [u8; 8] = [0x89, b'F', b'W', b'L', b'C', b'A', b'P', b'\n'];
/// Length of the preamble in bytes: magic (8), major (u16), minor (u16), reserved (u32).
pub const PREAMBLE_LEN: usize = 16;
/// The major version this crate writes and the newest it reads.
pub const VERSION_MAJOR: u16 = 1;
/// The minor version this crate writes.
pub const VERSION_MINOR: u16 = 1;

/// The 4 bytes every record starts with: `0xF5 'W' 'L' 'R'`.
pub const SYNC: [u8; 4] = [0xF5, b'W', b'L', b'R'];
/// Bytes of a record before its payload: sync (4), kind (1), flags (1), reserved (2),
/// payload_len (4).
pub const RECORD_HEADER_LEN: usize = 12;
/// Bytes of the CRC-32C trailer after the payload.
pub const RECORD_CRC_LEN: usize = 4;
/// Bytes a record adds around its payload (header and CRC).
pub const RECORD_OVERHEAD: usize = RECORD_HEADER_LEN + RECORD_CRC_LEN;
/// Largest payload a record may declare, in bytes (16 MiB). A larger length is corruption.
pub const MAX_PAYLOAD_LEN: u32 = 16 * 1024 * 1024;

/// What a record holds, from its `kind` byte.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum RecordKind {
    /// UTF-8 text (TOML): the sensor description and configuration in force. First record of a
    /// file; repeated when a restarted recorder begins a new segment.
    Header = 1,
    /// One digitizer frame (one pulse); see [`super::frame`].
    DigitizerFrame = 2,
    /// Navigation bytes exactly as they came off a port, with their receive time.
    NavBytes = 3,
    /// A digitizer frame with the pulse's geometry (anchor and direction) in front: pulses
    /// imported from files that carry it (LAS, PulseWaves). Format 1.1.
    GeoFrame = 4,
}

impl RecordKind {
    /// The kind for a `kind` byte, or `None` for a kind this version does not know.
    pub fn from_u8(byte: u8) -> Option<RecordKind> {
        match byte {
            1 => Some(RecordKind::Header),
            2 => Some(RecordKind::DigitizerFrame),
            3 => Some(RecordKind::NavBytes),
            4 => Some(RecordKind::GeoFrame),
            _ => None,
        }
    }
}

/// The 16-byte preamble this crate writes (version [`VERSION_MAJOR`].[`VERSION_MINOR`]).
pub fn preamble() -> [u8; PREAMBLE_LEN] {
    let mut p = [0u8; PREAMBLE_LEN];
    p[..8].copy_from_slice(&MAGIC);
    p[8..10].copy_from_slice(&VERSION_MAJOR.to_le_bytes());
    p[10..12].copy_from_slice(&VERSION_MINOR.to_le_bytes());
    p
}

/// Checks a preamble read from `path`; `bytes` holds whatever the file starts with (at most
/// [`PREAMBLE_LEN`] bytes are looked at). Returns the file's `(major, minor)` version.
///
/// Errors: no bytes -> [`CaptureError::Empty`]; bytes that are not a prefix of the magic ->
/// [`CaptureError::NotACapture`]; a correct but incomplete preamble ->
/// [`CaptureError::TruncatedPreamble`]; major newer than [`VERSION_MAJOR`] ->
/// [`CaptureError::NewerVersion`]; major 0 -> [`CaptureError::UnsupportedVersion`].
pub fn check_preamble(bytes: &[u8], path: &std::path::Path) -> Result<(u16, u16), CaptureError> {
    let path = || path.to_path_buf();
    if bytes.is_empty() {
        return Err(CaptureError::Empty { path: path() });
    }
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        return Err(CaptureError::NotACapture { path: path() });
    }
    if bytes.len() < PREAMBLE_LEN {
        return Err(CaptureError::TruncatedPreamble {
            path: path(),
            len: bytes.len(),
        });
    }
    let major = u16::from_le_bytes([bytes[8], bytes[9]]);
    let minor = u16::from_le_bytes([bytes[10], bytes[11]]);
    if major > VERSION_MAJOR {
        return Err(CaptureError::NewerVersion {
            path: path(),
            major,
            minor,
        });
    }
    if major < VERSION_MAJOR {
        return Err(CaptureError::UnsupportedVersion {
            path: path(),
            major,
            minor,
        });
    }
    Ok((major, minor))
}

/// CRC-32C of a record: over `kind`, `flags`, `reserved`, `payload_len` (the 8 header bytes after
/// the sync marker) and the payload.
pub fn record_crc(header_after_sync: &[u8], payload: &[u8]) -> u32 {
    crc32c::crc32c_append(crc32c::crc32c(header_after_sync), payload)
}

/// Errors of the capture reader and writer.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The file has no bytes at all.
    #[error("{}: empty file, not a capture (no preamble)", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// The file does not start with the capture magic.
    #[error("{}: not an fwlidar capture (wrong magic bytes)", path.display())]
    NotACapture {
        /// The file.
        path: PathBuf,
    },
    /// The file starts with the magic but ends inside the 16-byte preamble.
    #[error("{}: capture preamble truncated after {len} of 16 bytes", path.display())]
    TruncatedPreamble {
        /// The file.
        path: PathBuf,
        /// Bytes present.
        len: usize,
    },
    /// The file was written by a newer major version of the format, which this reader refuses.
    #[error(
        "{}: capture format version {major}.{minor} is newer than this program supports \
         ({VERSION_MAJOR}.x); upgrade fwlidar to read it",
        path.display()
    )]
    NewerVersion {
        /// The file.
        path: PathBuf,
        /// Major version in the file.
        major: u16,
        /// Minor version in the file.
        minor: u16,
    },
    /// The file declares a major version older than any this program knows (0).
    #[error("{}: capture format version {major}.{minor} is not supported", path.display())]
    UnsupportedVersion {
        /// The file.
        path: PathBuf,
        /// Major version in the file.
        major: u16,
        /// Minor version in the file.
        minor: u16,
    },
    /// Reading or writing failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file (or the display name of the stream).
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
    /// `create` was asked to write a file that already exists; nothing was written.
    #[error("{}: file already exists; refusing to overwrite a capture", path.display())]
    AlreadyExists {
        /// The file.
        path: PathBuf,
    },
    /// A record's payload would exceed [`MAX_PAYLOAD_LEN`]; nothing was written.
    #[error("record payload of {len} bytes exceeds the maximum of {max} bytes")]
    RecordTooLarge {
        /// Payload length in bytes.
        len: usize,
        /// The maximum, [`MAX_PAYLOAD_LEN`].
        max: u32,
    },
    /// A pulse could not be encoded as a digitizer frame; nothing was written.
    #[error("cannot encode pulse {pulse_id}: {source}")]
    Encode {
        /// The pulse's digitizer id.
        pulse_id: u64,
        /// Why.
        #[source]
        source: FrameError,
    },
}

/// What a reader passed over instead of returning it as a record. All counts are cumulative;
/// `truncated_tail_bytes` and the last resync are only settled once the reader reached the end.
///
/// Accounting: preamble + bytes of the records returned + `bytes_skipped` +
/// `truncated_tail_bytes` = bytes read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SkipReport {
    /// Bytes passed over that were followed by a valid record: garbage, damaged records, and
    /// valid records of an unknown kind or with a bad payload.
    pub bytes_skipped: u64,
    /// Record candidates (sync marker, plausible length, complete) whose CRC did not match.
    pub bad_checksums: u64,
    /// Times the reader lost sync and found a valid record again.
    pub resyncs: u64,
    /// Bytes at the end of the input after which no valid record was found (a record cut short
    /// by a crash, or trailing damage).
    pub truncated_tail_bytes: u64,
    /// Valid records (CRC correct) of a kind this version does not know; skipped.
    pub unknown_kinds: u64,
    /// Valid records of a known kind whose payload is malformed (e.g. a frame whose declared
    /// sizes disagree with its length, a header that is not UTF-8); skipped.
    pub bad_payloads: u64,
}

impl SkipReport {
    /// True when nothing was skipped.
    pub fn is_clean(&self) -> bool {
        *self == SkipReport::default()
    }
}

/// When the capture writer syncs to disk.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FsyncPolicy {
    /// Never call fsync; the OS writes back when it likes (a power loss may lose more than a
    /// kill -9).
    Never,
    /// fsync (`File::sync_data`) after every flush. The default.
    #[default]
    OnFlush,
}

/// How often the capture writer hands buffered records to the OS (and, per `fsync`, to the disk).
/// A kill -9 loses at most the records written since the last flush.
///
/// TOML: `{ every_records = 256, every_ms = 200, fsync = "on_flush" }` (the defaults).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FlushPolicy {
    /// Flush after this many records since the last flush; 0 = not by count. Default 256.
    pub every_records: u32,
    /// Flush when a record is written at least this many milliseconds after the last flush;
    /// 0 = not by time. Default 200 ms.
    pub every_ms: u32,
    /// Whether a flush also syncs to disk. Default `on_flush`.
    pub fsync: FsyncPolicy,
}

impl Default for FlushPolicy {
    fn default() -> Self {
        FlushPolicy {
            every_records: 256,
            every_ms: 200,
            fsync: FsyncPolicy::OnFlush,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn preamble_round_trips() {
        let p = preamble();
        assert_eq!(p.len(), PREAMBLE_LEN);
        assert_eq!(check_preamble(&p, Path::new("x")).unwrap(), (1, 1));
        // Files written by 1.0 writers are read by this 1.1 reader.
        let mut old = p;
        old[10] = 0;
        assert_eq!(check_preamble(&old, Path::new("x")).unwrap(), (1, 0));
    }

    #[test]
    fn preamble_errors_name_the_path() {
        let path = Path::new("/data/flight.fwc");
        let err = check_preamble(&[], path).unwrap_err();
        assert!(matches!(err, CaptureError::Empty { .. }));
        assert!(err.to_string().contains("/data/flight.fwc"));

        let err = check_preamble(b"GARBAGE GARBAGE!", path).unwrap_err();
        assert!(matches!(err, CaptureError::NotACapture { .. }));
        assert!(err.to_string().contains("/data/flight.fwc"));

        let err = check_preamble(&preamble()[..10], path).unwrap_err();
        assert!(matches!(
            err,
            CaptureError::TruncatedPreamble { len: 10, .. }
        ));

        let mut newer = preamble();
        newer[8..10].copy_from_slice(&2u16.to_le_bytes());
        newer[10..12].copy_from_slice(&3u16.to_le_bytes());
        let err = check_preamble(&newer, path).unwrap_err();
        assert!(matches!(
            err,
            CaptureError::NewerVersion {
                major: 2,
                minor: 3,
                ..
            }
        ));
        let msg = err.to_string();
        assert!(
            msg.contains("2.3") && msg.contains("/data/flight.fwc"),
            "{msg}"
        );

        let mut newer_minor = preamble();
        newer_minor[10..12].copy_from_slice(&7u16.to_le_bytes());
        assert_eq!(check_preamble(&newer_minor, path).unwrap(), (1, 7));
    }

    #[test]
    fn record_kinds_from_bytes() {
        assert_eq!(RecordKind::from_u8(1), Some(RecordKind::Header));
        assert_eq!(RecordKind::from_u8(2), Some(RecordKind::DigitizerFrame));
        assert_eq!(RecordKind::from_u8(3), Some(RecordKind::NavBytes));
        assert_eq!(RecordKind::from_u8(0), None);
        assert_eq!(RecordKind::from_u8(4), Some(RecordKind::GeoFrame));
        assert_eq!(RecordKind::from_u8(5), None);
    }

    #[test]
    fn crc_covers_header_and_payload() {
        let a = record_crc(&[2, 0, 0, 0, 3, 0, 0, 0], b"abc");
        let b = record_crc(&[2, 0, 0, 0, 3, 0, 0, 0], b"abd");
        let c = record_crc(&[3, 0, 0, 0, 3, 0, 0, 0], b"abc");
        assert_ne!(a, b);
        assert_ne!(a, c);
        let mut all = vec![2, 0, 0, 0, 3, 0, 0, 0];
        all.extend_from_slice(b"abc");
        assert_eq!(a, crc32c::crc32c(&all));
    }

    #[test]
    fn flush_policy_defaults_and_unknown_fields() {
        let p: FlushPolicy = toml::from_str("").unwrap();
        assert_eq!(p, FlushPolicy::default());
        assert_eq!(p.every_records, 256);
        assert_eq!(p.every_ms, 200);
        assert_eq!(p.fsync, FsyncPolicy::OnFlush);
        let p: FlushPolicy = toml::from_str("every_records = 0\nfsync = \"never\"").unwrap();
        assert_eq!(p.every_records, 0);
        assert_eq!(p.every_ms, 200);
        assert_eq!(p.fsync, FsyncPolicy::Never);
        assert!(toml::from_str::<FlushPolicy>("every_record = 1").is_err());
        assert!(toml::from_str::<FlushPolicy>("fsync = \"always\"").is_err());
    }

    #[test]
    fn skip_report_serializes() {
        let r = SkipReport {
            bad_checksums: 2,
            ..SkipReport::default()
        };
        assert!(!r.is_clean());
        let json = serde_json::to_string(&r).unwrap();
        assert!(json.contains("\"bad_checksums\":2"), "{json}");
    }
}
