//! The output coordinate reference system and WGS84 ↔ ECEF (see the module documentation of
//! [`crate::geo`]).

use proj4rs::proj::Proj;
use proj4rs::transform::transform;

use crate::nav::trajectory::{WGS84_A, WGS84_E2};

/// Errors of coordinate conversion.
#[derive(Debug, thiserror::Error)]
pub enum GeoError {
    /// The EPSG code is not one `proj4rs` knows.
    #[error("EPSG:{code} is not a coordinate reference system fwlidar knows ({why})")]
    UnknownEpsg {
        /// The code.
        code: u32,
        /// What proj4rs said.
        why: String,
    },
    /// The CRS is geographic or geocentric, not a map projection.
    #[error("EPSG:{code} is not a projected coordinate reference system ({proj4})")]
    NotProjected {
        /// The code.
        code: u32,
        /// Its PROJ string.
        proj4: String,
    },
    /// A point could not be converted.
    #[error("cannot convert ({lat}, {lon}, {h}) to {to}: {why}")]
    Convert {
        /// Latitude, degrees.
        lat: f64,
        /// Longitude, degrees.
        lon: f64,
        /// Height, metres.
        h: f64,
        /// Target.
        to: String,
        /// What proj4rs said.
        why: String,
    },
}

/// WGS84 geographic, PROJ's pivot (parsed once).
fn wgs84() -> &'static Proj {
    static P: std::sync::OnceLock<Proj> = std::sync::OnceLock::new();
    P.get_or_init(|| {
        Proj::from_proj_string("+proj=longlat +datum=WGS84 +no_defs")
            .expect("the WGS84 definition parses")
    })
}

/// WGS84 geocentric (ECEF), parsed once: the reference for the closed forms in tests.
#[cfg(test)]
fn geocentric() -> &'static Proj {
    static P: std::sync::OnceLock<Proj> = std::sync::OnceLock::new();
    P.get_or_init(|| {
        Proj::from_proj_string("+proj=geocent +datum=WGS84 +units=m +no_defs")
            .expect("the WGS84 geocentric definition parses")
    })
}

/// The EPSG code of a CRS given as `EPSG:<code>` or as WKT with an EPSG identifier (the last
/// one: the CRS's own, after those of its parts).
pub fn epsg_of(crs: &str) -> Option<u32> {
    let t = crs.trim();
    if let Some(code) = t.strip_prefix("EPSG:") {
        return code.trim().parse().ok();
    }
    let at = t.rfind("\"EPSG\",")?;
    let rest = t[at + 7..].trim_start().trim_start_matches('"');
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

/// The EPSG code of the WGS84 UTM zone containing (`lat`, `lon`) degrees: 326zz north, 327zz
/// south, with the Norway and Svalbard exceptions of the UTM grid.
pub fn utm_epsg(lat: f64, lon: f64) -> u32 {
    let lon = (lon + 180.0).rem_euclid(360.0) - 180.0;
    let mut zone = (((lon + 180.0) / 6.0).floor() as i32).clamp(0, 59) + 1;
    if (56.0..64.0).contains(&lat) && (3.0..12.0).contains(&lon) {
        zone = 32;
    }
    if (72.0..84.0).contains(&lat) {
        zone = match lon {
            l if (0.0..9.0).contains(&l) => 31,
            l if (9.0..21.0).contains(&l) => 33,
            l if (21.0..33.0).contains(&l) => 35,
            l if (33.0..42.0).contains(&l) => 37,
            _ => zone,
        };
    }
    if lat >= 0.0 {
        32600 + zone as u32
    } else {
        32700 + zone as u32
    }
}

/// OGC WKT (WKT1) of a WGS 84 / UTM zone CRS (EPSG 32601..=32660 north, 32701..=32760 south),
/// written from the zone's defining parameters (central meridian 6·zone − 183°, scale 0.9996,
/// false easting 500 km, false northing 0 or 10 000 km): what LAS 1.4 output needs, without a
/// CRS database. `None` for other codes.
pub fn utm_wkt(code: u32) -> Option<String> {
    let (zone, south) = match code {
        32601..=32660 => (code - 32600, false),
        32701..=32760 => (code - 32700, true),
        _ => return None,
    };
    let meridian = 6 * zone as i32 - 183;
    Some(format!(
        "PROJCS[\"WGS 84 / UTM zone {zone}{hemi}\",GEOGCS[\"WGS 84\",DATUM[\"WGS_1984\",\
         SPHEROID[\"WGS 84\",6378137,298.257223563]],PRIMEM[\"Greenwich\",0],\
         UNIT[\"degree\",0.0174532925199433]],PROJECTION[\"Transverse_Mercator\"],\
         PARAMETER[\"latitude_of_origin\",0],PARAMETER[\"central_meridian\",{meridian}],\
         PARAMETER[\"scale_factor\",0.9996],PARAMETER[\"false_easting\",500000],\
         PARAMETER[\"false_northing\",{north}],UNIT[\"metre\",1],AUTHORITY[\"EPSG\",\"{code}\"]]",
        hemi = if south { "S" } else { "N" },
        north = if south { 10_000_000 } else { 0 },
    ))
}

/// A projected output CRS.
pub struct OutputCrs {
    code: u32,
    proj: Proj,
}

impl std::fmt::Debug for OutputCrs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "OutputCrs(EPSG:{})", self.code)
    }
}

