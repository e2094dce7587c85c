//! `fwlidar inspect`: what a capture holds (navigation files: `inspect_nav.rs`) — header, record counts, time span, damage — and,
//! with `--pulses --json`, every pulse as one JSON object per line.

use std::io::Write;
use std::path::PathBuf;

use serde::Serialize;

use crate::cli::Failure;
use crate::format::{CaptureHeader, CaptureReader, Record};
use crate::pulse::{Pulse, PulsePool, SegmentKind};
use crate::source::{InputKind, SourceEvent};

/// Arguments of `fwlidar inspect`.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// The capture file.
    pub file: PathBuf,
    /// List every pulse instead of the overview.
    #[arg(long)]
    pub pulses: bool,
    /// Machine-readable output: the overview as one JSON object, or with `--pulses` one JSON
    /// object per pulse per line.
    #[arg(long)]
    pub json: bool,
    /// With `--pulses`: stop after this many pulses.
    #[arg(long)]
    pub limit: Option<u64>,
    /// Decode FILE as a navigation stream or trajectory (`nmea`, `novatel` or `sbet`): every
    /// sample, then a summary of what was rejected and why.
    #[arg(long, value_name = "FORMAT")]
    pub nav: Option<crate::nav::NavFormat>,
    /// With `--nav`: GPS − UTC leap seconds used to turn NMEA UTC times into GPS time.
    #[arg(long, default_value_t = crate::nav::decoder::LEAP_SECONDS_NOW)]
    pub leap_seconds: f64,
}

/// One pulse as `inspect --pulses --json` prints it.
#[derive(Serialize)]
pub struct PulseJson<'a> {
    /// Pulse identifier.
    pub pulse_id: u64,
    /// GPS time, seconds.
    pub gps_time: f64,
    /// Anchor (x, y, z) in the file's CRS, when the input carries it (LAS, PulseWaves); `null`
    /// for raw captures (georeferencing needs the trajectory).
    pub anchor: Option<[f64; 3]>,
    /// Direction (CRS units per nanosecond): `null` for raw captures.
    pub direction: Option<[f64; 3]>,
    /// Scan angles, degrees (secondary `null` when absent).
    pub scan_angle_deg: [Option<f32>; 2],
    /// Digitizer gain, V per count, and offset, V.
    pub digitizer: [f32; 2],
    /// The segments.
    pub segments: Vec<SegmentJson<'a>>,
}

/// One segment as `inspect --pulses --json` prints it.
#[derive(Serialize)]
pub struct SegmentJson<'a> {
    /// `outgoing` or `return`.
    pub kind: SegmentKind,
    /// Receiver channel.
    pub channel: u8,
    /// Start of the first sample from the pulse's reference time, ns.
    pub start_ns: f64,
    /// Sample interval, ns.
    pub sample_ns: f64,
    /// Raw counts.
    pub samples: &'a [u16],
}

fn finite(v: f32) -> Option<f32> {
    v.is_finite().then_some(v)
}

/// The overview of a capture.
#[derive(Default, Serialize)]
struct Overview {
    file: String,
    version: String,
    headers: u64,
    sensor: Option<String>,
    origin: Option<String>,
    frames: u64,
    bad_frames: u64,
    nav_records: u64,
    nav_bytes: u64,
    gps_time_first: Option<f64>,
    gps_time_last: Option<f64>,
    samples_min: Option<u64>,
    samples_max: Option<u64>,
    bits: Vec<u8>,
    skipped: crate::format::SkipReport,
}

/// Runs `fwlidar inspect`.
pub fn run(args: InspectArgs) -> Result<(), Failure> {
    if let Some(format) = args.nav {
        return crate::cli::inspect_nav::run(&args.file, format, args.leap_seconds, args.json);
    }
    match InputKind::of_file(&args.file).map_err(Failure::job)? {
        InputKind::Capture => inspect_capture(args),
        _ => inspect_source(args),
    }
}

