//! The GeoTIFF GeoKey directory (GeoKeyDirectoryTag, record 34735) as LAS (`LASF_Projection`)
//! and PulseWaves (`PulseWaves_Proj`) store it, and the coordinate reference system its keys
//! name. Shared by both readers so they decide the same way.
//!
//! The directory is u16 little-endian values: a header (version, revision, minor revision,
//! number of keys), then per key its id, TIFF tag location (0: the value is in the key itself),
//! count and value or offset. Reading never fails: a directory shorter than it declares is read
//! as far as it goes ([`GeoKeyDirectory::declared`] says how many were promised).
//!
//! **Precedence** ([`GeoKeyDirectory::crs`]), of the keys stored in the key itself; a code is
//! a value in 1..=32766 (0 and the private range 32768.. are no code):
//!
//! 1. ProjectedCSTypeGeoKey (3072) with an EPSG code (1..=32766): that projected CRS, whatever
//!    the model type says (it is the most specific statement). 32767 (user-defined) gives
//!    [`KeysCrs::UserDefinedProjection`]: the code, if any, must come from elsewhere (the
//!    PulseWaves reader reads a UTM zone from its citation).
//! 2. GTModelTypeGeoKey (1024) = 3, geocentric: EPSG:4978 (WGS 84 geocentric X, Y, Z), unless
//!    GeographicTypeGeoKey (2048) names another datum: a geocentric code there (4978, 4936) is
//!    taken as is; a WGS 84 code (4326, 4979) gives 4978 and an ETRS89 one (4258, 4937) gives
//!    4936 (ETRS89 geocentric); any other code leaves the CRS unknown, since this reader knows
//!    no geocentric code for that datum.
//! 3. GeographicTypeGeoKey (2048) with a code, when the model type is not 1 (projected): that
//!    geographic CRS. With a projected model and no usable projected code the geographic code
//!    is only the projection's datum, not the coordinates' CRS, so it is not used.
//! 4. Otherwise unknown, with the reason.

/// GTModelTypeGeoKey: 1 projected, 2 geographic, 3 geocentric.
pub const MODEL_TYPE_KEY: u16 = 1024;
/// GTCitationGeoKey (ASCII).
pub const CITATION_KEY: u16 = 1026;
/// GeographicTypeGeoKey (GeodeticCRSGeoKey in GeoTIFF 1.1).
pub const GEOGRAPHIC_TYPE_KEY: u16 = 2048;
/// ProjectedCSTypeGeoKey (ProjectedCRSGeoKey in GeoTIFF 1.1).
pub const PROJECTED_CS_KEY: u16 = 3072;
/// PCSCitationGeoKey (ASCII).
pub const PCS_CITATION_KEY: u16 = 3073;
/// GTModelTypeGeoKey value of a projected model.
pub const MODEL_PROJECTED: u16 = 1;
/// GTModelTypeGeoKey value of a geocentric model (X, Y, Z from the Earth's centre).
pub const MODEL_GEOCENTRIC: u16 = 3;
/// GeoTIFF "user-defined" code: no EPSG code.
pub const USER_DEFINED: u16 = 32767;
/// EPSG code of WGS 84 geocentric (X, Y, Z, metres).
pub const EPSG_WGS84_GEOCENTRIC: u16 = 4978;

/// Geographic (2D, 3D) and geocentric EPSG codes of the datums whose geocentric CRS is known
/// here: (geographic codes, geocentric code).
const GEOCENTRIC_OF_DATUM: [(&[u16], u16); 2] = [
    // WGS 84: 4326 (2D), 4979 (3D), 4978 geocentric.
    (&[4326, 4979, 4978], EPSG_WGS84_GEOCENTRIC),
    // ETRS89: 4258 (2D), 4937 (3D), 4936 geocentric.
    (&[4258, 4937, 4936], 4936),
];

/// One GeoKey entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GeoKey {
    /// Key id (1024, 2048, 3072, ...).
    pub id: u16,
    /// TIFF tag holding the value: 0 when the value is in the key itself, 34736 (doubles) or
    /// 34737 (ASCII) otherwise.
    pub location: u16,
    /// Number of values.
    pub count: u16,
    /// The value (location 0) or the offset into the tag at `location`.
    pub value_or_offset: u16,
}

