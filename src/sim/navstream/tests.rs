//! Unit tests of the navigation stream: configuration, noise statistics, dropouts, determinism
//! and the NovAtel byte layouts. Round trips through the decoders and the comparison with the
//! real SPAN log are in `tests/sim_navstream.rs`.

use super::*;

fn truth() -> NavFix {
    NavFix {
        utc_time_of_day_s: 0.0,
        lat_deg: -24.99,
        lon_deg: 31.59,
        altitude_m: 1000.0,
        heading_deg: 90.0,
        roll_deg: 1.5,
        pitch_deg: -0.5,
    }
}

fn stream(config: NavigationConfig, seed: u64) -> NavStream {
    NavStream::new(config, seed).expect("valid configuration")
}

/// Runs `n` epochs at the configured rate from 345 600 s; the bytes of each and the records.
fn run(s: &mut NavStream, n: u64) -> (Vec<Vec<u8>>, Vec<EpochRecord>) {
    let (mut bytes, mut records) = (Vec::new(), Vec::new());
    for k in 0..n {
        let t = s.epoch_gps_s(345_600.0, k);
        let mut out = Vec::new();
        let sent = s.epoch_bytes(t, &truth(), &mut out);
        assert_eq!(sent, !out.is_empty(), "epoch {k}");
        let r = *s.last_epoch().unwrap();
        assert_eq!((r.index, r.dropped.is_none()), (k, sent));
        bytes.push(out);
        records.push(r);
    }
    (bytes, records)
}

#[test]
fn defaults_and_a_full_table_parse() {
    let c = NavigationConfig::from_toml_str("[navigation]\n").unwrap();
    assert_eq!(c, NavigationConfig::default());
    assert_eq!(NavigationConfig::from_toml_str("").unwrap(), c);
    assert_eq!(c.rate_hz, 10.0);
    assert_eq!(c.formats, vec![StreamFormat::Nmea]);
    assert_eq!((c.gps_week, c.gps_utc_offset_s), (1690, 18.0));
    let c = NavigationConfig::from_toml_str(
        r#"
        [navigation]
        rate_hz = 20.0
        formats = ["novatel", "nmea"]
        gps_week = 2300
        gps_utc_offset_s = 17
        noise = { position_m = 0.05, attitude_deg = 0.005, heading_deg = 0.02 }
        dropouts = [{ start_s = 12.0, duration_s = 3.5 }, { start_s = 0, duration_s = 0.1 }]
        random_dropout_probability = 0.01
        "#,
    )
    .unwrap();
    assert_eq!(c.formats, vec![StreamFormat::Novatel, StreamFormat::Nmea]);
    assert_eq!(c.gps_utc_offset_s, 17.0);
    assert_eq!(
        c.noise,
        Some(NavNoise {
            position_m: 0.05,
            attitude_deg: 0.005,
            heading_deg: 0.02
        })
    );
    assert_eq!(c.dropouts.len(), 2);
    // Omitted noise fields are 0.
    let c = NavigationConfig::from_toml_str("[navigation]\nnoise = { heading_deg = 0.1 }").unwrap();
    assert_eq!(c.noise.unwrap().position_m, 0.0);
}

#[test]
fn toml_parse_errors_name_the_field() {
    for (text, field) in [
        (
            "[navigation]\nformats = [\"nmea\", \"ubx\"]",
            "navigation.formats[1]",
        ),
        ("[navigation]\nrate = 10.0", "navigation.rate"),
        ("[navigation]\nrate_hz = \"fast\"", "navigation.rate_hz"),
        (
            "[navigation]\nnoise = { position = 1.0 }",
            "navigation.noise.position",
        ),
        (
            "[navigation]\ndropouts = [{ start_s = 1.0 }]",
            "navigation.dropouts[0]",
        ),
        ("[navigation]\ngps_week = -3", "navigation.gps_week"),
        ("[nav]\n", "nav"),
    ] {
        match NavigationConfig::from_toml_str(text) {
            Err(NavStreamError::Parse { field: f, message }) => {
                assert_eq!(f, field, "{text}: {message}")
            }
            other => panic!("{text}: {other:?}"),
        }
    }
    let e = NavigationConfig::from_toml_str("[navigation]\nformats = [\"ubx\"]").unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("navigation.formats[0]") && msg.contains("ubx"),
        "{msg}"
    );
    assert!(msg.contains("nmea") && msg.contains("novatel"), "{msg}");
}

