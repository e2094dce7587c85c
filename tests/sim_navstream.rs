//! The simulated navigation stream (`fwlidar::sim::navstream`) through our real decoder path:
//! bytes fed to [`NavDecoder`] in odd-sized pieces come back as the state and time each epoch
//! reported, to the resolution of the format; and the NovAtel encoder's byte layout against
//! the real SPAN log of the fixtures (`nav/novatel/corrimudata.pcap.payload.bin`, see the
//! fixtures' MANIFEST.md; the test fails naming the file when it is missing).
//!
//! Resolutions (half of each is the largest rounding error allowed):
//! - NMEA GGA: time 0.01 s; latitude and longitude 1e-6 arc-minute (1.67e-8°, 1.9 mm of
//!   latitude); altitude 1 mm. PASHR: time 1 ms; heading, roll, pitch 0.01°.
//! - NovAtel INSPVAX: position and attitude f64 (exact); time the header's millisecond of the
//!   GPS week (exact for epochs on whole milliseconds).

mod common;

use fwlidar::nav::dating::GpsTime;
use fwlidar::nav::decoder::NavDecoder;
use fwlidar::nav::framer::{Frame, Framer};
use fwlidar::nav::{NavKind, NavSample, novatel};
use fwlidar::sim::navstream::{
    Dropout, InspvaxRecord, LongHeader, NavNoise, NavStream, NavigationConfig, StreamFormat,
    TimeRecord, id, write_frame,
};
use fwlidar::sim::nmea_writer::NavFix;

/// Start of every run: 1 s before a whole GPS second (so a ZDA dates the NMEA times).
const T0: f64 = 345_599.0;

/// A truth that moves, rolls, pitches and turns through north, in the south-west quadrant.
fn truth(k: u64) -> NavFix {
    let k = k as f64;
    NavFix {
        utc_time_of_day_s: 0.0,
        lat_deg: -33.123_456_789 + 1.3e-6 * k,
        lon_deg: -70.654_321_987 - 2.9e-6 * k,
        altitude_m: 1_234.567_89 + 0.0137 * k,
        heading_deg: (355.0 + 0.731 * k).rem_euclid(360.0),
        roll_deg: 12.0 * (0.05 * k).sin(),
        pitch_deg: -3.0 + 0.0123 * k,
    }
}

/// One epoch as the stream reported it.
struct Sent {
    gps_s: f64,
    fix: NavFix,
}

/// Runs `n` epochs of `config` (seed `seed`); the epochs sent and all the bytes.
fn simulate(config: NavigationConfig, seed: u64, n: u64) -> (Vec<Sent>, Vec<u8>) {
    let mut stream = NavStream::new(config, seed).unwrap();
    let (mut sent, mut bytes) = (Vec::new(), Vec::new());
    for k in 0..n {
        let t = stream.epoch_gps_s(T0, k);
        if stream.epoch_bytes(t, &truth(k), &mut bytes) {
            let r = stream.last_epoch().unwrap();
            sent.push(Sent {
                gps_s: t,
                fix: r.reported,
            });
        }
    }
    (sent, bytes)
}

/// Our decoder fed `bytes` in pieces of 1, 2, 3, 5, 7, 11, 13, 17 and 23 bytes in turn.
fn decode(bytes: &[u8]) -> Vec<(NavSample, GpsTime)> {
    let mut dec = NavDecoder::new(18.0, 4096, None);
    let mut got = Vec::new();
    let sizes = [1, 2, 3, 5, 7, 11, 13, 17, 23];
    let (mut at, mut i) = (0, 0);
    while at < bytes.len() {
        let end = (at + sizes[i % sizes.len()]).min(bytes.len());
        dec.push(&bytes[at..end], &mut |s, g| {
            got.push((s, g.expect("dated")))
        });
        at = end;
        i += 1;
    }
    dec.finish(&mut |s, g| got.push((s, g.expect("dated"))));
    let summary = dec.summary();
    assert_eq!(summary.rejected, 0, "{summary:?}");
    assert_eq!(summary.unframed_bytes, 0, "{summary:?}");
    assert!(summary.ignored.is_empty(), "{summary:?}");
    got
}

