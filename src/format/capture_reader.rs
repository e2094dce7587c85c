//! [`CaptureReader`]: walks the records of a capture, recovering every complete record of a
//! truncated or damaged file.
//!
//! The input is read in large chunks into one internal buffer and parsed in place: records are
//! returned as borrows of that buffer, so walking a capture does not allocate per record.
//!
//! Resync (see `docs/formats.md`): wherever a valid record does not start — no sync marker, a
//! length above [`MAX_PAYLOAD_LEN`], a CRC mismatch, or a length that runs past the end of the
//! input — the reader advances one byte and scans for the next sync marker. Bytes passed over
//! before the next valid record are counted in [`SkipReport::bytes_skipped`]; bytes after which no
//! valid record follows are the [`SkipReport::truncated_tail_bytes`].

use std::fs::File;
use std::io::{self, Read};
use std::path::{Path, PathBuf};

use super::capture::{
    CaptureError, MAX_PAYLOAD_LEN, PREAMBLE_LEN, RECORD_CRC_LEN, RECORD_HEADER_LEN,
    RECORD_OVERHEAD, RecordKind, SYNC, SkipReport, check_preamble,
};
use super::frame::{
    FrameError, GEOMETRY_LEN, check_frame, decode_frame, decode_nav, split_geo_frame,
};
use crate::pulse::Pulse;

/// Size of each read from the input, bytes.
const CHUNK: usize = 1024 * 1024;
/// Compact the buffer before reading when less than this much room is left after the data.
const MIN_READ: usize = 64 * 1024;

/// One record of a capture, borrowed from the reader's buffer (valid until the next call).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Record<'a> {
    /// Header text (TOML): the sensor description and configuration in force from here on.
    Header(&'a str),
    /// A digitizer frame (one pulse); decode it with [`FrameRecord::decode_into`].
    Frame(FrameRecord<'a>),
    /// Navigation bytes as they came off a port.
    Nav {
        /// Port number (the recorder's numbering).
        port: u8,
        /// Host receive time, nanoseconds since the Unix epoch.
        receive_time_ns: u64,
        /// The bytes verbatim.
        bytes: &'a [u8],
    },
}

/// A digitizer frame record whose payload has been checked to be well formed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRecord<'a> {
    payload: &'a [u8],
    /// The 48-byte geometry prefix of a GeoFrame record (checked finite), `None` for a plain
    /// DigitizerFrame.
    geometry: Option<&'a [u8]>,
}

impl<'a> FrameRecord<'a> {
    /// The frame payload bytes (layout in `docs/formats.md`).
    pub fn payload(&self) -> &'a [u8] {
        self.payload
    }

    /// The digitizer's pulse id, without decoding the samples.
    pub fn pulse_id(&self) -> u64 {
        let mut b = [0u8; 8];
        if let Some(s) = self.payload.get(..8) {
            b.copy_from_slice(s);
        }
        u64::from_le_bytes(b)
    }

    /// Whether the record carries the pulse's geometry (a GeoFrame record).
    pub fn has_geometry(&self) -> bool {
        self.geometry.is_some()
    }

    /// Decodes the frame into `pulse`, reusing its buffers (see [`decode_frame`]), and sets its
    /// geometry (`None` for a plain frame); `seq` and `arrived` are left for the source to set.
    pub fn decode_into(&self, pulse: &mut Pulse) -> Result<(), FrameError> {
        let geometry = match self.geometry {
            Some(g) => Some(split_geo_frame(g)?.0),
            None => None,
        };
        decode_frame(self.payload, pulse)?;
        pulse.geometry = geometry;
        Ok(())
    }
}

/// What a valid record turned out to be, by offsets into the buffer (no borrow held).
enum Found {
    Header,
    Frame,
    GeoFrame,
    Nav,
}

/// Reads the records of a capture from any byte source.
pub struct CaptureReader<R: Read> {
    inner: R,
    path: PathBuf,
    version: (u16, u16),
    buf: Vec<u8>,
    /// Index in `buf` of the next unparsed byte.
    start: usize,
    /// End of valid data in `buf`.
    end: usize,
    /// Input offset of `buf[0]`.
    buf_offset: u64,
    eof: bool,
    done: bool,
    /// Input offset where sync was lost (the first byte not part of a valid record), if it is.
    lost_at: Option<u64>,
    skipped: SkipReport,
}

