//! The coordinate reference system of the anchors and targets, from the `PulseWaves_Proj`
//! records (the GeoTIFF keys of LAS: 34735 key directory, 34736 doubles, 34737 ASCII; 2112 OGC
//! WKT). Damaged or ambiguous keys never fail the read: they leave the CRS unknown, or take the
//! best reading, and say so in a warning. The keys are read, and their precedence decided, by
//! [`crate::format::geokeys`] (shared with the LAS reader); this module adds the WKT, the UTM
//! zone of a user-defined projection's citation, and the warnings.

use super::le;
use super::vlr::Vlr;
use crate::format::geokeys::{
    CITATION_KEY, GeoKeyDirectory, KeysCrs, PCS_CITATION_KEY, PROJECTED_CS_KEY,
};

/// What the projection records say.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CrsInfo {
    /// OGC WKT, or `EPSG:<code>`; `None` when not known.
    pub crs: Option<String>,
    /// What was doubtful, for the report (also logged with `tracing::warn`).
    pub warnings: Vec<String>,
}

fn key_name(id: u16) -> &'static str {
    match id {
        1024 => "GTModelTypeGeoKey",
        1025 => "GTRasterTypeGeoKey",
        1026 => "GTCitationGeoKey",
        2048 => "GeographicTypeGeoKey",
        2049 => "GeogCitationGeoKey",
        2052 => "GeogLinearUnitsGeoKey",
        2054 => "GeogAngularUnitsGeoKey",
        3072 => "ProjectedCSTypeGeoKey",
        3073 => "PCSCitationGeoKey",
        3074 => "ProjectionGeoKey",
        3076 => "ProjLinearUnitsGeoKey",
        4096 => "VerticalCSTypeGeoKey",
        4099 => "VerticalUnitsGeoKey",
        _ => "GeoKey",
    }
}

/// A WGS 84 / UTM code (EPSG 32601..32660 north, 32701..32760 south).
fn is_wgs84_utm(code: u16) -> bool {
    (32601..=32660).contains(&code) || (32701..=32760).contains(&code)
}

/// Reads the CRS from the kept projection records of `file` (later records win).
pub fn from_records(records: &[Vlr]) -> CrsInfo {
    let mut info = CrsInfo::default();
    let find = |id: u32| records.iter().rev().find(|r| r.record_id == id);
    if let Some(wkt) = find(2112) {
        let text = le::text(&wkt.payload, 0, wkt.payload.len());
        if !text.is_empty() {
            info.crs = Some(text);
            return info;
        }
        info.warnings
            .push(format!("{}: the OGC WKT record (2112) is empty", wkt.place));
    }
    let Some(dir) = find(34735) else {
        info.warnings
            .push("no GeoKey directory (34735) and no OGC WKT (2112): CRS unknown".into());
        return info;
    };
    let ascii = find(34737).map(|r| r.payload.as_slice()).unwrap_or(&[]);
    let keys = GeoKeyDirectory::parse(&dir.payload);
    if dir.payload.len() < 8 || keys.declared > keys.available() {
        info.warnings.push(format!(
            "{}: GeoKey directory (34735) declares {} keys but holds {}; reading those",
            dir.place,
            keys.declared,
            keys.available()
        ));
    }
    let citation = |id: u16| {
        keys.keys
            .iter()
            .find(|k| k.id == id && k.location == 34737)
            .map(|k| {
                let start = usize::from(k.value_or_offset);
                let end = start.saturating_add(usize::from(k.count));
                le::text(
                    ascii
                        .get(start.min(ascii.len())..end.min(ascii.len()))
                        .unwrap_or(&[]),
                    0,
                    usize::MAX,
                )
            })
    };
    let unknown = match keys.crs() {
        KeysCrs::Epsg(code) => {
            info.crs = Some(format!("EPSG:{code}"));
            return info;
        }
        KeysCrs::UserDefinedProjection => {
            let cite = citation(PCS_CITATION_KEY)
                .or_else(|| citation(CITATION_KEY))
                .unwrap_or_default();
            let all = String::from_utf8_lossy(ascii).to_string();
            match utm_from_citation(&cite, &all) {
                Some(code) => {
                    info.warnings.push(format!(
                        "user-defined projected CRS (ProjectedCSTypeGeoKey 3072 = 32767); taken \
                         as EPSG:{code} from its citation {cite:?}"
                    ));
                    info.crs = Some(format!("EPSG:{code}"));
                }
                None => info.warnings.push(format!(
                    "user-defined projected CRS (ProjectedCSTypeGeoKey 3072 = 32767) with \
                     citation {cite:?}: CRS unknown"
                )),
            }
            return info;
        }
        KeysCrs::Unknown(why) => why,
    };
    // No usable code: look for a projected CRS code stored under the wrong key.
    if let Some(k) = keys
        .keys
        .iter()
        .find(|k| k.location == 0 && k.id != PROJECTED_CS_KEY && is_wgs84_utm(k.value_or_offset))
    {
        info.warnings.push(format!(
            "malformed GeoKeys: {} ({}) holds {}, which is not a value of that key but looks \
             like EPSG:{} stored under the wrong key; CRS left unknown",
            key_name(k.id),
            k.id,
            k.value_or_offset,
            k.value_or_offset
        ));
    } else {
        info.warnings.push(format!("{unknown}: CRS unknown"));
    }
    info
}

/// `EPSG:326zz`/`327zz` when a citation names WGS 84 and a UTM zone (e.g.
/// `UTM_North zone 33|WGS84|`).
fn utm_from_citation(cite: &str, all_ascii: &str) -> Option<u16> {
    let c = cite.to_ascii_lowercase();
    let all = format!("{c} {}", all_ascii.to_ascii_lowercase());
    if !c.contains("utm")
        || !(all.contains("wgs84") || all.contains("wgs 84") || all.contains("wgs_84"))
    {
        return None;
    }
    let after = &c[c.find("zone")? + 4..];
    let digits: String = after
        .trim_start_matches([' ', '_'])
        .chars()
        .take_while(|ch| ch.is_ascii_digit())
        .collect();
    let zone: u16 = digits.parse().ok().filter(|z| (1..=60).contains(z))?;
    let rest = after
        .trim_start_matches([' ', '_'])
        .get(digits.len()..)
        .unwrap_or("");
    let south = c.contains("south") || rest.starts_with('s');
    let north = c.contains("north") || rest.starts_with('n');
    match (north, south) {
        (true, false) => Some(32600 + zone),
        (false, true) => Some(32700 + zone),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utm_citations() {
        assert_eq!(
            utm_from_citation("UTM_North zone 33", "UTM_North zone 33|WGS84|"),
            Some(32633)
        );
        assert_eq!(
            utm_from_citation("WGS84_UTM_zone_13N WGS84", "x"),
            Some(32613)
        );
        assert_eq!(utm_from_citation("UTM zone 33", "WGS84"), None);
        assert_eq!(utm_from_citation("Lambert", "WGS84"), None);
        assert_eq!(utm_from_citation("utm zone", "WGS84"), None);
    }
}
