//! [`CaptureWriter`]: appends records to a capture file with a flush/fsync policy.
//!
//! Records are encoded into a reusable scratch buffer (no per-record allocation once warm) and
//! handed to a [`BufWriter`]. The buffer goes to the OS when the policy's record count or time
//! threshold is reached (and is fsynced per [`FsyncPolicy`]); a kill -9 therefore loses at most the
//! records written since the last flush, and the reader recovers everything before them.

use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::capture::{
    CaptureError, FlushPolicy, FsyncPolicy, MAX_PAYLOAD_LEN, PREAMBLE_LEN, RECORD_HEADER_LEN,
    RecordKind, SYNC, check_preamble, preamble,
};
use super::frame::{encode_frame, encode_geometry, encode_nav};
use crate::pulse::Pulse;

/// Capacity of the writer's buffer, bytes.
const BUFFER_CAPACITY: usize = 256 * 1024;

/// Writes a capture: preamble (for a new file), a header record, then frames and nav records.
pub struct CaptureWriter<W: Write> {
    out: BufWriter<W>,
    path: PathBuf,
    policy: FlushPolicy,
    sync: Option<fn(&W) -> io::Result<()>>,
    scratch: Vec<u8>,
    records_since_flush: u32,
    last_flush: Instant,
    records_written: u64,
    bytes_written: u64,
}

fn sync_file(f: &File) -> io::Result<()> {
    f.sync_data()
}

impl CaptureWriter<File> {
    /// Creates a new capture at `path` and writes the preamble and a header record holding
    /// `header_text` (TOML), then flushes (and fsyncs per `policy`).
    ///
    /// Refuses to overwrite: if `path` exists the result is [`CaptureError::AlreadyExists`] and
    /// the existing file is not touched.
    pub fn create(
        path: impl AsRef<Path>,
        header_text: &str,
        policy: FlushPolicy,
    ) -> Result<Self, CaptureError> {
        let path = path.as_ref();
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(path)
            .map_err(|source| match source.kind() {
                io::ErrorKind::AlreadyExists => CaptureError::AlreadyExists {
                    path: path.to_path_buf(),
                },
                _ => CaptureError::Io {
                    path: path.to_path_buf(),
                    source,
                },
            })?;
        let mut w = CaptureWriter::with_sync(file, path, policy, Some(sync_file));
        w.write_raw(&preamble())?;
        w.write_header(header_text)?;
        w.flush()?;
        Ok(w)
    }

    /// Reopens an existing capture at `path` to record a new segment: checks its preamble (a
    /// newer major version is refused with [`CaptureError::NewerVersion`]), then appends a header
    /// record holding `header_text` and flushes. Records already in the file are not touched; a
    /// partial record left at its end by a crash is skipped by readers (resync).
    pub fn append(
        path: impl AsRef<Path>,
        header_text: &str,
        policy: FlushPolicy,
    ) -> Result<Self, CaptureError> {
        let path = path.as_ref();
        let io_err = |source| CaptureError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut file = OpenOptions::new()
            .read(true)
            .append(true)
            .open(path)
            .map_err(io_err)?;
        let mut head = [0u8; PREAMBLE_LEN];
        let mut got = 0;
        while got < PREAMBLE_LEN {
            match file.read(&mut head[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io_err(e)),
            }
        }
        check_preamble(&head[..got], path)?;
        file.seek(SeekFrom::End(0)).map_err(io_err)?;
        let mut w = CaptureWriter::with_sync(file, path, policy, Some(sync_file));
        w.write_header(header_text)?;
        w.flush()?;
        Ok(w)
    }
}

impl<W: Write> CaptureWriter<W> {
    /// A writer over any byte sink (tests, benches, pipes): writes the preamble and a header
    /// record holding `header_text`. `display_name` names the sink in errors. The policy's
    /// `fsync` has no effect here (there is no file to sync); flushes still follow the policy.
    pub fn from_writer(
        inner: W,
        display_name: impl Into<PathBuf>,
        header_text: &str,
        policy: FlushPolicy,
    ) -> Result<Self, CaptureError> {
        let path: PathBuf = display_name.into();
        let mut w = CaptureWriter::with_sync(inner, &path, policy, None);
        w.write_raw(&preamble())?;
        w.write_header(header_text)?;
        Ok(w)
    }

    fn with_sync(
        inner: W,
        path: &Path,
        policy: FlushPolicy,
        sync: Option<fn(&W) -> io::Result<()>>,
    ) -> Self {
        CaptureWriter {
            out: BufWriter::with_capacity(BUFFER_CAPACITY, inner),
            path: path.to_path_buf(),
            policy,
            sync,
            scratch: Vec::with_capacity(4096),
            records_since_flush: 0,
            last_flush: Instant::now(),
            records_written: 0,
            bytes_written: 0,
        }
    }