#[test]
fn validation_names_the_field() {
    for (text, field, reason) in [
        ("rate_hz = 0.0", "navigation.rate_hz", "must be > 0"),
        ("rate_hz = -5.0", "navigation.rate_hz", "must be > 0"),
        ("rate_hz = nan", "navigation.rate_hz", "must be > 0"),
        ("rate_hz = 200.0", "navigation.rate_hz", "at most 100"),
        ("formats = []", "navigation.formats", "at least one"),
        (
            "formats = [\"nmea\", \"nmea\"]",
            "navigation.formats[1]",
            "repeats",
        ),
        ("gps_week = 0", "navigation.gps_week", "1..=65535"),
        ("gps_week = 70000", "navigation.gps_week", "1..=65535"),
        (
            "gps_utc_offset_s = 17.5",
            "navigation.gps_utc_offset_s",
            "whole",
        ),
        (
            "gps_utc_offset_s = -1",
            "navigation.gps_utc_offset_s",
            "whole",
        ),
        (
            "noise = { position_m = -0.1 }",
            "navigation.noise.position_m",
            ">= 0",
        ),
        (
            "noise = { attitude_deg = inf }",
            "navigation.noise.attitude_deg",
            ">= 0",
        ),
        (
            "noise = { heading_deg = -1 }",
            "navigation.noise.heading_deg",
            ">= 0",
        ),
        (
            "dropouts = [{ start_s = 1, duration_s = 1 }, { start_s = -1.0, duration_s = 1 }]",
            "navigation.dropouts[1].start_s",
            ">= 0",
        ),
        (
            "dropouts = [{ start_s = 1, duration_s = -2 }]",
            "navigation.dropouts[0].duration_s",
            "> 0",
        ),
        (
            "dropouts = [{ start_s = 1, duration_s = 0 }]",
            "navigation.dropouts[0].duration_s",
            "> 0",
        ),
        (
            "random_dropout_probability = 1.5",
            "navigation.random_dropout_probability",
            "0..=1",
        ),
    ] {
        let text = format!("[navigation]\n{text}\n");
        match NavigationConfig::from_toml_str(&text) {
            Err(e @ NavStreamError::Invalid { .. }) => {
                let NavStreamError::Invalid {
                    field: f,
                    reason: r,
                } = &e
                else {
                    unreachable!()
                };
                assert_eq!(f, field, "{text}");
                assert!(r.contains(reason), "{text}: {r}");
                assert!(e.to_string().starts_with(field), "{e}");
            }
            other => panic!("{text}: {other:?}"),
        }
    }
    // 200 Hz is fine for NovAtel alone (millisecond header times).
    let c = NavigationConfig {
        rate_hz: 200.0,
        formats: vec![StreamFormat::Novatel],
        ..Default::default()
    };
    assert!(NavStream::new(c, 0).is_ok());
    let bad = NavigationConfig {
        rate_hz: 0.0,
        ..Default::default()
    };
    assert_eq!(
        NavStream::new(bad, 0).unwrap_err().to_string(),
        "navigation.rate_hz must be > 0 (got 0)"
    );
}

#[test]
fn without_noise_the_truth_is_reported_exactly() {
    let config = NavigationConfig {
        formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
        ..Default::default()
    };
    let mut s = stream(config, 7);
    let (bytes, records) = run(&mut s, 50);
    assert!(bytes.iter().all(|b| !b.is_empty()));
    for r in &records {
        assert_eq!(r.errors, NavErrors::default());
        let t = truth();
        let p = r.reported;
        assert_eq!(
            (p.lat_deg, p.lon_deg, p.altitude_m),
            (t.lat_deg, t.lon_deg, t.altitude_m)
        );
        assert_eq!(
            (p.roll_deg, p.pitch_deg, p.heading_deg),
            (t.roll_deg, t.pitch_deg, t.heading_deg)
        );
        assert!((p.utc_time_of_day_s - (r.gps_s - 18.0).rem_euclid(86_400.0)).abs() < 1e-12);
    }
    // Noise configured with zero sigmas changes nothing either.
    let zero = NavigationConfig {
        noise: Some(NavNoise::default()),
        ..Default::default()
    };
    let (zbytes, _) = run(&mut stream(zero, 7), 50);
    let (nbytes, _) = run(&mut stream(NavigationConfig::default(), 7), 50);
    assert_eq!(zbytes, nbytes);
    assert_eq!(noisy_fix(&truth(), &NavErrors::default()), truth());
}

