//! The output coordinate reference system and WGS84 ↔ ECEF (see the module documentation of
//! [`crate::geo`]).

use proj4rs::proj::Proj;
use proj4rs::transform::transform;

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

/// WGS84 geographic, PROJ's pivot.
fn wgs84() -> Proj {
    Proj::from_proj_string("+proj=longlat +datum=WGS84 +no_defs")
        .expect("the WGS84 definition parses")
}

fn geocentric() -> Proj {
    Proj::from_proj_string("+proj=geocent +datum=WGS84 +units=m +no_defs")
        .expect("the WGS84 geocentric definition parses")
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

/// A projected output CRS.
pub struct OutputCrs {
    code: u32,
    proj: Proj,
    wgs84: Proj,
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
        Ok(OutputCrs {
            code,
            proj,
            wgs84: wgs84(),
        })
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
        transform(&self.wgs84, &self.proj, &mut p).map_err(|e| GeoError::Convert {
            lat,
            lon,
            h,
            to: format!("EPSG:{}", self.code),
            why: e.to_string(),
        })?;
        Ok([p.0, p.1, h])
    }
}

/// ECEF (metres) of a WGS84 position (degrees, ellipsoidal metres).
pub fn ecef_of(lat: f64, lon: f64, h: f64) -> Result<[f64; 3], GeoError> {
    let mut p = (lon.to_radians(), lat.to_radians(), h);
    transform(&wgs84(), &geocentric(), &mut p).map_err(|e| GeoError::Convert {
        lat,
        lon,
        h,
        to: "ECEF".into(),
        why: e.to_string(),
    })?;
    Ok([p.0, p.1, p.2])
}

/// WGS84 position (degrees, ellipsoidal metres) of an ECEF point (metres).
pub fn geodetic_of_ecef(x: [f64; 3]) -> Result<[f64; 3], GeoError> {
    let mut p = (x[0], x[1], x[2]);
    transform(&geocentric(), &wgs84(), &mut p).map_err(|e| GeoError::Convert {
        lat: f64::NAN,
        lon: f64::NAN,
        h: f64::NAN,
        to: "WGS84".into(),
        why: e.to_string(),
    })?;
    Ok([p.1.to_degrees(), p.0.to_degrees(), p.2])
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn geographic_crs_is_refused_as_output() {
        let e = OutputCrs::from_epsg(4326).unwrap_err().to_string();
        assert!(
            e.contains("EPSG:4326") && e.contains("not a projected"),
            "{e}"
        );
        assert!(OutputCrs::from_epsg(99_999).is_err());
    }

    #[test]
    fn ecef_round_trip() {
        let x = ecef_of(52.0, 13.0, 100.0).unwrap();
        let g = geodetic_of_ecef(x).unwrap();
        assert!((g[0] - 52.0).abs() < 1e-10 && (g[1] - 13.0).abs() < 1e-10);
        assert!((g[2] - 100.0).abs() < 1e-6);
    }
}
