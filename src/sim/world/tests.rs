use super::*;
use crate::sim::analytic_scene::parse_toml;

/// A scene from TOML text, its sensor the CAO profile (16 ns, 1 ns, 8 bit, 0.56 mrad).
fn world(text: &str) -> WorldSim {
    let scene: WorldScene = parse_toml(text, "test scene").unwrap();
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes");
    let sensor = scene.resolve_sensor(&base).unwrap();
    WorldSim::new(&scene, &sensor, &base).unwrap()
}

const SENSOR: &str = r#"
[sensor]
profile = "../sensors/optech_altm3100ea_cao.toml"
"#;

fn nadir_line(extra: &str, sensor_extra: &str) -> String {
    format!(
        "{extra}\n[flight]\naltitude_m = 1000.0\npulse_rate_hz = 1000.0\n\
         lines = [{{ start_m = [0.0, 0.0], end_m = [0.5, 0.0] }}]\n{SENSOR}{sensor_extra}"
    )
}

fn pulses(sim: &mut WorldSim) -> Vec<(Pulse, ShotTruth)> {
    let mut out = Vec::new();
    loop {
        let (mut p, mut t) = (Pulse::default(), ShotTruth::default());
        match sim.fill_next(&mut p, &mut t) {
            None => return out,
            Some(_) => out.push((p, t)),
        }
    }
}

fn sigma(fwhm: f64) -> f64 {
    fwhm / FWHM_PER_SIGMA
}

/// Area, centroid and variance of a sampled waveform (times `start + i`).
fn moments(w: &[f64], start: f64, dt: f64) -> (f64, f64, f64) {
    let a: f64 = w.iter().sum();
    let m = w
        .iter()
        .enumerate()
        .map(|(i, v)| v * (start + i as f64 * dt))
        .sum::<f64>()
        / a;
    let v = w
        .iter()
        .enumerate()
        .map(|(i, v)| v * (start + i as f64 * dt - m).powi(2))
        .sum::<f64>()
        / a;
    (a * dt, m, v)
}

#[test]
fn a_scene_without_effects_gives_the_analytic_echo() {
    let mut sim = world(&nadir_line("seed = 1", ""));
    let mpn = sim.metres_per_ns();
    let ps = pulses(&mut sim);
    // 0.5 m at 60 m/s: 8.3 ms of pulses at 1 kHz.
    assert_eq!(ps.len(), 9);
    for (p, t) in &ps {
        // The scanner sits at the lever arm (0 for the CAO profile) 1000 m above flat ground.
        let r = t.origin[2];
        assert!((r - 1000.0).abs() < 1e-6, "{r}");
        let te = r / mpn;
        let a = 200.0 * 0.3 * (1000.0 / r).powi(2);
        let s = sigma(16.0);
        let start = p.segments[1].start_ns;
        assert_eq!(start, t.return_start_ns);
        // The window starts 25 m above the ground, on the sample clock.
        assert!((start - (r - 25.0) / mpn).abs() <= 0.5, "{start}");
        let raw = p.raw_of(1);
        for (i, c) in t.clean.iter().enumerate() {
            let x = start + i as f64 - te;
            let want = if x.abs() <= 7.0 * s {
                a * (-0.5 * (x / s).powi(2)).exp()
            } else {
                0.0
            };
            assert!((c - want).abs() < 1e-9 * a, "bin {i}: {c} vs {want}");
            // The recorded samples are the analytic waveform to 1/128 count (64 steps a count).
            let counts = raw[i] as f64 / 64.0;
            assert!(
                (counts - (12.0 + want)).abs() <= 1.0 / 128.0 + 1e-12,
                "bin {i}"
            );
        }
        assert_eq!(p.bits, 16);
        assert!((p.gain_v_per_dn - 1.0 / 64.0).abs() < 1e-9);
        // One scatterer: the terrain, the whole beam.
        assert_eq!(t.scatterers.len(), 1);
        assert_eq!(t.scatterers[0].kind, ObjectKind::Terrain);
        assert!((t.scatterers[0].fraction - 1.0).abs() < 1e-12);
        // The truth is the same cross-section with a 2 ns pulse, area preserving.
        let (area_truth, m_truth, _) = moments(&t.truth, start, 1.0);
        let (area, m, var) = moments(&t.clean, start, 1.0);
        // A 2 ns pulse sampled at 1 ns sums to its area within 2e-6.
        assert!(
            (area_truth / area - 1.0).abs() < 1e-5,
            "{area_truth} vs {area}"
        );
        assert!((m - te).abs() < 1e-6 && (m_truth - te).abs() < 1e-3);
        assert!((var / (s * s) - 1.0).abs() < 1e-6);
    }
    // No effects, no randomness: another seed gives the same samples.
    let mut other = world(&nadir_line("seed = 99", ""));
    let qs = pulses(&mut other);
    assert!(ps.iter().zip(&qs).all(|(a, b)| a.0.raw == b.0.raw));
}

