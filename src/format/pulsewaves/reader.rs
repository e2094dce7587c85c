//! [`PulseWavesReader`]: a `.pls` + `.wvs` pair over any `Read + Seek` (files, or byte slices in
//! a `Cursor` for the fuzzer), read pulse by pulse into pooled [`Pulse`]s.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use super::crs::{self, CrsInfo};
use super::descriptor::PulseDescriptor;
use super::error::PulseWavesError;
use super::header::{PLS_HEADER_LEN, PlsHeader, WVS_HEADER_LEN, WvsHeader};
use super::pulse_record::PulseRecord;
use super::scanner::Scanner;
use super::vlr::{self, PROJ_USER, SPEC_USER};
use super::waves::WavesReader;
use crate::pulse::{Pulse, PulseGeometry};

/// Seconds between the GPS epoch and the origin of adjusted standard GPS time.
const ADJUSTED_STANDARD_SHIFT_S: f64 = 1e9;
/// Seconds in a GPS week.
const WEEK_S: f64 = 604_800.0;

/// What the pulses' GPS times count.
///
/// The 0.3 draft defines no bit of the global parameters; the reader takes bit 0 set to mean
/// adjusted standard GPS time (as in LAS), else tells the base from the header's time range:
/// within one week → seconds of week; larger → standard GPS time, which it converts to adjusted
/// standard (minus 10⁹ s, folded into the offset so no precision is lost).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeBase {
    /// GPS seconds of the week.
    GpsSecondsOfWeek,
    /// Adjusted standard GPS time (GPS seconds since the epoch minus 10⁹).
    GpsAdjustedStandard,
    /// Not known (negative times).
    Unknown,
}

impl TimeBase {
    /// The name `SourceFacts::time_base` uses, when known.
    pub fn as_str(self) -> Option<&'static str> {
        match self {
            TimeBase::GpsSecondsOfWeek => Some("gps_seconds_of_week"),
            TimeBase::GpsAdjustedStandard => Some("gps_adjusted_standard"),
            TimeBase::Unknown => None,
        }
    }
}

/// Reads a PulseWaves pulse file and its waves file.
pub struct PulseWavesReader<P, W> {
    pls: BufReader<P>,
    waves: WavesReader<W>,
    pls_name: String,
    header: PlsHeader,
    descriptors: Vec<Option<PulseDescriptor>>,
    scanners: Vec<Scanner>,
    crs: CrsInfo,
    time_base: TimeBase,
    /// Offset added to `T × t_scale`, seconds (the header's, shifted for [`TimeBase`]).
    time_offset_s: f64,
    warnings: Vec<String>,
    lookup_tables: u64,
    skipped_records: u64,
    next: u64,
    failed: bool,
    record: Vec<u8>,
    wave_bytes: u64,
}

/// The `.wvs` file beside `pls`: same stem with `.wvs`, else `.WVS`.
pub fn waves_path_for(pls: &Path) -> Result<PathBuf, PulseWavesError> {
    let lower = pls.with_extension("wvs");
    let upper = pls.with_extension("WVS");
    if lower.is_file() {
        Ok(lower)
    } else if upper.is_file() {
        Ok(upper)
    } else {
        Err(PulseWavesError::MissingWaves {
            pls: pls.display().to_string(),
            lower: lower.display().to_string(),
            upper: upper.display().to_string(),
        })
    }
}

impl PulseWavesReader<File, File> {
    /// Opens `pls` and the `.wvs` file beside it ([`waves_path_for`]).
    pub fn open(pls: &Path) -> Result<Self, PulseWavesError> {
        let wvs = waves_path_for(pls)?;
        let (pn, wn) = (pls.display().to_string(), wvs.display().to_string());
        let pf = File::open(pls).map_err(|e| PulseWavesError::io(&pn, e))?;
        let wf = File::open(&wvs).map_err(|e| PulseWavesError::io(&wn, e))?;
        PulseWavesReader::new(pf, &pn, wf, &wn)
    }
}

