//! The written results of `fwlidar tradeoff`: one CSV row per (setting, pulse width, family)
//! case, one CSV row per setting pooled over the cases (`tradeoff_summary.csv`), and a markdown
//! report (setup, a summary per setting with the pulse rates it sustains, what each `--chain`
//! ran, and per-case tables).

use std::fmt::Write as _;

use crate::eval::tradeoff::{CaseResult, Processing, Setting, SettingSummary, SweepConfig};

/// Pulse rates the report checks every setting against, pulses per second.
pub const RATES_HZ: [f64; 4] = [100e3, 500e3, 1e6, 2e6];

/// Columns of the CSV, in order.
pub const CSV_COLUMNS: [&str; 17] = [
    "method",
    "parameter",
    "family",
    "width_ns",
    "pulses",
    "rmse",
    "rmse_2ns",
    "true_detections",
    "false_detections",
    "truth_peaks",
    "detection_rate",
    "false_per_pulse",
    "sam_deg",
    "time_mean_us",
    "time_median_us",
    "time_p99_us",
    "max_rate_hz",
];

/// Columns of the summary CSV (`tradeoff_summary.csv`), in order.
pub const SUMMARY_COLUMNS: [&str; 17] = [
    "method",
    "parameter",
    "pulses",
    "rmse",
    "rmse_2ns",
    "true_detections",
    "truth_peaks",
    "detection_rate",
    "false_detections",
    "false_per_pulse",
    "sam_deg",
    "time_mean_us",
    "time_median_us",
    "slowest_case_median_us",
    "max_rate_hz",
    "dropped",
    "pareto",
];

/// The summary CSV: a header of [`SUMMARY_COLUMNS`], then one row per setting pooled over
/// every (pulse width, family) case, each pulse weighing the same ([`SettingSummary`]): RMSE
/// over every bin of every pulse, detection rate = true detections / truth peaks, false peaks
/// per pulse = false detections / pulses, times in µs (mean and median over every pulse), the
/// rate `workers` threads sustain at the slowest case's median, pulses/s.
pub fn summary_csv(settings: &[Setting], summary: &[SettingSummary], workers: usize) -> String {
    let mut s = SUMMARY_COLUMNS.join(",");
    s.push('\n');
    for sm in summary {
        let set = &settings[sm.setting];
        let _ = writeln!(
            s,
            "{},{},{},{:.6},{:.6},{},{},{:.4},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.0},{},{}",
            set.method,
            set.parameter,
            sm.pulses,
            sm.rmse,
            sm.rmse_2ns,
            sm.true_detections,
            sm.truth_peaks,
            sm.detection_rate,
            sm.false_detections,
            sm.false_per_pulse,
            sm.sam_deg,
            sm.mean_ns / 1e3,
            sm.median_ns / 1e3,
            sm.slowest_case_median_ns / 1e3,
            sm.max_rate_hz(workers),
            sm.dropped,
            sm.pareto,
        );
    }
    s
}

/// The machine the sweep ran on, as the report states it.
#[derive(Clone, Debug, PartialEq)]
pub struct Machine {
    /// Logical cores available to the process.
    pub cores: usize,
    /// Pipeline workers on it (one per core, as the runtime's default): what the rates are
    /// computed for.
    pub workers: usize,
    /// CPU model, when known.
    pub cpu: Option<String>,
}

impl Machine {
    /// This machine: cores from the OS, the CPU model from `/proc/cpuinfo` when readable.
    pub fn detect() -> Self {
        let cores = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        });
        Machine {
            cores,
            workers: crate::pipeline::runner::resolve_workers(0),
            cpu,
        }
    }
}

/// The CSV: a header of [`CSV_COLUMNS`], then one row per case. Times in µs; rates in pulses/s
/// for `workers` threads at the case's median time.
pub fn csv(settings: &[Setting], cases: &[CaseResult], workers: usize) -> String {
    let mut s = CSV_COLUMNS.join(",");
    s.push('\n');
    for c in cases {
        let set = &settings[c.setting];
        let med = c.median_ns();
        let _ = writeln!(
            s,
            "{},{},{},{},{},{:.6},{:.6},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.0}",
            set.method,
            set.parameter,
            c.family.name(),
            c.width_ns,
            c.pulses,
            c.rmse.rmse(),
            c.rmse_2ns.rmse(),
            c.peaks.true_detections,
            c.peaks.false_detections,
            c.truth_peaks,
            c.detection_rate(),
            c.false_per_pulse(),
            c.sam_deg,
            c.mean_ns() / 1e3,
            med / 1e3,
            c.p99_ns() / 1e3,
            workers as f64 / (med * 1e-9),
        );
    }
    s
}

/// A time in µs with sensible digits.
fn us(ns: f64) -> String {
    let u = ns / 1e3;
    if u < 1.0 {
        format!("{u:.3}")
    } else if u < 100.0 {
        format!("{u:.1}")
    } else {
        format!("{u:.0}")
    }
}