impl OutputCrs {
    /// The projected CRS with this EPSG code.
    pub fn from_epsg(code: u32) -> Result<Self, GeoError> {
        let short = u16::try_from(code).map_err(|_| GeoError::UnknownEpsg {
            code,
            why: "code out of range".into(),
        })?;
        let proj = Proj::from_epsg_code(short).map_err(|e| GeoError::UnknownEpsg {
            code,
            why: e.to_string(),
        })?;
        if proj.is_latlong() || proj.is_geocent() {
            return Err(GeoError::NotProjected {
                code,
                proj4: proj.projname().to_string(),
            });
        }
        Ok(OutputCrs { code, proj })
    }

    /// The WGS84 UTM zone of a position (the first fix of a flight).
    pub fn utm_at(lat: f64, lon: f64) -> Result<Self, GeoError> {
        OutputCrs::from_epsg(utm_epsg(lat, lon))
    }

    /// The EPSG code.
    pub fn epsg(&self) -> u32 {
        self.code
    }

    /// Projects a WGS84 position (degrees, ellipsoidal metres) to (easting, northing, height):
    /// the height stays ellipsoidal.
    pub fn project(&self, lat: f64, lon: f64, h: f64) -> Result<[f64; 3], GeoError> {
        let mut p = (lon.to_radians(), lat.to_radians(), h);
        transform(wgs84(), &self.proj, &mut p).map_err(|e| GeoError::Convert {
            lat,
            lon,
            h,
            to: format!("EPSG:{}", self.code),
            why: e.to_string(),
        })?;
        Ok([p.0, p.1, h])
    }
}

impl OutputCrs {
    /// Projects two WGS84 positions at once (one call into the projection: what a pulse's
    /// chord needs). Same units and result as [`OutputCrs::project`].
    pub fn project_pair(&self, a: [f64; 3], b: [f64; 3]) -> Result<[[f64; 3]; 2], GeoError> {
        let mut pts = [
            (a[1].to_radians(), a[0].to_radians(), a[2]),
            (b[1].to_radians(), b[0].to_radians(), b[2]),
        ];
        transform(wgs84(), &self.proj, &mut pts[..]).map_err(|e| GeoError::Convert {
            lat: a[0],
            lon: a[1],
            h: a[2],
            to: format!("EPSG:{}", self.code),
            why: e.to_string(),
        })?;
        Ok([[pts[0].0, pts[0].1, a[2]], [pts[1].0, pts[1].1, b[2]]])
    }
}

