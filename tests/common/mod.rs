//! Helpers shared by the integration tests: the real binary, and the real-data fixtures.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `fwlidar` binary built for these tests.
pub const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");
/// The repository root.
pub const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The `replay` flags that ask for the text outputs (`pulses.csv` + `waveforms.csv`,
/// `returns.csv`) beside the default binary ones, for tests that read them.
pub const CSV_OUTPUTS: [&str; 4] = [
    "--set",
    "output.waveform_format=csv",
    "--set",
    "output.returns=true",
];

/// Runs `fwlidar` with `args` from the repository root.
pub fn fwlidar(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .current_dir(ROOT)
        .output()
        .expect("run fwlidar")
}

/// Bytes as text, lossily.
pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A real-data fixture file: `$FWLIDAR_FIXTURES/<rel>`, else `<root>/tests/data/<rel>` (the
/// repository carries every file its tests read; `tests/data/MANIFEST.md`). Panics naming the
/// missing file.
pub fn fixture(rel: &str) -> PathBuf {
    fwlidar::fixtures::path(rel)
}

/// Runs the benchmark script `tests/python/<script>` with `--fwlidar <the test binary>
/// --workdir <dir>` and then `args`; returns (exit code, stdout, stderr).
pub fn python_bench(script: &str, dir: &Path, args: &[&str]) -> (i32, String, String) {
    let o = Command::new(python())
        .arg(Path::new(ROOT).join("tests/python").join(script))
        .args(["--fwlidar", BIN, "--workdir"])
        .arg(dir)
        .args(args)
        .output()
        .expect("run python");
    (
        o.status.code().unwrap_or(-1),
        text(&o.stdout),
        text(&o.stderr),
    )
}

/// The README's test command: it installs every program and Python package the tests use
/// (apt packages, the `.venv` of `tests/python/requirements.txt`) and then runs the suite. A
/// test whose tool is missing fails naming it, never passes silently.
pub const SETUP: &str = "tests/run.sh";

/// The full path of the program `name` (from the Debian package `package`), looked for on the
/// PATH and in the sbin folders (daemons live in /usr/sbin, which a user's PATH may lack).
/// Panics saying what needs it and the command that installs it.
pub fn tool(name: &str, package: &str, why: &str) -> PathBuf {
    find_tool(name).unwrap_or_else(|| {
        panic!(
            "`{name}` (Debian package {package}) is not installed: {why}; run `{SETUP}` (the \
             README's test command installs it and the other tools the tests use)"
        )
    })
}

/// The full path of `name` on the PATH or in the sbin folders, if it is there.
pub fn find_tool(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin", "/sbin", "/usr/local/sbin"].map(PathBuf::from))
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// The Python with the real readers of our outputs and the reference implementations
/// (`tests/python/requirements.txt`): `$FWLIDAR_PYTHON`, else `.venv/bin/python`, as
/// [`SETUP`] makes it. Panics naming the command when it is missing.
pub fn python() -> PathBuf {
    if let Ok(p) = std::env::var("FWLIDAR_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = Path::new(ROOT).join(".venv/bin/python");
    assert!(
        venv.exists(),
        "this check reads our outputs with the field's Python readers, and {} is missing: run \
         `{SETUP}` (it creates .venv with the packages of tests/python/requirements.txt), or \
         set FWLIDAR_PYTHON to a Python that has them",
        venv.display()
    );
    venv
}

/// [`python()`], checked to import every one of `modules`; panics naming the missing ones and
/// the command that installs them.
pub fn python_with(modules: &[&str]) -> PathBuf {
    let py = python();
    let probe = format!("import {}", modules.join(", "));
    let o = Command::new(&py)
        .args(["-c", &probe])
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}; run `{SETUP}`", py.display()));
    assert!(
        o.status.success(),
        "{} cannot `{probe}`: run `{SETUP}` (it installs tests/python/requirements.txt into \
         .venv): {}",
        py.display(),
        text(&o.stderr).lines().last().unwrap_or("")
    );
    py
}

/// `gdalinfo -json FILE`: GDAL's own reading of a raster or VRT we wrote. Panics when gdalinfo
/// is missing (naming [`SETUP`]) or refuses the file.
pub fn gdalinfo_json(path: &Path) -> serde_json::Value {
    let gdal = tool(
        "gdalinfo",
        "gdal-bin",
        "GDAL opens our rasters in this check",
    );
    let o = Command::new(gdal)
        .arg("-json")
        .arg(path)
        .output()
        .expect("run gdalinfo");
    assert!(
        o.status.success(),
        "gdalinfo {} failed: {}",
        path.display(),
        text(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("gdalinfo prints JSON")
}

/// A tmpfs mounted on a folder for one test (a small disk to fill, a read-only file system
/// that root cannot write either); unmounted when dropped. Mounting needs root, as the README's
/// test command runs; a machine that refuses it fails the test, saying so.
pub struct Tmpfs(PathBuf);

impl Tmpfs {
    /// Mounts a tmpfs of `size` (mount's syntax: `48k`) on `dir`, which is made.
    pub fn mount(dir: &Path, size: &str) -> Tmpfs {
        std::fs::create_dir_all(dir).unwrap();
        let o = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir)
            .output()
            .expect("run mount");
        assert!(
            o.status.success(),
            "this check mounts a {size} tmpfs on {} and needs root to (run `{SETUP}` as root): {}",
            dir.display(),
            text(&o.stderr)
        );
        Tmpfs(dir.to_path_buf())
    }

    /// Remounts it read-only: nobody, root included, may write it afterwards.
    pub fn read_only(&self) {
        let o = Command::new("mount")
            .args(["-o", "remount,ro"])
            .arg(&self.0)
            .output()
            .expect("run mount");
        assert!(o.status.success(), "remount ro: {}", text(&o.stderr));
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).output();
    }
}

/// proptest's configuration for `cases` cases whose failures are kept in
/// `proptest-regressions/tests/<name>.txt` (committed with the fix, as the crate's own unit
/// tests keep theirs there), not beside the test's source: a failing run leaves nothing new in
/// `tests/`.
pub fn proptest_cases(cases: u32, regressions: &'static str) -> proptest::test_runner::Config {
    proptest::test_runner::Config {
        cases,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::Direct(regressions),
        )),
        ..proptest::test_runner::Config::default()
    }
}

/// What a run's printed summary says of the output `name` (`returns.las`, `voxels.zarr`, ...):
/// the text after the name on its line of the "written in DIR:" block, if the block names it.
pub fn summary_output<'a>(stdout: &'a str, name: &str) -> Option<&'a str> {
    stdout.lines().find_map(|l| {
        l.strip_prefix("    ")?
            .strip_prefix(name)
            .filter(|rest| rest.starts_with(' '))
            .map(str::trim)
    })
}

