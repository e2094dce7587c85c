//! Discrete returns as LAS 1.4 points: point data record format 6 (default) or format 9 with the
//! waveforms they came from in an external waveform data packet file (`.las` + `.wdp`), in one
//! file or rotated every N seconds of pulse time.
//!
//! - One point per fitted return ([`Pulse::returns`]) of every pulse that has a
//!   [`PulseGeometry`]; its position is `anchor + time_ns · direction` (CRS units), stored with
//!   scale [`SCALE`] and an offset taken from the file's first point (multiples of 1000 CRS
//!   units).
//! - Format 9 only: one waveform packet per (pulse, return segment that has at least one
//!   return): the segment's **raw digitizer counts**, 8-bit when the pulse's `bits` ≤ 8, else
//!   16-bit little-endian; the packet's descriptor carries the pulse's gain and offset
//!   (`volts = offset + gain · count`) and the sample interval in picoseconds. Descriptors (VLR
//!   `LASF_Spec` / 99 + index) are made on demand per distinct (bits, samples, sample interval,
//!   gain, offset), at most 255 per file; a 256th is an error.
//! - The parametric line (format 9): for a point P with return point waveform location L (ps
//!   from the packet's first sample to the return), `(x_t, y_t, z_t) = −direction / 1000` (CRS
//!   units per ps), so the first sample lies at `P + L · (x_t, y_t, z_t)`.
//! - Intensity: the Gaussian's amplitude in digitizer counts (`amplitude / gain`), normalised to
//!   16 bits as LAS asks (`× 65536 / 2^bits`), rounded, clipped to 0..=65535 (clips counted).
//! - With [`LasWaveOptions::extra_bytes`]: four f32 per point declared in an Extra Bytes VLR
//!   ([`return_extra_dims`]): `amplitude` (V), `width` (FWHM, ns), `backscatter` (calibrated;
//!   the declared no-data value −9999 while it is NaN) and `residual` (V).
//!
//! **Crash safety.** Each file is written as `NAME.partial` and renamed into place when it is
//! complete (the `.wdp` first). Its header and VLRs are written *provisionally* at open and
//! rewritten (seek back, then on at the end) whenever they change: when the first point fixes
//! the offset and when a descriptor is added; so at any moment the bytes the OS has are a LAS
//! file whose VLRs are final and whose points follow them, only the point count and bounds being
//! stale. `fwlidar repair` (`format::las_repair`) completes such a file after a crash. The open
//! file's buffers are handed to the OS every [`LasWaveOptions::flush_s`] seconds of pulse time.
//! With rotation ([`LasWaveOptions::rotate_s`]) a crash thus costs at most the open file's
//! header (repairable) and its last unflushed points. Layout and every field: `docs/formats.md`,
//! "Returns as LAS 1.4 (output)".

use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::core::atomic_file::AtomicFile;
use crate::format::las_write::{
    self as lw, DESCRIPTOR_SIZE, EVLR_HEADER_SIZE, ExtraDim, HEADER_SIZE, Header, LasWriteError,
    MAX_DESCRIPTORS, PF6_SIZE, PF9_SIZE, PointRecord6, PointRecord9, VLR_HEADER_SIZE,
    WavePacketDescriptor,
};
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::{Pulse, PulseGeometry};
use crate::sink::SinkReport;

/// Scale of the stored X, Y, Z: 1 mm in a projected CRS in metres.
pub const SCALE: f64 = 0.001;
/// The offset is the first point's position rounded down to a multiple of this (CRS units).
pub const OFFSET_STEP: f64 = 1000.0;
/// Bytes of extra bytes per point with [`LasWaveOptions::extra_bytes`]: `amplitude`, `width`,
/// `backscatter`, `residual`, f32 each.
pub const EXTRA_BYTES: usize = 16;
/// User id of the padding VLR that fills the unused descriptor room.
pub const PADDING_USER_ID: &str = "fwlidar";
/// Record id of the padding VLR.
pub const PADDING_RECORD_ID: u16 = 1;
/// Room reserved between the header and the points for the descriptor VLRs (format 9), bytes.
pub const DESCRIPTOR_ROOM: usize = MAX_DESCRIPTORS * (VLR_HEADER_SIZE + DESCRIPTOR_SIZE);
/// Largest return number LAS point formats 6–10 hold.
pub const MAX_RETURNS: usize = 15;
/// FWHM of a Gaussian in standard deviations, `2 √(2 ln 2)`.
pub const FWHM_PER_SIGMA: f64 = 2.354_820_045_030_949;

/// The extra dimensions of every return point, in record order.
pub fn return_extra_dims() -> [ExtraDim; 4] {
    [
        ExtraDim::f32("amplitude", "Gaussian peak amplitude (V)"),
        ExtraDim::f32("width", "Gaussian FWHM (ns)"),
        ExtraDim::f32("backscatter", "calibrated backscatter").with_no_data(),
        ExtraDim::f32("residual", "RMS fit residual of segment (V)"),
    ]
}

/// Settings of the LAS output.
#[derive(Clone, Debug, PartialEq)]
pub struct LasWaveOptions {
    /// Coordinate reference system of the pulses' geometry as OGC WKT, written as VLR
    /// `LASF_Projection` / 2112; `None` writes no CRS record.
    pub crs_wkt: Option<String>,
    /// Append the [`return_extra_dims`] (f32 each) to every point, declared in an Extra Bytes
    /// VLR. Default true.
    pub extra_bytes: bool,
    /// The pulses' GPS time is Adjusted Standard GPS time (global encoding bit 0); else GPS
    /// seconds of the week. Default false.
    pub adjusted_standard_gps_time: bool,
    /// Point data record format: 6 (points only) or 9 (points with waveform packets in a `.wdp`
    /// beside each `.las`). Default 6.
    pub point_format: u8,
    /// Start a new file when a pulse's GPS time is this many seconds past the first pulse of the
    /// open file (or before it): `returns_0000.las`, `returns_0001.las`, …; 0 = one file,
    /// `returns.las`. Default 0.
    pub rotate_s: f64,
    /// Hand the open file's buffered bytes to the OS when a pulse's GPS time is this many
    /// seconds past the last time it was done (0 = only when the 1 MiB buffers fill). Default 1.
    pub flush_s: f64,
    /// The CRS decided during the run (by the georeferencing: the UTM zone of the first fix),
    /// when `crs_wkt` is `None`: written at the end of each file, once known, as the OGC WKT
    /// EVLR (`LASF_Projection` / 2112, which LAS 1.4 allows after the points), so a file whose
    /// CRS was not known when it was opened still carries it. A value that is not WKT (e.g.
    /// `EPSG:<code>`) is not written (and said).
    pub crs_decided: Option<std::sync::Arc<std::sync::OnceLock<String>>>,
}