#[test]
fn echo_energy_goes_with_reflectance_over_range_squared() {
    let area = |alt: f64, rho: f64| {
        let mut sim = world(&format!(
            "materials = {{ ground = {rho} }}\n[flight]\naltitude_m = {alt}\npulse_rate_hz = 100.0\n\
             lines = [{{ start_m = [0.0, 0.0], end_m = [1.0, 0.0] }}]\n{SENSOR}"
        ));
        let (p, t) = pulses(&mut sim).remove(0);
        moments(&t.clean, p.segments[1].start_ns, 1.0).0
    };
    let a = area(1000.0, 0.3);
    assert!((area(1000.0, 0.6) / a - 2.0).abs() < 1e-9);
    assert!((area(2000.0, 0.3) / a - 0.25).abs() < 1e-9);
    assert!((area(500.0, 0.15) / a - 2.0).abs() < 1e-9);
}

#[test]
fn the_receiver_response_widens_the_echo_and_keeps_its_energy() {
    let run = |rx: f64| {
        let mut sim = world(&nadir_line("", &format!("receiver_fwhm_ns = {rx}\n")));
        let (p, t) = pulses(&mut sim).remove(0);
        moments(&t.clean, p.segments[1].start_ns, 1.0)
    };
    let (a0, m0, v0) = run(0.0);
    let (a1, m1, v1) = run(8.0);
    assert!((a1 / a0 - 1.0).abs() < 1e-9);
    assert!((m1 - m0).abs() < 1e-6);
    let want = sigma(16.0).powi(2) + sigma(8.0).powi(2);
    assert!((v1 / want - 1.0).abs() < 1e-6 && (v0 / sigma(16.0).powi(2) - 1.0).abs() < 1e-6);
}

#[test]
fn an_off_nadir_footprint_on_flat_ground_broadens_the_echo_as_its_geometry_predicts() {
    // A 2 ns pulse and a 5 mrad beam at 20° make the broadening dominate.
    let run = |zenith: f64, effects: &str| {
        let mut sim = world(&format!(
            "effects = [{effects}]\nfootprint_rings = 8\n[flight]\naltitude_m = 1000.0\n\
             pulse_rate_hz = 100.0\nlines = [{{ start_m = [0.0, 0.0], end_m = [1.0, 0.0] }}]\n\
             scan = {{ pattern = \"fixed\", zenith_deg = {zenith}, azimuth_deg = 90.0 }}\n\
             [sensor]\nprofile = \"../sensors/optech_altm3100ea_cao.toml\"\noutgoing_fwhm_ns = 2.0\n\
             return_samples = 300\n"
        ));
        let (p, t) = pulses(&mut sim).remove(0);
        let r = t
            .scatterers
            .iter()
            .map(|s| s.range_m * s.fraction)
            .sum::<f64>();
        (
            moments(&t.clean, p.segments[1].start_ns, 1.0),
            r,
            sim.metres_per_ns(),
            p,
        )
    };
    let ((_, _, v_axis), _, _, _) = run(20.0, "\"off_nadir\"");
    assert!(
        (v_axis / sigma(2.0).powi(2) - 1.0).abs() < 1e-4,
        "one ray: no broadening {v_axis} vs {}",
        sigma(2.0).powi(2)
    );
    let ((_, _, v), range, mpn, p) = run(20.0, "\"off_nadir\", \"footprint\"");
    assert!(
        (p.scan_angle_deg[0] - 20.0).abs() < 1e-4,
        "{:?}",
        p.scan_angle_deg
    );
    // Range spread across the footprint: σ_beam tan(i), σ_beam = R γ / 4.
    let gamma = 0.56e-3;
    let s_range = range * gamma / 4.0 * 20f64.to_radians().tan();
    let want = (s_range / mpn).powi(2);
    let got = v - sigma(2.0).powi(2);
    assert!(
        (got / want - 1.0).abs() < 0.1,
        "broadening {got:.5} ns² vs {want:.5} ns² (σ_range {s_range:.4} m)"
    );
    // At nadir the footprint does not broaden a flat target.
    let ((_, _, v0), _, _, _) = run(0.0, "\"off_nadir\", \"footprint\"");
    assert!((v0 / sigma(2.0).powi(2) - 1.0).abs() < 1e-3, "{v0}");
}

