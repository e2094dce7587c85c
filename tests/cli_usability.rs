//! What a new user meets first, through the real binary: `--set KEY=VALUE` on `replay` and
//! `run` (the outputs change; a misspelt key or a bad value exits 2 naming the field), the
//! descriptor tables of `inspect` on real LAS and PulseWaves files, and the shell completions
//! and manual pages generated from the command line.

mod common;

use std::path::Path;
use std::process::Output;

use common::{fixture, fwlidar, text};

fn assert_usage_error(o: &Output, needles: &[&str]) {
    let err = text(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "stderr: {err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
}

fn replay(out: &Path, sets: &[&str]) -> Output {
    let mut args = vec!["replay", "--out", out.to_str().unwrap(), "--no-progress"];
    for s in sets {
        args.extend(["--set", s]);
    }
    fwlidar(&args)
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap()
}

#[test]
fn set_overrides_change_what_replay_writes() {
    let dir = tempfile::tempdir().unwrap();
    // The same replay, LAS on and voxels off, then the other way round: each override is
    // explicit, so the test does not depend on the defaults of config/replay.toml.
    let a = dir.path().join("a");
    let o = replay(&a, &["output.las=true", "voxels.enabled=false"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(a.join("returns.las").is_file(), "--set output.las=true");
    assert!(
        !a.join("voxels.zarr").exists(),
        "--set voxels.enabled=false"
    );
    let las = std::fs::read(a.join("returns.las")).unwrap();
    assert_eq!(&las[..4], b"LASF");

    let b = dir.path().join("b");
    let o = replay(&b, &["output.las=false", "voxels.enabled=true"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(!b.join("returns.las").exists());
    assert!(b.join("voxels.zarr").is_dir());

    // An index into the stage list: a one-tap kernel limit makes every outgoing pulse too long
    // for the deconvolve stage, which (long_kernel = "drop") drops the pulses as
    // `kernel_over_max_taps`; a later --set wins.
    let c = dir.path().join("c");
    let o = replay(
        &c,
        &[
            "voxels.enabled=false",
            "pipeline.stages[1].max_taps=128",
            "pipeline.stages[1].max_taps=1",
            "pipeline.stages[1].long_kernel=drop",
        ],
    );
    assert!(o.status.success(), "{}", text(&o.stderr));
    let s = summary(&c);
    let deconvolve = &s["stages"][1];
    assert_eq!(deconvolve["name"], "deconvolve");
    let received = deconvolve["received"].as_u64().unwrap();
    assert!(received > 0);
    assert_eq!(
        deconvolve["dropped"]["kernel_over_max_taps"].as_u64(),
        Some(received),
        "{s}"
    );
    // Without it, nothing is dropped there.
    let s = summary(&b);
    assert_eq!(
        s["stages"][1]["dropped"]["bad_kernel"].as_u64(),
        None,
        "{s}"
    );
}

#[test]
fn set_errors_exit_2_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    // A misspelt key.
    let o = replay(&out, &["output.lass=true"]);
    assert_usage_error(
        &o,
        &[
            "config/replay.toml (embedded)",
            "output.lass",
            "unknown key `lass`",
            "(from --set output.lass=true)",
        ],
    );
    // A value of the wrong type (a bare word is a string).
    let o = replay(&out, &["output.las=yes"]);
    assert_usage_error(
        &o,
        &[
            "output.las:",
            "expected a boolean",
            "(from --set output.las=yes)",
        ],
    );
    // A value out of range, found by the semantic checks.
    let o = replay(&out, &["pipeline.stages[1].max_taps=0"]);
    assert_usage_error(&o, &["pipeline.stages[1].max_taps", "max_taps=0"]);
    // A stage that does not have the key.
    let o = replay(&out, &["pipeline.stages[0].max_taps=8"]);
    assert_usage_error(&o, &["pipeline.stages[0].max_taps", "unknown key"]);
    // An index past the end, and text that is no override.
    let o = replay(&out, &["pipeline.stages[99].max_taps=8"]);
    assert_usage_error(&o, &["pipeline.stages", "there is no index 99"]);
    let o = replay(&out, &["output.las"]);
    assert_usage_error(&o, &["--set `output.las` is not KEY=VALUE"]);
    assert!(!out.exists(), "a refused configuration writes nothing");

    // With --config FILE the file is named, and a problem in the file keeps its line.
    let cfg = dir.path().join("run.toml");
    std::fs::write(&cfg, "[output]\nreturns = 1\n").unwrap();
    let o = fwlidar(&[
        "replay",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--set",
        "output.waveforms=\"no\"",
    ]);
    assert_usage_error(
        &o,
        &[
            &format!("{}:2:11: output.returns:", cfg.display()),
            &format!("{}: output.waveforms:", cfg.display()),
            "(from --set output.waveforms=\"no\")",
        ],
    );
    // The same override repairs the file.
    let o = fwlidar(&[
        "replay",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
        "--set",
        "output.returns=true",
        "--set",
        "voxels.enabled=false",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));

    // The daemon checks its overrides before it opens anything.
    let o = fwlidar(&[
        "run",
        "--config",
        "config/onboard.toml",
        "--out",
        dir.path().join("daemon").to_str().unwrap(),
        "--set",
        "daemon.frame=\"udp:127.0.0.1:0\"",
    ]);
    assert_usage_error(&o, &["config/onboard.toml", "daemon.frame", "unknown key"]);
    let o = fwlidar(&[
        "run",
        "--config",
        "config/onboard.toml",
        "--out",
        dir.path().join("daemon").to_str().unwrap(),
        "--set",
        "voxels.enabled=maybe",
    ]);
    assert_usage_error(&o, &["voxels.enabled", "expected a boolean"]);
    assert!(!dir.path().join("daemon").exists());
}

/// Lines of `inspect` output that follow `title`, up to the next line with less indentation.
fn section<'t>(out: &'t str, title: &str) -> Vec<&'t str> {
    let mut lines = out.lines().skip_while(|l| l.trim() != title);
    let Some(head) = lines.next() else {
        panic!("no {title:?} in:\n{out}");
    };
    let indent = head.len() - head.trim_start().len();
    lines
        .take_while(|l| l.len() - l.trim_start().len() > indent)
        .collect()
}

fn words(line: &str) -> Vec<&str> {
    line.split_whitespace().collect()
}

#[test]
fn inspect_shows_las_descriptors_as_a_table() {
    let las = fixture("waveform/riegl_q680i/100429_152240_2535pt_UTM.las");
    let o = fwlidar(&["inspect", las.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    assert!(
        !out.contains("{\""),
        "no JSON blob in the human output:\n{out}"
    );
    let table = section(&out, "wave packet descriptors:");
    // The RIEGL file defines 100 descriptors: 1 (60 samples) and 2 (120 samples) are used,
    // 3 to 100 are empty and identical, so they share a row.
    assert_eq!(
        words(table[0]),
        [
            "index",
            "bits",
            "compression",
            "samples",
            "interval",
            "(ps)",
            "gain",
            "(V/count)",
            "offset",
            "(V)"
        ]
    );
    assert_eq!(table.len(), 4, "{out}");
    assert_eq!(words(table[1]), ["1", "16", "0", "60", "1000", "1", "0"]);
    assert_eq!(words(table[2]), ["2", "16", "0", "120", "1000", "1", "0"]);
    assert_eq!(words(table[3]), ["3-100", "16", "0", "0", "0", "1", "0"]);
    // Aligned: every row as long as the header up to the last column's right edge.
    let ends: Vec<usize> = table.iter().map(|l| l.len()).collect();
    assert!(ends.iter().all(|&e| e == ends[0]), "{table:#?}");
    // Plain values one per line.
    assert!(out.lines().any(|l| words(l) == ["points", "2535"]), "{out}");

    // --json keeps the whole report, the descriptors included.
    let o = fwlidar(&["inspect", "--json", las.to_str().unwrap()]);
    assert!(o.status.success());
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let d = j["report"]["wave_packet_descriptors"].as_array().unwrap();
    assert_eq!(d.len(), 100);
    assert_eq!(d[1]["index"], 2);
    assert_eq!(d[1]["samples"], 120);
    assert_eq!(d[1]["temporal_spacing_ps"], 1000);
    assert_eq!(j["report"]["descriptors"], 100);
}

#[test]
fn inspect_shows_pulsewaves_descriptors_and_scanners_as_tables() {
    let pls = fixture("waveform/pulsewaves/test.pls");
    let o = fwlidar(&["inspect", pls.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    assert!(
        !out.contains("{\""),
        "no JSON blob in the human output:\n{out}"
    );
    let table = section(&out, "pulse descriptors:");
    assert_eq!(
        words(table[0])[..9],
        [
            "index", "scanner", "sampling", "type", "channel", "bits", "segments", "samples",
            "interval"
        ]
    );
    // Nine descriptors with 1 + 2·1 + ... samplings: one row per sampling.
    assert_eq!(table.len(), 1 + 1 + 2 * 4 + 3 * 4, "{out}");
    assert_eq!(
        words(table[1]),
        [
            "1",
            "1",
            "1",
            "outgoing",
            "0",
            "8",
            "1",
            "24",
            "1",
            "-",
            "only",
            "outgoing,",
            "no",
            "returning"
        ]
    );
    // Descriptor 9's returning samplings vary in segments and samples; its second and third
    // rows leave the index blank.
    let last = table[table.len() - 1];
    assert_eq!(
        words(last),
        ["3", "returning", "1", "8", "variable", "variable", "1", "-"]
    );
    let header_index = table[0].find("sampling").unwrap();
    assert_eq!(&last[..header_index].trim(), &"", "{last:?}");
    // The scanner record, a column per scanner.
    let scanners = section(&out, "scanners:");
    assert_eq!(words(scanners[0]), ["scanner", "1"]);
    assert!(
        scanners
            .iter()
            .any(|l| words(l) == ["instrument", "RIEGL", "Q560"]),
        "{scanners:#?}"
    );
    assert!(
        scanners
            .iter()
            .any(|l| words(l) == ["beam_divergence_mrad", "0.3"]),
        "f32 values shown to 7 digits: {scanners:#?}"
    );
    assert!(
        out.lines().any(|l| words(l) == ["crs", "EPSG:32613"]),
        "{out}"
    );

    // The RIEGL PulseWaves file: 12 descriptors, its warnings one per line.
    let pls = fixture("waveform/riegl_q680i/100429_152240_2535pt_UTM.pls");
    let o = fwlidar(&["inspect", pls.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    let table = section(&out, "pulse descriptors:");
    let index_end = table[0].find("index").unwrap() + "index".len();
    let firsts: Vec<&str> = table[1..]
        .iter()
        .filter(|l| !l[..index_end].trim().is_empty())
        .map(|l| words(l)[0])
        .collect();
    assert_eq!(firsts, (1..=12).map(|i| i.to_string()).collect::<Vec<_>>());
    let warnings = section(&out, "warnings:");
    assert_eq!(warnings.len(), 2, "{out}");
    assert!(warnings[0].contains("UTM_North zone 33"));

    let o = fwlidar(&["inspect", "--json", pls.to_str().unwrap()]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["report"]["descriptors"].as_array().unwrap().len(), 12);
}

#[test]
fn bash_completions_are_valid_and_name_every_command() {
    let o = fwlidar(&["completions", "bash"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let script = text(&o.stdout);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fwlidar.bash");
    std::fs::write(&path, &script).unwrap();
    let check = std::process::Command::new("bash")
        .arg("-n")
        .arg(&path)
        .output()
        .expect("bash");
    assert!(check.status.success(), "bash -n: {}", text(&check.stderr));
    for cmd in [
        "run",
        "replay",
        "repair",
        "simulate",
        "validate",
        "inspect",
        "import",
        "process",
        "tradeoff",
        "merge",
        "biomass",
        "metrics",
        "metrics-plot",
        "completions",
        "man",
    ] {
        assert!(
            script.contains(&format!("fwlidar__{cmd})"))
                || script.contains(&format!("fwlidar,{cmd})")),
            "no completion for {cmd}"
        );
    }
    // Options of a subcommand, --set included, and the shells' names.
    assert!(script.contains("--set"));
    assert!(
        script.contains("bash zsh fish") || script.contains("elvish"),
        "{script}"
    );
    // Loaded into bash, it registers the completion function.
    let load = std::process::Command::new("bash")
        .arg("-c")
        .arg(format!("source {} && complete -p fwlidar", path.display()))
        .output()
        .expect("bash");
    assert!(load.status.success(), "{}", text(&load.stderr));
    assert!(
        text(&load.stdout).contains("fwlidar"),
        "{}",
        text(&load.stdout)
    );

    for shell in ["zsh", "fish", "elvish", "powershell"] {
        let o = fwlidar(&["completions", shell]);
        assert!(o.status.success(), "{shell}: {}", text(&o.stderr));
        let s = text(&o.stdout);
        assert!(s.contains("replay") && s.contains("--set"), "{shell}");
    }
    let o = fwlidar(&["completions", "tcsh"]);
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn man_pages_render_and_are_never_written_over() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("man1");
    let o = fwlidar(&["man", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    for want in [
        "fwlidar.1",
        "fwlidar-replay.1",
        "fwlidar-man.1",
        "fwlidar-run.1",
        "fwlidar-biomass.1",
        "fwlidar-metrics.1",
        "fwlidar-trees.1",
        "fwlidar-response.1",
        "fwlidar-compare.1",
    ] {
        assert!(names.iter().any(|n| n == want), "{want} missing: {names:?}");
    }
    assert!(!names.iter().any(|n| n == "fwlidar-help.1"), "{names:?}");
    assert_eq!(names.len(), 1 + 19, "{names:?}");

    let main = std::fs::read_to_string(out.join("fwlidar.1")).unwrap();
    assert!(
        main.starts_with(".ie") || main.contains(".TH fwlidar 1"),
        "{main}"
    );
    for section in [
        ".SH NAME",
        ".SH SYNOPSIS",
        ".SH DESCRIPTION",
        ".SH OPTIONS",
        ".SH SUBCOMMANDS",
    ] {
        assert!(main.contains(section), "{section} missing");
    }
    let replay = std::fs::read_to_string(out.join("fwlidar-replay.1")).unwrap();
    assert!(replay.contains(".TH fwlidar-replay 1"), "{replay}");
    assert!(replay.contains("\\-\\-set"), "{replay}");

    // Rendered by groff (what `man -l` runs).
    {
        let groff = common::tool("groff", "groff-base", "groff renders our manual pages");
        let r = std::process::Command::new(groff)
            .args(["-man", "-Tutf8", "-Wall"])
            .arg(out.join("fwlidar.1"))
            .output()
            .expect("run groff");
        assert!(r.status.success(), "{}", text(&r.stderr));
        let page = text(&r.stdout);
        // groff -Tutf8 overstrikes bold text; compare without the backspaces.
        let plain: String = {
            let mut s = String::new();
            for ch in page.chars() {
                if ch == '\u{8}' {
                    s.pop();
                } else {
                    s.push(ch);
                }
            }
            s
        };
        for want in [
            "NAME",
            "SYNOPSIS",
            "replay",
            "completions",
            "streaming processing",
        ] {
            assert!(
                plain.contains(want),
                "{want} missing from the rendered page:\n{plain}"
            );
        }
        assert!(
            text(&r.stderr).trim().is_empty(),
            "groff warns: {}",
            text(&r.stderr)
        );
    }

    // A second run refuses, names the pages, and leaves them as they were.
    std::fs::write(out.join("fwlidar-merge.1"), "mine").unwrap();
    let o = fwlidar(&["man", "--out", out.to_str().unwrap()]);
    assert_usage_error(&o, &["fwlidar.1", "fwlidar-merge.1", "never written over"]);
    assert_eq!(
        std::fs::read_to_string(out.join("fwlidar-merge.1")).unwrap(),
        "mine"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("fwlidar.1")).unwrap(),
        main
    );
    // One page in the way is enough to write nothing.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("fwlidar-run.1"), "mine").unwrap();
    let o = fwlidar(&["man", "--out", other.to_str().unwrap()]);
    assert_usage_error(&o, &["fwlidar-run.1"]);
    assert_eq!(std::fs::read_dir(&other).unwrap().count(), 1);
}

/// The README's first command, as a new user runs it (stdout and stderr not a terminal): the
/// summary names every file and folder it wrote, fits 100 columns, and stderr carries no
/// colour codes nor a debug-formatted field.
#[test]
fn the_first_run_names_every_output_it_wrote_plainly() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let o = fwlidar(&[
        "replay",
        "replay/two_layer.fwcap",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let stdout = text(&o.stdout);
    let written: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    for name in [
        "returns.las",
        "waveforms.npy",
        "waveform_index.npy",
        "pulse_metrics.csv",
        "rasters",
        "voxels.zarr",
        "summary.json",
    ] {
        assert!(
            written.iter().any(|w| w == name),
            "{name} not written: {written:?}"
        );
    }
    for name in &written {
        let named = common::summary_output(&stdout, name)
            .or_else(|| common::summary_output(&stdout, &format!("{name}/")))
            .is_some()
            || stdout.contains(&format!("{name} indexes"));
        assert!(named, "the summary does not name {name}:\n{stdout}");
    }
    for line in stdout.lines() {
        assert!(
            line.chars().count() <= 100,
            "a summary line over 100 columns ({}):\n{line}",
            line.chars().count()
        );
    }
    let voxels = common::summary_output(&stdout, "voxels.zarr").unwrap();
    assert!(!voxels.contains("compressed into"), "{voxels}");
    let err = text(&o.stderr);
    assert!(!err.contains('\u{1b}'), "colour codes on stderr: {err:?}");
    for info in err.lines().filter(|l| l.contains(" INFO ")) {
        assert!(
            !info.contains('='),
            "an INFO line with key=value fields instead of words: {info}"
        );
    }
}

/// `replay` with no file, run from a folder that is not a clone: the sample is found in the
/// source tree the program was built from (its path printed), and the help says so; the
/// one-liners of the commands that read waveform files name GEDI L1B; `--out` states its
/// default.
#[test]
fn help_matches_the_program_and_replay_finds_its_sample_from_anywhere() {
    let elsewhere = tempfile::tempdir().unwrap();
    let out = elsewhere.path().join("o");
    let o = std::process::Command::new(common::BIN)
        .args(["replay", "--no-progress", "--out"])
        .arg(&out)
        .current_dir(elsewhere.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    let sample = Path::new(common::ROOT).join("replay/two_layer.fwcap");
    assert!(
        text(&o.stdout).contains(&sample.display().to_string()),
        "{}",
        text(&o.stdout)
    );
    assert!(out.join("summary.json").is_file());

    let top = text(&fwlidar(&["--help"]).stdout);
    for cmd in ["replay", "inspect", "import"] {
        let line = top
            .lines()
            .find(|l| l.trim_start().starts_with(&format!("{cmd} ")))
            .unwrap_or_else(|| panic!("no {cmd} in:\n{top}"));
        assert!(line.contains("GEDI L1B"), "{line}");
    }
    let replay_help = text(&fwlidar(&["replay", "--help"]).stdout);
    assert!(
        replay_help.contains("replay/two_layer.fwcap"),
        "{replay_help}"
    );
    assert!(
        replay_help.contains("`out` in the embedded configuration"),
        "{replay_help}"
    );
}
