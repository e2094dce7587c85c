//! File formats fwlidar reads and writes: raw, byte-exact layers that validate as little as
//! possible and never panic on input, below the checked domain types.
//!
//! - [`capture`]: the native capture container v1.1 (constants, errors, skip report, flush
//!   policy); [`capture_reader`] and [`capture_writer`] read and write it.
//! - [`frame`]: the digitizer frame and nav payloads inside capture records.
//! - [`table`]: waveform tables (CSV, NumPy `.npy`) for `fwlidar process`.
//! - [`las_read`]: LAS 1.3/1.4 waveform packets (point formats 4, 5, 9, 10, plain or LAZ,
//!   `.wdp` or internal) read as pulses.
//! - [`las_write`]: LAS 1.4 header, VLR/EVLR, Extra Bytes and point formats 6 and 9 encoding
//!   (returns output).
//! - [`las_points`]: a complete LAS 1.4 point format 6 file written atomically from an iterator
//!   of points with extra dimensions (voxel tiles and other point outputs).
//! - [`las_repair`]: rebuilding the header of a LAS 1.4 file cut off by a crash.
//! - [`pulsewaves`]: PulseWaves 0.3 `.pls` + `.wvs` reader (input).
//! - [`gedi`]: NASA GEDI Level 1B geolocated waveforms (HDF5, through the pure-Rust
//!   `hdf5-reader` crate): beams, shot records, waveforms in blocks of shots.
//! - [`geokeys`]: the GeoTIFF GeoKey directory of LAS and PulseWaves files and the CRS it names
//!   (one precedence for both readers).
//!
//! Byte layouts are specified in `docs/formats.md`.

pub mod capture;
pub mod capture_reader;
pub mod capture_writer;
pub mod frame;
pub mod gedi;
pub mod geokeys;
pub mod header;
pub mod las_points;
pub mod las_read;
pub mod las_repair;
pub mod las_write;
pub mod pulsewaves;
pub mod table;

pub use capture::{CaptureError, FlushPolicy, FsyncPolicy, RecordKind, SkipReport};
pub use capture_reader::{CaptureReader, FrameRecord, Record};
pub use capture_writer::CaptureWriter;
pub use frame::FrameError;
pub use header::{CaptureHeader, CaptureMeta};
