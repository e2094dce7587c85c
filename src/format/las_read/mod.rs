//! Reading LAS 1.3 / 1.4 (ASPRS R15) files with waveform packets: point data record formats 4,
//! 5, 9 and 10, waveform packet descriptors, and the packets themselves from an external `.wdp`
//! file or the internal waveform data packet record.
//!
//! One [`Pulse`] is made per waveform packet: consecutive points that name the same packet
//! (same descriptor index and byte offset) are the returns of one pulse and give one pulse; a
//! packet named again after other packets starts a new pulse (its waveform is emitted again,
//! and counted in [`LasReadStats::packets_revisited`]).
//!
//! The pulse's geometry is the inverse of `sink::las_wave`'s: for a point P with return point
//! waveform location L (ps) and parametric vector v = (x(t), y(t), z(t)) (CRS units per ps), the
//! first sample lies at `anchor = P + L · v` and time runs along `direction = −1000 · v` (CRS
//! units per ns). The one return segment starts at 0 ns. `docs/formats.md`, "LAS 1.3/1.4
//! waveforms (input)", says why and how the real RIEGL file confirms it.
//!
//! The parser never panics and never allocates by a size read from the file without first
//! checking it against the file's length: the points are checked to fit in the file before the
//! first is read, each packet before it is read. Errors ([`LasReadError`]) name the file and the
//! field.
//!
//! LAZ files (point formats 4, 5, 9, 10 stored as 132, 133, 137, 138 with the LASzip VLR) are
//! read too: `laz.rs` decompresses their point records, chunk by chunk, into the bytes a LAS
//! file would hold, and the same decoding follows. Their waveform packets come from the `.wdp`
//! beside them or from inside the file, as for LAS; LASzip-compressed packets (a `.wdz`) are
//! refused with the command that decompresses them.
//!
//! `header.rs` reads the header and (E)VLRs ([`LasInfo`]); this module reads the points and
//! packets ([`LasReader`]).

mod header;
mod laz;

use std::fs::File;
use std::io::{BufReader, Cursor, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::format::las_write::{
    DESCRIPTOR_RECORD_ID_BASE, DESCRIPTOR_SIZE, EVLR_HEADER_SIZE, Header, MAX_DESCRIPTORS,
    PointRecord9, WavePacketDescriptor,
};
use crate::pulse::{Pulse, PulseGeometry, SegmentKind};

pub use header::{
    DescriptorRecord, GEO_KEY_DIRECTORY_RECORD_ID, LasInfo, WaveformLocation, epsg_of_geokeys,
};
use header::{PointLayout, Positioned, defined_list, stream_len};
use laz::LazPoints;
pub use laz::{LASZIP_RECORD_ID, LASZIP_USER_ID};

/// Size of the LAS 1.3 public header block (up to the start of the waveform data packet
/// record), bytes.
pub const HEADER_SIZE_13: usize = 235;
/// Global encoding bit 1: waveform data packets are internal (the waveform data packet record,
/// an EVLR in LAS 1.4).
pub const GLOBAL_WAVEFORM_INTERNAL: u16 = 1 << 1;
/// Longest WKT read from an EVLR, bytes (VLRs hold at most 65535).
pub const MAX_WKT_BYTES: u64 = 1 << 20;

/// Why a LAS file cannot be read. Every variant names the file and, where one is at fault, the
/// field.
#[derive(Debug, thiserror::Error)]
pub enum LasReadError {
    /// The operating system failed to read.
    #[error("{file}: cannot read {what}: {source}")]
    Io {
        /// The file.
        file: String,
        /// What was being read.
        what: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A part of the file the header promises lies past its end.
    #[error("{file}: truncated: {what} needs bytes {start}..{end} but the file has {len} bytes")]
    Truncated {
        /// The file.
        file: String,
        /// What was expected there.
        what: String,
        /// First byte of it.
        start: u64,
        /// One past its last byte (saturated at `u64::MAX`).
        end: u64,
        /// Length of the file, bytes.
        len: u64,
    },
    /// The file does not start with `LASF`.
    #[error("{file}: not a LAS file (file signature {found:?}, expected \"LASF\")")]
    Signature {
        /// The file.
        file: String,
        /// The first bytes found.
        found: String,
    },
    /// A field holds a value that makes no sense.
    #[error("{file}: {field}: {reason}")]
    Invalid {
        /// The file.
        file: String,
        /// The field, with where it is (`header: ...`, `point 12: ...`, `VLR 3 ...`).
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A valid LAS feature fwlidar does not read.
    #[error("{file}: {field}: {what} is not supported")]
    Unsupported {
        /// The file.
        file: String,
        /// The field.
        field: String,
        /// The value and what would be needed.
        what: String,
    },
    /// A point names a waveform packet descriptor that no VLR defines.
    #[error(
        "{file}: point {point}: wave packet descriptor index {index} points nowhere \
         (descriptors {defined} defined)"
    )]
    NoDescriptor {
        /// The file.
        file: String,
        /// Point number, from 0.
        point: u64,
        /// The index it names.
        index: u8,
        /// The indices that are defined, e.g. `1, 2` or `1-100`, or `none`.
        defined: String,
    },
    /// The external waveform data file is missing.
    #[error(
        "{las}: the waveform data packets are in an external file (global encoding bit 2) but \
         neither {wdp} nor {alt} exists"
    )]
    MissingWdp {
        /// The LAS file.
        las: String,
        /// The `.wdp` path looked for.
        wdp: String,
        /// The `.WDP` path looked for.
        alt: String,
    },
    /// The waveform packets are external but LASzip-compressed: a `.wdz` lies beside the file
    /// instead of a `.wdp`.
    #[error(
        "{las}: the waveform data packets are in {wdz}, compressed by LASzip, which fwlidar does \
         not read (no {wdp} beside it); decompress them with LAStools: `{command}` writes the \
         file again uncompressed with its packets in a .wdp beside it; then read that file"
    )]
    CompressedWdp {
        /// The LAS or LAZ file.
        las: String,
        /// The `.wdz` found.
        wdz: String,
        /// The `.wdp` path looked for.
        wdp: String,
        /// The LAStools command that decompresses the file and its packets.
        command: String,
    },
    /// A waveform packet lies (partly) outside the waveform data.
    #[error(
        "{file}: point {point}: waveform packet at bytes {start}..{end} lies outside the \
         waveform data ({len} bytes): the file is truncated or the point's byte offset to \
         waveform data is wrong"
    )]
    PacketOutside {
        /// The file holding the waveform data (`.wdp`, or the LAS file when internal).
        file: String,
        /// Point number, from 0.
        point: u64,
        /// First byte of the packet in that file.
        start: u64,
        /// One past its last byte (saturated at `u64::MAX`).
        end: u64,
        /// Length of the file, bytes.
        len: u64,
    },
}

