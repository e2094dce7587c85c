use super::*;
use crate::pulse::FittedReturn;
use crate::pulse::testing::apply;

/// Two-way time of a target at `range_m` with the default refractive index, ns.
fn two_way_ns(range_m: f64) -> f64 {
    range_m / CalibrateConfig::default().metres_per_ns()
}

/// Counts of a Gaussian of peak `amp` and standard deviation `sigma` samples at `mu` on a
/// 10-count pedestal, `n` samples.
fn gaussian_counts(n: usize, mu: f64, sigma: f64, amp: f64) -> Vec<u16> {
    (0..n)
        .map(|i| {
            let d = (i as f64 - mu) / sigma;
            (10.0 + amp * (-0.5 * d * d).exp()).round() as u16
        })
        .collect()
}

/// A raw pulse (signal empty, 1 ns sampling, volts = counts): an outgoing pulse of peak
/// `outgoing_peak` counts peaking exactly at `emission_ns` (an integer), a 64-sample return
/// segment around `return_ns`, and one fitted return of `amplitude` volts at `return_ns`.
fn pulse(outgoing_peak: f64, emission_ns: f64, return_ns: f64, amplitude: f32) -> Pulse {
    let mut p = Pulse::default();
    p.push_segment(
        SegmentKind::Outgoing,
        0,
        emission_ns - 16.0,
        gaussian_counts(33, 16.0, 3.0, outgoing_peak),
    );
    let start = return_ns.floor() - 32.0;
    let seg = p.push_segment(
        SegmentKind::Return,
        0,
        start,
        gaussian_counts(64, return_ns - start, 3.0, amplitude as f64),
    );
    p.returns.push(FittedReturn {
        segment: seg as u16,
        position_bins: (return_ns - start) as f32,
        time_ns: return_ns,
        amplitude,
        ..Default::default()
    });
    p
}

/// A LAS-like pulse: one return segment starting at t0 = 0 (its first sample), no outgoing.
fn las_like(amplitude: f32) -> Pulse {
    let mut p = Pulse::default();
    p.push_segment(
        SegmentKind::Return,
        0,
        0.0,
        gaussian_counts(64, 30.0, 3.0, 100.0),
    );
    p.returns.push(FittedReturn {
        segment: 0,
        position_bins: 30.0,
        time_ns: 30.0,
        amplitude,
        ..Default::default()
    });
    p
}

fn calibrate(config: CalibrateConfig, pulses: impl IntoIterator<Item = Pulse>) -> Vec<Box<Pulse>> {
    let stage = Calibrate::try_new(config).unwrap();
    apply(pulses, |p| stage.calibrate(p)).emitted
}

fn backscatter(config: CalibrateConfig, p: Pulse) -> f32 {
    calibrate(config, [p])[0].returns[0].backscatter
}

fn rel(a: f32, b: f32) -> f32 {
    (a / b - 1.0).abs()
}

/// The outgoing pulse's energy as the stage measures it, V·ns.
fn energy_of(p: &Pulse) -> f64 {
    let o = p.outgoing().unwrap();
    let s = p.segments[o];
    let x: Vec<f32> = p.raw_of(o).iter().map(|&c| c as f32).collect();
    outgoing_facts(&x, s.start_ns, p.sample_ns)
        .unwrap()
        .energy_v_ns
}

#[test]
fn a_flat_target_at_two_ranges_has_equal_backscatter_with_range_on_and_r2_ratio_off() {
    // An extended target returns 1/R²: the same surface at 800 m and 1200 m.
    let (r1, r2) = (800.0, 1200.0);
    let k = 0.5 * 1000.0f64 * 1000.0;
    let a = |r: f64| (k / (r * r)) as f32;
    let near = || pulse(200.0, 0.0, two_way_ns(r1), a(r1));
    let far = || pulse(200.0, 0.0, two_way_ns(r2), a(r2));
    let on = CalibrateConfig::default();
    let (b1, b2) = (backscatter(on.clone(), near()), backscatter(on, far()));
    assert!(b1.is_finite() && b1 > 0.0);
    assert!(
        rel(b1, b2) < 1e-5,
        "range on: {b1} at {r1} m, {b2} at {r2} m"
    );
    let off = CalibrateConfig {
        range: false,
        ..Default::default()
    };
    let (b1, b2) = (backscatter(off.clone(), near()), backscatter(off, far()));
    let expected = ((r2 / r1) * (r2 / r1)) as f32;
    assert!(
        rel(b1 / b2, expected) < 1e-5,
        "range off: ratio {}",
        b1 / b2
    );
}