/// A rate in pulses/s as kHz or MHz.
pub fn rate(hz: f64) -> String {
    if !hz.is_finite() {
        "—".into()
    } else if hz >= 1e6 {
        format!("{:.1} MHz", hz / 1e6)
    } else {
        format!("{:.0} kHz", hz / 1e3)
    }
}

/// The markdown report. `plot_file` is the SVG's file name, linked from the report.
pub fn markdown(
    config: &SweepConfig,
    settings: &[Setting],
    cases: &[CaseResult],
    summary: &[SettingSummary],
    machine: &Machine,
    plot_file: &str,
) -> String {
    let mut s = String::new();
    setup_section(&mut s, config, cases, machine, plot_file);
    summary_table(&mut s, settings, summary, machine.workers);
    chain_notes(&mut s, settings, summary);
    case_tables(&mut s, config, settings, cases);
    s
}

/// The report's setup: cases (pulses, widths in ns, families, truth peaks per pulse), noise,
/// truth and peak matching, the machine, and the plot.
fn setup_section(
    s: &mut String,
    config: &SweepConfig,
    cases: &[CaseResult],
    machine: &Machine,
    plot_file: &str,
) {
    let w = machine.workers;
    let widths: Vec<String> = config.widths_ns.iter().map(|w| format!("{w}")).collect();
    let families: Vec<&str> = config.families.iter().map(|f| f.name()).collect();
    let truth_peaks: u64 = cases
        .iter()
        .filter(|c| c.setting == 0)
        .map(|c| c.truth_peaks)
        .sum();
    let pulses_per_setting = config.pulses * config.widths_ns.len() * config.families.len();
    let _ = writeln!(s, "### Setup\n");
    let _ = writeln!(
        s,
        "- {} pulses per case; cases: outgoing pulse FWHM {} ns × truth families {} \
         ({} pulses per setting, {:.2} truth peaks per pulse); {} bins at {} ns; seed {}.",
        config.pulses,
        widths.join(", "),
        families.join(", "),
        pulses_per_setting,
        truth_peaks as f64 / pulses_per_setting.max(1) as f64,
        config.bins,
        config.sample_ns,
        config.seed,
    );
    let _ = writeln!(
        s,
        "- Noise: uniform in ±{} × the noise-free received peak. Truth: the cross-section \
         convolved with a 2 ns FWHM pulse. Peaks: floor {} × the waveform's maximum{}, agreement \
         within ±{} bin(s).",
        config.noise_fraction,
        config.peak_floor,
        if config.peak_snr > 0.0 {
            format!(
                ", echo strength in the data ≥ {} × the received noise σ (noise-aware detector)",
                config.peak_snr
            )
        } else {
            String::new()
        },
        config.peak_tolerance_bins
    );
    let _ = writeln!(
        s,
        "- Machine: {} logical core(s){}; times are single-thread wall clock per pulse (one \
         core): means over pulses (what decides throughput; the Pareto front and the plot use \
         them) and medians; pulse rates assume {} worker thread(s) (one per core, as the \
         runtime's default) at the slowest case's median: rate = workers / time.\n",
        machine.cores,
        machine
            .cpu
            .as_deref()
            .map(|c| format!(" ({c})"))
            .unwrap_or_default(),
        w,
    );
    let _ = writeln!(s, "![error against time per pulse]({plot_file})\n");
}

/// The summary table: one row per setting (pooled over widths and families) with its times
/// (µs per pulse), the largest pulse rate `w` workers sustain, which of [`RATES_HZ`] it
/// keeps, its scores and whether it is on the Pareto front.
fn summary_table(s: &mut String, settings: &[Setting], summary: &[SettingSummary], w: usize) {
    let _ = writeln!(
        s,
        "### Summary per setting (pulse-weighted over pulse widths and families)\n"
    );
    let _ = writeln!(
        s,
        "Every pulse of every case weighs the same: RMSE over every bin of every pulse (the \
         square root of the pulse-weighted mean of the cases' squared RMSEs), true detections = \
         Σ true / Σ truth peaks, false/pulse = Σ false / Σ pulses, times over every pulse. \
         `tradeoff_summary.csv` holds the same rows with the counts.\n"
    );
    let rate_heads: Vec<String> = RATES_HZ.iter().map(|&r| rate(r)).collect();
    let _ = writeln!(
        s,
        "| setting | mean µs/pulse | median µs/pulse | slowest case µs | max rate ({w} worker{}) | {} | RMSE | RMSE at 2 ns | true det. | false/pulse | SAM ° | Pareto |",
        if w == 1 { "" } else { "s" },
        rate_heads.join(" | ")
    );
    let _ = writeln!(
        s,
        "|---|---:|---:|---:|---:|{}---:|---:|---:|---:|---:|:-:|",
        ":-:|".repeat(RATES_HZ.len())
    );
    for sm in summary {
        let set = &settings[sm.setting];
        let max = sm.max_rate_hz(w);
        let keeps: Vec<&str> = RATES_HZ
            .iter()
            .map(|&r| if max >= r { "yes" } else { "no" })
            .collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {:.4} | {:.4} | {:.1} % | {:.2} | {:.1} | {} |",
            set.label(),
            us(sm.mean_ns),
            us(sm.median_ns),
            us(sm.slowest_case_median_ns),
            rate(max),
            keeps.join(" | "),
            sm.rmse,
            sm.rmse_2ns,
            100.0 * sm.detection_rate,
            sm.false_per_pulse,
            sm.sam_deg,
            if sm.pareto { "●" } else { "" }
        );
    }
    let _ = writeln!(s);
}

