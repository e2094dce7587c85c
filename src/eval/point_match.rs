//! Our returns against another processor's points of the same pulses (`fwlidar compare`): the
//! way to check a survey against the instrument maker's product.
//!
//! Points are read with the `las` crate (any LAS 1.0-1.4 point format, plain or LAZ) and
//! grouped into pulses by their GPS time: points within [`CompareOptions::time_tolerance_s`] of
//! each other are one pulse (every return of a pulse carries the pulse's time in both files).
//! Within a pulse, pairs of one reference point and one of ours closer than
//! [`CompareOptions::within_m`] in 3D are matched closest first, each point at most once.
//!
//! Figures ([`Comparison`]): the share of the reference's points matched ("found"), the share
//! of ours matched ("are reference echoes"), returns per pulse of each over the pulses both
//! files hold, the signed offset of each matched pair along z (ours − reference: negative is
//! below, i.e. further along a down-looking beam) by the reference's return number, and how
//! our intensity ranks the matched echoes against the reference's amplitude (its `Amplitude`
//! extra byte when it has one, else its intensity): Spearman's rank correlation. Our
//! intensities at 65 535 are counted (clipped).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

/// Settings of a comparison.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CompareOptions {
    /// Largest 3D distance of a match, m.
    pub within_m: f64,
    /// Points whose GPS times differ by at most this are one pulse, s.
    pub time_tolerance_s: f64,
}

impl Default for CompareOptions {
    fn default() -> Self {
        CompareOptions {
            within_m: 0.15,
            time_tolerance_s: 1e-6,
        }
    }
}

/// The points of one LAS file that the comparison reads.
#[derive(Clone, Debug, Default)]
pub struct PointSet {
    /// The file.
    pub file: String,
    /// Per point: GPS time (s), position (m), return number, intensity.
    pub gps_time: Vec<f64>,
    /// Positions, m (the file's CRS).
    pub xyz: Vec<[f64; 3]>,
    /// Return numbers (1-based).
    pub return_number: Vec<u8>,
    /// Intensities.
    pub intensity: Vec<u16>,
    /// Extra-byte values by name (scaled as the file's extra-bytes record says).
    pub extra: BTreeMap<String, Vec<f64>>,
}

/// Reads every point of a LAS or LAZ file; errors name the file.
pub fn read_points(path: &Path) -> Result<PointSet, String> {
    let name = path.display().to_string();
    let mut reader = las::Reader::from_path(path).map_err(|e| format!("{name}: {e}"))?;
    let dims = extra_dims(reader.header());
    let data = reader.read_all().map_err(|e| format!("{name}: {e}"))?;
    let mut set = PointSet {
        file: name.clone(),
        ..PointSet::default()
    };
    for d in &dims {
        set.extra
            .insert(d.name.clone(), Vec::with_capacity(data.len()));
    }
    for p in data.points() {
        let p = p.map_err(|e| format!("{name}: {e}"))?;
        let t = p
            .gps_time
            .ok_or_else(|| format!("{name}: the points carry no GPS time (point format 0 or 2)"))?;
        set.gps_time.push(t);
        set.xyz.push([p.x, p.y, p.z]);
        set.return_number.push(p.return_number);
        set.intensity.push(p.intensity);
        for d in &dims {
            let v = d.value(&p.extra_bytes);
            if let Some(col) = set.extra.get_mut(&d.name) {
                col.push(v);
            }
        }
    }
    Ok(set)
}

/// One extra-bytes dimension of a LAS file (the `LASF_Spec` record 4).
struct ExtraDim {
    name: String,
    offset: usize,
    data_type: u8,
    scale: f64,
    add: f64,
}

impl ExtraDim {
    fn value(&self, b: &[u8]) -> f64 {
        let at = |n: usize| b.get(self.offset..self.offset + n);
        let raw = match self.data_type {
            1 => at(1).map(|x| f64::from(x[0])),
            2 => at(1).map(|x| f64::from(x[0] as i8)),
            3 => at(2).map(|x| f64::from(u16::from_le_bytes([x[0], x[1]]))),
            4 => at(2).map(|x| f64::from(i16::from_le_bytes([x[0], x[1]]))),
            5 => at(4).map(|x| f64::from(u32::from_le_bytes([x[0], x[1], x[2], x[3]]))),
            6 => at(4).map(|x| f64::from(i32::from_le_bytes([x[0], x[1], x[2], x[3]]))),
            9 => at(4).map(|x| f64::from(f32::from_le_bytes([x[0], x[1], x[2], x[3]]))),
            10 => at(8)
                .and_then(|x| x.try_into().ok())
                .map(f64::from_le_bytes),
            7 => at(8)
                .and_then(|x| x.try_into().ok())
                .map(|x| u64::from_le_bytes(x) as f64),
            8 => at(8)
                .and_then(|x| x.try_into().ok())
                .map(|x| i64::from_le_bytes(x) as f64),
            _ => None,
        };
        raw.map_or(f64::NAN, |v| v * self.scale + self.add)
    }
}

