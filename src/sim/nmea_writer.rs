//! A minimal NMEA 0183 writer for the simulator: `$GPGGA` position fixes, `$PASHR` attitude
//! sentences and a `$GPZDA` date on whole UTC seconds, with their `*hh` checksums, for a
//! straight flight line at constant speed and heading ([`FlightLine`]).
//!
//! Sentences end in CR LF. The checksum is the XOR of every byte between `$` and `*`, written
//! as two upper-case hexadecimal digits.

use crate::sim::analytic_scene::FlightConfig;

use crate::nav::crc::nmea_xor as checksum;
use crate::nav::trajectory::radii;

/// A complete sentence `$<body>*hh\r\n` for `body`.
pub fn sentence(body: &str) -> String {
    format!("${body}*{:02X}\r\n", checksum(body.as_bytes()))
}

/// Whether `line` (with or without its trailing CR LF) is `$<body>*hh` with a matching
/// checksum (hex digits of either case).
pub fn checksum_ok(line: &str) -> bool {
    let line = line.trim_end_matches(['\r', '\n']);
    let Some(rest) = line.strip_prefix('$') else {
        return false;
    };
    let Some((body, hex)) = rest.rsplit_once('*') else {
        return false;
    };
    hex.len() == 2 && u8::from_str_radix(hex, 16).is_ok_and(|h| h == checksum(body.as_bytes()))
}

/// The aircraft's state at one navigation epoch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavFix {
    /// UTC time of day, seconds (0..86400).
    pub utc_time_of_day_s: f64,
    /// Latitude, degrees (north positive).
    pub lat_deg: f64,
    /// Longitude, degrees (east positive, -180..180).
    pub lon_deg: f64,
    /// Antenna height above mean sea level, metres.
    pub altitude_m: f64,
    /// True heading, degrees (0..360).
    pub heading_deg: f64,
    /// Roll, degrees (right wing down positive).
    pub roll_deg: f64,
    /// Pitch, degrees (nose up positive).
    pub pitch_deg: f64,
}

/// `hhmmss` followed by `decimals` decimals of the second, for a time of day in seconds.
fn hhmmss(tod_s: f64, decimals: u32) -> String {
    let scale = 10u64.pow(decimals);
    let day = 86_400 * scale;
    let ticks = ((tod_s * scale as f64).round() as i64).rem_euclid(day as i64) as u64;
    let (s, frac) = (ticks / scale, ticks % scale);
    let (h, m, s) = (s / 3600, s / 60 % 60, s % 60);
    format!(
        "{h:02}{m:02}{s:02}.{frac:0width$}",
        width = decimals as usize
    )
}

/// Degrees as NMEA `(d)ddmm.mmmmmm` with `deg_digits` digits of degrees, and the hemisphere.
fn ddmm(value_deg: f64, deg_digits: usize, pos: char, neg: char) -> (String, char) {
    let hemi = if value_deg < 0.0 { neg } else { pos };
    // Minutes in micro-minutes, so the carry from 59.9999995 to the next degree is exact.
    let micro_min = (value_deg.abs() * 60.0e6).round() as u64;
    let deg = micro_min / 60_000_000;
    let rem = micro_min % 60_000_000;
    (
        format!(
            "{deg:0deg_digits$}{:02}.{:06}",
            rem / 1_000_000,
            rem % 1_000_000
        ),
        hemi,
    )
}

/// A `$GPGGA` sentence for `fix` (fix quality 1, 12 satellites, HDOP 0.8, geoid separation 0).
pub fn gga(fix: &NavFix) -> String {
    let (lat, ns) = ddmm(fix.lat_deg, 2, 'N', 'S');
    let (lon, ew) = ddmm(fix.lon_deg, 3, 'E', 'W');
    sentence(&format!(
        "GPGGA,{},{lat},{ns},{lon},{ew},1,12,0.8,{:.3},M,0.000,M,,",
        hhmmss(fix.utc_time_of_day_s, 2),
        fix.altitude_m
    ))
}

/// A `$PASHR` attitude sentence for `fix`: time, true heading, `T`, roll, pitch, heave (0),
/// roll/pitch/heading accuracies (degrees), GPS quality (1) and INS status (1: aligned).
pub fn pashr(fix: &NavFix) -> String {
    sentence(&format!(
        "PASHR,{},{:06.2},T,{:+06.2},{:+06.2},+0.00,0.010,0.010,0.020,1,1",
        hhmmss(fix.utc_time_of_day_s, 3),
        fix.heading_deg.rem_euclid(360.0),
        fix.roll_deg,
        fix.pitch_deg
    ))
}