impl CaptureReader<File> {
    /// Opens the capture at `path` and checks its preamble.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, CaptureError> {
        let path = path.as_ref();
        let file = File::open(path).map_err(|source| CaptureError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        CaptureReader::new(file, path)
    }
}

impl<R: Read> CaptureReader<R> {
    /// A reader over `reader`, named `display_name` in errors; reads and checks the preamble.
    ///
    /// Errors: [`CaptureError::Empty`], [`CaptureError::NotACapture`],
    /// [`CaptureError::TruncatedPreamble`], [`CaptureError::NewerVersion`] (a newer major
    /// version; newer minor versions are read), [`CaptureError::Io`].
    pub fn new(reader: R, display_name: impl Into<PathBuf>) -> Result<Self, CaptureError> {
        let mut r = CaptureReader {
            inner: reader,
            path: display_name.into(),
            version: (0, 0),
            buf: vec![0u8; CHUNK],
            start: 0,
            end: 0,
            buf_offset: 0,
            eof: false,
            done: false,
            lost_at: None,
            skipped: SkipReport::default(),
        };
        r.fill(PREAMBLE_LEN)?;
        let avail = &r.buf[..r.end.min(PREAMBLE_LEN)];
        r.version = check_preamble(avail, &r.path)?;
        r.start = PREAMBLE_LEN;
        Ok(r)
    }

    /// The file's format version `(major, minor)`.
    pub fn version(&self) -> (u16, u16) {
        self.version
    }

    /// The path (or display name) being read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What has been skipped so far. The last resync and the truncated tail are settled when
    /// [`next_record`](Self::next_record) has returned `None`.
    pub fn skipped(&self) -> &SkipReport {
        &self.skipped
    }

    /// Input bytes consumed so far (preamble included): for progress reporting.
    pub fn position(&self) -> u64 {
        self.buf_offset + self.start as u64
    }

    /// Ensures `n` bytes are buffered from `start`, unless the input ends first.
    fn fill(&mut self, n: usize) -> Result<(), CaptureError> {
        if self.end - self.start >= n || self.eof {
            return Ok(());
        }
        if self.start + n > self.buf.len()
            || (self.buf.len() - self.end < MIN_READ && self.start > 0)
        {
            self.buf.copy_within(self.start..self.end, 0);
            self.buf_offset += self.start as u64;
            self.end -= self.start;
            self.start = 0;
            if n > self.buf.len() {
                let want = n.div_ceil(CHUNK) * CHUNK;
                self.buf.resize(want, 0);
            }
        }
        while self.end - self.start < n {
            match self.inner.read(&mut self.buf[self.end..]) {
                Ok(0) => {
                    self.eof = true;
                    break;
                }
                Ok(k) => self.end += k.min(self.buf.len() - self.end),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(source) => {
                    return Err(CaptureError::Io {
                        path: self.path.clone(),
                        source,
                    });
                }
            }
        }
        Ok(())
    }

    fn lose_sync(&mut self) {
        if self.lost_at.is_none() {
            self.lost_at = Some(self.position());
        }
    }

    /// Moves past the byte at `start` and on to the next place a sync marker could begin (a full
    /// marker, or a prefix of one at the end of the buffered data).
    fn scan_on(&mut self) {
        self.start += 1;
        let hay = &self.buf[self.start..self.end];
        let mut from = 0;
        while let Some(k) = hay[from..].iter().position(|&b| b == SYNC[0]) {
            let at = from + k;
            let n = (hay.len() - at).min(SYNC.len());
            if hay[at..at + n] == SYNC[..n] {
                self.start += at;
                return;
            }
            from = at + 1;
        }
        self.start = self.end;
    }