#[test]
fn a_tilted_plane_at_nadir_broadens_like_an_off_nadir_beam() {
    let mut sim = world(&format!(
        "effects = [\"footprint\"]\nfootprint_rings = 8\n[terrain]\nkind = \"plane\"\n\
         slope_deg = 30.0\naspect_deg = 45.0\n[flight]\npulse_rate_hz = 100.0\n\
         lines = [{{ start_m = [0.0, 0.0], end_m = [1.0, 0.0] }}]\n\
         {SENSOR}outgoing_fwhm_ns = 2.0\n"
    ));
    let mpn = sim.metres_per_ns();
    let (p, t) = pulses(&mut sim).remove(0);
    let (_, _, v) = moments(&t.clean, p.segments[1].start_ns, 1.0);
    let s_range = 1000.0 * 0.56e-3 / 4.0 * 30f64.to_radians().tan();
    let got = v - sigma(2.0).powi(2);
    let want = (s_range / mpn).powi(2);
    assert!((got / want - 1.0).abs() < 0.1, "{got} vs {want}");
    // Lambertian: the energy falls with the cosine of the incidence.
    let e: f64 = t.scatterers.iter().map(|s| s.amplitude_dn).sum();
    assert!(
        (e / (200.0 * 0.3 * 30f64.to_radians().cos()) - 1.0).abs() < 0.01,
        "{e}"
    );
}

#[test]
fn two_planes_give_two_echoes_at_their_separation() {
    // A flat roof 10 m up whose edge runs under the beam: half the footprint on each.
    let mut sim = world(&format!(
        "effects = [\"footprint\"]\nfootprint_rings = 6\n\
         [[box]]\nrectangle_m = [0.0, -20.0, 20.0, 20.0]\nheight_m = 10.0\nmaterial = \"ground\"\n\
         [flight]\npulse_rate_hz = 100.0\nlines = [{{ start_m = [0.0, 0.0], end_m = [0.0, 1.0] }}]\n\
         {SENSOR}outgoing_fwhm_ns = 2.0\n"
    ));
    let mpn = sim.metres_per_ns();
    let (p, t) = pulses(&mut sim).remove(0);
    let start = p.segments[1].start_ns;
    let peaks: Vec<f64> = (1..t.clean.len() - 1)
        .filter(|&i| {
            t.clean[i] > t.clean[i - 1] && t.clean[i] >= t.clean[i + 1] && t.clean[i] > 5.0
        })
        .map(|i| start + i as f64)
        .collect();
    assert_eq!(peaks.len(), 2, "{peaks:?}");
    assert!(
        ((peaks[1] - peaks[0]) - 10.0 / mpn).abs() <= 1.0,
        "{peaks:?}"
    );
    let frac = |k: ObjectKind| -> f64 {
        t.scatterers
            .iter()
            .filter(|s| s.kind == k)
            .map(|s| s.fraction)
            .sum()
    };
    assert!(
        (frac(ObjectKind::Box) - 0.5).abs() < 0.1 && (frac(ObjectKind::Terrain) - 0.5).abs() < 0.1
    );
    assert!((frac(ObjectKind::Box) + frac(ObjectKind::Terrain) - 1.0).abs() < 1e-12);
}

