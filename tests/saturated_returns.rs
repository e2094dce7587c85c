//! Saturated returns on board: a scene whose roof echoes reach the 8-bit digitizer's full
//! scale (255 counts), simulated with and without the `saturation` effect from one seed, then
//! replayed through denoise and deconvolve as `fwlidar replay` runs them. The deconvolve stage
//! flags the samples at the full scale and NNLS leaves them out of its fit: each deconvolved
//! return keeps most of the energy the unsaturated recording gives, where Richardson-Lucy (which
//! fits the flattened top) keeps about half. The run notes every such pulse
//! (`deconvolve.clipped_samples`) and ends with a warning naming the setting. Figures over
//! pulse widths and clip depths: docs/accuracy.md, "Saturated returns on board".

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::{fwlidar, text};

/// A flat roof under a nadir-looking 8 ns, 8-bit sensor, bright enough to clip the top half
/// of its echo when `saturation` is on.
fn scene(dir: &Path, name: &str, effects: &str) -> PathBuf {
    let profile =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sensors/optech_altm3100ea_cao.toml");
    let toml = format!(
        r#"seed = 7
effects = [{effects}]

[terrain]
kind = "plane"
slope_deg = 0.0
aspect_deg = 0.0

[[box]]
rectangle_m = [-20.0, -20.0, 20.0, 20.0]
height_m = 4.0

[flight]
altitude_m = 1000.0
speed_mps = 60.0
pulse_rate_hz = 50000.0
lines = [{{ start_m = [-15.0, 0.0], end_m = [15.0, 0.0] }}]
scan = {{ pattern = "oscillating", half_angle_deg = 1.0, rate_hz = 70.0 }}

[sensor]
profile = "{}"
outgoing_fwhm_ns = 8.0
window_top_m = 30.0
return_samples = 256
peak_dn = 4000.0

[noise]
kind = "gaussian"
sigma_dn = 1.5

[navigation]
rate_hz = 100.0
formats = ["novatel"]
"#,
        profile.display()
    );
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, toml).unwrap();
    let capture = dir.join(format!("{name}.fwcap"));
    let o = fwlidar(&[
        "simulate",
        "--scene",
        path.to_str().unwrap(),
        "--out",
        capture.to_str().unwrap(),
        "--pulses",
        "200",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    capture
}

fn chain(dir: &Path, method: &str) -> PathBuf {
    let path = dir.join(format!("{method}.toml"));
    let m = match method {
        "nnls" => r#"{ method = "nnls" }"#,
        _ => r#"{ method = "richardson_lucy", iterations = 20 }"#,
    };
    std::fs::write(
        &path,
        format!(
            "[[pipeline.stages]]\ntype = \"denoise\"\n\n[[pipeline.stages]]\ntype = \
             \"deconvolve\"\nmethod = {m}\n"
        ),
    )
    .unwrap();
    path
}

/// Replays `capture` with `config` into `out`; returns the run's stderr and stdout.
fn replay(capture: &Path, config: &Path, out: &Path) -> String {
    let o = fwlidar(&[
        "replay",
        capture.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    format!("{}{}", text(&o.stdout), text(&o.stderr))
}

/// The body of a version-1 `.npy` file and its header text.
fn npy(path: &Path) -> (String, Vec<u8>) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..6], b"\x93NUMPY", "{}", path.display());
    let (len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ => (
            u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
            12,
        ),
    };
    let header = String::from_utf8_lossy(&bytes[start..start + len]).into_owned();
    (header, bytes[start + len..].to_vec())
}

/// The area (sum of samples, volt-samples) of every pulse's deconvolved return segment, by
/// pulse id, from `waveforms.npy` and its structured index `waveform_index.npy`.
fn return_areas(out: &Path) -> BTreeMap<u64, f64> {
    let (_, samples) = npy(&out.join("waveforms.npy"));
    let samples: Vec<f32> = samples
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let (header, index) = npy(&out.join("waveform_index.npy"));
    // pulse_id u8, gps_time f8, segment u2, kind u1, channel u1, start_ns f8, sample_ns f8,
    // n_samples u4, offset u8, baseline_v f4, noise_v f4: 56 bytes, packed.
    assert!(
        header.contains("'kind', '|u1'") && header.contains("'offset', '<u8'"),
        "{header}"
    );
    let mut areas = BTreeMap::new();
    for r in index.chunks_exact(56) {
        let id = u64::from_le_bytes(r[0..8].try_into().unwrap());
        let kind = r[18];
        let n = u32::from_le_bytes(r[36..40].try_into().unwrap()) as usize;
        let offset = u64::from_le_bytes(r[40..48].try_into().unwrap()) as usize;
        if kind == 1 {
            let a: f64 = samples[offset..offset + n].iter().map(|&v| v as f64).sum();
            areas.insert(id, a);
        }
    }
    areas
}

/// Median over pulses of `a / b`.
fn median_ratio(a: &BTreeMap<u64, f64>, b: &BTreeMap<u64, f64>) -> f64 {
    let mut r: Vec<f64> = b
        .iter()
        .filter(|(_, v)| **v > 0.0)
        .filter_map(|(k, v)| a.get(k).map(|x| x / v))
        .collect();
    assert!(r.len() >= 150, "{} pulses compared", r.len());
    r.sort_by(f64::total_cmp);
    r[r.len() / 2]
}

#[test]
fn nnls_on_board_keeps_the_energy_of_echoes_that_saturate_the_digitizer() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let clipped = scene(d, "clipped", r#""noise", "quantisation", "saturation""#);
    let whole = scene(d, "whole", r#""noise", "quantisation""#);
    let (nnls, rl) = (chain(d, "nnls"), chain(d, "rl"));
    let log = replay(&clipped, &nnls, &d.join("clipped_nnls"));
    replay(&whole, &nnls, &d.join("whole_nnls"));
    let rl_log = replay(&clipped, &rl, &d.join("clipped_rl"));
    let reference = return_areas(&d.join("whole_nnls"));
    let kept = median_ratio(&return_areas(&d.join("clipped_nnls")), &reference);
    let fitted = median_ratio(&return_areas(&d.join("clipped_rl")), &reference);
    println!("median area / unsaturated NNLS: nnls {kept:.3}, richardson_lucy {fitted:.3}");
    assert!(
        kept > 0.8,
        "NNLS with the full-scale samples left out keeps {kept}"
    );
    assert!(fitted < 0.6, "RL fits the flattened top: {fitted}");
    // Every pulse clipped: counted, and the run ends with a warning naming the setting.
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join("clipped_nnls/summary.json")).unwrap(),
    )
    .unwrap();
    let stage = summary["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "deconvolve")
        .unwrap();
    assert_eq!(stage["notes"]["clipped_samples"], 200, "{stage}");
    assert!(
        log.contains("WARNING") && log.contains("full scale"),
        "{log}"
    );
    assert!(log.contains("pipeline.stages[1].method"), "{log}");
    assert!(rl_log.contains("leaves those samples out"), "{rl_log}");
    // Nothing at the full scale: no note.
    let unsat: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("whole_nnls/summary.json")).unwrap())
            .unwrap();
    assert!(!unsat.to_string().contains("clipped_samples"));
}