fn stream_len<R: Seek>(r: &mut R, name: &str) -> Result<u64, PulseWavesError> {
    r.seek(SeekFrom::End(0))
        .map_err(|e| PulseWavesError::io(name, e))
}

fn read_head<R: Read + Seek>(
    r: &mut R,
    name: &str,
    len: u64,
    want: usize,
) -> Result<Vec<u8>, PulseWavesError> {
    let n = (want as u64).min(len) as usize;
    let mut b = vec![0u8; n];
    r.seek(SeekFrom::Start(0))
        .map_err(|e| PulseWavesError::io(name, e))?;
    r.read_exact(&mut b)
        .map_err(|e| PulseWavesError::io(name, e))?;
    Ok(b)
}

impl<P: Read + Seek, W: Read + Seek> PulseWavesReader<P, W> {
    /// Reads the headers and records of a pulse file `pls` and waves file `wvs` (called
    /// `pls_name` and `wvs_name` in messages), ready to read the first pulse.
    pub fn new(
        mut pls: P,
        pls_name: &str,
        mut wvs: W,
        wvs_name: &str,
    ) -> Result<Self, PulseWavesError> {
        let pls_len = stream_len(&mut pls, pls_name)?;
        let head = read_head(&mut pls, pls_name, pls_len, PLS_HEADER_LEN)?;
        let header = PlsHeader::parse(&head, pls_name, pls_len)?;
        let scan = vlr::scan(&mut pls, pls_name, &header, pls_len)?;

        let mut descriptors: Vec<Option<PulseDescriptor>> = vec![None; 256];
        let mut scanners: Vec<Scanner> = Vec::new();
        let mut proj = Vec::new();
        for r in scan.kept {
            if r.user_id == SPEC_USER && (200_001..=200_255).contains(&r.record_id) {
                let index = (r.record_id - 200_000) as u8;
                let d = PulseDescriptor::parse(&r.payload, index, pls_name)?;
                if let Some(slot) = descriptors.get_mut(usize::from(index)) {
                    *slot = Some(d);
                }
            } else if r.user_id == SPEC_USER && (100_001..=100_255).contains(&r.record_id) {
                let index = (r.record_id - 100_000) as u8;
                let s = Scanner::parse(&r.payload, index, pls_name)?;
                scanners.retain(|o| o.index != index);
                scanners.push(s);
            } else if r.user_id == PROJ_USER || r.user_id == "LASF_Projection" {
                proj.push(r);
            }
        }
        scanners.sort_by_key(|s| s.index);
        let crs = crs::from_records(&proj);
        let mut warnings = Vec::new();
        for w in &crs.warnings {
            tracing::warn!(file = %pls_name, "{w}");
            warnings.push(w.clone());
        }
        if scan.lookup_tables > 0 {
            warnings.push(format!(
                "{} sample lookup table(s) present and not applied: samples are raw counts",
                scan.lookup_tables
            ));
        }

        let (time_base, time_offset_s) = time_base_of(&header);
        if time_base == TimeBase::Unknown {
            let w = format!(
                "GPS times {}..{} s are neither seconds of week nor standard GPS time: time base \
                 unknown",
                header.min_t as f64 * header.t_scale + header.t_offset,
                header.max_t as f64 * header.t_scale + header.t_offset
            );
            tracing::warn!(file = %pls_name, "{w}");
            warnings.push(w);
        }

        let wvs_len = stream_len(&mut wvs, wvs_name)?;
        let mut waves = WavesReader::new(wvs, wvs_name, wvs_len);
        let mut wh = vec![0u8; (WVS_HEADER_LEN as u64).min(wvs_len) as usize];
        waves.read_at(0, &mut wh)?;
        WvsHeader::parse(&wh, wvs_name, wvs_len)?;

        pls.seek(SeekFrom::Start(header.pulse_data_start()))
            .map_err(|e| PulseWavesError::io(pls_name, e))?;
        // The pulse table was checked to fit in the file, so `pulse_size` is bounded by it
        // whenever there is a pulse to read.
        let record = if header.pulses() > 0 {
            vec![0u8; header.pulse_size as usize]
        } else {
            Vec::new()
        };
        Ok(PulseWavesReader {
            pls: BufReader::with_capacity(64 * 1024, pls),
            waves,
            pls_name: pls_name.to_string(),
            header,
            descriptors,
            scanners,
            crs,
            time_base,
            time_offset_s,
            warnings,
            lookup_tables: scan.lookup_tables,
            skipped_records: scan.skipped,
            next: 0,
            failed: false,
            record,
            wave_bytes: 0,
        })
    }