fn of_kind(got: &[(NavSample, GpsTime)], kind: NavKind) -> Vec<(NavSample, GpsTime)> {
    got.iter()
        .filter(|(s, _)| s.kind == kind)
        .copied()
        .collect()
}

/// Angle difference a − b wrapped to -180..180, degrees.
fn angle_diff(a: f64, b: f64) -> f64 {
    (a - b + 540.0).rem_euclid(360.0) - 180.0
}

fn close(what: &str, got: f64, want: f64, tol: f64) {
    assert!(
        (got - want).abs() <= tol,
        "{what}: got {got}, want {want} (tolerance {tol})"
    );
}

/// GGA and PASHR of each sent epoch, in order, equal its reported state to the resolution.
fn check_nmea(sent: &[Sent], got: &[(NavSample, GpsTime)]) {
    let gga = of_kind(got, NavKind::Gga);
    let pashr = of_kind(got, NavKind::Pashr);
    assert_eq!((gga.len(), pashr.len()), (sent.len(), sent.len()));
    for (e, ((g, gt), (p, pt))) in sent.iter().zip(gga.iter().zip(&pashr)) {
        assert_eq!(gt.week, 1690);
        close("GGA time", gt.sow, e.gps_s, 0.005 + 1e-9);
        close("PASHR time", pt.sow, e.gps_s, 0.0005 + 1e-9);
        let deg = 0.5e-6 / 60.0 + 1e-12;
        close("latitude", g.lat.unwrap(), e.fix.lat_deg, deg);
        close("longitude", g.lon.unwrap(), e.fix.lon_deg, deg);
        close(
            "altitude",
            g.height.unwrap(),
            e.fix.altitude_m,
            0.0005 + 1e-9,
        );
        let a = 0.005 + 1e-9;
        close("roll", p.roll.unwrap(), e.fix.roll_deg, a);
        close("pitch", p.pitch.unwrap(), e.fix.pitch_deg, a);
        close(
            "heading",
            angle_diff(p.heading.unwrap(), e.fix.heading_deg),
            0.0,
            a,
        );
    }
}

/// INSPVAX of each sent epoch, in order, equals its reported state exactly.
fn check_novatel(sent: &[Sent], got: &[(NavSample, GpsTime)]) {
    let ins = of_kind(got, NavKind::Inspvax);
    assert_eq!(ins.len(), sent.len());
    for (e, (s, t)) in sent.iter().zip(&ins) {
        assert_eq!(t.week, 1690);
        assert_eq!((t.sow * 1000.0).round(), (e.gps_s * 1000.0).round());
        assert_eq!(
            (s.lat, s.lon, s.height_msl, s.height),
            (
                Some(e.fix.lat_deg),
                Some(e.fix.lon_deg),
                Some(e.fix.altitude_m),
                Some(e.fix.altitude_m)
            )
        );
        assert_eq!(
            (s.roll, s.pitch, s.heading),
            (
                Some(e.fix.roll_deg),
                Some(e.fix.pitch_deg),
                Some(e.fix.heading_deg)
            )
        );
        assert_eq!(s.ins_status, Some(3));
    }
    // TIME on every whole GPS second sent, stating 18 leap seconds.
    let whole = sent
        .iter()
        .filter(|e| (e.gps_s * 1000.0).round() % 1000.0 == 0.0)
        .count();
    let time = of_kind(got, NavKind::Time);
    assert_eq!(time.len(), whole);
    assert!(time.iter().all(|(s, _)| s.gps_minus_utc == Some(18.0)));
}

