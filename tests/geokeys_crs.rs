//! The CRS of a geocentric GeoKey directory (GTModelTypeGeoKey 1024 = 3 is EPSG:4978), on
//! temporary copies of real LAS and PulseWaves files whose GeoKeys are patched: the model type
//! set to geocentric, the projected code cleared or the datum changed.

mod common;

use std::path::{Path, PathBuf};

use common::{fixture, fwlidar, text};

/// Byte offset of the GeoKey directory in `bytes`: the header (1, 1, 0, n) followed by `n`
/// keys whose ids are GeoKeys (1024..=5000). The real files hold exactly one.
fn directory_at(bytes: &[u8]) -> usize {
    let u16_at = |i: usize| u16::from_le_bytes([bytes[i], bytes[i + 1]]);
    let found: Vec<usize> = (0..bytes.len().saturating_sub(16))
        .filter(|&i| {
            let n = usize::from(u16_at(i + 6));
            (u16_at(i), u16_at(i + 2), u16_at(i + 4)) == (1, 1, 0)
                && (1..=64).contains(&n)
                && i + 8 + 8 * n <= bytes.len()
                && (0..n).all(|k| (1024..=5000).contains(&u16_at(i + 8 + 8 * k)))
        })
        .collect();
    assert_eq!(found.len(), 1, "GeoKey directories at {found:?}");
    found[0]
}

/// Sets the value of key `id` (stored in the key itself) of the directory in `bytes`; returns
/// the old value.
fn set_key(bytes: &mut [u8], id: u16, value: u16) -> u16 {
    let dir = directory_at(bytes);
    let n = usize::from(u16::from_le_bytes([bytes[dir + 6], bytes[dir + 7]]));
    let key = (0..n)
        .map(|k| dir + 8 + 8 * k)
        .find(|&at| u16::from_le_bytes([bytes[at], bytes[at + 1]]) == id)
        .unwrap_or_else(|| panic!("no key {id}"));
    assert_eq!(
        u16::from_le_bytes([bytes[key + 2], bytes[key + 3]]),
        0,
        "key {id} is stored in the key itself"
    );
    let old = u16::from_le_bytes([bytes[key + 6], bytes[key + 7]]);
    bytes[key + 6..key + 8].copy_from_slice(&value.to_le_bytes());
    old
}

/// Copies `file` and its companion (same stem, extension `companion`) into `dir`, patching
/// the GeoKeys of the copy of `file` with `keys` (id, value).
fn patched_copy(dir: &Path, file: &Path, companion: &str, keys: &[(u16, u16)]) -> PathBuf {
    let copy = dir.join(file.file_name().unwrap());
    std::fs::copy(
        file.with_extension(companion),
        copy.with_extension(companion),
    )
    .unwrap();
    let mut bytes = std::fs::read(file).unwrap();
    for &(id, value) in keys {
        set_key(&mut bytes, id, value);
    }
    std::fs::write(&copy, bytes).unwrap();
    copy
}

fn facts_crs(path: &Path) -> Option<String> {
    fwlidar::source::open_file(path).unwrap().facts().crs
}

#[test]
fn geocentric_las_is_epsg_4978() {
    let las = fixture("waveform/riegl_q680i/100429_152240_2535pt_UTM.las");
    // As shipped: a projected model with a user-defined projection, so the WKT decides.
    let mut bytes = std::fs::read(&las).unwrap();
    assert_eq!(set_key(&mut bytes, 1024, 1), 1, "projected model");
    assert_eq!(
        set_key(&mut bytes, 3072, 32767),
        32767,
        "user-defined projection"
    );
    assert_eq!(
        set_key(&mut bytes, 2048, 32767),
        32767,
        "user-defined datum"
    );
    assert!(
        facts_crs(&las)
            .unwrap()
            .starts_with("PROJCS[\"UTM_North zone 33\"")
    );

    let dir = tempfile::tempdir().unwrap();
    // Geocentric model, no projected code: EPSG:4978 (a GeoKeys code comes before the WKT
    // unless global encoding bit 4 says otherwise; docs/formats.md).
    let copy = patched_copy(dir.path(), &las, "wdp", &[(1024, 3), (3072, 0)]);
    assert_eq!(facts_crs(&copy).as_deref(), Some("EPSG:4978"));
    // The copy still reads: every pulse, as the original.
    let o = fwlidar(&["inspect", "--json", copy.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["pulses"], 2376);

    // ETRS89 named as the datum: its geocentric CRS.
    let etrs = tempfile::tempdir().unwrap();
    let copy = patched_copy(
        etrs.path(),
        &las,
        "wdp",
        &[(1024, 3), (3072, 0), (2048, 4258)],
    );
    assert_eq!(facts_crs(&copy).as_deref(), Some("EPSG:4936"));

    // A projected code says more than the model type.
    let utm = tempfile::tempdir().unwrap();
    let copy = patched_copy(utm.path(), &las, "wdp", &[(1024, 3), (3072, 32633)]);
    assert_eq!(facts_crs(&copy).as_deref(), Some("EPSG:32633"));
}

#[test]
fn geocentric_pulsewaves_is_epsg_4978() {
    // LVIS: a geographic model on WGS 84 (1024 = 2, 2048 = 4326).
    let pls = fixture("waveform/pulsewaves/lvis_example1.pls");
    assert_eq!(facts_crs(&pls).as_deref(), Some("EPSG:4326"));

    let dir = tempfile::tempdir().unwrap();
    let copy = patched_copy(dir.path(), &pls, "wvs", &[(1024, 3)]);
    assert_eq!(facts_crs(&copy).as_deref(), Some("EPSG:4978"));
    let o = fwlidar(&["inspect", "--json", copy.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["report"]["crs"], "EPSG:4978");
    assert_eq!(j["report"]["warnings"], serde_json::json!([]));
    assert_eq!(j["pulses"], 1000);

    // A datum whose geocentric code is not known here (NAD83): unknown, and said why.
    let nad = tempfile::tempdir().unwrap();
    let copy = patched_copy(nad.path(), &pls, "wvs", &[(1024, 3), (2048, 4269)]);
    let o = fwlidar(&["inspect", "--json", copy.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["report"]["crs"], serde_json::Value::Null);
    let warning = j["report"]["warnings"][0].as_str().unwrap();
    assert!(
        warning.contains("geocentric") && warning.contains("EPSG:4269"),
        "{warning}"
    );
}
