//! Processed waveforms as two NumPy `.npy` files that `numpy.load` reads directly (no parsing,
//! memory-mappable), the default waveform output of `replay`:
//!
//! - `waveforms.npy`: one-dimensional `<f4` array, every segment's processed signal in volts,
//!   segment after segment, in pulse order;
//! - `waveform_index.npy`: one record per segment, a structured array with the fields
//!   [`INDEX_FIELDS`]: `pulse_id`, `gps_time` (s), `segment` (index in the pulse), `kind`
//!   (0 outgoing, 1 return), `channel`, `start_ns` (first sample's time after the pulse's t0,
//!   ns), `sample_ns` (ns), `n_samples`, `offset` (index of the segment's first sample in
//!   `waveforms.npy`), `baseline_v` and `noise_v` (V).
//!
//! ```python
//! w = np.load('out/waveforms.npy', mmap_mode='r')
//! ix = np.load('out/waveform_index.npy')
//! seg = w[ix['offset'][i] : ix['offset'][i] + ix['n_samples'][i]]
//! ```
//!
//! Segments a stage has not processed (empty `signal`) are written as raw counts converted to
//! volts, as `waveforms.csv` does. The arrays' lengths are known only at the end: both files are
//! written with a header reserved at the start and completed, then moved into place atomically
//! (see [`AtomicFile`]). About 4 bytes per sample plus 52 per segment (`waveforms.csv`: ~12 per
//! sample as text).

use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

use crate::core::atomic_file::AtomicFile;
use crate::format::table::npy_preamble;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::{Pulse, SegmentKind};
use crate::sink::{SinkReport, WaveformsReport};

/// The fields of `waveform_index.npy`: name and NumPy type (little-endian).
pub const INDEX_FIELDS: [(&str, &str); 11] = [
    ("pulse_id", "<u8"),
    ("gps_time", "<f8"),
    ("segment", "<u2"),
    ("kind", "|u1"),
    ("channel", "|u1"),
    ("start_ns", "<f8"),
    ("sample_ns", "<f8"),
    ("n_samples", "<u4"),
    ("offset", "<u8"),
    ("baseline_v", "<f4"),
    ("noise_v", "<f4"),
];

/// Bytes of one `waveform_index.npy` record.
pub const INDEX_RECORD: usize = 8 + 8 + 2 + 1 + 1 + 8 + 8 + 4 + 8 + 4 + 4;

/// Bytes reserved for each file's NPY preamble: room for the dictionary with any 20-digit
/// length.
const PREAMBLE: usize = 512;

/// The NumPy dtype description of the index records.
fn index_descr() -> String {
    let fields: Vec<String> = INDEX_FIELDS
        .iter()
        .map(|(n, t)| format!("('{n}', '{t}')"))
        .collect();
    format!("[{}]", fields.join(", "))
}

/// Writes `waveforms.npy` and `waveform_index.npy` into a folder.
pub struct WaveformNpySink {
    samples: AtomicFile,
    index: AtomicFile,
    /// Samples written so far (the next segment's `offset`).
    n_samples: u64,
    /// Segments written so far.
    n_segments: u64,
    /// Scratch for one segment's little-endian samples, reused.
    buf: Vec<u8>,
}

fn io(file: &AtomicFile, source: std::io::Error) -> SinkError {
    SinkError::Io {
        path: file.path().display().to_string(),
        source,
    }
}

impl WaveformNpySink {
    /// Starts writing into `dir` (which must exist).
    pub fn create(dir: &Path) -> Result<Self, SinkError> {
        let mut samples = AtomicFile::create(dir.join("waveforms.npy"))?;
        let mut index = AtomicFile::create(dir.join("waveform_index.npy"))?;
        let room = vec![b' '; PREAMBLE];
        for f in [&mut samples, &mut index] {
            let r = f.writer()?.write_all(&room);
            r.map_err(|e| io(f, e))?;
        }
        Ok(WaveformNpySink {
            samples,
            index,
            n_samples: 0,
            n_segments: 0,
            buf: Vec::with_capacity(1 << 16),
        })
    }

    /// Segments written so far.
    pub fn segments(&self) -> u64 {
        self.n_segments
    }

    /// Rewrites `file`'s reserved preamble for `descr` and `shape`.
    fn complete(file: &mut AtomicFile, descr: &str, shape: u64) -> Result<(), SinkError> {
        let pre = npy_preamble(descr, &[shape], PREAMBLE).expect("the dtype fits the header");
        debug_assert_eq!(pre.len(), PREAMBLE);
        let w = file.writer()?;
        let r = w.seek(SeekFrom::Start(0)).and_then(|_| w.write_all(&pre));
        r.map_err(|e| io(file, e))
    }
}

