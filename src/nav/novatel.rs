//! NovAtel OEM binary messages to [`NavSample`]s: INSPVAX, INSPVA (and INSPVAS), BESTPOS,
//! CORRIMUDATA (and CORRIMUS) and TIME. Input is a frame as [`super::framer::Framer`] returns it
//! (CRC already verified). Field offsets follow the OEM7 firmware reference manual; all
//! little-endian.
//!
//! Conventions as NovAtel defines them, which are ours: roll is a right-handed rotation about
//! the forward axis (right wing down positive), pitch about the right axis (nose up positive),
//! azimuth (our `heading`) clockwise from true north. INSPVAX and BESTPOS give the height above
//! mean sea level and the undulation (geoid − ellipsoid separation); INSPVA gives the ellipsoidal
//! height.

use super::{NavKind, NavSample, NavTime};

/// Message identifiers decoded here.
pub mod id {
    /// INSPVA: INS position, velocity and attitude.
    pub const INSPVA: u16 = 507;
    /// INSPVAS: INSPVA with the short header.
    pub const INSPVAS: u16 = 508;
    /// INSPVAX: extended INSPVA with standard deviations.
    pub const INSPVAX: u16 = 1465;
    /// BESTPOS: best available GNSS position.
    pub const BESTPOS: u16 = 42;
    /// CORRIMUDATA: corrected IMU increments.
    pub const CORRIMUDATA: u16 = 812;
    /// CORRIMUS: CORRIMUDATA with the short header.
    pub const CORRIMUS: u16 = 813;
    /// TIME: receiver time and UTC offset.
    pub const TIME: u16 = 101;
}

/// A little-endian reader over a message body that fails instead of panicking.
struct Body<'a>(&'a [u8]);

impl Body<'_> {
    fn bytes<const N: usize>(&self, at: usize) -> Result<[u8; N], &'static str> {
        self.0
            .get(at..at + N)
            .and_then(|s| s.try_into().ok())
            .ok_or("message_too_short")
    }
    fn f64(&self, at: usize) -> Result<f64, &'static str> {
        Ok(f64::from_le_bytes(self.bytes(at)?))
    }
    fn f32(&self, at: usize) -> Result<f64, &'static str> {
        Ok(f32::from_le_bytes(self.bytes(at)?) as f64)
    }
    fn u32(&self, at: usize) -> Result<u32, &'static str> {
        Ok(u32::from_le_bytes(self.bytes(at)?))
    }
    fn u8(&self, at: usize) -> Result<u8, &'static str> {
        self.0.get(at).copied().ok_or("message_too_short")
    }
}

/// Message id and header time of a frame's header (long or short).
pub fn header_id_time(header: &[u8], short: bool) -> Option<(u16, NavTime)> {
    let id = u16::from_le_bytes(header.get(4..6)?.try_into().ok()?);
    let (week, ms) = if short {
        (
            u16::from_le_bytes(header.get(6..8)?.try_into().ok()?),
            u32::from_le_bytes(header.get(8..12)?.try_into().ok()?),
        )
    } else {
        (
            u16::from_le_bytes(header.get(14..16)?.try_into().ok()?),
            u32::from_le_bytes(header.get(16..20)?.try_into().ok()?),
        )
    };
    let time = if week == 0 {
        // Time status UNKNOWN: the receiver has no GPS time yet.
        NavTime::None
    } else {
        NavTime::Gps {
            week: week as u32,
            sow: ms as f64 / 1000.0,
        }
    };
    Some((id, time))
}