#[test]
fn a_crown_lets_through_the_beer_lambert_gap_fraction() {
    for (lad, g) in [(0.3, 0.5), (1.0, 0.5), (2.0, 0.9)] {
        let mut sim = world(&format!(
            "[[tree]]\nposition_m = [0.2, 0.0]\nheight_m = 15.0\nstem_radius_m = 0.0\n\
             leaf_area_density = {lad}\ng_function = {g}\n\
             crown = {{ shape = \"cylinder\", base_m = 5.0, radius_m = 3.0 }}\n\
             [flight]\npulse_rate_hz = 100.0\nlines = [{{ start_m = [0.0, 0.0], end_m = [0.0, 1.0] }}]\n{SENSOR}"
        ));
        let (_, t) = pulses(&mut sim).remove(0);
        let crown: f64 = t
            .scatterers
            .iter()
            .filter(|s| s.kind == ObjectKind::Crown)
            .map(|s| s.fraction)
            .sum();
        let ground: f64 = t
            .scatterers
            .iter()
            .filter(|s| s.kind == ObjectKind::Terrain)
            .map(|s| s.fraction)
            .sum();
        let gap = (-g * lad * 10.0f64).exp();
        assert!(
            (ground - gap).abs() < 1e-9,
            "LAD {lad}: ground {ground} vs gap {gap}"
        );
        assert!((crown - (1.0 - gap)).abs() < 1e-9);
        // The crown's echo starts at its top (15 m) and the energy is where the leaves are.
        let first = t
            .scatterers
            .iter()
            .find(|s| s.kind == ObjectKind::Crown)
            .unwrap();
        assert!((first.position[2] - 15.0).abs() < 1e-6);
    }
}

#[test]
fn effects_are_applied_only_when_named() {
    let base = |effects: &str, extra: &str| {
        let mut sim = world(&nadir_line(
            &format!("seed = 5\neffects = [{effects}]\n{extra}"),
            "",
        ));
        pulses(&mut sim)
    };
    let clean = base("", "");
    // Quantisation alone: whole counts of the sensor, no noise.
    let q = base("\"quantisation\"", "");
    for ((p, t), (pc, _)) in q.iter().zip(&clean) {
        assert_eq!(p.gain_v_per_dn, 1.0);
        for (i, &r) in p.raw_of(1).iter().enumerate() {
            assert_eq!(r as f64, (12.0 + t.clean[i]).round());
        }
        assert_ne!(p.raw, pc.raw);
    }
    // Noise alone (uniform ±3 counts): within its amplitude, zero mean, seeded.
    let noisy = base(
        "\"noise\"",
        "[noise]\nkind = \"uniform\"\namplitude_dn = 3.0\n",
    );
    let mut sum = 0.0;
    let mut n = 0.0;
    for (p, t) in &noisy {
        for (i, &r) in p.raw_of(1).iter().enumerate() {
            let d = r as f64 / 64.0 - (12.0 + t.clean[i]);
            assert!(d.abs() <= 3.0 + 1.0 / 64.0);
            sum += d;
            n += 1.0;
        }
    }
    assert!((sum / n).abs() < 0.1, "mean {}", sum / n);
    assert!(
        noisy
            .iter()
            .zip(&base(
                "\"noise\"",
                "[noise]\nkind = \"uniform\"\namplitude_dn = 3.0\n"
            ))
            .all(|(a, b)| a.0.raw == b.0.raw)
    );
    // Saturation: a bright target clips at 255 only when asked.
    let bright = "materials = { ground = 1.0 }\n";
    let over = |effects: &str| {
        let mut sim = world(&nadir_line(
            &format!("effects = [{effects}]\n{bright}"),
            "peak_dn = 400.0\n",
        ));
        pulses(&mut sim).remove(0).0
    };
    let free = over("\"quantisation\"");
    assert!(
        free.raw_of(1).iter().any(|&r| r > 255),
        "no limit without saturation"
    );
    let clipped = over("\"quantisation\", \"saturation\"");
    assert_eq!(clipped.raw_of(1).iter().max(), Some(&255));
    assert_eq!(clipped.bits, 8);
    // Ringing: after the echo the waveform swings below the baseline.
    let ring = base("\"ringing\"", "");
    let (_, t) = &ring[0];
    assert!(t.clean.iter().any(|&v| v < -1.0));
    assert!(clean[0].1.clean.iter().all(|&v| v >= 0.0));
}

#[test]
fn timing_jitter_moves_outgoing_and_return_together() {
    let mut sim = world(&nadir_line(
        "seed = 3\neffects = [\"timing_jitter\"]\ntiming_jitter_ns = 0.5\n",
        "",
    ));
    let ps = pulses(&mut sim);
    let js: Vec<f64> = ps.iter().map(|(_, t)| t.jitter_ns).collect();
    assert!(js.iter().any(|j| j.abs() > 0.05));
    let mpn = sim.metres_per_ns();
    for (p, t) in &ps {
        let (_, m, _) = moments(&t.clean, p.segments[1].start_ns, 1.0);
        assert!((m - (t.origin[2] / mpn + t.jitter_ns)).abs() < 1e-6);
        // The truth stays on the true time.
        let (_, mt, _) = moments(&t.truth, p.segments[1].start_ns, 1.0);
        assert!((mt - t.origin[2] / mpn).abs() < 1e-3);
    }
}