    fn io_err(&self, source: io::Error) -> CaptureError {
        CaptureError::Io {
            path: self.path.clone(),
            source,
        }
    }

    fn write_raw(&mut self, bytes: &[u8]) -> Result<(), CaptureError> {
        self.out.write_all(bytes).map_err(|e| self.io_err(e))?;
        self.bytes_written += bytes.len() as u64;
        Ok(())
    }

    /// Starts a record of `kind` in the scratch buffer; the payload is appended after this.
    fn begin_record(&mut self, kind: RecordKind) {
        self.scratch.clear();
        self.scratch.extend_from_slice(&SYNC);
        self.scratch
            .extend_from_slice(&[kind as u8, 0, 0, 0, 0, 0, 0, 0]);
    }

    /// Completes the record in the scratch buffer (length and CRC) and writes it.
    fn end_record(&mut self) -> Result<(), CaptureError> {
        let payload_len = self.scratch.len() - RECORD_HEADER_LEN;
        if payload_len > MAX_PAYLOAD_LEN as usize {
            self.scratch.clear();
            return Err(CaptureError::RecordTooLarge {
                len: payload_len,
                max: MAX_PAYLOAD_LEN,
            });
        }
        self.scratch[8..12].copy_from_slice(&(payload_len as u32).to_le_bytes());
        let crc = crc32c::crc32c(&self.scratch[4..]);
        self.scratch.extend_from_slice(&crc.to_le_bytes());
        let rec = std::mem::take(&mut self.scratch);
        let res = self.write_raw(&rec);
        self.scratch = rec;
        res?;
        self.records_written += 1;
        self.records_since_flush += 1;
        self.flush_if_due()
    }

    /// Writes a header record (UTF-8 text, TOML by convention) — e.g. when the configuration in
    /// force changes.
    pub fn write_header(&mut self, header_text: &str) -> Result<(), CaptureError> {
        self.begin_record(RecordKind::Header);
        self.scratch.extend_from_slice(header_text.as_bytes());
        self.end_record()
    }

    /// Writes one pulse as a digitizer frame record. A pulse that cannot be encoded
    /// ([`CaptureError::Encode`]) or is too large ([`CaptureError::RecordTooLarge`]) writes
    /// nothing.
    ///
    /// A pulse with [`Pulse::geometry`] is written as a GeoFrame record (the geometry, then the
    /// frame), so that an imported LAS or PulseWaves pulse keeps its anchor and direction.
    pub fn write_pulse(&mut self, pulse: &Pulse) -> Result<(), CaptureError> {
        let encoded = match &pulse.geometry {
            Some(g) => {
                self.begin_record(RecordKind::GeoFrame);
                encode_geometry(g, &mut self.scratch)
                    .and_then(|()| encode_frame(pulse, &mut self.scratch))
            }
            None => {
                self.begin_record(RecordKind::DigitizerFrame);
                encode_frame(pulse, &mut self.scratch)
            }
        };
        if let Err(source) = encoded {
            self.scratch.clear();
            return Err(CaptureError::Encode {
                pulse_id: pulse.pulse_id,
                source,
            });
        }
        self.end_record()
    }

    /// Writes a digitizer frame record holding `payload` exactly as received (the on-board
    /// recorder keeps the digitizer's bytes, whether or not they decode).
    pub fn write_frame_payload(&mut self, payload: &[u8]) -> Result<(), CaptureError> {
        self.begin_record(RecordKind::DigitizerFrame);
        self.scratch.extend_from_slice(payload);
        self.end_record()
    }

    /// Writes navigation bytes as they came off `port`, received at `receive_time_ns` (host clock,
    /// nanoseconds since the Unix epoch).
    pub fn write_nav(
        &mut self,
        port: u8,
        receive_time_ns: u64,
        bytes: &[u8],
    ) -> Result<(), CaptureError> {
        self.begin_record(RecordKind::NavBytes);
        encode_nav(port, receive_time_ns, bytes, &mut self.scratch);
        self.end_record()
    }

    /// Flushes if the policy's record count or time threshold has been reached. Called after every
    /// record; call it from an idle timer too, since a writer that receives nothing does not
    /// flush by itself.
    pub fn flush_if_due(&mut self) -> Result<(), CaptureError> {
        if self.records_since_flush == 0 {
            return Ok(());
        }
        let by_count =
            self.policy.every_records != 0 && self.records_since_flush >= self.policy.every_records;
        let by_time = self.policy.every_ms != 0
            && self.last_flush.elapsed() >= Duration::from_millis(self.policy.every_ms as u64);
        if by_count || by_time {
            self.flush()?;
        }
        Ok(())
    }

