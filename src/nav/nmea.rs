//! NMEA 0183 sentences to [`NavSample`]s: GGA, RMC, ZDA, HDT, VTG, GST and the PASHR attitude
//! sentence (heading, roll, pitch, heave) as OxTS and other INS makers send it.
//!
//! Written by hand rather than with the `nmea` crate: PASHR is proprietary and not in it, we
//! need the ellipsoidal height and standard deviations that crate folds away, and one parser for
//! every sentence keeps a single, exact count of what was rejected and why. Input is a sentence
//! body as the [`super::framer::Framer`] returns it (checksum already verified): the address
//! field and the data fields, without `$`, `*` and the checksum.

use super::{NavKind, NavSample, NavTime};

/// Knots to metres per second (1 international knot = 1852 m / 3600 s).
pub const KNOT_MPS: f64 = 1852.0 / 3600.0;

/// What one sentence gave (returned by value and consumed at once: the size of a sample does
/// not matter here).
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Decoded {
    /// A navigation sample.
    Sample(NavSample),
    /// A well-formed sentence of a type we do not use (GSV, GSA, ...): its 3-5 letter type.
    Ignored([u8; 5]),
    /// A sentence that is not usable, with the reason (`bad_latitude`, `no_fix`, ...).
    Rejected(&'static str),
}

/// Decodes one sentence body (`GPGGA,123519,4807.038,N,...`).
pub fn decode(body: &[u8]) -> Decoded {
    let Ok(text) = std::str::from_utf8(body) else {
        return Decoded::Rejected("not_text");
    };
    let mut fields = [""; 24];
    let mut n = 0;
    for f in text.split(',') {
        if n == fields.len() {
            return Decoded::Rejected("too_many_fields");
        }
        fields[n] = f;
        n += 1;
    }
    let f = &fields[..n];
    let address = f[0];
    let kind: &str = if address.starts_with('P') {
        address
    } else if address.len() == 5 && address.is_ascii() {
        &address[2..]
    } else {
        return Decoded::Rejected("bad_address");
    };
    let result = match kind {
        "GGA" => gga(f),
        "RMC" => rmc(f),
        "ZDA" => zda(f),
        "HDT" => hdt(f),
        "VTG" => vtg(f),
        "GST" => gst(f),
        "PASHR" => pashr(f),
        _ => {
            let mut t = [b' '; 5];
            for (d, s) in t.iter_mut().zip(kind.bytes()) {
                *d = s;
            }
            return Decoded::Ignored(t);
        }
    };
    match result {
        Ok(s) => Decoded::Sample(s),
        Err(why) => Decoded::Rejected(why),
    }
}

type R<T> = Result<T, &'static str>;

fn field<'a>(f: &[&'a str], i: usize) -> R<&'a str> {
    f.get(i).copied().ok_or("too_few_fields")
}

fn num(s: &str, why: &'static str) -> R<f64> {
    let v: f64 = s.trim().parse().map_err(|_| why)?;
    if v.is_finite() { Ok(v) } else { Err(why) }
}

fn opt_num(s: &str, why: &'static str) -> R<Option<f64>> {
    if s.trim().is_empty() {
        Ok(None)
    } else {
        num(s, why).map(Some)
    }
}

/// `hhmmss[.sss]` to seconds since midnight.
fn time_of_day(s: &str) -> R<f64> {
    let s = s.trim();
    if s.len() < 6 || !s.as_bytes()[..6].iter().all(u8::is_ascii_digit) {
        return Err("bad_time");
    }
    let h: f64 = s[0..2].parse().map_err(|_| "bad_time")?;
    let m: f64 = s[2..4].parse().map_err(|_| "bad_time")?;
    let sec: f64 = s[4..].parse().map_err(|_| "bad_time")?;
    if h >= 24.0 || m >= 60.0 || !(0.0..61.0).contains(&sec) {
        return Err("bad_time");
    }
    Ok(h * 3600.0 + m * 60.0 + sec)
}

/// `(d)ddmm.mmmm` + hemisphere to signed degrees.
fn angle(v: &str, hemi: &str, max_deg: f64, pos: &str, neg: &str, why: &'static str) -> R<f64> {
    let x = num(v, why)?;
    if x < 0.0 {
        return Err(why);
    }
    let deg = (x / 100.0).floor();
    let min = x - deg * 100.0;
    if min >= 60.0 {
        return Err(why);
    }
    let a = deg + min / 60.0;
    if a > max_deg {
        return Err(why);
    }
    match hemi.trim() {
        h if h == pos => Ok(a),
        h if h == neg => Ok(-a),
        _ => Err(why),
    }
}

