//! `fwlidar inspect`: what a capture holds (navigation files: `inspect_nav.rs`) — header, record counts, time span, damage — and,
//! with `--pulses --json`, every pulse as one JSON object per line.

use std::io::Write;
use std::path::PathBuf;

use serde::Serialize;

use crate::cli::Failure;
use crate::format::{CaptureHeader, CaptureReader, Record};
use crate::pipeline::ports::SourceEvent;
use crate::pulse::{Pulse, PulsePool, SegmentKind};
use crate::source::InputKind;
use crate::source::gedi::GediReport;
use crate::source::las::WavePacketDescriptorReport;
use crate::source::pulsewaves::{PulseDescriptorReport, PulseWavesReport, SamplingCount};
use crate::source::report::{InputReport, SourceReport};

/// Arguments of `fwlidar inspect`.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// The file: a capture, LAS or LAZ (+ .wdp), PulseWaves (.pls + .wvs) or GEDI L1B (.h5).
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

/// Inspects a file read through its [`crate::pipeline::ports::Source`] (LAS, PulseWaves): every pulse, or
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
            "{}\n  format: {}\n  {} pulses ({} with anchor and direction), {} navigation records ({} bytes)\n  GPS time {} .. {} s; samples per pulse {}..{}; bits {:?}",
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
        )
        .map_err(write_err)?;
        write_report(&mut out, &ov.report).map_err(write_err)?;
    }
    out.flush().map_err(write_err)
}

/// Writes a source's report for people: its plain values one per line, the format's lists
/// (LAS wave packet descriptors, PulseWaves pulse descriptors and scanners, GEDI beams) as
/// aligned tables, GEDI's extent as ranges, the warnings one per line, what wrappers add as
/// compact JSON. `--json` prints the report as is.
fn write_report(out: &mut impl Write, report: &SourceReport) -> std::io::Result<()> {
    let json = report.to_json();
    let Some(map) = json.as_object() else {
        return writeln!(out, "  report: {json}");
    };
    writeln!(out, "  report:")?;
    let plain: Vec<_> = map
        .iter()
        .filter(|(_, v)| !v.is_array() && !v.is_object())
        .collect();
    let width = plain.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    for (k, v) in plain {
        writeln!(out, "    {k:<width$}  {}", cell(v))?;
    }
    match &report.input {
        InputReport::Las(r) => write_table_section(
            out,
            "wave_packet_descriptors",
            "wave packet descriptors",
            &las_descriptor_rows(&r.wave_packet_descriptors),
        )?,
        InputReport::PulseWaves(r) => write_pulsewaves_lists(out, r)?,
        InputReport::Gedi(r) => write_gedi_lists(out, r)?,
        _ => {}
    }
    if let Some(g) = &report.georeference {
        writeln!(out, "  georeference: {}", to_json(g))?;
    }
    if let Some(s) = &report.shard {
        writeln!(out, "  shard: {}", to_json(s))?;
    }
    Ok(())
}

fn to_json(v: &impl serde::Serialize) -> serde_json::Value {
    serde_json::to_value(v).unwrap_or_default()
}

/// A list as a table under its title, or `name: none` when it is empty (`rows` holds the
/// header alone).
fn write_table_section(
    out: &mut impl Write,
    name: &str,
    title: &str,
    rows: &[Vec<String>],
) -> std::io::Result<()> {
    if rows.len() <= 1 {
        return writeln!(out, "  {name}: none");
    }
    writeln!(out, "  {title}:")?;
    write_table(out, "    ", rows)
}

/// A PulseWaves file's pulse descriptors and scanners as tables, its warnings one per line.
fn write_pulsewaves_lists(out: &mut impl Write, r: &PulseWavesReport) -> std::io::Result<()> {
    write_table_section(
        out,
        "descriptors",
        "pulse descriptors",
        &pulse_descriptor_rows(&r.descriptors),
    )?;
    let scanners: Vec<(u64, serde_json::Value)> = r
        .scanners
        .iter()
        .map(|s| (u64::from(s.index), to_json(s)))
        .collect();
    write_table_section(
        out,
        "scanners",
        "scanners",
        &transposed_rows("scanner", &scanners),
    )?;
    if r.warnings.is_empty() {
        writeln!(out, "  warnings: none")
    } else {
        writeln!(out, "  warnings:")?;
        r.warnings
            .iter()
            .try_for_each(|w| writeln!(out, "    - {w}"))
    }
}