    /// Hands every buffered record to the OS and, when the policy says `on_flush` and the sink is
    /// a file, syncs it to disk.
    pub fn flush(&mut self) -> Result<(), CaptureError> {
        self.out.flush().map_err(|e| self.io_err(e))?;
        if self.policy.fsync == FsyncPolicy::OnFlush
            && let Some(sync) = self.sync
        {
            sync(self.out.get_ref()).map_err(|e| self.io_err(e))?;
        }
        self.records_since_flush = 0;
        self.last_flush = Instant::now();
        Ok(())
    }

    /// Flushes (per policy) and returns the underlying sink.
    pub fn finish(mut self) -> Result<W, CaptureError> {
        self.flush()?;
        let path = self.path.clone();
        self.out.into_inner().map_err(|e| CaptureError::Io {
            path,
            source: e.into_error(),
        })
    }

    /// Records written so far by this writer (headers included).
    pub fn records_written(&self) -> u64 {
        self.records_written
    }

    /// Bytes written so far by this writer (preamble included for a new file), whether flushed
    /// or still buffered.
    pub fn bytes_written(&self) -> u64 {
        self.bytes_written
    }

    /// The path (or display name) this writer writes to.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::capture::{PREAMBLE_LEN, RECORD_OVERHEAD};
    use crate::pulse::SegmentKind;
    use std::cell::RefCell;
    use std::rc::Rc;

    /// A sink that records how many `flush` calls reached it and what was written.
    #[derive(Clone, Default)]
    struct Spy {
        data: Rc<RefCell<Vec<u8>>>,
        flushes: Rc<RefCell<u32>>,
    }