/// Latitude and longitude from four fields starting at `i`; `None` when all are empty.
fn position(f: &[&str], i: usize) -> R<Option<(f64, f64)>> {
    let (la, ns, lo, ew) = (
        field(f, i)?,
        field(f, i + 1)?,
        field(f, i + 2)?,
        field(f, i + 3)?,
    );
    if la.is_empty() && lo.is_empty() {
        return Ok(None);
    }
    let lat = angle(la, ns, 90.0, "N", "S", "bad_latitude")?;
    let lon = angle(lo, ew, 180.0, "E", "W", "bad_longitude")?;
    Ok(Some((lat, lon)))
}

/// Days since 1970-01-01 of a civil date (proleptic Gregorian).
pub fn days_from_civil(y: i64, m: u32, d: u32) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m as i64 + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d as i64 - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

fn valid_date(y: i64, m: u32, d: u32) -> bool {
    let leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    let dim = [
        31,
        if leap { 29 } else { 28 },
        31,
        30,
        31,
        30,
        31,
        31,
        30,
        31,
        30,
        31,
    ];
    (1..=12).contains(&m) && d >= 1 && d <= dim[(m - 1) as usize]
}

fn time_or_none(s: &str) -> R<NavTime> {
    if s.trim().is_empty() {
        Ok(NavTime::None)
    } else {
        Ok(NavTime::UtcTimeOfDay {
            seconds: time_of_day(s)?,
        })
    }
}

fn gga(f: &[&str]) -> R<NavSample> {
    let time = time_or_none(field(f, 1)?)?;
    let quality = field(f, 6)?;
    let fix = if quality.trim().is_empty() {
        None
    } else {
        Some(quality.trim().parse::<u32>().map_err(|_| "bad_quality")?)
    };
    if fix == Some(0) {
        return Err("no_fix");
    }
    let Some((lat, lon)) = position(f, 2)? else {
        return Err("no_fix");
    };
    let mut s = NavSample::new(NavKind::Gga, time);
    s.lat = Some(lat);
    s.lon = Some(lon);
    s.fix = fix;
    s.satellites = match field(f, 7)?.trim() {
        "" => None,
        v => Some(v.parse().map_err(|_| "bad_satellites")?),
    };
    let msl = opt_num(field(f, 9)?, "bad_altitude")?;
    let sep = opt_num(f.get(11).copied().unwrap_or(""), "bad_geoid_separation")?;
    s.height_msl = msl;
    s.height = msl.zip(sep).map(|(a, b)| a + b);
    Ok(s)
}

fn rmc(f: &[&str]) -> R<NavSample> {
    let tod = time_of_day(field(f, 1)?)?;
    let status = field(f, 2)?;
    let date = field(f, 9)?.trim();
    let days = if date.is_empty() {
        None
    } else {
        if date.len() != 6 || !date.bytes().all(|b| b.is_ascii_digit()) {
            return Err("bad_date");
        }
        let d: u32 = date[0..2].parse().map_err(|_| "bad_date")?;
        let m: u32 = date[2..4].parse().map_err(|_| "bad_date")?;
        let yy: i64 = date[4..6].parse().map_err(|_| "bad_date")?;
        // Two-digit years: 80..99 are 1980..1999 (GPS began in 1980), 00..79 are 2000..2079.
        let y = if yy >= 80 { 1900 + yy } else { 2000 + yy };
        if !valid_date(y, m, d) {
            return Err("bad_date");
        }
        Some(days_from_civil(y, m, d))
    };
    let time = match days {
        Some(days) => NavTime::Utc { days, seconds: tod },
        None => NavTime::UtcTimeOfDay { seconds: tod },
    };
    let mut s = NavSample::new(NavKind::Rmc, time);
    if status.trim() != "A" {
        // A void RMC still carries the receiver's date and time, but no fix.
        return Err("no_fix");
    }
    let Some((lat, lon)) = position(f, 3)? else {
        return Err("no_fix");
    };
    s.lat = Some(lat);
    s.lon = Some(lon);
    s.speed = opt_num(field(f, 7)?, "bad_speed")?.map(|k| k * KNOT_MPS);
    s.course = opt_num(field(f, 8)?, "bad_course")?;
    Ok(s)
}

fn zda(f: &[&str]) -> R<NavSample> {
    let tod = time_of_day(field(f, 1)?)?;
    let d: u32 = field(f, 2)?.trim().parse().map_err(|_| "bad_date")?;
    let m: u32 = field(f, 3)?.trim().parse().map_err(|_| "bad_date")?;
    let y: i64 = field(f, 4)?.trim().parse().map_err(|_| "bad_date")?;
    if !(1980..=2200).contains(&y) || !valid_date(y, m, d) {
        return Err("bad_date");
    }
    Ok(NavSample::new(
        NavKind::Zda,
        NavTime::Utc {
            days: days_from_civil(y, m, d),
            seconds: tod,
        },
    ))
}

