//! The IGN LiDAR-HD DTM (GeoTIFF, Lambert-93) read by `fwlidar::geo::dem`, sampled at the
//! ground points of the same tile's point cloud, which a real LAZ reader (laspy with lazrs, in
//! the venv `.ci/run` makes) extracts: the residuals say whether our reader puts every pixel
//! where it belongs.

mod common;

use std::process::Command;

use common::{fixture, python};
use fwlidar::geo::dem::Dem;

#[test]
fn ign_dtm_agrees_with_its_own_ground_points() {
    let tif = fixture("dem/ign_lidarhd/DTM_test_data_77055_627760_LA93_IGN69_50CM.tif");
    let laz = fixture("dem/ign_lidarhd/test_data_77055_627760_LA93_IGN69.laz");
    let dem = Dem::open(&tif).unwrap();
    assert_eq!(dem.size, (100, 100));
    assert_eq!(dem.pixel, [0.5, 0.5]);
    assert_eq!(dem.epsg, Some(2154));
    assert_eq!(dem.nodata, Some(-9999.0));
    dem.check_crs("dtm", 2154).unwrap();
    assert!(dem.check_crs("dtm", 32631).is_err());

    let script = "import laspy, sys\n\
                  las = laspy.read(sys.argv[1])\n\
                  g = las.classification == 2\n\
                  print(int(g.sum()), len(las.points))\n\
                  for x, y, z in zip(las.x[g], las.y[g], las.z[g]):\n\
                  \x20   print(f'{x:.3f} {y:.3f} {z:.3f}')\n";
    let out = Command::new(python())
        .args(["-c", script, laz.to_str().unwrap()])
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "laspy/lazrs could not read the LAZ: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    let head: Vec<usize> = lines
        .next()
        .unwrap()
        .split(' ')
        .map(|v| v.parse().unwrap())
        .collect();
    assert_eq!(
        head,
        vec![22_343, 60_653],
        "ground points, all points (MANIFEST)"
    );
    let points: Vec<Vec<f64>> = lines
        .map(|l| l.split(' ').map(|x| x.parse().unwrap()).collect())
        .collect();
    let mut residuals = Vec::new();
    let mut outside = 0;
    for v in &points {
        match dem.height_at(v[0], v[1]) {
            Some(z) => residuals.push(v[2] - z),
            None => outside += 1,
        }
    }
    // The same with the grid misplaced by one pixel (what a corner/centre or tie-point slip
    // would do): the check must be able to tell.
    let mut shifted = dem.clone();
    shifted.first_centre[0] += 0.5;
    shifted.first_centre[1] -= 0.5;
    let mut shifted_abs: Vec<f64> = points
        .iter()
        .filter_map(|v| shifted.height_at(v[0], v[1]).map(|z| (v[2] - z).abs()))
        .collect();
    shifted_abs.sort_by(f64::total_cmp);
    let shifted_mad50 = shifted_abs[shifted_abs.len() / 2];
    let n = residuals.len();
    let mut abs: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
    abs.sort_by(f64::total_cmp);
    let mut sorted = residuals.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[n / 2];
    let mad50 = abs[n / 2];
    let p95 = abs[(n as f64 * 0.95) as usize];
    eprintln!(
        "DTM at {n} ground points ({outside} outside the pixel centres or next to nodata): \
         residual median {median:+.3} m, |residual| median {mad50:.3} m, p95 {p95:.3} m, max {:.3} m; \
         grid one pixel off: |residual| median {shifted_mad50:.3} m",
        abs[n - 1]
    );
    // The DTM was made from these ground points (0.5 m cells). Figures: docs/navigation.md.
    assert!(outside < n / 10, "{outside} of {} outside", n + outside);
    assert!(median.abs() < 0.02, "bias {median}");
    // This tile is gentle terrain: a one-pixel slip of the grid raises the median |residual|
    // from 12 to 21 mm, so the bar sits between them (and the slipped grid must fail it).
    const BAR: f64 = 0.015;
    assert!(mad50 < BAR, "median |residual| {mad50}");
    assert!(p95 < 0.25, "p95 {p95}");
    assert!(
        shifted_mad50 > BAR,
        "a one-pixel slip must fail the bar: {shifted_mad50} against {mad50}"
    );
}
