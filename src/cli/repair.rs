//! `fwlidar repair FILE.las`: rebuilds the header of a LAS 1.4 file cut off by a crash (point
//! count, per-return counts, bounding box, legacy counts; a partial last record is cut; the
//! `.wdp`'s record length is fixed), after copying the original to `FILE.las.bak`. The work is in
//! `format::las_repair`; layout and rules: `docs/formats.md`, "Repairing a cut LAS file".

use std::path::PathBuf;

use crate::cli::Failure;
use crate::format::las_repair::{RepairError, repair_file};

/// Arguments of `fwlidar repair`.
#[derive(Debug, clap::Args)]
pub struct RepairArgs {
    /// The LAS 1.4 file (point format 6–10) whose header to rebuild; also a `NAME.las.partial`
    /// left by a killed `replay` (its `.wdp` is then `NAME.wdp.partial`).
    pub file: PathBuf,
    /// Print the report (every field changed, before and after) as one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Runs `fwlidar repair`.
pub fn run(args: RepairArgs) -> Result<(), Failure> {
    let report = repair_file(&args.file).map_err(|e: RepairError| Failure::job(e))?;
    if args.json {
        let s = serde_json::to_string_pretty(&report)
            .map_err(|e| Failure::job(format!("cannot encode the report: {e}")))?;
        println!("{s}");
        return Ok(());
    }
    if !report.repaired {
        println!(
            "{}: nothing to repair ({} points, header consistent)",
            report.file, report.points
        );
        return Ok(());
    }
    println!(
        "{}: repaired: {} points (header said {}), backup {}",
        report.file,
        report.points,
        report.points_in_header,
        report.backup.as_deref().unwrap_or("-")
    );
    if report.trailing_bytes_dropped > 0 {
        println!(
            "  cut {} bytes of a partial last point record",
            report.trailing_bytes_dropped
        );
    }
    if report.points_dropped_without_waveform > 0 {
        println!(
            "  dropped {} trailing points whose waveform packets lie past the end of the .wdp",
            report.points_dropped_without_waveform
        );
    }
    for c in &report.changed {
        println!("  {}: {} -> {}", c.field, c.before, c.after);
    }
    if let Some(w) = &report.wdp
        && w.record_length_before != w.record_length_after
    {
        println!(
            "  {}: record length {} -> {}",
            w.file, w.record_length_before, w.record_length_after
        );
    }
    for n in &report.notes {
        println!("  note: {n}");
    }
    Ok(())
}
