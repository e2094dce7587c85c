//! Payloads of the capture records that carry data: the digitizer frame (one [`Pulse`]) and raw
//! navigation bytes. Byte layouts are in `docs/formats.md` ("Capture format v1.1"); all integers
//! and floats are little-endian.
//!
//! Decoding reuses the pulse's buffers: once a pulse has held a frame of a given size, decoding
//! another of at most that size does not allocate.

use crate::pulse::{Pulse, PulseGeometry, Segment, SegmentKind};

/// Bytes of the fixed part of a digitizer frame payload: pulse_id u64, gps_time f64,
/// scan_angle_deg [f32; 2], sample_ns f64, gain_v_per_dn f32, offset_v f32, bits u8,
/// n_segments u8, reserved u16.
pub const FRAME_FIXED_LEN: usize = 44;
/// Bytes of each segment header in a frame: kind u8, channel u8, reserved u16, start_ns f64,
/// n_samples u32.
pub const SEGMENT_HEADER_LEN: usize = 16;
/// Bytes of the geometry prefix of a GeoFrame payload (format 1.1): anchor `[f64; 3]` then
/// direction `[f64; 3]` (CRS units, and CRS units per ns), followed by a digitizer frame payload.
pub const GEOMETRY_LEN: usize = 48;
/// Bytes of the fixed part of a nav payload: port u8, reserved [u8; 3], receive_time_ns u64.
pub const NAV_FIXED_LEN: usize = 12;

/// Why a frame or nav payload could not be encoded or decoded.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The payload is shorter than the frame's fixed part.
    #[error("frame payload is {len} bytes, shorter than its {FRAME_FIXED_LEN}-byte fixed part")]
    TooShort {
        /// Payload length, bytes.
        len: usize,
    },
    /// Bits per sample other than 8 or 16.
    #[error("{bits} bits per sample; only 8 and 16 are defined")]
    BadBits {
        /// The declared bits per sample.
        bits: u8,
    },
    /// A segment kind byte other than 0 (outgoing) or 1 (return).
    #[error("segment {index} has kind {kind}; only 0 (outgoing) and 1 (return) are defined")]
    BadSegmentKind {
        /// Segment index in the frame.
        index: usize,
        /// The kind byte.
        kind: u8,
    },
    /// The sizes the frame declares disagree with its length.
    #[error("frame payload is {len} bytes but its segment headers declare {declared} bytes")]
    LengthMismatch {
        /// Payload length, bytes.
        len: usize,
        /// Bytes the fixed part and the segments declare (up to the point they overran).
        declared: u64,
    },
    /// A pulse with more segments than a frame can hold.
    #[error("pulse has {n} segments; a frame holds at most 255")]
    TooManySegments {
        /// Number of segments of the pulse.
        n: usize,
    },
    /// A segment of the pulse points outside its raw sample buffer.
    #[error("segment {index} covers samples {first}..{end} but the pulse has {raw_len} samples")]
    SegmentOutOfBounds {
        /// Segment index.
        index: usize,
        /// First sample index.
        first: u64,
        /// One past the last sample index.
        end: u64,
        /// Length of the pulse's raw buffer.
        raw_len: usize,
    },
    /// An 8-bit pulse holds a sample above 255.
    #[error("segment {index} holds sample value {value}, which does not fit in 8 bits")]
    SampleOutOfRange {
        /// Segment index.
        index: usize,
        /// The offending count.
        value: u16,
    },
    /// A GeoFrame payload too short for its geometry, or a geometry with a non-finite value.
    #[error("geoframe geometry is unusable: {0}")]
    BadGeometry(&'static str),
    /// The payload is shorter than the nav payload's fixed part.
    #[error("nav payload is {len} bytes, shorter than its {NAV_FIXED_LEN}-byte fixed part")]
    NavTooShort {
        /// Payload length, bytes.
        len: usize,
    },
}

/// The shape of a structurally valid frame payload, as [`check_frame`] found it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameShape {
    /// Bits per sample: 8 or 16.
    pub bits: u8,
    /// Number of segments.
    pub n_segments: u8,
    /// Total samples over all segments.
    pub total_samples: usize,
}

