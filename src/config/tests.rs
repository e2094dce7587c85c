//! Loading run configurations and sensor profiles: every problem reported at once, with its
//! field path and location (the loader is `core::toml_load`; these tests exercise it on the
//! run configuration's schema).

use super::*;
use crate::core::config_error::Location;
use crate::core::config_error::{ConfigErrors, IssueKind};
use crate::core::sensor::SensorFile;
use crate::core::toml_load::{load_file, load_str, read_top_level_keys};

fn run(text: &str) -> Result<RunConfig, ConfigErrors> {
    load_str(text, "run.toml")
}

fn sensor(text: &str) -> Result<SensorFile, ConfigErrors> {
    load_str(text, "sensor.toml")
}

#[test]
fn unknown_decompose_option_values_name_their_keys() {
    let e = run(
        "[[pipeline.stages]]\ntype = \"decompose\"\nbaseline = \"median\"\n\
                 start_values = \"guess\"\npeak_rule = \"any\"\n",
    )
    .unwrap_err();
    let p = paths(&e);
    for key in ["baseline", "start_values", "peak_rule"] {
        let want = format!("pipeline.stages[0].{key}");
        assert!(p.contains(&want.as_str()), "{key}: {p:?}");
    }
}

/// Path, (line, column) and reason of an issue.
type Summary = (String, Option<(usize, usize)>, String);

fn issues(e: &ConfigErrors) -> Vec<Summary> {
    e.issues
        .iter()
        .map(|i| {
            (
                i.path.clone(),
                i.location.map(|l| (l.line, l.column)),
                i.reason.clone(),
            )
        })
        .collect()
}

fn paths(e: &ConfigErrors) -> Vec<&str> {
    e.issues.iter().map(|i| i.path.as_str()).collect()
}

const GOOD_SENSOR: &str = r#"
[sensor]
name = "test"
wavelength_nm = 1064
pulse_fwhm_ns = 4.0
pulse_rate_hz = 100000
beam_divergence_mrad = 0.5
sample_interval_ns = 1.0
bits_per_sample = 8
"#;

#[test]
fn config_empty_run_file_gets_defaults() {
    assert_eq!(run("").unwrap(), RunConfig::default());
    assert_eq!(sensor(GOOD_SENSOR).unwrap().sensor.bits_per_sample, 8);
}

#[test]
fn config_unknown_top_level_key_has_path_and_location() {
    let e = run("sensor_profile = \"x.toml\"\nbogus = 1\n").unwrap_err();
    let i = issues(&e);
    // The sensor profile does not exist, which is reported too.
    assert_eq!(paths(&e), ["sensor_profile", "bogus"], "{e}");
    assert_eq!(i[1].1, Some((2, 1)));
    assert!(i[1].2.starts_with("unknown key `bogus`"), "{e}");
    assert_eq!(e.issues[1].kind, IssueKind::Schema);
    assert_eq!(e.issues[0].kind, IssueKind::Invalid);
    assert!(i[0].2.contains("no such file"), "{e}");
}

#[test]
fn config_unknown_key_inside_stage_has_indexed_path() {
    let text = "[[pipeline.stages]]\ntype = \"passthrough\"\n\n\
                [[pipeline.stages]]\ntype = \"denoise\"\n  bogus = 1\n";
    let e = run(text).unwrap_err();
    let i = issues(&e);
    assert_eq!(paths(&e), ["pipeline.stages[1].bogus"], "{e}");
    assert_eq!(i[0].1, Some((6, 3)));
    let e = run("[[pipeline.stages]]\ntype = \"passthrough\"\nbogus = 1\n").unwrap_err();
    assert_eq!(paths(&e), ["pipeline.stages[0].bogus"], "{e}");
    assert_eq!(issues(&e)[0].1, Some((3, 1)));
}

#[test]
fn config_wrong_type_is_reported_at_the_value() {
    let e = run("[pipeline]\nqueue_capacity = \"big\"\n").unwrap_err();
    let i = issues(&e);
    assert_eq!(paths(&e), ["pipeline.queue_capacity"], "{e}");
    assert_eq!(i[0].1, Some((2, 18)));
    assert!(i[0].2.contains("invalid type"), "{e}");
    // Inside a tagged stage entry serde loses the path; the loader finds the key.
    let e =
        run("[[pipeline.stages]]\ntype = \"denoise\"\nmax_samples = 64\ncutoff_ghz = \"high\"\n")
            .unwrap_err();
    let i = issues(&e);
    assert_eq!(paths(&e), ["pipeline.stages[0].cutoff_ghz"], "{e}");
    assert_eq!(i[0].1, Some((4, 14)));
    assert!(i[0].2.contains("invalid type: string \"high\""), "{e}");
}

