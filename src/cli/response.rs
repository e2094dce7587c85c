//! `fwlidar response learn INPUT... --out FILE`: the system response learned from waveform
//! files' own echoes ([`crate::signal::learned_response`]), written as a documented text file
//! (`docs/formats.md`, "Learned response") with a figure of each channel's shape and its
//! spread beside it. A `decompose` stage uses it by name (`response = "FILE"`).

use std::fmt::Write as _;
use std::path::PathBuf;

use crate::cli::Failure;
use crate::core::atomic_file::write_atomic;
use crate::signal::learned_response::{
    GAUSSIAN_MISFIT, LearnedResponse, ResponseFile, ResponseLearner,
};

/// Arguments of `fwlidar response`.
#[derive(Debug, clap::Args)]
pub struct ResponseArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: ResponseCommand,
}

/// `fwlidar response` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum ResponseCommand {
    /// Learn the system response of each channel from the isolated, strong, unsaturated single
    /// echoes of waveform files (captures, LAS/LAZ, PulseWaves, GEDI L1B).
    Learn(LearnArgs),
}

/// Arguments of `fwlidar response learn`.
#[derive(Debug, clap::Args)]
pub struct LearnArgs {
    /// Waveform files of one instrument (their pulses are read in turn).
    #[arg(required = true, num_args = 1..)]
    pub inputs: Vec<PathBuf>,
    /// The response file to write (TOML; never written over).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Most pulses read, all files together.
    #[arg(long, default_value_t = 200_000)]
    pub pulses: u64,
    /// The figure of the learned shapes (SVG). Default: the response file with `.svg`.
    #[arg(long)]
    pub figure: Option<PathBuf>,
}

/// Runs `fwlidar response`.
pub fn run(args: ResponseArgs) -> Result<(), Failure> {
    match args.command {
        ResponseCommand::Learn(a) => learn(a),
    }
}

fn learn(args: LearnArgs) -> Result<(), Failure> {
    let figure = args
        .figure
        .clone()
        .unwrap_or_else(|| args.out.with_extension("svg"));
    for out in [&args.out, &figure] {
        if out.exists() {
            return Err(Failure::usage(format!(
                "{}: already exists; a response file or figure is never written over",
                out.display()
            )));
        }
    }
    let mut learner = ResponseLearner::new();
    for input in &args.inputs {
        crate::run::learn::read_into(&mut learner, input, args.pulses)?;
    }
    let names: Vec<String> = args
        .inputs
        .iter()
        .map(|p| p.display().to_string())
        .collect();
    let from = format!(
        "learned from {} pulses of {}",
        learner.pulses(),
        names.join(", ")
    );
    let file = learner
        .finish(&from)
        .map_err(|e| Failure::job(format!("{}: {e}", names.join(", "))))?;
    write_atomic(&args.out, file.to_text().as_bytes())
        .map_err(|e| Failure::job(format!("{}: {e}", args.out.display())))?;
    write_atomic(&figure, response_svg(&file).as_bytes())
        .map_err(|e| Failure::job(format!("{}: {e}", figure.display())))?;
    println!("fwlidar response learn  ->  {}", args.out.display());
    println!("  {from}");
    for r in &file.responses {
        println!("  {}", channel_line(r));
    }
    println!("  figure: {}", figure.display());
    Ok(())
}

/// One channel in words: echoes, width, tail, whether Gaussian, whether it changes with
/// amplitude.
pub fn channel_line(r: &LearnedResponse) -> String {
    format!(
        "channel {}: {} echoes of {} candidates ({:.0}-{:.0} counts); FWHM {:.2} ns, from {:.1} \
         to {:.1} ns of the peak; {} (misfit {:.1} % of the peak, Gaussian below {:.0} %); {}",
        r.channel,
        r.echoes,
        r.candidates,
        r.amplitude_counts[0],
        r.amplitude_counts[1],
        f64::from(r.fwhm_samples) * r.sample_ns,
        f64::from(r.start_samples) * r.sample_ns,
        f64::from(r.end_samples()) * r.sample_ns,
        if r.is_gaussian() {
            "Gaussian"
        } else {
            "not Gaussian"
        },
        100.0 * r.gaussian_misfit,
        100.0 * GAUSSIAN_MISFIT,
        match r.amplitude_dependence {
            Some(d) => format!(
                "shape {} with amplitude ({:.1} % of the peak between the weakest and strongest \
                 third, beyond the noise)",
                if r.changes_with_amplitude() == Some(true) {
                    "changes"
                } else {
                    "does not change"
                },
                100.0 * d.clamp(0.0, 1.0)
            ),
            None => "whether the shape changes with amplitude cannot be told (the echoes' \
                     amplitudes span too narrow a range)"
                .to_string(),
        },
    )
}

