//! The end of a run: `summary.json` (the runner's report with the run's warnings) and the
//! one-screen summary printed after it.

use std::path::Path;

use serde::Serialize;

use super::RunReport;
use super::learn::ResponseReport;
use super::warnings::{RunWarning, warnings_block};
use crate::core::atomic_file::write_atomic;
use crate::nav::consumer::NavReport;
use crate::sink::las_wave::LasWaveReport;
use crate::sink::metrics_rasters::MetricsRastersReport;
use crate::sink::pulse_metrics_csv::PulseMetricsCsvReport;
use crate::sink::voxel_tiles::VoxelReport;
use crate::sink::{SinkReport, WaveformsReport};
use crate::source::report::SourceReport;
use crate::stages::Chain;
use crate::voxel::voxelise::DepositStats;

/// What `summary.json` holds: the runner's report, then the run's warnings.
#[derive(Serialize)]
pub struct Summary<'a> {
    /// The runner's report.
    #[serde(flatten)]
    pub report: &'a RunReport,
    /// What made an output empty or thinned it (`run::warnings`).
    pub warnings: &'a [RunWarning],
    /// The system response the `decompose` stage found echoes against, when it asked for one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub response: Option<&'a ResponseReport>,
}

/// Writes `summary` as `summary.json`-style pretty JSON to `path`, atomically. The error
/// names the file.
pub fn write_summary(path: &Path, summary: &impl Serialize) -> Result<(), String> {
    let json =
        serde_json::to_vec_pretty(summary).map_err(|e| format!("cannot encode summary: {e}"))?;
    write_atomic(path, &json).map_err(|e| e.to_string())
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1000.0
}

/// Prints the one-screen summary of a run to stdout, its warnings last; `chain` says what the
/// stages' notes mean.
pub fn print_summary(
    r: &RunReport,
    warnings: &[RunWarning],
    chain: &Chain,
    input: &str,
    out: &Path,
    summary: &Path,
    response: Option<&ResponseReport>,
) {
    println!();
    println!("fwlidar replay  {input}  ->  {}", out.display());
    print_pulses(r, chain);
    if let Some(resp) = response {
        for line in resp.lines() {
            println!("  {line}");
        }
    }
    print_capture_damage(&r.source);
    print_navigation_ports(&r.nav);
    print_georeference(&r.source);
    print_outputs(r, out, summary);
    print_stage_times(r);
    println!(
        "  {:.2} s wall, {:.0} pulses/s, {} workers",
        r.wall_time_s, r.pulses_per_s, r.workers,
    );
    print!("{}", warnings_block(warnings));
}

/// Pulses in, out, dropped (by reason) and passed on with a note.
fn print_pulses(r: &RunReport, chain: &Chain) {
    println!(
        "  pulses: {} in, {} out, {} dropped, {} errors{}",
        r.pulses_in,
        r.pulses_out,
        r.dropped_total,
        r.errors,
        if r.stopped_early {
            "  (stopped early by signal)"
        } else {
            ""
        }
    );
    for (reason, n) in &r.dropped {
        println!("    dropped {n:>10}  {reason}");
    }
    for (i, st) in r.stages.iter().enumerate() {
        for (note, n) in &st.notes {
            let meaning = chain
                .stage(i)
                .map_or("passed on partly unprocessed", |s| s.note_meaning(note));
            println!("    passed  {n:>10}  {}.{note} ({meaning})", st.name);
        }
    }
}

/// `"3 a, 1 b"` of counts by name (`None` when there are none).
fn counts_list<'a>(m: impl IntoIterator<Item = (&'a String, &'a u64)>) -> Option<String> {
    let list: Vec<String> = m.into_iter().map(|(k, n)| format!("{n} {k}")).collect();
    (!list.is_empty()).then(|| list.join(", "))
}

/// A number as the summary's JSON writes it (`5.0`, `0.30000001192092896` for an `f32`).
fn json_number(x: f64) -> serde_json::Value {
    serde_json::Value::from(x)
}

/// What the capture reader skipped.
fn print_capture_damage(source: &SourceReport) {
    if let Some(s) = source.capture_damage() {
        if s.is_clean() {
            println!("  capture: intact, no byte skipped");
            return;
        }
        println!(
            "  capture damage: {} bytes skipped ({} bad checksums), {} bytes of truncated tail",
            s.bytes_skipped, s.bad_checksums, s.truncated_tail_bytes
        );
    }
}