/// The error for a failed read; call it inside `map_err(|e| ...)` so that nothing is formatted
/// or allocated unless reading fails.
pub(super) fn io_err(file: &str, what: impl Into<String>, source: std::io::Error) -> LasReadError {
    LasReadError::Io {
        file: file.to_string(),
        what: what.into(),
        source,
    }
}

/// An [`LasReadError::Invalid`].
pub(super) fn invalid(
    file: &str,
    field: impl Into<String>,
    reason: impl Into<String>,
) -> LasReadError {
    LasReadError::Invalid {
        file: file.to_string(),
        field: field.into(),
        reason: reason.into(),
    }
}

/// The `.wdp` (and `.WDP`) paths looked for beside a LAS file.
pub fn wdp_paths(las: &Path) -> (PathBuf, PathBuf) {
    (las.with_extension("wdp"), las.with_extension("WDP"))
}

/// The `.wdz` (and `.WDZ`) paths of LASzip-compressed waveform packets beside a file.
pub fn wdz_paths(las: &Path) -> (PathBuf, PathBuf) {
    (las.with_extension("wdz"), las.with_extension("WDZ"))
}

/// The LAStools command that decompresses `las` (LAS or LAZ) and its `.wdz` packets: laszip's
/// `-waveform` option reads the `.wdz` and, for LAS output, writes the packets uncompressed to a
/// `.wdp` beside the output (descriptors' compression type set back to 0). Paths with spaces or
/// shell characters are single-quoted.
pub fn laszip_decompress_command(las: &Path) -> String {
    let is_laz = las
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("laz"));
    let out = if is_laz {
        las.with_extension("las")
    } else {
        let stem = las.file_stem().unwrap_or_default().to_string_lossy();
        las.with_file_name(format!("{stem}_wdp.las"))
    };
    let arg = |p: &Path| {
        let t = p.display().to_string();
        if t.contains(|c: char| c.is_whitespace() || "'\"$`\\".contains(c)) {
            format!("'{}'", t.replace('\'', "'\\''"))
        } else {
            t
        }
    };
    format!("laszip -i {} -o {} -waveform", arg(las), arg(&out))
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

