//! `fwlidar inspect --nav nmea|novatel|sbet FILE`: every decoded navigation sample, and what
//! was rejected and why. With `--json`, one JSON object per sample per line and, as the last
//! line, the summary object (`"summary": true`, `records`, `rejected`, `rejected_by_reason`, ...).

use std::io::{Read, Write};
use std::path::Path;

use serde::Serialize;

use crate::cli::Failure;
use crate::nav::dating::{GPS_EPOCH_DAYS, GpsTime, civil_of_days};
use crate::nav::decoder::{DecodeSummary, NavDecoder};
use crate::nav::sbet::SbetReader;
use crate::nav::{NavFormat, NavSample, NavTime};

/// Samples held while waiting for the first NMEA date (ZDA/RMC): 10 s at 25 Hz plus margin.
const MAX_UNDATED: usize = 512;

/// One sample as a JSON line.
#[derive(Serialize)]
struct SampleJson<'a> {
    /// GPS seconds of the week.
    gps_time: Option<f64>,
    /// Full GPS week, when known.
    #[serde(skip_serializing_if = "Option::is_none")]
    gps_week: Option<u32>,
    /// UTC as ISO 8601, for NMEA records (what the receiver sent, dated).
    #[serde(skip_serializing_if = "Option::is_none")]
    utc: Option<String>,
    #[serde(flatten)]
    sample: &'a NavSample,
}

fn iso(days: i64, seconds: f64) -> String {
    let (y, m, d) = civil_of_days(days);
    let ms = (seconds * 1000.0).round() as i64;
    let (h, rem) = (ms / 3_600_000, ms % 3_600_000);
    let (mi, rem) = (rem / 60_000, rem % 60_000);
    format!(
        "{y:04}-{m:02}-{d:02}T{h:02}:{mi:02}:{:02}.{:03}Z",
        rem / 1000,
        rem % 1000
    )
}

fn write_sample(
    out: &mut impl Write,
    s: &NavSample,
    t: Option<GpsTime>,
    json: bool,
) -> std::io::Result<()> {
    let (gps_time, gps_week) = match (t, s.time) {
        (Some(t), _) => (Some(t.sow), Some(t.week)),
        (None, NavTime::GpsSecondsOfWeek { sow }) => (Some(sow), None),
        _ => (None, None),
    };
    let utc = match s.time {
        NavTime::Utc { days, seconds } if days >= GPS_EPOCH_DAYS => Some(iso(days, seconds)),
        _ => None,
    };
    if json {
        serde_json::to_writer(
            &mut *out,
            &SampleJson {
                gps_time,
                gps_week,
                utc,
                sample: s,
            },
        )
        .map_err(std::io::Error::other)?;
        writeln!(out)
    } else {
        let v = serde_json::to_value(s).map_err(std::io::Error::other)?;
        let mut line = match gps_time {
            Some(g) => format!("{g:>14.3}"),
            None => format!("{:>14}", "-"),
        };
        if let serde_json::Value::Object(m) = v {
            for (k, v) in m {
                line.push_str(&format!("  {k}={v}"));
            }
        }
        writeln!(out, "{line}")
    }
}

#[derive(Serialize)]
struct SummaryJson<'a> {
    summary: bool,
    file: String,
    format: NavFormat,
    #[serde(flatten)]
    counts: &'a DecodeSummary,
}

/// Runs `inspect --nav`.
pub fn run(path: &Path, format: NavFormat, leap_seconds: f64, json: bool) -> Result<(), Failure> {
    let file = std::fs::File::open(path)
        .map_err(|e| Failure::job(format!("{}: cannot open: {e}", path.display())))?;
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    let mut write_err = None;
    let mut sbet_failure = None;
    let mut emit = |s: NavSample, t: Option<GpsTime>| {
        if write_err.is_none()
            && let Err(e) = write_sample(&mut out, &s, t, json)
        {
            write_err = Some(e);
        }
    };
    let counts = match format {
        NavFormat::Nmea | NavFormat::Novatel => {
            let mut dec = NavDecoder::new(leap_seconds, MAX_UNDATED, None);
            let mut input = std::io::BufReader::with_capacity(1 << 16, file);
            let mut buf = vec![0u8; 1 << 16];
            loop {
                let n = match input.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => {
                        return Err(Failure::job(format!(
                            "{}: cannot read: {e}",
                            path.display()
                        )));
                    }
                };
                dec.push(&buf[..n], &mut emit);
            }
            dec.finish(&mut emit);
            dec.summary()
        }
        NavFormat::Sbet => {
            let mut counts = DecodeSummary::default();
            let name = path.display().to_string();
            let mut failure = None;
            for r in SbetReader::new(std::io::BufReader::new(file), name) {
                match r {
                    Ok(s) => {
                        counts.records += 1;
                        *counts.by_kind.entry("SBET".into()).or_insert(0) += 1;
                        emit(s, None);
                    }
                    Err(e) => {
                        let why = match &e {
                            crate::nav::sbet::SbetError::Truncated { .. } => "truncated",
                            crate::nav::sbet::SbetError::BadField { .. } => "bad_field",
                            crate::nav::sbet::SbetError::Io { .. } => "io",
                        };
                        counts.rejected += 1;
                        *counts.rejected_by_reason.entry(why.into()).or_insert(0) += 1;
                        failure = Some(e.to_string());
                    }
                }
            }
            counts.bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
            sbet_failure = failure;
            counts
        }
    };
    let io = |e: std::io::Error| Failure::job(format!("cannot write to stdout: {e}"));
    match write_err {
        // The reader went away (`| head`): not an error of ours.
        Some(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Ok(()),
        Some(e) => return Err(io(e)),
        None => {}
    }
    let summary = SummaryJson {
        summary: true,
        file: path.display().to_string(),
        format,
        counts: &counts,
    };
    if json {
        serde_json::to_writer(&mut out, &summary).map_err(|e| io(std::io::Error::other(e)))?;
        writeln!(out).map_err(io)?;
    } else {
        writeln!(
            out,
            "{}: {} records, {} rejected {:?}, ignored {:?}, {} of {} bytes outside any record",
            summary.file,
            counts.records,
            counts.rejected,
            counts.rejected_by_reason,
            counts.ignored,
            counts.unframed_bytes,
            counts.bytes
        )
        .map_err(io)?;
    }
    out.flush().map_err(io)?;
    match sbet_failure {
        // A damaged trajectory file: everything readable was printed, and the exit says so.
        Some(f) => Err(Failure::job(f)),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nav::nmea::days_from_civil;

    #[test]
    fn civil_is_the_inverse_of_days_from_civil() {
        for days in [-1000i64, 0, 3657, 10_000, 18_000, 20_000, 60_000] {
            let (y, m, d) = civil_of_days(days);
            assert_eq!(days_from_civil(y, m, d), days);
        }
        assert_eq!(
            iso(days_from_civil(2020, 3, 18), 48_500.6),
            "2020-03-18T13:28:20.600Z"
        );
    }
}