/// One line per navigation port: bytes, samples by kind, GPS time span, rejections.
fn print_navigation_ports(nav: &NavReport) {
    for (port, v) in &nav.ports {
        let kinds = counts_list(&v.by_kind).unwrap_or_default();
        let span = match (&v.first_gps_time, &v.last_gps_time) {
            (Some(a), Some(b)) => format!(", week {} {:.1}-{:.1} s", a.week, a.sow, b.sow),
            _ => String::new(),
        };
        let rejected = match counts_list(&v.rejected_by_reason) {
            Some(l) => format!(", {} rejected ({l})", v.rejected),
            None if v.rejected > 0 => format!(", {} rejected", v.rejected),
            None => String::new(),
        };
        println!(
            "  navigation port {port}: {} bytes, {} samples ({kinds}){span}{rejected}",
            v.bytes, v.records,
        );
    }
}

/// Pulses placed by the georeferencing, and those it missed by reason.
fn print_georeference(source: &SourceReport) {
    if let Some(g) = source.georeference() {
        println!(
            "  georeference: {} pulses placed in {}, {} carried their own geometry, missed: {}",
            g.georeferenced,
            g.output_crs.as_deref().unwrap_or("(no fix, no CRS)"),
            g.with_own_geometry,
            counts_list(&g.missed).unwrap_or_else(|| "none".into()),
        );
    }
}

/// Every output the run wrote, one line each in the order the outputs ran (`name  what it
/// holds`), then `summary.json`; the full reports are in `summary.json`.
fn print_outputs(r: &RunReport, out: &Path, summary: &Path) {
    println!("  written in {}:", out.display());
    for (name, report) in &r.sinks.0 {
        match report {
            SinkReport::Waveforms(w) => print_waveforms(name, w),
            SinkReport::ReturnsCsv(c) => output_line("returns.csv", &format!("{} returns", c.rows)),
            SinkReport::Las(las) => print_las(las),
            SinkReport::HyperPoints(h) => output_line(
                "hyper_points.las",
                &format!(
                    "{} samples above {} V of {} pulses{}",
                    h.points,
                    json_number(f64::from(h.threshold_v)),
                    h.pulses_written,
                    without_geometry(h.pulses_without_geometry)
                ),
            ),
            SinkReport::PulseMetricsCsv(m) => print_pulse_metrics(m),
            SinkReport::MetricsRasters(m) => print_rasters(m),
            SinkReport::Voxels(v) => print_voxels(v, r.pulses_out),
            SinkReport::None => {}
        }
    }
    let file = summary.file_name().map_or_else(
        || summary.display().to_string(),
        |f| f.to_string_lossy().into_owned(),
    );
    output_line(
        &file,
        "this summary, with each stage's and output's whole report",
    );
}

/// One output's line: its name in a column, then what it holds.
fn output_line(name: &str, what: &str) {
    println!("    {name:<18} {what}");
}

/// `; N pulses without geometry left out`, or nothing.
fn without_geometry(n: u64) -> String {
    if n > 0 {
        format!("; {n} pulses without geometry left out")
    } else {
        String::new()
    }
}

/// The processed waveforms: `waveforms.npy` + its index, or the CSV pair.
fn print_waveforms(sink: &str, w: &WaveformsReport) {
    if sink == "waveform_csv" {
        output_line(
            "waveforms.csv",
            &format!(
                "{} segments, one per line (V); pulses.csv indexes them",
                w.segments
            ),
        );
    } else {
        output_line(
            "waveforms.npy",
            &format!(
                "{} segments, {} samples (V); waveform_index.npy indexes them",
                w.segments, w.samples
            ),
        );
    }
}

/// `returns.las`: points, pulses, skips and the waveform packets.
fn print_las(las: &LasWaveReport) {
    let name = if las.files.len() == 1 {
        las.files[0].clone()
    } else {
        format!("returns_NNNN.las ({} files)", las.files.len())
    };
    let wdp = if las.point_format == 9 {
        format!("; .wdp: {} packets, {} bytes", las.packets, las.wdp_bytes)
    } else {
        String::new()
    };
    let unrepresentable = if las.returns_unrepresentable > 0 {
        format!("; {} returns unrepresentable", las.returns_unrepresentable)
    } else {
        String::new()
    };
    output_line(
        &name,
        &format!(
            "{} points (format {}) of {} pulses{}{unrepresentable}{wdp}",
            las.points,
            las.point_format,
            las.pulses_written,
            without_geometry(las.pulses_without_geometry),
        ),
    );
}