/// A decoded nav payload, borrowing its bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NavPayload<'a> {
    /// Port the bytes came from (the recorder's numbering).
    pub port: u8,
    /// Host receive time, nanoseconds since the Unix epoch.
    pub receive_time_ns: u64,
    /// The bytes exactly as they came off the port.
    pub bytes: &'a [u8],
}

#[inline]
fn le_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

#[inline]
fn le_u64(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

#[inline]
fn le_f32(b: &[u8], at: usize) -> f32 {
    f32::from_bits(le_u32(b, at))
}

#[inline]
fn le_f64(b: &[u8], at: usize) -> f64 {
    f64::from_bits(le_u64(b, at))
}

/// Appends the 48-byte geometry prefix of a GeoFrame payload (anchor, then direction) to `out`.
/// Non-finite values are refused ([`FrameError::BadGeometry`]); `out` is then left as it was.
pub fn encode_geometry(g: &PulseGeometry, out: &mut Vec<u8>) -> Result<(), FrameError> {
    if !g.anchor.iter().chain(&g.direction).all(|v| v.is_finite()) {
        return Err(FrameError::BadGeometry("non-finite anchor or direction"));
    }
    for v in g.anchor.iter().chain(&g.direction) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    Ok(())
}

/// Splits a GeoFrame payload into its geometry and the digitizer frame payload that follows it.
/// Errors when the payload is shorter than [`GEOMETRY_LEN`] or a value is not finite; the frame
/// part is not checked here (see [`check_frame`]).
pub fn split_geo_frame(payload: &[u8]) -> Result<(PulseGeometry, &[u8]), FrameError> {
    if payload.len() < GEOMETRY_LEN {
        return Err(FrameError::BadGeometry("payload shorter than 48 bytes"));
    }
    let v = |i: usize| le_f64(payload, 8 * i);
    let g = PulseGeometry {
        anchor: [v(0), v(1), v(2)],
        direction: [v(3), v(4), v(5)],
    };
    if !g.anchor.iter().chain(&g.direction).all(|v| v.is_finite()) {
        return Err(FrameError::BadGeometry("non-finite anchor or direction"));
    }
    Ok((g, &payload[GEOMETRY_LEN..]))
}

/// Appends the frame payload of `pulse` to `out` (clear `out` first for a standalone payload).
/// Segments are written in order with the samples of [`Segment::range`]. On error `out` is left
/// as it was.
pub fn encode_frame(pulse: &Pulse, out: &mut Vec<u8>) -> Result<(), FrameError> {
    let bytes_per_sample = match pulse.bits {
        8 => 1usize,
        16 => 2,
        bits => return Err(FrameError::BadBits { bits }),
    };
    if pulse.segments.len() > u8::MAX as usize {
        return Err(FrameError::TooManySegments {
            n: pulse.segments.len(),
        });
    }
    let mut total = 0usize;
    for (index, s) in pulse.segments.iter().enumerate() {
        let end = s.first as u64 + s.len as u64;
        if end > pulse.raw.len() as u64 {
            return Err(FrameError::SegmentOutOfBounds {
                index,
                first: s.first as u64,
                end,
                raw_len: pulse.raw.len(),
            });
        }
        total += s.len as usize;
    }
    let start_len = out.len();
    out.reserve(
        FRAME_FIXED_LEN + SEGMENT_HEADER_LEN * pulse.segments.len() + total * bytes_per_sample,
    );
    out.extend_from_slice(&pulse.pulse_id.to_le_bytes());
    out.extend_from_slice(&pulse.gps_time.to_le_bytes());
    out.extend_from_slice(&pulse.scan_angle_deg[0].to_le_bytes());
    out.extend_from_slice(&pulse.scan_angle_deg[1].to_le_bytes());
    out.extend_from_slice(&pulse.sample_ns.to_le_bytes());
    out.extend_from_slice(&pulse.gain_v_per_dn.to_le_bytes());
    out.extend_from_slice(&pulse.offset_v.to_le_bytes());
    out.push(pulse.bits);
    out.push(pulse.segments.len() as u8);
    out.extend_from_slice(&[0, 0]);
    for (index, s) in pulse.segments.iter().enumerate() {
        out.push(match s.kind {
            SegmentKind::Outgoing => 0,
            SegmentKind::Return => 1,
        });
        out.push(s.channel);
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&s.start_ns.to_le_bytes());
        out.extend_from_slice(&s.len.to_le_bytes());
        let samples = &pulse.raw[s.range()];
        if bytes_per_sample == 1 {
            for &v in samples {
                if v > u8::MAX as u16 {
                    out.truncate(start_len);
                    return Err(FrameError::SampleOutOfRange { index, value: v });
                }
                out.push(v as u8);
            }
        } else {
            for &v in samples {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    Ok(())
}

/// Checks that a frame payload is well formed (bits 8 or 16, known segment kinds, declared sizes
/// adding up to exactly its length) without decoding the samples.
pub fn check_frame(payload: &[u8]) -> Result<FrameShape, FrameError> {
    let len = payload.len();
    if len < FRAME_FIXED_LEN {
        return Err(FrameError::TooShort { len });
    }
    let bits = payload[40];
    let bytes_per_sample: u64 = match bits {
        8 => 1,
        16 => 2,
        bits => return Err(FrameError::BadBits { bits }),
    };
    let n_segments = payload[41];
    let mut pos = FRAME_FIXED_LEN as u64;
    let mut total_samples = 0usize;
    for index in 0..n_segments as usize {
        if pos + SEGMENT_HEADER_LEN as u64 > len as u64 {
            return Err(FrameError::LengthMismatch {
                len,
                declared: pos + SEGMENT_HEADER_LEN as u64,
            });
        }
        let at = pos as usize;
        let kind = payload[at];
        if kind > 1 {
            return Err(FrameError::BadSegmentKind { index, kind });
        }
        let n = le_u32(payload, at + 12) as u64;
        pos += SEGMENT_HEADER_LEN as u64 + n * bytes_per_sample;
        if pos > len as u64 {
            return Err(FrameError::LengthMismatch { len, declared: pos });
        }
        total_samples += n as usize;
    }
    if pos != len as u64 {
        return Err(FrameError::LengthMismatch { len, declared: pos });
    }
    Ok(FrameShape {
        bits,
        n_segments,
        total_samples,
    })
}

/// Decodes a frame payload into `pulse`, reusing its buffers: the digitizer fields are set,
/// `segments` and `raw` are replaced, `signal` is cleared and `noise` reset. `seq` and `arrived`
/// are left alone (the source sets them). On error the pulse is unchanged.
///
/// Does not allocate when `pulse.segments` and `pulse.raw` already have the capacity.
pub fn decode_frame(payload: &[u8], pulse: &mut Pulse) -> Result<(), FrameError> {
    let shape = check_frame(payload)?;
    if shape.total_samples > u32::MAX as usize {
        return Err(FrameError::LengthMismatch {
            len: payload.len(),
            declared: shape.total_samples as u64,
        });
    }
    let p = payload;
    pulse.pulse_id = le_u64(p, 0);
    pulse.gps_time = le_f64(p, 8);
    pulse.scan_angle_deg = [le_f32(p, 16), le_f32(p, 20)];
    pulse.sample_ns = le_f64(p, 24);
    pulse.gain_v_per_dn = le_f32(p, 32);
    pulse.offset_v = le_f32(p, 36);
    pulse.bits = shape.bits;
    pulse.segments.clear();
    pulse.raw.clear();
    pulse.signal.clear();
    pulse.noise = Default::default();
    pulse.segments.reserve(shape.n_segments as usize);
    pulse.raw.reserve(shape.total_samples);
    let mut at = FRAME_FIXED_LEN;
    for _ in 0..shape.n_segments {
        let kind = if p[at] == 0 {
            SegmentKind::Outgoing
        } else {
            SegmentKind::Return
        };
        let channel = p[at + 1];
        let start_ns = le_f64(p, at + 4);
        let n = le_u32(p, at + 12);
        at += SEGMENT_HEADER_LEN;
        let first = pulse.raw.len() as u32;
        if shape.bits == 8 {
            let bytes = &p[at..at + n as usize];
            pulse.raw.extend(bytes.iter().map(|&b| b as u16));
            at += n as usize;
        } else {
            let bytes = &p[at..at + 2 * n as usize];
            pulse.raw.extend(
                bytes
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]])),
            );
            at += 2 * n as usize;
        }
        pulse.segments.push(Segment {
            kind,
            channel,
            start_ns,
            first,
            len: n,
        });
    }
    Ok(())
}