/// The real RIEGL waveform LAS fixture (LAS 1.4, point format 9, packets in the `.wdp`).
pub const RIEGL_LAS: &str = "waveform/riegl_q680i/100429_152240_2535pt_UTM.las";

/// LAZ copies of the real RIEGL fixture written by the real LAZ writers
/// (`tests/python/write_laz.py`: laspy and lazrs), each with the fixture's `.wdp` beside it, in
/// `dir` (made anew): `r9.laz` (format 9, one fixed-size chunk), `r9v.laz` (format 9,
/// variable-size chunks of 500 points), `r4.las` and `r4.laz` (LAS 1.3 format 4, converted by
/// laspy). Returns the script's JSON line (`{"r9.laz": [point format byte, chunk size,
/// variable], ...}`).
pub fn write_laz_copies(dir: &Path) -> serde_json::Value {
    let las = fixture(RIEGL_LAS);
    let wdp = las.with_extension("wdp");
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).unwrap();
    let o = Command::new(python())
        .arg(Path::new(ROOT).join("tests/python/write_laz.py"))
        .arg(&las)
        .arg(dir)
        .output()
        .expect("run python");
    assert!(
        o.status.success(),
        "write_laz.py failed: {}{}",
        text(&o.stdout),
        text(&o.stderr)
    );
    for stem in ["r9", "r9v", "r4"] {
        let to = dir.join(format!("{stem}.wdp"));
        std::fs::write(&to, std::fs::read(&wdp).unwrap()).unwrap();
    }
    serde_json::from_slice(&o.stdout).expect("write_laz.py prints one JSON line")
}