#[test]
fn packet_loss_drops_frames_and_lists_them() {
    let text = format!(
        "seed = 11\neffects = [\"packet_loss\"]\npacket_loss = 0.1\n[flight]\npulse_rate_hz = 20000.0\n\
         lines = [{{ start_m = [0.0, 0.0], end_m = [6.0, 0.0] }}]\n{SENSOR}"
    );
    let items = WorldItems::new(world(&text)).unwrap();
    let mut items = items;
    let mut seqs = Vec::new();
    for item in items.by_ref() {
        if let SimItem::Pulse(p) = item {
            seqs.push(p.seq);
        }
    }
    let lost = items.lost().to_vec();
    let total = seqs.len() + lost.len();
    assert_eq!(total, 2001);
    let rate = lost.len() as f64 / total as f64;
    assert!((rate - 0.1).abs() < 0.025, "{rate}");
    assert!(lost.iter().all(|l| !seqs.contains(l)));
}

#[test]
fn scan_patterns_sweep_as_designed() {
    use flight::scan_angles;
    let osc = ScanPatternFixture::Osc.pattern();
    let a: Vec<f64> = (0..100)
        .map(|i| scan_angles(&osc, i as f64 * 0.001)[0])
        .collect();
    assert!(
        (a[0] + 15.0).abs() < 1e-9 && (a[25] - 15.0).abs() < 1e-9 && (a[50] + 15.0).abs() < 1e-9
    );
    let poly = ScanPatternFixture::Poly.pattern();
    let b: Vec<f64> = (0..100)
        .map(|i| scan_angles(&poly, i as f64 * 0.001)[0])
        .collect();
    assert!(
        b.windows(2).filter(|w| w[1] < w[0]).count() <= 2,
        "sawtooth"
    );
    let palmer = ScanPatternFixture::Palmer.pattern();
    for i in 0..50 {
        let [th, ph] = scan_angles(&palmer, i as f64 * 0.0013);
        let b = crate::geo::direct_georeference::beam_in_scanner(th, ph);
        assert!((b.z.acos().to_degrees() - 12.0).abs() < 1e-9, "on the cone");
    }
}

enum ScanPatternFixture {
    Osc,
    Poly,
    Palmer,
}

impl ScanPatternFixture {
    fn pattern(&self) -> scene::ScanPattern {
        match self {
            ScanPatternFixture::Osc => scene::ScanPattern::Oscillating {
                half_angle_deg: 15.0,
                rate_hz: 20.0,
            },
            ScanPatternFixture::Poly => scene::ScanPattern::Polygon {
                half_angle_deg: 15.0,
                rate_hz: 20.0,
            },
            ScanPatternFixture::Palmer => scene::ScanPattern::Palmer {
                half_angle_deg: 12.0,
                rate_hz: 20.0,
            },
        }
    }
}

#[test]
fn the_plot_grid_aims_every_beam_at_its_cell() {
    let mut sim = world(&format!(
        "effects = [\"off_nadir\"]\n[flight]\npulse_rate_hz = 4800.0\n\
         grid = {{ columns = 40, rows = 40, spacing_m = 0.5 }}\n\
         scan = {{ pattern = \"fixed\", zenith_deg = 20.0, azimuth_deg = 90.0 }}\n{SENSOR}"
    ));
    let ps = pulses(&mut sim);
    assert_eq!(ps.len(), 1600);
    for (k, (_, t)) in ps.iter().enumerate() {
        let ground = t.scatterers.last().unwrap();
        let (row, col) = (k / 40, k % 40);
        let want = [-9.75 + col as f64 * 0.5, -9.75 + row as f64 * 0.5];
        // The recorded (f32) scan angles carry 1e-8 rad: 0.02 mm at 1 km.
        assert!(
            (ground.position[0] - want[0]).abs() < 1e-4
                && (ground.position[1] - want[1]).abs() < 1e-4,
            "{k}: {:?} vs {want:?}",
            ground.position
        );
        let zen = (-t.beam[2]).acos().to_degrees();
        assert!((zen - 20.0).abs() < 0.6, "{zen}");
    }
}

