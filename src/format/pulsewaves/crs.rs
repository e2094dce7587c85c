//! The coordinate reference system of the anchors and targets, from the `PulseWaves_Proj`
//! records (the GeoTIFF keys of LAS: 34735 key directory, 34736 doubles, 34737 ASCII; 2112 OGC
//! WKT). Damaged or ambiguous keys never fail the read: they leave the CRS unknown, or take the
//! best reading, and say so in a warning.

use super::le;
use super::vlr::Vlr;

/// What the projection records say.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CrsInfo {
    /// OGC WKT, or `EPSG:<code>`; `None` when not known.
    pub crs: Option<String>,
    /// What was doubtful, for the report (also logged with `tracing::warn`).
    pub warnings: Vec<String>,
}

/// A GeoKey entry: (key ID, TIFF tag location, count, value or offset).
type Key = (u16, u16, u16, u16);

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
    let shorts: Vec<u16> = dir.payload.chunks_exact(2).map(|c| le::u16(c, 0)).collect();
    let declared = shorts.get(3).copied().unwrap_or(0) as usize;
    let available = shorts.len().saturating_sub(4) / 4;
    if shorts.len() < 4 || declared > available {
        info.warnings.push(format!(
            "{}: GeoKey directory (34735) declares {declared} keys but holds {available}; \
             reading those",
            dir.place
        ));
    }
    let keys: Vec<Key> = shorts
        .get(4..)
        .unwrap_or(&[])
        .chunks_exact(4)
        .take(declared.min(available))
        .map(|k| (k[0], k[1], k[2], k[3]))
        .collect();
    let direct = |id: u16| keys.iter().find(|k| k.0 == id && k.1 == 0).map(|k| k.3);
    let citation = |id: u16| {
        keys.iter().find(|k| k.0 == id && k.1 == 34737).map(|k| {
            let start = usize::from(k.3);
            let end = start.saturating_add(usize::from(k.2));
            le::text(
                ascii
                    .get(start.min(ascii.len())..end.min(ascii.len()))
                    .unwrap_or(&[]),
                0,
                usize::MAX,
            )
        })
    };
    let model = direct(1024);
    match direct(3072) {
        Some(code @ 1..=32766) => {
            info.crs = Some(format!("EPSG:{code}"));
            return info;
        }
        Some(32767) => {
            let cite = citation(3073)
                .or_else(|| citation(1026))
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
        _ => {}
    }
    if model != Some(1)
        && let Some(code @ 1..=32766) = direct(2048)
    {
        info.crs = Some(format!("EPSG:{code}"));
        return info;
    }
    // No usable code: look for a projected CRS code stored under the wrong key.
    if let Some(k) = keys
        .iter()
        .find(|k| k.1 == 0 && k.0 != 3072 && is_wgs84_utm(k.3))
    {
        info.warnings.push(format!(
            "malformed GeoKeys: {} ({}) holds {}, which is not a value of that key but looks \
             like EPSG:{} stored under the wrong key; CRS left unknown",
            key_name(k.0),
            k.0,
            k.3,
            k.3
        ));
    } else {
        info.warnings.push(format!(
            "GeoKeys name no EPSG code (GTModelTypeGeoKey {}): CRS unknown",
            model.map_or("absent".to_string(), |m| m.to_string())
        ));
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