#[test]
fn the_emission_is_the_outgoing_peak_and_the_range_counts_from_it() {
    let run = calibrate(
        CalibrateConfig::default(),
        [pulse(200.0, 5.0, 5.0 + two_way_ns(1000.0), 1.0)],
    );
    let cal = run[0].calibration.unwrap();
    assert!((cal.emission_ns - 5.0).abs() < 1e-9, "{cal:?}");
    assert!(cal.range_normalised);
    assert!((cal.range_m(5.0 + two_way_ns(1000.0)) - 1000.0).abs() < 1e-9);
    // At the reference range the range factor is 1: backscatter = amplitude × scale.
    let b = run[0].returns[0].backscatter;
    assert!(rel(b, cal.scale) < 1e-6, "{b} vs scale {}", cal.scale);
    // Sub-sample peak: the vertex of the parabola through the peak and its neighbours, and the
    // energy above the median of the first 8 samples.
    let x = [
        0.0f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 4.0, 2.0, 0.0,
    ];
    let f = outgoing_facts(&x, 10.0, 0.5).unwrap();
    // Through (−1, 3), (0, 4), (1, 2): vertex at 0.5 · (3 − 2) / (3 − 8 + 2) = −1/6.
    let vertex = 9.0 - 1.0 / 6.0;
    assert!((f.peak_ns - (10.0 + vertex * 0.5)).abs() < 1e-9, "{f:?}");
    assert!((f.energy_v_ns - 9.0 * 0.5).abs() < 1e-9, "{f:?}");
    assert_eq!(outgoing_facts(&[], 0.0, 1.0), None);
}

#[test]
fn doubling_the_outgoing_pulse_halves_the_backscatter() {
    let t = two_way_ns(950.0);
    let p1 = || pulse(100.0, 0.0, t, 2.0);
    // The same shot with twice the outgoing pulse above its 10-count pedestal.
    let mut p2 = p1();
    let o = p2.segments[0].range();
    for c in &mut p2.raw[o] {
        *c = 2 * *c - 10;
    }
    assert!(rel((energy_of(&p2) / energy_of(&p1())) as f32, 2.0) < 1e-9);
    let b1 = backscatter(CalibrateConfig::default(), p1());
    let b2 = backscatter(CalibrateConfig::default(), p2);
    assert!(rel(b1 / b2, 2.0) < 1e-6, "{b1} / {b2}");
    // The energy factor is E_ref / E_out: 1 at the reference energy.
    let cfg = CalibrateConfig {
        reference_energy_v_ns: energy_of(&p1()),
        ..Default::default()
    };
    let cal = calibrate(cfg, [p1()])[0].calibration.unwrap();
    assert!(rel(cal.scale, 1.0) < 1e-6, "{cal:?}");
}

#[test]
fn the_system_constant_scales_and_comes_from_the_profile_when_left_out() {
    let t = two_way_ns(1000.0);
    let base = backscatter(CalibrateConfig::default(), pulse(200.0, 0.0, t, 1.0));
    let cfg = CalibrateConfig {
        system_constant_value: Some(2.5),
        ..Default::default()
    };
    let scaled = backscatter(cfg.clone(), pulse(200.0, 0.0, t, 1.0));
    assert!(rel(scaled, 2.5 * base) < 1e-6);
    // From the input's sensor profile when left out; a configured value wins.
    let mut sensor = crate::core::sensor::test_sensor();
    sensor.calibration_constant = 4.0;
    let facts = SourceFacts {
        sensor: Some(sensor),
        t0_is_emission: Some(true),
        ..Default::default()
    };
    let mut resolved = CalibrateConfig::default();
    resolved.resolve_from_input(&facts);
    assert_eq!(resolved.system_constant_value, Some(4.0));
    assert_eq!(resolved.t0_is_emission, Some(true));
    let from_profile = backscatter(resolved, pulse(200.0, 0.0, t, 1.0));
    assert!(rel(from_profile, 4.0 * base) < 1e-6);
    let mut kept = cfg;
    kept.resolve_from_input(&facts);
    assert_eq!(kept.system_constant_value, Some(2.5));
    // Nothing states it: 1.
    let mut none = CalibrateConfig::default();
    none.resolve_from_input(&SourceFacts::default());
    assert_eq!(none.system_constant_value, None);
    assert_eq!(backscatter(none, pulse(200.0, 0.0, t, 1.0)), base);
}