fn heading_deg(v: f64) -> R<f64> {
    if (0.0..=360.0).contains(&v) {
        Ok(if v == 360.0 { 0.0 } else { v })
    } else {
        Err("bad_heading")
    }
}

fn hdt(f: &[&str]) -> R<NavSample> {
    let Some(h) = opt_num(field(f, 1)?, "bad_heading")? else {
        return Err("no_value");
    };
    let mut s = NavSample::new(NavKind::Hdt, NavTime::None);
    s.heading = Some(heading_deg(h)?);
    Ok(s)
}

fn vtg(f: &[&str]) -> R<NavSample> {
    let course = opt_num(field(f, 1)?, "bad_course")?;
    // Speed in knots (field 5) or, failing that, km/h (field 7).
    let knots = opt_num(f.get(5).copied().unwrap_or(""), "bad_speed")?;
    let kmh = opt_num(f.get(7).copied().unwrap_or(""), "bad_speed")?;
    let speed = knots.map(|k| k * KNOT_MPS).or(kmh.map(|k| k / 3.6));
    if course.is_none() && speed.is_none() {
        return Err("no_value");
    }
    let mut s = NavSample::new(NavKind::Vtg, NavTime::None);
    s.course = course;
    s.speed = speed;
    Ok(s)
}

fn gst(f: &[&str]) -> R<NavSample> {
    let time = time_or_none(field(f, 1)?)?;
    let lat = opt_num(field(f, 6)?, "bad_sigma")?;
    let lon = opt_num(field(f, 7)?, "bad_sigma")?;
    let alt = opt_num(field(f, 8)?, "bad_sigma")?;
    match (lat, lon, alt) {
        (Some(a), Some(b), Some(c)) => {
            let mut s = NavSample::new(NavKind::Gst, time);
            s.position_sigma = Some([a, b, c]);
            Ok(s)
        }
        _ => Err("no_value"),
    }
}

