//! PulseWaves 0.3 input: the pulse file (`.pls`: header, VLRs, pulse records, AVLRs) and the
//! waves file (`.wvs`: the sampled segments of every pulse), uncompressed.
//!
//! One concern per file:
//! - [`header`]: the `.pls` header (352 bytes) and the `.wvs` header (60 bytes);
//! - [`vlr`]: variable length records before the pulses and appended ones after them;
//! - [`pulse_record`]: the 48-byte pulse record (format 0);
//! - [`descriptor`]: pulse descriptors (a composition record and its sampling records);
//! - [`scanner`]: scanner records;
//! - [`crs`]: GeoKeys and OGC WKT records → the coordinate reference system;
//! - [`waves`]: the per-pulse layout of the `.wvs` file;
//! - [`reader`]: [`PulseWavesReader`], which ties them together over any `Read + Seek` pair and
//!   fills pooled [`crate::pulse::Pulse`]s.
//!
//! Field layouts were checked against real files (`docs/formats.md`, "PulseWaves (input)");
//! where the files differ from the 0.3 specification draft, the files win.

pub mod crs;
pub mod descriptor;
pub mod error;
pub mod header;
pub mod pulse_record;
pub mod reader;
pub mod scanner;
pub mod vlr;
pub mod waves;

pub use descriptor::{Composition, PulseDescriptor, Sampling, SamplingType};
pub use error::PulseWavesError;
pub use header::{PlsHeader, WvsHeader};
pub use pulse_record::PulseRecord;
pub use reader::{PulseWavesReader, TimeBase, waves_path_for};
pub use scanner::Scanner;

/// Little-endian field access on a byte slice that never panics: a field that does not fit is
/// read as zero. Callers check lengths first; this is the last line of defence.
pub(crate) mod le {
    #[inline]
    fn arr<const N: usize>(b: &[u8], at: usize) -> [u8; N] {
        let mut out = [0u8; N];
        if let Some(end) = at.checked_add(N)
            && let Some(s) = b.get(at..end)
        {
            out.copy_from_slice(s);
        }
        out
    }
    #[inline]
    pub fn u8(b: &[u8], at: usize) -> u8 {
        b.get(at).copied().unwrap_or(0)
    }
    #[inline]
    pub fn u16(b: &[u8], at: usize) -> u16 {
        u16::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn i16(b: &[u8], at: usize) -> i16 {
        i16::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn u32(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn i32(b: &[u8], at: usize) -> i32 {
        i32::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn i64(b: &[u8], at: usize) -> i64 {
        i64::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn f32(b: &[u8], at: usize) -> f32 {
        f32::from_le_bytes(arr(b, at))
    }
    #[inline]
    pub fn f64(b: &[u8], at: usize) -> f64 {
        f64::from_le_bytes(arr(b, at))
    }
    /// A fixed-size, NUL-padded text field as a trimmed string (invalid UTF-8 replaced).
    pub fn text(b: &[u8], at: usize, len: usize) -> String {
        let end = at.saturating_add(len).min(b.len());
        let s = b.get(at.min(end)..end).unwrap_or(&[]);
        let s = match s.iter().position(|&c| c == 0) {
            Some(n) => &s[..n],
            None => s,
        };
        String::from_utf8_lossy(s).trim().to_string()
    }
}