#[test]
fn nmea_round_trips_through_our_decoder() {
    let (sent, bytes) = simulate(NavigationConfig::default(), 0, 95);
    assert_eq!(sent.len(), 95);
    let got = decode(&bytes);
    check_nmea(&sent, &got);
    // A ZDA on every whole UTC second: 345 599 .. 345 608 s.
    assert_eq!(of_kind(&got, NavKind::Zda).len(), 10);
    // The reported state is the truth (no noise configured).
    for (k, e) in sent.iter().enumerate() {
        let t = truth(k as u64);
        assert_eq!(
            (e.fix.lat_deg, e.fix.roll_deg, e.fix.heading_deg),
            (t.lat_deg, t.roll_deg, t.heading_deg)
        );
    }
}

#[test]
fn novatel_round_trips_through_our_decoder() {
    let config = NavigationConfig {
        formats: vec![StreamFormat::Novatel],
        rate_hz: 50.0,
        ..Default::default()
    };
    let (sent, bytes) = simulate(config, 0, 230);
    let got = decode(&bytes);
    check_novatel(&sent, &got);
    assert_eq!(
        got.len(),
        230 + 5,
        "INSPVAX at 50 Hz and TIME each whole second"
    );
    // The velocity is the truth's change since the previous epoch (0 at the first).
    let ins = of_kind(&got, NavKind::Inspvax);
    assert_eq!(ins[0].0.vel_up, Some(0.0));
    close(
        "up velocity",
        ins[10].0.vel_up.unwrap(),
        0.0137 * 50.0,
        1e-9,
    );
    close(
        "north velocity",
        ins[10].0.vel_north.unwrap(),
        1.3e-6_f64.to_radians() * 6_335_439.0 * 50.0,
        0.05,
    );
}

#[test]
fn both_formats_with_noise_and_dropouts_decode_to_the_sent_epochs() {
    let config = NavigationConfig {
        formats: vec![StreamFormat::Nmea, StreamFormat::Novatel],
        noise: Some(NavNoise {
            position_m: 0.3,
            attitude_deg: 0.05,
            heading_deg: 0.1,
        }),
        dropouts: vec![Dropout {
            start_s: 2.5,
            duration_s: 1.2,
        }],
        random_dropout_probability: 0.1,
        ..Default::default()
    };
    let (sent, bytes) = simulate(config, 77, 120);
    // 12 epochs in the outage, about 11 more lost at random.
    assert!((80..108).contains(&sent.len()), "{} sent", sent.len());
    assert!(
        sent.iter()
            .all(|e| !(T0 + 2.5 - 1e-6..T0 + 3.7 - 1e-6).contains(&e.gps_s))
    );
    let got = decode(&bytes);
    check_nmea(&sent, &got);
    check_novatel(&sent, &got);
}

/// The NovAtel frames of the real SPAN log: (header, body) of every INSPVAX and TIME.
fn real_frames(bytes: &[u8]) -> Vec<(Vec<u8>, Vec<u8>)> {
    let mut framer = Framer::new();
    framer.push(bytes);
    framer.finish();
    let mut frames = Vec::new();
    while let Some(f) = framer.next_frame() {
        if let Frame::Novatel { header, body } = f {
            let id = u16::from_le_bytes([header[4], header[5]]);
            if id == id::INSPVAX || id == id::TIME {
                frames.push((header.to_vec(), body.to_vec()));
            }
        }
    }
    frames
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}
fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// Our header for the real one: message id, week and ms from the real header; the fields the
/// simulator writes as constants (port, sequence, idle time, receiver status, reserved,
/// software build) copied, so that the whole frame can be compared byte for byte.
fn header_like(real: &[u8]) -> LongHeader {
    let mut h = LongHeader::new(u16_at(real, 4), u16_at(real, 14), u32_at(real, 16));
    assert_eq!(h.message_type, real[6], "message type");
    assert_eq!(h.time_status, real[13], "time status (FINESTEERING)");
    h.port_address = real[7];
    h.sequence = u16_at(real, 10);
    h.idle_time = real[12];
    h.receiver_status = u32_at(real, 20);
    h.reserved = u16_at(real, 24);
    h.sw_version = u16_at(real, 26);
    h
}

