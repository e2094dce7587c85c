//! `fwlidar validate`: checks configuration files — run configurations, sensor profiles, scenes —
//! and reports every problem with the file, line:column, the field's path and the reason.

use std::path::PathBuf;

use crate::cli::Failure;
use crate::config::{Validated, validate_any};
use crate::pipeline::registry::StageConfig;
use crate::signal::deconvolve::KernelSource;

/// Arguments of `fwlidar validate`.
#[derive(Debug, clap::Args)]
pub struct ValidateArgs {
    /// Files to check.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
}

/// Runs `fwlidar validate`: prints `FILE: ok (kind)` or every issue; exit 2 if any file fails.
pub fn run(args: ValidateArgs) -> Result<(), Failure> {
    let mut failed = 0usize;
    for file in &args.files {
        match validate_any(file) {
            Ok(v) => {
                let kind = match &v {
                    Validated::Sensor(s) => format!("sensor profile: {}", s.sensor.name),
                    Validated::Run(r) => format!(
                        "run configuration: {} stage(s), input edge {:?}",
                        r.pipeline.stages.len(),
                        r.pipeline.input_edge
                    ),
                    Validated::Scene(s) => format!("scene: {} pulses", s.scene.pulses),
                    Validated::World(s) => format!(
                        "described scene: {} tree(s), {} grass patch(es), {} box(es), {} roof(s), \
                         effects [{}]",
                        s.tree.len(),
                        s.grass.len(),
                        s.boxes.len(),
                        s.roof.len(),
                        s.effects
                            .iter()
                            .map(|e| e.name())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                };
                println!("{}: ok ({kind})", file.display());
                if let Validated::Run(r) = &v {
                    for line in stage_costs(&r.pipeline.stages) {
                        println!("  {line}");
                    }
                }
            }
            Err(e) => {
                failed += 1;
                eprintln!("{e}");
            }
        }
    }
    if failed > 0 {
        return Err(Failure::usage(format!(
            "{failed} of {} file(s) failed validation",
            args.files.len()
        )));
    }
    Ok(())
}

/// Groups the digits of `n` by thousands with spaces (`1 860 770`).
fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// One line per stage with a fixed per-pulse budget: the deconvolve stages' worst-case flops
/// per return segment (method, iteration budget, segment and kernel sizes), the decompose
/// stages' Levenberg-Marquardt budget.
pub fn stage_costs(stages: &[StageConfig]) -> Vec<String> {
    let mut lines = Vec::new();
    for (i, stage) in stages.iter().enumerate() {
        match stage {
            StageConfig::Deconvolve(c) => {
                let w = c.worst_case();
                let kernel = match c.kernel {
                    KernelSource::Outgoing => format!("outgoing pulse of <= {} taps", w.taps),
                    KernelSource::Taps { .. } => format!("calibrated, {} taps", w.taps),
                    KernelSource::FlatTarget { .. } => {
                        format!("response measured on a flat target, {} taps", w.taps)
                    }
                };
                let iterations = if w.iterations == 0 {
                    "direct".to_string()
                } else {
                    format!("{} iterations", w.iterations)
                };
                lines.push(format!(
                    "stage {i} deconvolve ({}, {iterations}, kernel: {kernel}): worst case {} flop \
                     per return segment of <= {} samples",
                    c.method.name(),
                    grouped(w.flops),
                    w.samples
                ));
            }
            StageConfig::Decompose(c) => lines.push(format!(
                "stage {i} decompose: at most {} Levenberg-Marquardt steps and {} components per \
                 return segment of <= {} samples",
                c.max_iterations, c.max_components, c.max_samples
            )),
            _ => {}
        }
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grouped_digits() {
        assert_eq!(grouped(0), "0");
        assert_eq!(grouped(999), "999");
        assert_eq!(grouped(1000), "1 000");
        assert_eq!(grouped(1_860_770), "1 860 770");
    }
}
