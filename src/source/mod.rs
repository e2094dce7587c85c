//! Sources: where pulses and navigation bytes come from (a recorded capture, LAS files with
//! waveforms, PulseWaves files, NASA GEDI Level 1B granules; the network and serial ports).

pub mod capture;
pub mod chain;
pub mod gedi;
pub mod georeferencing;
pub mod las;
pub mod live_frames;
pub mod pulsewaves;
pub mod report;
pub mod serial;
pub mod shard;

use std::io::Read;
use std::path::Path;

use crate::pipeline::ports::{Source, SourceEvent};
use crate::pulse::{Pulse, PulsePool};
use report::SourceReport;

/// A source of the runs this crate puts together: its report is a [`SourceReport`].
pub type DynSource = dyn Source<Report = SourceReport>;

/// One pulse from a file reader into a pooled pulse: `Ok(true)` from `read` is a pulse, `Ok(false)`
/// the end; the pool gets its pulse back unless one is handed out. The error is the reader's
/// message (it names the file).
pub(crate) fn next_pooled<E: std::fmt::Display>(
    pool: &PulsePool,
    read: impl FnOnce(&mut Pulse) -> Result<bool, E>,
) -> Result<SourceEvent, String> {
    let mut pulse = pool.take();
    match read(&mut pulse) {
        Ok(true) => Ok(SourceEvent::Pulse(pulse)),
        Ok(false) => {
            pool.give(pulse);
            Ok(SourceEvent::End)
        }
        Err(e) => {
            pool.give(pulse);
            Err(e.to_string())
        }
    }
}

/// The file formats an input file can be, told apart by their first bytes ([`InputKind::sniff`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputKind {
    /// fwlidar capture (`docs/formats.md`), magic `\x89FWLCAP\n`.
    Capture,
    /// ASPRS LAS (file signature `LASF`); waveforms in point formats 4, 5, 9, 10.
    Las,
    /// PulseWaves `.pls` (file signature `PulseWavesPulse\0`).
    PulseWaves,
    /// HDF5 (signature `\x89HDF\r\n\x1a\n`), read as a NASA GEDI Level 1B granule; any other
    /// HDF5 file is refused when opened, with what it is when it is a GEDI granule of another
    /// level.
    Gedi,
}

impl InputKind {
    /// Recognises a file from its first bytes (at least 16 for PulseWaves); `None` if unknown.
    pub fn sniff(head: &[u8]) -> Option<InputKind> {
        if head.starts_with(&crate::format::capture::MAGIC) {
            Some(InputKind::Capture)
        } else if head.starts_with(b"LASF") {
            Some(InputKind::Las)
        } else if head.starts_with(b"PulseWavesPulse") {
            Some(InputKind::PulseWaves)
        } else if head.starts_with(&crate::format::gedi::HDF5_SIGNATURE) {
            Some(InputKind::Gedi)
        } else {
            None
        }
    }

    /// Reads the first bytes of `path` and recognises its format. The error names the file.
    pub fn of_file(path: &Path) -> Result<InputKind, String> {
        let mut head = [0u8; 16];
        let mut f = std::fs::File::open(path)
            .map_err(|e| format!("{}: cannot open: {e}", path.display()))?;
        let mut n = 0;
        while n < head.len() {
            match f.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(format!("{}: cannot read: {e}", path.display())),
            }
        }
        if n == 0 {
            return Err(format!("{}: the file is empty (0 bytes)", path.display()));
        }
        InputKind::sniff(&head[..n]).ok_or_else(|| {
            format!(
                "{}: not an fwlidar capture, a LAS file, a PulseWaves .pls file or a GEDI \
                 Level 1B HDF5 granule (its first bytes match none of their signatures)",
                path.display()
            )
        })
    }
}

/// Opens any supported input file as a [`Source`], by its format ([`InputKind::of_file`]).
/// Errors name the file.
pub fn open_file(path: &Path) -> Result<Box<DynSource>, String> {
    match InputKind::of_file(path)? {
        InputKind::Capture => Ok(Box::new(
            capture::CaptureSource::open(path).map_err(|e| e.to_string())?,
        )),
        InputKind::PulseWaves => Ok(Box::new(
            pulsewaves::PulseWavesSource::open(path).map_err(|e| e.to_string())?,
        )),
        InputKind::Las => Ok(Box::new(
            las::LasSource::open(path).map_err(|e| e.to_string())?,
        )),
        InputKind::Gedi => Ok(Box::new(
            gedi::GediSource::open(path).map_err(|e| e.to_string())?,
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sniff_tells_the_formats_apart() {
        assert_eq!(
            InputKind::sniff(&crate::format::capture::preamble()),
            Some(InputKind::Capture)
        );
        assert_eq!(InputKind::sniff(b"LASF\0\0\0\0"), Some(InputKind::Las));
        assert_eq!(
            InputKind::sniff(b"PulseWavesPulse\0"),
            Some(InputKind::PulseWaves)
        );
        assert_eq!(
            InputKind::sniff(b"\x89HDF\r\n\x1a\n\0\0\0\0"),
            Some(InputKind::Gedi)
        );
        assert_eq!(InputKind::sniff(b"\x89HDF"), None);
        assert_eq!(InputKind::sniff(b"LAS"), None);
        assert_eq!(InputKind::sniff(b""), None);
        assert_eq!(InputKind::sniff(b"hello world, not"), None);
    }
}
