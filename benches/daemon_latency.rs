//! End-to-end latency of the on-board daemon, frame arrival to voxel deposit, at steady pulse
//! rates: the real `fwlidar run` with **`config/onboard.toml` itself** (the on-board chain:
//! denoise, Richardson-Lucy 12 iterations from the Wiener start by the outgoing pulse with the
//! output's noise floor on the echo windows, Gaussian decomposition of the QC page's pulses
//! only, calibration, georeferencing per span, voxel tiles, no LAS, the capture recorded and
//! fsynced), fed in real time by `fwlidar simulate --live` (the survey-line scene: oscillating
//! mirror, NovAtel INSPVAX at 100 Hz) over loopback TCP and a pseudo-terminal. Only what one
//! machine needs is overridden on the command line (see [`daemon_args`]). The latencies are the
//! daemon's own HDR histogram (every pulse, 3 significant digits), read from its summary; this
//! harness only sets the rate and prints the table for docs/performance.md, with the CPU the
//! stream player (`simulate --live --from`) itself took, in cores (its user + system time over
//! the run's duration: on this 2-core machine what it leaves the daemon).
//!
//! `cargo bench --bench daemon_latency` (quiet machine; about 20 s per rate).
//! `FWLIDAR_LATENCY_FULL_RATES=2000,5000` and `FWLIDAR_LATENCY_LIGHT_RATES=20000` pick the
//! rates (pulses per second) of the full chain and of a light one (denoise, calibrate),
//! `FWLIDAR_LATENCY_SECONDS=15` the length of each run, `FWLIDAR_LATENCY_WORKERS=2` the
//! worker count (default: config/onboard.toml's, 0 = the daemon's own choice),
//! `FWLIDAR_LATENCY_QUEUE=65536` the queue capacity in pulses (default: config/onboard.toml's
//! 8192). Each run's stream is simulated into a capture first and played from it in real time
//! (`fwlidar simulate --live --from`), so the simulator's own cost does not take the daemon's
//! cores. `FWLIDAR_LATENCY_BIN=/path/to/fwlidar` measures another build (both the player and
//! the daemon), to alternate two builds within one period of the machine.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

const BUILT_BIN: &str = env!("CARGO_BIN_EXE_fwlidar");

/// The `fwlidar` binary to measure: `FWLIDAR_LATENCY_BIN` (another build, to compare two
/// builds alternately in one period of this machine) or the one cargo built with this bench.
fn bin() -> String {
    std::env::var("FWLIDAR_LATENCY_BIN").unwrap_or_else(|_| BUILT_BIN.to_string())
}
const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The light chain, over config/onboard.toml's stages: the FFT low-pass and the calibration
/// (the voxels get the denoised waveform).
const LIGHT_STAGES: &str = r#"[{ type = "denoise" }, { type = "calibrate" }]"#;

/// The daemon's command line: `config/onboard.toml` as it is, with only what a bench on one
/// machine must change set on the command line — the frame input (the stream player's TCP
/// port), the navigation terminal, the QC port, the survey name, shorter retry intervals, the
/// sensor profile of the played scene (the capture's, Optech ALTM 3100EA), and the bench's
/// worker count, queue capacity, voxel size and, for the light chain, its stages.
fn daemon_args(
    chain: &str,
    frames_port: u16,
    nav: &Path,
    qc_port: u16,
    voxel_m: [f64; 2],
    out: &Path,
) -> Vec<String> {
    let mut a: Vec<String> = vec![
        "run".into(),
        "--config".into(),
        format!("{ROOT}/config/onboard.toml"),
        "--out".into(),
        out.display().to_string(),
        "--frames".into(),
        format!("tcp-connect:127.0.0.1:{frames_port}"),
        "--qc".into(),
        format!("127.0.0.1:{qc_port}"),
        "--nav-device".into(),
        nav.display().to_string(),
    ];
    let mut set = |kv: String| {
        a.push("--set".into());
        a.push(kv);
    };
    set(format!(
        "sensor_profile=\"{ROOT}/config/sensors/optech_altm3100ea_cao.toml\""
    ));
    set("daemon.survey=\"latency\"".into());
    set("daemon.retry_ms=50".into());
    set("navigation.serial[0].reconnect_ms=50".into());
    if let Ok(w) = std::env::var("FWLIDAR_LATENCY_WORKERS") {
        set(format!("pipeline.workers={w}"));
    }
    if let Ok(q) = std::env::var("FWLIDAR_LATENCY_QUEUE") {
        set(format!("pipeline.queue_capacity={q}"));
    }
    set(format!(
        "voxels.voxel_size_m=[{h}, {h}, {v}]",
        h = voxel_m[0],
        v = voxel_m[1]
    ));
    if chain == "light" {
        set(format!("pipeline.stages={LIGHT_STAGES}"));
    }
    a
}