/// A GEDI granule's beams as a table and its extent as ranges (min .. max).
fn write_gedi_lists(out: &mut impl Write, r: &GediReport) -> std::io::Result<()> {
    let mut rows = vec![
        [
            "name",
            "shots",
            "pulses",
            "stale",
            "no samples",
            "too long",
            "bad geolocation",
            "degraded",
        ]
        .map(String::from)
        .to_vec(),
    ];
    for b in &r.beams {
        rows.push(vec![
            b.name.clone(),
            b.shots.to_string(),
            b.pulses.to_string(),
            b.stale.to_string(),
            b.no_samples.to_string(),
            b.too_long.to_string(),
            b.bad_geolocation.to_string(),
            b.degraded.to_string(),
        ]);
    }
    write_table_section(out, "beams", "beams", &rows)?;
    let e = &r.extent;
    let range = |v: Option<[f64; 2]>| match v {
        Some([lo, hi]) => format!("{} .. {}", number_cell(lo), number_cell(hi)),
        None => "-".into(),
    };
    let lines: [(&str, String); 9] = [
        ("elevation_m", range(e.elevation_m)),
        (
            "gps_time",
            // Times to the microsecond: 7 digits would hide the span.
            e.gps_time
                .map_or("-".into(), |[lo, hi]| format!("{lo:.6} .. {hi:.6} s")),
        ),
        ("latitude_deg", range(e.latitude_deg)),
        ("longitude_deg", range(e.longitude_deg)),
        ("noise_stddev_counts", range(e.noise_stddev_counts)),
        (
            "rx_samples",
            e.rx_samples
                .map_or("-".into(), |[lo, hi]| format!("{lo} .. {hi}")),
        ),
        ("tx_fwhm_ns", range(e.tx_fwhm_ns)),
        ("x_m", range(e.x_m)),
        ("y_m", range(e.y_m)),
    ];
    writeln!(out, "  extent (min .. max):")?;
    let width = lines.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    lines
        .iter()
        .try_for_each(|(k, text)| writeln!(out, "    {k:<width$}  {text}"))
}

/// A number as a table cell (see [`cell`]).
fn number_cell(x: f64) -> String {
    cell(&serde_json::Value::from(x))
}

/// A JSON value as a table cell: strings unquoted, numbers to 7 significant digits (the
/// precision of the `f32` most of them come from), `null` as `-`.
fn cell(v: &serde_json::Value) -> String {
    use serde_json::Value;
    match v {
        Value::Null => "-".into(),
        Value::String(s) => s.clone(),
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            if x == 0.0 || !x.is_finite() {
                return format!("{x}");
            }
            let decimals = (6 - x.abs().log10().floor() as i32).clamp(0, 20) as usize;
            let s = format!("{x:.decimals$}");
            if s.contains('.') {
                s.trim_end_matches('0').trim_end_matches('.').to_string()
            } else {
                s
            }
        }
        other => other.to_string(),
    }
}

/// The LAS wave packet descriptors as table rows (header first); consecutive indices with the
/// same fields share a row (`3-100`).
fn las_descriptor_rows(list: &[WavePacketDescriptorReport]) -> Vec<Vec<String>> {
    let mut rows = vec![
        [
            "index",
            "bits",
            "compression",
            "samples",
            "interval (ps)",
            "gain (V/count)",
            "offset (V)",
        ]
        .map(String::from)
        .to_vec(),
    ];
    let mut run: Option<(u64, u64, Vec<String>)> = None;
    let flush = |run: &mut Option<(u64, u64, Vec<String>)>, rows: &mut Vec<Vec<String>>| {
        if let Some((first, last, cells)) = run.take() {
            let index = if first == last {
                first.to_string()
            } else {
                format!("{first}-{last}")
            };
            rows.push(std::iter::once(index).chain(cells).collect());
        }
    };
    for d in list {
        let index = d.index as u64;
        let cells = vec![
            d.bits_per_sample.to_string(),
            d.compression.to_string(),
            d.samples.to_string(),
            d.temporal_spacing_ps.to_string(),
            number_cell(d.digitizer_gain),
            number_cell(d.digitizer_offset),
        ];
        match &mut run {
            Some((_, last, c)) if *last + 1 == index && *c == cells => *last = index,
            _ => {
                flush(&mut run, &mut rows);
                run = Some((index, index, cells));
            }
        }
    }
    flush(&mut run, &mut rows);
    rows
}

/// The PulseWaves pulse descriptors as table rows (header first): one row per sampling, the
/// descriptor's index, scanner and description on its first.
fn pulse_descriptor_rows(list: &[PulseDescriptorReport]) -> Vec<Vec<String>> {
    let mut rows = vec![
        [
            "index",
            "scanner",
            "sampling",
            "type",
            "channel",
            "bits",
            "segments",
            "samples",
            "interval (ns)",
            "lookup table",
            "description",
        ]
        .map(String::from)
        .to_vec(),
    ];
    let count = |c: SamplingCount| match c {
        SamplingCount::Fixed(n) => n.to_string(),
        SamplingCount::Variable(v) => v.to_string(),
    };
    for d in list {
        if d.samplings.is_empty() {
            let mut row = vec![d.index.to_string(), d.scanner_index.to_string()];
            row.extend(std::iter::repeat_n(String::new(), 8));
            row.push(d.description.clone());
            rows.push(row);
        }
        for (i, s) in d.samplings.iter().enumerate() {
            let first = i == 0;
            let on_first = |text: String| if first { text } else { String::new() };
            rows.push(vec![
                on_first(d.index.to_string()),
                on_first(d.scanner_index.to_string()),
                (i + 1).to_string(),
                cell(&to_json(&s.kind)),
                s.channel.to_string(),
                s.bits_per_sample.to_string(),
                count(s.segments),
                count(s.samples),
                number_cell(f64::from(s.sample_units_ns)),
                match s.lookup_table_index {
                    0 => "-".to_string(),
                    n => n.to_string(),
                },
                on_first(d.description.clone()),
            ]);
        }
    }
    rows
}