/// A `$GPZDA` sentence (UTC time, day, month, year, zone 00:00) for GPS time `sow` seconds of
/// GPS week `week`, with `leap_s` = GPS − UTC.
pub fn zda(week: u32, sow: f64, leap_s: f64) -> String {
    let utc = week as f64 * crate::nav::dating::WEEK_S + sow - leap_s;
    let days = (utc / 86_400.0).floor();
    let tod = utc - days * 86_400.0;
    let (y, m, d) =
        crate::nav::dating::civil_of_days(crate::nav::dating::GPS_EPOCH_DAYS + days as i64);
    sentence(&format!(
        "GPZDA,{},{d:02},{m:02},{y:04},00,00",
        hhmmss(tod, 2)
    ))
}

/// A straight, level flight line at constant ground speed and heading.
///
/// Positions are computed in the local tangent plane of the start point and converted with the
/// WGS84 meridian and prime-vertical radii of curvature at the start latitude (a constant
/// heading, accurate to well below a metre over the few kilometres of a simulated line).
#[derive(Clone, Debug)]
pub struct FlightLine {
    config: FlightConfig,
    start_gps_s: f64,
    altitude_m: f64,
    /// Metres per radian of latitude at the start.
    meridian_radius_m: f64,
    /// Metres per radian of longitude at the start latitude.
    parallel_radius_m: f64,
}

impl FlightLine {
    /// The line flown from `config`'s start point at GPS time `start_gps_s` (seconds) and at
    /// `altitude_m` above mean sea level.
    pub fn new(config: &FlightConfig, start_gps_s: f64, altitude_m: f64) -> Self {
        let phi = config.start_lat_deg.to_radians();
        let (m, n) = radii(phi);
        FlightLine {
            config: config.clone(),
            start_gps_s,
            altitude_m,
            meridian_radius_m: m,
            parallel_radius_m: n * phi.cos(),
        }
    }

    /// The aircraft's state at GPS time `gps_s` (seconds).
    pub fn fix_at(&self, gps_s: f64) -> NavFix {
        let c = &self.config;
        let d = c.speed_mps * (gps_s - self.start_gps_s);
        let heading = c.heading_deg.to_radians();
        let (north, east) = (d * heading.cos(), d * heading.sin());
        let lat_deg = c.start_lat_deg + (north / self.meridian_radius_m).to_degrees();
        let lon_deg = c.start_lon_deg + (east / self.parallel_radius_m).to_degrees();
        NavFix {
            utc_time_of_day_s: (gps_s - c.gps_utc_offset_s).rem_euclid(86_400.0),
            lat_deg,
            lon_deg: (lon_deg + 180.0).rem_euclid(360.0) - 180.0,
            altitude_m: self.altitude_m,
            heading_deg: c.heading_deg.rem_euclid(360.0),
            roll_deg: 0.0,
            pitch_deg: 0.0,
        }
    }