/// The figure: each channel's shape against time from its peak (ns), with the band of ± its
/// spread, and a Gaussian of the same FWHM dashed; a log panel below shows the tail.
pub fn response_svg(file: &ResponseFile) -> String {
    let (w, h) = (760.0, 520.0);
    let (left, right) = (70.0, 20.0);
    let panels = [(40.0, 230.0, false), (300.0, 180.0, true)];
    let t0 = file
        .responses
        .iter()
        .map(|r| f64::from(r.start_samples) * r.sample_ns)
        .fold(0.0, f64::min);
    let t1 = file
        .responses
        .iter()
        .map(|r| f64::from(r.end_samples()) * r.sample_ns)
        .fold(1.0, f64::max);
    let colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd"];
    let mut s = String::new();
    let _ = write!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"{w}\" height=\"{h}\" \
         fill=\"white\"/>\n<text x=\"{left}\" y=\"22\" font-size=\"14\">Learned system \
         response: {}</text>\n",
        xml(&file_names(&file.learned_from))
    );
    let x_of = |t: f64| left + (t - t0) / (t1 - t0) * (w - left - right);
    for (top, height, log) in panels {
        let y_of = |v: f64| {
            if log {
                let v = v.max(1e-3);
                top + height * (0.0 - v.log10()) / 3.0
            } else {
                top + height * (1.1 - v) / 1.2
            }
        };
        let _ = writeln!(
            s,
            "<rect x=\"{left}\" y=\"{top}\" width=\"{}\" height=\"{height}\" fill=\"none\" \
             stroke=\"#888\"/>",
            w - left - right
        );
        let ticks: &[f64] = if log {
            &[1.0, 0.1, 0.01, 0.001]
        } else {
            &[0.0, 0.5, 1.0]
        };
        for &v in ticks {
            let _ = writeln!(
                s,
                "<text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{v}</text>",
                left - 6.0,
                y_of(v) + 4.0
            );
        }
        let _ = writeln!(
            s,
            "<text x=\"14\" y=\"{:.1}\" transform=\"rotate(-90 14 {:.1})\" \
             text-anchor=\"middle\">{}</text>",
            top + height / 2.0,
            top + height / 2.0,
            if log {
                "fraction of peak (log)"
            } else {
                "fraction of peak"
            }
        );
        for (k, r) in file.responses.iter().enumerate() {
            let c = colours[k % colours.len()];
            let pts = |f: &dyn Fn(usize) -> f64| -> String {
                (0..r.shape.len())
                    .map(|i| {
                        let t =
                            f64::from(r.start_samples + i as f32 * r.step_samples) * r.sample_ns;
                        format!("{:.1},{:.1}", x_of(t), y_of(f(i)))
                    })
                    .collect::<Vec<_>>()
                    .join(" ")
            };
            if !log {
                let upper = pts(&|i| f64::from(r.shape[i] + r.spread[i]));
                let lower: Vec<String> = (0..r.shape.len())
                    .rev()
                    .map(|i| {
                        let t =
                            f64::from(r.start_samples + i as f32 * r.step_samples) * r.sample_ns;
                        format!(
                            "{:.1},{:.1}",
                            x_of(t),
                            y_of(f64::from(r.shape[i] - r.spread[i]))
                        )
                    })
                    .collect();
                let _ = writeln!(
                    s,
                    "<polygon points=\"{upper} {}\" fill=\"{c}\" fill-opacity=\"0.18\" \
                     stroke=\"none\"/>",
                    lower.join(" ")
                );
                let sigma = f64::from(r.fwhm_samples) / 2.354_82;
                let gauss = pts(&|i| {
                    let x = f64::from(r.start_samples + i as f32 * r.step_samples);
                    (-0.5 * (x / sigma).powi(2)).exp()
                });
                let _ = writeln!(
                    s,
                    "<polyline points=\"{gauss}\" fill=\"none\" stroke=\"#555\" \
                     stroke-dasharray=\"4 3\"/>"
                );
            }
            let _ = writeln!(
                s,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{c}\" stroke-width=\"1.6\"/>",
                pts(&|i| f64::from(r.shape[i]))
            );
            if !log {
                let _ = writeln!(
                    s,
                    "<text x=\"{:.1}\" y=\"{:.1}\" fill=\"{c}\" text-anchor=\"end\">channel {}: \
                     FWHM {:.2} ns, {} echoes; band ± spread; dashed: Gaussian of the same \
                     FWHM</text>",
                    w - right - 10.0,
                    top + 18.0 + 16.0 * k as f64,
                    r.channel,
                    f64::from(r.fwhm_samples) * r.sample_ns,
                    r.echoes
                );
            }
        }
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">time from the peak (ns)</text>",
        (left + w - right) / 2.0,
        h - 12.0
    );
    for t in (t0.ceil() as i64..=t1.floor() as i64).filter(|t| t % 10 == 0) {
        let _ = writeln!(
            s,
            "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{t}</text>",
            x_of(t as f64),
            h - 30.0
        );
    }
    s.push_str("</svg>\n");
    s
}

/// `text` with every path cut to its file name (a figure's title stays on one line).
fn file_names(text: &str) -> String {
    text.split(' ')
        .map(|w| w.rsplit('/').next().unwrap_or(w))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Text safe inside SVG.
fn xml(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