/// Size in bytes of an extra-bytes data type (0: undocumented, its size in `options`).
fn type_size(data_type: u8, options: u8) -> usize {
    match data_type {
        0 => usize::from(options),
        1 | 2 => 1,
        3 | 4 => 2,
        5 | 6 | 9 => 4,
        7 | 8 | 10 => 8,
        // Deprecated two- and three-element types.
        11..=20 => [2, 2, 4, 4, 8, 8, 16, 16, 8, 16][usize::from(data_type - 11)],
        21..=30 => [3, 3, 6, 6, 12, 12, 24, 24, 12, 24][usize::from(data_type - 21)],
        _ => 0,
    }
}

/// The extra-bytes dimensions the header describes, with their offsets.
fn extra_dims(h: &las::Header) -> Vec<ExtraDim> {
    let mut out = Vec::new();
    for v in h.vlrs().iter().chain(h.evlrs()) {
        if v.user_id.trim_end_matches('\0') != "LASF_Spec" || v.record_id != 4 {
            continue;
        }
        let mut offset = 0;
        for rec in v.data.chunks_exact(192) {
            let (data_type, options) = (rec[2], rec[3]);
            let name = String::from_utf8_lossy(&rec[4..36])
                .trim_end_matches('\0')
                .to_string();
            let f = |at: usize| f64::from_le_bytes(rec[at..at + 8].try_into().unwrap_or([0; 8]));
            let scale = if options & 0x08 != 0 { f(112) } else { 1.0 };
            let add = if options & 0x10 != 0 { f(136) } else { 0.0 };
            out.push(ExtraDim {
                name,
                offset,
                data_type,
                scale: if scale == 0.0 { 1.0 } else { scale },
                add,
            });
            offset += type_size(data_type, options);
        }
    }
    out
}

/// Matched figures per return number of the reference.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ByReturn {
    /// Reference points of this return number.
    pub reference: u64,
    /// Of those, matched.
    pub found: u64,
    /// Median z offset of the matched pairs (ours − reference), m.
    pub median_offset_m: f64,
    /// Median absolute z offset, m.
    pub median_abs_offset_m: f64,
}

/// What `fwlidar compare` measures (module doc).
#[derive(Clone, Debug, Default, Serialize)]
pub struct Comparison {
    /// Our file.
    pub ours_file: String,
    /// The reference file.
    pub reference_file: String,
    /// Largest distance of a match, m.
    pub within_m: f64,
    /// Pulses in both files (by GPS time).
    pub pulses_in_both: u64,
    /// Reference points of those pulses.
    pub reference_points: u64,
    /// Our points of those pulses.
    pub our_points: u64,
    /// Pulses only the reference holds, and only ours.
    pub pulses_only_reference: u64,
    /// Pulses only our file holds.
    pub pulses_only_ours: u64,
    /// Matched pairs.
    pub matched: u64,
    /// Share of the reference's points matched.
    pub reference_found: f64,
    /// Share of our points that match a reference point.
    pub ours_are_reference: f64,
    /// Our returns per pulse over the reference's, over the pulses in both.
    pub returns_ratio: f64,
    /// By the reference's return number (1, 2, 3, ...).
    pub by_return: BTreeMap<u8, ByReturn>,
    /// Median absolute 3D distance of the matched pairs, m.
    pub median_distance_m: f64,
    /// Spearman's rank correlation of our intensity with the reference's amplitude over the
    /// matched pairs.
    pub intensity_rank_correlation: f64,
    /// What the reference's amplitude was (`Amplitude` extra byte, or `intensity`).
    pub reference_amplitude: String,
    /// Our points with intensity 65 535 (clipped).
    pub our_intensity_clipped: u64,
    /// Signed z offsets of the matched pairs, m (for the figure).
    #[serde(skip)]
    pub offsets_m: Vec<f64>,
    /// Matched (our intensity, reference amplitude) pairs (for the figure).
    #[serde(skip)]
    pub intensity_pairs: Vec<(f64, f64)>,
}