impl Default for LasWaveOptions {
    fn default() -> Self {
        LasWaveOptions {
            crs_wkt: None,
            extra_bytes: true,
            adjusted_standard_gps_time: false,
            point_format: 6,
            rotate_s: 0.0,
            flush_s: 1.0,
            crs_decided: None,
        }
    }
}

/// What the LAS sink wrote and skipped (in `summary.json` under `sinks.las`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct LasWaveReport {
    /// Point records written.
    pub points: u64,
    /// Pulses that gave at least one point.
    pub pulses_written: u64,
    /// Pulses with returns but no geometry: skipped.
    pub pulses_without_geometry: u64,
    /// Pulses with no fitted return: nothing to write.
    pub pulses_without_returns: u64,
    /// Returns skipped because their position is not finite or more than 2^31 mm from the
    /// offset, or they name a segment the pulse does not have.
    pub returns_unrepresentable: u64,
    /// Returns past the 15th of a pulse (written with return number 15).
    pub returns_beyond_15: u64,
    /// Returns whose amplitude lies above the digitizer's full scale (a saturated echo, or a
    /// fit overshooting it), their intensity recorded as the full scale.
    pub intensity_at_full_scale: u64,
    /// Waveform packets written to the `.wdp` files (format 9).
    pub packets: u64,
    /// Size of the `.wdp` files, bytes (their 60-byte headers included; format 9).
    pub wdp_bytes: u64,
    /// Waveform packet descriptors used (largest number in one file; format 9).
    pub descriptors: u64,
    /// Point data record format written.
    pub point_format: u8,
    /// The LAS files completed, in order (names in the output folder).
    pub files: Vec<String>,
}

/// What distinguishes two descriptors: stored bits, samples, spacing (ps), gain and offset
/// (f32 bit patterns, as the pulse carries them).
type DescKey = (u8, u32, u32, u32, u32);

/// The file being written and what its header will say.
struct OpenFile {
    las: AtomicFile,
    wdp: Option<AtomicFile>,
    las_path: PathBuf,
    wdp_path: PathBuf,
    /// GPS time of the first pulse written to it (NaN before).
    start_gps: f64,
    /// GPS time of the last hand-over of the buffers to the OS (NaN before).
    flushed_gps: f64,
    descriptors: Vec<(DescKey, WavePacketDescriptor)>,
    last_descriptor: usize,
    offset: Option<[f64; 3]>,
    min: [i32; 3],
    max: [i32; 3],
    by_return: [u64; MAX_RETURNS],
    points: u64,
    wdp_pos: u64,
    /// Where the WKT EVLR starts, once written when the file is completed.
    evlr_start: Option<u64>,
}

/// Writes the returns as LAS into a folder.
pub struct LasWaveSink {
    dir: PathBuf,
    options: LasWaveOptions,
    dims: Vec<ExtraDim>,
    /// Encoded VLRs known at creation (WKT, Extra Bytes), in file order.
    fixed_vlrs: Vec<u8>,
    fixed_vlr_count: u32,
    record_len: usize,
    file: Option<OpenFile>,
    /// Index of the open (or next) file.
    file_index: u32,
    finished: bool,
    report: LasWaveReport,
    // Scratch reused from pulse to pulse.
    order: Vec<u16>,
    packet_of_segment: Vec<Option<(u8, u64, u32)>>,
    record: Vec<u8>,
    samples: Vec<u8>,
    preamble: Vec<u8>,
}

fn las_err(path: &Path, source: LasWriteError) -> SinkError {
    SinkError::output(crate::format::las_points::LasFileError::Las {
        path: path.display().to_string(),
        source,
    })
}