/// What each chain (`--chain`) ran and left out, and the pulses its stages dropped (scored as
/// all-zero waveforms); nothing without chains.
fn chain_notes(s: &mut String, settings: &[Setting], summary: &[SettingSummary]) {
    let chains: Vec<(&Setting, u64)> = summary
        .iter()
        .filter_map(|sm| {
            let set = &settings[sm.setting];
            matches!(set.processing, Processing::Chain(_)).then_some((set, sm.dropped))
        })
        .collect();
    if chains.is_empty() {
        return;
    }
    let _ = writeln!(s, "### Chains\n");
    for (set, dropped) in chains {
        let Processing::Chain(spec) = &set.processing else {
            continue;
        };
        let skipped = if spec.skipped.is_empty() {
            String::new()
        } else {
            format!(
                "; not run (they do not change the waveform): {}",
                spec.skipped.join(", ")
            )
        };
        let _ = writeln!(
            s,
            "- `{}`: the stages of `{}` that change the waveform, {}{skipped}; {dropped} \
             pulse(s) dropped by a stage (scored as all-zero waveforms).",
            set.method,
            spec.file.display(),
            spec.stage_names().join(" → "),
        );
    }
    let _ = writeln!(
        s,
        "\nA chain's pulse is the simulated waveform as a 16-bit digitizer records it (one gain \
         per pulse over its range), with its outgoing pulse (the case's system pulse, noise-free) \
         as a second segment: a `kernel = \"outgoing\"` deconvolution uses it after the denoise \
         stage, as replay does, where the built-in settings deconvolve by the exact system \
         pulse. Timed as the built-in settings: the stages alone, one thread.\n"
    );
}

/// The per-case tables, one per score: rows = settings, columns = family × width (ns).
fn case_tables(s: &mut String, config: &SweepConfig, settings: &[Setting], cases: &[CaseResult]) {
    let widths: Vec<String> = config.widths_ns.iter().map(|w| format!("{w}")).collect();
    let families: Vec<&str> = config.families.iter().map(|f| f.name()).collect();
    let mut cols: Vec<(usize, usize)> = Vec::new();
    for fi in 0..config.families.len() {
        for wi in 0..config.widths_ns.len() {
            cols.push((fi, wi));
        }
    }
    let head: Vec<String> = cols
        .iter()
        .map(|&(fi, wi)| format!("{} {} ns", families[fi], widths[wi]))
        .collect();
    let find = |si: usize, fi: usize, wi: usize| {
        cases.iter().find(|c| {
            c.setting == si && c.family == config.families[fi] && c.width_ns == config.widths_ns[wi]
        })
    };
    type Cell = fn(&CaseResult) -> String;
    let tables: [(&str, Cell); 5] = [
        ("RMSE (eq. 14, fraction of the truth's peak)", |c| {
            format!("{:.4}", c.rmse.rmse())
        }),
        (
            "RMSE at the truth's resolution (the output convolved with the 2 ns pulse, fraction of the truth's peak)",
            |c| format!("{:.4}", c.rmse_2ns.rmse()),
        ),
        (
            "True detections (% of truth peaks) / false detections per pulse",
            |c| {
                format!(
                    "{:.0} % / {:.2}",
                    100.0 * c.detection_rate(),
                    c.false_per_pulse()
                )
            },
        ),
        ("Spectral angle (degrees, mean over pulses)", |c| {
            format!("{:.1}", c.sam_deg)
        }),
        ("Time per pulse (µs, median, one core)", |c| {
            us(c.median_ns())
        }),
    ];
    for (title, cell) in tables {
        let _ = writeln!(s, "### {title}\n");
        let _ = writeln!(s, "| setting | {} |", head.join(" | "));
        let _ = writeln!(s, "|---|{}", "---:|".repeat(cols.len()));
        for (si, set) in settings.iter().enumerate() {
            let cells: Vec<String> = cols
                .iter()
                .map(|&(fi, wi)| find(si, fi, wi).map(cell).unwrap_or_default())
                .collect();
            let _ = writeln!(s, "| {} | {} |", set.label(), cells.join(" | "));
        }
        let _ = writeln!(s);
    }
}
