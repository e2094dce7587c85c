//! Applanix SBET (smoothed best estimate of trajectory) files: post-processed trajectories as
//! records of 17 little-endian `f64`, 136 bytes each, no header:
//!
//! | # | field | unit |
//! |---|---|---|
//! | 0 | time | GPS seconds of the week |
//! | 1, 2 | latitude, longitude | radians (WGS84) |
//! | 3 | altitude | metres above the ellipsoid |
//! | 4, 5, 6 | velocity along the wander-angle frame's x, y, z | m/s |
//! | 7, 8 | roll, pitch | radians |
//! | 9 | platform heading | radians, clockwise from true north |
//! | 10 | wander angle | radians |
//! | 11, 12, 13 | body accelerations x, y, z | m/s² |
//! | 14, 15, 16 | body angular rates x, y, z | rad/s |
//!
//! The heading is taken as the true heading; velocities stay in the wander frame (with the
//! wander angle beside them), as the file gives them.

use std::io::Read;

use super::{NavKind, NavSample, NavTime};

/// Bytes per SBET record.
pub const RECORD_BYTES: usize = 136;

/// A damaged SBET file.
#[derive(Debug, thiserror::Error)]
pub enum SbetError {
    /// The file ends inside a record.
    #[error("{file}: record {record} is truncated: {bytes} of {RECORD_BYTES} bytes")]
    Truncated {
        /// The file.
        file: String,
        /// Index of the cut record.
        record: u64,
        /// Bytes present.
        bytes: usize,
    },
    /// A field that cannot be a trajectory value.
    #[error("{file}: record {record}: field `{field}` is {value}")]
    BadField {
        /// The file.
        file: String,
        /// Record index.
        record: u64,
        /// Field name.
        field: &'static str,
        /// The value.
        value: f64,
    },
    /// Reading failed.
    #[error("{file}: cannot read: {source}")]
    Io {
        /// The file.
        file: String,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Reads SBET records one at a time.
pub struct SbetReader<R> {
    input: R,
    file: String,
    record: u64,
    done: bool,
}

impl<R: Read> SbetReader<R> {
    /// Reads records from `input`; `file` names it in errors.
    pub fn new(input: R, file: impl Into<String>) -> Self {
        SbetReader {
            input,
            file: file.into(),
            record: 0,
            done: false,
        }
    }

    fn fill(&mut self, buf: &mut [u8; RECORD_BYTES]) -> Result<usize, SbetError> {
        let mut n = 0;
        while n < RECORD_BYTES {
            match self.input.read(&mut buf[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    return Err(SbetError::Io {
                        file: self.file.clone(),
                        source: e,
                    });
                }
            }
        }
        Ok(n)
    }
}

/// One record's 17 values as a sample.
pub fn sample_of(v: &[f64; 17]) -> Result<NavSample, (&'static str, f64)> {
    const NAMES: [&str; 17] = [
        "time",
        "latitude",
        "longitude",
        "altitude",
        "x_velocity",
        "y_velocity",
        "z_velocity",
        "roll",
        "pitch",
        "heading",
        "wander",
        "x_acceleration",
        "y_acceleration",
        "z_acceleration",
        "x_angular_rate",
        "y_angular_rate",
        "z_angular_rate",
    ];
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err((NAMES[i], v[i]));
    }
    if !(0.0..=604_801.0).contains(&v[0]) {
        return Err(("time", v[0]));
    }
    if v[1].abs() > std::f64::consts::FRAC_PI_2 {
        return Err(("latitude", v[1]));
    }
    let mut s = NavSample::new(NavKind::Sbet, NavTime::GpsSecondsOfWeek { sow: v[0] });
    s.lat = Some(v[1].to_degrees());
    s.lon = Some(v[2].to_degrees());
    s.height = Some(v[3]);
    s.roll = Some(v[7].to_degrees());
    s.pitch = Some(v[8].to_degrees());
    s.heading = Some(v[9].to_degrees().rem_euclid(360.0));
    s.wander_velocity = Some([v[4], v[5], v[6], v[10].to_degrees()]);
    s.linear = Some([v[11], v[12], v[13]]);
    s.angular = Some([v[14], v[15], v[16]]);
    Ok(s)
}

impl<R: Read> Iterator for SbetReader<R> {
    type Item = Result<NavSample, SbetError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let mut buf = [0u8; RECORD_BYTES];
        let n = match self.fill(&mut buf) {
            Ok(n) => n,
            Err(e) => {
                self.done = true;
                return Some(Err(e));
            }
        };
        if n == 0 {
            self.done = true;
            return None;
        }
        let record = self.record;
        self.record += 1;
        if n < RECORD_BYTES {
            self.done = true;
            return Some(Err(SbetError::Truncated {
                file: self.file.clone(),
                record,
                bytes: n,
            }));
        }
        let mut v = [0f64; 17];
        for (i, x) in v.iter_mut().enumerate() {
            let mut b = [0u8; 8];
            b.copy_from_slice(&buf[i * 8..i * 8 + 8]);
            *x = f64::from_le_bytes(b);
        }
        Some(sample_of(&v).map_err(|(field, value)| SbetError::BadField {
            file: self.file.clone(),
            record,
            field,
            value,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(v: [f64; 17]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn records_truncation_and_bad_values() {
        let mut v = [0.0f64; 17];
        v[0] = 151_631.0;
        v[1] = 0.5;
        v[9] = -0.1;
        let mut bytes = record(v);
        v[1] = f64::NAN;
        bytes.extend(record(v));
        bytes.extend_from_slice(&[0u8; 100]);
        let out: Vec<_> = SbetReader::new(&bytes[..], "t.sbet").collect();
        assert_eq!(out.len(), 3);
        let s = out[0].as_ref().unwrap();
        assert!((s.lat.unwrap() - 0.5f64.to_degrees()).abs() < 1e-12);
        assert!((s.heading.unwrap() - (360.0 - 0.1f64.to_degrees())).abs() < 1e-9);
        let e = out[1].as_ref().unwrap_err().to_string();
        assert!(e.contains("t.sbet") && e.contains("latitude"), "{e}");
        let e = out[2].as_ref().unwrap_err().to_string();
        assert!(e.contains("record 2 is truncated: 100 of 136"), "{e}");
    }
}