/// Voxel size (horizontal, vertical), metres: `FWLIDAR_LATENCY_VOXEL=1.0,0.5` (default, the
/// on-board profile's) or the replay default `0.5,0.15`.
fn voxel_m() -> [f64; 2] {
    let v: Vec<f64> = std::env::var("FWLIDAR_LATENCY_VOXEL")
        .unwrap_or_else(|_| "1.0,0.5".into())
        .split(',')
        .filter_map(|x| x.trim().parse().ok())
        .collect();
    [
        v.first().copied().unwrap_or(1.0),
        v.get(1).copied().unwrap_or(0.5),
    ]
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

struct Row {
    chain: &'static str,
    rate: f64,
    processed: u64,
    dropped: u64,
    p50: f64,
    p99: f64,
    p999: f64,
    max: f64,
    /// CPU the stream player took, cores (user + system seconds per second of its run).
    player_cores: f64,
    /// Pulses dropped by reason (the summary's `dropped`, compact JSON).
    reasons: String,
}

/// User + system CPU seconds of this process's waited-for children so far.
fn children_cpu_s() -> f64 {
    // SAFETY: getrusage(2) fills the zeroed struct we own.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn measure(chain: &'static str, rate: f64, seconds: f64) -> Row {
    let dir = tempfile::tempdir().unwrap();
    let nav = dir.path().join("gnss0");
    let pulses = (rate * seconds) as u64;
    // The stream is simulated into a capture first and then played from it in real time
    // (`simulate --live --from`): simulating the scene costs ~6 µs a pulse, more than two
    // cores have at 400 kHz, while playing a capture costs a frame encoding and a send.
    let capture = dir.path().join("line.fwcap");
    let made = Command::new(bin())
        .args(["simulate", "--no-progress", "--no-truth-voxels", "--scene"])
        .arg(Path::new(ROOT).join("config/scenes/survey_line.toml"))
        .args(["--pulses", &pulses.to_string()])
        .args(["--set", &format!("flight.pulse_rate_hz={rate:.1}")])
        .args([
            "--set",
            &format!(
                "flight.lines=[{{ start_m = [-{half:.0}, 0.0], end_m = [{half:.0}, 0.0] }}]",
                half = 60.0 * (seconds + 2.0) / 2.0
            ),
        ])
        .arg("--out")
        .arg(&capture)
        .stdout(Stdio::null())
        .status()
        .unwrap();
    assert!(made.success(), "fwlidar simulate failed");
    for truth in fwlidar::cli::simulate::truth_paths(&capture) {
        // The truth beside the capture is not needed here (it is large at these rates).
        let _ = std::fs::remove_file(&truth);
    }
    let cpu_before = children_cpu_s();
    let started = std::time::Instant::now();
    let mut sim = Command::new(bin())
        .args(["simulate", "--live", "--no-progress", "--from"])
        .arg(&capture)
        .args(["--speed", "1"])
        .args(["--frames", "tcp-listen:127.0.0.1:0", "--nav-pty-link"])
        .arg(&nav)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(sim.stdout.take().unwrap()).lines();
    let port = loop {
        let line = lines.next().expect("simulator output").unwrap();
        if line.contains("listening on tcp") {
            break line
                .split_whitespace()
                .find_map(|w| w.trim_end_matches(',').parse::<SocketAddr>().ok())
                .unwrap()
                .port();
        }
    };
    let out = dir.path().join("out");
    let mut daemon = Command::new(bin())
        .args(daemon_args(chain, port, &nav, free_port(), voxel_m(), &out))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    for line in lines.map_while(Result::ok) {
        if line.starts_with("sent ") {
            break;
        }
    }
    sim.wait().unwrap();
    let player_cores = (children_cpu_s() - cpu_before) / started.elapsed().as_secs_f64();
    // Let the last pulses through, then stop the daemon cleanly.
    std::thread::sleep(Duration::from_secs(2));
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(daemon.id() as i32, libc::SIGTERM) };
    daemon.wait().unwrap();
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("latency_0000.summary.json")).unwrap(),
    )
    .unwrap();
    let e = &summary["end_to_end"];
    let us = |k: &str| e[k].as_f64().unwrap_or(f64::NAN) / 1e3;
    Row {
        chain,
        rate,
        processed: summary["pulses_out"].as_u64().unwrap_or(0),
        dropped: summary["dropped_total"].as_u64().unwrap_or(0),
        p50: us("p50_ns"),
        p99: us("p99_ns"),
        p999: us("p999_ns"),
        max: us("max_ns"),
        player_cores,
        reasons: summary["dropped"].to_string(),
    }
}

fn main() {
    // `cargo test --benches` runs benches with `--bench` absent: do nothing then.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let rates = |var: &str, default: &str| -> Vec<f64> {
        std::env::var(var)
            .unwrap_or_else(|_| default.into())
            .split(',')
            .filter_map(|r| r.trim().parse().ok())
            .collect()
    };
    let seconds: f64 = std::env::var("FWLIDAR_LATENCY_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(15.0);
    println!(
        "| chain | pulse rate (/s) | pulses processed | dropped | p50 (µs) | p99 (µs) | p99.9 (µs) | max (µs) | stream player (cores) | dropped by reason |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|");
    let runs = rates("FWLIDAR_LATENCY_FULL_RATES", "100000,200000")
        .into_iter()
        .map(|r| ("full", r))
        .chain(
            rates("FWLIDAR_LATENCY_LIGHT_RATES", "20000,50000,100000")
                .into_iter()
                .map(|r| ("light", r)),
        );
    for (chain, rate) in runs {
        let r = measure(chain, rate, seconds);
        println!(
            "| {} | {:.0} | {} | {} | {:.0} | {:.0} | {:.0} | {:.0} | {:.2} | {} |",
            r.chain,
            r.rate,
            r.processed,
            r.dropped,
            r.p50,
            r.p99,
            r.p999,
            r.max,
            r.player_cores,
            r.reasons
        );
    }
}
