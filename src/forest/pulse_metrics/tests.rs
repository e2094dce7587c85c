use super::*;
use crate::forest::gedi_check;

fn gaussian(n: usize, centre: f64, sigma: f64, area: f64, out: &mut [f32]) {
    for (i, v) in out.iter_mut().enumerate().take(n) {
        let u = (i as f64 - centre) / sigma;
        *v += (area / (sigma * SQRT_2PI) * (-0.5 * u * u).exp()) as f32;
    }
}

fn input(samples: &[f32], mean: f64, sd: f64, smoothing: f64) -> WaveformInput<'_> {
    WaveformInput {
        pulse_sigma_ns: 0.0,
        samples,
        start_ns: 10.0,
        sample_ns: 1.0,
        noise_mean: mean,
        noise_sd: sd,
        smoothing_ns: smoothing,
        geometry: None,
        geographic: false,
    }
}

/// A canopy echo 90 bins (13.5 m) above a ground echo, no noise: the ground, the heights, the
/// energies and the cover follow from the two Gaussians.
#[test]
fn two_echoes_give_ground_heights_and_cover() {
    let n = 400;
    let mut y = vec![100.0f32; n];
    gaussian(n, 160.0, 4.0, 800.0, &mut y); // canopy, 800 units of energy
    gaussian(n, 250.0, 4.0, 1600.0, &mut y); // ground, 1600
    let mut c = MetricsComputer::default();
    let config = MetricsConfig::default();
    let m = c.compute(&config, &input(&y, 100.0, 1.0, 2.0));
    assert_eq!(m.status, MetricsStatus::Ok);
    assert_eq!(m.modes, 2);
    assert!((m.ground_ns - 260.0).abs() < 0.05, "ground {}", m.ground_ns);
    // Canopy centre 90 bins above the ground: 90 × 0.1499 m.
    let canopy_h = 90.0 * HALF_C_M_PER_NS;
    assert!(m.rh[100] as f64 > canopy_h, "rh100 {}", m.rh[100]);
    assert!((m.rh[100] as f64 - canopy_h) < 3.5 * 4.0 * HALF_C_M_PER_NS);
    // Two thirds of the energy is ground: RH50 is near 0, RH75 inside the canopy's lower half.
    assert!(m.rh[50].abs() < 0.5, "rh50 {}", m.rh[50]);
    assert!(
        (f64::from(m.rh[90]) - canopy_h).abs() < 1.0,
        "rh90 {}",
        m.rh[90]
    );
    for p in 1..=100 {
        assert!(m.rh[p] >= m.rh[p - 1], "RH monotone at {p}");
    }
    assert!(
        (f64::from(m.energy_total) - 2400.0).abs() < 30.0,
        "{}",
        m.energy_total
    );
    assert!(
        (f64::from(m.energy_ground) - 1600.0).abs() < 40.0,
        "rg {}",
        m.energy_ground
    );
    let cover = 800.0 / (800.0 + 1.5 * 1600.0);
    assert!(
        (f64::from(m.cover) - cover).abs() < 0.02,
        "cover {} vs {cover}",
        m.cover
    );
    assert!(
        (f64::from(m.pai) + 2.0 * (1.0 - cover).ln()).abs() < 0.05,
        "pai {}",
        m.pai
    );
    // The canopy sits in the 10-15 m bin (5 m bins): the whole PAVD there.
    let total_pavd: f32 = m.pavd[..m.pavd_bins as usize].iter().sum::<f32>() * 5.0;
    assert!(
        (total_pavd - m.pai).abs() < 0.01,
        "Σ PAVD dz {total_pavd} = PAI {}",
        m.pai
    );
    assert!(m.pavd[2] > 0.9 * m.pai / 5.0, "{:?}", &m.pavd[..4]);
    assert!(
        m.crown_thickness_m > 0.5 && m.crown_thickness_m < 4.0,
        "{}",
        m.crown_thickness_m
    );
    assert!(m.fhd > 0.0 && m.fhd < 2.0, "fhd {}", m.fhd);
    assert!(
        (m.ground_sigma_m - 4.0 * HALF_C_M_PER_NS as f32).abs() < 0.1,
        "{}",
        m.ground_sigma_m
    );
    assert!(m.ground_skew.abs() < 0.3, "{}", m.ground_skew);
}