/// Inspects a file read through its [`crate::source::Source`] (LAS, PulseWaves): every pulse, or
/// an overview with the source's own report.
fn inspect_source(args: InspectArgs) -> Result<(), Failure> {
    let mut source = crate::source::open_file(&args.file).map_err(Failure::job)?;
    let pool = PulsePool::new(4);
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    let write_err = |e: std::io::Error| Failure::job(format!("cannot write output: {e}"));
    let mut ov = SourceOverview {
        file: args.file.display().to_string(),
        format: source.name(),
        ..Default::default()
    };
    let mut listed = 0u64;
    loop {
        match source
            .next(&pool)
            .map_err(|e| Failure::job(e.to_string()))?
        {
            SourceEvent::End => break,
            SourceEvent::Idle => {}
            SourceEvent::Nav(chunk) => {
                ov.nav_records += 1;
                ov.nav_bytes += chunk.bytes.len() as u64;
            }
            SourceEvent::Pulse(pulse) => {
                ov.pulses += 1;
                ov.gps_time_first.get_or_insert(pulse.gps_time);
                ov.gps_time_last = Some(pulse.gps_time);
                ov.with_geometry += u64::from(pulse.geometry.is_some());
                let n = pulse.raw.len() as u64;
                ov.samples_min = Some(ov.samples_min.map_or(n, |m| m.min(n)));
                ov.samples_max = Some(ov.samples_max.map_or(n, |m| m.max(n)));
                if !ov.bits.contains(&pulse.bits) {
                    ov.bits.push(pulse.bits);
                }
                if args.pulses && args.limit.is_none_or(|l| listed < l) {
                    listed += 1;
                    print_pulse(&mut out, &pulse, args.json).map_err(write_err)?;
                }
                pool.give(pulse);
                if args.pulses && args.limit.is_some_and(|l| listed >= l) {
                    break;
                }
            }
        }
    }
    if args.pulses {
        return out.flush().map_err(write_err);
    }
    ov.report = source.report();
    if args.json {
        serde_json::to_writer_pretty(&mut out, &ov)
            .map_err(|e| Failure::job(format!("cannot write output: {e}")))?;
        writeln!(out).map_err(write_err)?;
    } else {
        writeln!(
            out,
            "{}\n  format: {}\n  {} pulses ({} with anchor and direction), {} navigation records ({} bytes)\n  GPS time {} .. {} s; samples per pulse {}..{}; bits {:?}\n  report: {}",
            ov.file,
            ov.format,
            ov.pulses,
            ov.with_geometry,
            ov.nav_records,
            ov.nav_bytes,
            ov.gps_time_first.unwrap_or(f64::NAN),
            ov.gps_time_last.unwrap_or(f64::NAN),
            ov.samples_min.unwrap_or(0),
            ov.samples_max.unwrap_or(0),
            ov.bits,
            ov.report
        )
        .map_err(write_err)?;
    }
    out.flush().map_err(write_err)
}

/// The overview of a file read through a source.
#[derive(Default, Serialize)]
struct SourceOverview {
    file: String,
    format: &'static str,
    pulses: u64,
    with_geometry: u64,
    nav_records: u64,
    nav_bytes: u64,
    gps_time_first: Option<f64>,
    gps_time_last: Option<f64>,
    samples_min: Option<u64>,
    samples_max: Option<u64>,
    bits: Vec<u8>,
    report: serde_json::Value,
}

