//! `fwlidar process`: the offline tool for waveform tables (CSV or `.npy`, one waveform per
//! row). Each row is denoised (unless `--no-denoise`), deconvolved with a kernel (unless
//! `--method none`) and written, same length, to the output table; `--returns` adds the
//! Gaussian decomposition of every processed row.
//!
//! Values are taken in the file's unit (volts, or digitizer counts: no gain is known, so the
//! outputs are in the same "signal units"). The job either writes every output complete or
//! nothing: any bad row fails the whole job (exit 1) naming the file and line (CSV) or row
//! (NPY), and outputs are only moved into place after every row was processed.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::cli::learn_kernel::{KernelLearning, learn_kernel};
use crate::core::atomic_file::{AtomicFile, write_atomic};
use crate::forest::measure::pulse_sigma_ns;
use crate::forest::pulse_metrics::MetricsConfig;
use crate::forest::table_metrics::{TableMetrics, TableWaveform, read_geometry};
use crate::format::table::{Table, TableFormat, read_table, write_table};
use crate::pulse::{FittedReturn, PulseGeometry};
use crate::signal::decompose::{DecomposeConfig, Decomposer};
use crate::signal::deconvolve::response::response_from_flat_target;
use crate::signal::deconvolve::{
    ChoiceCounts, Deconvolver, MethodConfig, NnlsOrRlConfig, Targeted,
};
use crate::signal::denoise::{Denoise, DenoiseConfig};
use crate::signal::drift::{DriftBaseline, flag_saturated};
use crate::signal::echo_strength::{DetectedEcho, EchoDetector};
use crate::signal::kernel::{Kernel, remove_baseline};

pub use crate::signal::kernel::KERNEL_BASELINE_SAMPLES;

/// Rows from which a progress bar is drawn (on a terminal).
const PROGRESS_MIN_ROWS: usize = 1000;

/// Deconvolution methods of `fwlidar process`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ProcessMethod {
    /// Richardson-Lucy.
    Rl,
    /// Wiener filter.
    Wiener,
    /// Non-negative least squares.
    Nnls,
    /// Gold.
    Gold,
    /// NNLS or Richardson-Lucy, chosen per row by their residuals.
    #[value(name = "nnls_or_rl")]
    NnlsOrRl,
    /// No deconvolution (denoise only, or a plain copy with `--no-denoise`).
    None,
}

impl ProcessMethod {
    /// The method's name on the command line.
    pub fn cli_name(self) -> &'static str {
        match self {
            ProcessMethod::Rl => "rl",
            ProcessMethod::Wiener => "wiener",
            ProcessMethod::Nnls => "nnls",
            ProcessMethod::Gold => "gold",
            ProcessMethod::NnlsOrRl => "nnls_or_rl",
            ProcessMethod::None => "none",
        }
    }

    /// The method's name in configuration (`method = "..."`), `None` for `none`.
    pub fn config_name(self) -> Option<&'static str> {
        match self {
            ProcessMethod::Rl => Some("richardson_lucy"),
            ProcessMethod::Wiener => Some("wiener"),
            ProcessMethod::Nnls => Some("nnls"),
            ProcessMethod::Gold => Some("gold"),
            ProcessMethod::NnlsOrRl => Some("nnls_or_rl"),
            ProcessMethod::None => None,
        }
    }
}

/// Arguments of `fwlidar process`.
#[derive(Debug, clap::Args)]
pub struct ProcessArgs {
    /// Waveform table to process (`.csv` or `.npy`), one waveform per row.
    #[arg(long)]
    pub input: PathBuf,
    /// System response (`.csv` or `.npy`): one row, or one column (one value per line, as in
    /// NEON's `imp.csv`); with `--kernel-per-row`, one outgoing pulse per input row. Its
    /// baseline (median of the first 8 samples) is removed, negative samples clipped, the
    /// rest normalised to unit sum and centred on its peak. A method needs `--kernel`,
    /// `--response`, or both (the response is deconvolved first).
    #[arg(long)]
    pub kernel: Option<PathBuf>,
    /// Calibrated system response `h` (`.csv` or `.npy`, one row or one column), deconvolved
    /// from every row *before* `--kernel` (the waveformlidar package's two steps: returns by
    /// the system response, then by the outgoing pulse). Prepared like `--kernel`; with
    /// `--response-outgoing` it is a flat-target return instead, and `h` is measured from it.
    #[arg(long)]
    pub response: Option<PathBuf>,
    /// The outgoing pulse recorded with the flat-target return given as `--response` (one row
    /// or column): `h` is then that return deconvolved by this pulse, with `--method`
    /// (e.g. NEON's `imp.csv` and `imp_out.csv`).
    #[arg(long, requires = "response")]
    pub response_outgoing: Option<PathBuf>,
    /// Deconvolution method.
    #[arg(long, value_enum)]
    pub method: ProcessMethod,
    /// Iteration budget of iterative methods (for NNLS its outer iterations,
    /// `max_iterations`: at most one non-zero sample each). When absent, the method's
    /// default — except
    /// Richardson-Lucy and Gold with `--target-fwhm-ns`: 50 × the kernel's FWHM / the target's
    /// (20 to 1000; e.g. 200 for an 8 ns kernel to 2 ns), since a narrower target needs more
    /// iterations (docs/accuracy.md, "Deconvolution over noise models").
    #[arg(long)]
    pub iterations: Option<u32>,
    /// Deliver the result as seen by a Gaussian target pulse of this FWHM, ns (e.g. 2), not as
    /// spikes: RL, Gold and Wiener deconvolve by the kernel that maps the target pulse to the
    /// system pulse, NNLS draws its spikes as the target pulse (see `docs/signal.md`). With
    /// `--response` and `--kernel` it applies to the last step (the kernel).
    #[arg(long)]
    pub target_fwhm_ns: Option<f64>,
    /// Richardson-Lucy and Gold: stop by the noise (discrepancy principle) once the residual
    /// RMS is at most this multiple of the row's noise level (dimensionless, > 0); the
    /// iterations stay the cap. See `stop_at_noise` in docs/signal.md.
    #[arg(long)]
    pub stop_at_noise: Option<f32>,
    /// NNLS: spikes only near echoes — a sample may hold a spike only when a sample above this
    /// multiple of the row's noise level lies within its kernel's reach (dimensionless, > 0;
    /// 0 = anywhere). Default with `--method nnls`: 4. See `support_at_noise` in
    /// docs/signal.md.
    #[arg(long)]
    pub support_at_noise: Option<f32>,
    /// Sample interval, ns.
    #[arg(long, default_value_t = 1.0)]
    pub sample_ns: f64,
    /// Low-pass cut-off of the denoise step, GHz (must lie below 1 / (2 × sample interval)).
    /// Default 0.2, except for NNLS: no low-pass (the fit by the kernel's pulses is the
    /// smoothing; at a 4 ns pulse the 0.2 GHz low-pass took the close pairs NNLS resolves,
    /// docs/accuracy.md "Deconvolution over noise models").
    #[arg(long)]
    pub cutoff_ghz: Option<f64>,
    /// The kernel table holds one outgoing pulse per input row (row counts must match).
    #[arg(long)]
    pub kernel_per_row: bool,
    /// Learn the kernel from the rows themselves: their isolated, strong single echoes aligned
    /// to a quarter of a sample and averaged (as `fwlidar response learn` does on a file), for
    /// when the system pulse is not known to better than ~10 %. `--kernel`, when given, is the
    /// starting point: the summary states the learned width against it, and it is used when
    /// the rows hold too few clean single echoes (under 20). Not with `--kernel-per-row` or
    /// `--response`.
    #[arg(long)]
    pub learn_kernel: bool,
    /// Skip the denoise step (no baseline removal, no low-pass).
    #[arg(long)]
    pub no_denoise: bool,
    /// The baseline the denoise step removes: `line` (default), a straight line fitted to the
    /// row's lower samples (a pedestal or a drifting baseline, no pre-trigger window needed;
    /// `src/signal/drift.rs`); `level`, the denoise step's level alone (the median of the
    /// first samples).
    #[arg(long, value_enum, default_value_t = BaselineModel::Line)]
    pub baseline: BaselineModel,
    /// Trailing zeros of a row are padding, not samples (zero-padded exports such as NEON's
    /// `return.csv` and `outg.csv`): only the samples before them are processed, and the output
    /// row keeps its length with zeros in their place. Applies to kernel rows too.
    #[arg(long)]
    pub zero_padding: bool,
    /// Leading columns of every input row to ignore (an index column, for example).
    #[arg(long, default_value_t = 0)]
    pub skip_columns: usize,
    /// Output table (`.csv` or `.npy`), one processed waveform per input row, same lengths.
    #[arg(long)]
    pub out: PathBuf,
    /// Also decompose every processed row into Gaussians and write them here (CSV:
    /// `waveform,position_bins,amplitude,sigma_bins`, waveform the 0-based row index).
    #[arg(long)]
    pub returns: Option<PathBuf>,
    /// Also detect the echoes of every processed row and write them here (CSV:
    /// `waveform,position_bins,amplitude,snr`, waveform the 0-based row index): the local
    /// maxima whose echo adds at least `--peak-snr` × the row's noise σ to the received
    /// waveform (the noise-aware detector, docs/signal.md).
    #[arg(long)]
    pub peaks: Option<PathBuf>,
    /// Least signal-to-noise ratio of an echo `--peaks` keeps, multiples of the row's noise σ
    /// (5: chosen on the tradeoff sweep at 3 % noise, checked at 1.5 and 6 %; docs/accuracy.md).
    #[arg(long, default_value_t = 5.0)]
    pub peak_snr: f32,
    /// Also measure the forest metrics of every row and write them here (CSV, the columns of
    /// the replay's `pulse_metrics.csv`, `docs/forest.md`): `pulse_id` is the 0-based row
    /// index, `gps_time` empty, times in ns from the row's first sample.
    #[arg(long)]
    pub metrics: Option<PathBuf>,
    /// Which waveform `--metrics` measures: `raw` (the input row, smoothed by the σ of the
    /// outgoing pulse from `--kernel`, else of `--response`, else 6.5 ns) or `signal` (the
    /// processed output row, not smoothed again).
    #[arg(long, value_enum, default_value_t = MetricsWaveform::Raw, requires = "metrics")]
    pub metrics_source: MetricsWaveform,
    /// Geometry of every row for `--metrics` (CSV with a header: `x0,y0,z0` the position of
    /// sample 0 in a projected CRS, `dx,dy,dz` the displacement per ns, one row per waveform;
    /// the waveformlidar package's `geo.csv` is read as it is). Without it heights use the
    /// nominal vertical scale, c/2 = 0.1499 m per ns (a nadir beam), and x, y, z are empty.
    #[arg(long, requires = "metrics")]
    pub geometry: Option<PathBuf>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
}