#[test]
fn bare_ground_has_no_cover_and_noise_alone_no_signal() {
    let n = 300;
    let mut y = vec![50.0f32; n];
    gaussian(n, 150.0, 5.0, 2000.0, &mut y);
    let mut c = MetricsComputer::default();
    let m = c.compute(&MetricsConfig::default(), &input(&y, 50.0, 1.0, 3.0));
    assert_eq!(m.status, MetricsStatus::Ok);
    assert_eq!(m.modes, 1);
    assert!(m.cover < 0.02, "cover {}", m.cover);
    assert!(m.rh[50].abs() < 0.1, "rh50 {}", m.rh[50]);
    let flat = vec![50.0f32; n];
    let m = c.compute(&MetricsConfig::default(), &input(&flat, 50.0, 1.0, 3.0));
    assert_eq!(m.status, MetricsStatus::NoSignal);
    assert!(m.rh[50].is_nan());
    let mut bad = y.clone();
    bad[7] = f32::NAN;
    let m = c.compute(&MetricsConfig::default(), &input(&bad, 50.0, 1.0, 3.0));
    assert_eq!(m.status, MetricsStatus::NonFinite);
    let m = c.compute(&MetricsConfig::default(), &input(&y[..2], 50.0, 1.0, 3.0));
    assert_eq!(m.status, MetricsStatus::NoWaveform);
}

#[test]
fn extended_gaussian_fit_recovers_a_skewed_echo() {
    let truth = ExtGauss {
        area: 5000.0,
        centre: 60.0,
        sigma: 7.0,
        gamma: 1.2,
    };
    let y: Vec<f32> = (0..160)
        .map(|i| (20.0 + truth.value(i as f64)) as f32)
        .collect();
    let start = ExtGauss {
        area: 4000.0,
        centre: 62.0,
        sigma: 5.0,
        gamma: 0.0,
    };
    let bounds = FitBounds {
        centre: (56.0, 66.0),
        sigma: (0.5, 100.0),
    };
    let fit = fit_ext_gauss(&mut FitScratch::default(), &y, 20.0, 30, 159, start, bounds);
    assert!((fit.area - 5000.0).abs() < 5.0, "{fit:?}");
    assert!(
        (fit.centre - 60.0).abs() < 0.05 && (fit.sigma - 7.0).abs() < 0.05,
        "{fit:?}"
    );
    assert!((fit.gamma - 1.2).abs() < 0.02, "{fit:?}");
    for x in [-3.0, -0.5, 0.0, 0.2, 1.0, 2.5] {
        let e: f64 = erf(x);
        // erf is odd and bounded; erf(0.5) = 0.520 499 877 8 (tables).
        assert!(e.abs() <= 1.0 && (erf(-x) + e).abs() < 1e-8);
    }
    assert!((erf(0.5) - 0.520_499_877_8).abs() < 2e-7);
}

/// The canopy above a height is found by stepping from a guess on a grid that never rises,
/// and by binary search on any other: both are `partition_point`'s answer.
#[test]
fn points_above_a_height_are_the_partition_point() {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let gaps = GapModel::new(&MetricsConfig::default(), 1.0, 1.0, 0.0);
    for case in 0..400 {
        let len = rng.random_range(1..700usize);
        let (ground, vz) = (rng.random_range(0.0..300.0), rng.random_range(0.01..0.3));
        let mut x: f64 = rng.random_range(0.0..50.0);
        let mut heights: Vec<f64> = (0..len)
            .map(|_| {
                let h = (ground - x) * vz;
                x += 0.25;
                h
            })
            .collect();
        if case % 5 == 0 && len > 2 {
            // Not falling everywhere (and a repeated height): the binary search's answer.
            heights.swap(0, len / 2);
            heights[1] = heights[2];
        }
        let cum = vec![0.0; len + 1];
        let above = CanopyAbove::new(&heights, &cum, gaps);
        let (lo, hi) = (
            heights[len - 1].min(heights[0]),
            heights[len - 1].max(heights[0]),
        );
        let mut probes: Vec<f64> = (0..60)
            .map(|_| rng.random_range(lo - 5.0..hi + 5.0))
            .collect();
        probes.extend(heights.iter().take(20).copied());
        probes.extend([f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 0.0, -0.0]);
        for h in probes {
            assert_eq!(
                above.points_at_or_above(h),
                heights.partition_point(|&hh| hh >= h),
                "case {case}, h {h}"
            );
        }
    }
}