#[test]
fn config_independent_errors_are_all_reported_in_one_run() {
    let text = r#"bogus = 1
[pipeline]
workers = -1
queue_capacity = 1
input_edge = "sometimes"

[[pipeline.stages]]
type = "wavelet"

[[pipeline.stages]]
type = "denoise"
cutoff_ghz = "high"
extra = true

[[pipeline.stages]]
type = "denoise"
max_samples = 8
pretrigger_samples = 2

[output]
dir = ""
waveforms = "yes"
"#;
    let e = run(text).unwrap_err();
    assert_eq!(
        paths(&e),
        [
            "bogus",
            "pipeline.workers",
            "pipeline.queue_capacity",
            "pipeline.input_edge",
            "pipeline.stages[0].type",
            "pipeline.stages[1].cutoff_ghz",
            "pipeline.stages[1].extra",
            "pipeline.stages[2].max_samples",
            "output.dir",
            "output.waveforms",
        ],
        "{e}"
    );
    let lines: Vec<usize> = e.issues.iter().map(|i| i.location.unwrap().line).collect();
    assert_eq!(lines, [1, 3, 4, 5, 8, 12, 13, 17, 21, 22], "{e}");
}

#[test]
fn config_required_key_of_wrong_type_is_reported_once() {
    let text = GOOD_SENSOR.replace("wavelength_nm = 1064", "wavelength_nm = \"1064\"");
    let e = sensor(&text).unwrap_err();
    assert_eq!(paths(&e), ["sensor.wavelength_nm"], "{e}");
}

#[test]
fn config_missing_keys_are_all_reported() {
    let e = sensor("[sensor]\nname = \"x\"\nbits_per_sample = 12\n").unwrap_err();
    assert_eq!(
        paths(&e),
        [
            "sensor.wavelength_nm",
            "sensor.pulse_fwhm_ns",
            "sensor.pulse_rate_hz",
            "sensor.beam_divergence_mrad",
            "sensor.sample_interval_ns",
            "sensor.bits_per_sample",
        ],
        "{e}"
    );
    assert!(e.issues[1].reason.starts_with("missing required key"));
    assert_eq!(e.issues[5].kind, IssueKind::Invalid);
    // Missing keys point at their table.
    assert_eq!(e.issues[1].location, Some(Location { line: 1, column: 1 }));
    let e = sensor("").unwrap_err();
    assert_eq!(paths(&e), ["sensor"], "{e}");
    assert_eq!(e.issues[0].location, None);
}

#[test]
fn config_missing_stage_type_is_reported() {
    let e =
        run("[[pipeline.stages]]\ncutoff_ghz = 0.1\n[[pipeline.stages]]\ntype = 3\n").unwrap_err();
    assert_eq!(
        paths(&e),
        ["pipeline.stages[0].type", "pipeline.stages[1].type"],
        "{e}"
    );
}

#[test]
fn config_semantic_issues_are_all_reported() {
    let text = GOOD_SENSOR
        .replace("bits_per_sample = 8", "bits_per_sample = 12")
        .replace("wavelength_nm = 1064", "wavelength_nm = -1")
        .replace("pulse_rate_hz = 100000", "pulse_rate_hz = nan");
    let e = sensor(&text).unwrap_err();
    assert_eq!(
        paths(&e),
        [
            "sensor.wavelength_nm",
            "sensor.pulse_rate_hz",
            "sensor.bits_per_sample"
        ],
        "{e}"
    );
    assert!(e.issues.iter().all(|i| i.kind == IssueKind::Invalid));
    assert_eq!(e.issues[2].reason, "must be 8 or 16, got 12");
    let e = run("[pipeline]\nqueue_capacity = 2000000\nstages = []\n").unwrap_err();
    assert_eq!(
        paths(&e),
        ["pipeline.queue_capacity", "pipeline.stages"],
        "{e}"
    );
    let e =
        run("[[pipeline.stages]]\ntype = \"denoise\"\npretrigger_samples = 4096\n").unwrap_err();
    assert_eq!(paths(&e), ["pipeline.stages[0].pretrigger_samples"], "{e}");
}

