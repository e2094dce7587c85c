//! The end of a run: `summary.json` (the runner's report with the run's warnings) and the
//! one-screen summary printed after it.

use std::path::Path;

use serde::Serialize;

use super::RunReport;
use super::warnings::{RunWarning, warnings_block};
use crate::core::atomic_file::write_atomic;
use crate::nav::consumer::NavReport;
use crate::sink::SinkReports;
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
) {
    println!();
    println!("fwlidar replay  {input}  ->  {}", out.display());
    print_pulses(r, chain);
    print_capture_damage(&r.source);
    print_navigation_ports(&r.nav);
    print_georeference(&r.source);
    print_las(&r.sinks);
    print_hyper_points(&r.sinks);
    print_voxels(r);
    print_stage_times(r);
    println!(
        "  {:.2} s wall, {:.0} pulses/s, {} workers; summary in {}",
        r.wall_time_s,
        r.pulses_per_s,
        r.workers,
        summary.display()
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
            (Some(a), Some(b)) => format!(", GPS week {} {:.1}..{:.1} s", a.week, a.sow, b.sow),
            _ => String::new(),
        };
        let reasons = counts_list(&v.rejected_by_reason)
            .map(|l| format!(" ({l})"))
            .unwrap_or_default();
        println!(
            "  navigation port {port}: {} bytes, {} samples ({kinds}){span}, {} rejected{reasons}",
            v.bytes, v.records, v.rejected,
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

/// `returns.las`: points, pulses, skips and the waveform packets.
fn print_las(sinks: &SinkReports) {
    let Some(las) = sinks.las() else {
        return;
    };
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
    println!(
        "  {name}: {} points (format {}) from {} pulses; {} pulses without geometry \
         skipped, {} returns unrepresentable{wdp}",
        las.points,
        las.point_format,
        las.pulses_written,
        las.pulses_without_geometry,
        las.returns_unrepresentable,
    );
}

/// `hyper_points.las`: points above the threshold.
fn print_hyper_points(sinks: &SinkReports) {
    if let Some(h) = sinks.hyper_points() {
        println!(
            "  hyper_points.las: {} points above {} V from {} pulses; {} pulses without geometry \
             skipped",
            h.points,
            json_number(f64::from(h.threshold_v)),
            h.pulses_written,
            h.pulses_without_geometry
        );
    }
}

/// `voxels.zarr`: bins and tiles, or why nothing was deposited.
fn print_voxels(r: &RunReport) {
    let Some(v) = r.sinks.voxels() else {
        return;
    };
    let d = &v.deposits;
    let outside = d.bins_outside_extent + d.bins_outside_heights + d.bins_outside_dem;
    if d.bins_deposited + d.bins_resumed == 0 {
        println!(
            "  voxels.zarr: nothing deposited ({})",
            nothing_deposited_reason(r.pulses_out, d, outside)
        );
    } else {
        let t = v.tiles.clone().unwrap_or_default();
        println!(
            "  voxels.zarr: {} bins of {} pulses deposited ({} outside the grid); tiles {} opened, \
             {} closed ({} early), {} merged with the store, at most {} open ({} height chunks \
             of {:.1} MB in memory at most); {:.1} MB compressed into {:.1} MB ({} chunk files, \
             {} inner chunks){}",
            d.bins_deposited,
            d.pulses_deposited,
            outside,
            t.lifecycle.opened,
            t.lifecycle.closed,
            t.lifecycle.closed_early,
            t.lifecycle.merged,
            t.lifecycle.peak_open,
            t.lifecycle.peak_chunks,
            t.lifecycle.chunk_bytes as f64 / 1e6,
            t.bytes_written as f64 / 1e6,
            t.bytes_stored as f64 / 1e6,
            t.chunks_written,
            t.inner_chunks_written,
            match d.bins_resumed {
                n if n > 0 => format!("; resumed: {n} bins already in the store"),
                _ => String::new(),
            }
        );
    }
    let skipped = d.pulses_no_geometry + d.pulses_non_finite;
    if skipped > 0 {
        println!(
            "    voxels skipped {skipped} pulses ({} without geometry, {} non-finite)",
            d.pulses_no_geometry, d.pulses_non_finite
        );
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