#[test]
fn each_switch_off_removes_exactly_its_factor() {
    let (range_m, amplitude) = (1300.0, 0.8f32);
    let t = two_way_ns(range_m);
    let p = || pulse(150.0, 0.0, t, amplitude);
    let c = 3.0;
    let all = CalibrateConfig {
        system_constant_value: Some(c),
        reference_energy_v_ns: 40.0,
        ..Default::default()
    };
    let full = backscatter(all.clone(), p());
    let range_factor = ((range_m / 1000.0) * (range_m / 1000.0)) as f32;
    let energy_factor = (40.0 / energy_of(&p())) as f32;
    assert!(rel(full, amplitude * c as f32 * range_factor * energy_factor) < 1e-5);
    let without = |f: fn(&mut CalibrateConfig)| {
        let mut cfg = all.clone();
        f(&mut cfg);
        backscatter(cfg, p())
    };
    assert!(rel(without(|c| c.range = false), full / range_factor) < 1e-5);
    assert!(rel(without(|c| c.energy = false), full / energy_factor) < 1e-5);
    assert!(rel(without(|c| c.system_constant = false), full / c as f32) < 1e-5);
    let none = without(|c| {
        c.range = false;
        c.energy = false;
        c.system_constant = false;
    });
    assert_eq!(none, amplitude);
}

#[test]
fn volts_are_made_from_counts_only_when_the_signal_is_empty() {
    let mut p = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    p.gain_v_per_dn = 0.5;
    p.offset_v = -0.25;
    let raw = p.raw.clone();
    let out = calibrate(CalibrateConfig::default(), [p]);
    assert_eq!(out[0].signal.len(), raw.len());
    for (v, c) in out[0].signal.iter().zip(&raw) {
        assert_eq!(*v, -0.25 + 0.5 * *c as f32);
    }
    // Switched off: the counts themselves, and the energy in counts·ns is twice the volts'.
    let mut p = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    p.gain_v_per_dn = 0.5;
    let out_counts = calibrate(
        CalibrateConfig {
            volts: false,
            ..Default::default()
        },
        [p],
    );
    for (v, c) in out_counts[0].signal.iter().zip(&raw) {
        assert_eq!(*v, *c as f32);
    }
    let (s_v, s_c) = (
        out[0].calibration.unwrap().scale,
        out_counts[0].calibration.unwrap().scale,
    );
    assert!(rel(s_v, 2.0 * s_c) < 1e-6, "{s_v} vs {s_c}");
    // A signal already filled (a denoise stage ran) is left as it is.
    let mut p = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    p.signal = p.raw.iter().map(|&c| c as f32 * 0.001).collect();
    let before = p.signal.clone();
    let out = calibrate(CalibrateConfig::default(), [p]);
    assert_eq!(out[0].signal, before);
}

#[test]
fn the_factor_applies_to_every_bin_and_is_nan_before_the_emission() {
    let t = two_way_ns(1000.0);
    let out = calibrate(CalibrateConfig::default(), [pulse(200.0, 0.0, t, 1.0)]);
    let p = &out[0];
    let cal = p.calibration.unwrap();
    let r = p.segments[1];
    for (i, &v) in p.signal_of(1).iter().enumerate() {
        let t_i = r.start_ns + i as f64 * p.sample_ns;
        let range = t_i * cal.metres_per_ns / 1000.0;
        let expected = v * cal.scale * (range * range) as f32;
        assert!(rel(cal.calibrated(v, t_i), expected) < 1e-5);
    }
    assert!(cal.factor_at(0.0).is_nan() && cal.factor_at(-3.0).is_nan());
    // A return before the emission gets no backscatter, and is noted.
    let mut early = pulse(200.0, 100.0, t, 1.0);
    early.returns[0].time_ns = 50.0;
    let stage = Calibrate::new(CalibrateConfig::default());
    let run = apply([early], |p| stage.calibrate(p));
    assert!(run.emitted[0].returns[0].backscatter.is_nan());
    assert_eq!(run.notes.get("return_before_emission"), 1);
}