#[test]
fn config_cutoff_is_checked_against_the_referenced_sensor() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("sensors")).unwrap();
    let slow = GOOD_SENSOR.replace("sample_interval_ns = 1.0", "sample_interval_ns = 4.0");
    std::fs::write(dir.path().join("sensors/slow.toml"), slow).unwrap();
    let run_file = dir.path().join("run.toml");
    std::fs::write(
        &run_file,
        "sensor_profile = \"sensors/slow.toml\"\n[[pipeline.stages]]\ntype = \"denoise\"\n",
    )
    .unwrap();
    let e = load_file::<RunConfig>(&run_file).unwrap_err();
    assert_eq!(paths(&e), ["pipeline.stages[0].cutoff_ghz"], "{e}");
    assert!(
        e.issues[0].reason.contains("Nyquist frequency 0.125 GHz"),
        "{e}"
    );
    // The stage exists in the file; its default cut-off is not, so the entry is located.
    assert_eq!(e.issues[0].location.map(|l| l.line), Some(2));
    std::fs::write(
        &run_file,
        "sensor_profile = \"sensors/slow.toml\"\n[[pipeline.stages]]\ntype = \"denoise\"\ncutoff_ghz = 0.1\n",
    )
    .unwrap();
    load_file::<RunConfig>(&run_file).unwrap();
    std::fs::write(&run_file, "sensor_profile = \"sensors/none.toml\"\n").unwrap();
    let e = load_file::<RunConfig>(&run_file).unwrap_err();
    assert_eq!(paths(&e), ["sensor_profile"], "{e}");
}

#[test]
fn config_missing_file_directory_and_binary_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.toml");
    let e = load_file::<RunConfig>(&missing).unwrap_err();
    assert_eq!(e.file, missing);
    assert_eq!(e.issues[0].kind, IssueKind::Io);
    assert_eq!(
        e.to_string(),
        format!("{}: no such file", missing.display())
    );
    let e = load_file::<RunConfig>(dir.path()).unwrap_err();
    assert!(e.to_string().contains("is a directory"), "{e}");
    assert!(e.to_string().starts_with(&dir.path().display().to_string()));
    let binary = dir.path().join("bin.toml");
    std::fs::write(&binary, b"a = 1\nb = \"\xff\xfe\"\n").unwrap();
    let e = read_top_level_keys(&binary).unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Io);
    assert_eq!(e.issues[0].location, Some(Location { line: 2, column: 6 }));
    assert!(e.to_string().contains("not UTF-8"), "{e}");
}

#[test]
fn config_invalid_toml_reports_line_and_column() {
    let e = run("[pipeline]\nworkers = \nqueue_capacity = 4\n").unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Syntax);
    assert_eq!(e.issues[0].location.map(|l| l.line), Some(2), "{e}");
    let e = run("[pipeline\n").unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Syntax);
    assert_eq!(e.issues[0].location.map(|l| l.line), Some(1), "{e}");
    // Duplicate keys are syntax errors in TOML.
    let e = run("[output]\ndir = \"a\"\ndir = \"b\"\n").unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Syntax, "{e}");
    assert_eq!(e.issues[0].location.map(|l| l.line), Some(3), "{e}");
}

#[test]
fn config_display_prints_file_line_column_path_reason() {
    let e = run("[pipeline]\nqueue_capacity = 1\n").unwrap_err();
    assert_eq!(
        e.to_string(),
        "run.toml:2:18: pipeline.queue_capacity: must be in 2..=1048576 pulses, got 1"
    );
}

#[test]
fn config_loader_never_panics_on_truncated_or_mangled_text() {
    let text = r#"sensor_profile = "sensors/none.toml"
[pipeline]
workers = 2
queue_capacity = 64
input_edge = "drop_newest"
[[pipeline.stages]]
type = "denoise"
cutoff_ghz = 0.2
[[pipeline.stages]]
type = "passthrough"
[output]
dir = "out"
"#;
    for cut in 0..=text.len() {
        let _ = run(&text[..cut]);
        let _ = sensor(&text[..cut]);
        let mangled: String = text
            .chars()
            .enumerate()
            .map(|(i, c)| if i == cut { '"' } else { c })
            .collect();
        let _ = run(&mangled);
    }
}

fn run_with(text: &str, sets: &[&str]) -> Result<RunConfig, ConfigErrors> {
    load_str_with(text, "run.toml", sets)
}