/// Groups point indices into pulses by GPS time: runs of sorted times within `tol` of the
/// run's first.
fn pulses(t: &[f64], tol: f64) -> Vec<(f64, Vec<usize>)> {
    let mut order: Vec<usize> = (0..t.len()).collect();
    order.sort_by(|&a, &b| t[a].total_cmp(&t[b]));
    let mut out: Vec<(f64, Vec<usize>)> = Vec::new();
    for i in order {
        match out.last_mut() {
            Some((t0, v)) if t[i] - *t0 <= tol => v.push(i),
            _ => out.push((t[i], vec![i])),
        }
    }
    out
}

/// Compares `ours` with `reference` (module doc).
pub fn compare(ours: &PointSet, reference: &PointSet, o: &CompareOptions) -> Comparison {
    let ours_p = pulses(&ours.gps_time, o.time_tolerance_s);
    let ref_p = pulses(&reference.gps_time, o.time_tolerance_s);
    let (amp_name, ref_amp): (String, Vec<f64>) = match reference.extra.get("Amplitude") {
        Some(a) => ("Amplitude extra byte".into(), a.clone()),
        None => (
            "intensity".into(),
            reference.intensity.iter().map(|&v| f64::from(v)).collect(),
        ),
    };
    let mut c = Comparison {
        ours_file: ours.file.clone(),
        reference_file: reference.file.clone(),
        within_m: o.within_m,
        reference_amplitude: amp_name,
        our_intensity_clipped: ours.intensity.iter().filter(|&&v| v == u16::MAX).count() as u64,
        ..Comparison::default()
    };
    let (mut i, mut j) = (0, 0);
    let mut distances = Vec::new();
    let mut by: BTreeMap<u8, Vec<f64>> = BTreeMap::new();
    while i < ours_p.len() && j < ref_p.len() {
        let (to, ro) = (ours_p[i].0, ref_p[j].0);
        if (to - ro).abs() <= o.time_tolerance_s {
            c.pulses_in_both += 1;
            c.our_points += ours_p[i].1.len() as u64;
            c.reference_points += ref_p[j].1.len() as u64;
            match_pulse(
                ours,
                reference,
                &ours_p[i].1,
                &ref_p[j].1,
                o,
                &mut |a, b, d| {
                    distances.push(d);
                    c.matched += 1;
                    c.offsets_m.push(ours.xyz[a][2] - reference.xyz[b][2]);
                    c.intensity_pairs
                        .push((f64::from(ours.intensity[a]), ref_amp[b]));
                    let rn = reference.return_number[b];
                    c.by_return.entry(rn).or_default().found += 1;
                    by.entry(rn)
                        .or_default()
                        .push(ours.xyz[a][2] - reference.xyz[b][2]);
                },
            );
            for &b in &ref_p[j].1 {
                c.by_return
                    .entry(reference.return_number[b])
                    .or_default()
                    .reference += 1;
            }
            i += 1;
            j += 1;
        } else if to < ro {
            c.pulses_only_ours += 1;
            i += 1;
        } else {
            c.pulses_only_reference += 1;
            j += 1;
        }
    }
    c.pulses_only_ours += (ours_p.len() - i) as u64;
    c.pulses_only_reference += (ref_p.len() - j) as u64;
    let share = |a: u64, b: u64| if b > 0 { a as f64 / b as f64 } else { f64::NAN };
    c.reference_found = share(c.matched, c.reference_points);
    c.ours_are_reference = share(c.matched, c.our_points);
    c.returns_ratio = share(c.our_points, c.reference_points);
    c.median_distance_m = median(&mut distances);
    for (rn, e) in c.by_return.iter_mut() {
        let mut v = by.remove(rn).unwrap_or_default();
        e.median_offset_m = median(&mut v);
        let mut a: Vec<f64> = v.iter().map(|x| x.abs()).collect();
        e.median_abs_offset_m = median(&mut a);
    }
    c.intensity_rank_correlation = spearman(&c.intensity_pairs);
    c
}