    /// The bytes a receiver port would deliver for the epoch at GPS time `gps_s` (seconds of
    /// the flight's GPS week): one GGA and one PASHR sentence, and a ZDA when the epoch falls
    /// on a whole UTC second (once per second, as receivers date their output).
    pub fn epoch_bytes(&self, gps_s: f64) -> Vec<u8> {
        let fix = self.fix_at(gps_s);
        let mut s = gga(&fix);
        s.push_str(&pashr(&fix));
        let centis = (fix.utc_time_of_day_s * 100.0).round() as i64;
        if centis % 100 == 0 {
            s.push_str(&zda(
                self.config.gps_week,
                gps_s,
                self.config.gps_utc_offset_s,
            ));
        }
        s.into_bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checksum_matches_real_receiver_sentences() {
        // From the gpsd regression log rst39.log (OxTS GPS/IMU), checked against the fixture
        // file itself below when it is present.
        assert!(checksum_ok(
            "$PASHR,204132.000,010.51,T,+00.39,-00.79,-00.84,0.151,0.075,0.555,1,0*03"
        ));
        assert!(checksum_ok(
            "$GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138*15"
        ));
        assert!(!checksum_ok(
            "$GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138*16"
        ));
        let path = crate::fixtures::path("nav/gpsd/rst39.log");
        let log = std::fs::read(&path).unwrap();
        let log = String::from_utf8_lossy(&log);
        let mut n = 0;
        for line in log
            .lines()
            .filter(|l| l.starts_with("$GPGGA") || l.starts_with("$PASHR"))
        {
            assert!(checksum_ok(line), "{line}");
            n += 1;
        }
        assert!(n > 100, "only {n} sentences checked");
    }

    #[test]
    fn the_stream_decodes_to_the_simulated_gps_times() {
        // GGA/PASHR carry UTC time of day, ZDA the date: decoded and dated by our own
        // navigation parsers, every sample lands at the GPS time it was simulated for.
        let config = FlightConfig::default();
        let line = FlightLine::new(&config, 345_598.0, 1000.0);
        let mut dec = crate::nav::decoder::NavDecoder::new(18.0, 64, None);
        let mut got = Vec::new();
        for k in 0..40 {
            let t = 345_598.0 + k as f64 * 0.1;
            dec.push(&line.epoch_bytes(t), &mut |s, g| got.push((t, s.kind, g)));
        }
        dec.finish(&mut |_, _| {});
        assert_eq!(dec.summary().rejected, 0, "{:?}", dec.summary());
        assert_eq!(dec.summary().by_kind["ZDA"], 4, "one per whole second");
        assert_eq!(got.len(), 40 * 2 + 4);
        for (_, kind, g) in &got {
            let g = g.expect("dated");
            assert_eq!(g.week, 1690, "{kind:?}");
        }
        // Samples are released in order; each GGA's time equals one of the epochs.
        let ggas: Vec<f64> = got
            .iter()
            .filter(|(_, k, _)| *k == crate::nav::NavKind::Gga)
            .map(|(_, _, g)| g.unwrap().sow)
            .collect();
        for (k, sow) in ggas.iter().enumerate() {
            assert!(
                (sow - (345_598.0 + k as f64 * 0.1)).abs() < 1e-6,
                "{k}: {sow}"
            );
        }
    }

    #[test]
    fn time_and_angles_are_formatted_as_nmea() {
        assert_eq!(hhmmss(3661.013, 2), "010101.01");
        assert_eq!(hhmmss(86399.9996, 3), "000000.000");
        assert_eq!(ddmm(-24.5, 2, 'N', 'S'), ("2430.000000".into(), 'S'));
        assert_eq!(
            ddmm(31.999_999_999_9, 3, 'E', 'W'),
            ("03200.000000".into(), 'E')
        );
        let fix = NavFix {
            utc_time_of_day_s: 45_296.25,
            lat_deg: 42.0,
            lon_deg: -88.5,
            altitude_m: 1000.0,
            heading_deg: 90.0,
            roll_deg: -1.5,
            pitch_deg: 0.25,
        };
        let g = gga(&fix);
        assert!(
            g.starts_with("$GPGGA,123456.25,4200.000000,N,08830.000000,W,1,"),
            "{g}"
        );
        assert!(g.ends_with("\r\n") && checksum_ok(&g));
        let p = pashr(&fix);
        assert!(
            p.starts_with("$PASHR,123456.250,090.00,T,-01.50,+00.25,"),
            "{p}"
        );
        assert!(checksum_ok(&p));
    }

    /// Latitude and longitude (degrees) of a GGA sentence.
    fn parse_gga(line: &str) -> (f64, f64) {
        let f: Vec<&str> = line.split(',').collect();
        let dm = |s: &str, deg_digits: usize| {
            s[..deg_digits].parse::<f64>().unwrap() + s[deg_digits..].parse::<f64>().unwrap() / 60.0
        };
        let lat = dm(f[2], 2) * if f[3] == "S" { -1.0 } else { 1.0 };
        let lon = dm(f[4], 3) * if f[5] == "W" { -1.0 } else { 1.0 };
        (lat, lon)
    }

    #[test]
    fn the_aircraft_moves_along_its_heading_at_its_speed() {
        for heading in [0.0, 37.0, 90.0, 200.0, 315.0] {
            let config = FlightConfig {
                start_lat_deg: -24.99,
                start_lon_deg: 31.59,
                speed_mps: 60.0,
                heading_deg: heading,
                ..Default::default()
            };
            let line = FlightLine::new(&config, 1000.0, 1000.0);
            let text = |t: f64| String::from_utf8(line.epoch_bytes(t)).unwrap();
            let (a, b) = (text(1000.0), text(1010.0));
            for s in a.split_inclusive("\r\n").chain(b.split_inclusive("\r\n")) {
                assert!(checksum_ok(s), "{s}");
            }
            let (lat0, lon0) = parse_gga(&a);
            let (lat1, lon1) = parse_gga(&b);
            assert!((lat0 + 24.99).abs() < 1e-7 && (lon0 - 31.59).abs() < 1e-7);
            // Independent check on a sphere of the mean Earth radius (0.5 % tolerance).
            let (p0, p1) = (lat0.to_radians(), lat1.to_radians());
            let dl = (lon1 - lon0).to_radians();
            let h =
                ((p1 - p0) / 2.0).sin().powi(2) + p0.cos() * p1.cos() * (dl / 2.0).sin().powi(2);
            let dist = 2.0 * 6_371_008.8 * h.sqrt().asin();
            assert!(
                (dist / 600.0 - 1.0).abs() < 0.005,
                "heading {heading}: {dist} m in 10 s"
            );
            let bearing = (dl.sin() * p1.cos())
                .atan2(p0.cos() * p1.sin() - p0.sin() * p1.cos() * dl.cos())
                .to_degrees()
                .rem_euclid(360.0);
            let diff = (bearing - heading + 540.0).rem_euclid(360.0) - 180.0;
            assert!(diff.abs() < 0.2, "heading {heading}: bearing {bearing}");
            assert!(b.contains(&format!("PASHR,{}", hhmmss(1010.0 - 18.0, 3))));
        }
    }
}