/// Counts of what was read, for the source's report.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct LasReadStats {
    /// Point records read.
    pub points: u64,
    /// Points whose wave packet descriptor index is 0 (no waveform): skipped.
    pub points_without_waveform: u64,
    /// Pulses made (one per run of consecutive points naming the same packet).
    pub pulses: u64,
    /// Pulses whose point has a parametric line that is not finite or zero: no geometry.
    pub pulses_without_geometry: u64,
    /// Pulses whose packet starts before the end of the furthest packet read so far (a packet
    /// named again after others, or packets stored out of order).
    pub packets_revisited: u64,
    /// Bytes of waveform packets read.
    pub waveform_bytes: u64,
    /// Waveform packet descriptors used by the points read so far.
    pub descriptors_used: u64,
    /// LAZ chunks decompressed (started) so far; absent from the report for LAS.
    #[serde(skip_serializing_if = "is_zero")]
    pub laz_chunks: u64,
}

/// The waveform data: a `.wdp` file, or the LAS file again, read through a buffer.
struct WaveData<W> {
    file: String,
    r: Positioned<W>,
    len: u64,
    /// Where packet offsets count from in `r`.
    base: u64,
}

impl<W: Read + Seek> WaveData<W> {
    fn new(file: String, mut w: W, base: u64) -> Result<Self, LasReadError> {
        let len = stream_len(&mut w, &file)?;
        Ok(WaveData {
            file,
            r: Positioned::new(w, 1 << 16),
            len,
            base,
        })
    }
}

/// Where the point records come from.
enum Points<R: Read + Seek> {
    /// Plain LAS: the records as stored.
    Raw(BufReader<R>),
    /// LAZ: decompressed chunk by chunk.
    Laz(Box<LazPoints<R>>),
}

/// Reads the waveform packets of a LAS (or LAZ) file as pulses ([`LasReader::next_pulse`]).
pub struct LasReader<R: Read + Seek, W> {
    info: LasInfo,
    layout: PointLayout,
    points: Points<R>,
    wave: Option<WaveData<W>>,
    next_point: u64,
    pending: Option<(u64, PointRecord9)>,
    /// The error of a point read after a pulse's first, returned by the next call.
    deferred: Option<LasReadError>,
    record: Vec<u8>,
    packet: Vec<u8>,
    checked: [bool; MAX_DESCRIPTORS + 1],
    furthest_end: u64,
    stats: LasReadStats,
}

impl LasReader<File, File> {
    /// Opens a LAS or LAZ file and its waveform data (the `.wdp` beside it when external; the
    /// file again when internal). A `.wdz` beside it instead of a `.wdp` is an error that says
    /// how to decompress it ([`LasReadError::CompressedWdp`]).
    pub fn open(path: &Path) -> Result<Self, LasReadError> {
        let name = path.display().to_string();
        let mut las = File::open(path).map_err(|e| io_err(&name, "the file", e))?;
        let info = LasInfo::read(&name, &mut las)?;
        let wave = match info.waveform {
            WaveformLocation::External => {
                let (wdp, alt) = wdp_paths(path);
                let (wdz, wdz_alt) = wdz_paths(path);
                let chosen = if wdp.exists() {
                    wdp
                } else if alt.exists() {
                    alt
                } else if let Some(z) = [wdz, wdz_alt].into_iter().find(|z| z.exists()) {
                    return Err(LasReadError::CompressedWdp {
                        las: name,
                        wdz: z.display().to_string(),
                        wdp: wdp.display().to_string(),
                        command: laszip_decompress_command(path),
                    });
                } else {
                    return Err(LasReadError::MissingWdp {
                        las: name,
                        wdp: wdp.display().to_string(),
                        alt: alt.display().to_string(),
                    });
                };
                let wname = chosen.display().to_string();
                let f = File::open(&chosen).map_err(|e| io_err(&wname, "the waveform data", e))?;
                Some(WaveData::new(wname, f, 0)?)
            }
            WaveformLocation::Internal { record_start } => {
                let f = File::open(path).map_err(|e| io_err(&name, "the waveform data", e))?;
                Some(WaveData::new(name.clone(), f, record_start)?)
            }
            WaveformLocation::Absent => None,
        };
        LasReader::with_parts(info, las, wave)
    }
}

