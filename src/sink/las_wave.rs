//! Discrete returns as a LAS 1.4 file of point data record format 9, with the waveforms they
//! came from in an external waveform data packet file: `returns.las` + `returns.wdp`.
//!
//! - One point per fitted return ([`Pulse::returns`]) of every pulse that has a
//!   [`PulseGeometry`]; its position is `anchor + time_ns · direction` (CRS units), stored with
//!   scale [`SCALE`] and an offset taken from the first point (multiples of 1000 CRS units).
//! - One waveform packet per (pulse, return segment that has at least one return): the segment's
//!   **raw digitizer counts**, 8-bit when the pulse's `bits` ≤ 8, else 16-bit little-endian, so
//!   the file holds what the sensor recorded; the packet's descriptor carries the pulse's gain and
//!   offset (`volts = offset + gain · count`) and the sample interval in picoseconds.
//!   Descriptors (VLR `LASF_Spec` / 99 + index) are made on demand per distinct (bits, samples,
//!   sample interval, gain, offset), at most 255; a 256th is an error.
//! - The parametric line: for a point P with return point waveform location L (ps from the
//!   packet's first sample to the return), `(x_t, y_t, z_t) = −direction / 1000` (CRS units per
//!   ps), so the first sample lies at `P + L · (x_t, y_t, z_t)` and sample `i` at
//!   `P + (L − i · spacing_ps) · (x_t, y_t, z_t)`.
//! - Intensity: the Gaussian's amplitude in digitizer counts (`amplitude / gain`), normalised to
//!   16 bits as LAS asks (`× 65536 / 2^bits`), rounded, clipped to 0..=65535 (clips counted).
//! - With [`LasWaveOptions::extra_bytes`]: two extra f32 per point, `amplitude_v` (V) and
//!   `sigma_ns` (ns), declared in an Extra Bytes VLR.
//!
//! Pulses without geometry or without returns write nothing and are counted
//! ([`LasWaveReport`]). Points stream through a buffered writer; the header and the VLRs are
//! written at [`PulseSink::finish`] by seeking back into a region reserved for them (the unused
//! part of the descriptor room is one padding VLR). Both files are written as `NAME.partial`
//! and renamed into place at the end (see [`AtomicFile`]), the `.wdp` first. Layout and every
//! field: `docs/formats.md`, "Returns as LAS 1.4 with waveforms (output)".

use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::format::las_write::{
    self as lw, DESCRIPTOR_SIZE, EVLR_HEADER_SIZE, EXTRA_BYTES_DESCRIPTOR_SIZE, HEADER_SIZE,
    Header, LasWriteError, MAX_DESCRIPTORS, PF9_SIZE, PointRecord9, VLR_HEADER_SIZE,
    WavePacketDescriptor,
};
use crate::pulse::{Pulse, PulseGeometry};
use crate::sink::atomic_file::AtomicFile;
use crate::sink::{PulseSink, SinkError};

/// Scale of the stored X, Y, Z: 1 mm in a projected CRS in metres.
pub const SCALE: f64 = 0.001;
/// The offset is the first point's position rounded down to a multiple of this (CRS units).
pub const OFFSET_STEP: f64 = 1000.0;
/// Bytes of extra bytes per point with [`LasWaveOptions::extra_bytes`]: `amplitude_v`,
/// `sigma_ns`, both f32.
pub const EXTRA_BYTES: usize = 8;
/// User id of the padding VLR that fills the unused descriptor room.
pub const PADDING_USER_ID: &str = "fwlidar";
/// Record id of the padding VLR.
pub const PADDING_RECORD_ID: u16 = 1;
/// Room reserved between the header and the points for the descriptor VLRs, bytes.
pub const DESCRIPTOR_ROOM: usize = MAX_DESCRIPTORS * (VLR_HEADER_SIZE + DESCRIPTOR_SIZE);
/// Largest return number LAS point formats 6–10 hold.
pub const MAX_RETURNS: usize = 15;