    /// Settles the skip report at the end of the input.
    fn finish(&mut self) {
        let eof_pos = self.buf_offset + self.end as u64;
        let tail_from = self.lost_at.take().unwrap_or_else(|| self.position());
        self.skipped.truncated_tail_bytes += eof_pos - tail_from;
        self.start = self.end;
        self.done = true;
    }

    /// The next record, `None` at the end of the input. Damaged stretches are skipped and
    /// counted in [`skipped`](Self::skipped); only an I/O error is returned as `Err` (after which
    /// the reader returns `None`). Never panics, whatever the input.
    pub fn next_record(&mut self) -> Option<Result<Record<'_>, CaptureError>> {
        if self.done {
            return None;
        }
        let (found, payload_at, payload_len) = loop {
            if let Err(e) = self.fill(RECORD_OVERHEAD) {
                self.done = true;
                return Some(Err(e));
            }
            if self.end - self.start < RECORD_OVERHEAD {
                self.finish();
                return None;
            }
            let h = &self.buf[self.start..self.start + RECORD_HEADER_LEN];
            if h[..4] != SYNC {
                self.lose_sync();
                self.scan_on();
                continue;
            }
            let kind = h[4];
            let len = u32::from_le_bytes([h[8], h[9], h[10], h[11]]);
            if len > MAX_PAYLOAD_LEN {
                self.lose_sync();
                self.scan_on();
                continue;
            }
            let total = RECORD_OVERHEAD + len as usize;
            if let Err(e) = self.fill(total) {
                self.done = true;
                return Some(Err(e));
            }
            if self.end - self.start < total {
                // Runs past the end: maybe a cut-off record, maybe a corrupt length. Scan on.
                self.lose_sync();
                self.scan_on();
                continue;
            }
            let rec = &self.buf[self.start..self.start + total];
            let crc_at = total - RECORD_CRC_LEN;
            let stored = u32::from_le_bytes([
                rec[crc_at],
                rec[crc_at + 1],
                rec[crc_at + 2],
                rec[crc_at + 3],
            ]);
            if crc32c::crc32c(&rec[4..crc_at]) != stored {
                self.skipped.bad_checksums += 1;
                self.lose_sync();
                self.scan_on();
                continue;
            }
            // A valid record starts here.
            let payload = &rec[RECORD_HEADER_LEN..crc_at];
            let found = match RecordKind::from_u8(kind) {
                Some(RecordKind::Header) => {
                    std::str::from_utf8(payload).ok().map(|_| Found::Header)
                }
                Some(RecordKind::DigitizerFrame) => check_frame(payload).ok().map(|_| Found::Frame),
                Some(RecordKind::GeoFrame) => split_geo_frame(payload)
                    .ok()
                    .and_then(|(_, frame)| check_frame(frame).ok())
                    .map(|_| Found::GeoFrame),
                Some(RecordKind::NavBytes) => decode_nav(payload).ok().map(|_| Found::Nav),
                None => None,
            };
            if let Some(lost) = self.lost_at.take() {
                self.skipped.bytes_skipped += self.position() - lost;
                self.skipped.resyncs += 1;
            }
            let payload_at = self.start + RECORD_HEADER_LEN;
            self.start += total;
            match found {
                Some(f) => break (f, payload_at, len as usize),
                None => {
                    if RecordKind::from_u8(kind).is_some() {
                        self.skipped.bad_payloads += 1;
                    } else {
                        self.skipped.unknown_kinds += 1;
                    }
                    self.skipped.bytes_skipped += total as u64;
                }
            }
        };
        let payload = &self.buf[payload_at..payload_at + payload_len];
        let record = match found {
            Found::Header => Record::Header(std::str::from_utf8(payload).unwrap_or_default()),
            Found::Frame => Record::Frame(FrameRecord {
                payload,
                geometry: None,
            }),
            Found::GeoFrame => Record::Frame(FrameRecord {
                payload: payload.get(GEOMETRY_LEN..).unwrap_or_default(),
                geometry: payload.get(..GEOMETRY_LEN),
            }),
            Found::Nav => match decode_nav(payload) {
                Ok(n) => Record::Nav {
                    port: n.port,
                    receive_time_ns: n.receive_time_ns,
                    bytes: n.bytes,
                },
                Err(_) => Record::Nav {
                    port: 0,
                    receive_time_ns: 0,
                    bytes: &[],
                },
            },
        };
        Some(Ok(record))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::capture::{FlushPolicy, preamble};
    use crate::format::capture_writer::CaptureWriter;
    use crate::pulse::SegmentKind;
    use std::io::Cursor;