/// The fixture's 32 GEDI shots: our RH against L2A's `rh`, our cover, PAI and FHD against L2B.
/// Prints the table of docs/accuracy.md ("GEDI"); run with `--nocapture` to see it.
#[test]
fn gedi_fixture_matches_level_2a_and_2b() {
    let f = |n: &str| crate::fixtures::path(&format!("waveform/gedi/{n}_O01964_beams0001_1011.h5"));
    let rows = gedi_check::compare(
        &f("GEDI01_B"),
        &f("GEDI02_A"),
        &f("GEDI02_B"),
        &MetricsConfig::default(),
        6.5,
    )
    .unwrap();
    assert_eq!(rows.len(), 32);
    assert!(
        rows.iter()
            .all(|r| r.ours.status == MetricsStatus::Ok && r.l2a_algorithm == 1)
    );
    println!("{}", gedi_check::summary_markdown(&rows));
    for p in [50usize, 98] {
        let (med, worst) =
            gedi_check::median_and_worst(&rows, |r| f64::from(r.ours.rh[p]) - r.l2a_rh[p]);
        assert!(med <= 0.5, "RH{p}: median |Δ| {med:.2} m");
        assert!(worst <= 1.0, "RH{p}: worst |Δ| {worst:.2} m");
    }
    let (med, _) = gedi_check::median_and_worst(&rows, |r| f64::from(r.ours.cover) - r.l2b_cover);
    assert!(med <= 0.05, "cover: median |Δ| {med:.3}");
}

fn vertical(start_ns_z: f64) -> crate::pulse::PulseGeometry {
    // Nadir beam: z falls by c/2 per ns from `start_ns_z` at t = 0.
    crate::pulse::PulseGeometry {
        anchor: [500.0, 500.0, start_ns_z],
        direction: [0.0, 0.0, -HALF_C_M_PER_NS],
    }
}

fn flat_dem(z: f32) -> RunDem {
    let dem = Dem::from_heights((20, 20), [495.5, 504.5], [1.0, 1.0], None, vec![z; 400])
        .expect("20 × 20 heights");
    RunDem(std::sync::Arc::new(dem))
}

/// An oblique beam over a sloping DEM: the fixed point is the exact crossing.
#[test]
fn the_beam_crosses_a_sloping_dem_where_the_plane_says() {
    // z = 0.1 (x − 490) over x 490..590.
    let heights: Vec<f32> = (0..100 * 10)
        .map(|i| 0.1 * ((i % 100) as f32 + 0.5))
        .collect();
    let dem = Dem::from_heights((100, 10), [490.5, 504.5], [1.0, 1.0], None, heights).unwrap();
    let g = crate::pulse::PulseGeometry {
        anchor: [500.0, 500.0, 100.0],
        direction: [0.05, 0.0, -0.15],
    };
    // 100 − 0.15 t = 0.1 (10 + 0.05 t)  ⇒  t = 99 / 0.155.
    let t = dem_crossing_ns(&dem, &g, 0.0).expect("converges");
    assert!((t - 99.0 / 0.155).abs() < 1e-3, "t {t}");
    // Outside the DEM, or a horizontal beam: none.
    let away = crate::pulse::PulseGeometry {
        anchor: [0.0, 0.0, 100.0],
        ..g
    };
    assert_eq!(dem_crossing_ns(&dem, &away, 0.0), None);
    let flat = crate::pulse::PulseGeometry {
        direction: [0.1, 0.0, 0.0],
        ..g
    };
    assert_eq!(dem_crossing_ns(&dem, &flat, 0.0), None);
}

