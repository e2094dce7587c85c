//! `fwlidar validate`: checks configuration files — run configurations, sensor profiles, scenes —
//! and reports every problem with the file, line:column, the field's path and the reason.

use std::path::PathBuf;

use std::path::Path;

use crate::cli::Failure;
use crate::config::RunConfig;
use crate::core::config_error::ConfigErrors;
use crate::core::sensor::SensorFile;
use crate::core::toml_load::{load_str, read_top_level_keys};
use crate::stages::StageConfig;

/// A configuration file, validated, as recognised by [`validate_any`].
#[derive(Clone, Debug, PartialEq)]
pub enum Validated {
    /// A sensor profile (a `[sensor]` table).
    Sensor(SensorFile),
    /// A run configuration (`sensor_profile`, `[pipeline]`, `[output]`).
    Run(Box<RunConfig>),
    /// A simulator scene (a `[scene]` table).
    Scene(Box<crate::sim::SceneFile>),
    /// A described simulator scene (a `[flight]` table: terrain, objects, flight plan).
    World(Box<crate::sim::world::scene::WorldScene>),
}

/// Validates the file at `path` as whichever kind it is, decided by its top-level tables: a
/// `[flight]` table makes it a described simulator scene, a `[sensor]` table a sensor profile,
/// a `[scene]` table an analytic simulator scene (schema, values and its sensor profile),
/// anything else a run configuration. Every problem is reported, as by `config::load_file`.
pub fn validate_any(path: impl AsRef<Path>) -> Result<Validated, ConfigErrors> {
    let path = path.as_ref();
    let (text, keys) = read_top_level_keys(path)?;
    let has = |k: &str| keys.iter().any(|key| key == k);
    if has("flight") {
        load_str(&text, path).map(|f| Validated::World(Box::new(f)))
    } else if has("sensor") {
        load_str(&text, path).map(Validated::Sensor)
    } else if has("scene") {
        load_str(&text, path).map(|f| Validated::Scene(Box::new(f)))
    } else {
        load_str(&text, path).map(|r| Validated::Run(Box::new(r)))
    }
}

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

/// One line per stage with a fixed per-pulse budget (the deconvolve stages' worst-case flops
/// per return segment, the decompose stages' Levenberg-Marquardt budget), as each stage states
/// it.
pub fn stage_costs(stages: &[StageConfig]) -> Vec<String> {
    let mut lines = Vec::new();
    for (i, stage) in stages.iter().enumerate() {
        for line in stage.as_kind().cost_lines() {
            lines.push(format!("stage {i} {line}"));
        }
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_any_decides_by_top_level_tables() {
        use crate::core::config_error::IssueKind;
        let dir = tempfile::tempdir().unwrap();
        let sensor = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sensors/riegl_lms_q680i.toml"),
        )
        .unwrap();
        let write = |name: &str, text: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        let s = write("s.toml", &sensor);
        assert!(matches!(validate_any(&s), Ok(Validated::Sensor(_))));
        let r = write("r.toml", "[pipeline]\nworkers = 2\n");
        assert!(matches!(validate_any(&r), Ok(Validated::Run(_))));
        let c = write("c.toml", "[scene]\ntrees = 6\n");
        let e = validate_any(&c).unwrap_err();
        assert!(
            e.issues
                .iter()
                .any(|i| i.kind == IssueKind::Schema && i.path == "scene.trees"),
            "{e}"
        );
        // A file that mixes kinds is checked against the first kind found.
        let m = write("m.toml", &format!("{sensor}\n[pipeline]\nworkers = 2\n"));
        let e = validate_any(&m).unwrap_err();
        let paths: Vec<&str> = e.issues.iter().map(|i| i.path.as_str()).collect();
        assert_eq!(paths, ["pipeline"], "{e}");
        // Unreadable text is reported before any kind is chosen.
        let b = dir.path().join("b.toml");
        std::fs::write(&b, b"a = 1\nb = \"\xff\xfe\"\n").unwrap();
        let e = validate_any(&b).unwrap_err();
        assert_eq!(e.issues[0].kind, IssueKind::Io);
    }
}