/// Writes a Float32 GeoTIFF DEM in UTM 36S (EPSG:32736, the simulated scenes' zone) of
/// `width` × `height` 1 m pixels, its top-left corner at (`x0`, `y0`), each pixel the height
/// `z(x, y)` at its centre (m); `-9999` is the stated nodata.
pub fn write_utm36s_dem(
    path: &Path,
    (x0, y0): (f64, f64),
    (width, height): (u32, u32),
    mut z: impl FnMut(f64, f64) -> f32,
) {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    let mut data = Vec::with_capacity((width * height) as usize);
    for row in 0..height {
        for col in 0..width {
            data.push(z(x0 + f64::from(col) + 0.5, y0 - f64::from(row) - 0.5));
        }
    }
    let f = std::fs::File::create(path).unwrap();
    let mut enc = TiffEncoder::new(f).unwrap();
    let mut img = enc.new_image::<Gray32Float>(width, height).unwrap();
    let e = img.encoder();
    e.write_tag(Tag::ModelPixelScaleTag, &[1.0f64, 1.0, 0.0][..])
        .unwrap();
    e.write_tag(Tag::ModelTiepointTag, &[0.0f64, 0.0, 0.0, x0, y0, 0.0][..])
        .unwrap();
    e.write_tag(
        Tag::GeoKeyDirectoryTag,
        &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32736][..],
    )
    .unwrap();
    e.write_tag(Tag::GdalNodata, "-9999").unwrap();
    img.write_data(&data).unwrap();
}

/// The tracks (start, end in m, scene coordinates) of four survey lines that cross at the
/// origin: the campaign tests' flight lines.
pub const CROSSING_TRACKS: [(&str, &str); 4] = [
    ("[-1.0, 0.0]", "[300.0, 0.0]"),
    ("[0.0, -1.0]", "[0.0, 300.0]"),
    ("[-1.0, -1.0]", "[200.0, 200.0]"),
    ("[1.0, -1.0]", "[-200.0, 200.0]"),
];

/// Simulated survey lines along `tracks` (`config/scenes/survey_line.toml`, 12 000 pulses
/// each), as `dir/lines/line<i>.fwcap`.
pub fn survey_lines(dir: &Path, tracks: &[(&str, &str)]) {
    std::fs::create_dir_all(dir.join("lines")).unwrap();
    for (i, (a, b)) in tracks.iter().enumerate() {
        let cap = dir.join(format!("lines/line{i}.fwcap"));
        let set = format!("flight.lines=[{{start_m={a}, end_m={b}}}]");
        let o = fwlidar(&[
            "simulate",
            "--scene",
            "config/scenes/survey_line.toml",
            "--pulses",
            "12000",
            "--no-truth-voxels",
            "--out",
            cap.to_str().unwrap(),
            "--set",
            &set,
        ]);
        assert!(o.status.success(), "{}", text(&o.stderr));
    }
}

/// The four crossing lines ([`CROSSING_TRACKS`]) as `dir/lines/line0..3.fwcap`.
pub fn crossing_lines(dir: &Path) {
    survey_lines(dir, &CROSSING_TRACKS);
}

/// A campaign file `dir/name` over those lines, writing into `dir/out` (voxels only).
pub fn crossing_campaign(dir: &Path, name: &str, out: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(
        &p,
        format!(
            "[campaign]\nname = \"crossing\"\ncaptures = [\"lines/line?.fwcap\"]\n\
             set = [\"output.waveforms=false\", \"output.las=false\", \"output.rasters=false\"]\n\
             out = \"{out}\"\nepsg = 32736\n"
        ),
    )
    .unwrap();
    p
}

/// Every file under `dir` with its bytes, by relative path, sorted.
pub fn file_tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    out.sort();
    out
}