/// Mean and standard deviation.
fn stats(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

#[test]
fn noise_has_zero_mean_and_the_configured_sigma() {
    let noise = NavNoise {
        position_m: 0.5,
        attitude_deg: 0.05,
        heading_deg: 0.2,
    };
    let config = NavigationConfig {
        noise: Some(noise),
        formats: vec![StreamFormat::Novatel],
        ..Default::default()
    };
    let mut s = stream(config, 42);
    let (_, records) = run(&mut s, 5000);
    let t = truth();
    let (m, n) = radii(t.lat_deg.to_radians());
    type Column = (&'static str, f64, Box<dyn Fn(&EpochRecord) -> f64>);
    let columns: [Column; 9] = [
        ("north", noise.position_m, Box::new(|r| r.errors.north_m)),
        ("east", noise.position_m, Box::new(|r| r.errors.east_m)),
        ("up", noise.position_m, Box::new(|r| r.errors.up_m)),
        ("roll", noise.attitude_deg, Box::new(|r| r.errors.roll_deg)),
        (
            "pitch",
            noise.attitude_deg,
            Box::new(|r| r.errors.pitch_deg),
        ),
        (
            "heading",
            noise.heading_deg,
            Box::new(|r| r.errors.heading_deg),
        ),
        // The reported values carry the same errors.
        (
            "reported north",
            noise.position_m,
            Box::new(move |r| (r.reported.lat_deg - t.lat_deg).to_radians() * m),
        ),
        (
            "reported east",
            noise.position_m,
            Box::new(move |r| {
                (r.reported.lon_deg - t.lon_deg).to_radians() * n * t.lat_deg.to_radians().cos()
            }),
        ),
        (
            "reported heading",
            noise.heading_deg,
            Box::new(move |r| r.reported.heading_deg - t.heading_deg),
        ),
    ];
    for (name, sigma, f) in &columns {
        let v: Vec<f64> = records.iter().map(f).collect();
        let (mean, std) = stats(&v);
        // The mean of 5000 draws has a standard error of sigma / 70.7: 4 of them is 0.057.
        assert!(
            mean.abs() < 0.057 * sigma,
            "{name}: mean {mean}, sigma {sigma}"
        );
        assert!(
            (std / sigma - 1.0).abs() < 0.10,
            "{name}: std {std}, sigma {sigma}"
        );
    }
    // Independent components: north and east uncorrelated (|r| < 0.05, 3.5 standard errors).
    let north: Vec<f64> = records.iter().map(|r| r.errors.north_m).collect();
    let east: Vec<f64> = records.iter().map(|r| r.errors.east_m).collect();
    let r = north.iter().zip(&east).map(|(a, b)| a * b).sum::<f64>()
        / (north.iter().map(|a| a * a).sum::<f64>() * east.iter().map(|b| b * b).sum::<f64>())
            .sqrt();
    assert!(r.abs() < 0.05, "correlation {r}");
}

#[test]
fn dropouts_remove_exactly_the_configured_epochs() {
    let config = NavigationConfig {
        dropouts: vec![
            Dropout {
                start_s: 0.3,
                duration_s: 0.2,
            },
            Dropout {
                start_s: 1.0,
                duration_s: 0.05,
            },
            Dropout {
                start_s: 2.95,
                duration_s: 10.0,
            },
        ],
        formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
        ..Default::default()
    };
    let (bytes, records) = run(&mut stream(config, 1), 40);
    let lost: Vec<u64> = records
        .iter()
        .filter(|r| r.dropped.is_some())
        .map(|r| r.index)
        .collect();
    // [0.3, 0.5): epochs 3, 4; [1.0, 1.05): epoch 10; [2.95, 12.95): epochs 30..=39.
    let mut want = vec![3, 4, 10];
    want.extend(30..40);
    assert_eq!(lost, want);
    assert!(
        records
            .iter()
            .all(|r| r.dropped.is_none_or(|d| d == DropReason::Dropout))
    );
    assert!(want.iter().all(|&k| bytes[k as usize].is_empty()));
    // The epochs around an outage are as without it.
    let (clean, _) = run(
        &mut stream(
            NavigationConfig {
                formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
                ..Default::default()
            },
            1,
        ),
        40,
    );
    for k in (0..40).filter(|k| !want.contains(k)) {
        assert_eq!(bytes[k as usize], clean[k as usize], "epoch {k}");
    }
}

#[test]
fn random_dropouts_follow_the_probability_and_leave_the_noise_alone() {
    let noise = Some(NavNoise {
        position_m: 1.0,
        attitude_deg: 0.1,
        heading_deg: 0.1,
    });
    let lossy = NavigationConfig {
        noise,
        random_dropout_probability: 0.2,
        ..Default::default()
    };
    let (bytes, records) = run(&mut stream(lossy, 9), 5000);
    let lost = records
        .iter()
        .filter(|r| r.dropped == Some(DropReason::Random))
        .count();
    // Binomial(5000, 0.2): mean 1000, standard deviation 28.3; 4.5 of them.
    assert!((lost as i64 - 1000).abs() < 127, "{lost} lost");
    assert_eq!(bytes.iter().filter(|b| b.is_empty()).count(), lost);
    // The errors drawn do not depend on the losses.
    let (_, clean) = run(
        &mut stream(
            NavigationConfig {
                noise,
                ..Default::default()
            },
            9,
        ),
        5000,
    );
    assert!(
        records
            .iter()
            .zip(&clean)
            .all(|(a, b)| a.errors == b.errors)
    );
    let all = NavigationConfig {
        random_dropout_probability: 1.0,
        ..Default::default()
    };
    let (bytes, _) = run(&mut stream(all, 9), 100);
    assert!(bytes.iter().all(|b| b.is_empty()));
}

#[test]
fn the_same_seed_gives_the_same_bytes_and_another_seed_other_bytes() {
    let config = NavigationConfig {
        formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
        noise: Some(NavNoise {
            position_m: 0.1,
            attitude_deg: 0.01,
            heading_deg: 0.05,
        }),
        random_dropout_probability: 0.1,
        ..Default::default()
    };
    let (a, _) = run(&mut stream(config.clone(), 123), 300);
    let (b, _) = run(&mut stream(config.clone(), 123), 300);
    let (c, _) = run(&mut stream(config, 124), 300);
    assert_eq!(a, b);
    assert_ne!(a, c);
    let differing = a.iter().zip(&c).filter(|(x, y)| x != y).count();
    assert!(differing > 250, "only {differing} of 300 epochs differ");
}

#[test]
fn bad_input_is_not_sent_and_does_not_panic() {
    let mut s = stream(
        NavigationConfig {
            formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
            dropouts: vec![Dropout {
                start_s: 0.0,
                duration_s: 0.05,
            }],
            ..Default::default()
        },
        0,
    );
    let mut out = Vec::new();
    // A non-finite first time does not become the origin of the dropouts.
    assert!(!s.epoch_bytes(f64::NAN, &truth(), &mut out));
    assert_eq!(
        s.last_epoch().unwrap().dropped,
        Some(DropReason::InvalidInput)
    );
    let nan_lat = NavFix {
        lat_deg: f64::NAN,
        ..truth()
    };
    assert!(!s.epoch_bytes(100.0, &nan_lat, &mut out));
    assert!(out.is_empty());
    // 100.0 was the first finite time: the origin; 100.0 + 0.1 is outside the outage.
    assert!(s.epoch_bytes(100.1, &truth(), &mut out));
    // Times outside the week roll over; times outside weeks 1..=65535 are invalid input.
    for t in [-1.0, 1e7] {
        assert!(s.epoch_bytes(t, &truth(), &mut out));
    }
    for t in [1e300, -1e300, f64::INFINITY, -1690.0 * 604_800.0] {
        assert!(!s.epoch_bytes(t, &truth(), &mut out), "{t}");
        assert_eq!(
            s.last_epoch().unwrap().dropped,
            Some(DropReason::InvalidInput)
        );
    }
    // At a pole an east error cannot move the longitude; nothing becomes NaN.
    let mut noisy = stream(
        NavigationConfig {
            noise: Some(NavNoise {
                position_m: 1.0,
                attitude_deg: 100.0,
                heading_deg: 100.0,
            }),
            formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
            ..Default::default()
        },
        3,
    );
    for lat in [90.0, -90.0] {
        for k in 0..20 {
            let pole = NavFix {
                lat_deg: lat,
                ..truth()
            };
            assert!(noisy.epoch_bytes(100.0 + k as f64, &pole, &mut out));
            let r = noisy.last_epoch().unwrap().reported;
            assert_eq!(r.lon_deg, truth().lon_deg);
            assert!(r.lat_deg.abs() <= 90.0 && r.pitch_deg.abs() <= 90.0);
            assert!(r.roll_deg.abs() <= 180.0 && (0.0..360.0).contains(&r.heading_deg));
        }
    }
    assert!(!String::from_utf8_lossy(&out).contains("NaN"));
    assert_eq!(week_ms(1690, 604_800.5), Some((1691, 500)));
    assert_eq!(week_ms(1690, -0.25), Some((1689, 604_799_750)));
    assert_eq!(week_ms(1690, 0.0004), Some((1690, 0)));
    assert_eq!(week_ms(1, -1.0), None);
    assert_eq!(week_ms(65535, 604_800.0), None);
    assert_eq!(week_ms(1, f64::NAN), None);
}

#[test]
fn novatel_frames_have_the_manual_layout() {
    let h = LongHeader::new(id::INSPVAX, 1820, 160_205_900);
    let rec = InspvaxRecord {
        ins_status: 3,
        position_type: 56,
        lat_deg: 43.5,
        lon_deg: -80.25,
        height_msl_m: 326.0,
        undulation_m: -36.5,
        velocity_neu_mps: [1.0, 2.0, 3.0],
        roll_deg: 1.0,
        pitch_deg: 0.5,
        azimuth_deg: 94.0,
        position_sigma_m: [0.1, 0.2, 0.3],
        velocity_sigma_mps: [0.01; 3],
        attitude_sigma_deg: [0.02, 0.03, 0.04],
        extended_status: 92,
        time_since_update_s: 2,
    };
    let mut out = Vec::new();
    write_frame(&h, &rec.encode(), &mut out);
    assert_eq!(out.len(), LONG_HEADER_LEN + INSPVAX_LEN + 4);
    assert_eq!(&out[..4], &[0xAA, 0x44, 0x12, 28]);
    assert_eq!(u16::from_le_bytes([out[8], out[9]]), 126);
    let body = &out[28..28 + 126];
    let f64_at = |at: usize| f64::from_le_bytes(body[at..at + 8].try_into().unwrap());
    let f32_at = |at: usize| f32::from_le_bytes(body[at..at + 4].try_into().unwrap());
    assert_eq!((f64_at(8), f64_at(16), f64_at(24)), (43.5, -80.25, 326.0));
    assert_eq!(f32_at(32), -36.5);
    assert_eq!((f64_at(60), f64_at(68), f64_at(76)), (1.0, 0.5, 94.0));
    assert_eq!((f32_at(84), f32_at(116)), (0.1, 0.04));
    assert_eq!(&body[120..], &[92, 0, 0, 0, 2, 0]);
    let crc = u32::from_le_bytes(out[out.len() - 4..].try_into().unwrap());
    assert_eq!(crc, novatel_crc32(&out[..out.len() - 4]));
    // Our decoder reads it back (full decoder-path round trips: tests/sim_navstream.rs).
    let s = crate::nav::novatel::decode(&out[..28], body, false)
        .unwrap()
        .unwrap();
    assert_eq!((s.height_msl, s.height), (Some(326.0), Some(326.0 - 36.5)));

    // TIME: 2014-11-24 20:29:50 UTC is GPS week 1820, 160 206 s with 16 leap seconds (the
    // date and fields of the real log's TIME message).
    let t = TimeRecord::at(1820, 160_206_000, 16.0);
    assert_eq!(
        (
            t.utc_year,
            t.utc_month,
            t.utc_day,
            t.utc_hour,
            t.utc_min,
            t.utc_ms
        ),
        (2014, 11, 24, 20, 29, 50_000)
    );
    assert_eq!((t.utc_offset_s, t.utc_status), (-16.0, 1));
    let b = t.encode();
    let s = crate::nav::novatel::decode(
        &LongHeader::new(id::TIME, 1820, 160_206_000).encode(44),
        &b,
        false,
    )
    .unwrap()
    .unwrap();
    assert_eq!(s.gps_minus_utc, Some(16.0));
}

#[test]
fn whole_seconds_carry_zda_and_time() {
    let config = NavigationConfig {
        formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
        ..Default::default()
    };
    // From 345 599.7 s: epochs at .7, .8, .9, 345 600.0 (UTC 345 582: a whole second), .1.
    let mut s = stream(config, 0);
    for k in 0..5 {
        let t = s.epoch_gps_s(345_599.7, k);
        let mut out = Vec::new();
        assert!(s.epoch_bytes(t, &truth(), &mut out));
        let text = String::from_utf8_lossy(&out);
        let whole = k == 3;
        assert_eq!(text.contains("$GPZDA"), whole, "epoch {k}");
        let time_frames = out
            .windows(6)
            .filter(|w| w[..4] == [0xAA, 0x44, 0x12, 28] && w[4..6] == id::TIME.to_le_bytes())
            .count();
        assert_eq!(time_frames, whole as usize, "epoch {k}");
    }
}