/// Records (each with its number and its fields as a JSON object) as a table with a row per
/// field and a column per record (`scanner 1`, ...).
fn transposed_rows(what: &str, list: &[(u64, serde_json::Value)]) -> Vec<Vec<String>> {
    let mut keys: Vec<&str> = Vec::new();
    for (_, o) in list {
        for k in o.as_object().into_iter().flat_map(|o| o.keys()) {
            if k != "index" && !keys.contains(&k.as_str()) {
                keys.push(k);
            }
        }
    }
    let mut header = vec![String::new()];
    header.extend(list.iter().map(|(n, _)| format!("{what} {n}")));
    let mut rows = vec![header];
    for k in keys {
        let mut row = vec![k.to_string()];
        row.extend(
            list.iter()
                .map(|(_, o)| cell(o.get(k).unwrap_or(&serde_json::Value::Null))),
        );
        rows.push(row);
    }
    rows
}

/// Writes `rows` (the first is the header) as columns separated by two spaces, each line
/// prefixed by `indent`: columns whose cells are all numbers are right-aligned, others left.
fn write_table(out: &mut impl Write, indent: &str, rows: &[Vec<String>]) -> std::io::Result<()> {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let width = |c: usize| {
        rows.iter()
            .filter_map(|r| r.get(c))
            .map(|s| s.chars().count())
            .max()
            .unwrap_or(0)
    };
    let numeric = |c: usize| {
        rows.iter()
            .skip(1)
            .filter_map(|r| r.get(c))
            .filter(|s| !s.is_empty())
            .all(|s| s.parse::<f64>().is_ok())
    };
    let layout: Vec<(usize, bool)> = (0..columns).map(|c| (width(c), numeric(c))).collect();
    for row in rows {
        let mut line = String::from(indent);
        for (c, (w, right)) in layout.iter().enumerate() {
            let text = row.get(c).map_or("", String::as_str);
            if c > 0 {
                line.push_str("  ");
            }
            let pad = w.saturating_sub(text.chars().count());
            if *right {
                line.extend(std::iter::repeat_n(' ', pad));
                line.push_str(text);
            } else {
                line.push_str(text);
                line.extend(std::iter::repeat_n(' ', pad));
            }
        }
        writeln!(out, "{}", line.trim_end())?;
    }
    Ok(())
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
    report: SourceReport,
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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn inspect_cells_round_to_seven_digits() {
        assert_eq!(cell(&json!(0.30000001192092896)), "0.3");
        assert_eq!(cell(&json!(28.300003051757812)), "28.3");
        assert_eq!(cell(&json!(0.00390625)), "0.00390625");
        assert_eq!(cell(&json!(1.0)), "1");
        assert_eq!(cell(&json!(0.0)), "0");
        assert_eq!(cell(&json!(1234567.5)), "1234568");
        assert_eq!(cell(&json!(240)), "240");
        assert_eq!(cell(&json!("text")), "text");
        assert_eq!(cell(&json!(null)), "-");
    }

    #[test]
    fn inspect_identical_consecutive_descriptors_share_a_row() {
        let d = |index: usize, samples: u32| WavePacketDescriptorReport {
            index,
            bits_per_sample: 16,
            compression: 0,
            samples,
            temporal_spacing_ps: 1000,
            digitizer_gain: 1.0,
            digitizer_offset: 0.0,
            payload_bytes: 26,
        };
        let rows = las_descriptor_rows(&[d(1, 60), d(2, 0), d(3, 0), d(4, 0), d(6, 0), d(7, 5)]);
        let index: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
        // 5 is missing, so 6 starts a new run; 7 differs.
        assert_eq!(index, ["index", "1", "2-4", "6", "7"]);
        assert_eq!(rows[2], ["2-4", "16", "0", "0", "1000", "1", "0"]);
    }

    #[test]
    fn inspect_tables_align_numbers_right_and_text_left() {
        let rows: Vec<Vec<String>> = [["n", "name"], ["5", "a"], ["120", "long name"]]
            .iter()
            .map(|r| r.iter().map(|s| s.to_string()).collect())
            .collect();
        let mut out = Vec::new();
        write_table(&mut out, "  ", &rows).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "    n  name\n    5  a\n  120  long name\n"
        );
    }
}