    fn pulse(id: u64) -> Pulse {
        let mut p = Pulse {
            pulse_id: id,
            ..Pulse::default()
        };
        p.push_segment(SegmentKind::Outgoing, 0, -3.0, [10, 20, 30]);
        p.push_segment(
            SegmentKind::Return,
            1,
            800.0,
            (0..40).map(|i| i * 100 + id as u16),
        );
        p
    }

    fn capture(n: u64) -> Vec<u8> {
        let mut w = CaptureWriter::from_writer(
            Vec::new(),
            "mem",
            "sensor = \"test\"",
            FlushPolicy::default(),
        )
        .unwrap();
        for i in 0..n {
            w.write_pulse(&pulse(i)).unwrap();
            w.write_nav(2, 1000 + i, b"$GPZDA*00\r\n").unwrap();
        }
        w.finish().unwrap()
    }

    /// Walks a capture: (frame ids, nav count, headers, report).
    fn walk(bytes: &[u8]) -> (Vec<u64>, usize, Vec<String>, SkipReport) {
        let mut r = CaptureReader::new(Cursor::new(bytes), "mem").unwrap();
        let (mut ids, mut navs, mut headers) = (Vec::new(), 0, Vec::new());
        let mut p = Pulse::default();
        while let Some(rec) = r.next_record() {
            match rec.unwrap() {
                Record::Header(h) => headers.push(h.to_string()),
                Record::Frame(f) => {
                    f.decode_into(&mut p).unwrap();
                    assert_eq!(f.pulse_id(), p.pulse_id);
                    let want = pulse(p.pulse_id);
                    assert_eq!(p.raw, want.raw);
                    assert_eq!(p.segments, want.segments);
                    ids.push(p.pulse_id);
                }
                Record::Nav {
                    port,
                    receive_time_ns,
                    bytes,
                } => {
                    assert_eq!(port, 2);
                    assert!(receive_time_ns >= 1000);
                    assert_eq!(bytes, b"$GPZDA*00\r\n");
                    navs += 1;
                }
            }
        }
        assert_eq!(r.position(), bytes.len() as u64);
        assert!(r.next_record().is_none());
        (ids, navs, headers, *r.skipped())
    }

    #[test]
    fn reads_what_was_written() {
        let bytes = capture(50);
        let (ids, navs, headers, rep) = walk(&bytes);
        assert_eq!(ids, (0..50).collect::<Vec<_>>());
        assert_eq!(navs, 50);
        assert_eq!(headers, vec!["sensor = \"test\"".to_string()]);
        assert!(rep.is_clean(), "{rep:?}");
    }

    #[test]
    fn only_a_preamble_is_an_empty_capture() {
        let (ids, navs, headers, rep) = walk(&preamble());
        assert!(ids.is_empty() && navs == 0 && headers.is_empty());
        assert!(rep.is_clean());
    }

    #[test]
    fn garbage_is_skipped_and_counted() {
        let clean = capture(3);
        let mut bytes = clean.clone();
        // garbage, including a false sync marker, after the header record
        let header_end = PREAMBLE_LEN + RECORD_OVERHEAD + "sensor = \"test\"".len();
        let junk = [1u8, 0xF5, b'W', b'L', b'R', 2, 0, 0, 0, 9, 9, 9, 0xF5, 7];
        bytes.splice(header_end..header_end, junk);
        let (ids, navs, _, rep) = walk(&bytes);
        assert_eq!(ids, vec![0, 1, 2]);
        assert_eq!(navs, 3);
        assert_eq!(rep.bytes_skipped, junk.len() as u64);
        assert_eq!(rep.resyncs, 1);
        assert_eq!(rep.truncated_tail_bytes, 0);
    }