/// The baseline `fwlidar process` removes ahead of the denoise step's own level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BaselineModel {
    /// A straight line through the row's lower samples ([`crate::signal::drift`]).
    Line,
    /// No line: the denoise step's level only.
    Level,
}

/// The waveform `fwlidar process --metrics` measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MetricsWaveform {
    /// The input row as read (as the replay's `source = "raw"`).
    Raw,
    /// The processed output row (denoised, deconvolved; as `source = "signal"`).
    Signal,
}

/// What a run did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ProcessReport {
    /// Waveforms processed.
    pub waveforms: usize,
    /// Samples processed.
    pub samples: usize,
    /// Returns found (with `--returns`).
    pub returns: usize,
    /// Echoes detected (with `--peaks`).
    pub echoes: usize,
    /// Waveforms with forest metrics (status `ok`, with `--metrics`).
    pub metrics_ok: usize,
    /// Time spent measuring the metrics (with `--metrics`), seconds.
    pub metrics_s: f64,
    /// Wall time, seconds.
    pub wall_s: f64,
    /// Iterations derived for the target pulse (`--target-fwhm-ns` without `--iterations`).
    pub target_iterations: Option<u32>,
    /// Rows with samples clipped at their maximum (runs of two or more), which NNLS leaves out
    /// of its fit.
    pub saturated_rows: usize,
    /// Rows whose noise level could not be measured (zero: more than half of their first
    /// differences are equal, as in a flat record or one whose zero padding is processed as
    /// samples), where NNLS's spikes only near echoes (`--support-at-noise`) had no level to
    /// apply and spikes went anywhere; 0 when the option is off or the method is not NNLS.
    pub rows_without_noise_level: usize,
    /// Rows ending in a run of at least [`PADDING_RUN`] zeros processed as samples (without
    /// `--zero-padding`): likely zero padding, which the baseline, the noise level and the
    /// deconvolution then take for data.
    pub padded_rows: usize,
    /// With `--method nnls_or_rl`: over how many rows NNLS ran (RL misfit its echoes) and over
    /// how many its result was kept.
    pub choice: Option<ChoiceCounts>,
    /// With `--learn-kernel`: what was learned.
    pub learning: Option<KernelLearning>,
}

/// Shortest run of zeros at the end of a row that the summary names as likely zero padding
/// (samples; a recorded baseline is rarely exactly 0.0 eight times in a row).
pub const PADDING_RUN: usize = 8;