/// One `fwlidar replay` of the four crossing lines (`crossing_lines`) in sequence into
/// `out`, with the campaign's `run.toml`: the store a campaign's mosaic must equal.
pub fn sequential_replay(dir: &Path, run_toml: &Path, out: &Path) -> PathBuf {
    let caps: Vec<String> = (0..4)
        .map(|i| {
            dir.join(format!("lines/line{i}.fwcap"))
                .display()
                .to_string()
        })
        .collect();
    let mut args = vec!["replay"];
    args.extend(caps.iter().map(String::as_str));
    args.extend([
        "--config",
        run_toml.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    let o = fwlidar(&args);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let said = text(&o.stdout);
    assert!(said.contains("48000 in, 48000 out"), "{said}");
    out.join("voxels.zarr")
}

/// The tiles a voxel store has committed, with their watermarks and height chunks, read
/// without opening the store (a run may be writing it): its tile records (a file per tile) or
/// its journal (tiles grouped into shard files; a torn last line is not committed, and a
/// batch counts once its shards are renamed into place, as readers see them).
pub fn committed_tiles(store: &Path) -> BTreeMap<[i64; 2], (u64, Vec<u32>)> {
    let mut out = BTreeMap::new();
    if let Ok(dir) = std::fs::read_dir(store.join("fwlidar_state/tiles")) {
        for e in dir.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            let Some((x, y)) = name.split_once('_') else {
                continue;
            };
            let (Ok(x), Ok(y)) = (x.parse(), y.parse()) else {
                continue; // `TX_TY.partial`: being written
            };
            let Ok(v) = serde_json::from_slice::<serde_json::Value>(
                &std::fs::read(e.path()).unwrap_or_default(),
            ) else {
                continue;
            };
            if v["pending"].as_bool() == Some(true) {
                continue;
            }
            let chunks = v["chunks"].as_array().map_or(vec![0], |c| {
                c.iter().map(|k| k.as_u64().unwrap() as u32).collect()
            });
            out.insert([x, y], (v["watermark"].as_u64().unwrap_or(0), chunks));
        }
    }
    let journal = store.join("fwlidar_state/journal");
    if let Ok((batches, _torn)) = fwlidar::voxel::shard_group::Journal::read(&journal) {
        for b in &batches {
            // A batch whose shards are not all renamed into place yet is not readable yet.
            let renamed = b
                .shards
                .iter()
                .all(|s| !store.join(format!("{s}.pending.{}", b.seq)).exists());
            for t in &b.tiles {
                if renamed {
                    out.insert(t.tile, (t.watermark, t.chunks.clone()));
                } else {
                    out.remove(&t.tile);
                }
            }
        }
    }
    out
}

/// The tiles a store's journal holds (tiles grouped into shard files) with their height
/// chunks, without their watermarks.
fn journal_tiles(journal: &Path) -> Vec<([i64; 2], Vec<u32>)> {
    let (batches, torn) = fwlidar::voxel::shard_group::Journal::read(journal).unwrap();
    assert_eq!(torn, None, "{}", journal.display());
    fwlidar::voxel::shard_group::latest_tiles(&batches)
        .into_iter()
        .map(|(tile, (_, chunks))| (tile, chunks))
        .collect()
}

/// Asserts that the store `mosaic` is the store `replayed` byte for byte, metadata included,
/// apart from the tiles' resume records (a record per tile, or the journal when tiles are
/// grouped into shard files), whose watermarks say when each tile closed (a merged store's are
/// 0); those must list the same tiles and height chunks.
pub fn assert_same_store_but_watermarks(mosaic: &Path, replayed: &Path) {
    let (m, r) = (file_tree(mosaic), file_tree(replayed));
    let names = |t: &[(PathBuf, Vec<u8>)]| t.iter().map(|f| f.0.clone()).collect::<Vec<_>>();
    assert_eq!(names(&m), names(&r), "the stores hold different files");
    assert!(m.len() > 10);
    let records = Path::new("fwlidar_state/tiles");
    for ((p, mine), (_, theirs)) in m.iter().zip(&r) {
        if p == Path::new("fwlidar_state/journal") {
            let tiles = journal_tiles(&mosaic.join(p));
            assert!(!tiles.is_empty(), "{}", mosaic.display());
            assert_eq!(tiles, journal_tiles(&replayed.join(p)), "{}", p.display());
        } else if p.starts_with(records) {
            let chunks = |b: &[u8]| {
                serde_json::from_slice::<serde_json::Value>(b).unwrap()["chunks"].clone()
            };
            assert_eq!(chunks(mine), chunks(theirs), "{}", p.display());
        } else {
            assert!(
                mine == theirs,
                "{} of {} differs from the sequential replay's",
                p.display(),
                mosaic.display()
            );
        }
    }
}
