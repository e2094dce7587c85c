//! The waves of one pulse in the `.wvs` file, at the pulse's `offset_to_waves`: the
//! composition's extra bytes, then for each sampling of its descriptor, in order: the number of
//! segments (when `bits_for_number_of_segments > 0`, else the fixed number), then per segment
//! the duration from the anchor (`bits_for_duration_from_anchor`: 0, 8, 16 or 32-bit signed
//! integer; scaled and offset into sampling units), the number of samples (when
//! `bits_for_number_of_samples > 0`, else the fixed number) and the samples (8 or 16-bit
//! unsigned, little-endian). Lookup tables are not applied: samples stay raw counts.

use std::io::{BufRead, BufReader, Read, Seek};

use super::descriptor::{PulseDescriptor, Sampling, SamplingType};
use super::error::PulseWavesError;
use crate::pulse::{Pulse, SegmentKind};

/// Buffered, bounds-checked reading of a `.wvs` file.
pub struct WavesReader<W> {
    r: BufReader<W>,
    name: String,
    len: u64,
    pos: u64,
    scratch: Vec<u8>,
}

/// Hands the next `n` bytes to `f`, straight from the buffer when they are in it (no copy,
/// and no store-to-load stall on a small stack copy), else through `spill`. The caller has
/// checked that the bytes are in the file.
fn take<W: Read, T>(
    r: &mut BufReader<W>,
    spill: &mut Vec<u8>,
    n: usize,
    f: impl FnOnce(&[u8]) -> T,
) -> std::io::Result<T> {
    if r.buffer().len() < n && r.buffer().is_empty() {
        r.fill_buf()?;
    }
    if let Some(s) = r.buffer().get(..n) {
        let v = f(s);
        r.consume(n);
        return Ok(v);
    }
    spill.resize(n, 0);
    r.read_exact(spill)?;
    Ok(f(spill))
}

/// Where a read is, for messages.
struct At<'a> {
    pulse: u64,
    sampling: usize,
    s: &'a Sampling,
    segment: Option<u64>,
}

impl std::fmt::Display for At<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = match self.s.kind {
            SamplingType::Outgoing => "outgoing",
            SamplingType::Returning => "returning",
        };
        write!(
            f,
            "pulse {}: sampling {} ({kind}, channel {})",
            self.pulse, self.sampling, self.s.channel
        )?;
        if let Some(seg) = self.segment {
            write!(f, ": segment {seg}")?;
        }
        Ok(())
    }
}

impl<W: Read + Seek> WavesReader<W> {
    /// Wraps `inner` (positioned anywhere) of `len` bytes, called `name` in messages.
    pub fn new(inner: W, name: &str, len: u64) -> Self {
        WavesReader {
            r: BufReader::with_capacity(256 * 1024, inner),
            name: name.to_string(),
            len,
            pos: u64::MAX,
            scratch: Vec::new(),
        }
    }

    /// The file's length, bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the file is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Reads `buf.len()` bytes at `at` (for the header).
    pub fn read_at(&mut self, at: u64, buf: &mut [u8]) -> Result<(), PulseWavesError> {
        self.seek_to(at)?;
        self.r
            .read_exact(buf)
            .map_err(|e| PulseWavesError::io(&self.name, e))?;
        self.pos = at + buf.len() as u64;
        Ok(())
    }

    fn seek_to(&mut self, at: u64) -> Result<(), PulseWavesError> {
        if self.pos == at {
            return Ok(());
        }
        let res = if self.pos == u64::MAX {
            self.r.seek(std::io::SeekFrom::Start(at)).map(|_| ())
        } else {
            // Keeps the buffer when the target is inside it.
            self.r.seek_relative(at as i64 - self.pos as i64)
        };
        res.map_err(|e| {
            self.pos = u64::MAX;
            PulseWavesError::io(&self.name, e)
        })?;
        self.pos = at;
        Ok(())
    }

    /// An I/O error: the position is no longer known, the next read seeks.
    fn io_err(&mut self, e: std::io::Error) -> PulseWavesError {
        self.pos = u64::MAX;
        PulseWavesError::io(&self.name, e)
    }

    /// Checks that `n` bytes from the current position are in the file.
    fn need(&self, n: u64, what: impl FnOnce() -> String) -> Result<(), PulseWavesError> {
        match self.pos.checked_add(n) {
            Some(end) if end <= self.len => Ok(()),
            end => Err(PulseWavesError::truncated(
                &self.name,
                what(),
                self.pos,
                end.unwrap_or(u64::MAX),
                self.len,
            )),
        }
    }

