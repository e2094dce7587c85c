//! `fwlidar validate`: checks configuration files — run configurations, sensor profiles, scenes —
//! and reports every problem with the file, line:column, the field's path and the reason.

use std::path::PathBuf;

use crate::cli::Failure;
use crate::config::{Validated, validate_any};

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
                let kind = match v {
                    Validated::Sensor(s) => format!("sensor profile: {}", s.sensor.name),
                    Validated::Run(r) => format!(
                        "run configuration: {} stage(s), input edge {:?}",
                        r.pipeline.stages.len(),
                        r.pipeline.input_edge
                    ),
                    Validated::Scene(s) => format!("scene: {} pulses", s.scene.pulses),
                };
                println!("{}: ok ({kind})", file.display());
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