impl<'a> LasReader<Cursor<&'a [u8]>, Cursor<&'a [u8]>> {
    /// Reads a LAS file held in memory, named `las.las` in errors, with its `.wdp` (named
    /// `las.wdp`) when the packets are external (for tests and fuzzing).
    pub fn from_bytes(las: &'a [u8], wdp: Option<&'a [u8]>) -> Result<Self, LasReadError> {
        let name = "las.las";
        let info = LasInfo::read(name, &mut Cursor::new(las))?;
        let wave = match info.waveform {
            WaveformLocation::External => match wdp {
                Some(w) => Some(WaveData::new("las.wdp".into(), Cursor::new(w), 0)?),
                None => {
                    return Err(LasReadError::MissingWdp {
                        las: name.into(),
                        wdp: "las.wdp".into(),
                        alt: "las.WDP".into(),
                    });
                }
            },
            WaveformLocation::Internal { record_start } => {
                Some(WaveData::new(name.into(), Cursor::new(las), record_start)?)
            }
            WaveformLocation::Absent => None,
        };
        LasReader::with_parts(info, Cursor::new(las), wave)
    }
}

impl<R: Read + Seek, W: Read + Seek> LasReader<R, W> {
    fn with_parts(
        info: LasInfo,
        mut las: R,
        wave: Option<WaveData<W>>,
    ) -> Result<Self, LasReadError> {
        let Some(layout) = PointLayout::of(info.header.point_format) else {
            return Err(invalid(
                &info.file,
                "header: point data record format",
                "not 4, 5, 9, 10",
            ));
        };
        let points = match &info.laz {
            Some(vlr) => Points::Laz(Box::new(LazPoints::open(&info, vlr, las)?)),
            None => {
                las.seek(SeekFrom::Start(u64::from(info.header.offset_to_point_data)))
                    .map_err(|e| io_err(&info.file, "the point records", e))?;
                Points::Raw(BufReader::with_capacity(1 << 16, las))
            }
        };
        let record = vec![0u8; usize::from(info.header.point_record_length)];
        Ok(LasReader {
            layout,
            points,
            wave,
            next_point: 0,
            pending: None,
            deferred: None,
            record,
            packet: Vec::new(),
            checked: [false; MAX_DESCRIPTORS + 1],
            furthest_end: 0,
            stats: LasReadStats::default(),
            info,
        })
    }

    /// What the header and VLRs state.
    pub fn info(&self) -> &LasInfo {
        &self.info
    }

    /// Counts so far.
    pub fn stats(&self) -> &LasReadStats {
        &self.stats
    }

    /// Bytes of the file covered so far and in all (header, VLRs and point records; for LAZ the
    /// compressed records, estimated within the chunk being read), for progress.
    pub fn progress(&self) -> (u64, u64) {
        let rl = u64::from(self.info.header.point_record_length);
        let base = u64::from(self.info.header.offset_to_point_data);
        let (done, all) = match &self.points {
            Points::Raw(_) => (
                self.next_point.saturating_mul(rl),
                self.info.header.number_of_points.saturating_mul(rl),
            ),
            Points::Laz(z) => z.progress(),
        };
        (base.saturating_add(done), base.saturating_add(all))
    }

    /// Whether the point records are LAZ-compressed.
    pub fn is_laz(&self) -> bool {
        matches!(self.points, Points::Laz(_))
    }

    /// The next point record, `None` after the last.
    fn read_point(&mut self) -> Result<Option<(u64, PointRecord9)>, LasReadError> {
        if self.next_point >= self.info.header.number_of_points {
            return Ok(None);
        }
        let n = self.next_point;
        match &mut self.points {
            Points::Raw(r) => r
                .read_exact(&mut self.record)
                .map_err(|e| io_err(&self.info.file, format!("point {n}"), e))?,
            Points::Laz(z) => {
                z.read_point(n, &mut self.record)?;
                self.stats.laz_chunks = z.chunks_started;
            }
        }
        self.next_point += 1;
        self.stats.points += 1;
        Ok(Some((n, PointRecord9::decode(&self.record, self.layout))))
    }

    /// The next point that names a waveform packet.
    fn read_wave_point(&mut self) -> Result<Option<(u64, PointRecord9)>, LasReadError> {
        while let Some((n, p)) = self.read_point()? {
            if p.wave_packet_index != 0 {
                return Ok(Some((n, p)));
            }
            self.stats.points_without_waveform += 1;
        }
        Ok(None)
    }