#[test]
fn pulses_without_outgoing_or_range_follow_the_policies_and_are_counted() {
    let c = CalibrateConfig {
        system_constant_value: Some(2.0),
        ..Default::default()
    };
    // LAS-like (t0 = first sample): no range, no energy; passed unscaled, both noted.
    let las = CalibrateConfig {
        t0_is_emission: Some(false),
        ..c.clone()
    };
    let stage = Calibrate::new(las.clone());
    let run = apply([las_like(0.5), las_like(0.25)], |p| stage.calibrate(p));
    assert_eq!(run.emitted.len(), 2);
    assert_eq!(run.notes.get("range_unknown"), 2);
    assert_eq!(run.notes.get("no_outgoing"), 2);
    let cal = run.emitted[0].calibration.unwrap();
    assert!(!cal.range_normalised);
    assert_eq!(cal.scale, 2.0);
    assert_eq!(run.emitted[1].returns[0].backscatter, 0.5);
    // Dropped and counted under the reason, range first.
    for (cfg, reason) in [
        (
            CalibrateConfig {
                range_unknown: UnknownPolicy::Drop,
                ..las.clone()
            },
            "range_unknown",
        ),
        (
            CalibrateConfig {
                energy_unknown: UnknownPolicy::Drop,
                ..las.clone()
            },
            "no_outgoing",
        ),
    ] {
        let stage = Calibrate::new(cfg);
        let run = apply([las_like(0.5), pulse(200.0, 0.0, 7000.0, 1.0)], |p| {
            stage.calibrate(p)
        });
        assert_eq!(run.emitted.len(), 1, "{reason}");
        assert_eq!(run.dropped.get(reason), 1, "{reason}");
        assert_eq!(run.errors, 0);
    }
    // A capture without outgoing segment times from emission: the range is known.
    let mut no_out = pulse(200.0, 0.0, two_way_ns(2000.0), 1.0);
    no_out.segments.remove(0);
    let stage = Calibrate::new(CalibrateConfig {
        t0_is_emission: Some(true),
        ..c.clone()
    });
    let run = apply([no_out], |p| stage.calibrate(p));
    let cal = run.emitted[0].calibration.unwrap();
    assert!(cal.range_normalised && cal.emission_ns == 0.0);
    assert!(rel(run.emitted[0].returns[0].backscatter, 2.0 * 4.0) < 1e-5);
    assert_eq!(run.notes.get("no_outgoing"), 1);
    assert_eq!(run.notes.get("range_unknown"), 0);
    // A flat outgoing pulse has no energy (and gives no emission time).
    let mut flat = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    let o = flat.segments[0].range();
    flat.raw[o.clone()].fill(10);
    let stage = Calibrate::new(c.clone());
    let run = apply([flat], |p| stage.calibrate(p));
    assert_eq!(run.notes.get("bad_outgoing_energy"), 1);
    assert_eq!(run.notes.get("range_unknown"), 1);
    let stage = Calibrate::new(CalibrateConfig {
        energy_unknown: UnknownPolicy::Drop,
        ..c
    });
    let mut flat = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    flat.raw[o].fill(10);
    let run = apply([flat], |p| stage.calibrate(p));
    assert_eq!(run.dropped.get("bad_outgoing_energy"), 1);
}

#[test]
fn unreadable_pulses_are_rejected_with_a_reason() {
    let good = || pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    let mut out_of_bounds = good();
    out_of_bounds.segments[1].len = 1000;
    let mut mismatch = good();
    mismatch.signal = vec![0.0; 3];
    let mut nan_gain = good();
    nan_gain.gain_v_per_dn = f32::NAN;
    let mut zero_interval = good();
    zero_interval.sample_ns = 0.0;
    let stage = Calibrate::new(CalibrateConfig::default());
    let run = apply(
        [good(), out_of_bounds, mismatch, nan_gain, zero_interval],
        |p| stage.calibrate(p),
    );
    assert_eq!(run.emitted.len(), 1);
    assert_eq!(run.errors, 4);
    assert_eq!(run.dropped.get("segment_out_of_bounds"), 1);
    assert_eq!(run.dropped.get("signal_length_mismatch"), 1);
    assert_eq!(run.dropped.get("bad_digitizer_parameters"), 2);
}

#[test]
fn an_invalid_configuration_is_refused() {
    for (bad, key) in [
        (
            CalibrateConfig {
                reference_range_m: 0.0,
                ..Default::default()
            },
            "reference_range_m",
        ),
        (
            CalibrateConfig {
                reference_energy_v_ns: f64::NAN,
                ..Default::default()
            },
            "reference_energy_v_ns",
        ),
        (
            CalibrateConfig {
                system_constant_value: Some(-1.0),
                ..Default::default()
            },
            "system_constant_value",
        ),
        (
            CalibrateConfig {
                refractive_index: 0.9,
                ..Default::default()
            },
            "refractive_index",
        ),
    ] {
        let e = bad.validate().unwrap_err();
        assert!(e.to_string().starts_with(key), "{e}");
        assert!(Calibrate::try_new(bad.clone()).is_err());
    }
    assert!(CalibrateConfig::default().validate().is_ok());
}

#[test]
fn the_signal_buffer_is_reused() {
    let mut p = pulse(200.0, 0.0, two_way_ns(1000.0), 1.0);
    p.signal = Vec::with_capacity(1000);
    let out = calibrate(CalibrateConfig::default(), [p]);
    assert_eq!(out[0].signal.capacity(), 1000);
}