/// A dense crown hides the ground: the lowest mode is the crown's and the height collapses;
/// with the DEM as the ground the crown stands at its height, all its energy canopy.
#[test]
fn the_dem_gives_the_ground_a_crown_hides() {
    let n = 300;
    let mut y = vec![0.0f32; n];
    gaussian(n, 100.0, 3.0, 600.0, &mut y); // crown top echo
    gaussian(n, 130.0, 3.0, 300.0, &mut y); // deeper in the crown
    // t0 = start (10 ns) at 40 m: bin b is at 40 − (b) × c/2; the DEM at 10 m is bin 200.1.
    let ground_bin = 30.0 / HALF_C_M_PER_NS;
    let mut w = input(&y, 0.0, 1.0, 1.0);
    let geometry = vertical(40.0 + 10.0 * HALF_C_M_PER_NS);
    w.geometry = Some(geometry);
    let mut c = MetricsComputer::default();
    let by_mode = c.compute(&MetricsConfig::default(), &w);
    assert_eq!(by_mode.ground_from, GroundFrom::LowestMode);
    assert!(by_mode.canopy_height < 6.0, "{}", by_mode.canopy_height);
    let config = MetricsConfig {
        ground: GroundFrom::Dem,
        dem: Some(flat_dem(10.0)),
        ..MetricsConfig::default()
    };
    let m = c.compute(&config, &w);
    assert_eq!(m.status, MetricsStatus::Ok);
    assert_eq!(m.ground_from, GroundFrom::Dem);
    assert!(
        (m.ground_ns - (10.0 + ground_bin)).abs() < 1e-3,
        "{}",
        m.ground_ns
    );
    assert!((m.ground_xyz[2] - 10.0).abs() < 1e-6, "{:?}", m.ground_xyz);
    // The lowest mode stays known (the crown's second echo).
    assert!((m.mode_ns - 140.0).abs() < 0.5, "{}", m.mode_ns);
    // The crown top is 100 bins above the ground bin less the threshold's lead.
    let top_h = (ground_bin - 100.0) * HALF_C_M_PER_NS;
    assert!(
        f64::from(m.canopy_height) > top_h && f64::from(m.canopy_height) < top_h + 1.5,
        "canopy {} vs {top_h}",
        m.canopy_height
    );
    assert_eq!(m.energy_ground, 0.0);
    assert!(m.cover > 0.999, "{}", m.cover);
    // A DEM ground needs the DEM: without it, the lowest mode.
    let without = MetricsConfig {
        ground: GroundFrom::Dem,
        ..MetricsConfig::default()
    };
    assert_eq!(c.compute(&without, &w).ground_from, GroundFrom::LowestMode);
}

/// A point target's echo: the signal start leads its centre by the pulse's rise to the
/// threshold; the leading edge puts the top back on it.
#[test]
fn the_leading_edge_puts_a_point_target_at_its_echo() {
    let n = 200;
    let mut y = vec![0.0f32; n];
    gaussian(n, 80.0, 4.0, 400.0, &mut y); // peak 40 units
    gaussian(n, 150.0, 4.0, 400.0, &mut y); // ground
    let mut w = input(&y, 0.0, 1.0, 0.0);
    w.pulse_sigma_ns = 4.0;
    let mut c = MetricsComputer::default();
    let start = c.compute(&MetricsConfig::default(), &w);
    // 3 σ of noise against a 40-unit peak: σ √(2 ln(40/3)) = 9.1 bins early.
    assert!(
        (start.top_ns - (10.0 + 80.0 - 9.1)).abs() < 0.3,
        "{}",
        start.top_ns
    );
    assert_eq!(start.canopy_height, start.rh[100]);
    let edge = c.compute(
        &MetricsConfig {
            top: TopFrom::LeadingEdge,
            ..MetricsConfig::default()
        },
        &w,
    );
    assert!((edge.top_ns - 90.0).abs() < 0.3, "{}", edge.top_ns);
    let h = 70.0 * HALF_C_M_PER_NS;
    assert!(
        (f64::from(edge.canopy_height) - h).abs() < 0.05,
        "{}",
        edge.canopy_height
    );
    // RH100 stays GEDI's (the signal start).
    assert_eq!(edge.rh[100], start.rh[100]);
}
