//! The calibrate stage end to end: `fwlidar replay` of the bundled two-layer sample writes a
//! `backscatter` column, finite for every return, equal for ground echoes at the same range, and
//! range-normalised as `docs/calibration.md` says.

mod common;

use std::path::Path;

/// Speed of light, metres per nanosecond (the simulator's scene is in vacuum).
use fwlidar::core::units::C_M_PER_NS;

/// Replays the sample with `config` (None: the embedded `config/replay.toml`); the rows of
/// returns.csv as column name → value maps, and the summary.
fn replay(dir: &Path, config: Option<&str>) -> (Vec<Vec<(String, String)>>, serde_json::Value) {
    let out = dir.join("out");
    let mut args = vec![
        "replay".to_string(),
        "replay/two_layer.fwcap".into(),
        "--out".into(),
        out.display().to_string(),
        "--no-progress".into(),
    ];
    args.extend(common::CSV_OUTPUTS.map(String::from));
    if let Some(text) = config {
        let cfg = dir.join("run.toml");
        std::fs::write(&cfg, text).unwrap();
        args.extend(["--config".into(), cfg.display().to_string()]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = common::fwlidar(&args);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("returns.csv")).unwrap();
    let mut lines = csv.lines();
    let head: Vec<String> = lines
        .next()
        .unwrap()
        .split(',')
        .map(str::to_string)
        .collect();
    assert_eq!(
        head.last().map(String::as_str),
        Some("backscatter"),
        "{head:?}"
    );
    let rows = lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            assert_eq!(f.len(), head.len(), "{l}");
            head.iter()
                .cloned()
                .zip(f.iter().map(|v| v.to_string()))
                .collect()
        })
        .collect();
    let summary =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    (rows, summary)
}

fn num(row: &[(String, String)], name: &str) -> f64 {
    let v = &row.iter().find(|(k, _)| k == name).unwrap().1;
    v.parse()
        .unwrap_or_else(|_| panic!("{name} = {v:?} in {row:?}"))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Which surface a return's time belongs to: 0 the plane (985 m), 1 the ground (1000 m).
fn surface(t_ns: f64) -> Option<usize> {
    [985.0, 1000.0]
        .iter()
        .position(|r| (t_ns - 2.0 * r / C_M_PER_NS).abs() < 1.5)
}

#[test]
fn replay_writes_a_finite_backscatter_equal_for_ground_echoes_at_one_range() {
    let dir = tempfile::tempdir().unwrap();
    let (rows, summary) = replay(dir.path(), None);
    assert!(rows.len() > 4000, "{} returns", rows.len());
    let stage = summary["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "calibrate")
        .expect("the embedded configuration calibrates");
    assert_eq!(stage["received"], 2000, "{stage}");
    assert_eq!(stage["sent"], 2000, "{stage}");

    let mut ground = Vec::new();
    let mut ground_factor = Vec::new();
    let mut per_pulse: std::collections::BTreeMap<u64, Vec<(usize, f64, f64)>> = Default::default();
    for r in &rows {
        let (b, a, t) = (
            num(r, "backscatter"),
            num(r, "amplitude_v"),
            num(r, "time_ns"),
        );
        assert!(b.is_finite() && b > 0.0, "{r:?}");
        if let Some(k) = surface(t) {
            per_pulse
                .entry(num(r, "pulse_id") as u64)
                .or_default()
                .push((k, b / a, t));
            if k == 1 {
                ground.push(b);
                ground_factor.push(b / a);
            }
        }
    }
    assert!(ground.len() > 1900, "{} ground echoes", ground.len());

    // Ground echoes at one range have one backscatter: the tolerance is the amplitude noise of
    // the decomposition (uniform 3 DN noise on ~75 DN echoes), robust spread < 10 %, and the
    // two halves of the line agree within 2 %.
    let (first, second) = ground.split_at(ground.len() / 2);
    let (m1, m2) = (median(&mut first.to_vec()), median(&mut second.to_vec()));
    assert!((m1 / m2 - 1.0).abs() < 0.02, "halves {m1} and {m2}");
    let m = median(&mut ground.clone());
    let mut dev: Vec<f64> = ground.iter().map(|b| (b - m).abs()).collect();
    let spread = 1.4826 * median(&mut dev) / m;
    assert!(spread < 0.10, "robust relative spread {spread}");
    // The calibration factor itself varies only with the outgoing energy (its noise): ±8 %.
    let mf = median(&mut ground_factor.clone());
    for f in &ground_factor {
        assert!((f / mf - 1.0).abs() < 0.08, "factor {f}, median {mf}");
    }

    // Within one pulse (one energy, one system constant) the factors of the ground and the plane
    // differ by the range factor alone: (t_ground / t_plane)², t from the emission (the
    // outgoing peak, t0 here).
    let mut pairs = 0;
    for v in per_pulse.values() {
        if let [(0, fp, tp), (1, fg, tg)] = v.as_slice() {
            let expected = (tg / tp) * (tg / tp);
            assert!(
                ((fg / fp) / expected - 1.0).abs() < 1e-4,
                "{fg} / {fp} vs {expected}"
            );
            pairs += 1;
        }
    }
    assert!(
        pairs > 1500,
        "{pairs} pulses with one plane and one ground return"
    );
}

#[test]
fn with_every_factor_switched_off_the_backscatter_is_the_amplitude() {
    let dir = tempfile::tempdir().unwrap();
    let config = std::fs::read_to_string(Path::new(common::ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("\nrange = true", "\nrange = false")
        .replace("\nenergy = true", "\nenergy = false")
        .replace("\nsystem_constant = true", "\nsystem_constant = false");
    assert!(config.contains("\nrange = false") && config.contains("\nenergy = false"));
    assert!(config.contains("\nsystem_constant = false"));
    let (rows, _) = replay(dir.path(), Some(&config));
    assert!(rows.len() > 4000);
    for r in &rows {
        let get = |n: &str| &r.iter().find(|(k, _)| k == n).unwrap().1;
        assert_eq!(get("backscatter"), get("amplitude_v"), "{r:?}");
    }
}