/// Median of a non-empty slice (sorted copy).
fn median(values: &[f32]) -> f32 {
    let mut s = values.to_vec();
    s.sort_unstable_by(f32::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// Noise level of a segment that was not denoised, signal units: the robust standard deviation
/// of its first differences divided by √2 (1.4826 × MAD / √2); 0 for fewer than 3 samples.
pub fn noise_from_differences(y: &[f32]) -> f32 {
    if y.len() < 3 {
        return 0.0;
    }
    let d: Vec<f32> = y.windows(2).map(|w| w[1] - w[0]).collect();
    let m = median(&d);
    let dev: Vec<f32> = d.iter().map(|v| (v - m).abs()).collect();
    1.4826 * median(&dev) / std::f32::consts::SQRT_2
}

/// Noise mean and σ of a raw row for `--metrics`, from its first [`KERNEL_BASELINE_SAMPLES`]
/// samples (the samples recorded before the first echo, which also give the denoise baseline):
/// their median and their root-mean-square deviation from it. This holds when the echoes fill
/// most of the record (NEON's records are cut around the echoes), where the robust median of
/// the whole record sits on the echo, and it does not depend on the processing options. `None`
/// (the robust estimate of the whole row) when the row is shorter than that or its first
/// samples are all equal.
fn raw_noise(row: &[f32]) -> Option<(f64, f64)> {
    if row.len() < 2 * KERNEL_BASELINE_SAMPLES {
        return None;
    }
    let head = &row[..KERNEL_BASELINE_SAMPLES];
    let level = f64::from(median(head));
    let ms = head
        .iter()
        .map(|&v| (f64::from(v) - level).powi(2))
        .sum::<f64>()
        / head.len() as f64;
    (ms > 0.0).then(|| (level, ms.sqrt()))
}

/// Number of samples of `row` before its trailing zeros.
pub fn unpadded_len(row: &[f32]) -> usize {
    row.iter().rposition(|&v| v != 0.0).map_or(0, |i| i + 1)
}

/// Builds a kernel from one row of the kernel table: the median of its first
/// [`KERNEL_BASELINE_SAMPLES`] samples removed, then [`Kernel::set_from_outgoing`].
pub fn kernel_from_row(row: &[f32], kernel: &mut Kernel) -> Result<(), String> {
    if row.is_empty() {
        return Err("no samples".into());
    }
    if let Some(j) = row.iter().position(|v| !v.is_finite()) {
        return Err(format!("sample {j} is {} (not a finite number)", row[j]));
    }
    let shifted = remove_baseline(row);
    kernel
        .set_from_outgoing(&shifted, row.len())
        .map_err(|e| e.to_string())
}

fn read(path: &Path, what: &str) -> Result<Table, Failure> {
    if !path.exists() {
        return Err(Failure::job(format!(
            "{what} {} does not exist",
            path.display()
        )));
    }
    read_table(path).map_err(Failure::job)
}

/// The kernels to use: one, or one per input row.
fn load_kernels(args: &ProcessArgs, input_rows: usize) -> Result<Vec<Kernel>, Failure> {
    let Some(path) = &args.kernel else {
        return Ok(Vec::new());
    };
    let name = path.display().to_string();
    let table = read(path, "kernel")?;
    if table.rows.is_empty() {
        return Err(Failure::job(format!("kernel {name} holds no values")));
    }
    let rows: Vec<(String, Vec<f32>)> = if args.kernel_per_row {
        if table.rows.len() != input_rows {
            return Err(Failure::job(format!(
                "kernel {name} has {} rows but --kernel-per-row needs one per input row ({input_rows})",
                table.rows.len()
            )));
        }
        (0..table.rows.len())
            .map(|i| (table.row_origin(i), table.rows[i].clone()))
            .collect()
    } else {
        vec![single_row(&table, "kernel", &name)?]
    };
    rows.iter()
        .map(|(origin, row)| {
            let row = if args.zero_padding {
                &row[..unpadded_len(row)]
            } else {
                &row[..]
            };
            let mut k = Kernel::with_capacity(row.len());
            kernel_from_row(row, &mut k)
                .map_err(|e| Failure::job(format!("kernel {name}: {origin}: {e}")))?;
            Ok(k)
        })
        .collect()
}

/// The one row of a table that holds a single pulse: one row, or one column (one value per
/// line, as NEON's `imp.csv`). `what` and `name` name the option and file in errors.
fn single_row(table: &Table, what: &str, name: &str) -> Result<(String, Vec<f32>), Failure> {
    if table.rows.is_empty() {
        return Err(Failure::job(format!("{what} {name} holds no values")));
    }
    if table.rows.len() == 1 {
        Ok((table.row_origin(0), table.rows[0].clone()))
    } else if table.rows.iter().all(|r| r.len() == 1) {
        Ok((
            "its column".to_string(),
            table.rows.iter().map(|r| r[0]).collect(),
        ))
    } else {
        Err(Failure::usage(format!(
            "{what} {name} has {} rows of several values; give one row (or one column) as the \
             system response{}",
            table.rows.len(),
            if what == "kernel" {
                ", or --kernel-per-row for one outgoing pulse per waveform"
            } else {
                ""
            }
        )))
    }
}

/// One pulse read from `path` (one row or column), its zero padding removed with
/// `--zero-padding`.
fn read_single(args: &ProcessArgs, path: &Path, what: &str) -> Result<Vec<f32>, Failure> {
    let name = path.display().to_string();
    let table = read(path, what)?;
    let (origin, row) = single_row(&table, what, &name)?;
    let row = if args.zero_padding {
        row[..unpadded_len(&row)].to_vec()
    } else {
        row
    };
    if let Some(j) = row.iter().position(|v| !v.is_finite()) {
        return Err(Failure::job(format!(
            "{what} {name}: {origin}: sample {j} is {} (not a finite number)",
            row[j]
        )));
    }
    Ok(row)
}

/// The calibrated system response of `--response` (measured from a flat target with
/// `--response-outgoing`), `None` without `--response`.
fn load_response(
    args: &ProcessArgs,
    method: Option<&MethodConfig>,
) -> Result<Option<Kernel>, Failure> {
    let (Some(path), Some(method)) = (&args.response, method) else {
        return Ok(None);
    };
    let name = path.display().to_string();
    let row = read_single(args, path, "response")?;
    let mut k = Kernel::with_capacity(row.len());
    match &args.response_outgoing {
        None => kernel_from_row(&row, &mut k)
            .map_err(|e| Failure::job(format!("response {name}: {e}")))?,
        Some(out_path) => {
            let out = read_single(args, out_path, "response outgoing pulse")?;
            k = response_from_flat_target(&row, &out, method, row.len()).map_err(|e| {
                Failure::job(format!(
                    "response {name} with outgoing pulse {}: {e}",
                    out_path.display()
                ))
            })?;
        }
    }
    tracing::info!(taps = k.len(), center = k.center, "system response");
    Ok(Some(k))
}

/// Default low-pass cut-off of the denoise step, GHz (the seed's, at 1 ns sampling).
const DEFAULT_CUTOFF_GHZ: f64 = 0.2;

/// The denoise step's low-pass cut-off, GHz: `--cutoff-ghz`, else none for NNLS and
/// [`DEFAULT_CUTOFF_GHZ`] for the other methods.
fn low_pass_ghz(args: &ProcessArgs) -> Option<f64> {
    match (args.cutoff_ghz, args.method) {
        (Some(c), _) => Some(c),
        (None, ProcessMethod::Nnls) => None,
        (None, _) => Some(DEFAULT_CUTOFF_GHZ),
    }
}

fn check_args(args: &ProcessArgs) -> Result<(), Failure> {
    TableFormat::from_path(&args.input).map_err(Failure::usage)?;
    TableFormat::from_path(&args.out).map_err(Failure::usage)?;
    if !(args.peak_snr.is_finite() && args.peak_snr >= 0.0) {
        return Err(Failure::usage(format!(
            "--peak-snr must be a non-negative multiple of the noise, got {}",
            args.peak_snr
        )));
    }
    if let Some(m) = &args.metrics
        && m.extension().and_then(|e| e.to_str()) != Some("csv")
    {
        return Err(Failure::usage(format!(
            "--metrics {}: the metrics are written as CSV; give a name ending in .csv",
            m.display()
        )));
    }
    for k in [&args.kernel, &args.response, &args.response_outgoing]
        .into_iter()
        .flatten()
    {
        TableFormat::from_path(k).map_err(Failure::usage)?;
    }
    if !(args.sample_ns.is_finite() && args.sample_ns > 0.0) {
        return Err(Failure::usage(format!(
            "--sample-ns must be a positive number of ns, got {}",
            args.sample_ns
        )));
    }
    if let Some(cutoff) = low_pass_ghz(args).filter(|_| !args.no_denoise) {
        if !(cutoff.is_finite() && cutoff > 0.0) {
            return Err(Failure::usage(format!(
                "--cutoff-ghz must be a positive frequency in GHz, got {cutoff}"
            )));
        }
        if cutoff * args.sample_ns >= 0.5 {
            return Err(Failure::usage(format!(
                "--cutoff-ghz {} is not below the Nyquist frequency {} GHz of --sample-ns {}",
                cutoff,
                0.5 / args.sample_ns,
                args.sample_ns
            )));
        }
    }
    if args.learn_kernel {
        if args.method == ProcessMethod::None {
            return Err(Failure::usage(
                "--learn-kernel needs a deconvolution --method (it learns the kernel to deconvolve by)",
            ));
        }
        if args.kernel_per_row || args.response.is_some() {
            return Err(Failure::usage(
                "--learn-kernel learns one kernel for every row, the whole system response: it \
                 cannot be combined with --kernel-per-row or --response",
            ));
        }
    }
    if args.method != ProcessMethod::None
        && args.kernel.is_none()
        && args.response.is_none()
        && !args.learn_kernel
    {
        return Err(Failure::usage(format!(
            "--method {} needs --kernel (outgoing pulse or system response), --response, both, \
             or --learn-kernel",
            args.method.cli_name()
        )));
    }
    if args.method == ProcessMethod::None && args.response.is_some() {
        return Err(Failure::usage(
            "--response has no meaning with --method none",
        ));
    }
    if args.response_outgoing.is_some() && args.response.is_none() {
        return Err(Failure::usage("--response-outgoing needs --response"));
    }
    if args.method == ProcessMethod::None && args.stop_at_noise.is_some() {
        return Err(Failure::usage(
            "--stop-at-noise has no meaning with --method none",
        ));
    }
    if args.support_at_noise.is_some()
        && !matches!(args.method, ProcessMethod::Nnls | ProcessMethod::NnlsOrRl)
    {
        return Err(Failure::usage(format!(
            "--support-at-noise applies to --method nnls only, not {}",
            args.method.cli_name()
        )));
    }
    if args.method == ProcessMethod::None && args.iterations.is_some() {
        return Err(Failure::usage(
            "--iterations has no meaning with --method none",
        ));
    }
    if let Some(f) = args.target_fwhm_ns {
        if args.method == ProcessMethod::None {
            return Err(Failure::usage(
                "--target-fwhm-ns has no meaning with --method none",
            ));
        }
        crate::signal::deconvolve::target::check_target_fwhm("--target-fwhm-ns", f)
            .map_err(Failure::usage)?;
    }
    if args.kernel_per_row && args.kernel.is_none() {
        return Err(Failure::usage("--kernel-per-row needs --kernel"));
    }
    Ok(())
}

/// Iterations per unit of kernel FWHM / target FWHM when a target pulse is asked for without
/// `--iterations` (RL and Gold): 200 for an 8 ns kernel to 2 ns, where RL-200 resolved 77–80 %
/// of the close pairs of the noise-model benchmark and RL 20 none.
const TARGET_ITERATIONS_PER_RATIO: f64 = 50.0;
/// Bounds of the iterations derived for a target pulse.
const TARGET_ITERATIONS: (u32, u32) = (20, 1000);

/// The iteration budget `process` gives RL and Gold deconvolving to a target pulse when
/// `--iterations` is absent: [`TARGET_ITERATIONS_PER_RATIO`] × the kernels' median FWHM / the
/// target's, within [`TARGET_ITERATIONS`]. `None` when it does not apply (another method, no
/// target, iterations given, no kernel, or a kernel without a width).
fn target_iterations(args: &ProcessArgs, kernels: &[Kernel]) -> Option<u32> {
    let target = args.target_fwhm_ns?;
    if args.iterations.is_some() || !matches!(args.method, ProcessMethod::Rl | ProcessMethod::Gold)
    {
        return None;
    }
    let mut widths: Vec<f64> = kernels.iter().filter_map(Kernel::fwhm_samples).collect();
    if widths.is_empty() || target.is_nan() || target <= 0.0 {
        return None;
    }
    widths.sort_by(f64::total_cmp);
    let fwhm_ns = widths[widths.len() / 2] * args.sample_ns;
    let n = (TARGET_ITERATIONS_PER_RATIO * fwhm_ns / target).round();
    Some(n.clamp(TARGET_ITERATIONS.0 as f64, TARGET_ITERATIONS.1 as f64) as u32)
}

/// NNLS's spikes only near echoes in `process` when `--support-at-noise` is absent (noise
/// levels; [`crate::signal::deconvolve::NnlsConfig::support_at_noise`]).
const PROCESS_SUPPORT_AT_NOISE: f32 = 4.0;

/// True when NNLS puts spikes only near echoes in this run (`--method nnls`, the option not 0).
fn support_applies(args: &ProcessArgs) -> bool {
    args.method == ProcessMethod::Nnls
        && args.support_at_noise.unwrap_or(PROCESS_SUPPORT_AT_NOISE) > 0.0
}

/// Least and largest NNLS spike budget `process` gives when `--iterations` is absent.
const NNLS_BUDGET: (u32, u32) = (50, 256);

/// The NNLS spike budget (`max_iterations`) `process` gives when `--iterations` is absent: one
/// spike per two samples of the longest row, within [`NNLS_BUDGET`]. The Lawson-Hanson run ends
/// by its own optimality test (KKT) long before such a budget on sparse returns; the budget of
/// the stage's default (50) stopped it early and cost 0.02–0.05 of RMSE / raw on every noise
/// model of docs/accuracy.md, while 128 and 256 gave identical results. `None` when it does
/// not apply (another method, or iterations given).
fn nnls_budget(args: &ProcessArgs, max_samples: usize) -> Option<u32> {
    if args.iterations.is_some()
        || !matches!(args.method, ProcessMethod::Nnls | ProcessMethod::NnlsOrRl)
    {
        return None;
    }
    let half = u32::try_from(max_samples / 2).unwrap_or(u32::MAX);
    Some(half.clamp(NNLS_BUDGET.0, NNLS_BUDGET.1))
}

/// The method configuration: built from a serde value so that the methods' own fields and
/// defaults apply; `iterations` is only set when given (or derived: `derived`).
fn method_config(
    args: &ProcessArgs,
    derived: Option<u32>,
) -> Result<Option<MethodConfig>, Failure> {
    let Some(name) = args.method.config_name() else {
        return Ok(None);
    };
    let mut value = serde_json::json!({ "method": name });
    if args.method == ProcessMethod::NnlsOrRl {
        return choice_config(args, derived).map(Some);
    }
    if let Some(n) = args.iterations.or(derived) {
        // NNLS's budget is its Lawson-Hanson outer iterations (at most one non-zero sample
        // each).
        let key = match args.method {
            ProcessMethod::Nnls => "max_iterations",
            _ => "iterations",
        };
        value[key] = serde_json::json!(n);
    }
    if args.method == ProcessMethod::Nnls {
        // The fit weighted by a noise variance estimated from the row when it follows the
        // signal (docs/accuracy.md, "Deconvolution over noise models", third step).
        value["noise_weights"] = serde_json::json!(true);
        // Spikes only near echoes (docs/accuracy.md, "NNLS: spikes only near echoes").
        let tau = args.support_at_noise.unwrap_or(PROCESS_SUPPORT_AT_NOISE);
        if tau.is_finite() && tau > 0.0 {
            value["support_at_noise"] = serde_json::json!(tau);
        } else if tau != 0.0 {
            return Err(Failure::usage(format!(
                "--support-at-noise must be 0 (off) or a positive number of noise levels, got \
                 {tau}"
            )));
        }
    }
    if let Some(tau) = args.stop_at_noise {
        if !(tau.is_finite() && tau > 0.0) {
            return Err(Failure::usage(format!(
                "--stop-at-noise must be a positive number of noise levels, got {tau}"
            )));
        }
        value["stop_at_noise"] = serde_json::json!(tau);
    }
    serde_json::from_value::<MethodConfig>(value)
        .map(Some)
        .map_err(|e| {
            if args.iterations.is_some() || args.stop_at_noise.is_some() {
                Failure::usage(format!(
                    "--iterations or --stop-at-noise is not accepted by method {name}: {e}"
                ))
            } else {
                Failure::usage(format!("method {name}: {e}"))
            }
        })
}

/// The per-pulse choice between NNLS and RL as `process` runs it: its defaults, NNLS with
/// `process`'s spike budget (`derived`) and noise-weighted refit as for `--method nnls`; the
/// options that set one method's budget or stop (`--iterations`, `--stop-at-noise`,
/// `--support-at-noise`) are refused (each method keeps its own).
fn choice_config(args: &ProcessArgs, derived: Option<u32>) -> Result<MethodConfig, Failure> {
    for (given, option) in [
        (args.iterations.is_some(), "--iterations"),
        (args.stop_at_noise.is_some(), "--stop-at-noise"),
        (args.support_at_noise.is_some(), "--support-at-noise"),
    ] {
        if given {
            return Err(Failure::usage(format!(
                "{option} is not accepted by --method nnls_or_rl: NNLS and RL keep their own \
                 settings (a deconvolve stage's configuration sets them)"
            )));
        }
    }
    let mut config = NnlsOrRlConfig::default();
    config.nnls.noise_weights = true;
    if let Some(n) = derived {
        config.nnls.max_iterations = n;
    }
    Ok(MethodConfig::NnlsOrRl(config))
}

/// Runs `fwlidar process`.
pub fn run(args: ProcessArgs) -> Result<(), Failure> {
    let report = process(&args)?;
    if report.rows_without_noise_level > 0 {
        tracing::warn!(
            rows = report.rows_without_noise_level,
            "no noise level measured in these rows (more than half of their first differences \
             are equal: a flat record, or zero padding processed as samples): NNLS put spikes \
             anywhere in them, --support-at-noise had nothing to apply"
        );
    }
    if report.padded_rows > 0 {
        tracing::warn!(
            rows = report.padded_rows,
            "these rows end in {PADDING_RUN} or more zeros, processed as samples: if that is \
             zero padding, --zero-padding processes only the recorded samples (the baseline, \
             the noise level and the deconvolution otherwise see a step down to 0)"
        );
    }
    let per = if report.waveforms > 0 {
        report.wall_s * 1e6 / report.waveforms as f64
    } else {
        0.0
    };
    println!(
        "fwlidar process  {}  ->  {}: {} waveforms, {} samples, method {}{}{}{}{}{}{}{}{}{}{}; {:.3} s, {:.1} µs per waveform",
        args.input.display(),
        args.out.display(),
        report.waveforms,
        report.samples,
        args.method.cli_name(),
        report
            .learning
            .as_ref()
            .map_or_else(String::new, KernelLearning::words),
        match report.target_iterations {
            Some(n) => format!(" ({n} iterations for the target pulse)"),
            None => String::new(),
        },
        report
            .choice
            .map_or_else(String::new, |c| choice_words(c, report.waveforms)),
        match (args.no_denoise, low_pass_ghz(&args)) {
            (true, _) => "",
            (false, Some(_)) => ", denoised",
            (false, None) => ", baseline removed (no low-pass)",
        },
        match report.saturated_rows {
            0 => String::new(),
            r if matches!(args.method, ProcessMethod::Nnls | ProcessMethod::NnlsOrRl) => {
                format!(", {r} rows with clipped samples (left out of the fit)")
            }
            r => format!(
                ", {r} rows with clipped samples (only --method nnls and nnls_or_rl leave them \
                 out)"
            ),
        },
        match report.rows_without_noise_level {
            0 => String::new(),
            r => format!(
                ", spikes anywhere in {r} rows (no noise level measured, so \
                 --support-at-noise had nothing to apply)"
            ),
        },
        match report.padded_rows {
            0 => String::new(),
            r => format!(
                ", {r} rows end in {PADDING_RUN} or more zeros (if that is zero padding, \
                 pass --zero-padding)"
            ),
        },
        match &args.returns {
            Some(p) => format!(", {} returns in {}", report.returns, p.display()),
            None => String::new(),
        },
        match &args.peaks {
            Some(p) => format!(
                ", {} echoes at >= {} sigma in {}",
                report.echoes,
                args.peak_snr,
                p.display()
            ),
            None => String::new(),
        },
        match &args.metrics {
            Some(p) => format!(
                ", metrics of {} waveforms ({} {}, {:.1} µs per waveform) in {}",
                report.metrics_ok,
                match args.metrics_source {
                    MetricsWaveform::Raw => "raw",
                    MetricsWaveform::Signal => "processed",
                },
                if args.geometry.is_some() {
                    "with geometry"
                } else {
                    "at c/2 per ns"
                },
                if report.waveforms > 0 {
                    report.metrics_s * 1e6 / report.waveforms as f64
                } else {
                    0.0
                },
                p.display()
            ),
            None => String::new(),
        },
        report.wall_s,
        per
    );
    Ok(())
}

/// How the per-row choice of `--method nnls_or_rl` went over `rows` rows, for the summary
/// line (with `--response` and a kernel a row is deconvolved twice, each counted).
fn choice_words(c: ChoiceCounts, rows: usize) -> String {
    let unit = if c.segments == rows as u64 {
        "rows"
    } else {
        "deconvolutions (by the response, then by the kernel)"
    };
    format!(
        " (NNLS ran on {} of {} {unit}, where RL misfit its echoes, and was kept on {})",
        c.second_runs, c.segments, c.second_kept
    )
}

/// Does the work of `fwlidar process` and returns what it did (no summary line).
pub fn process(args: &ProcessArgs) -> Result<ProcessReport, Failure> {
    let started = Instant::now();
    check_args(args)?;
    let mut method = method_config(args, None)?;
    let input_name = args.input.display().to_string();
    let table = read_input(args, &input_name)?;
    let mut kernels = load_kernels(args, table.rows.len())?;
    let mut learning = None;
    if args.learn_kernel {
        let (k, how) = learn_kernel(args, &table, kernels.first(), &input_name)?;
        kernels = vec![k];
        learning = Some(how);
    }
    let derived = target_iterations(args, &kernels);
    if let Some(n) = derived {
        tracing::info!(
            iterations = n,
            "iterations for the target pulse: 50 x kernel FWHM / target FWHM (--iterations sets them)"
        );
        method = method_config(args, Some(n))?;
    }
    let longest = table.rows.iter().map(Vec::len).max().unwrap_or(0);
    if let Some(n) = nnls_budget(args, longest) {
        tracing::info!(
            spikes = n,
            "NNLS spike budget: half the longest row's samples (--iterations sets it)"
        );
        method = method_config(args, Some(n))?;
    }
    let response = load_response(args, method.as_ref())?;
    let mut steps = RowSteps::new(args, method, kernels, response, &table, &input_name)?;
    let max_samples = steps.max_samples;
    tracing::info!(
        input = %input_name,
        rows = table.rows.len(),
        max_samples,
        method = args.method.cli_name(),
        "process started"
    );

    let n = table.rows.len();
    let bar = progress_bar(args, n);
    let mut outputs: Vec<Vec<f32>> = Vec::with_capacity(n);
    for (i, row) in table.rows.iter().enumerate() {
        let at = || format!("{input_name}: {}", table.row_origin(i));
        outputs.push(steps.row(i, row, &at)?);
        bar.inc(1);
    }
    bar.finish_and_clear();

    // Every row succeeded: now write, each file complete or not at all.
    if let Some(path) = &args.returns {
        write_returns(path, &steps.returns)?;
    }
    if let Some(path) = &args.peaks {
        write_echoes(path, &steps.echoes)?;
    }
    if let (Some(path), Some(tm)) = (&args.metrics, &steps.metrics) {
        write_atomic(path, tm.csv().as_bytes())
            .map_err(|e| Failure::job(format!("{}: {e}", path.display())))?;
    }
    write_table(&args.out, &outputs).map_err(Failure::job)?;
    Ok(ProcessReport {
        waveforms: n,
        samples: steps.samples,
        returns: steps.returns.len(),
        echoes: steps.echoes.len(),
        metrics_ok: steps.metrics.as_ref().map_or(0, TableMetrics::ok),
        metrics_s: steps.metrics_s,
        wall_s: started.elapsed().as_secs_f64(),
        target_iterations: derived,
        saturated_rows: steps.saturated_rows,
        rows_without_noise_level: steps.rows_without_noise_level,
        padded_rows: steps.padded_rows,
        choice: steps
            .deconvolver
            .as_ref()
            .and_then(Deconvolver::choice_counts),
        learning,
    })
}

/// The input table (`input_name` names it in errors), its `--skip-columns` removed; an error
/// when it holds no rows.
fn read_input(args: &ProcessArgs, input_name: &str) -> Result<Table, Failure> {
    let mut table = read(&args.input, "input")?;
    table
        .skip_columns(args.skip_columns, input_name)
        .map_err(Failure::job)?;
    if table.rows.is_empty() {
        return Err(Failure::job(format!(
            "input {input_name} holds no waveforms"
        )));
    }
    Ok(table)
}

/// The `--geometry` table, one row per waveform of the input (`rows` of them, the input named
/// `input_name`); empty without `--geometry`.
fn read_row_geometry(
    args: &ProcessArgs,
    rows: usize,
    input_name: &str,
) -> Result<Vec<PulseGeometry>, Failure> {
    let Some(path) = &args.geometry else {
        return Ok(Vec::new());
    };
    let g = read_geometry(path).map_err(Failure::job)?;
    if g.len() != rows {
        return Err(Failure::job(format!(
            "geometry {} has {} rows but the input {input_name} has {} waveforms; give one \
             geometry row per waveform, in the same order",
            path.display(),
            g.len(),
            rows
        )));
    }
    Ok(g)
}

/// A progress bar over `n` rows on a terminal (hidden with `--no-progress`, under
/// [`PROGRESS_MIN_ROWS`] rows, or when stderr is no terminal).
fn progress_bar(args: &ProcessArgs, n: usize) -> ProgressBar {
    if !args.no_progress && n >= PROGRESS_MIN_ROWS && std::io::stderr().is_terminal() {
        let bar = ProgressBar::new(n as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} waveforms",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    } else {
        ProgressBar::hidden()
    }
}

/// Smoothing σ of row `i`'s raw waveform for `--metrics`, ns: the σ of its outgoing pulse (as
/// the replay's metrics stage), from the kernel rows, else the system response, else GEDI's
/// 6.5 ns; 0 (none) when the metrics measure the processed row.
fn metrics_smoothing_ns(
    args: &ProcessArgs,
    kernels: &[Kernel],
    response: Option<&Kernel>,
    i: usize,
) -> f64 {
    if args.metrics_source == MetricsWaveform::Signal {
        return 0.0;
    }
    let pulse = match kernels.len() {
        0 => response,
        1 => kernels.first(),
        _ => kernels.get(i),
    };
    pulse
        .and_then(|k| pulse_sigma_ns(&k.taps, args.sample_ns))
        .unwrap_or(MetricsConfig::FALLBACK_SMOOTHING_NS)
}

/// The steps every row goes through (denoise, deconvolution, metrics, decomposition, each
/// where asked for), their buffers, and what they produced so far.
struct RowSteps<'a> {
    args: &'a ProcessArgs,
    /// Longest input row, samples.
    max_samples: usize,
    /// The outgoing pulses of `--kernel`: none, one for every row, or one per row.
    kernels: Vec<Kernel>,
    /// The system response of `--response`.
    response: Option<Kernel>,
    denoise: Option<Denoise>,
    deconvolver: Option<Targeted>,
    /// The `--geometry` of every row; empty without.
    geometry: Vec<PulseGeometry>,
    metrics: Option<TableMetrics>,
    /// Time spent measuring the metrics, seconds.
    metrics_s: f64,
    decomposer: Option<Decomposer>,
    /// The returns of every row so far, with the row's index.
    returns: Vec<(usize, FittedReturn)>,
    /// The returns of the current row.
    fits: Vec<FittedReturn>,
    /// The noise-aware detector of `--peaks`, the echoes of every row so far with the row's
    /// index, and those of the current row.
    detector: Option<EchoDetector>,
    echoes: Vec<(usize, DetectedEcho)>,
    row_echoes: Vec<DetectedEcho>,
    /// The system pulse the current row was deconvolved by (the detector's), taps.
    pulse: Vec<f32>,
    /// The current row denoised (or copied), `max_samples` values.
    work: Vec<f32>,
    /// The baseline line fit and the current row with the line removed.
    drift: DriftBaseline,
    detrended: Vec<f32>,
    /// The current row's samples clipped at its maximum.
    excluded: Vec<bool>,
    /// Rows with clipped samples so far.
    saturated_rows: usize,
    /// Rows so far where spikes only near echoes had no noise level to apply.
    rows_without_noise_level: usize,
    /// Rows so far ending in [`PADDING_RUN`] or more zeros, processed as samples.
    padded_rows: usize,
    /// The current row deconvolved by the response, before the kernel, `max_samples` values.
    first: Vec<f32>,
    /// Samples processed (padding excluded).
    samples: usize,
}

impl<'a> RowSteps<'a> {
    /// The steps for the rows of `table` (named `input_name` in errors), with the
    /// deconvolution `method`, the `kernels` and the `response` where given; an error when the
    /// `--geometry` table does not match the input.
    fn new(
        args: &'a ProcessArgs,
        method: Option<MethodConfig>,
        kernels: Vec<Kernel>,
        response: Option<Kernel>,
        table: &Table,
        input_name: &str,
    ) -> Result<Self, Failure> {
        let max_samples = table.rows.iter().map(Vec::len).max().unwrap_or(0);
        let max_taps = kernels
            .iter()
            .chain(response.iter())
            .map(Kernel::len)
            .max()
            .unwrap_or(0);
        let cutoff = low_pass_ghz(args).filter(|_| !args.no_denoise);
        let denoise = cutoff.map(|cutoff_ghz| {
            Denoise::new(DenoiseConfig {
                cutoff_ghz,
                max_samples,
                ..Default::default()
            })
        });
        let deconvolver = method.map(|m| {
            Targeted::new(
                m.build(max_samples, max_taps),
                args.target_fwhm_ns,
                max_samples,
                max_taps,
            )
        });
        let geometry = read_row_geometry(args, table.rows.len(), input_name)?;
        let metrics = args
            .metrics
            .as_ref()
            .map(|_| TableMetrics::new(MetricsConfig::default(), max_samples));
        let decomposer = args
            .returns
            .as_ref()
            .map(|_| Decomposer::new(DecomposeConfig::default(), max_samples));
        Ok(RowSteps {
            args,
            max_samples,
            kernels,
            response,
            denoise,
            deconvolver,
            geometry,
            metrics,
            metrics_s: 0.0,
            decomposer,
            returns: Vec::new(),
            fits: Vec::new(),
            detector: args
                .peaks
                .as_ref()
                .map(|_| EchoDetector::new(max_samples, 2 * max_taps)),
            echoes: Vec::new(),
            row_echoes: Vec::new(),
            pulse: Vec::with_capacity(2 * max_taps),
            work: vec![0.0f32; max_samples],
            drift: DriftBaseline::with_capacity(max_samples),
            detrended: vec![0.0f32; max_samples],
            excluded: Vec::with_capacity(max_samples),
            saturated_rows: 0,
            rows_without_noise_level: 0,
            padded_rows: 0,
            first: vec![0.0f32; max_samples],
            samples: 0,
        })
    }

    /// Row `i` of the input (`at` names it in errors) through every step: checked, denoised,
    /// deconvolved, measured and decomposed. Returns the processed row, as long as the input
    /// row (its zero padding, with `--zero-padding`, kept as zeros).
    fn row(&mut self, i: usize, row: &[f32], at: &dyn Fn() -> String) -> Result<Vec<f32>, Failure> {
        if let Some(j) = row.iter().position(|v| !v.is_finite()) {
            return Err(Failure::job(format!(
                "{}: sample {} is {} (not a finite number); nothing written",
                at(),
                j + 1,
                row[j]
            )));
        }
        let full = row.len();
        let recorded = unpadded_len(row);
        let len = if self.args.zero_padding {
            recorded
        } else {
            self.padded_rows += usize::from(recorded > 0 && full - recorded >= PADDING_RUN);
            full
        };
        if len == 0 {
            return Err(Failure::job(format!(
                "{}: the row holds only zero padding; nothing written",
                at()
            )));
        }
        let row = &row[..len];
        self.samples += len;
        let clipped = flag_saturated(row, &mut self.excluded);
        self.saturated_rows += usize::from(clipped > 0);
        let noise_v = self.denoise_row(row, clipped > 0, at)?;
        if support_applies(self.args) && !(noise_v.is_finite() && noise_v > 0.0) {
            self.rows_without_noise_level += 1;
        }
        let mut out = vec![0.0f32; full];
        self.deconvolve_row(i, &mut out[..len], noise_v, at)?;
        if let Some(j) = out.iter().position(|v| !v.is_finite()) {
            return Err(Failure::job(format!(
                "{}: processing produced a non-finite value at sample {}; nothing written",
                at(),
                j + 1
            )));
        }
        self.measure_row(i, row, &out[..len], noise_v);
        self.decompose_row(i, &out[..len], noise_v, at)?;
        self.detect_row(i, row, &out[..len]);
        Ok(out)
    }

    /// Denoises `row` into `work` (a copy with `--no-denoise`); returns its noise level in the
    /// table's unit (the denoise step's, else from the sample differences).
    /// With `--baseline line`, the row's baseline line is removed first (the samples in
    /// `excluded` take no part in its fit when `clipped`).
    fn denoise_row(
        &mut self,
        row: &[f32],
        clipped: bool,
        at: &dyn Fn() -> String,
    ) -> Result<f32, Failure> {
        let n = row.len();
        if self.args.no_denoise {
            self.work[..n].copy_from_slice(row);
            return Ok(noise_from_differences(row));
        }
        let flat = &mut self.detrended[..n];
        if self.args.baseline == BaselineModel::Line {
            let line = self.drift.fit(row, clipped.then_some(&self.excluded[..]));
            for (i, (f, &v)) in flat.iter_mut().zip(row).enumerate() {
                *f = (v as f64 - line.at(i)) as f32;
            }
        } else {
            flat.copy_from_slice(row);
        }
        let w = &mut self.work[..n];
        Ok(match self.denoise.as_mut() {
            Some(d) => {
                d.denoise_segment(&self.detrended[..n], self.args.sample_ns, w)
                    .map_err(|e| Failure::job(format!("{}: {e}", at())))?
                    .noise_v
            }
            None => {
                // No low-pass (NNLS): the baseline removed, the noise level as the denoise
                // step states it (a mean absolute deviation, σ √(2/π)).
                let level = if self.args.baseline == BaselineModel::Level {
                    median(&row[..n.min(KERNEL_BASELINE_SAMPLES)])
                } else {
                    0.0
                };
                for (o, &v) in w.iter_mut().zip(&self.detrended[..n]) {
                    *o = v - level;
                }
                noise_from_differences(row) * std::f32::consts::FRAC_2_PI.sqrt()
            }
        })
    }

    /// Deconvolves the denoised row `i` (in `work`, noise level `noise_v`) into `out`: by the
    /// system response, then by the row's outgoing pulse (or kernel), each where given; a copy
    /// without a method.
    fn deconvolve_row(
        &mut self,
        i: usize,
        out: &mut [f32],
        noise_v: f32,
        at: &dyn Fn() -> String,
    ) -> Result<(), Failure> {
        let len = out.len();
        let w = &self.work[..len];
        let sample_ns = self.args.sample_ns;
        let Some(dec) = self.deconvolver.as_mut() else {
            out.copy_from_slice(w);
            return Ok(());
        };
        let fail = |e| Failure::job(format!("{}: deconvolution failed: {e}", at()));
        // Stage 1: the system response; stage 2: the outgoing pulse (or kernel).
        let input: &[f32] = match &self.response {
            Some(h) if self.kernels.is_empty() => {
                dec.run(w, h, noise_v, sample_ns, out).map_err(fail)?;
                &[]
            }
            Some(h) => {
                let f = &mut self.first[..len];
                dec.plain().run(w, h, noise_v, sample_ns, f).map_err(fail)?;
                f
            }
            None => w,
        };
        if !self.kernels.is_empty() {
            let k = if self.kernels.len() == 1 {
                &self.kernels[0]
            } else {
                &self.kernels[i]
            };
            if self.excluded[..len].iter().any(|&e| e) {
                let ex = &self.excluded[..len];
                dec.run_excluding(input, k, noise_v, sample_ns, ex, out)
                    .map_err(fail)?;
            } else {
                dec.run(input, k, noise_v, sample_ns, out).map_err(fail)?;
            }
        }
        Ok(())
    }

    /// With `--metrics`, measures row `i`: the input `row` (the raw waveform) or the processed
    /// `out` (noise level `noise_v`), as `--metrics-source` says; adds the time taken to
    /// `metrics_s`.
    fn measure_row(&mut self, i: usize, row: &[f32], out: &[f32], noise_v: f32) {
        let args = self.args;
        let Some(tm) = self.metrics.as_mut() else {
            return;
        };
        let t0 = Instant::now();
        let (samples, noise) = match args.metrics_source {
            MetricsWaveform::Raw => (row, raw_noise(row)),
            // After denoise the baseline is 0 and the noise level a mean absolute
            // deviation (σ √(2/π)), as the replay's metrics stage reads it.
            MetricsWaveform::Signal => (
                out,
                (!args.no_denoise && noise_v > 0.0)
                    .then(|| (0.0, f64::from(noise_v) * std::f64::consts::FRAC_PI_2.sqrt())),
            ),
        };
        tm.measure(&TableWaveform {
            row: i,
            samples,
            sample_ns: args.sample_ns,
            noise,
            smoothing_ns: metrics_smoothing_ns(args, &self.kernels, self.response.as_ref(), i),
            geometry: self.geometry.get(i).copied(),
        });
        self.metrics_s += t0.elapsed().as_secs_f64();
    }

    /// With `--returns`, decomposes the processed row `i` (`out`, noise level `noise_v`) and
    /// keeps its returns.
    fn decompose_row(
        &mut self,
        i: usize,
        out: &[f32],
        noise_v: f32,
        at: &dyn Fn() -> String,
    ) -> Result<(), Failure> {
        if let Some(dec) = self.decomposer.as_mut() {
            self.fits.clear();
            dec.fit(out, noise_v, &mut self.fits)
                .map_err(|e| Failure::job(format!("{}: decomposition failed: {e}", at())))?;
            self.returns.extend(self.fits.iter().map(|f| (i, *f)));
        }
        Ok(())
    }
}

impl RowSteps<'_> {
    /// With `--peaks`, detects the echoes of the processed row `i` (`out`) that the received
    /// `row` shows at `--peak-snr` × its noise σ or more, through the pulse the row was
    /// deconvolved by: the kernel, the response, or both convolved; a delta without
    /// deconvolution. σ: the received row's, from its first differences
    /// ([`DriftBaseline::difference_sigma`]: blind to a pedestal or a drift, and to echoes
    /// wider than a few samples even when they fill the record), the estimate the tradeoff
    /// sweep chose the default ratio with.
    fn detect_row(&mut self, i: usize, row: &[f32], out: &[f32]) {
        let Some(det) = self.detector.as_mut() else {
            return;
        };
        let sigma = self.drift.difference_sigma(row) as f32;
        self.pulse.clear();
        let kernel = match self.kernels.len() {
            0 => None,
            1 => Some(&self.kernels[0]),
            _ => Some(&self.kernels[i]),
        };
        match (self.deconvolver.is_some(), kernel, &self.response) {
            (false, _, _) | (true, None, None) => self.pulse.push(1.0),
            (true, Some(k), None) => self.pulse.extend_from_slice(&k.taps),
            (true, None, Some(h)) => self.pulse.extend_from_slice(&h.taps),
            (true, Some(k), Some(h)) => {
                self.pulse.resize(k.taps.len() + h.taps.len() - 1, 0.0);
                for (a, &ka) in k.taps.iter().enumerate() {
                    for (b, &hb) in h.taps.iter().enumerate() {
                        self.pulse[a + b] += ka * hb;
                    }
                }
            }
        }
        det.set_pulse(&self.pulse);
        det.detect(out, sigma, self.args.peak_snr, &mut self.row_echoes);
        self.echoes.extend(self.row_echoes.iter().map(|e| (i, *e)));
    }
}