#[test]
fn bad_scenes_name_the_field() {
    let err = |text: &str| -> String {
        let scene: WorldScene = match parse_toml(text, "s") {
            Ok(s) => s,
            Err(e) => return e.to_string(),
        };
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes");
        let sensor = scene.resolve_sensor(&base).unwrap();
        scene.validate(&sensor).unwrap_err().to_string()
    };
    let line = "[flight]\nlines = [{ start_m = [0.0, 0.0], end_m = [1.0, 0.0] }]\n";
    assert!(
        err(&format!(
            "effects = [\"multiple_scattering\"]\n{line}{SENSOR}"
        ))
        .contains("multiple_scattering")
    );
    assert!(err(&format!("effects = [\"noise\"]\n{line}{SENSOR}")).contains("noise"));
    assert!(err(&format!("effects = [\"sparkle\"]\n{line}{SENSOR}")).contains("effects"));
    assert!(err(&format!("[[tree]]\nposition_m = [0.0, 0.0]\nheight_m = 5.0\ncrown = {{ base_m = 6.0, radius_m = 1.0 }}\n{line}{SENSOR}")).contains("tree.crown.base_m"));
    assert!(err(&format!("[[grass]]\nrectangle_m = [1.0, 0.0, 0.0, 1.0]\nheight_m = 1.0\nleaf_area_density = 1.0\n{line}{SENSOR}")).contains("grass.rectangle_m"));
    assert!(err(&format!("[[box]]\nrectangle_m = [0.0, 0.0, 1.0, 1.0]\nheight_m = 3.0\nmaterial = \"unobtainium\"\n{line}{SENSOR}")).contains("unobtainium"));
    assert!(err(&format!("[flight]\nlines = []\n{SENSOR}")).contains("flight.lines"));
    assert!(err(&format!("{line}scan = {{ pattern = \"palmer\", half_angle_deg = 70.0, rate_hz = 10.0 }}\n{SENSOR}")).contains("half_angle_deg"));
}

#[test]
fn the_normal_quantile_matches_known_values_and_draws_are_normal() {
    for (p, z) in [
        (0.5, 0.0),
        (0.975, 1.959_963_984_540_054),
        (0.841_344_746_068_543, 1.0),
        (0.001, -3.090_232_306_167_813),
        (1e-9, -5.997_807_015_007_686),
        (0.02, -2.053_748_910_631_823),
    ] {
        let got = normal_quantile(p);
        assert!(
            (got - z).abs() < 1e-8 * z.abs().max(1.0),
            "Φ⁻¹({p}) = {got}, want {z}"
        );
        assert!((normal_quantile(1.0 - p) + z).abs() < 1e-8 * z.abs().max(1.0));
    }
    let mut n = Normals { rng: rng(7, 1) };
    let draws: Vec<f64> = (0..200_000).map(|_| n.next()).collect();
    let mean = draws.iter().sum::<f64>() / draws.len() as f64;
    let var = draws.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / draws.len() as f64;
    let beyond3 = draws.iter().filter(|d| d.abs() > 3.0).count() as f64 / draws.len() as f64;
    assert!(
        mean.abs() < 0.01 && (var - 1.0).abs() < 0.01,
        "{mean} {var}"
    );
    assert!((beyond3 / 0.0027 - 1.0).abs() < 0.15, "tails {beyond3}");
}

#[test]
fn media_render_the_same_from_the_kernel_tables_and_one_by_one() {
    // Ringing listed with a zero amplitude sends the media's bins through the exact path.
    let scene = |effects: &str| {
        format!(
            "effects = [{effects}]\nringing = {{ amplitude = 0.0 }}\n\
             [[tree]]\nposition_m = [0.3, 0.0]\nheight_m = 14.0\nleaf_area_density = 0.9\n\
             crown = {{ shape = \"cone\", base_m = 4.0, radius_m = 3.0 }}\n\
             [[grass]]\nrectangle_m = [-5.0, -5.0, 5.0, 5.0]\nheight_m = 0.7\nleaf_area_density = 1.5\n\
             [flight]\npulse_rate_hz = 1000.0\nlines = [{{ start_m = [0.0, -1.0], end_m = [0.0, 1.0] }}]\n\
             {SENSOR}receiver_fwhm_ns = 3.0\n"
        )
    };
    let a = pulses(&mut world(&scene("")));
    let b = pulses(&mut world(&scene("\"ringing\"")));
    assert_eq!(a.len(), b.len());
    for ((_, ta), (_, tb)) in a.iter().zip(&b) {
        assert!(ta.scatterers.iter().any(|s| s.kind == ObjectKind::Crown));
        let peak = ta.clean.iter().cloned().fold(0.0, f64::max);
        for (x, y) in ta.clean.iter().zip(&tb.clean) {
            assert!((x - y).abs() < 1e-9 * peak, "{x} vs {y}");
        }
    }
}