    impl Write for Spy {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.data.borrow_mut().extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            *self.flushes.borrow_mut() += 1;
            Ok(())
        }
    }

    fn pulse() -> Pulse {
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Return, 0, 0.0, [1, 2, 3]);
        p
    }

    #[test]
    fn writes_preamble_and_header_record() {
        let w =
            CaptureWriter::from_writer(Vec::new(), "mem", "a = 1", FlushPolicy::default()).unwrap();
        let bytes = w.finish().unwrap();
        assert_eq!(&bytes[..PREAMBLE_LEN], &preamble());
        let rec = &bytes[PREAMBLE_LEN..];
        assert_eq!(rec.len(), RECORD_OVERHEAD + 5);
        assert_eq!(&rec[..4], &SYNC);
        assert_eq!(rec[4], RecordKind::Header as u8);
        assert_eq!(&rec[8..12], &5u32.to_le_bytes());
        assert_eq!(&rec[12..17], b"a = 1");
        let crc = crc32c::crc32c(&rec[4..17]);
        assert_eq!(&rec[17..21], &crc.to_le_bytes());
    }

    #[test]
    fn flushes_by_record_count() {
        let spy = Spy::default();
        let policy = FlushPolicy {
            every_records: 3,
            every_ms: 0,
            fsync: FsyncPolicy::OnFlush,
        };
        let mut w = CaptureWriter::from_writer(spy.clone(), "spy", "", policy).unwrap();
        // the header is record 1
        assert_eq!(*spy.flushes.borrow(), 0);
        w.write_pulse(&pulse()).unwrap();
        assert_eq!(*spy.flushes.borrow(), 0);
        let before = spy.data.borrow().len();
        assert_eq!(before, 0, "nothing reaches the sink before a flush");
        w.write_nav(1, 2, b"xyz").unwrap();
        assert_eq!(*spy.flushes.borrow(), 1);
        assert_eq!(spy.data.borrow().len() as u64, w.bytes_written());
        for _ in 0..3 {
            w.write_pulse(&pulse()).unwrap();
        }
        assert_eq!(*spy.flushes.borrow(), 2);
        assert_eq!(w.records_written(), 6);
    }

    #[test]
    fn flushes_by_time() {
        let spy = Spy::default();
        let policy = FlushPolicy {
            every_records: 0,
            every_ms: 1,
            fsync: FsyncPolicy::Never,
        };
        let mut w = CaptureWriter::from_writer(spy.clone(), "spy", "", policy).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        w.write_pulse(&pulse()).unwrap();
        assert_eq!(*spy.flushes.borrow(), 1);
    }

    #[test]
    fn no_policy_means_no_flush_until_asked() {
        let spy = Spy::default();
        let policy = FlushPolicy {
            every_records: 0,
            every_ms: 0,
            fsync: FsyncPolicy::Never,
        };
        let mut w = CaptureWriter::from_writer(spy.clone(), "spy", "", policy).unwrap();
        for _ in 0..1000 {
            w.write_pulse(&pulse()).unwrap();
        }
        assert_eq!(*spy.flushes.borrow(), 0);
        w.flush().unwrap();
        assert_eq!(*spy.flushes.borrow(), 1);
    }

    #[test]
    fn bad_pulse_writes_nothing() {
        let mut w =
            CaptureWriter::from_writer(Vec::new(), "mem", "", FlushPolicy::default()).unwrap();
        let before = w.bytes_written();
        let mut p = pulse();
        p.bits = 8;
        p.raw[0] = 1000;
        p.pulse_id = 42;
        let err = w.write_pulse(&p).unwrap_err();
        assert!(
            matches!(err, CaptureError::Encode { pulse_id: 42, .. }),
            "{err}"
        );
        assert_eq!(w.bytes_written(), before);
        w.write_pulse(&pulse()).unwrap();
    }

    #[test]
    fn oversized_record_is_refused() {
        let mut w =
            CaptureWriter::from_writer(Vec::new(), "mem", "", FlushPolicy::default()).unwrap();
        let before = w.bytes_written();
        let big = vec![0u8; MAX_PAYLOAD_LEN as usize];
        let err = w.write_nav(0, 0, &big).unwrap_err();
        assert!(matches!(err, CaptureError::RecordTooLarge { .. }), "{err}");
        assert_eq!(w.bytes_written(), before);
        // exactly the maximum fits
        w.write_nav(0, 0, &big[12..]).unwrap();
    }

    #[test]
    fn create_refuses_existing_and_append_adds_header() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.fwc");
        let w = CaptureWriter::create(&path, "first", FlushPolicy::default()).unwrap();
        w.finish().unwrap();
        let len1 = std::fs::metadata(&path).unwrap().len();
        let err = match CaptureWriter::create(&path, "again", FlushPolicy::default()) {
            Err(e) => e,
            Ok(_) => panic!("create overwrote"),
        };
        assert!(matches!(err, CaptureError::AlreadyExists { .. }));
        assert_eq!(std::fs::metadata(&path).unwrap().len(), len1);
        let mut w = CaptureWriter::append(&path, "second", FlushPolicy::default()).unwrap();
        w.write_pulse(&pulse()).unwrap();
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..PREAMBLE_LEN], &preamble());
        let second = &bytes[len1 as usize..];
        assert_eq!(&second[12..18], b"second");
    }

    #[test]
    fn flushed_records_are_in_the_file_before_finish() {
        let dir = tempfile::tempdir().unwrap();
        let every = FlushPolicy {
            every_records: 2,
            every_ms: 0,
            fsync: FsyncPolicy::OnFlush,
        };
        let path = dir.path().join("every2.fwc");
        let mut w = CaptureWriter::create(&path, "h", every).unwrap();
        let on_disk = |p: &Path| std::fs::metadata(p).unwrap().len();
        assert_eq!(
            on_disk(&path),
            w.bytes_written(),
            "header is flushed by create"
        );
        w.write_pulse(&pulse()).unwrap();
        assert!(
            on_disk(&path) < w.bytes_written(),
            "one record stays buffered"
        );
        w.write_pulse(&pulse()).unwrap();
        assert_eq!(on_disk(&path), w.bytes_written(), "second record flushes");
        // dropping without finish (as a crash would) loses nothing already flushed
        let flushed = w.bytes_written();
        std::mem::forget(w);
        assert_eq!(on_disk(&path), flushed);

        let never = FlushPolicy {
            every_records: 0,
            every_ms: 0,
            fsync: FsyncPolicy::Never,
        };
        let path = dir.path().join("never.fwc");
        let mut w = CaptureWriter::create(&path, "h", never).unwrap();
        let after_header = on_disk(&path);
        for _ in 0..10 {
            w.write_pulse(&pulse()).unwrap();
        }
        assert_eq!(on_disk(&path), after_header);
        w.flush_if_due().unwrap();
        assert_eq!(on_disk(&path), after_header);
        w.flush().unwrap();
        assert_eq!(on_disk(&path), w.bytes_written());
    }

    #[test]
    fn append_refuses_non_captures() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("not.fwc");
        std::fs::write(&path, b"hello world, not a capture").unwrap();
        let err = match CaptureWriter::append(&path, "", FlushPolicy::default()) {
            Err(e) => e,
            Ok(_) => panic!("appended to a non-capture"),
        };
        assert!(matches!(err, CaptureError::NotACapture { .. }));
        let mut newer = preamble();
        newer[8] = 2;
        std::fs::write(&path, newer).unwrap();
        let err = match CaptureWriter::append(&path, "", FlushPolicy::default()) {
            Err(e) => e,
            Ok(_) => panic!("appended to a newer major"),
        };
        assert!(matches!(err, CaptureError::NewerVersion { major: 2, .. }));
        assert_eq!(std::fs::read(&path).unwrap(), newer);
    }
}