fn finite(v: f64, why: &'static str) -> Result<f64, &'static str> {
    if v.is_finite() { Ok(v) } else { Err(why) }
}

fn lat_lon(b: &Body<'_>, at: usize) -> Result<(f64, f64), &'static str> {
    let lat = finite(b.f64(at)?, "bad_latitude")?;
    let lon = finite(b.f64(at + 8)?, "bad_longitude")?;
    if lat.abs() > 90.0 {
        return Err("bad_latitude");
    }
    if lon.abs() > 360.0 {
        return Err("bad_longitude");
    }
    Ok((lat, lon))
}

/// Latitude, longitude, height above MSL (f64 each from `at`) and undulation (f32 after them),
/// as INSPVAX and BESTPOS lay them out.
fn position_msl(s: &mut NavSample, b: &Body<'_>, at: usize) -> Result<(), &'static str> {
    let (lat, lon) = lat_lon(b, at)?;
    s.lat = Some(lat);
    s.lon = Some(lon);
    let msl = finite(b.f64(at + 16)?, "bad_height")?;
    let und = finite(b.f32(at + 24)?, "bad_height")?;
    s.height_msl = Some(msl);
    s.height = Some(msl + und);
    Ok(())
}

/// Own week and seconds fields (INSPVA, CORRIMUDATA) as a time; week 0 means unknown.
fn own_time(b: &Body<'_>) -> Result<NavTime, &'static str> {
    let week = b.u32(0)?;
    let sow = finite(b.f64(4)?, "bad_time")?;
    if !(0.0..604_800.0 + 1.0).contains(&sow) {
        return Err("bad_time");
    }
    Ok(if week == 0 {
        NavTime::None
    } else {
        NavTime::Gps { week, sow }
    })
}

fn attitude(s: &mut NavSample, b: &Body<'_>, at: usize) -> Result<(), &'static str> {
    let roll = finite(b.f64(at)?, "bad_roll")?;
    let pitch = finite(b.f64(at + 8)?, "bad_pitch")?;
    let az = finite(b.f64(at + 16)?, "bad_heading")?;
    if !(-360.0..=360.0).contains(&az) || roll.abs() > 180.0 || pitch.abs() > 90.0 {
        return Err("bad_attitude");
    }
    s.roll = Some(roll);
    s.pitch = Some(pitch);
    s.heading = Some(az.rem_euclid(360.0));
    Ok(())
}

fn velocity(s: &mut NavSample, b: &Body<'_>, at: usize) -> Result<(), &'static str> {
    s.vel_north = Some(finite(b.f64(at)?, "bad_velocity")?);
    s.vel_east = Some(finite(b.f64(at + 8)?, "bad_velocity")?);
    s.vel_up = Some(finite(b.f64(at + 16)?, "bad_velocity")?);
    Ok(())
}

/// Decodes a message: `Ok(None)` for a message id not decoded here, `Err(reason)` for one that
/// is but whose contents are unusable.
pub fn decode(header: &[u8], body: &[u8], short: bool) -> Result<Option<NavSample>, &'static str> {
    let (msg, header_time) = header_id_time(header, short).ok_or("bad_header")?;
    let b = Body(body);
    let s = match msg {
        id::INSPVA | id::INSPVAS => {
            let mut s = NavSample::new(NavKind::Inspva, own_time(&b)?);
            let (lat, lon) = lat_lon(&b, 12)?;
            s.lat = Some(lat);
            s.lon = Some(lon);
            s.height = Some(finite(b.f64(28)?, "bad_height")?);
            velocity(&mut s, &b, 36)?;
            attitude(&mut s, &b, 60)?;
            s.ins_status = Some(b.u32(84)?);
            s
        }
        id::INSPVAX => {
            let mut s = NavSample::new(NavKind::Inspvax, header_time);
            s.ins_status = Some(b.u32(0)?);
            s.fix = Some(b.u32(4)?);
            position_msl(&mut s, &b, 8)?;
            velocity(&mut s, &b, 36)?;
            attitude(&mut s, &b, 60)?;
            s.position_sigma = Some([b.f32(84)?, b.f32(88)?, b.f32(92)?]);
            s.attitude_sigma = Some([b.f32(108)?, b.f32(112)?, b.f32(116)?]);
            s
        }
        id::BESTPOS => {
            let mut s = NavSample::new(NavKind::Bestpos, header_time);
            let status = b.u32(0)?;
            if status != 0 {
                // Solution status other than SOL_COMPUTED: no usable position.
                return Err("no_fix");
            }
            s.fix = Some(b.u32(4)?);
            position_msl(&mut s, &b, 8)?;
            s.position_sigma = Some([b.f32(40)?, b.f32(44)?, b.f32(48)?]);
            s.satellites = Some(b.u8(65)? as u32);
            s
        }
        id::CORRIMUDATA | id::CORRIMUS => {
            let mut s = NavSample::new(NavKind::Corrimudata, own_time(&b)?);
            s.angular = Some([
                finite(b.f64(12)?, "bad_imu")?,
                finite(b.f64(20)?, "bad_imu")?,
                finite(b.f64(28)?, "bad_imu")?,
            ]);
            s.linear = Some([
                finite(b.f64(36)?, "bad_imu")?,
                finite(b.f64(44)?, "bad_imu")?,
                finite(b.f64(52)?, "bad_imu")?,
            ]);
            s
        }
        id::TIME => {
            let mut s = NavSample::new(NavKind::Time, header_time);
            let utc_offset = finite(b.f64(20)?, "bad_time")?;
            // UTC status: 0 invalid, 1 valid, 2 warning.
            if b.u32(40)? == 0 {
                return Err("utc_invalid");
            }
            s.gps_minus_utc = Some(-utc_offset);
            s
        }
        _ => return Ok(None),
    };
    Ok(Some(s))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(id: u16, len: usize, week: u16, ms: u32) -> Vec<u8> {
        let mut h = vec![0xAA, 0x44, 0x12, 28];
        h.extend_from_slice(&id.to_le_bytes());
        h.extend_from_slice(&[0, 0]);
        h.extend_from_slice(&(len as u16).to_le_bytes());
        h.resize(14, 0);
        h.extend_from_slice(&week.to_le_bytes());
        h.extend_from_slice(&ms.to_le_bytes());
        h.resize(28, 0);
        h
    }

    #[test]
    fn inspva_fields_land_where_the_manual_puts_them() {
        let mut b = Vec::new();
        b.extend_from_slice(&2000u32.to_le_bytes());
        b.extend_from_slice(&123.5f64.to_le_bytes());
        for v in [45.0f64, -75.0, 100.0, 1.0, 2.0, 3.0, 0.5, -0.25, 359.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&3u32.to_le_bytes());
        let s = decode(&header(id::INSPVA, b.len(), 2000, 0), &b, false)
            .unwrap()
            .unwrap();
        assert_eq!(
            s.time,
            NavTime::Gps {
                week: 2000,
                sow: 123.5
            }
        );
        assert_eq!(
            (s.lat, s.lon, s.height),
            (Some(45.0), Some(-75.0), Some(100.0))
        );
        assert_eq!(
            (s.vel_north, s.vel_east, s.vel_up),
            (Some(1.0), Some(2.0), Some(3.0))
        );
        assert_eq!(
            (s.roll, s.pitch, s.heading),
            (Some(0.5), Some(-0.25), Some(359.0))
        );
        assert_eq!(s.ins_status, Some(3));
        // A short body is an error, not a panic.
        assert_eq!(
            decode(&header(id::INSPVA, 40, 2000, 0), &b[..40], false),
            Err("message_too_short")
        );
        // Unknown ids are not decoded.
        assert_eq!(decode(&header(9999, 0, 2000, 0), &[], false), Ok(None));
    }
}
