//! `fwlidar process --learn-kernel`: the deconvolution kernel learned from the rows themselves
//! ([`crate::signal::learned_response`]), for when the system pulse is not known well enough:
//! a kernel 10 % too narrow or too wide costs a deconvolution more than its method choice
//! (docs/accuracy.md, "Deconvolution by a learned kernel").
//!
//! Each row is one return segment: its baseline line removed as `--baseline` says (the learner
//! then takes the median of its first samples as the level), a row with clipped samples taken for
//! the stretch of `--kernel` only, with those samples left out (its strongest echo is cut), the quantum one count when every value of the table is an
//! integer (digitizer counts) and none otherwise. The learner takes each row's strongest sample
//! when it is an isolated, strong single echo, aligns those echoes to a quarter of a sample and
//! averages the narrower half; the kernel is that shape at whole samples, centred on its peak.
//!
//! With `--kernel`, that kernel is the starting point: its shape is kept and stretched in time
//! to the echoes ([`crate::signal::kernel_stretch`]: a least-squares fit of every sample of each
//! echo, the median stretch), and it is used as given when the rows hold too few clean single
//! echoes (said on stderr). Without `--kernel` the learned shape is the kernel; with too few
//! echoes that is an error.

use crate::cli::Failure;
use crate::format::table::Table;
use crate::signal::drift::{DriftBaseline, flag_saturated, is_counts};
use crate::signal::kernel::Kernel;
use crate::signal::kernel_stretch::stretched_taps;
use crate::signal::learned_response::{MIN_ECHOES, ResponseLearner};

use super::process::{BaselineModel, ProcessArgs, unpadded_len};

/// What `--learn-kernel` did, for the summary line.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelLearning {
    /// Echoes the kernel was learned from (0 when the given kernel was kept).
    pub echoes: usize,
    /// The stretch in time applied to `--kernel` (`None`: the learned shape itself).
    pub stretch: Option<f32>,
    /// Full width at half maximum of the kernel learned, ns (`None` when none was learned).
    pub learned_fwhm_ns: Option<f64>,
    /// Full width at half maximum of `--kernel`, ns, when one was given.
    pub given_fwhm_ns: Option<f64>,
    /// Why the given kernel was kept, when it was.
    pub kept_given: Option<String>,
}

impl KernelLearning {
    /// The summary line's words: `, kernel learned from 180 echoes of the rows (FWHM 8.81 ns;
    /// --kernel's 8.00 ns, 10.1 % narrower)`.
    pub fn words(&self) -> String {
        match (&self.kept_given, self.learned_fwhm_ns) {
            (Some(why), _) => format!(", --kernel kept ({why})"),
            (None, Some(f)) => {
                let against = match self.given_fwhm_ns {
                    Some(g) if g > 0.0 => format!(
                        "; --kernel's {g:.2} ns, {:.1} % {}",
                        100.0 * (f - g).abs() / g,
                        if f >= g { "narrower" } else { "wider" }
                    ),
                    _ => String::new(),
                };
                match self.stretch {
                    Some(s) => format!(
                        ", --kernel stretched {s:.3}x to {} echoes of the rows (FWHM {f:.2} \
                         ns{against})",
                        self.echoes
                    ),
                    None => format!(
                        ", kernel learned from {} echoes of the rows (FWHM {f:.2} ns{against})",
                        self.echoes
                    ),
                }
            }
            (None, None) => String::new(),
        }
    }
}