/// ECEF (metres) of a WGS84 position (degrees, ellipsoidal metres). The closed form
/// `((N + h) cos φ cos λ, (N + h) cos φ sin λ, (N (1 − e²) + h) sin φ)` — a formula, not a
/// projection, and exact; checked against PROJ's geocentric conversion in
/// `tests/geodesy_proj.rs`. Non-finite input is an error.
pub fn ecef_of(lat: f64, lon: f64, h: f64) -> Result<[f64; 3], GeoError> {
    if !(lat.is_finite() && lon.is_finite() && h.is_finite()) || lat.abs() > 90.0 {
        return Err(GeoError::Convert {
            lat,
            lon,
            h,
            to: "ECEF".into(),
            why: "not a geodetic position".into(),
        });
    }
    let (sp, cp) = lat.to_radians().sin_cos();
    let (sl, cl) = lon.to_radians().sin_cos();
    let n = WGS84_A / (1.0 - WGS84_E2 * sp * sp).sqrt();
    Ok([
        (n + h) * cp * cl,
        (n + h) * cp * sl,
        (n * (1.0 - WGS84_E2) + h) * sp,
    ])
}

/// WGS84 position (degrees, ellipsoidal metres) of an ECEF point (metres), by Heikkinen's
/// exact closed form (no iteration); agrees with PROJ's geocentric inverse to a micrometre
/// (tested). Points near the Earth's centre (within 50 km), where the form degenerates, and
/// non-finite input are errors.
pub fn geodetic_of_ecef(x: [f64; 3]) -> Result<[f64; 3], GeoError> {
    let fail = |why: &str| GeoError::Convert {
        lat: f64::NAN,
        lon: f64::NAN,
        h: f64::NAN,
        to: "WGS84 from ECEF".into(),
        why: why.into(),
    };
    let [x, y, z] = x;
    if !(x.is_finite() && y.is_finite() && z.is_finite()) {
        return Err(fail("not a finite point"));
    }
    let a = WGS84_A;
    let e2 = WGS84_E2;
    let b2 = a * a * (1.0 - e2);
    let b = b2.sqrt();
    let ep2 = (a * a - b2) / b2;
    let p2 = x * x + y * y;
    let p = p2.sqrt();
    if (p2 + z * z).sqrt() < 50_000.0 {
        return Err(fail("too close to the Earth's centre"));
    }
    let f = 54.0 * b2 * z * z;
    let g = p2 + (1.0 - e2) * z * z - e2 * (a * a - b2);
    let c = e2 * e2 * f * p2 / (g * g * g);
    let s = (1.0 + c + (c * c + 2.0 * c).sqrt()).cbrt();
    let k = s + 1.0 / s + 1.0;
    let pp = f / (3.0 * k * k * g * g);
    let q = (1.0 + 2.0 * e2 * e2 * pp).sqrt();
    let r0 = -(pp * e2 * p) / (1.0 + q)
        + (0.5 * a * a * (1.0 + 1.0 / q)
            - pp * (1.0 - e2) * z * z / (q * (1.0 + q))
            - 0.5 * pp * p2)
            .max(0.0)
            .sqrt();
    let t = p - e2 * r0;
    let u = (t * t + z * z).sqrt();
    let v = (t * t + (1.0 - e2) * z * z).sqrt();
    let z0 = b2 * z / (a * v);
    let h = u * (1.0 - b2 / (a * v));
    let lat = (z + ep2 * z0).atan2(p);
    let lon = y.atan2(x);
    let _ = b;
    Ok([lat.to_degrees(), lon.to_degrees(), h])
}