    /// Fills `pulse` (its segments, samples and fields; `seq` and `arrived` are left to the
    /// caller) with the next pulse; `false` after the last. Points without
    /// a waveform are skipped (counted). The pulse's `pulse_id` is the number of its first point
    /// (from 0).
    ///
    /// A point that cannot be read after the pulse's first (a damaged LAZ chunk, say) does not
    /// lose the pulse, whose packet is read already: the pulse is returned and the error comes
    /// with the next call.
    pub fn next_pulse(&mut self, pulse: &mut Pulse) -> Result<bool, LasReadError> {
        if let Some(e) = self.deferred.take() {
            return Err(e);
        }
        let first = match self.pending.take() {
            Some(p) => p,
            None => match self.read_wave_point()? {
                Some(p) => p,
                None => return Ok(false),
            },
        };
        self.fill(pulse, first.0, &first.1)?;
        // The rest of the pulse: following points naming the same packet.
        loop {
            let (n, p) = match self.read_point() {
                Ok(Some(np)) => np,
                Ok(None) => break,
                Err(e) => {
                    self.deferred = Some(e);
                    break;
                }
            };
            if p.wave_packet_index == 0 {
                self.stats.points_without_waveform += 1;
            } else if p.wave_packet_index != first.1.wave_packet_index
                || p.wave_offset != first.1.wave_offset
            {
                self.pending = Some((n, p));
                break;
            }
        }
        self.stats.pulses += 1;
        Ok(true)
    }

    /// The checked descriptor `index` named by point `n`.
    fn descriptor(&mut self, n: u64, index: u8) -> Result<WavePacketDescriptor, LasReadError> {
        let file = &self.info.file;
        let Some(rec) = self
            .info
            .descriptors
            .get(usize::from(index))
            .copied()
            .flatten()
        else {
            return Err(LasReadError::NoDescriptor {
                file: file.clone(),
                point: n,
                index,
                defined: defined_list(&self.info.descriptors),
            });
        };
        let d = rec.descriptor;
        let i = usize::from(index);
        if self.checked.get(i).copied().unwrap_or(false) {
            return Ok(d);
        }
        let field = |what: &str| {
            format!(
                "point {n}: wave packet descriptor {index} (LASF_Spec {}): {what}",
                u16::from(index) + DESCRIPTOR_RECORD_ID_BASE
            )
        };
        if rec.payload_len < DESCRIPTOR_SIZE as u64 {
            return Err(invalid(
                file,
                field("record length"),
                format!("{} bytes, {DESCRIPTOR_SIZE} expected", rec.payload_len),
            ));
        }
        if d.compression != 0 {
            return Err(LasReadError::Unsupported {
                file: file.clone(),
                field: field("compression type"),
                what: format!("{} (only 0, uncompressed, is defined)", d.compression),
            });
        }
        if !(1..=16).contains(&d.bits_per_sample) {
            return Err(LasReadError::Unsupported {
                file: file.clone(),
                field: field("bits per sample"),
                what: format!(
                    "{} bits per sample (1 to 8 stored in one byte, 9 to 16 in two are read)",
                    d.bits_per_sample
                ),
            });
        }
        if d.number_of_samples == 0 {
            return Err(invalid(file, field("number of samples"), "0"));
        }
        if d.temporal_spacing_ps == 0 {
            return Err(invalid(file, field("temporal sample spacing"), "0 ps"));
        }
        if let Some(c) = self.checked.get_mut(i) {
            *c = true;
        }
        self.stats.descriptors_used += 1;
        Ok(d)
    }