/// The kernel for every row of `table` (named `input_name` in errors) learned from its rows,
/// `given` (`--kernel`) the starting point; with what was done. An error when nothing could be
/// learned and no kernel was given.
pub fn learn_kernel(
    args: &ProcessArgs,
    table: &Table,
    given: Option<&Kernel>,
    input_name: &str,
) -> Result<(Kernel, KernelLearning), Failure> {
    let rows = || {
        table.rows.iter().map(|r| {
            if args.zero_padding {
                &r[..unpadded_len(r)]
            } else {
                &r[..]
            }
        })
    };
    let quantum = if rows().all(is_counts) { 1.0 } else { 0.0 };
    let mut learner = ResponseLearner::with_quantum(quantum);
    let mut drift = DriftBaseline::with_capacity(0);
    let mut excluded = Vec::new();
    let mut flat = Vec::new();
    for row in rows() {
        if row.iter().any(|v| !v.is_finite()) {
            continue;
        }
        let clipped = flag_saturated(row, &mut excluded) > 0;
        flat.clear();
        if args.baseline == BaselineModel::Line {
            let line = drift.fit(row, clipped.then_some(&excluded[..]));
            flat.extend(
                row.iter()
                    .enumerate()
                    .map(|(i, &v)| (f64::from(v) - line.at(i)) as f32),
            );
        } else {
            flat.extend_from_slice(row);
        }
        match longest_run(&excluded).filter(|_| clipped) {
            Some(run) => learner.add_clipped_segment(0, args.sample_ns, &flat, run),
            None => learner.add_segment(0, args.sample_ns, &flat, f32::INFINITY),
        }
    }
    let given_fwhm_ns = given
        .and_then(Kernel::fwhm_samples)
        .map(|f| f * args.sample_ns);
    let learned = match given {
        Some(g) => stretch_given(&learner, g),
        None => learner
            .finish(&format!("the rows of {input_name}"))
            .map_err(|e| e.to_string())
            .and_then(|file| {
                let r = file
                    .for_channel(0)
                    .ok_or_else(|| "no response learned".to_string())?;
                let (taps, center) = r.kernel_taps();
                let mut k = Kernel::with_capacity(taps.len());
                k.set_from_taps(&taps, center, taps.len())
                    .map_err(|e| format!("the learned shape: {e}"))?;
                Ok((k, r.echoes, None))
            }),
    };
    let learned = learned.map(|(k, echoes, stretch)| {
        let fwhm = k.fwhm_samples().unwrap_or(f64::NAN) * args.sample_ns;
        (k, echoes, fwhm, stretch)
    });
    match (learned, given) {
        (Ok((k, echoes, fwhm, stretch)), _) => Ok((
            k,
            KernelLearning {
                echoes,
                stretch,
                learned_fwhm_ns: Some(fwhm),
                given_fwhm_ns,
                kept_given: None,
            },
        )),
        (Err(why), Some(g)) => {
            tracing::warn!(
                "--learn-kernel learned nothing from {input_name} ({why}): --kernel is used as given"
            );
            Ok((
                g.clone(),
                KernelLearning {
                    echoes: 0,
                    stretch: None,
                    learned_fwhm_ns: None,
                    given_fwhm_ns,
                    kept_given: Some(why),
                },
            ))
        }
        (Err(why), None) => Err(Failure::job(format!(
            "{input_name}: --learn-kernel: {why}; give --kernel as the starting point"
        ))),
    }
}

/// `given` stretched in time to the hard-target echoes `learner` collected, with their number
/// and the stretch; why not when there are too few.
fn stretch_given(
    learner: &ResponseLearner,
    given: &Kernel,
) -> Result<(Kernel, usize, Option<f32>), String> {
    let (s, n) = learner
        .kernel_stretch(&given.taps, given.center)
        .ok_or_else(|| {
            format!(
                "{} strong, isolated single echoes in the rows (at least {MIN_ECHOES} are needed)",
                learner.candidates()
            )
        })?;
    let (taps, center) = stretched_taps(&given.taps, given.center, s);
    let mut k = Kernel::with_capacity(taps.len());
    k.set_from_taps(&taps, center, taps.len())
        .map_err(|e| format!("--kernel stretched {s:.3}x: {e}"))?;
    Ok((k, n, Some(s)))
}

/// The longest run of `true` in `flags`, if any.
fn longest_run(flags: &[bool]) -> Option<std::ops::Range<usize>> {
    let mut best: Option<std::ops::Range<usize>> = None;
    let mut i = 0;
    while i < flags.len() {
        if flags[i] {
            let start = i;
            while i < flags.len() && flags[i] {
                i += 1;
            }
            if best.as_ref().is_none_or(|b| i - start > b.len()) {
                best = Some(start..i);
            }
        } else {
            i += 1;
        }
    }
    best
}
