//! `fwlidar campaign` (issue 22): four simulated survey lines that cross each other, planned,
//! run here with one and two processes and merge trees of different shapes: the mosaics are
//! byte-identical, and the store of one replay of the four lines in sequence (but its resume
//! records); split into shards (`replay --shard`), the same bytes again; a line whose replay was killed (no `done.json`, a half-written
//! folder) is replayed alone on the next run and the mosaic is again the same bytes; xarray +
//! dask read the mosaic lazily and reduce it chunk by chunk. Bad campaign files name the file
//! and the field.

mod common;

use std::path::Path;

fn run(file: &Path, local: &str, fan_in: &str) -> serde_json::Value {
    let o = common::fwlidar(&[
        "campaign",
        "run",
        file.to_str().unwrap(),
        "--local",
        local,
        "--fan-in",
        fan_in,
    ]);
    assert!(
        o.status.success(),
        "{}\n{}",
        common::text(&o.stdout),
        common::text(&o.stderr)
    );
    let report = file.parent().unwrap().join(if file.ends_with("a.toml") {
        "out_a/campaign.json"
    } else {
        "out_b/campaign.json"
    });
    serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap()
}

#[test]
fn the_mosaic_is_the_same_bytes_whatever_the_processes_merge_tree_and_a_killed_line() {
    let dir = tempfile::tempdir().unwrap();
    common::crossing_lines(dir.path());
    let a = common::crossing_campaign(dir.path(), "a.toml", "out_a");
    let b = common::crossing_campaign(dir.path(), "b.toml", "out_b");
    // The plan: four tasks.
    let o = common::fwlidar(&["campaign", "plan", a.to_str().unwrap()]);
    let plan = common::text(&o.stdout);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    assert_eq!(plan.matches("to run").count(), 4, "{plan}");
    // Two processes, pairwise merges (two levels) / one process, one merge of all four.
    let ra = run(&a, "2", "2");
    let rb = run(&b, "1", "8");
    assert_eq!(ra["merge"]["levels"], 2);
    assert_eq!(rb["merge"]["levels"], 1);
    let lines = ra["lines"].as_array().unwrap();
    assert_eq!(lines.len(), 4);
    for l in lines {
        assert_eq!(l["pulses_in"], 12000, "{l}");
        assert!(l["cpu_s"].as_f64().unwrap() > 0.0, "{l}");
        assert!(l["tiles"].as_u64().unwrap() > 10, "{l}");
        assert!(l["store_bytes"].as_u64().unwrap() > 1_000_000, "{l}");
        assert_eq!(l["bins_outside_grid"], 0, "{l}");
    }
    let mosaic_a = common::file_tree(&dir.path().join("out_a/mosaic.zarr"));
    let mosaic_b = common::file_tree(&dir.path().join("out_b/mosaic.zarr"));
    assert!(mosaic_a.len() > 10);
    assert!(mosaic_a == mosaic_b, "the mosaics differ");
    // The mosaic is the store of one replay of the four lines in sequence with the campaign's
    // run.toml: every file the same bytes, metadata included, but the tiles' resume records,
    // whose watermarks say when each tile closed (a merged store's are 0); those list the same
    // tiles and height chunks.
    let seq = common::sequential_replay(
        dir.path(),
        &dir.path().join("out_a/run.toml"),
        &dir.path().join("seq"),
    );
    common::assert_same_store_but_watermarks(&dir.path().join("out_a/mosaic.zarr"), &seq);
    // The metrics rasters of the mosaic, written by the merge.
    assert!(
        ra["metrics"]["cells_ok"][0].as_u64().unwrap() > 1000,
        "{}",
        ra["metrics"]
    );
    assert!(dir.path().join("out_a/rasters/chm.vrt").is_file());
    // Lines split into three shards each (`shard_gb`, `replay --shard i/3`): twelve tasks,
    // and the same mosaic bytes.
    let s = dir.path().join("s.toml");
    let text = std::fs::read_to_string(&a)
        .unwrap()
        .replace("out_a", "out_s");
    let bytes = std::fs::metadata(dir.path().join("lines/line0.fwcap"))
        .unwrap()
        .len() as f64;
    std::fs::write(&s, format!("{text}shard_gb = {}\n", bytes / 2.5e9)).unwrap();
    let o = common::fwlidar(&["campaign", "run", s.to_str().unwrap(), "--local", "2"]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let rs: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("out_s/campaign.json")).unwrap(),
    )
    .unwrap();
    let shards = rs["lines"].as_array().unwrap();
    assert_eq!(shards.len(), 12, "{rs}");
    assert_eq!(shards[1]["name"], "line0.shard2of3");
    assert_eq!(
        shards
            .iter()
            .map(|l| l["pulses_in"].as_u64().unwrap())
            .sum::<u64>(),
        48000
    );
    assert!(
        common::file_tree(&dir.path().join("out_s/mosaic.zarr")) == mosaic_a,
        "the mosaic of the shards differs"
    );
    // The lines cross: some tiles hold several lines, and the mosaic holds every line's
    // samples (its data equal a plain `fwlidar merge` of the line stores).
    let flat = dir.path().join("flat.zarr");
    let mut args = vec!["merge", "--no-progress", "--out", flat.to_str().unwrap()];
    let stores: Vec<String> = (0..4)
        .map(|i| {
            dir.path()
                .join(format!("out_a/lines/line{i}/voxels.zarr"))
                .display()
                .to_string()
        })
        .collect();
    args.extend(stores.iter().map(String::as_str));
    let o = common::fwlidar(&args);
    let said = common::text(&o.stdout);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let several: u64 = said
        .split('(')
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap();
    assert!(several > 0, "{said}");
    let flat_files = common::file_tree(&flat);
    for (p, bytes) in &mosaic_a {
        if p != Path::new("zarr.json") {
            let f = flat_files.iter().find(|(q, _)| q == p).unwrap();
            assert!(&f.1 == bytes, "{} differs from a plain merge", p.display());
        }
    }
    // xarray + dask open the mosaic lazily and reduce it chunk by chunk: its samples are the
    // lines' samples, every one.
    let mut args: Vec<String> = vec![
        "tests/python/read_mosaic_dask.py".into(),
        dir.path().join("out_a/mosaic.zarr").display().to_string(),
    ];
    args.extend(stores.iter().cloned());
    let o = std::process::Command::new(common::python())
        .args(&args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    eprintln!("{r}");
    assert_eq!(r["lazy"], true, "{r}");
    assert!(r["npartitions"].as_u64().unwrap() > 1, "{r}");
    let lines_total: u64 = r["line_samples"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert!(lines_total > 0);
    assert_eq!(r["mosaic_samples"].as_u64().unwrap(), lines_total, "{r}");
    // A killed line: its done marker gone and its store half-written. The next run replays it
    // alone and the mosaic is the same bytes.
    let line2 = dir.path().join("out_a/lines/line2");
    std::fs::remove_file(line2.join("done.json")).unwrap();
    std::fs::remove_dir_all(line2.join("voxels.zarr/pulse_count")).unwrap();
    let again = run(&a, "2", "3");
    let replayed: Vec<&str> = again["lines"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|l| l["ran"] == true)
        .map(|l| l["name"].as_str().unwrap())
        .collect();
    assert_eq!(replayed, ["line2"]);
    assert!(
        common::file_tree(&dir.path().join("out_a/mosaic.zarr")) == mosaic_b,
        "the mosaic after the killed line's rerun differs"
    );
    // The Slurm path without Slurm: the scripts `submit --dry-run` writes, their array tasks
    // run one by one as `campaign task`, then the merge job's `campaign merge`: the same bytes.
    let c = common::crossing_campaign(dir.path(), "c.toml", "out_c");
    let o = common::fwlidar(&[
        "campaign",
        "submit",
        c.to_str().unwrap(),
        "--dry-run",
        "--partition",
        "short",
        "--merge-nodes",
        "2",
    ]);
    let said = common::text(&o.stdout);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    assert!(said.contains("--dependency=afterok"), "{said}");
    let script = std::fs::read_to_string(dir.path().join("out_c/slurm/lines.sbatch")).unwrap();
    assert!(script.contains("#SBATCH --array=0,1,2,3"), "{script}");
    assert!(script.contains("#SBATCH --partition=short"), "{script}");
    assert!(script.contains("#SBATCH --mem="), "{script}");
    assert!(script.contains("campaign task"), "{script}");
    let merge = std::fs::read_to_string(dir.path().join("out_c/slurm/merge.sbatch")).unwrap();
    assert!(
        merge.contains("campaign merge") && merge.contains("--groups 2"),
        "{merge}"
    );
    // The merge spread over two nodes: an array of two group merges between lines and merge.
    let groups =
        std::fs::read_to_string(dir.path().join("out_c/slurm/merge_groups.sbatch")).unwrap();
    assert!(groups.contains("#SBATCH --array=0-1"), "{groups}");
    assert!(groups.contains("--groups 2 --group"), "{groups}");
    assert!(
        said.contains("afterok:<lines job>") && said.contains("afterok:<groups job>"),
        "{said}"
    );
    // The merge job refuses to run before the lines.
    let o = common::fwlidar(&["campaign", "merge", c.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(common::text(&o.stderr).contains("not done"));
    for i in [3, 1, 0, 2] {
        let idx = i.to_string();
        let o = common::fwlidar(&["campaign", "task", c.to_str().unwrap(), "--index", &idx]);
        assert!(o.status.success(), "{}", common::text(&o.stderr));
    }
    // A resubmission now has no array left: the merge job alone.
    let o = common::fwlidar(&["campaign", "submit", c.to_str().unwrap(), "--dry-run"]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    assert!(!common::text(&o.stdout).contains("lines.sbatch"));
    // The two group merges (what the array's tasks run), then the last merge.
    for g in ["1", "0"] {
        let o = common::fwlidar(&[
            "campaign",
            "merge",
            c.to_str().unwrap(),
            "--groups",
            "2",
            "--group",
            g,
        ]);
        assert!(o.status.success(), "{}", common::text(&o.stderr));
        assert!(
            common::text(&o.stdout).contains("2 tasks"),
            "{}",
            common::text(&o.stdout)
        );
    }
    assert!(
        dir.path()
            .join("out_c/merge/group0of2.zarr/zarr.json")
            .is_file()
    );
    let o = common::fwlidar(&[
        "campaign",
        "merge",
        c.to_str().unwrap(),
        "--groups",
        "2",
        "--processes",
        "2",
    ]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let rc: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("out_c/campaign.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(rc["merge"]["groups"], 2, "{rc}");
    assert_eq!(rc["merge"]["groups_merged_here"], 0, "{rc}");
    assert!(!dir.path().join("out_c/merge").exists());
    assert!(
        common::file_tree(&dir.path().join("out_c/mosaic.zarr")) == mosaic_b,
        "the mosaic of the task-by-task run differs"
    );
}

/// Runs `fwlidar args`, which must exit with 2 and say every one of `words` on stderr.
fn refused(args: &[&str], words: &[&str]) {
    let o = common::fwlidar(args);
    let e = common::text(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
    for w in words {
        assert!(e.contains(w), "{args:?} does not say {w:?}: {e}");
    }
}

#[test]
fn bad_campaign_files_name_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("c.toml");
    let file = f.to_str().unwrap();
    let campaign = |body: &str| std::fs::write(&f, format!("[campaign]\n{body}")).unwrap();
    campaign("name = \"x\"\ncaptures = [\"nothing/*.fwcap\"]\nout = \"o\"\nepsg = 32736\n");
    refused(
        &["campaign", "plan", file],
        &["c.toml", "campaign.captures[0]"],
    );
    campaign("name = \"x y\"\ncaptures = []\nout = \"o\"\nepsg = 32736\nlines = 3\n");
    refused(&["campaign", "plan", file], &["c.toml", "lines"]);
    // A configuration without voxels cannot make a mosaic.
    std::fs::create_dir_all(dir.path().join("l")).unwrap();
    std::fs::copy("replay/two_layer.fwcap", dir.path().join("l/a.fwcap")).unwrap();
    campaign(
        "name = \"x\"\ncaptures = [\"l/a.fwcap\"]\nset = [\"voxels.enabled=false\"]\n\
         out = \"o\"\nepsg = 32736\n",
    );
    refused(&["campaign", "run", file], &["campaign.config", "voxels"]);
    assert!(!dir.path().join("o").exists());
    campaign("name = \"x\"\ncaptures = [\"l/a.fwcap\"]\nout = \"o\"\nepsg = 32736\nshard_gb = 0\n");
    refused(
        &["campaign", "plan", file],
        &["c.toml", "campaign.shard_gb"],
    );
    // `replay --shard` takes i/n with 1 <= i <= n; several inputs need one named CRS.
    let out = dir.path().join("r");
    let out_s = out.to_str().unwrap();
    let cap = "replay/two_layer.fwcap";
    refused(
        &["replay", cap, "--shard", "4/3", "--out", out_s],
        &["--shard", "i/n"],
    );
    refused(
        &["replay", cap, "--shard", "1/100000000", "--out", out_s],
        &["--shard 1/100000000", "holds none"],
    );
    refused(&["replay", cap, cap, "--out", out_s], &["output_epsg"]);
    assert!(!out.exists());
    // Merge groups: 2 or more, fewer than the tasks.
    campaign("name = \"x\"\ncaptures = [\"l/a.fwcap\"]\nout = \"o\"\nepsg = 32736\n");
    let o = common::fwlidar(&["campaign", "merge", file, "--groups", "2", "--group", "0"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(common::text(&o.stderr).contains("does not exist"));
}