/// Appends a nav payload to `out`: `port`, three reserved zero bytes, `receive_time_ns`
/// (host clock, ns since the Unix epoch), then `bytes` verbatim.
pub fn encode_nav(port: u8, receive_time_ns: u64, bytes: &[u8], out: &mut Vec<u8>) {
    out.reserve(NAV_FIXED_LEN + bytes.len());
    out.extend_from_slice(&[port, 0, 0, 0]);
    out.extend_from_slice(&receive_time_ns.to_le_bytes());
    out.extend_from_slice(bytes);
}

/// Decodes a nav payload, borrowing its bytes.
pub fn decode_nav(payload: &[u8]) -> Result<NavPayload<'_>, FrameError> {
    if payload.len() < NAV_FIXED_LEN {
        return Err(FrameError::NavTooShort { len: payload.len() });
    }
    Ok(NavPayload {
        port: payload[0],
        receive_time_ns: le_u64(payload, 4),
        bytes: &payload[NAV_FIXED_LEN..],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_pulse(bits: u8) -> Pulse {
        let mut p = Pulse {
            pulse_id: 0x0102_0304_0506_0708,
            gps_time: 123_456.789_012,
            scan_angle_deg: [-12.5, f32::NAN],
            sample_ns: 1.0,
            gain_v_per_dn: 0.0025,
            offset_v: -0.1,
            bits,
            ..Pulse::default()
        };
        let hi = if bits == 8 { 255 } else { 65535 };
        p.push_segment(SegmentKind::Outgoing, 0, -4.0, [0, 1, hi, 17]);
        p.push_segment(SegmentKind::Return, 2, 6021.5, (0..50).map(|i| i * 5));
        p
    }

    fn assert_same(a: &Pulse, b: &Pulse) {
        assert_eq!(a.pulse_id, b.pulse_id);
        assert_eq!(a.gps_time.to_bits(), b.gps_time.to_bits());
        assert_eq!(a.scan_angle_deg[0].to_bits(), b.scan_angle_deg[0].to_bits());
        assert_eq!(a.scan_angle_deg[1].to_bits(), b.scan_angle_deg[1].to_bits());
        assert_eq!(a.sample_ns.to_bits(), b.sample_ns.to_bits());
        assert_eq!(a.gain_v_per_dn.to_bits(), b.gain_v_per_dn.to_bits());
        assert_eq!(a.offset_v.to_bits(), b.offset_v.to_bits());
        assert_eq!(a.bits, b.bits);
        assert_eq!(a.segments, b.segments);
        assert_eq!(a.raw, b.raw);
    }

    #[test]
    fn frame_round_trips_8_and_16_bit() {
        for bits in [8, 16] {
            let p = sample_pulse(bits);
            let mut buf = Vec::new();
            encode_frame(&p, &mut buf).unwrap();
            let bps = bits as usize / 8;
            assert_eq!(
                buf.len(),
                FRAME_FIXED_LEN + 2 * SEGMENT_HEADER_LEN + 54 * bps
            );
            let shape = check_frame(&buf).unwrap();
            assert_eq!(shape.total_samples, 54);
            assert_eq!(shape.n_segments, 2);
            let mut q = Pulse {
                seq: 99,
                ..Pulse::default()
            };
            let arrived = q.arrived;
            decode_frame(&buf, &mut q).unwrap();
            assert_same(&p, &q);
            assert_eq!(q.seq, 99, "seq is the source's business");
            assert_eq!(q.arrived, arrived);
        }
    }

    #[test]
    fn layout_is_little_endian_as_documented() {
        let mut p = Pulse {
            pulse_id: 7,
            bits: 16,
            ..Pulse::default()
        };
        p.push_segment(SegmentKind::Return, 3, 2.0, [0x1234]);
        let mut buf = Vec::new();
        encode_frame(&p, &mut buf).unwrap();
        assert_eq!(&buf[0..8], &7u64.to_le_bytes());
        assert_eq!(buf[40], 16);
        assert_eq!(buf[41], 1);
        assert_eq!(&buf[42..44], &[0, 0]);
        assert_eq!(buf[44], 1);
        assert_eq!(buf[45], 3);
        assert_eq!(&buf[48..56], &2.0f64.to_le_bytes());
        assert_eq!(&buf[56..60], &1u32.to_le_bytes());
        assert_eq!(&buf[60..62], &[0x34, 0x12]);
    }

    #[test]
    fn decode_reuses_buffers() {
        let p = sample_pulse(16);
        let mut buf = Vec::new();
        encode_frame(&p, &mut buf).unwrap();
        let mut q = Pulse::default();
        decode_frame(&buf, &mut q).unwrap();
        let (raw_ptr, seg_ptr) = (q.raw.as_ptr(), q.segments.as_ptr());
        let cap = q.raw.capacity();
        for _ in 0..10 {
            decode_frame(&buf, &mut q).unwrap();
        }
        assert_eq!(q.raw.as_ptr(), raw_ptr);
        assert_eq!(q.segments.as_ptr(), seg_ptr);
        assert_eq!(q.raw.capacity(), cap);
        assert_same(&p, &q);
    }

    #[test]
    fn encode_rejects_bad_pulses_and_leaves_out_alone() {
        let mut out = vec![9u8; 3];
        let mut p = sample_pulse(8);
        p.raw[2] = 256;
        assert_eq!(
            encode_frame(&p, &mut out),
            Err(FrameError::SampleOutOfRange {
                index: 0,
                value: 256
            })
        );
        assert_eq!(out, vec![9u8; 3]);
        let mut p = sample_pulse(16);
        p.bits = 12;
        assert_eq!(
            encode_frame(&p, &mut out),
            Err(FrameError::BadBits { bits: 12 })
        );
        let mut p = sample_pulse(16);
        p.segments[1].len += 1;
        assert!(matches!(
            encode_frame(&p, &mut out),
            Err(FrameError::SegmentOutOfBounds { index: 1, .. })
        ));
        let mut p = Pulse::default();
        for _ in 0..256 {
            p.push_segment(SegmentKind::Return, 0, 0.0, [1]);
        }
        assert_eq!(
            encode_frame(&p, &mut out),
            Err(FrameError::TooManySegments { n: 256 })
        );
        assert_eq!(out, vec![9u8; 3]);
    }

    #[test]
    fn malformed_payloads_are_errors_and_leave_the_pulse_alone() {
        let p = sample_pulse(16);
        let mut buf = Vec::new();
        encode_frame(&p, &mut buf).unwrap();
        let mut q = sample_pulse(8);
        // every proper prefix and one extra byte disagree with the declared sizes
        for cut in 0..buf.len() {
            assert!(decode_frame(&buf[..cut], &mut q).is_err(), "cut {cut}");
        }
        let mut longer = buf.clone();
        longer.push(0);
        assert!(matches!(
            check_frame(&longer),
            Err(FrameError::LengthMismatch { .. })
        ));
        let mut bad = buf.clone();
        bad[40] = 12;
        assert_eq!(check_frame(&bad), Err(FrameError::BadBits { bits: 12 }));
        let mut bad = buf.clone();
        bad[FRAME_FIXED_LEN] = 2;
        assert_eq!(
            check_frame(&bad),
            Err(FrameError::BadSegmentKind { index: 0, kind: 2 })
        );
        let mut bad = buf.clone();
        bad[FRAME_FIXED_LEN + 12..FRAME_FIXED_LEN + 16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            check_frame(&bad),
            Err(FrameError::LengthMismatch { .. })
        ));
        assert_same(&q, &sample_pulse(8));
    }

    #[test]
    fn nav_round_trips() {
        let mut out = Vec::new();
        encode_nav(3, 1_700_000_000_123_456_789, b"$GPGGA,1*00\r\n", &mut out);
        assert_eq!(out.len(), NAV_FIXED_LEN + 13);
        let n = decode_nav(&out).unwrap();
        assert_eq!(n.port, 3);
        assert_eq!(n.receive_time_ns, 1_700_000_000_123_456_789);
        assert_eq!(n.bytes, b"$GPGGA,1*00\r\n");
        assert_eq!(
            decode_nav(&out[..11]),
            Err(FrameError::NavTooShort { len: 11 })
        );
        assert_eq!(decode_nav(&out[..12]).unwrap().bytes, b"");
    }
}