impl PulseSink for WaveformNpySink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "waveform_npy"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        for (i, seg) in p.segments.iter().enumerate() {
            self.buf.clear();
            let signal = p.signal_of(i);
            if signal.len() == seg.len as usize {
                for v in signal {
                    self.buf.extend_from_slice(&v.to_le_bytes());
                }
            } else {
                for c in p.raw_of(i) {
                    self.buf
                        .extend_from_slice(&p.counts_to_volts(*c).to_le_bytes());
                }
            }
            let r = self.samples.writer()?.write_all(&self.buf);
            r.map_err(|e| io(&self.samples, e))?;

            let mut rec = [0u8; INDEX_RECORD];
            let mut at = 0;
            let mut put = |b: &[u8]| {
                rec[at..at + b.len()].copy_from_slice(b);
                at += b.len();
            };
            put(&p.pulse_id.to_le_bytes());
            put(&p.gps_time.to_le_bytes());
            put(&(i as u16).to_le_bytes());
            put(&[match seg.kind {
                SegmentKind::Outgoing => 0,
                SegmentKind::Return => 1,
            }]);
            put(&[seg.channel]);
            put(&seg.start_ns.to_le_bytes());
            put(&p.sample_ns.to_le_bytes());
            put(&seg.len.to_le_bytes());
            put(&self.n_samples.to_le_bytes());
            put(&p.noise.baseline_v.to_le_bytes());
            put(&p.noise.noise_v.to_le_bytes());
            let r = self.index.writer()?.write_all(&rec);
            r.map_err(|e| io(&self.index, e))?;
            self.n_samples += u64::from(seg.len);
            self.n_segments += 1;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        self.samples.flush()?;
        Ok(self.index.flush()?)
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        Self::complete(&mut self.samples, "'<f4'", self.n_samples)?;
        Self::complete(&mut self.index, &index_descr(), self.n_segments)?;
        self.samples.commit()?;
        Ok(self.index.commit()?)
    }

    fn report(&self) -> SinkReport {
        SinkReport::Waveforms(WaveformsReport {
            segments: self.n_segments,
            samples: self.n_samples,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::table::parse_npy;

    #[test]
    fn the_preamble_is_reserved_room_and_the_samples_parse_back() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = WaveformNpySink::create(dir.path()).unwrap();
        let mut p = Pulse {
            pulse_id: 7,
            gps_time: 12.5,
            sample_ns: 1.0,
            ..Default::default()
        };
        p.push_segment(SegmentKind::Outgoing, 0, 0.0, [1u16, 2, 3]);
        p.push_segment(SegmentKind::Return, 1, 100.0, [4u16, 5]);
        p.signal.extend_from_slice(&[0.5, 1.5, 2.5, -1.0, 3.25]);
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        let bytes = std::fs::read(dir.path().join("waveforms.npy")).unwrap();
        assert_eq!(bytes.len(), PREAMBLE + 5 * 4);
        // Our own NPY reader takes it as one row of five values.
        let t = parse_npy(&bytes, "waveforms.npy").unwrap();
        assert_eq!(t.rows, vec![vec![0.5, 1.5, 2.5, -1.0, 3.25]]);
        let ix = std::fs::read(dir.path().join("waveform_index.npy")).unwrap();
        assert_eq!(ix.len(), PREAMBLE + 2 * INDEX_RECORD);
        let header = String::from_utf8_lossy(&ix[10..PREAMBLE]);
        assert!(header.contains("'shape': (2,)"), "{header}");
        assert!(header.contains("('offset', '<u8')"), "{header}");
        // The second record: offset 3, 2 samples, kind 1, channel 1, start 100 ns.
        let r = &ix[PREAMBLE + INDEX_RECORD..];
        assert_eq!(u64::from_le_bytes(r[..8].try_into().unwrap()), 7);
        assert_eq!(r[18], 1);
        assert_eq!(r[19], 1);
        assert_eq!(f64::from_le_bytes(r[20..28].try_into().unwrap()), 100.0);
        assert_eq!(u32::from_le_bytes(r[36..40].try_into().unwrap()), 2);
        assert_eq!(u64::from_le_bytes(r[40..48].try_into().unwrap()), 3);
    }
}