/// Settings of the LAS output.
#[derive(Clone, Debug, PartialEq)]
pub struct LasWaveOptions {
    /// Coordinate reference system of the pulses' geometry as OGC WKT, written as VLR
    /// `LASF_Projection` / 2112; `None` writes no CRS record.
    pub crs_wkt: Option<String>,
    /// Append `amplitude_v` and `sigma_ns` (f32 each) to every point, declared in an Extra
    /// Bytes VLR. Default true.
    pub extra_bytes: bool,
    /// The pulses' GPS time is Adjusted Standard GPS time (global encoding bit 0); else GPS
    /// seconds of the week. Default false.
    pub adjusted_standard_gps_time: bool,
}

impl Default for LasWaveOptions {
    fn default() -> Self {
        LasWaveOptions {
            crs_wkt: None,
            extra_bytes: true,
            adjusted_standard_gps_time: false,
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
    /// Intensities clipped to 65535.
    pub intensity_clipped: u64,
    /// Waveform packets written to the `.wdp`.
    pub packets: u64,
    /// Size of the `.wdp`, bytes (its 60-byte header included).
    pub wdp_bytes: u64,
    /// Waveform packet descriptors used.
    pub descriptors: u64,
}

/// What distinguishes two descriptors: stored bits, samples, spacing (ps), gain and offset
/// (f32 bit patterns, as the pulse carries them).
type DescKey = (u8, u32, u32, u32, u32);

/// Writes `returns.las` and `returns.wdp` into a folder.
pub struct LasWaveSink {
    las: AtomicFile,
    wdp: AtomicFile,
    las_path: PathBuf,
    wdp_path: PathBuf,
    options: LasWaveOptions,
    /// Encoded VLRs known at creation (WKT, Extra Bytes), in file order.
    fixed_vlrs: Vec<u8>,
    fixed_vlr_count: u32,
    record_len: usize,
    descriptors: Vec<(DescKey, WavePacketDescriptor)>,
    last_descriptor: usize,
    offset: Option<[f64; 3]>,
    min: [i32; 3],
    max: [i32; 3],
    by_return: [u64; MAX_RETURNS],
    wdp_pos: u64,
    finished: bool,
    report: LasWaveReport,
    // Scratch reused from pulse to pulse.
    order: Vec<u16>,
    packet_of_segment: Vec<Option<(u8, u64, u32)>>,
    record: Vec<u8>,
    samples: Vec<u8>,
}

fn las_err(path: &Path, source: LasWriteError) -> SinkError {
    SinkError::Las {
        path: path.display().to_string(),
        source,
    }
}

fn io_err(path: &Path, source: std::io::Error) -> SinkError {
    SinkError::Io {
        path: path.display().to_string(),
        source,
    }
}

impl LasWaveSink {
    /// Starts writing `returns.las` and `returns.wdp` into `dir` (which must exist).
    pub fn create(dir: &Path, options: LasWaveOptions) -> Result<Self, SinkError> {
        let las_path = dir.join("returns.las");
        let mut fixed_vlrs = Vec::new();
        let mut fixed_vlr_count = 0;
        if let Some(wkt) = &options.crs_wkt {
            if wkt.as_bytes().contains(&0) {
                return Err(las_err(
                    &las_path,
                    LasWriteError::Unrepresentable("the CRS WKT contains a NUL byte".into()),
                ));
            }
            let len = wkt.len() + 1;
            let h = lw::vlr_header(lw::LASF_PROJECTION, lw::WKT_RECORD_ID, len, "OGC WKT CRS")
                .map_err(|e| las_err(&las_path, e))?;
            fixed_vlrs.extend_from_slice(&h);
            fixed_vlrs.extend_from_slice(wkt.as_bytes());
            fixed_vlrs.push(0);
            fixed_vlr_count += 1;
        }
        if options.extra_bytes {
            let h = lw::vlr_header(
                lw::LASF_SPEC,
                lw::EXTRA_BYTES_RECORD_ID,
                2 * EXTRA_BYTES_DESCRIPTOR_SIZE,
                "fwlidar return attributes",
            )
            .map_err(|e| las_err(&las_path, e))?;
            fixed_vlrs.extend_from_slice(&h);
            fixed_vlrs.extend_from_slice(&lw::extra_bytes_descriptor(
                lw::EXTRA_BYTES_F32,
                "amplitude_v",
                "Gaussian peak amplitude, volts",
            ));
            fixed_vlrs.extend_from_slice(&lw::extra_bytes_descriptor(
                lw::EXTRA_BYTES_F32,
                "sigma_ns",
                "Gaussian standard deviation, ns",
            ));
            fixed_vlr_count += 1;
        }
        let record_len = PF9_SIZE + if options.extra_bytes { EXTRA_BYTES } else { 0 };

        let mut las = AtomicFile::create(&las_path)?;
        let mut wdp = AtomicFile::create(dir.join("returns.wdp"))?;
        // Room for the header and every VLR; filled in at finish.
        let preamble = HEADER_SIZE + fixed_vlrs.len() + DESCRIPTOR_ROOM;
        las.writer()?
            .write_all(&vec![0u8; preamble])
            .map_err(|e| io_err(&las_path, e))?;
        let wdp_path = wdp.path().to_path_buf();
        wdp.writer()?
            .write_all(&[0u8; EVLR_HEADER_SIZE])
            .map_err(|e| io_err(&wdp_path, e))?;
        Ok(LasWaveSink {
            las,
            wdp,
            las_path,
            wdp_path,
            options,
            fixed_vlrs,
            fixed_vlr_count,
            record_len,
            descriptors: Vec::with_capacity(MAX_DESCRIPTORS),
            last_descriptor: 0,
            offset: None,
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            by_return: [0; MAX_RETURNS],
            wdp_pos: EVLR_HEADER_SIZE as u64,
            finished: false,
            report: LasWaveReport::default(),
            order: Vec::with_capacity(64),
            packet_of_segment: Vec::with_capacity(8),
            record: vec![0u8; record_len],
            samples: Vec::with_capacity(1 << 13),
        })
    }

    /// What has been written and skipped so far.
    pub fn stats(&self) -> &LasWaveReport {
        &self.report
    }

    /// Bytes from the start of `returns.las` to the first point record.
    pub fn offset_to_points(&self) -> u64 {
        (HEADER_SIZE + self.fixed_vlrs.len() + DESCRIPTOR_ROOM) as u64
    }

    /// Index (1..=255) of the descriptor for `key`, made on first use.
    fn descriptor(&mut self, key: DescKey, d: WavePacketDescriptor) -> Result<u8, SinkError> {
        if self.descriptors.get(self.last_descriptor).map(|e| e.0) == Some(key) {
            return Ok(self.last_descriptor as u8 + 1);
        }
        let i = match self.descriptors.iter().position(|e| e.0 == key) {
            Some(i) => i,
            None => {
                if self.descriptors.len() == MAX_DESCRIPTORS {
                    return Err(las_err(self.las.path(), LasWriteError::TooManyDescriptors));
                }
                self.descriptors.push((key, d));
                self.descriptors.len() - 1
            }
        };
        self.last_descriptor = i;
        Ok(i as u8 + 1)
    }

    /// Writes segment `s` of `p` as a waveform packet: (descriptor index, offset, size).
    fn write_packet(&mut self, p: &Pulse, s: usize) -> Result<(u8, u64, u32), SinkError> {
        let raw = p.raw_of(s);
        let bits: u8 = if p.bits <= 8 { 8 } else { 16 };
        let spacing = (p.sample_ns * 1000.0).round();
        if !(spacing >= 1.0 && spacing <= f64::from(u32::MAX)) {
            return Err(las_err(
                self.las.path(),
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
        self.wdp
            .writer()?
            .write_all(&self.samples)
            .map_err(|e| io_err(&self.wdp_path, e))?;
        let at = self.wdp_pos;
        self.wdp_pos += u64::from(size);
        self.report.packets += 1;
        Ok((index, at, size))
    }

    /// Intensity of a return of amplitude `amplitude_v`: counts normalised to 16 bits.
    fn intensity(&mut self, p: &Pulse, amplitude_v: f32) -> u16 {
        let gain = f64::from(p.gain_v_per_dn);
        let amp = f64::from(amplitude_v);
        if !(gain > 0.0 && gain.is_finite() && amp.is_finite()) {
            return 0;
        }
        let bits = p.bits.clamp(1, 16);
        let v = (amp / gain * f64::from(1u32 << (16 - bits))).round();
        if v > 65535.0 {
            self.report.intensity_clipped += 1;
            65535
        } else if v > 0.0 {
            v as u16
        } else {
            0
        }
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
        let mut written = 0;
        for rank in 0..self.order.len() {
            let r = p.returns[self.order[rank] as usize];
            let s = r.segment as usize;
            let pos: [f64; 3] = std::array::from_fn(|k| g.anchor[k] + r.time_ns * g.direction[k]);
            if s >= p.segments.len() || pos.iter().any(|v| !v.is_finite()) {
                self.report.returns_unrepresentable += 1;
                continue;
            }
            let offset = *self
                .offset
                .get_or_insert_with(|| pos.map(|v| (v / OFFSET_STEP).floor() * OFFSET_STEP));
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
            let (index, at, size) = match self.packet_of_segment[s] {
                Some(packet) => packet,
                None => {
                    let packet = self.write_packet(p, s)?;
                    self.packet_of_segment[s] = Some(packet);
                    packet
                }
            };
            let seg = p.segments[s];
            let return_number = (rank + 1).min(MAX_RETURNS) as u8;
            if rank >= MAX_RETURNS {
                self.report.returns_beyond_15 += 1;
            }
            let rec = PointRecord9 {
                xyz,
                intensity: self.intensity(p, r.amplitude),
                return_number,
                number_of_returns: n_returns,
                scanner_channel: seg.channel.min(3),
                classification: 0,
                scan_angle,
                gps_time: p.gps_time,
                wave_packet_index: index,
                wave_offset: at,
                wave_size: size,
                wave_location_ps: ((r.time_ns - seg.start_ns) * 1000.0) as f32,
                xyz_t,
            };
            rec.encode_into(&mut self.record);
            if self.options.extra_bytes {
                let sigma_ns = (f64::from(r.sigma_bins) * p.sample_ns) as f32;
                self.record[PF9_SIZE..PF9_SIZE + 4].copy_from_slice(&r.amplitude.to_le_bytes());
                self.record[PF9_SIZE + 4..PF9_SIZE + 8].copy_from_slice(&sigma_ns.to_le_bytes());
            }
            self.las
                .writer()?
                .write_all(&self.record)
                .map_err(|e| io_err(&self.las_path, e))?;
            for (k, v) in xyz.into_iter().enumerate() {
                self.min[k] = self.min[k].min(v);
                self.max[k] = self.max[k].max(v);
            }
            self.by_return[return_number as usize - 1] += 1;
            self.report.points += 1;
            written += 1;
        }
        Ok(written)
    }

    /// The header as it stands.
    fn header(&self) -> Header {
        let n = self.report.points;
        let offset = self.offset.unwrap_or([0.0; 3]);
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
        let mut global = lw::GLOBAL_WAVEFORM_EXTERNAL | lw::GLOBAL_WKT;
        if self.options.adjusted_standard_gps_time {
            global |= lw::GLOBAL_ADJUSTED_STANDARD_GPS;
        }
        Header {
            global_encoding: global,
            system_identifier: "fwlidar waveform decomposition".into(),
            generating_software: concat!("fwlidar ", env!("CARGO_PKG_VERSION")).into(),
            creation_day_of_year: day,
            creation_year: year,
            offset_to_point_data: self.offset_to_points() as u32,
            number_of_vlrs: self.fixed_vlr_count
                + self.descriptors.len() as u32
                + u32::from(self.descriptors.len() < MAX_DESCRIPTORS),
            point_format: 9,
            point_record_length: self.record_len as u16,
            scale: [SCALE; 3],
            offset,
            max: bound(&self.max),
            min: bound(&self.min),
            start_of_waveform_data: 0,
            start_of_first_evlr: 0,
            number_of_evlrs: 0,
            number_of_points: n,
            points_by_return: self.by_return,
        }
    }

    /// Header and VLRs, exactly `offset_to_points` bytes.
    fn preamble(&self) -> Result<Vec<u8>, SinkError> {
        let mut b = Vec::with_capacity(self.offset_to_points() as usize);
        b.extend_from_slice(&self.header().encode());
        b.extend_from_slice(&self.fixed_vlrs);
        let path = self.las.path();
        for (i, (_, d)) in self.descriptors.iter().enumerate() {
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
        let room = (MAX_DESCRIPTORS - self.descriptors.len()) * (VLR_HEADER_SIZE + DESCRIPTOR_SIZE);
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
        debug_assert_eq!(b.len() as u64, self.offset_to_points());
        Ok(b)
    }
}

impl PulseSink for LasWaveSink {
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
        // Counts are kept per point, so the header matches the file even when a later return
        // of the pulse fails (e.g. a 256th descriptor) and the run ends there.
        let n = self.write_points(p, &g)?;
        self.report.pulses_written += u64::from(n > 0);
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        self.las.flush()?;
        self.wdp.flush()
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        if self.finished {
            return Ok(());
        }
        let wdp_path = self.wdp.path().to_path_buf();
        let evlr = lw::evlr_header(
            lw::LASF_SPEC,
            lw::WAVEFORM_DATA_RECORD_ID,
            self.wdp_pos - EVLR_HEADER_SIZE as u64,
            "fwlidar raw waveform packets",
        );
        let w = self.wdp.writer()?;
        w.seek(SeekFrom::Start(0))
            .and_then(|_| w.write_all(&evlr))
            .map_err(|e| io_err(&wdp_path, e))?;
        let preamble = self.preamble()?;
        let las_path = self.las.path().to_path_buf();
        let w = self.las.writer()?;
        w.seek(SeekFrom::Start(0))
            .and_then(|_| w.write_all(&preamble))
            .map_err(|e| io_err(&las_path, e))?;
        self.report.wdp_bytes = self.wdp_pos;
        self.report.descriptors = self.descriptors.len() as u64;
        self.wdp.commit()?;
        self.las.commit()?;
        self.finished = true;
        tracing::info!(
            points = self.report.points,
            packets = self.report.packets,
            pulses_without_geometry = self.report.pulses_without_geometry,
            "returns.las written"
        );
        Ok(())
    }

    fn report(&self) -> serde_json::Value {
        serde_json::to_value(&self.report).unwrap_or(serde_json::Value::Null)
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
                ..Default::default()
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
                intensity_clipped: 1,
                packets: 3,
                wdp_bytes: 60 + 2 * 20 + 2 * 10 + 2 * 20,
                descriptors: 3,
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
        assert_eq!(u16_at(&b, 105), 67, "59 bytes of format 9 + 8 extra bytes");
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
        assert_eq!(b.len(), offset + 4 * 67);

        let v = vlrs(&b);
        assert_eq!(v[0].0, "LASF_Projection");
        assert_eq!(v[0].1, 2112);
        assert_eq!(v[0].2, [wkt.as_bytes(), b"\0"].concat());
        assert_eq!(
            (v[1].0.as_str(), v[1].1, v[1].2.len()),
            ("LASF_Spec", 4, 384)
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
        let pt = |i: usize| &b[offset + 67 * i..offset + 67 * (i + 1)];
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
        assert_eq!((f32_at(pt(0), 59), f32_at(pt(0), 63)), (1.0, 2.0));
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
                ..Default::default()
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
        let mut sink = LasWaveSink::create(dir.path(), LasWaveOptions::default()).unwrap();
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
        assert_eq!(b.len(), u32_at(&b, 96) as usize + 256 * 67);
        assert_eq!(sink.stats().points, 256);
    }

    #[test]
    fn unrepresentable_returns_are_skipped_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), LasWaveOptions::default()).unwrap();
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
        let Err(e) = LasWaveSink::create(&missing, LasWaveOptions::default()) else {
            panic!("created in a missing folder");
        };
        assert!(e.to_string().contains("nope/returns.las"), "{e}");
        let Err(e) = LasWaveSink::create(
            dir.path(),
            LasWaveOptions {
                crs_wkt: Some("bad\0wkt".into()),
                ..Default::default()
            },
        ) else {
            panic!("accepted a NUL in the WKT");
        };
        assert!(e.to_string().contains("returns.las") && e.to_string().contains("NUL"));
    }

    #[test]
    fn empty_run_gives_a_valid_empty_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = LasWaveSink::create(dir.path(), LasWaveOptions::default()).unwrap();
        sink.finish().unwrap();
        let b = std::fs::read(dir.path().join("returns.las")).unwrap();
        assert_eq!(u64_at(&b, 247), 0);
        assert_eq!(b.len(), u32_at(&b, 96) as usize);
        assert_eq!(vlrs(&b).len(), 2);
        let w = std::fs::read(dir.path().join("returns.wdp")).unwrap();
        assert_eq!((w.len(), u64_at(&w, 20)), (60, 0));
    }
}