/// Matches the points of one pulse, closest pairs first, each point once; `on_match(ours
/// index, reference index, distance)`.
fn match_pulse(
    ours: &PointSet,
    reference: &PointSet,
    a: &[usize],
    b: &[usize],
    o: &CompareOptions,
    on_match: &mut dyn FnMut(usize, usize, f64),
) {
    let mut pairs = Vec::new();
    for &i in a {
        for &j in b {
            let d = dist(ours.xyz[i], reference.xyz[j]);
            if d <= o.within_m {
                pairs.push((d, i, j));
            }
        }
    }
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let (mut used_a, mut used_b) = (Vec::new(), Vec::new());
    for (d, i, j) in pairs {
        if used_a.contains(&i) || used_b.contains(&j) {
            continue;
        }
        used_a.push(i);
        used_b.push(j);
        on_match(i, j, d);
    }
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Ranks of `v` (average ranks for ties), 1-based.
fn ranks(v: &[f64]) -> Vec<f64> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
    let mut r = vec![0.0; v.len()];
    let mut k = 0;
    while k < idx.len() {
        let mut e = k;
        while e + 1 < idx.len() && v[idx[e + 1]] == v[idx[k]] {
            e += 1;
        }
        let avg = (k + e) as f64 / 2.0 + 1.0;
        for &i in &idx[k..=e] {
            r[i] = avg;
        }
        k = e + 1;
    }
    r
}

/// Spearman's rank correlation of the pairs (NaN with fewer than 3).
pub fn spearman(pairs: &[(f64, f64)]) -> f64 {
    if pairs.len() < 3 {
        return f64::NAN;
    }
    let a: Vec<f64> = pairs.iter().map(|p| p.0).collect();
    let b: Vec<f64> = pairs.iter().map(|p| p.1).collect();
    let (ra, rb) = (ranks(&a), ranks(&b));
    let n = ra.len() as f64;
    let (ma, mb) = (ra.iter().sum::<f64>() / n, rb.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    sab / (saa * sbb).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(points: &[(f64, [f64; 3], u8, u16)]) -> PointSet {
        PointSet {
            file: "x".into(),
            gps_time: points.iter().map(|p| p.0).collect(),
            xyz: points.iter().map(|p| p.1).collect(),
            return_number: points.iter().map(|p| p.2).collect(),
            intensity: points.iter().map(|p| p.3).collect(),
            extra: BTreeMap::new(),
        }
    }

    #[test]
    fn points_match_within_their_pulse_closest_first() {
        let reference = set(&[
            (1.0, [0.0, 0.0, 10.0], 1, 300),
            (1.0, [0.0, 0.0, 5.0], 2, 200),
            (2.0, [0.0, 0.0, 7.0], 1, 100),
            (3.0, [0.0, 0.0, 7.0], 1, 50),
        ]);
        let ours = set(&[
            (1.0, [0.0, 0.0, 10.05], 1, 900),
            (1.0, [0.0, 0.0, 9.95], 2, 800),
            (1.0, [0.0, 0.0, 5.1], 3, 500),
            (2.0, [0.0, 0.0, 7.5], 1, 10),
            (4.0, [0.0, 0.0, 7.0], 1, 1),
        ]);
        let c = compare(&ours, &reference, &CompareOptions::default());
        assert_eq!(c.pulses_in_both, 2);
        assert_eq!((c.reference_points, c.our_points), (3, 4));
        assert_eq!(c.matched, 2);
        assert_eq!((c.pulses_only_reference, c.pulses_only_ours), (1, 1));
        assert!((c.reference_found - 2.0 / 3.0).abs() < 1e-12);
        assert!((c.ours_are_reference - 0.5).abs() < 1e-12);
        assert_eq!(c.by_return[&1].found, 1);
        assert_eq!(c.by_return[&2].found, 1);
        assert_eq!(c.by_return[&1].reference, 2);
    }

    #[test]
    fn spearman_of_monotonic_pairs_is_one() {
        let p: Vec<(f64, f64)> = (0..10).map(|i| (i as f64, (i as f64).exp())).collect();
        assert!((spearman(&p) - 1.0).abs() < 1e-12);
        let q: Vec<(f64, f64)> = (0..10).map(|i| (i as f64, -(i as f64))).collect();
        assert!((spearman(&q) + 1.0).abs() < 1e-12);
    }
}