/// `$PASHR,hhmmss.sss,heading,T,roll,pitch,heave,roll σ,pitch σ,heading σ,aiding,IMU status`.
/// Other PASHR sentences (Ashtech's `PASHR,POS`, `PASHR,RID`, ...) are ignored.
fn pashr(f: &[&str]) -> R<NavSample> {
    let t = field(f, 1)?;
    if !t.trim().starts_with(|c: char| c.is_ascii_digit()) {
        return Err("pashr_not_attitude");
    }
    let tod = time_of_day(t)?;
    let heading = heading_deg(num(field(f, 2)?, "bad_heading")?)?;
    if field(f, 3)?.trim() != "T" {
        return Err("bad_heading");
    }
    let roll = num(field(f, 4)?, "bad_roll")?;
    let pitch = num(field(f, 5)?, "bad_pitch")?;
    if roll.abs() > 180.0 {
        return Err("bad_roll");
    }
    if pitch.abs() > 90.0 {
        return Err("bad_pitch");
    }
    let mut s = NavSample::new(NavKind::Pashr, NavTime::UtcTimeOfDay { seconds: tod });
    s.heading = Some(heading);
    s.roll = Some(roll);
    s.pitch = Some(pitch);
    s.heave = opt_num(f.get(6).copied().unwrap_or(""), "bad_heave")?;
    let sr = opt_num(f.get(7).copied().unwrap_or(""), "bad_sigma")?;
    let sp = opt_num(f.get(8).copied().unwrap_or(""), "bad_sigma")?;
    let sh = opt_num(f.get(9).copied().unwrap_or(""), "bad_sigma")?;
    if let (Some(a), Some(b), Some(c)) = (sr, sp, sh) {
        s.attitude_sigma = Some([a, b, c]);
    }
    s.fix = match f.get(10).map(|v| v.trim()) {
        Some(v) if !v.is_empty() => Some(v.parse().map_err(|_| "bad_status")?),
        _ => None,
    };
    s.ins_status = match f.get(11).map(|v| v.trim()) {
        Some(v) if !v.is_empty() => Some(v.parse().map_err(|_| "bad_status")?),
        _ => None,
    };
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(body: &str) -> NavSample {
        match decode(body.as_bytes()) {
            Decoded::Sample(s) => s,
            other => panic!("{body}: {other:?}"),
        }
    }

    #[test]
    fn gga_of_the_oxts_log() {
        let s = sample("GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138");
        assert_eq!(
            s.time,
            NavTime::UtcTimeOfDay {
                seconds: 20.0 * 3600.0 + 41.0 * 60.0 + 32.1
            }
        );
        assert!((s.lat.unwrap() - (42.0 + 5.733715 / 60.0)).abs() < 1e-12);
        assert!((s.lon.unwrap() + (88.0 + 2.040978 / 60.0)).abs() < 1e-12);
        assert_eq!(s.height_msl, Some(221.921));
        assert_eq!(s.height, None, "no geoid separation given");
        assert_eq!(s.fix, Some(2));
        assert_eq!(s.satellites, Some(8));
    }

    #[test]
    fn gga_height_is_ellipsoidal_with_the_geoid_separation() {
        let s = sample(
            "GPGGA,132820.60,4134.49821229,N,09345.03351845,W,2,09,1.0,278.020,M,-31.442,M,7.6,0133",
        );
        // gpsd's decoding of the same sentence: altHAE 246.578, lat 41.574970205.
        assert!((s.height.unwrap() - 246.578).abs() < 1e-9);
        assert!((s.lat.unwrap() - 41.574970205).abs() < 1e-9);
        assert!((s.lon.unwrap() + 93.750558641).abs() < 1e-9);
    }

    #[test]
    fn pashr_attitude() {
        let s = sample("PASHR,204132.040,010.99,T,+00.41,-00.75,-00.84,0.151,0.088,0.569,1,0");
        assert_eq!(s.kind, NavKind::Pashr);
        assert_eq!(s.heading, Some(10.99));
        assert_eq!(s.roll, Some(0.41));
        assert_eq!(s.pitch, Some(-0.75));
        assert_eq!(s.heave, Some(-0.84));
        assert_eq!(s.attitude_sigma, Some([0.151, 0.088, 0.569]));
    }

    #[test]
    fn rmc_date_and_void_status() {
        let s = sample(
            "GPRMC,132820.60,A,4134.49821229,N,09345.03351845,W,3.252,92.308,180320,11.5985,E,D",
        );
        assert_eq!(
            s.time,
            NavTime::Utc {
                days: days_from_civil(2020, 3, 18),
                seconds: 13.0 * 3600.0 + 28.0 * 60.0 + 20.6
            }
        );
        assert!((s.speed.unwrap() - 3.252 * KNOT_MPS).abs() < 1e-12);
        assert_eq!(
            decode(b"GPRMC,000406.00,V,,,,,,,161206,,"),
            Decoded::Rejected("no_fix")
        );
    }

    #[test]
    fn zda_hdt_vtg_gst() {
        let s = sample("GPZDA,005947.00,08,07,2010,+00,00");
        assert_eq!(
            s.time,
            NavTime::Utc {
                days: days_from_civil(2010, 7, 8),
                seconds: 47.0 + 59.0 * 60.0
            }
        );
        assert_eq!(sample("GPHDT,274.07,T").heading, Some(274.07));
        assert_eq!(decode(b"GPHDT,,T"), Decoded::Rejected("no_value"));
        let v = sample("GPVTG,000.0,T,357.0,M,000.1,N,0000.1,K,A");
        assert_eq!(v.course, Some(0.0));
        let g = sample("GPGST,172814.0,0.006,0.023,0.020,273.6,0.023,0.020,0.031");
        assert_eq!(g.position_sigma, Some([0.023, 0.020, 0.031]));
    }

    #[test]
    fn odd_sentences_are_rejected_with_a_reason_never_a_panic() {
        for (s, why) in [
            ("GPGGA,,,,,,0,,,,M,,M,,", "no_fix"),
            ("GPGGA,1234", "bad_time"),
            (
                "GPGGA,123456,9100.0,N,00000.0,E,1,05,1,1,M,,M,,",
                "bad_latitude",
            ),
            (
                "GPGGA,123456,4500.0,X,00000.0,E,1,05,1,1,M,,M,,",
                "bad_latitude",
            ),
            (
                "GPGGA,123456,4560.0,N,00000.0,E,1,05,1,1,M,,M,,",
                "bad_latitude",
            ),
            ("GPRMC,000344.03,A,4808.9992,N,4,02.3", "too_few_fields"),
            ("GPZDA,005947.00,30,02,2010,+00,00", "bad_date"),
            ("PASHR,204132.040,410.99,T,0,0,0", "bad_heading"),
            ("GP", "bad_address"),
        ] {
            assert_eq!(decode(s.as_bytes()), Decoded::Rejected(why), "{s}");
        }
        assert!(matches!(decode(b"GPGSV,3,1,12"), Decoded::Ignored(_)));
        assert_eq!(days_from_civil(1980, 1, 6), 3657);
        assert_eq!(days_from_civil(1970, 1, 1), 0);
    }

    proptest::proptest! {
        #[test]
        fn arbitrary_sentences_never_panic(s in "([A-Z]{2}(GGA|RMC|ZDA|HDT|VTG|GST)|PASHR),[-+0-9.,TNSEWAV]{0,80}") {
            let _ = decode(s.as_bytes());
        }
    }
}