    #[test]
    fn a_huge_length_is_not_trusted() {
        let mut bytes = capture(2);
        let at = PREAMBLE_LEN + 8;
        bytes[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let (ids, navs, headers, rep) = walk(&bytes);
        assert_eq!(ids, vec![0, 1]);
        assert_eq!(navs, 2);
        assert!(headers.is_empty());
        assert_eq!(rep.resyncs, 1);
        assert_eq!(rep.bytes_skipped, (RECORD_OVERHEAD + 15) as u64);
    }

    #[test]
    fn unknown_kinds_and_bad_payloads_are_counted() {
        let mut bytes = preamble().to_vec();
        let mut rec = |kind: u8, payload: &[u8]| {
            let mut r = SYNC.to_vec();
            r.extend_from_slice(&[kind, 0, 0, 0]);
            r.extend_from_slice(&(payload.len() as u32).to_le_bytes());
            r.extend_from_slice(payload);
            let crc = crc32c::crc32c(&r[4..]);
            r.extend_from_slice(&crc.to_le_bytes());
            bytes.extend_from_slice(&r);
            r.len() as u64
        };
        let mut skipped = 0;
        skipped += rec(77, b"from the future");
        skipped += rec(2, &[0u8; 10]); // frame too short
        skipped += rec(1, &[0xFF, 0xFE]); // header not UTF-8
        skipped += rec(3, &[0u8; 4]); // nav too short
        rec(1, b"ok = true");
        let mut r = CaptureReader::new(Cursor::new(&bytes), "mem").unwrap();
        assert_eq!(
            r.next_record().unwrap().unwrap(),
            Record::Header("ok = true")
        );
        assert!(r.next_record().is_none());
        let rep = r.skipped();
        assert_eq!(rep.unknown_kinds, 1);
        assert_eq!(rep.bad_payloads, 3);
        assert_eq!(rep.bytes_skipped, skipped);
        assert_eq!(rep.resyncs, 0);
    }

    /// A reader that hands out one byte per call, to exercise buffer refills everywhere.
    struct Trickle<'a>(&'a [u8]);
    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            if self.0.is_empty() || buf.is_empty() {
                return Ok(0);
            }
            buf[0] = self.0[0];
            self.0 = &self.0[1..];
            Ok(1)
        }
    }

    #[test]
    fn tiny_reads_give_the_same_records() {
        let bytes = capture(20);
        let mut r = CaptureReader::new(Trickle(&bytes), "trickle").unwrap();
        let mut n = 0;
        while let Some(rec) = r.next_record() {
            rec.unwrap();
            n += 1;
        }
        assert_eq!(n, 41);
        assert!(r.skipped().is_clean());
    }

    #[test]
    fn records_larger_than_the_chunk_are_read() {
        let mut w =
            CaptureWriter::from_writer(Vec::new(), "mem", "", FlushPolicy::default()).unwrap();
        let big: Vec<u8> = (0..3 * CHUNK + 17).map(|i| (i % 251) as u8).collect();
        w.write_nav(9, 1, &big).unwrap();
        w.write_nav(9, 2, b"after").unwrap();
        let bytes = w.finish().unwrap();
        let mut r = CaptureReader::new(Cursor::new(&bytes), "mem").unwrap();
        assert!(matches!(r.next_record(), Some(Ok(Record::Header("")))));
        match r.next_record() {
            Some(Ok(Record::Nav { bytes, .. })) => assert_eq!(bytes, &big[..]),
            other => panic!("{other:?}"),
        }
        match r.next_record() {
            Some(Ok(Record::Nav { bytes, .. })) => assert_eq!(bytes, b"after"),
            other => panic!("{other:?}"),
        }
        assert!(r.next_record().is_none());
    }

    struct Failing;
    impl Read for Failing {
        fn read(&mut self, _: &mut [u8]) -> io::Result<usize> {
            Err(io::Error::other("disk on fire"))
        }
    }

    /// Hands out `good`, then fails.
    struct FailAfter<'a>(&'a [u8]);
    impl Read for FailAfter<'_> {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            if self.0.is_empty() {
                return Err(io::Error::other("cable pulled"));
            }
            let n = buf.len().min(self.0.len());
            buf[..n].copy_from_slice(&self.0[..n]);
            self.0 = &self.0[n..];
            Ok(n)
        }
    }

    #[test]
    fn an_io_error_mid_stream_is_returned_once() {
        let bytes = capture(5);
        let cut = bytes.len() - 30;
        let mut r = CaptureReader::new(FailAfter(&bytes[..cut]), "usb").unwrap();
        let mut ok = 0;
        let mut errs = Vec::new();
        while let Some(rec) = r.next_record() {
            match rec {
                Ok(_) => ok += 1,
                Err(e) => errs.push(e.to_string()),
            }
        }
        assert_eq!(ok, 10, "records before the failure are returned");
        assert_eq!(errs.len(), 1);
        assert!(
            errs[0].contains("usb") && errs[0].contains("cable pulled"),
            "{errs:?}"
        );
        assert!(r.next_record().is_none());
    }

    #[test]
    fn io_errors_name_the_source() {
        let err = match CaptureReader::new(Failing, "/dev/fire") {
            Err(e) => e,
            Ok(_) => panic!("read from a failing source"),
        };
        let msg = err.to_string();
        assert!(
            msg.contains("/dev/fire") && msg.contains("disk on fire"),
            "{msg}"
        );
    }

    #[test]
    fn geoframes_carry_the_pulse_geometry_and_plain_frames_clear_it() {
        use crate::pulse::PulseGeometry;
        let g = PulseGeometry {
            anchor: [533_000.125, 5_260_000.5, 1_234.75],
            direction: [0.01, -0.02, -0.1488],
        };
        let mut w =
            CaptureWriter::from_writer(Vec::new(), "mem", "h", FlushPolicy::default()).unwrap();
        let mut geo = pulse(7);
        geo.geometry = Some(g);
        w.write_pulse(&geo).unwrap();
        w.write_pulse(&pulse(8)).unwrap();
        // A geometry that is not finite is refused and writes nothing.
        let mut bad = pulse(9);
        bad.geometry = Some(PulseGeometry {
            anchor: [f64::NAN, 0.0, 0.0],
            direction: [0.0; 3],
        });
        assert!(w.write_pulse(&bad).is_err());
        let bytes = w.finish().unwrap();
        assert_eq!(&bytes[8..12], &[1, 0, 1, 0], "version 1.1");

        let mut r = CaptureReader::new(Cursor::new(&bytes[..]), "mem").unwrap();
        let mut p = Pulse::default();
        let mut seen = Vec::new();
        while let Some(rec) = r.next_record() {
            if let Record::Frame(f) = rec.unwrap() {
                f.decode_into(&mut p).unwrap();
                assert_eq!(p.raw, pulse(p.pulse_id).raw);
                assert_eq!(f.pulse_id(), p.pulse_id);
                seen.push((p.pulse_id, f.has_geometry(), p.geometry));
            }
        }
        // The plain frame decoded into the same pulse after the GeoFrame has no geometry.
        assert_eq!(seen, vec![(7, true, Some(g)), (8, false, None)]);
        assert!(r.skipped().is_clean());
    }

    #[test]
    fn a_geoframe_with_a_non_finite_geometry_is_a_bad_payload() {
        use crate::format::capture::record_crc;
        use crate::format::frame::encode_frame;
        let mut payload = Vec::new();
        for v in [1.0f64, f64::INFINITY, 3.0, 0.0, 0.0, -0.15] {
            payload.extend_from_slice(&v.to_le_bytes());
        }
        encode_frame(&pulse(3), &mut payload).unwrap();
        let mut bytes = preamble().to_vec();
        let mut head = vec![0xF5, b'W', b'L', b'R', 4, 0, 0, 0];
        head.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        let crc = record_crc(&head[4..], &payload);
        bytes.extend_from_slice(&head);
        bytes.extend_from_slice(&payload);
        bytes.extend_from_slice(&crc.to_le_bytes());
        let (ids, _, _, report) = walk(&bytes);
        assert!(ids.is_empty());
        assert_eq!(report.bad_payloads, 1);
    }
}
