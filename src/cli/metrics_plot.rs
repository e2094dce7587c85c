//! `fwlidar metrics-plot METRICS.csv --out FIGURE.svg`: the relative heights (RH25, RH50, RH75,
//! RH98 above the ground) and cover of every waveform of a `pulse_metrics.csv` (written by
//! `fwlidar replay` or `fwlidar process --metrics`) as one SVG figure, sorted by RH98 or in file
//! order (along the scan). The drawing is in `forest::metrics_plot`; `docs/forest.md` shows it.

use std::path::PathBuf;

use crate::cli::Failure;
use crate::core::atomic_file::write_atomic;
use crate::forest::metrics_plot::{PlotOrder, read_metrics, svg};

/// Arguments of `fwlidar metrics-plot`.
#[derive(Debug, clap::Args)]
pub struct MetricsPlotArgs {
    /// The metrics CSV (`pulse_metrics.csv` of a replay, or `fwlidar process --metrics`); it
    /// needs the columns pulse_id, status, rh25, rh50, rh75, rh98 and cover.
    pub metrics: PathBuf,
    /// The SVG figure to write (replaced if it exists; written complete or not at all).
    #[arg(long)]
    pub out: PathBuf,
    /// Order of the waveforms along the x axis: by RH98, or as in the file (along the scan).
    #[arg(long, value_enum, default_value_t = PlotOrder::Rh98)]
    pub order: PlotOrder,
    /// Title of the figure (default: the metrics file's name).
    #[arg(long)]
    pub title: Option<String>,
}

/// Runs `fwlidar metrics-plot`.
pub fn run(args: MetricsPlotArgs) -> Result<(), Failure> {
    if args.out.extension().and_then(|e| e.to_str()) != Some("svg") {
        return Err(Failure::usage(format!(
            "--out {}: the figure is an SVG; give a name ending in .svg",
            args.out.display()
        )));
    }
    let rows = read_metrics(&args.metrics).map_err(Failure::job)?;
    let title = args
        .title
        .clone()
        .unwrap_or_else(|| args.metrics.display().to_string());
    let doc = svg(&rows, args.order, &title);
    write_atomic(&args.out, doc.as_bytes())
        .map_err(|e| Failure::job(format!("{}: {e}", args.out.display())))?;
    let ok = rows.iter().filter(|r| r.ok).count();
    println!(
        "fwlidar metrics-plot  {}  ->  {}: {ok} of {} waveforms drawn ({})",
        args.metrics.display(),
        args.out.display(),
        rows.len(),
        match args.order {
            PlotOrder::Rh98 => "sorted by RH98",
            PlotOrder::Track => "in file order",
        }
    );
    Ok(())
}