#[test]
fn novatel_encoding_reproduces_the_real_span_log() {
    let path = common::fixture("nav/novatel/corrimudata.pcap.payload.bin");
    let bytes = std::fs::read(&path).unwrap();
    let frames = real_frames(&bytes);
    let (mut n_ins, mut n_time) = (0, 0);
    for (header, body) in &frames {
        // Decoded by our decoder ...
        let s = novatel::decode(header, body, false).unwrap().unwrap();
        let h = header_like(header);
        assert_eq!(header[3] as usize, fwlidar::sim::navstream::LONG_HEADER_LEN);
        let mut real = header.clone();
        real.extend_from_slice(body);
        let crc = fwlidar::nav::crc::novatel_crc32(&real);
        real.extend_from_slice(&crc.to_le_bytes());
        // ... and re-encoded by ours from the decoded values.
        let mut ours = Vec::new();
        if h.message_id == id::INSPVAX {
            n_ins += 1;
            let sigma = |a: [f64; 3]| a.map(|v| v as f32);
            let rec = InspvaxRecord {
                ins_status: s.ins_status.unwrap(),
                position_type: s.fix.unwrap(),
                lat_deg: s.lat.unwrap(),
                lon_deg: s.lon.unwrap(),
                height_msl_m: s.height_msl.unwrap(),
                undulation_m: (s.height.unwrap() - s.height_msl.unwrap()) as f32,
                velocity_neu_mps: [s.vel_north.unwrap(), s.vel_east.unwrap(), s.vel_up.unwrap()],
                roll_deg: s.roll.unwrap(),
                pitch_deg: s.pitch.unwrap(),
                azimuth_deg: s.heading.unwrap(),
                position_sigma_m: sigma(s.position_sigma.unwrap()),
                // Not in a NavSample: from the real body at the manual's offsets.
                velocity_sigma_mps: [f32_at(body, 96), f32_at(body, 100), f32_at(body, 104)],
                attitude_sigma_deg: sigma(s.attitude_sigma.unwrap()),
                extended_status: u32_at(body, 120),
                time_since_update_s: u16_at(body, 124),
            };
            write_frame(&h, &rec.encode(), &mut ours);
        } else {
            n_time += 1;
            let mut rec = TimeRecord::at(h.week, h.ms, s.gps_minus_utc.unwrap());
            // The UTC date and time we compute from GPS time equal the receiver's.
            assert_eq!(
                (rec.utc_year, rec.utc_month, rec.utc_day),
                (u32_at(body, 28), body[32], body[33]),
                "UTC date at {} ms",
                h.ms
            );
            assert_eq!(
                (rec.utc_hour, rec.utc_min, rec.utc_ms, rec.utc_status),
                (body[34], body[35], u32_at(body, 36), u32_at(body, 40)),
                "UTC time at {} ms",
                h.ms
            );
            assert_eq!(rec.utc_offset_s, f64_at(body, 20));
            // Receiver clock model: not simulated (0); copied to compare the frame.
            rec.clock_status = u32_at(body, 0);
            rec.offset_s = f64_at(body, 4);
            rec.offset_std_s = f64_at(body, 12);
            write_frame(&h, &rec.encode(), &mut ours);
        }
        assert_eq!(ours, real, "message {} at {} ms", h.message_id, h.ms);
    }
    // The numbers the fixtures' MANIFEST states.
    assert!(n_ins >= 10 && n_time >= 2, "{n_ins} INSPVAX, {n_time} TIME");
    let first = &frames
        .iter()
        .find(|(h, _)| u16_at(h, 4) == id::INSPVAX)
        .unwrap()
        .1;
    close("latitude", f64_at(first, 8), 43.4041, 1e-4);
    close("azimuth", f64_at(first, 76), 94.2, 0.01);
    eprintln!(
        "{}: {n_ins} INSPVAX and {n_time} TIME frames re-encoded byte for byte (header constants \
         port/idle/receiver status/reserved/build copied from the real headers)",
        path.display()
    );
}