/// A parsed GeoKey directory.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GeoKeyDirectory {
    /// The keys read (at most as many as declared and as the payload holds).
    pub keys: Vec<GeoKey>,
    /// Number of keys the header declares (0 when there is no full header).
    pub declared: usize,
}

/// The CRS the keys name ([`GeoKeyDirectory::crs`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum KeysCrs {
    /// An EPSG code.
    Epsg(u16),
    /// ProjectedCSTypeGeoKey is 32767: a projection the keys describe by parameters (and a
    /// citation) rather than by code.
    UserDefinedProjection,
    /// No code; why, in words.
    Unknown(String),
}

impl GeoKeyDirectory {
    /// Parses a directory payload (bytes, u16 little-endian). Never panics.
    pub fn parse(payload: &[u8]) -> GeoKeyDirectory {
        let shorts: Vec<u16> = payload
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        let Some(&declared) = shorts.get(3) else {
            return GeoKeyDirectory::default();
        };
        let keys = shorts[4..]
            .chunks_exact(4)
            .take(usize::from(declared))
            .map(|k| GeoKey {
                id: k[0],
                location: k[1],
                count: k[2],
                value_or_offset: k[3],
            })
            .collect();
        GeoKeyDirectory {
            keys,
            declared: usize::from(declared),
        }
    }

    /// Number of keys the payload actually holds, of those declared.
    pub fn available(&self) -> usize {
        self.keys.len()
    }

    /// The value of key `id` when stored in the key itself (the first such key).
    pub fn direct(&self, id: u16) -> Option<u16> {
        self.keys
            .iter()
            .find(|k| k.id == id && k.location == 0)
            .map(|k| k.value_or_offset)
    }

    /// The CRS the keys name, by the precedence of the module documentation.
    pub fn crs(&self) -> KeysCrs {
        let model = self.direct(MODEL_TYPE_KEY);
        let code = |id| self.direct(id).filter(|c| (1..USER_DEFINED).contains(c));
        match self.direct(PROJECTED_CS_KEY) {
            Some(USER_DEFINED) => return KeysCrs::UserDefinedProjection,
            Some(c @ 1..USER_DEFINED) => return KeysCrs::Epsg(c),
            _ => {}
        }
        let geographic = code(GEOGRAPHIC_TYPE_KEY);
        if model == Some(MODEL_GEOCENTRIC) {
            let Some(g) = geographic else {
                return KeysCrs::Epsg(EPSG_WGS84_GEOCENTRIC);
            };
            return match GEOCENTRIC_OF_DATUM
                .iter()
                .find(|(codes, _)| codes.contains(&g))
            {
                Some((_, geocentric)) => KeysCrs::Epsg(*geocentric),
                None => KeysCrs::Unknown(format!(
                    "geocentric model (GTModelTypeGeoKey 3) on the datum of EPSG:{g} \
                     (GeographicTypeGeoKey), whose geocentric CRS code is not known here"
                )),
            };
        }
        match (model, geographic) {
            (Some(MODEL_PROJECTED), Some(g)) => KeysCrs::Unknown(format!(
                "projected model (GTModelTypeGeoKey 1) without a projected CRS code; \
                 GeographicTypeGeoKey EPSG:{g} names only its datum"
            )),
            (_, Some(g)) => KeysCrs::Epsg(g),
            (_, None) => KeysCrs::Unknown(format!(
                "GeoKeys name no EPSG code (GTModelTypeGeoKey {})",
                model.map_or("absent".to_string(), |m| m.to_string())
            )),
        }
    }