#[test]
fn a_geotiff_terrain_is_hit_at_the_dem_height() {
    // A real DEM (IGN LiDAR HD, 0.5 m cells), placed with its centre at the scene origin.
    let tif =
        crate::fixtures::path("dem/ign_lidarhd/DTM_test_data_77055_627760_LA93_IGN69_50CM.tif");
    let mut sim = world(&format!(
        "effects = [\"off_nadir\"]\n[terrain]\nkind = \"geotiff\"\npath = \"{}\"\n\
         [flight]\npulse_rate_hz = 2000.0\nlines = [{{ start_m = [-20.0, 0.0], end_m = [20.0, 0.0] }}]\n\
         scan = {{ pattern = \"oscillating\", half_angle_deg = 1.0, rate_hz = 30.0 }}\n{SENSOR}",
        tif.display()
    ));
    let ps = pulses(&mut sim);
    assert!(ps.len() > 1000);
    let geo = sim.geometry();
    let mut heights = Vec::new();
    for (_, t) in &ps {
        let g = t.scatterers.last().unwrap();
        assert_eq!(g.kind, ObjectKind::Terrain);
        let want = geo.ground_height(g.position[0], g.position[1]).unwrap();
        assert!(
            (g.position[2] - want).abs() < 1e-3,
            "{:?} vs {want}",
            g.position
        );
        heights.push(want);
    }
    // Real relief: the heights vary along the swath.
    let (lo, hi) = heights
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &h| {
            (a.min(h), b.max(h))
        });
    assert!(hi - lo > 0.05, "{lo}..{hi}");
}

#[test]
fn poisson_noise_grows_with_the_signal() {
    let mut sim = world(&nadir_line(
        "seed = 9\neffects = [\"noise\"]\n[noise]\nkind = \"poisson\"\nphotons_per_dn = 2.0\n",
        "",
    ));
    let ps = pulses(&mut sim);
    // Residuals where the echo is strong against where there is only the baseline.
    let (mut strong, mut dark) = (Vec::new(), Vec::new());
    for (p, t) in &ps {
        for (i, &r) in p.raw_of(1).iter().enumerate() {
            let d = r as f64 / 64.0 - (12.0 + t.clean[i]);
            if t.clean[i] > 40.0 {
                strong.push((d, t.clean[i]));
            } else if t.clean[i] == 0.0 {
                dark.push(d);
            }
        }
    }
    assert!(
        dark.iter().all(|d| d.abs() < 1.0 / 64.0),
        "no dark noise configured"
    );
    // Variance of counts = signal / photons_per_dn.
    let var: f64 = strong.iter().map(|(d, c)| d * d / (c / 2.0)).sum::<f64>() / strong.len() as f64;
    assert!(
        (var - 1.0).abs() < 0.25,
        "normalised variance {var} over {}",
        strong.len()
    );
}

#[test]
fn navigation_effects_change_the_navigation_only_when_named() {
    let run = |effects: &str| {
        let text = format!(
            "seed = 2\neffects = [{effects}]\n[flight]\npulse_rate_hz = 1000.0\n\
             lines = [{{ start_m = [0.0, 0.0], end_m = [120.0, 0.0] }}]\n{SENSOR}\
             [navigation]\nrate_hz = 20.0\nnoise = {{ position_m = 0.5, attitude_deg = 0.01 }}\n\
             dropouts = [{{ start_s = 0.5, duration_s = 0.25 }}]\n"
        );
        let items = WorldItems::new(world(&text)).unwrap();
        let mut nav = Vec::new();
        let mut pulses = 0;
        for item in items {
            match item {
                SimItem::Nav {
                    receive_time_ns,
                    bytes,
                } => nav.push((receive_time_ns, bytes)),
                SimItem::Pulse(_) => pulses += 1,
            }
        }
        (nav, pulses)
    };
    let (plain, n0) = run("");
    let (noisy, n1) = run("\"navigation_noise\"");
    let (gappy, n2) = run("\"navigation_dropouts\"");
    assert_eq!((n0, n1, n2), (2001, 2001, 2001), "pulses are not touched");
    assert_eq!(plain.len(), noisy.len());
    assert!(
        plain
            .iter()
            .zip(&noisy)
            .all(|(a, b)| a.0 == b.0 && a.1 != b.1)
    );
    // 0.5..0.75 s at 20 Hz: epochs 10..14 are not sent.
    assert_eq!(gappy.len(), plain.len() - 5);
    let t0 = plain[0].0;
    assert!(gappy.iter().all(|(t, _)| {
        let dt = (t - t0) as f64 * 1e-9;
        !(0.5 - 1e-6..0.75 - 1e-6).contains(&dt)
    }));
}