    /// Reads point `n`'s packet into `pulse`.
    fn fill(&mut self, pulse: &mut Pulse, n: u64, p: &PointRecord9) -> Result<(), LasReadError> {
        let d = self.descriptor(n, p.wave_packet_index)?;
        let file = &self.info.file;
        let bytes_per_sample: u64 = if d.bits_per_sample <= 8 { 1 } else { 2 };
        let expected = u64::from(d.number_of_samples) * bytes_per_sample;
        if u64::from(p.wave_size) != expected {
            return Err(invalid(
                file,
                format!("point {n}: waveform packet size"),
                format!(
                    "{} bytes, but descriptor {} gives {} samples of {} bits ({expected} bytes)",
                    p.wave_size, p.wave_packet_index, d.number_of_samples, d.bits_per_sample
                ),
            ));
        }
        let Some(wave) = self.wave.as_mut() else {
            return Err(invalid(
                file,
                format!("point {n}: wave packet descriptor index"),
                format!(
                    "{}, but the header states no waveform data (global encoding bits 1 and 2 \
                     clear, start of waveform data packet record 0)",
                    p.wave_packet_index
                ),
            ));
        };
        if p.wave_offset < EVLR_HEADER_SIZE as u64 {
            return Err(invalid(
                &wave.file,
                format!("point {n}: byte offset to waveform data"),
                format!(
                    "{}, inside the {EVLR_HEADER_SIZE}-byte header of the waveform data packet \
                     record (offsets count from the start of that header)",
                    p.wave_offset
                ),
            ));
        }
        let start = wave.base.checked_add(p.wave_offset);
        let end = start.and_then(|s| s.checked_add(u64::from(p.wave_size)));
        let (Some(start), Some(end)) = (start, end) else {
            return Err(LasReadError::PacketOutside {
                file: wave.file.clone(),
                point: n,
                start: start.unwrap_or(u64::MAX),
                end: u64::MAX,
                len: wave.len,
            });
        };
        if end > wave.len {
            return Err(LasReadError::PacketOutside {
                file: wave.file.clone(),
                point: n,
                start,
                end,
                len: wave.len,
            });
        }
        // The packet lies in the file, so its size is bounded by the file's length.
        self.packet.resize(p.wave_size as usize, 0);
        wave.r
            .read_exact_at(start, &mut self.packet)
            .map_err(|e| io_err(&wave.file, format!("point {n}'s waveform packet"), e))?;
        if start < self.furthest_end {
            self.stats.packets_revisited += 1;
        }
        self.furthest_end = self.furthest_end.max(end);
        self.stats.waveform_bytes += u64::from(p.wave_size);

        // As `Pulse::reset` without reading the clock: `seq` and `arrived` are the runner's.
        pulse.segments.clear();
        pulse.raw.clear();
        pulse.signal.clear();
        pulse.returns.clear();
        pulse.noise = Default::default();
        pulse.pulse_id = n;
        pulse.gps_time = p.core.gps_time;
        pulse.scan_angle_deg = [f32::from(p.core.scan_angle) * 0.006, f32::NAN];
        pulse.sample_ns = f64::from(d.temporal_spacing_ps) / 1000.0;
        pulse.gain_v_per_dn = d.digitizer_gain as f32;
        pulse.offset_v = d.digitizer_offset as f32;
        pulse.bits = d.bits_per_sample;
        if bytes_per_sample == 1 {
            pulse.push_segment(
                SegmentKind::Return,
                0,
                0.0,
                self.packet.iter().map(|&b| u16::from(b)),
            );
        } else {
            pulse.push_segment(
                SegmentKind::Return,
                0,
                0.0,
                self.packet
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]])),
            );
        }
        pulse.geometry = geometry(&self.info.header, p);
        if pulse.geometry.is_none() {
            self.stats.pulses_without_geometry += 1;
        }
        Ok(())
    }
}

/// The point's position, CRS units.
pub fn position(h: &Header, p: &PointRecord9) -> [f64; 3] {
    std::array::from_fn(|k| f64::from(p.core.xyz[k]) * h.scale[k] + h.offset[k])
}

/// The pulse geometry of a point's packet: anchor at the first sample `P + L · v`, direction
/// `−1000 · v` per ns; `None` when not finite or v is zero.
fn geometry(h: &Header, p: &PointRecord9) -> Option<PulseGeometry> {
    let pos = position(h, p);
    let l = f64::from(p.wave_location_ps);
    let v = p.xyz_t.map(f64::from);
    let anchor: [f64; 3] = std::array::from_fn(|k| pos[k] + l * v[k]);
    let direction = v.map(|x| -1000.0 * x);
    let finite = anchor.iter().chain(&direction).all(|x| x.is_finite());
    (finite && direction.iter().any(|&x| x != 0.0)).then_some(PulseGeometry { anchor, direction })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laszip_command_names_the_las_it_writes() {
        assert_eq!(
            laszip_decompress_command(Path::new("d/x.laz")),
            "laszip -i d/x.laz -o d/x.las -waveform"
        );
        assert_eq!(
            laszip_decompress_command(Path::new("d/X.LAZ")),
            "laszip -i d/X.LAZ -o d/X.las -waveform"
        );
        // A LAS input is not overwritten.
        assert_eq!(
            laszip_decompress_command(Path::new("x.las")),
            "laszip -i x.las -o x_wdp.las -waveform"
        );
        assert_eq!(
            laszip_decompress_command(Path::new("my dir/it's.laz")),
            "laszip -i 'my dir/it'\\''s.laz' -o 'my dir/it'\\''s.las' -waveform"
        );
    }
}