    fn read_unsigned(
        &mut self,
        bits: u8,
        what: impl FnOnce() -> String,
    ) -> Result<u32, PulseWavesError> {
        let n = usize::from(bits / 8).min(4);
        self.need(n as u64, what)?;
        let v = take(&mut self.r, &mut self.scratch, n, |b| match *b {
            [a] => u32::from(a),
            [a, b] => u32::from(u16::from_le_bytes([a, b])),
            [a, b, c, d] => u32::from_le_bytes([a, b, c, d]),
            _ => 0,
        })
        .map_err(|e| self.io_err(e))?;
        self.pos += n as u64;
        Ok(v)
    }

    fn read_signed(
        &mut self,
        bits: u8,
        what: impl FnOnce() -> String,
    ) -> Result<i64, PulseWavesError> {
        let n = usize::from(bits / 8).min(4);
        self.need(n as u64, what)?;
        let v = take(&mut self.r, &mut self.scratch, n, |b| match *b {
            [a] => i64::from(a as i8),
            [a, b] => i64::from(i16::from_le_bytes([a, b])),
            [a, b, c, d] => i64::from(i32::from_le_bytes([a, b, c, d])),
            _ => 0,
        })
        .map_err(|e| self.io_err(e))?;
        self.pos += n as u64;
        Ok(v)
    }

    /// Reads the waves of pulse `pulse_index` at `offset` as described by `d`, appending a
    /// segment to `pulse` per stored segment (`start_ns` = duration from the anchor × the
    /// sampling's sample units; an outgoing sampling's duration counts from the optical centre,
    /// so the composition's constant `optical_center_to_anchor` is subtracted). Returns the
    /// bytes of waves read.
    pub fn read_pulse(
        &mut self,
        pulse_index: u64,
        offset: i64,
        d: &PulseDescriptor,
        pulse: &mut Pulse,
    ) -> Result<u64, PulseWavesError> {
        let start = match u64::try_from(offset) {
            Ok(o) if o <= self.len => o,
            _ => {
                return Err(PulseWavesError::invalid(
                    &self.name,
                    format!("pulse {pulse_index}: offset_to_waves"),
                    format!("{offset} is outside the file ({} bytes)", self.len),
                ));
            }
        };
        self.seek_to(start)?;
        let extra = u64::from(d.composition.extra_wave_bytes);
        if extra > 0 {
            self.need(extra, || format!("pulse {pulse_index}: extra wave bytes"))?;
            let at = self.pos + extra;
            self.seek_to(at)?;
        }
        let oc = f64::from(d.composition.optical_center_to_anchor.unwrap_or(0));
        for (k, s) in d.samplings.iter().enumerate() {
            let mut at = At {
                pulse: pulse_index,
                sampling: k,
                s,
                segment: None,
            };
            let segments = if s.bits_for_number_of_segments > 0 {
                self.read_unsigned(s.bits_for_number_of_segments, || {
                    format!("{at}: number of segments")
                })?
            } else {
                u32::from(s.number_of_segments)
            };
            let kind = match s.kind {
                SamplingType::Outgoing => SegmentKind::Outgoing,
                SamplingType::Returning => SegmentKind::Return,
            };
            let su = f64::from(s.sample_units_ns);
            for g in 0..u64::from(segments) {
                at.segment = Some(g);
                let raw = if s.bits_for_duration_from_anchor > 0 {
                    self.read_signed(s.bits_for_duration_from_anchor, || {
                        format!("{at}: duration from anchor")
                    })?
                } else {
                    0
                };
                let mut duration = raw as f64 * f64::from(s.scale_for_duration_from_anchor)
                    + f64::from(s.offset_for_duration_from_anchor);
                if s.kind == SamplingType::Outgoing {
                    duration -= oc;
                }
                let n = if s.bits_for_number_of_samples > 0 {
                    self.read_unsigned(s.bits_for_number_of_samples, || {
                        format!("{at}: number of samples")
                    })?
                } else {
                    s.number_of_samples
                };
                if pulse.raw.len() as u64 + u64::from(n) > u64::from(u32::MAX) {
                    return Err(PulseWavesError::invalid(
                        &self.name,
                        format!("{at}: number of samples"),
                        format!("{n} more samples would exceed 2^32 samples in one pulse"),
                    ));
                }
                let bytes = u64::from(n) * s.bytes_per_sample();
                self.need(bytes, || {
                    format!("{at}: {n} samples of {} bits", s.bits_per_sample)
                })?;
                let start_ns = duration * su;
                let wide = s.bits_per_sample == 16;
                // `bytes` is bounded by the file's length (checked just above).
                take(&mut self.r, &mut self.scratch, bytes as usize, |b| {
                    if wide {
                        pulse.push_segment(
                            kind,
                            s.channel,
                            start_ns,
                            b.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])),
                        )
                    } else {
                        pulse.push_segment(
                            kind,
                            s.channel,
                            start_ns,
                            b.iter().map(|&v| u16::from(v)),
                        )
                    }
                })
                .map_err(|e| self.io_err(e))?;
                self.pos += bytes;
            }
        }
        Ok(self.pos - start)
    }
}