#[test]
fn other_pulse_shapes_keep_their_energy_and_their_peak_at_t0() {
    let run = |shape: &str, rx: f64| {
        let mut sim = world(&nadir_line(
            "",
            &format!("outgoing_fwhm_ns = 8.0\nreceiver_fwhm_ns = {rx}\npulse_shape = {shape}\n"),
        ));
        let mpn = sim.metres_per_ns();
        let (p, t) = pulses(&mut sim).remove(0);
        let start = p.segments[1].start_ns;
        let te = t.origin[2] / mpn;
        (t, start, te, p)
    };
    let s8 = sigma(8.0);
    // A bi-Gaussian with equal halves is the Gaussian, and a measured Gaussian too.
    let (g, start, te, _) = run("{ kind = \"gaussian\" }", 3.0);
    let (b, _, _, _) = run(
        "{ kind = \"bigaussian\", rise_ns = 4.0, fall_ns = 4.0 }",
        3.0,
    );
    let measured: Vec<String> = (-100..=100)
        .map(|k| {
            let z = k as f64 * 0.25 / s8;
            format!("{:.12}", 7.0 * (-0.5 * z * z).exp())
        })
        .collect();
    let (m, _, _, _) = run(
        &format!(
            "{{ kind = \"measured\", sample_ns = 0.25, samples = [{}] }}",
            measured.join(", ")
        ),
        3.0,
    );
    let peak = g.clean.iter().cloned().fold(0.0, f64::max);
    for i in 0..g.clean.len() {
        assert!(
            (g.clean[i] - b.clean[i]).abs() < 1e-4 * peak,
            "bi-Gaussian bin {i}"
        );
        assert!(
            (g.clean[i] - m.clean[i]).abs() < 2e-3 * peak,
            "measured bin {i}"
        );
    }
    // An asymmetric pulse (1.5 ns rise, 6 ns fall): its echo peaks at 2R/c (no receiver
    // blur), trails behind, and carries the area √(2π)(σr + σf)/2 times the amplitude.
    let (a, start_a, te_a, p) = run(
        "{ kind = \"bigaussian\", rise_ns = 1.5, fall_ns = 6.0 }",
        0.0,
    );
    let k = (0..a.clean.len())
        .max_by(|&i, &j| a.clean[i].total_cmp(&a.clean[j]))
        .unwrap();
    assert!(
        (start_a + k as f64 - te_a).abs() <= 0.5,
        "peak at {}",
        start_a + k as f64
    );
    let (area, mean, _) = moments(&a.clean, start_a, 1.0);
    assert!(mean > te_a + 1.0, "the fall trails: mean {mean} vs {te_a}");
    let amp = a.scatterers[0].amplitude_dn;
    let want = amp * (2.0 * std::f64::consts::PI).sqrt() * (1.5 + 6.0) / FWHM_PER_SIGMA;
    assert!((area / want - 1.0).abs() < 1e-3, "area {area} vs {want}");
    // The truth keeps that energy in its 2 ns pulse.
    let (area_t, _, _) = moments(&a.truth, start_a, 1.0);
    assert!((area_t / area - 1.0).abs() < 1e-3);
    // The recorded outgoing pulse has the same shape, peak at t0.
    let out = p.raw_of(0);
    let k0 = (0..out.len()).max_by_key(|&i| out[i]).unwrap();
    assert!((p.segments[0].start_ns + k0 as f64).abs() <= 0.5);
    let _ = (start, te);
    // Bad shapes name the field.
    let scene: WorldScene = parse_toml(
        &nadir_line(
            "",
            "pulse_shape = { kind = \"bigaussian\", rise_ns = 0.0, fall_ns = 3.0 }\n",
        ),
        "s",
    )
    .unwrap();
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes");
    let sensor = scene.resolve_sensor(&base).unwrap();
    assert!(
        scene
            .validate(&sensor)
            .unwrap_err()
            .to_string()
            .contains("sensor.pulse_shape")
    );
}