    /// The `.pls` header.
    pub fn header(&self) -> &PlsHeader {
        &self.header
    }

    /// The pulse descriptors, by index.
    pub fn descriptors(&self) -> impl Iterator<Item = &PulseDescriptor> {
        self.descriptors.iter().flatten()
    }

    /// The descriptor of `index`, if the file defines it.
    pub fn descriptor(&self, index: u8) -> Option<&PulseDescriptor> {
        self.descriptors
            .get(usize::from(index))
            .and_then(|d| d.as_ref())
    }

    /// The scanner records, by index.
    pub fn scanners(&self) -> &[Scanner] {
        &self.scanners
    }

    /// The CRS: OGC WKT or `EPSG:<code>`, when known.
    pub fn crs(&self) -> Option<&str> {
        self.crs.crs.as_deref()
    }

    /// The time base of [`Pulse::gps_time`].
    pub fn time_base(&self) -> TimeBase {
        self.time_base
    }

    /// What was doubtful but not fatal (malformed GeoKeys, lookup tables not applied, ...).
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// Lookup table records present (not applied).
    pub fn lookup_tables(&self) -> u64 {
        self.lookup_tables
    }

    /// VLRs and AVLRs the reader does not interpret.
    pub fn skipped_records(&self) -> u64 {
        self.skipped_records
    }

    /// Pulse records in the file.
    pub fn number_of_pulses(&self) -> u64 {
        self.header.pulses()
    }

    /// Pulses read so far.
    pub fn pulses_read(&self) -> u64 {
        self.next
    }

    /// Bytes of `.wvs` waves read so far.
    pub fn wave_bytes_read(&self) -> u64 {
        self.wave_bytes
    }

    /// Length of the `.wvs` file, bytes.
    pub fn waves_len(&self) -> u64 {
        self.waves.len()
    }

    /// Reads the next pulse into `pulse` (its segments and samples are replaced; `seq` and
    /// `arrived` are left alone). `Ok(false)` after the last pulse.
    ///
    /// Mapping: `pulse_id` = record index; `gps_time` = T × t_scale + offset (seconds, see
    /// [`TimeBase`]); geometry anchor = scaled anchor point; direction = (target − anchor) /
    /// (1000 × the composition's sample units), CRS units per ns; one segment per stored
    /// segment with `start_ns` = duration from anchor × sample units; `sample_ns` = the
    /// samplings' sample units; raw counts with gain 1 V/DN and offset 0 V.
    pub fn read_pulse(&mut self, pulse: &mut Pulse) -> Result<bool, PulseWavesError> {
        if self.failed || self.next >= self.header.pulses() {
            return Ok(false);
        }
        let res = self.read_next(pulse);
        match res {
            Ok(()) => {
                self.next += 1;
                Ok(true)
            }
            Err(e) => {
                // An error is final: the position in either file is no longer trustworthy.
                self.failed = true;
                Err(e)
            }
        }
    }