    /// The EPSG code the keys name, if any ([`GeoKeyDirectory::crs`]).
    pub fn epsg(&self) -> Option<u16> {
        match self.crs() {
            KeysCrs::Epsg(c) => Some(c),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A directory payload with `keys` as (id, value) stored in the key itself.
    fn directory(keys: &[(u16, u16)]) -> Vec<u8> {
        let mut shorts = vec![1u16, 1, 0, keys.len() as u16];
        for &(id, value) in keys {
            shorts.extend([id, 0, 1, value]);
        }
        shorts.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn crs(keys: &[(u16, u16)]) -> KeysCrs {
        GeoKeyDirectory::parse(&directory(keys)).crs()
    }

    #[test]
    fn geokeys_projected_code_comes_first() {
        assert_eq!(crs(&[(1024, 1), (3072, 32633)]), KeysCrs::Epsg(32633));
        assert_eq!(
            crs(&[(1024, 1), (2048, 4326), (3072, 32633)]),
            KeysCrs::Epsg(32633)
        );
        // Even against a geocentric model: the code is the more specific statement.
        assert_eq!(crs(&[(1024, 3), (3072, 32633)]), KeysCrs::Epsg(32633));
        assert_eq!(
            crs(&[(1024, 1), (3072, 32767)]),
            KeysCrs::UserDefinedProjection
        );
        // 0 and private codes are no code: the next rule decides.
        assert_eq!(
            crs(&[(1024, 2), (3072, 0), (2048, 4326)]),
            KeysCrs::Epsg(4326)
        );
        assert_eq!(crs(&[(1024, 3), (3072, 40000)]), KeysCrs::Epsg(4978));
    }

    #[test]
    fn geokeys_geocentric_model_is_epsg_4978() {
        assert_eq!(crs(&[(1024, 3)]), KeysCrs::Epsg(4978));
        assert_eq!(crs(&[(1024, 3), (2048, 4326)]), KeysCrs::Epsg(4978));
        assert_eq!(crs(&[(1024, 3), (2048, 4979)]), KeysCrs::Epsg(4978));
        assert_eq!(crs(&[(1024, 3), (2048, 4978)]), KeysCrs::Epsg(4978));
        assert_eq!(crs(&[(1024, 3), (2048, 32767)]), KeysCrs::Epsg(4978));
        // A geographic key naming another datum says more.
        assert_eq!(crs(&[(1024, 3), (2048, 4258)]), KeysCrs::Epsg(4936));
        assert_eq!(crs(&[(1024, 3), (2048, 4936)]), KeysCrs::Epsg(4936));
        let KeysCrs::Unknown(why) = crs(&[(1024, 3), (2048, 4269)]) else {
            panic!("NAD83 geocentric is not known here");
        };
        assert!(
            why.contains("EPSG:4269") && why.contains("geocentric"),
            "{why}"
        );
        // A geocentric model only counts when stored in the key itself.
        let mut b = directory(&[(1024, 3)]);
        b[10..12].copy_from_slice(&34736u16.to_le_bytes());
        assert!(matches!(
            GeoKeyDirectory::parse(&b).crs(),
            KeysCrs::Unknown(_)
        ));
    }

    #[test]
    fn geokeys_geographic_code_unless_the_model_is_projected() {
        assert_eq!(crs(&[(1024, 2), (2048, 4326)]), KeysCrs::Epsg(4326));
        assert_eq!(crs(&[(2048, 4326)]), KeysCrs::Epsg(4326));
        let KeysCrs::Unknown(why) = crs(&[(1024, 1), (2048, 4326)]) else {
            panic!("a projected model's datum is not the coordinates' CRS");
        };
        assert!(why.contains("projected model"), "{why}");
        let KeysCrs::Unknown(why) = crs(&[(1024, 2)]) else {
            panic!("no code");
        };
        assert!(why.contains("GTModelTypeGeoKey 2"), "{why}");
        assert!(matches!(crs(&[]), KeysCrs::Unknown(_)));
    }

    #[test]
    fn geokeys_short_or_overdeclared_directories_read_what_is_there() {
        let mut b = directory(&[(1024, 3), (3072, 32633)]);
        assert_eq!(GeoKeyDirectory::parse(&b).available(), 2);
        // Declares 1000 keys: reads the two present.
        b[6..8].copy_from_slice(&1000u16.to_le_bytes());
        let d = GeoKeyDirectory::parse(&b);
        assert_eq!((d.declared, d.available()), (1000, 2));
        assert_eq!(d.epsg(), Some(32633));
        // Cut inside the second key: only the first (geocentric) remains.
        let d = GeoKeyDirectory::parse(&b[..8 + 8 + 5]);
        assert_eq!((d.available(), d.epsg()), (1, Some(4978)));
        for n in 0..b.len() {
            let _ = GeoKeyDirectory::parse(&b[..n]).crs();
        }
        assert_eq!(GeoKeyDirectory::parse(&b[..7]), GeoKeyDirectory::default());
    }
}