fn io_err(path: &Path, source: std::io::Error) -> SinkError {
    SinkError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Name of LAS file `index` (`returns.las` without rotation, else `returns_NNNN.las`) and of its
/// `.wdp`.
pub fn file_names(rotating: bool, index: u32) -> (String, String) {
    if rotating {
        (
            format!("returns_{index:04}.las"),
            format!("returns_{index:04}.wdp"),
        )
    } else {
        ("returns.las".into(), "returns.wdp".into())
    }
}

impl LasWaveSink {
    /// Starts writing the returns into `dir` (which must exist): opens the first file.
    pub fn create(dir: &Path, options: LasWaveOptions) -> Result<Self, SinkError> {
        let (first_name, _) = file_names(options.rotate_s > 0.0, 0);
        let las_path = dir.join(first_name);
        if options.point_format != 6 && options.point_format != 9 {
            return Err(las_err(
                &las_path,
                LasWriteError::Unrepresentable(format!(
                    "point data record format {} (6 or 9 are written)",
                    options.point_format
                )),
            ));
        }
        let mut fixed_vlrs = Vec::new();
        let mut fixed_vlr_count = 0;
        if let Some(wkt) = &options.crs_wkt {
            fixed_vlrs.extend(lw::wkt_vlr(wkt).map_err(|e| las_err(&las_path, e))?);
            fixed_vlr_count += 1;
        }
        let dims: Vec<ExtraDim> = if options.extra_bytes {
            return_extra_dims().to_vec()
        } else {
            Vec::new()
        };
        if !dims.is_empty() {
            fixed_vlrs.extend(
                lw::extra_bytes_vlr(&dims, "fwlidar return attributes")
                    .map_err(|e| las_err(&las_path, e))?,
            );
            fixed_vlr_count += 1;
        }
        let core = if options.point_format == 9 {
            PF9_SIZE
        } else {
            PF6_SIZE
        };
        let record_len = core + lw::extra_bytes_len(&dims);
        let mut sink = LasWaveSink {
            dir: dir.to_path_buf(),
            report: LasWaveReport {
                point_format: options.point_format,
                ..Default::default()
            },
            options,
            dims,
            fixed_vlrs,
            fixed_vlr_count,
            record_len,
            file: None,
            file_index: 0,
            finished: false,
            order: Vec::with_capacity(64),
            packet_of_segment: Vec::with_capacity(8),
            record: vec![0u8; record_len],
            samples: Vec::with_capacity(1 << 13),
            preamble: Vec::new(),
        };
        sink.open_file()?;
        Ok(sink)
    }

    /// What has been written and skipped so far.
    pub fn stats(&self) -> &LasWaveReport {
        &self.report
    }

    fn waveforms(&self) -> bool {
        self.options.point_format == 9
    }

    /// Bytes from the start of a LAS file to its first point record.
    pub fn offset_to_points(&self) -> u64 {
        let room = if self.waveforms() { DESCRIPTOR_ROOM } else { 0 };
        (HEADER_SIZE + self.fixed_vlrs.len() + room) as u64
    }

    /// Opens file `self.file_index` with its provisional header and VLRs (and the `.wdp` with a
    /// provisional record header).
    fn open_file(&mut self) -> Result<(), SinkError> {
        let (las_name, wdp_name) = file_names(self.options.rotate_s > 0.0, self.file_index);
        let las_path = self.dir.join(las_name);
        let wdp_path = self.dir.join(wdp_name);
        let las = AtomicFile::create(&las_path)?;
        let wdp = if self.waveforms() {
            let mut w = AtomicFile::create(&wdp_path)?;
            let evlr = lw::evlr_header(
                lw::LASF_SPEC,
                lw::WAVEFORM_DATA_RECORD_ID,
                0,
                "fwlidar raw waveform packets",
            );
            w.writer()?
                .write_all(&evlr)
                .map_err(|e| io_err(&wdp_path, e))?;
            Some(w)
        } else {
            None
        };
        self.file = Some(OpenFile {
            las,
            wdp,
            las_path,
            wdp_path,
            start_gps: f64::NAN,
            flushed_gps: f64::NAN,
            descriptors: Vec::with_capacity(if self.waveforms() { MAX_DESCRIPTORS } else { 0 }),
            last_descriptor: 0,
            offset: None,
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            by_return: [0; MAX_RETURNS],
            points: 0,
            wdp_pos: EVLR_HEADER_SIZE as u64,
            evlr_start: None,
        });
        self.build_preamble()?;
        let f = self.file.as_mut().expect("just opened");
        f.las
            .writer()?
            .write_all(&self.preamble)
            .map_err(|e| io_err(&f.las_path, e))
    }

    /// Rewrites the open file's header and VLRs in place (they changed), then goes on at its
    /// end. The seek hands the buffered points to the OS first, and the second one the new
    /// preamble, so the OS always holds a preamble that matches the points after it.
    fn rewrite_preamble(&mut self) -> Result<(), SinkError> {
        self.build_preamble()?;
        let f = self.file.as_mut().expect("a file is open");
        let w = f.las.writer()?;
        w.seek(SeekFrom::Start(0))
            .and_then(|_| w.write_all(&self.preamble))
            .and_then(|_| w.seek(SeekFrom::End(0)))
            .map(|_| ())
            .map_err(|e| io_err(&f.las_path, e))
    }

    /// Index (1..=255) of the descriptor for `key`, made on first use (the preamble is then
    /// rewritten so the file on disk declares it before any point uses it).
    fn descriptor(&mut self, key: DescKey, d: WavePacketDescriptor) -> Result<u8, SinkError> {
        let f = self.file.as_mut().expect("a file is open");
        if f.descriptors.get(f.last_descriptor).map(|e| e.0) == Some(key) {
            return Ok(f.last_descriptor as u8 + 1);
        }
        let i = match f.descriptors.iter().position(|e| e.0 == key) {
            Some(i) => i,
            None => {
                if f.descriptors.len() == MAX_DESCRIPTORS {
                    return Err(las_err(&f.las_path, LasWriteError::TooManyDescriptors));
                }
                f.descriptors.push((key, d));
                let i = f.descriptors.len() - 1;
                f.last_descriptor = i;
                self.report.descriptors = self.report.descriptors.max(i as u64 + 1);
                self.rewrite_preamble()?;
                return Ok(i as u8 + 1);
            }
        };
        f.last_descriptor = i;
        Ok(i as u8 + 1)
    }

    /// Writes segment `s` of `p` as a waveform packet: (descriptor index, offset, size).
    fn write_packet(&mut self, p: &Pulse, s: usize) -> Result<(u8, u64, u32), SinkError> {
        let raw = p.raw_of(s);
        let bits: u8 = if p.bits <= 8 { 8 } else { 16 };
        let spacing = (p.sample_ns * 1000.0).round();
        if !(spacing >= 1.0 && spacing <= f64::from(u32::MAX)) {
            let f = self.file.as_ref().expect("a file is open");
            return Err(las_err(
                &f.las_path,
                LasWriteError::Unrepresentable(format!(
                    "sample interval {} ns is not a whole number of picoseconds in 1..2^32",
                    p.sample_ns
                )),
            ));
        }
        let n = u32::try_from(raw.len()).unwrap_or(u32::MAX);
        let d = WavePacketDescriptor {
            bits_per_sample: bits,
            compression: 0,
            number_of_samples: n,
            temporal_spacing_ps: spacing as u32,
            digitizer_gain: f64::from(p.gain_v_per_dn),
            digitizer_offset: f64::from(p.offset_v),
        };
        let key = (
            bits,
            n,
            spacing as u32,
            p.gain_v_per_dn.to_bits(),
            p.offset_v.to_bits(),
        );
        let index = self.descriptor(key, d)?;
        self.samples.clear();
        if bits == 8 {
            self.samples
                .extend(raw.iter().map(|&c| c.min(u16::from(u8::MAX)) as u8));
        } else {
            for c in raw {
                self.samples.extend_from_slice(&c.to_le_bytes());
            }
        }
        let size = self.samples.len() as u32;
        let f = self.file.as_mut().expect("a file is open");
        let wdp = f.wdp.as_mut().expect("format 9 has a .wdp");
        wdp.writer()?
            .write_all(&self.samples)
            .map_err(|e| io_err(&f.wdp_path, e))?;
        let at = f.wdp_pos;
        f.wdp_pos += u64::from(size);
        self.report.packets += 1;
        self.report.wdp_bytes += u64::from(size);
        Ok((index, at, size))
    }

    /// Intensity of a return of amplitude `amplitude_v` (`docs/formats.md`): the amplitude in
    /// counts, at most the digitizer's full scale (`2^bits − 1`; counted when above it), times
    /// `2^(16 − bits)`: the digitizer's range spread over 16 bits, never past it.
    fn intensity(&mut self, p: &Pulse, amplitude_v: f32) -> u16 {
        let gain = f64::from(p.gain_v_per_dn);
        let amp = f64::from(amplitude_v);
        if !(gain > 0.0 && gain.is_finite() && amp.is_finite()) {
            return 0;
        }
        let bits = p.bits.clamp(1, 16);
        let full_scale = f64::from((1u32 << bits) - 1);
        let mut counts = amp / gain;
        if counts > full_scale {
            self.report.intensity_at_full_scale += 1;
            counts = full_scale;
        }
        let v = (counts * f64::from(1u32 << (16 - bits))).round();
        if v > 0.0 { v.min(65535.0) as u16 } else { 0 }
    }

    fn write_points(&mut self, p: &Pulse, g: &PulseGeometry) -> Result<u64, SinkError> {
        self.order.clear();
        self.order
            .extend(0..p.returns.len().min(u16::MAX as usize) as u16);
        self.order.sort_unstable_by(|&a, &b| {
            p.returns[a as usize]
                .time_ns
                .total_cmp(&p.returns[b as usize].time_ns)
        });
        self.packet_of_segment.clear();
        self.packet_of_segment.resize(p.segments.len(), None);
        let n_returns = self.order.len().min(MAX_RETURNS) as u8;
        let scan_angle = {
            let a = f64::from(p.scan_angle_deg[0]) / 0.006;
            if a.is_finite() {
                a.round().clamp(-30000.0, 30000.0) as i16
            } else {
                0
            }
        };
        let xyz_t = g.direction.map(|d| (-d / 1000.0) as f32);
        let waveforms = self.waveforms();
        let core = if waveforms { PF9_SIZE } else { PF6_SIZE };
        let mut written = 0;
        for rank in 0..self.order.len() {
            let r = p.returns[self.order[rank] as usize];
            let s = r.segment as usize;
            let pos: [f64; 3] = std::array::from_fn(|k| g.anchor[k] + r.time_ns * g.direction[k]);
            if s >= p.segments.len() || pos.iter().any(|v| !v.is_finite()) {
                self.report.returns_unrepresentable += 1;
                continue;
            }
            let f = self.file.as_mut().expect("a file is open");
            let offset = match f.offset {
                Some(o) => o,
                None => {
                    let o = pos.map(|v| (v / OFFSET_STEP).floor() * OFFSET_STEP);
                    f.offset = Some(o);
                    // The offset is part of the header: on disk before the first point.
                    self.rewrite_preamble()?;
                    o
                }
            };
            let scaled =
                std::array::from_fn::<f64, 3, _>(|k| ((pos[k] - offset[k]) / SCALE).round());
            if scaled
                .iter()
                .any(|v| *v < f64::from(i32::MIN) || *v > f64::from(i32::MAX))
            {
                self.report.returns_unrepresentable += 1;
                continue;
            }
            let xyz = scaled.map(|v| v as i32);
            let seg = p.segments[s];
            let return_number = (rank + 1).min(MAX_RETURNS) as u8;
            if rank >= MAX_RETURNS {
                self.report.returns_beyond_15 += 1;
            }
            let point = PointRecord6 {
                xyz,
                intensity: self.intensity(p, r.amplitude),
                return_number,
                number_of_returns: n_returns,
                scanner_channel: seg.channel.min(3),
                classification: 0,
                scan_angle,
                gps_time: p.gps_time,
            };
            if waveforms {
                let (index, at, size) = match self.packet_of_segment[s] {
                    Some(packet) => packet,
                    None => {
                        let packet = self.write_packet(p, s)?;
                        self.packet_of_segment[s] = Some(packet);
                        packet
                    }
                };
                PointRecord9 {
                    core: point,
                    wave_packet_index: index,
                    wave_offset: at,
                    wave_size: size,
                    wave_location_ps: ((r.time_ns - seg.start_ns) * 1000.0) as f32,
                    xyz_t,
                }
                .encode_into(&mut self.record);
            } else {
                point.encode_into(&mut self.record);
            }
            if !self.dims.is_empty() {
                let width_ns = f64::from(r.sigma_bins) * p.sample_ns * FWHM_PER_SIGMA;
                let values = [
                    f64::from(r.amplitude),
                    width_ns,
                    f64::from(r.backscatter),
                    f64::from(r.residual),
                ];
                lw::encode_extras(&self.dims, &values, &mut self.record[core..]);
            }
            let f = self.file.as_mut().expect("a file is open");
            f.las
                .writer()?
                .write_all(&self.record)
                .map_err(|e| io_err(&f.las_path, e))?;
            for (k, v) in xyz.into_iter().enumerate() {
                f.min[k] = f.min[k].min(v);
                f.max[k] = f.max[k].max(v);
            }
            f.by_return[return_number as usize - 1] += 1;
            f.points += 1;
            self.report.points += 1;
            written += 1;
        }
        Ok(written)
    }

    /// The open file's header as it stands.
    fn header(&self) -> Header {
        let f = self.file.as_ref().expect("a file is open");
        let n = f.points;
        let offset = f.offset.unwrap_or([0.0; 3]);
        let bound = |v: &[i32; 3]| -> [f64; 3] {
            if n == 0 {
                [0.0; 3]
            } else {
                std::array::from_fn(|k| offset[k] + f64::from(v[k]) * SCALE)
            }
        };
        let (year, day) = lw::year_and_day(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
        );
        let mut global = lw::GLOBAL_WKT;
        if self.waveforms() {
            global |= lw::GLOBAL_WAVEFORM_EXTERNAL;
        }
        if self.options.adjusted_standard_gps_time {
            global |= lw::GLOBAL_ADJUSTED_STANDARD_GPS;
        }
        let descriptor_vlrs = if self.waveforms() {
            f.descriptors.len() as u32 + u32::from(f.descriptors.len() < MAX_DESCRIPTORS)
        } else {
            0
        };
        Header {
            global_encoding: global,
            system_identifier: "fwlidar waveform decomposition".into(),
            generating_software: concat!("fwlidar ", env!("CARGO_PKG_VERSION")).into(),
            creation_day_of_year: day,
            creation_year: year,
            offset_to_point_data: self.offset_to_points() as u32,
            number_of_vlrs: self.fixed_vlr_count + descriptor_vlrs,
            point_format: self.options.point_format,
            point_record_length: self.record_len as u16,
            scale: [SCALE; 3],
            offset,
            max: bound(&f.max),
            min: bound(&f.min),
            start_of_waveform_data: 0,
            start_of_first_evlr: f.evlr_start.unwrap_or(0),
            number_of_evlrs: u32::from(f.evlr_start.is_some()),
            number_of_points: n,
            points_by_return: f.by_return,
        }
    }

    /// Header and VLRs of the open file into `self.preamble`, exactly `offset_to_points` bytes.
    fn build_preamble(&mut self) -> Result<(), SinkError> {
        let header = self.header().encode();
        let f = self.file.as_ref().expect("a file is open");
        let b = &mut self.preamble;
        b.clear();
        b.extend_from_slice(&header);
        b.extend_from_slice(&self.fixed_vlrs);
        if self.options.point_format == 9 {
            let path = &f.las_path;
            for (i, (_, d)) in f.descriptors.iter().enumerate() {
                let id = lw::DESCRIPTOR_RECORD_ID_BASE + 1 + i as u16;
                b.extend_from_slice(
                    &lw::vlr_header(
                        lw::LASF_SPEC,
                        id,
                        DESCRIPTOR_SIZE,
                        "waveform packet descriptor",
                    )
                    .map_err(|e| las_err(path, e))?,
                );
                b.extend_from_slice(&d.encode());
            }
            let room =
                (MAX_DESCRIPTORS - f.descriptors.len()) * (VLR_HEADER_SIZE + DESCRIPTOR_SIZE);
            if room > 0 {
                let payload = room - VLR_HEADER_SIZE;
                b.extend_from_slice(
                    &lw::vlr_header(
                        PADDING_USER_ID,
                        PADDING_RECORD_ID,
                        payload,
                        "unused descriptor room",
                    )
                    .map_err(|e| las_err(path, e))?,
                );
                b.resize(b.len() + payload, 0);
            }
        }
        debug_assert_eq!(b.len() as u64, self.offset_to_points());
        Ok(())
    }

    /// Completes the open file: final header, the `.wdp`'s record header, both renamed into
    /// place (the `.wdp` first).
    fn close_file(&mut self) -> Result<(), SinkError> {
        if self.file.is_none() {
            return Ok(());
        }
        self.append_decided_crs()?;
        self.build_preamble()?;
        let mut f = self.file.take().expect("checked");
        if let Some(wdp) = f.wdp.as_mut() {
            let evlr = lw::evlr_header(
                lw::LASF_SPEC,
                lw::WAVEFORM_DATA_RECORD_ID,
                f.wdp_pos - EVLR_HEADER_SIZE as u64,
                "fwlidar raw waveform packets",
            );
            let w = wdp.writer()?;
            w.seek(SeekFrom::Start(0))
                .and_then(|_| w.write_all(&evlr))
                .map_err(|e| io_err(&f.wdp_path, e))?;
            self.report.wdp_bytes += EVLR_HEADER_SIZE as u64;
            wdp.commit()?;
        }
        let w = f.las.writer()?;
        w.seek(SeekFrom::Start(0))
            .and_then(|_| w.write_all(&self.preamble))
            .map_err(|e| io_err(&f.las_path, e))?;
        f.las.commit()?;
        let name = f
            .las_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        tracing::debug!(file = %name, points = f.points, "LAS file complete");
        self.report.files.push(name);
        self.file_index += 1;
        Ok(())
    }

    /// Appends the CRS decided during the run as the WKT EVLR after the open file's points
    /// (only when no CRS VLR was written at its start).
    fn append_decided_crs(&mut self) -> Result<(), SinkError> {
        if self.options.crs_wkt.is_some() {
            return Ok(());
        }
        let Some(crs) = self
            .options
            .crs_decided
            .as_ref()
            .and_then(|c| c.get())
            .cloned()
        else {
            return Ok(());
        };
        let f = self.file.as_mut().expect("a file is open");
        if !crs.starts_with("PROJCS[") && !crs.starts_with("GEOGCS[") {
            tracing::warn!(
                file = %f.las_path.display(),
                crs = %crs,
                "no WKT for the output CRS: the LAS file states no CRS"
            );
            return Ok(());
        }
        let mut evlr = lw::evlr_header(
            lw::LASF_PROJECTION,
            lw::WKT_RECORD_ID,
            crs.len() as u64 + 1,
            "OGC WKT CRS",
        )
        .to_vec();
        evlr.extend_from_slice(crs.as_bytes());
        evlr.push(0);
        let start = HEADER_SIZE as u64
            + self.fixed_vlrs.len() as u64
            + if self.options.point_format == 9 {
                DESCRIPTOR_ROOM as u64
            } else {
                0
            }
            + f.points * self.record_len as u64;
        let path = f.las_path.clone();
        f.las
            .writer()?
            .write_all(&evlr)
            .map_err(|e| io_err(&path, e))?;
        f.evlr_start = Some(start);
        Ok(())
    }

    /// Removes `returns_NNNN.las` / `.wdp` left by an earlier run from `NNNN` = the number of
    /// files this run wrote on (a shorter run must not leave an older run's tail beside it).
    fn remove_stale_rotated_files(&self) {
        if self.options.rotate_s <= 0.0 {
            return;
        }
        let mut k = self.file_index;
        loop {
            let (las, wdp) = file_names(true, k);
            let (las, wdp) = (self.dir.join(las), self.dir.join(wdp));
            let found = las.exists() || wdp.exists();
            if !found {
                break;
            }
            for p in [las, wdp] {
                if p.exists()
                    && let Err(e) = std::fs::remove_file(&p)
                {
                    tracing::warn!(file = %p.display(), "cannot remove a stale LAS file: {e}");
                }
            }
            k += 1;
        }
    }

    /// Closes the open file and opens the next when `gps_time` lies past its window.
    fn rotate_if_due(&mut self, gps_time: f64) -> Result<(), SinkError> {
        let rotate = self.options.rotate_s;
        if rotate <= 0.0 {
            return Ok(());
        }
        let start = self.file.as_ref().map_or(f64::NAN, |f| f.start_gps);
        if start.is_nan() || !(gps_time >= start + rotate || gps_time < start) {
            return Ok(());
        }
        self.close_file()?;
        self.open_file()
    }

    /// Hands the open file's buffers to the OS (the `.wdp` first).
    fn flush_open(&mut self) -> Result<(), SinkError> {
        if let Some(f) = self.file.as_mut() {
            if let Some(w) = f.wdp.as_mut() {
                w.flush()?;
            }
            f.las.flush()?;
        }
        Ok(())
    }
}

impl PulseSink for LasWaveSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "las"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        if p.returns.is_empty() {
            self.report.pulses_without_returns += 1;
            return Ok(());
        }
        let Some(g) = p.geometry else {
            self.report.pulses_without_geometry += 1;
            return Ok(());
        };
        if self.finished {
            return Err(io_err(
                &self.dir.join("returns.las"),
                std::io::Error::other("the LAS output is already finished"),
            ));
        }
        self.rotate_if_due(p.gps_time)?;
        let f = self.file.as_mut().expect("a file is open");
        if f.start_gps.is_nan() {
            f.start_gps = p.gps_time;
            f.flushed_gps = p.gps_time;
        }
        // Counts are kept per point, so the header matches the file even when a later return
        // of the pulse fails (e.g. a 256th descriptor) and the run ends there.
        let n = self.write_points(p, &g)?;
        self.report.pulses_written += u64::from(n > 0);
        let f = self.file.as_mut().expect("a file is open");
        let every = self.options.flush_s;
        let elapsed = p.gps_time - f.flushed_gps;
        // Also when time went backwards (or is NaN): a new time base, flush now.
        if every > 0.0 && (elapsed >= every || elapsed < 0.0 || elapsed.is_nan()) {
            f.flushed_gps = p.gps_time;
            self.flush_open()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        self.flush_open()
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        if self.finished {
            return Ok(());
        }
        self.close_file()?;
        self.remove_stale_rotated_files();
        self.finished = true;
        tracing::debug!(
            points = self.report.points,
            files = self.report.files.len(),
            packets = self.report.packets,
            pulses_without_geometry = self.report.pulses_without_geometry,
            "LAS returns written"
        );
        Ok(())
    }

    fn report(&self) -> SinkReport {
        SinkReport::Las(self.report.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::{FittedReturn, SegmentKind};

    /// A pulse with an outgoing segment, return segment 1 (20 samples from 100 ns) and return
    /// segment 2 (10 samples from 300 ns), looking straight down from (500 100.5, 4 200 000.25,
    /// 1000) at 0.15 m/ns.
    fn pulse(id: u64, gain: f32, geometry: bool, returns: &[(u16, f64, f32)]) -> Pulse {
        let mut p = Pulse {
            pulse_id: id,
            gps_time: 1000.0 + id as f64,
            gain_v_per_dn: gain,
            offset_v: -0.25,
            bits: 16,
            sample_ns: 1.0,
            scan_angle_deg: [-3.0, f32::NAN],
            geometry: geometry.then_some(PulseGeometry {
                anchor: [500_100.5, 4_200_000.25, 1000.0],
                direction: [0.0, 0.0, -0.15],
            }),
            ..Default::default()
        };
        p.push_segment(SegmentKind::Outgoing, 0, -5.0, (0..10).map(|i| i * 100));
        p.push_segment(SegmentKind::Return, 1, 100.0, (0..20).map(|i| 1000 + i));
        p.push_segment(SegmentKind::Return, 1, 300.0, (0..10).map(|i| 2000 + i));
        for &(segment, time_ns, amplitude) in returns {
            let start = p.segments[segment as usize].start_ns;
            p.returns.push(FittedReturn {
                segment,
                position_bins: (time_ns - start) as f32,
                time_ns,
                amplitude,
                sigma_bins: 2.0,
                residual: 0.0,
                backscatter: f32::NAN,
            });
        }
        p
    }

    fn pf9() -> LasWaveOptions {
        LasWaveOptions {
            point_format: 9,
            ..Default::default()
        }
    }

    fn u16_at(b: &[u8], o: usize) -> u16 {
        u16::from_le_bytes(b[o..o + 2].try_into().unwrap())
    }
    fn u32_at(b: &[u8], o: usize) -> u32 {
        u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
    }
    fn u64_at(b: &[u8], o: usize) -> u64 {
        u64::from_le_bytes(b[o..o + 8].try_into().unwrap())
    }
    fn f64_at(b: &[u8], o: usize) -> f64 {
        f64::from_le_bytes(b[o..o + 8].try_into().unwrap())
    }
    fn f32_at(b: &[u8], o: usize) -> f32 {
        f32::from_le_bytes(b[o..o + 4].try_into().unwrap())
    }

    /// (user id, record id, payload) of every VLR, walking from the header to the points.
    fn vlrs(b: &[u8]) -> Vec<(String, u16, Vec<u8>)> {
        let mut at = HEADER_SIZE;
        let mut out = Vec::new();
        for _ in 0..u32_at(b, 100) {
            let user = String::from_utf8_lossy(&b[at + 2..at + 18])
                .trim_end_matches('\0')
                .to_string();
            let id = u16_at(b, at + 18);
            let len = u16_at(b, at + 20) as usize;
            out.push((user, id, b[at + 54..at + 54 + len].to_vec()));
            at += 54 + len;
        }
        assert_eq!(
            at,
            u32_at(b, 96) as usize,
            "VLRs end where the points start"
        );
        out
    }

    #[test]
    fn header_records_descriptors_and_packets_agree() {
        let dir = tempfile::tempdir().unwrap();
        let wkt = "PROJCS[\"WGS 84 / UTM zone 33N\"]".to_string();
        let mut sink = LasWaveSink::create(
            dir.path(),
            LasWaveOptions {
                crs_wkt: Some(wkt.clone()),
                ..pf9()
            },
        )
        .unwrap();
        // Returns given out of time order: numbering follows time.
        sink.write(&pulse(
            0,
            0.5,
            true,
            &[(2, 305.0, 2.0), (1, 110.0, 1.0), (1, 112.5, 0.5)],
        ))
        .unwrap();
        sink.write(&pulse(1, 0.5, false, &[(1, 110.0, 1.0)]))
            .unwrap();
        sink.write(&pulse(2, 0.5, true, &[])).unwrap();
        sink.write(&pulse(3, 0.25, true, &[(1, 101.0, 40_000.0)]))
            .unwrap();
        assert!(
            !dir.path().join("returns.las").exists(),
            "appears at finish"
        );
        sink.finish().unwrap();
        sink.finish().unwrap();
        let r = sink.stats().clone();
        assert_eq!(
            r,
            LasWaveReport {
                points: 4,
                pulses_written: 2,
                pulses_without_geometry: 1,
                pulses_without_returns: 1,
                returns_unrepresentable: 0,
                returns_beyond_15: 0,
                intensity_at_full_scale: 1,
                packets: 3,
                wdp_bytes: 60 + 2 * 20 + 2 * 10 + 2 * 20,
                descriptors: 3,
                point_format: 9,
                files: vec!["returns.las".into()],
            }
        );

        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(&b[0..4], b"LASF");
        assert_eq!((b[24], b[25]), (1, 4));
        assert_eq!(
            u16_at(&b, 6),
            (1 << 2) | (1 << 4),
            "external waveforms, WKT"
        );
        assert_eq!(u16_at(&b, 94), 375);
        assert_eq!(b[104], 9);
        assert_eq!(u16_at(&b, 105), 75, "59 bytes of format 9 + 16 extra bytes");
        assert_eq!(u64_at(&b, 247), 4);
        assert_eq!(
            (u64_at(&b, 255), u64_at(&b, 263), u64_at(&b, 271)),
            (2, 1, 1)
        );
        assert_eq!(u64_at(&b, 227), 0, "waveforms are external");
        assert_eq!(f64_at(&b, 131), 0.001);
        assert_eq!(
            (f64_at(&b, 155), f64_at(&b, 163), f64_at(&b, 171)),
            (500_000.0, 4_200_000.0, 0.0)
        );
        let offset = u32_at(&b, 96) as usize;
        assert_eq!(offset as u64, sink.offset_to_points());
        assert_eq!(b.len(), offset + 4 * 75);

        let v = vlrs(&b);
        assert_eq!(v[0].0, "LASF_Projection");
        assert_eq!(v[0].1, 2112);
        assert_eq!(v[0].2, [wkt.as_bytes(), b"\0"].concat());
        assert_eq!(
            (v[1].0.as_str(), v[1].1, v[1].2.len()),
            ("LASF_Spec", 4, 768)
        );
        let ids: Vec<u16> = v[2..5].iter().map(|x| x.1).collect();
        assert_eq!(ids, [100, 101, 102]);
        // Descriptor 1: segment 1 of a gain-0.5 pulse (the first packet written).
        let d1 = &v[2].2;
        assert_eq!(
            (d1[0], d1[1], u32_at(d1, 2), u32_at(d1, 6)),
            (16, 0, 20, 1000)
        );
        assert_eq!((f64_at(d1, 10), f64_at(d1, 18)), (0.5, -0.25));
        assert_eq!(
            u32_at(&v[3].2, 2),
            10,
            "descriptor 2: the 10-sample segment"
        );
        assert_eq!(f64_at(&v[4].2, 10), 0.25, "descriptor 3: other gain");
        assert_eq!(v[5].0, "fwlidar", "padding fills the rest of the room");
        assert_eq!(v.len(), 6);

        // Points: time order within the pulse.
        let pt = |i: usize| &b[offset + 75 * i..offset + 75 * (i + 1)];
        let z = |i: usize| u32_at(pt(i), 8) as i32;
        assert_eq!(
            z(0),
            (1000.0f64 - 110.0 * 0.15).mul_add(1000.0, 0.0).round() as i32
        );
        assert_eq!(pt(0)[14], 0x31, "return 1 of 3");
        assert_eq!(pt(1)[14], 0x32);
        assert_eq!(pt(2)[14], 0x33);
        assert_eq!(pt(3)[14], 0x11);
        assert_eq!(u32_at(pt(0), 0) as i32, 100_500, "x - offset in mm");
        assert_eq!(u32_at(pt(0), 4) as i32, 250);
        assert_eq!(u16_at(pt(0), 18) as i16, -500, "-3° in 0.006° units");
        assert_eq!(f64_at(pt(0), 22), 1000.0);
        // Returns 1 and 2 share segment 1's packet; return 3 has segment 2's.
        let wave = |i: usize| (pt(i)[30], u64_at(pt(i), 31), u32_at(pt(i), 39));
        assert_eq!(wave(0), (1, 60, 40));
        assert_eq!(wave(1), (1, 60, 40));
        assert_eq!(wave(2), (2, 100, 20));
        assert_eq!(wave(3), (3, 120, 40));
        assert_eq!(
            f32_at(pt(1), 43),
            12_500.0,
            "ps from the segment's first sample"
        );
        assert_eq!(f32_at(pt(2), 43), 5_000.0);
        assert_eq!(
            (f32_at(pt(0), 47), f32_at(pt(0), 51), f32_at(pt(0), 55)),
            (0.0, 0.0, 0.15e-3),
            "-direction per ps"
        );
        // Intensity: 1 V / 0.5 V per count = 2 counts of a 16-bit digitizer; extra bytes.
        assert_eq!(u16_at(pt(0), 12), 2);
        assert_eq!(u16_at(pt(3), 12), 65535, "clipped");
        assert_eq!(f32_at(pt(0), 59), 1.0, "amplitude");
        assert_eq!(
            f32_at(pt(0), 63),
            (2.0 * FWHM_PER_SIGMA) as f32,
            "width: FWHM in ns"
        );
        assert_eq!(f32_at(pt(0), 67), -9999.0, "backscatter NaN: no-data");
        assert_eq!(f32_at(pt(0), 71), 0.0, "residual");
        // Bounds as stored.
        assert_eq!(f64_at(&b, 211), 1000.0 - 101.0 * 0.15, "max z");
        assert_eq!(f64_at(&b, 219), 1000.0 - 305.0 * 0.15, "min z");

        let w = std::fs::read(dir.path().join("returns.wdp")).unwrap();
        assert_eq!(w.len() as u64, r.wdp_bytes);
        assert_eq!(&w[2..11], b"LASF_Spec");
        assert_eq!(u16_at(&w, 18), 65535);
        assert_eq!(u64_at(&w, 20), w.len() as u64 - 60);
        assert_eq!(u16_at(&w, 60), 1000, "segment 1's raw counts");
        assert_eq!(u16_at(&w, 98), 1019);
        assert_eq!(u16_at(&w, 100), 2000);
    }

    #[test]
    fn without_extra_bytes_records_are_59_bytes_and_8_bit_samples_one_byte() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(
            dir.path(),
            LasWaveOptions {
                extra_bytes: false,
                ..pf9()
            },
        )
        .unwrap();
        let mut p = pulse(0, 0.5, true, &[(1, 110.0, 1.0)]);
        p.bits = 8;
        for c in &mut p.raw {
            *c %= 256;
        }
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(u16_at(&b, 105), 59);
        assert_eq!(u32_at(&b, 100), 2, "descriptor and padding");
        let offset = u32_at(&b, 96) as usize;
        assert_eq!(b.len(), offset + 59);
        assert_eq!(u16_at(&b, offset + 12), 512, "2 counts × 65536 / 256");
        assert_eq!(u32_at(&b, offset + 39), 20);
        let v = vlrs(&b);
        assert_eq!(v[0].2[0], 8);
        let w = std::fs::read(dir.path().join("returns.wdp")).unwrap();
        assert_eq!(&w[60..62], &[232, 233], "1000 % 256, 1001 % 256");
    }

    #[test]
    fn a_256th_descriptor_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), pf9()).unwrap();
        for i in 0..MAX_DESCRIPTORS {
            sink.write(&pulse(i as u64, 0.5 + i as f32, true, &[(1, 110.0, 1.0)]))
                .unwrap();
        }
        // A pulse whose first return reuses descriptor 1 (gain 0.5, segment 1) and whose second
        // needs a new one (segment 2's length): the first point stays in the file, counted.
        let e = sink
            .write(&pulse(999, 0.5, true, &[(1, 110.0, 1.0), (2, 305.0, 1.0)]))
            .unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("returns.las") && msg.contains("255"), "{msg}");
        sink.finish().unwrap();
        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(
            u32_at(&b, 100),
            256,
            "255 descriptors + extra bytes, no padding"
        );
        assert_eq!(vlrs(&b).last().unwrap().1, 99 + 255);
        assert_eq!(
            u64_at(&b, 247),
            256,
            "255 pulses + the first return of the failing one"
        );
        assert_eq!(b.len(), u32_at(&b, 96) as usize + 256 * 75);
        assert_eq!(sink.stats().points, 256);
    }

    #[test]
    fn unrepresentable_returns_are_skipped_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), pf9()).unwrap();
        sink.write(&pulse(0, 0.5, true, &[(1, 110.0, 1.0)]))
            .unwrap();
        let mut far = pulse(1, 0.5, true, &[(1, 110.0, 1.0), (1, 111.0, 1.0)]);
        far.geometry.as_mut().unwrap().anchor[0] = 1e10;
        sink.write(&far).unwrap();
        let mut nan = pulse(2, 0.5, true, &[(1, f64::NAN, 1.0)]);
        nan.returns[0].segment = 7;
        sink.write(&nan).unwrap();
        sink.finish().unwrap();
        assert_eq!(sink.stats().points, 1);
        assert_eq!(sink.stats().returns_unrepresentable, 3);
        assert_eq!(sink.stats().packets, 1);
    }

    #[test]
    fn a_missing_folder_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope");
        let Err(e) = LasWaveSink::create(&missing, pf9()) else {
            panic!("created in a missing folder");
        };
        assert!(e.to_string().contains("nope/returns.las"), "{e}");
        let Err(e) = LasWaveSink::create(
            dir.path(),
            LasWaveOptions {
                crs_wkt: Some("bad\0wkt".into()),
                ..pf9()
            },
        ) else {
            panic!("accepted a NUL in the WKT");
        };
        assert!(e.to_string().contains("returns.las") && e.to_string().contains("NUL"));
    }

    #[test]
    fn empty_run_gives_a_valid_empty_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), pf9()).unwrap();
        sink.finish().unwrap();
        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(u64_at(&b, 247), 0);
        assert_eq!(b.len(), u32_at(&b, 96) as usize);
        assert_eq!(vlrs(&b).len(), 2);
        let w = std::fs::read(dir.path().join("returns.wdp")).unwrap();
        assert_eq!((w.len(), u64_at(&w, 20)), (60, 0));
    }

    #[test]
    fn format_6_records_are_30_bytes_plus_extras_and_no_wdp() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), LasWaveOptions::default()).unwrap();
        let mut p = pulse(0, 0.5, true, &[(2, 305.0, 2.0), (1, 110.0, 1.0)]);
        p.returns[0].backscatter = 0.125;
        p.returns[0].residual = 0.5;
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        assert!(!dir.path().join("returns.wdp").exists());
        assert!(!dir.path().join("returns.wdp.partial").exists());
        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(b[104], 6);
        assert_eq!(u16_at(&b, 105), 46);
        assert_eq!(u16_at(&b, 6), 1 << 4, "WKT bit only");
        assert_eq!(u32_at(&b, 100), 1, "the Extra Bytes VLR");
        let offset = u32_at(&b, 96) as usize;
        assert_eq!(offset, 375 + 54 + 768);
        assert_eq!(b.len(), offset + 2 * 46);
        let pt = |i: usize| &b[offset + 46 * i..offset + 46 * (i + 1)];
        assert_eq!(pt(0)[14], 0x21);
        assert_eq!(pt(1)[14], 0x22);
        assert_eq!(f64_at(pt(1), 22), 1000.0);
        assert_eq!(f32_at(pt(1), 30), 2.0, "amplitude of the later return");
        assert_eq!(f32_at(pt(1), 38), 0.125, "backscatter");
        assert_eq!(f32_at(pt(1), 42), 0.5, "residual");
        assert_eq!(f32_at(pt(0), 38), -9999.0, "no-data");
        let v = vlrs(&b);
        let d = &v[0].2;
        let names: Vec<&[u8]> = (0..4).map(|k| &d[192 * k + 4..192 * k + 15]).collect();
        assert_eq!(&names[2][..11], b"backscatter");
        assert_eq!((d[192 * 2 + 2], d[192 * 2 + 3]), (9, 1), "f32, no_data bit");
        assert_eq!(f64_at(d, 192 * 2 + 40), -9999.0);
        assert_eq!((d[2], d[3]), (9, 0), "amplitude: f32, no options");
    }

    #[test]
    fn rotation_completes_each_file_before_the_next_and_removes_stale_ones() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("returns_0003.las"), b"stale").unwrap();
        std::fs::write(dir.path().join("returns_0004.wdp"), b"stale").unwrap();
        let mut sink = LasWaveSink::create(
            dir.path(),
            LasWaveOptions {
                rotate_s: 2.0,
                point_format: 9,
                ..Default::default()
            },
        )
        .unwrap();
        // gps_time = 1000 + id: files [1000, 1002), [1002, 1004), [1004, ...).
        for id in 0..5 {
            sink.write(&pulse(id, 0.5, true, &[(1, 110.0, 1.0)]))
                .unwrap();
            if id == 2 {
                assert!(dir.path().join("returns_0000.las").exists());
                assert!(dir.path().join("returns_0000.wdp").exists());
                assert!(dir.path().join("returns_0001.las.partial").exists());
            }
        }
        sink.finish().unwrap();
        assert_eq!(
            sink.stats().files,
            ["returns_0000.las", "returns_0001.las", "returns_0002.las"]
        );
        assert!(
            !dir.path().join("returns_0003.las").exists(),
            "stale file removed"
        );
        assert!(
            !dir.path().join("returns_0004.wdp").exists(),
            "stale file removed"
        );
        for (k, n) in [(0, 2), (1, 2), (2, 1)] {
            let b = std::fs::read(dir.path().join(format!("returns_{k:04}.las"))).unwrap();
            assert_eq!(u64_at(&b, 247), n);
            let w = std::fs::read(dir.path().join(format!("returns_{k:04}.wdp"))).unwrap();
            assert_eq!(
                u64_at(&w, 20),
                40 * n,
                "one 20-sample 16-bit packet per pulse"
            );
            let offset = u32_at(&b, 96) as usize;
            assert_eq!(
                u64_at(&b[offset..], 31),
                60,
                "packets count from each file's .wdp"
            );
        }
    }

    #[test]
    fn the_open_file_always_has_a_valid_provisional_header() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), pf9()).unwrap();
        sink.flush().unwrap();
        let partial = dir.path().join("returns.las.partial");
        let b = std::fs::read(&partial).unwrap();
        assert_eq!(&b[0..4], b"LASF");
        assert_eq!(b.len() as u64, sink.offset_to_points(), "preamble at open");
        assert_eq!(u64_at(&b, 247), 0);
        sink.write(&pulse(0, 0.5, true, &[(1, 110.0, 1.0)]))
            .unwrap();
        sink.write(&pulse(1, 0.5, true, &[(2, 305.0, 1.0)]))
            .unwrap();
        sink.flush().unwrap();
        let b = std::fs::read(&partial).unwrap();
        assert_eq!(
            f64_at(&b, 155),
            500_000.0,
            "offset on disk with the first point"
        );
        assert_eq!(b.len() as u64, sink.offset_to_points() + 2 * 75);
        let v = vlrs(&b);
        assert_eq!((v[1].1, v[2].1), (100, 101), "both descriptors on disk");
        let w = std::fs::read(dir.path().join("returns.wdp.partial")).unwrap();
        assert_eq!(u16_at(&w, 18), 65535, "provisional waveform record header");
        sink.finish().unwrap();
    }
}