fn inspect_capture(args: InspectArgs) -> Result<(), Failure> {
    let mut reader = CaptureReader::open(&args.file).map_err(Failure::job)?;
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    let mut ov = Overview {
        file: args.file.display().to_string(),
        ..Default::default()
    };
    let (maj, min) = reader.version();
    ov.version = format!("{maj}.{min}");
    let mut pulse = Pulse::default();
    let mut listed = 0u64;
    let write_err = |e: std::io::Error| Failure::job(format!("cannot write output: {e}"));
    while let Some(rec) = reader.next_record() {
        match rec.map_err(Failure::job)? {
            Record::Header(text) => {
                ov.headers += 1;
                if ov.sensor.is_none()
                    && let Ok(h) = CaptureHeader::parse(text)
                {
                    ov.sensor = Some(h.sensor.name);
                    ov.origin = Some(h.capture.origin);
                }
            }
            Record::Nav { bytes, .. } => {
                ov.nav_records += 1;
                ov.nav_bytes += bytes.len() as u64;
            }
            Record::Frame(f) => {
                if f.decode_into(&mut pulse).is_err() {
                    ov.bad_frames += 1;
                    continue;
                }
                ov.frames += 1;
                ov.gps_time_first.get_or_insert(pulse.gps_time);
                ov.gps_time_last = Some(pulse.gps_time);
                let n = pulse.raw.len() as u64;
                ov.samples_min = Some(ov.samples_min.map_or(n, |m| m.min(n)));
                ov.samples_max = Some(ov.samples_max.map_or(n, |m| m.max(n)));
                if !ov.bits.contains(&pulse.bits) {
                    ov.bits.push(pulse.bits);
                }
                if args.pulses && args.limit.is_none_or(|l| listed < l) {
                    listed += 1;
                    print_pulse(&mut out, &pulse, args.json).map_err(write_err)?;
                }
            }
        }
    }
    ov.skipped = *reader.skipped();
    if args.pulses {
        return out.flush().map_err(write_err);
    }
    if args.json {
        serde_json::to_writer_pretty(&mut out, &ov)
            .map_err(|e| Failure::job(format!("cannot write output: {e}")))?;
        writeln!(out).map_err(write_err)?;
    } else {
        let s = &ov.skipped;
        writeln!(
            out,
            "{}\n  capture format {}; {} header record(s); sensor: {}; origin: {}\n  {} frames ({} undecodable), {} navigation records ({} bytes)\n  GPS time {} .. {} s; samples per pulse {}..{}; bits {:?}\n  damage: {} bytes skipped, {} bad checksums, {} resyncs, {} unknown records, {} bad payloads, {} bytes truncated tail",
            ov.file,
            ov.version,
            ov.headers,
            ov.sensor.as_deref().unwrap_or("?"),
            ov.origin.as_deref().unwrap_or("?"),
            ov.frames,
            ov.bad_frames,
            ov.nav_records,
            ov.nav_bytes,
            ov.gps_time_first.unwrap_or(f64::NAN),
            ov.gps_time_last.unwrap_or(f64::NAN),
            ov.samples_min.unwrap_or(0),
            ov.samples_max.unwrap_or(0),
            ov.bits,
            s.bytes_skipped,
            s.bad_checksums,
            s.resyncs,
            s.unknown_kinds,
            s.bad_payloads,
            s.truncated_tail_bytes
        )
        .map_err(write_err)?;
    }
    out.flush().map_err(write_err)
}

fn print_pulse(out: &mut impl Write, p: &Pulse, json: bool) -> std::io::Result<()> {
    let segments = p
        .segments
        .iter()
        .enumerate()
        .map(|(i, s)| SegmentJson {
            kind: s.kind,
            channel: s.channel,
            start_ns: s.start_ns,
            sample_ns: p.sample_ns,
            samples: p.raw_of(i),
        })
        .collect::<Vec<_>>();
    if json {
        let j = PulseJson {
            pulse_id: p.pulse_id,
            gps_time: p.gps_time,
            anchor: p.geometry.map(|g| g.anchor),
            direction: p.geometry.map(|g| g.direction),
            scan_angle_deg: [finite(p.scan_angle_deg[0]), finite(p.scan_angle_deg[1])],
            digitizer: [p.gain_v_per_dn, p.offset_v],
            segments,
        };
        serde_json::to_writer(&mut *out, &j).map_err(std::io::Error::other)?;
        writeln!(out)
    } else {
        write!(out, "pulse {} t={:.6}", p.pulse_id, p.gps_time)?;
        for s in &segments {
            write!(
                out,
                "  [{:?} ch{} start {} ns, {} samples]",
                s.kind,
                s.channel,
                s.start_ns,
                s.samples.len()
            )?;
        }
        writeln!(out)
    }
}