    fn read_next(&mut self, pulse: &mut Pulse) -> Result<(), PulseWavesError> {
        let index = self.next;
        let size = self.record.len();
        let rec = {
            // Straight from the buffer when the whole record is in it.
            if self.pls.buffer().len() < size && self.pls.buffer().is_empty() {
                self.pls
                    .fill_buf()
                    .map_err(|e| PulseWavesError::io(&self.pls_name, e))?;
            }
            if let Some(b) = self.pls.buffer().get(..size) {
                let rec = PulseRecord::parse(b);
                self.pls.consume(size);
                rec
            } else {
                self.pls.read_exact(&mut self.record).map_err(|e| {
                    if e.kind() == std::io::ErrorKind::UnexpectedEof {
                        PulseWavesError::invalid(
                            &self.pls_name,
                            format!("pulse {index}"),
                            "the file ended early (it shrank while being read)",
                        )
                    } else {
                        PulseWavesError::io(&self.pls_name, e)
                    }
                })?;
                PulseRecord::parse(&self.record)
            }
        };
        let Some(d) = self
            .descriptors
            .get(usize::from(rec.descriptor_index))
            .and_then(|d| d.as_ref())
        else {
            let defined: Vec<String> = self.descriptors().map(|d| d.index.to_string()).collect();
            return Err(PulseWavesError::DescriptorIndex {
                file: self.pls_name.clone(),
                pulse: index,
                index: rec.descriptor_index,
                defined: format!(
                    "{} descriptor{}{}",
                    defined.len(),
                    if defined.len() == 1 { "" } else { "s" },
                    if defined.is_empty() {
                        String::new()
                    } else {
                        format!(": {}", defined.join(", "))
                    }
                ),
            });
        };
        let h = &self.header;
        pulse.segments.clear();
        pulse.raw.clear();
        pulse.signal.clear();
        pulse.returns.clear();
        pulse.pulse_id = index;
        pulse.gps_time = rec.gps_timestamp as f64 * h.t_scale + self.time_offset_s;
        pulse.scan_angle_deg = [f32::NAN, f32::NAN];
        pulse.sample_ns = d.sample_ns();
        pulse.gain_v_per_dn = 1.0;
        pulse.offset_v = 0.0;
        pulse.bits = d.bits();
        let per_ns = 1.0 / (1000.0 * f64::from(d.composition.sample_units_ns));
        let mut anchor = [0.0; 3];
        let mut direction = [0.0; 3];
        for i in 0..3 {
            anchor[i] = f64::from(rec.anchor[i]) * h.scale[i] + h.offset[i];
            direction[i] =
                (f64::from(rec.target[i]) - f64::from(rec.anchor[i])) * h.scale[i] * per_ns;
        }
        pulse.geometry = Some(PulseGeometry { anchor, direction });
        let n = self
            .waves
            .read_pulse(index, rec.offset_to_waves, d, pulse)?;
        self.wave_bytes += n;
        Ok(())
    }
}

