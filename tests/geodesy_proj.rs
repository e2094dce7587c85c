//! Our projections against PROJ itself: 24 reference points — both hemispheres, UTM zone edges,
//! the equator, high latitudes, the Lambert-93 of the IGN DEM fixture, geocentric — converted by
//! `cs2cs` (Debian's proj-bin, installed by `tests/run.sh`) and by `fwlidar::geo`, to 1 mm.

mod common;

use std::io::Write;
use std::process::{Command, Stdio};

use fwlidar::geo::{OutputCrs, ecef_of, utm_epsg};

/// (lat, lon, h) reference points, degrees and metres.
const POINTS: &[(f64, f64, f64)] = &[
    (47.8, 13.4, 450.0),         // Austria, the RIEGL flight (UTM 33N)
    (42.0955, -88.034, 220.0),   // Illinois, the OxTS log
    (43.4041, -80.4702, 290.0),  // Ontario, the NovAtel log
    (32.5452, -116.9782, 107.7), // the SBET
    (0.0, 0.0, 0.0),             // equator, Greenwich
    (0.000_01, 3.0, 10.0),       // equator on the central meridian of zone 31
    (-0.000_01, 3.0, 10.0),      // just south of it
    (-33.86, 151.21, 50.0),      // Sydney (56S)
    (-54.8, -68.3, 20.0),        // Ushuaia (19S)
    (-77.85, 166.67, 10.0),      // McMurdo (58S), high south
    (71.0, 25.8, 300.0),         // North Cape (35N), high north
    (83.5, -35.0, 1000.0),       // northern edge of UTM (27N)
    (-79.9, 0.5, 2000.0),        // southern edge of UTM (31S)
    (45.0, 11.999_999, 0.0),     // zone 32/33 edge, inside 32
    (45.0, 12.000_001, 0.0),     // zone 32/33 edge, inside 33
    (45.0, 5.999, 0.0),          // far from the central meridian of zone 31 (3° away)
    (60.0, 2.999, 0.0),          // zone 31N near its eastern edge
    (-45.0, -177.0, 0.0),        // zone 1S
    (45.0, 179.999, 0.0),        // zone 60N, antimeridian
    (10.0, -1.0, 0.0),           // zone 30N west of Greenwich
    (51.4779, -0.0015, 46.0),    // Greenwich observatory
    (35.0, 139.7, 40.0),         // Tokyo (54N)
    (-23.55, -46.63, 760.0),     // São Paulo (23S)
    (64.15, -21.94, 30.0),       // Reykjavik (27N)
];

/// Runs `cs2cs` from EPSG:4326 (lat lon order) to `to` on every point; (x, y, z) per point.
fn cs2cs(to: &str, points: &[(f64, f64, f64)]) -> Vec<[f64; 3]> {
    let cs2cs = common::tool(
        "cs2cs",
        "proj-bin",
        "PROJ's cs2cs is this check's reference",
    );
    let mut child = Command::new(cs2cs)
        .args(["-f", "%.6f", "EPSG:4326", to])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cs2cs cannot run: {e}"));
    let mut input = String::new();
    for (lat, lon, h) in points {
        input += &format!("{lat:.9} {lon:.9} {h:.4}\n");
    }
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| {
            let v: Vec<f64> = l
                .split_whitespace()
                .map(|x| x.parse().unwrap_or_else(|_| panic!("cs2cs printed {l:?}")))
                .collect();
            [v[0], v[1], v[2]]
        })
        .collect()
}

#[test]
fn utm_of_each_points_own_zone_matches_proj_to_a_millimetre() {
    let mut worst = 0.0f64;
    for &(lat, lon, h) in POINTS {
        let code = utm_epsg(lat, lon);
        let ours = OutputCrs::from_epsg(code)
            .unwrap()
            .project(lat, lon, h)
            .unwrap();
        let theirs = cs2cs(&format!("EPSG:{code}"), &[(lat, lon, h)])[0];
        let d = ((ours[0] - theirs[0]).powi(2) + (ours[1] - theirs[1]).powi(2)).sqrt();
        worst = worst.max(d);
        assert!(
            d < 0.001,
            "({lat}, {lon}) in EPSG:{code}: ours {ours:?}, PROJ {theirs:?}: {d} m"
        );
    }
    eprintln!(
        "UTM: {} points, worst difference from PROJ {:.3e} m",
        POINTS.len(),
        worst
    );
}

#[test]
fn lambert_93_and_geocentric_match_proj() {
    // Lambert-93 (the IGN LiDAR-HD DEM's CRS) only where it is defined: France.
    let france: Vec<_> = [
        (44.0, 3.0, 100.0),
        (48.85, 2.35, 35.0),
        (43.3, 5.4, 10.0),
        (50.6, 3.06, 20.0),
    ]
    .into_iter()
    .collect();
    let l93 = OutputCrs::from_epsg(2154).unwrap();
    for (p, theirs) in france.iter().zip(cs2cs("EPSG:2154", &france)) {
        let ours = l93.project(p.0, p.1, p.2).unwrap();
        let d = ((ours[0] - theirs[0]).powi(2) + (ours[1] - theirs[1]).powi(2)).sqrt();
        assert!(d < 0.001, "{p:?}: ours {ours:?}, PROJ {theirs:?}");
    }
    for (p, theirs) in POINTS.iter().zip(cs2cs("EPSG:4978", POINTS)) {
        let ours = ecef_of(p.0, p.1, p.2).unwrap();
        let d = (0..3)
            .map(|k| (ours[k] - theirs[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(d < 0.001, "{p:?}: ours {ours:?}, PROJ {theirs:?}: {d} m");
    }
}