/// `pulse_metrics.csv`: rows, and why the others have no metrics.
fn print_pulse_metrics(m: &PulseMetricsCsvReport) {
    let mut why = Vec::new();
    for (n, what) in [
        (m.no_ground, "no ground"),
        (m.no_signal, "no signal"),
        (m.no_waveform, "no waveform"),
        (m.non_finite, "non-finite"),
    ] {
        if n > 0 {
            why.push(format!("{n} {what}"));
        }
    }
    let why = if why.is_empty() {
        String::new()
    } else {
        format!(" ({})", why.join(", "))
    };
    output_line(
        "pulse_metrics.csv",
        &format!("{} pulses, {} with forest metrics{why}", m.rows, m.ok),
    );
}

/// The metrics rasters: the VRT mosaics and their tiles, or why there are none.
fn print_rasters(m: &MetricsRastersReport) {
    if m.written.is_empty() {
        output_line(
            "rasters/",
            &format!(
                "nothing written: no pulse had metrics and a position ({} without metrics, {} \
                 without a position or CRS)",
                m.without_metrics, m.without_position_or_crs
            ),
        );
        return;
    }
    let list: Vec<String> = m
        .written
        .iter()
        .map(|w| w.trim_start_matches("rasters/").to_string())
        .collect();
    output_line(
        "rasters/",
        &format!(
            "{}; cells of {} m and {} m",
            list.join(", "),
            json_number(m.chm_cell_m),
            json_number(m.profile_cell_m)
        ),
    );
}

/// `voxels.zarr`: bins and tiles, or why nothing was deposited; what went unusual on a
/// second line.
fn print_voxels(v: &VoxelReport, pulses_out: u64) {
    let d = &v.deposits;
    let outside = d.bins_outside_extent + d.bins_outside_heights + d.bins_outside_dem;
    if d.bins_deposited + d.bins_resumed == 0 {
        output_line(
            "voxels.zarr",
            &format!(
                "nothing deposited ({})",
                nothing_deposited_reason(pulses_out, d, outside)
            ),
        );
        return;
    }
    let t = v.tiles.clone().unwrap_or_default();
    let tiles = t.lifecycle.opened;
    output_line(
        "voxels.zarr",
        &format!(
            "{} bins of {} pulses in {tiles} tile{}; {} on disk",
            d.bins_deposited,
            d.pulses_deposited,
            if tiles == 1 { "" } else { "s" },
            megabytes(t.bytes_stored),
        ),
    );
    let mut notes = Vec::new();
    for (n, what) in [
        (outside, "bins outside the grid"),
        (
            d.pulses_no_geometry + d.pulses_non_finite,
            "pulses without geometry",
        ),
        (t.lifecycle.closed_early, "tiles closed early"),
        (t.lifecycle.merged, "tiles merged with the store"),
        (d.bins_resumed, "bins already in the store (resumed)"),
    ] {
        if n > 0 {
            notes.push(format!("{n} {what}"));
        }
    }
    if !notes.is_empty() {
        println!("    {:<18} {}", "", notes.join(", "));
    }
}

/// Bytes as `0.3 MB` (or `12 kB` below 0.1 MB).
fn megabytes(bytes: u64) -> String {
    if bytes < 100_000 {
        format!("{:.0} kB", bytes as f64 / 1e3)
    } else {
        format!("{:.1} MB", bytes as f64 / 1e6)
    }
}

/// Why the voxel sink deposited nothing, in words.
fn nothing_deposited_reason(pulses_out: u64, d: &DepositStats, outside: u64) -> String {
    let no_geometry = d.pulses_no_geometry + d.pulses_non_finite;
    if pulses_out == 0 {
        "no pulse reached it".into()
    } else if no_geometry >= pulses_out {
        format!("none of the {pulses_out} pulses had geometry: not georeferenced")
    } else if outside > 0 {
        format!("all {outside} return bins fell outside the grid")
    } else {
        format!("the {pulses_out} pulses had no return bins to deposit")
    }
}

/// Service time per stage, and the end-to-end latency.
fn print_stage_times(r: &RunReport) {
    println!(
        "  {:<14} {:>10} {:>10} {:>10} {:>10} {:>10}   (service time, µs)",
        "stage", "received", "p50", "p99", "p99.9", "max"
    );
    for s in &r.stages {
        println!(
            "  {:<14} {:>10} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
            s.name,
            s.received,
            us(s.service.p50_ns),
            us(s.service.p99_ns),
            us(s.service.p999_ns),
            us(s.service.max_ns)
        );
    }
    let e = &r.end_to_end;
    println!(
        "  end-to-end latency µs: p50 {:.1}  p99 {:.1}  p99.9 {:.1}  max {:.1}",
        us(e.p50_ns),
        us(e.p99_ns),
        us(e.p999_ns),
        us(e.max_ns)
    );
}