fn time_base_of(h: &PlsHeader) -> (TimeBase, f64) {
    let lo = h.min_t.min(h.max_t) as f64 * h.t_scale + h.t_offset;
    let hi = h.min_t.max(h.max_t) as f64 * h.t_scale + h.t_offset;
    let (lo, hi) = (lo.min(hi), lo.max(hi));
    if h.global_parameters & 1 != 0 {
        (TimeBase::GpsAdjustedStandard, h.t_offset)
    } else if lo >= 0.0 && hi <= WEEK_S {
        (TimeBase::GpsSecondsOfWeek, h.t_offset)
    } else if lo > WEEK_S {
        (
            TimeBase::GpsAdjustedStandard,
            h.t_offset - ADJUSTED_STANDARD_SHIFT_S,
        )
    } else {
        (TimeBase::Unknown, h.t_offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::SegmentKind;
    use std::io::Cursor;

    fn put<const N: usize>(b: &mut [u8], at: usize, v: [u8; N]) {
        b[at..at + N].copy_from_slice(&v);
    }

    fn vlr_header(user: &str, id: u32, len: i64) -> Vec<u8> {
        let mut h = vec![0u8; 96];
        h[..user.len()].copy_from_slice(user.as_bytes());
        put(&mut h, 16, id.to_le_bytes());
        put(&mut h, 24, len.to_le_bytes());
        h
    }

    /// A descriptor with what no real file has: extra wave bytes, a constant optical-centre
    /// offset, 0.5 ns units, signed 8-bit durations, variable segment and sample counts and
    /// 16-bit samples.
    fn descriptor() -> Vec<u8> {
        let mut d = vec![0u8; 92 + 2 * 104];
        put(&mut d, 0, 92u32.to_le_bytes());
        put(&mut d, 8, 3i32.to_le_bytes()); // optical centre to anchor, sampling units
        put(&mut d, 12, 2u16.to_le_bytes()); // extra wave bytes
        put(&mut d, 14, 2u16.to_le_bytes()); // samplings
        put(&mut d, 16, 0.5f32.to_le_bytes());
        for (k, (kind, channel, bseg, nseg, bsmp, nsmp)) in
            [(1u8, 0u8, 0u8, 1u16, 0u8, 3u32), (2, 2, 8, 0, 8, 0)]
                .into_iter()
                .enumerate()
        {
            let s = &mut d[92 + 104 * k..92 + 104 * (k + 1)];
            put(s, 0, 104u32.to_le_bytes());
            s[8] = kind;
            s[9] = channel;
            s[11] = 8; // bits for duration
            put(s, 12, 1.0f32.to_le_bytes());
            put(s, 16, 100.0f32.to_le_bytes());
            s[20] = bseg;
            s[21] = bsmp;
            put(s, 22, nseg.to_le_bytes());
            put(s, 24, nsmp.to_le_bytes());
            put(s, 28, 16u16.to_le_bytes());
            put(s, 32, 0.5f32.to_le_bytes());
        }
        d
    }

    /// Two pulses; the descriptor is an AVLR (walked from the end of the file).
    fn synthetic() -> (Vec<u8>, Vec<u8>) {
        let mut pls = vec![0u8; 352];
        pls[..16].copy_from_slice(b"PulseWavesPulse\0");
        pls[172] = 0;
        pls[173] = 3;
        put(&mut pls, 174, 352u16.to_le_bytes());
        put(&mut pls, 176, 352i64.to_le_bytes());
        put(&mut pls, 184, 2i64.to_le_bytes());
        put(&mut pls, 200, 48u32.to_le_bytes());
        put(&mut pls, 220, (-1i32).to_le_bytes());
        put(&mut pls, 224, 1e-6f64.to_le_bytes());
        put(&mut pls, 240, 1_000_000i64.to_le_bytes());
        put(&mut pls, 248, 2_000_000i64.to_le_bytes());
        for k in 0..3 {
            put(&mut pls, 256 + 8 * k, 0.01f64.to_le_bytes());
        }
        let mut wvs = b"PulseWavesWaves\0".to_vec();
        wvs.resize(60, 0);
        let mut offsets = Vec::new();
        // Pulse 0: extra bytes, outgoing at -5 with 3 samples, 2 return segments.
        offsets.push(wvs.len() as i64);
        wvs.extend([0xEE, 0xEE, (-5i8) as u8]);
        for v in [1u16, 2, 65535] {
            wvs.extend(v.to_le_bytes());
        }
        wvs.extend([2u8, 40, 2]);
        wvs.extend([7u16, 8].iter().flat_map(|v| v.to_le_bytes()));
        wvs.extend([(-128i8) as u8, 1, 0x34, 0x12]);
        // Pulse 1: no return segment.
        offsets.push(wvs.len() as i64);
        wvs.extend([0, 0, 0]);
        wvs.extend([0u8; 6]);
        wvs.push(0);
        for (i, off) in offsets.iter().enumerate() {
            let mut r = [0u8; 48];
            put(&mut r, 0, (1_000_000i64 * (i as i64 + 1)).to_le_bytes());
            put(&mut r, 8, off.to_le_bytes());
            put(&mut r, 16, 100i32.to_le_bytes()); // anchor x
            put(&mut r, 36, (-50_000i32).to_le_bytes()); // target z: 500 m below
            r[44] = 1;
            pls.extend(r);
        }
        pls.extend(vlr_header("PulseWaves_Spec", 0xFFFF_FFFF, 0));
        let d = descriptor();
        pls.extend(&d);
        pls.extend(vlr_header("PulseWaves_Spec", 200_001, d.len() as i64));
        (pls, wvs)
    }

    type Memory = PulseWavesReader<Cursor<Vec<u8>>, Cursor<Vec<u8>>>;

    fn open(pls: Vec<u8>, wvs: Vec<u8>) -> Result<Memory, PulseWavesError> {
        PulseWavesReader::new(Cursor::new(pls), "s.pls", Cursor::new(wvs), "s.wvs")
    }

    #[test]
    fn appended_descriptor_extra_bytes_signed_durations_and_16_bit_samples() {
        let (pls, wvs) = synthetic();
        let mut r = open(pls, wvs).unwrap();
        assert_eq!(r.descriptors().count(), 1);
        assert_eq!(r.time_base(), TimeBase::GpsSecondsOfWeek);
        let mut p = Pulse::default();
        assert!(r.read_pulse(&mut p).unwrap());
        assert_eq!(p.sample_ns, 0.5);
        assert_eq!(p.bits, 16);
        assert_eq!(p.gps_time, 1.0);
        let g = p.geometry.unwrap();
        assert_eq!(g.anchor, [1.0, 0.0, 0.0]);
        // 500 m over 1000 units of 0.5 ns.
        assert!((g.direction[2] + 1.0).abs() < 1e-12, "{:?}", g.direction);
        let segs: Vec<_> = p
            .segments
            .iter()
            .map(|s| (s.kind, s.channel, s.start_ns, s.len))
            .collect();
        assert_eq!(
            segs,
            vec![
                // (-5 + 100 - 3 optical centre) units × 0.5 ns
                (SegmentKind::Outgoing, 0, 46.0, 3),
                (SegmentKind::Return, 2, 70.0, 2),
                (SegmentKind::Return, 2, -14.0, 1),
            ]
        );
        assert_eq!(p.raw, vec![1, 2, 65535, 7, 8, 0x1234]);
        assert!(r.read_pulse(&mut p).unwrap());
        assert_eq!(p.segments.len(), 1);
        assert!(!r.read_pulse(&mut p).unwrap());
        assert_eq!(r.wave_bytes_read(), r.waves_len() - 60);
    }

    #[test]
    fn damaged_synthetic_files_name_the_field() {
        let (pls, wvs) = synthetic();
        // AVLR length reaching into the pulse records.
        let mut bad = pls.clone();
        let n = bad.len();
        put(&mut bad, n - 96 + 24, 100_000i64.to_le_bytes());
        let e = open(bad, wvs.clone()).err().unwrap().to_string();
        assert!(
            e.contains("s.pls: AVLR 0 (record 200001): record_length_before_footer"),
            "{e}"
        );
        // 12 bits per sample.
        let mut bad = pls.clone();
        let at = n - 96 - 300 + 92 + 28;
        put(&mut bad, at, 12u16.to_le_bytes());
        let e = open(bad, wvs.clone()).err().unwrap().to_string();
        assert!(
            e.contains("descriptor 1 (record 200001): sampling 0: bits_per_sample"),
            "{e}"
        );
        assert!(e.contains("not supported"), "{e}");
        // Different sample units between samplings.
        let mut bad = pls.clone();
        put(&mut bad, n - 96 - 104 + 32, 1.0f32.to_le_bytes());
        let e = open(bad, wvs.clone()).err().unwrap().to_string();
        assert!(e.contains("sampling 1: sample_units"), "{e}");
        // A sample count running past the end of the waves.
        let mut bad = wvs.clone();
        bad[71] = 200;
        let mut r = open(pls.clone(), bad).unwrap();
        let e = r
            .read_pulse(&mut Pulse::default())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("s.wvs: truncated: pulse 0: sampling 1 (returning, channel 2): segment 0: 200 samples"), "{e}");
        // Errors are final.
        assert!(!r.read_pulse(&mut Pulse::default()).unwrap());
        // Offset to waves outside the file.
        let mut bad = pls.clone();
        put(&mut bad, 352 + 8, 1_000_000i64.to_le_bytes());
        let mut r = open(bad, wvs).unwrap();
        let e = r
            .read_pulse(&mut Pulse::default())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("s.wvs: pulse 0: offset_to_waves"), "{e}");
    }
}