/// Writes the echoes CSV of `--peaks` atomically.
fn write_echoes(path: &Path, echoes: &[(usize, DetectedEcho)]) -> Result<(), Failure> {
    write_rows_csv(
        path,
        "waveform,position_bins,amplitude,snr",
        echoes,
        |w, (i, e)| {
            let p = &e.peak;
            writeln!(w, "{i},{},{},{:.2}", p.position_bins, p.amplitude, e.snr)
        },
    )
}

/// Writes the returns CSV atomically.
fn write_returns(path: &Path, returns: &[(usize, FittedReturn)]) -> Result<(), Failure> {
    write_rows_csv(
        path,
        "waveform,position_bins,amplitude,sigma_bins",
        returns,
        |w, (i, r)| {
            writeln!(
                w,
                "{i},{},{},{}",
                r.position_bins, r.amplitude, r.sigma_bins
            )
        },
    )
}

/// Writes `header` and a line per item (`line` writes it) to `path` atomically: complete or
/// not at all; an error names the file.
fn write_rows_csv<T>(
    path: &Path,
    header: &str,
    items: &[T],
    line: impl Fn(&mut dyn Write, &T) -> std::io::Result<()>,
) -> Result<(), Failure> {
    let fail = |e: &dyn std::fmt::Display| Failure::job(format!("{}: {e}", path.display()));
    let mut file = AtomicFile::create(path).map_err(|e| fail(&e))?;
    let w = file.writer().map_err(|e| fail(&e))?;
    let mut body = || -> std::io::Result<()> {
        writeln!(w, "{header}")?;
        for item in items {
            line(w, item)?;
        }
        Ok(())
    };
    body().map_err(|e| fail(&e))?;
    file.commit().map_err(|e| fail(&e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_from_differences_of_a_ramp_is_zero_and_of_steps_positive() {
        let ramp: Vec<f32> = (0..50).map(|i| i as f32).collect();
        assert_eq!(noise_from_differences(&ramp), 0.0);
        // Uniform noise of standard deviation 5/sqrt(3) = 2.9 on a ramp.
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let noisy: Vec<f32> = (0..2000)
            .map(|i| i as f32 + rng.random_range(-5.0f32..=5.0))
            .collect();
        let n = noise_from_differences(&noisy);
        assert!(n > 2.0 && n < 4.0, "{n}");
        assert_eq!(noise_from_differences(&[1.0, 2.0]), 0.0);
    }

    #[test]
    fn unpadded_len_stops_at_trailing_zeros_only() {
        assert_eq!(unpadded_len(&[1.0, 0.0, 2.0, 0.0, 0.0]), 3);
        assert_eq!(unpadded_len(&[0.0, 0.0]), 0);
        assert_eq!(unpadded_len(&[]), 0);
        assert_eq!(unpadded_len(&[-0.0, 5.0]), 2);
    }

    #[test]
    fn kernel_from_row_removes_the_baseline_and_centres_on_the_peak() {
        let mut row = vec![200.0f32; 12];
        row.extend([300.0, 600.0, 300.0, 200.0, 200.0]);
        let mut k = Kernel::default();
        kernel_from_row(&row, &mut k).unwrap();
        assert_eq!(k.center, 13);
        assert!((k.taps.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert_eq!(k.taps[0], 0.0);
        assert!(kernel_from_row(&[1.0, f32::NAN], &mut k).is_err());
        assert!(kernel_from_row(&[5.0; 10], &mut k).is_err());
    }

    /// `process --method rl` on a.csv with a kernel, every other option at its default.
    fn base_args() -> ProcessArgs {
        ProcessArgs {
            input: "a.csv".into(),
            kernel: Some("k.csv".into()),
            response: None,
            response_outgoing: None,
            method: ProcessMethod::Rl,
            iterations: None,
            stop_at_noise: None,
            support_at_noise: None,
            sample_ns: 1.0,
            target_fwhm_ns: None,
            cutoff_ghz: None,
            kernel_per_row: false,
            learn_kernel: false,
            no_denoise: false,
            baseline: BaselineModel::Line,
            zero_padding: false,
            skip_columns: 0,
            out: "o.csv".into(),
            returns: None,
            peaks: None,
            peak_snr: 5.0,
            metrics: None,
            metrics_source: MetricsWaveform::Raw,
            geometry: None,
            no_progress: true,
        }
    }

    #[test]
    fn a_target_pulse_without_iterations_takes_them_from_the_kernel_width() {
        let mut k8 = Kernel::with_capacity(128);
        k8.set_gaussian(8.0, 1.0).unwrap();
        let target = |t: f64| ProcessArgs {
            target_fwhm_ns: Some(t),
            ..base_args()
        };
        // 50 × 8 ns / 2 ns; a wider target, fewer; bounded both ways.
        assert_eq!(target_iterations(&target(2.0), &[k8.clone()]), Some(200));
        assert_eq!(target_iterations(&target(4.0), &[k8.clone()]), Some(100));
        assert_eq!(target_iterations(&target(40.0), &[k8.clone()]), Some(20));
        assert_eq!(target_iterations(&target(0.1), &[k8.clone()]), Some(1000));
        // The kernel's width in ns follows the sample interval.
        let half_ns = ProcessArgs {
            sample_ns: 0.5,
            ..target(2.0)
        };
        assert_eq!(target_iterations(&half_ns, &[k8.clone()]), Some(100));
        let gold = ProcessArgs {
            method: ProcessMethod::Gold,
            ..target(2.0)
        };
        assert_eq!(target_iterations(&gold, &[k8.clone()]), Some(200));
        // Not without a target, with iterations given, for the other methods or no kernel.
        assert_eq!(target_iterations(&base_args(), &[k8.clone()]), None);
        let given = ProcessArgs {
            iterations: Some(30),
            ..target(2.0)
        };
        assert_eq!(target_iterations(&given, &[k8.clone()]), None);
        let nnls = ProcessArgs {
            method: ProcessMethod::Nnls,
            ..target(2.0)
        };
        assert_eq!(target_iterations(&nnls, &[k8.clone()]), None);
        assert_eq!(target_iterations(&target(2.0), &[]), None);
        // And the method configuration takes them; NNLS's budget is `max_iterations`.
        let c = method_config(&target(2.0), Some(200)).unwrap().unwrap();
        assert!(format!("{c:?}").contains("iterations: 200"), "{c:?}");
        let nnls100 = ProcessArgs {
            iterations: Some(100),
            ..nnls
        };
        let c = method_config(&nnls100, None).unwrap().unwrap();
        assert!(format!("{c:?}").contains("max_iterations: 100"), "{c:?}");
    }

    #[test]
    fn method_config_from_names() {
        let base = base_args();
        for m in [
            ProcessMethod::Rl,
            ProcessMethod::Wiener,
            ProcessMethod::Nnls,
            ProcessMethod::Gold,
            ProcessMethod::NnlsOrRl,
        ] {
            let args = ProcessArgs {
                method: m,
                ..base_clone(&base)
            };
            assert!(method_config(&args, None).unwrap().is_some(), "{m:?}");
        }
        let none = ProcessArgs {
            method: ProcessMethod::None,
            ..base_clone(&base)
        };
        assert!(method_config(&none, None).unwrap().is_none());
        assert!(
            check_args(&ProcessArgs {
                cutoff_ghz: Some(0.6),
                ..base_clone(&base)
            })
            .is_err()
        );
        assert!(
            check_args(&ProcessArgs {
                kernel: None,
                ..base_clone(&base)
            })
            .is_err()
        );
        assert!(check_args(&base).is_ok());
    }

    fn base_clone(a: &ProcessArgs) -> ProcessArgs {
        ProcessArgs {
            input: a.input.clone(),
            kernel: a.kernel.clone(),
            response: a.response.clone(),
            response_outgoing: a.response_outgoing.clone(),
            method: a.method,
            iterations: a.iterations,
            stop_at_noise: a.stop_at_noise,
            support_at_noise: a.support_at_noise,
            sample_ns: a.sample_ns,
            target_fwhm_ns: a.target_fwhm_ns,
            cutoff_ghz: a.cutoff_ghz,
            kernel_per_row: a.kernel_per_row,
            learn_kernel: false,
            no_denoise: a.no_denoise,
            baseline: a.baseline,
            zero_padding: a.zero_padding,
            skip_columns: a.skip_columns,
            out: a.out.clone(),
            returns: a.returns.clone(),
            peaks: a.peaks.clone(),
            peak_snr: a.peak_snr,
            metrics: a.metrics.clone(),
            metrics_source: a.metrics_source,
            geometry: a.geometry.clone(),
            no_progress: a.no_progress,
        }
    }
}