/// PROJ's geocentric inverse through proj4rs: the reference the closed form is tested against.
#[cfg(test)]
fn geodetic_of_ecef_proj(x: [f64; 3]) -> [f64; 3] {
    let mut p = (x[0], x[1], x[2]);
    transform(geocentric(), wgs84(), &mut p).unwrap();
    [p.1.to_degrees(), p.0.to_degrees(), p.2]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epsg_from_code_or_wkt() {
        assert_eq!(epsg_of("EPSG:32618"), Some(32618));
        assert_eq!(
            epsg_of(
                r#"PROJCRS["WGS 84 / UTM zone 18N",BASEGEOGCRS["WGS 84",ID["EPSG",4326]],ID["EPSG",32618]]"#
            ),
            Some(32618)
        );
        assert_eq!(
            epsg_of(
                r#"PROJCS["x",GEOGCS["y",AUTHORITY["EPSG","4326"]],AUTHORITY["EPSG","32736"]]"#
            ),
            Some(32736)
        );
        assert_eq!(epsg_of("LOCAL_CS[\"x\"]"), None);
    }

    #[test]
    fn utm_zones_including_the_exceptions() {
        assert_eq!(utm_epsg(47.8, 13.0), 32633);
        assert_eq!(utm_epsg(-33.9, 151.2), 32756);
        assert_eq!(utm_epsg(60.0, 5.0), 32632, "Norway");
        assert_eq!(utm_epsg(78.0, 15.0), 32633, "Svalbard");
        assert_eq!(utm_epsg(0.0, 180.0), 32601);
        assert_eq!(utm_epsg(0.0, -180.0), 32601);
        assert_eq!(utm_epsg(10.0, 179.5), 32660);
        assert_eq!(utm_epsg(10.0, 359.0), 32630, "longitudes in 0..360 (LVIS)");
    }

    #[test]
    fn utm_wkt_states_the_zone_parameters() {
        let w = utm_wkt(32633).unwrap();
        assert!(w.starts_with("PROJCS[\"WGS 84 / UTM zone 33N\""), "{w}");
        assert!(
            w.contains("PARAMETER[\"central_meridian\",15]")
                && w.ends_with("AUTHORITY[\"EPSG\",\"32633\"]]")
        );
        let s = utm_wkt(32736).unwrap();
        assert!(s.contains("zone 36S") && s.contains("central_meridian\",33]"));
        assert!(s.contains("false_northing\",10000000]"));
        assert_eq!(utm_wkt(2154), None);
    }

    #[test]
    fn geographic_crs_is_refused_as_output() {
        let e = OutputCrs::from_epsg(4326).unwrap_err().to_string();
        assert!(
            e.contains("EPSG:4326") && e.contains("not a projected"),
            "{e}"
        );
        assert!(OutputCrs::from_epsg(99_999).is_err());
    }

    #[test]
    fn closed_form_inverse_agrees_with_proj() {
        for (lat, lon, h) in [
            (47.8, 13.4, 450.0),
            (-33.86, 151.21, 50.0),
            (89.9, 10.0, 3000.0),
            (-89.99, -120.0, 100.0),
            (0.0, 0.0, 0.0),
            (0.0, 179.9, 12_000.0),
            (60.0, -150.0, -50.0),
            (30.0, 90.0, 100_000.0),
        ] {
            let x = ecef_of(lat, lon, h).unwrap();
            let ours = geodetic_of_ecef(x).unwrap();
            let proj = geodetic_of_ecef_proj(x);
            // A micrometre: 1e-11 degrees of latitude is 1.1 µm.
            assert!(
                (ours[0] - proj[0]).abs() < 1e-11,
                "{lat} {lon} {h}: {ours:?} {proj:?}"
            );
            assert!(
                (ours[1] - proj[1]).abs() < 1e-11,
                "{lat} {lon} {h}: {ours:?} {proj:?}"
            );
            assert!(
                (ours[2] - proj[2]).abs() < 1e-6,
                "{lat} {lon} {h}: {ours:?} {proj:?}"
            );
            assert!((ours[0] - lat).abs() < 1e-11 && (ours[2] - h).abs() < 1e-6);
        }
        assert!(geodetic_of_ecef([0.0, 0.0, 0.0]).is_err());
        assert!(geodetic_of_ecef([f64::NAN, 0.0, 0.0]).is_err());
    }

    #[test]
    fn ecef_round_trip() {
        let x = ecef_of(52.0, 13.0, 100.0).unwrap();
        let g = geodetic_of_ecef(x).unwrap();
        assert!((g[0] - 52.0).abs() < 1e-10 && (g[1] - 13.0).abs() < 1e-10);
        assert!((g[2] - 100.0).abs() < 1e-6);
    }
}