const TWO_STAGES: &str = "[pipeline]\nworkers = 2\n[[pipeline.stages]]\ntype = \"denoise\"\n\
    [[pipeline.stages]]\ntype = \"deconvolve\"\nmax_taps = 96\n\
    method = { method = \"richardson_lucy\", iterations = 20 }\n[output]\nlas = false\n";

#[test]
fn config_overrides_change_the_loaded_value() {
    let base = run(TWO_STAGES).unwrap();
    let c = run_with(
        TWO_STAGES,
        &[
            "output.las=true",
            "pipeline.stages[1].max_taps=128",
            "voxels.enabled=false",
            "pipeline.workers=3",
        ],
    )
    .unwrap();
    assert!(!base.output.las && c.output.las);
    assert_eq!(c.pipeline.workers, 3);
    assert!(!c.voxels.enabled);
    let taps = |c: &RunConfig| match &c.pipeline.stages[1] {
        crate::stages::StageConfig::Deconvolve(d) => d.max_taps,
        other => panic!("stage 1 is {other:?}"),
    };
    assert_eq!((taps(&base), taps(&c)), (96, 128));
    // Everything not overridden is as the file says.
    let mut back = c.clone();
    back.output.las = false;
    back.pipeline.workers = 2;
    back.voxels.enabled = base.voxels.enabled;
    if let crate::stages::StageConfig::Deconvolve(d) = &mut back.pipeline.stages[1] {
        d.max_taps = 96;
    }
    assert_eq!(back, base);
}

#[test]
fn config_override_errors_name_the_field_and_the_override() {
    // A misspelt key: reported as an unknown key, without a place in the file.
    let e = run_with(TWO_STAGES, &["output.lass=true"]).unwrap_err();
    assert_eq!(
        issues(&e),
        [(
            "output.lass".to_string(),
            None,
            "unknown key `lass`, expected one of `dir`, `waveforms`, `waveform_format`, \
             `returns`, `las`, `las_point_format`, `las_rotate_s`, `las_flush_s`, \
             `hyper_points`, `hyper_threshold_v`, `metrics`, `rasters`, `chm_cell_m`, \
             `profile_cell_m`, `raster_tile_m` (from --set output.lass=true)"
                .to_string()
        )],
        "{e}"
    );
    // A value of the wrong type.
    let e = run_with(TWO_STAGES, &["output.las=ture"]).unwrap_err();
    assert_eq!(paths(&e), ["output.las"], "{e}");
    assert!(e.issues[0].location.is_none());
    assert!(
        e.issues[0].reason.contains("expected a boolean")
            && e.issues[0].reason.ends_with("(from --set output.las=ture)"),
        "{e}"
    );
    // A key the stage does not have, inside a tagged list entry.
    let e = run_with(TWO_STAGES, &["pipeline.stages[0].max_taps=128"]).unwrap_err();
    assert_eq!(paths(&e), ["pipeline.stages[0].max_taps"], "{e}");
    // A value out of range, found by the semantic checks.
    let e = run_with(TWO_STAGES, &["pipeline.stages[1].max_taps=0"]).unwrap_err();
    assert_eq!(paths(&e), ["pipeline.stages[1].max_taps"], "{e}");
    assert_eq!(e.issues[0].kind, IssueKind::Invalid);
    assert!(
        e.issues[0]
            .reason
            .ends_with("(from --set pipeline.stages[1].max_taps=0)")
    );
    // An index past the end, and text that is no override.
    let e = run_with(TWO_STAGES, &["pipeline.stages[2].max_taps=1"]).unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Override);
    assert_eq!(paths(&e), ["pipeline.stages"], "{e}");
    assert!(e.to_string().contains("has 2 entries"), "{e}");
    let e = run_with(TWO_STAGES, &["output.las"]).unwrap_err();
    assert_eq!(e.issues[0].kind, IssueKind::Override);
    // A problem in the file itself keeps its line and column beside an override.
    let e = run_with(
        &TWO_STAGES.replace("workers = 2", "workers = \"2\""),
        &["output.las=true"],
    )
    .unwrap_err();
    assert_eq!(issues(&e)[0].0, "pipeline.workers");
    assert_eq!(issues(&e)[0].1, Some((2, 11)), "{e}");
    // An override that repairs the file's problem is taken.
    let fixed = run_with(
        &TWO_STAGES.replace("workers = 2", "workers = \"2\""),
        &["pipeline.workers=2"],
    )
    .unwrap();
    assert_eq!(fixed, run(TWO_STAGES).unwrap());
}
