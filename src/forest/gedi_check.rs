//! Our metrics of GEDI Level 1B waveforms against NASA's own Level 2A (RH) and 2B (cover, PAI,
//! FHD) products of the same shots: the check `docs/accuracy.md` reports ("GEDI").
//!
//! Each shot's received waveform is measured from GEDI's raw counts with GEDI's noise mean and
//! σ (`noise_mean_corrected`, `noise_stddev_corrected`) and the geolocation of bin 0 and the
//! last bin, under [`MetricsConfig::default`] with the smoothing of GEDI's algorithm setting
//! group 1 (6.5 ns), the group the products selected for every shot of the fixture.

use std::path::Path;

use hdf5_reader::Hdf5File;

use crate::forest::pulse_metrics::{MetricsComputer, MetricsConfig, WaveformInput};
use crate::format::gedi::{GediError, GediL1b};
use crate::pulse::PulseGeometry;
use crate::pulse::waveform_metrics::WaveformMetrics;

/// One shot: ours and GEDI's.
#[derive(Clone, Debug)]
pub struct ShotComparison {
    /// Beam group name.
    pub beam: String,
    /// GEDI shot number.
    pub shot_number: u64,
    /// Our metrics.
    pub ours: WaveformMetrics,
    /// L2A `rh` (m), 101 values.
    pub l2a_rh: Vec<f64>,
    /// L2A `selected_algorithm`.
    pub l2a_algorithm: u8,
    /// L2B `cover`, `pai`, `fhd_normal`.
    pub l2b_cover: f64,
    /// L2B `pai`.
    pub l2b_pai: f64,
    /// L2B `fhd_normal`.
    pub l2b_fhd: f64,
}

/// Reads a dataset of any numeric type as f64 (an n-D one flattened, rows first).
pub fn read_f64(file: &Hdf5File, name: &str, path: &str) -> Result<Vec<f64>, GediError> {
    let err = |reason: String| GediError::Dataset {
        file: path.to_string(),
        dataset: name.to_string(),
        reason,
    };
    let ds = file.dataset(name).map_err(|e| err(e.to_string()))?;
    if let Ok(a) = ds.read_array::<f64>() {
        return Ok(a.iter().copied().collect());
    }
    if let Ok(a) = ds.read_array::<f32>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    if let Ok(a) = ds.read_array::<u64>() {
        return Ok(a.iter().map(|&v| v as f64).collect());
    }
    if let Ok(a) = ds.read_array::<u8>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    if let Ok(a) = ds.read_array::<i32>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    if let Ok(a) = ds.read_array::<u16>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    if let Ok(a) = ds.read_array::<u32>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    if let Ok(a) = ds.read_array::<i16>() {
        return Ok(a.iter().map(|&v| f64::from(v)).collect());
    }
    Err(err("not a float, integer or u64 dataset".into()))
}

/// Measures every shot of `l1b` and pairs it with the L2A and L2B values of the same shot
/// number. Shots missing from either product are left out.
pub fn compare(
    l1b: &Path,
    l2a: &Path,
    l2b: &Path,
    config: &MetricsConfig,
    smoothing_ns: f64,
) -> Result<Vec<ShotComparison>, GediError> {
    let open = |p: &Path| {
        Hdf5File::open(p).map_err(|e| GediError::Open {
            file: p.display().to_string(),
            reason: e.to_string(),
        })
    };
    let g = GediL1b::open(l1b)?;
    let fa = open(l2a)?;
    let fb = open(l2b)?;
    let (pa, pb) = (l2a.display().to_string(), l2b.display().to_string());
    let mut out = Vec::new();
    let mut computer = MetricsComputer::with_capacity(2048);
    for name in g.beams() {
        let beam = g.read_beam(name)?;
        let (mut rx, mut tx) = (Vec::new(), Vec::new());
        g.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx)?;
        let a_shots = read_f64(&fa, &format!("{name}/shot_number"), &pa)?;
        let rh = read_f64(&fa, &format!("{name}/rh"), &pa)?;
        let alg = read_f64(&fa, &format!("{name}/selected_algorithm"), &pa)?;
        let b_shots = read_f64(&fb, &format!("{name}/shot_number"), &pb)?;
        let cover = read_f64(&fb, &format!("{name}/cover"), &pb)?;
        let pai = read_f64(&fb, &format!("{name}/pai"), &pb)?;
        let fhd = read_f64(&fb, &format!("{name}/fhd_normal"), &pb)?;
        let base = beam.shots.first().map(|s| s.rx_start).unwrap_or(0);
        for s in &beam.shots {
            // Shot numbers exceed f64's integers only beyond 2^53; GEDI's are ~2·10^16: compare
            // through the same rounding on both sides.
            let key = s.shot_number as f64;
            let Some(ia) = a_shots.iter().position(|&v| v == key) else {
                continue;
            };
            let Some(ib) = b_shots.iter().position(|&v| v == key) else {
                continue;
            };
            let off = (s.rx_start - base) as usize;
            let samples = &rx[off..off + s.rx_count as usize];
            let n = f64::from(s.rx_count.max(2) - 1);
            // Vertical geometry only (metres of elevation per ns): heights need no projection.
            let geometry = PulseGeometry {
                anchor: [s.bin0[0], s.bin0[1], s.bin0[2]],
                direction: [
                    (s.lastbin[0] - s.bin0[0]) / n,
                    (s.lastbin[1] - s.bin0[1]) / n,
                    (s.lastbin[2] - s.bin0[2]) / n,
                ],
            };
            let ours = computer.compute(
                config,
                &WaveformInput {
                    pulse_sigma_ns: 0.0,
                    samples,
                    start_ns: 0.0,
                    sample_ns: 1.0,
                    noise_mean: s.noise_mean,
                    noise_sd: s.noise_stddev,
                    smoothing_ns,
                    geometry: Some(geometry),
                    geographic: true,
                },
            );
            out.push(ShotComparison {
                beam: name.clone(),
                shot_number: s.shot_number,
                ours,
                l2a_rh: rh[ia * 101..ia * 101 + 101].to_vec(),
                l2a_algorithm: alg[ia] as u8,
                l2b_cover: cover[ib],
                l2b_pai: pai[ib],
                l2b_fhd: fhd[ib],
            });
        }
    }
    Ok(out)
}

/// Median and largest absolute difference of `f(shot)` over the shots.
pub fn median_and_worst(rows: &[ShotComparison], f: impl Fn(&ShotComparison) -> f64) -> (f64, f64) {
    let mut d: Vec<f64> = rows
        .iter()
        .map(|r| f(r).abs())
        .filter(|v| v.is_finite())
        .collect();
    if d.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    d.sort_by(f64::total_cmp);
    let m = d.len();
    let med = if m % 2 == 1 {
        d[m / 2]
    } else {
        0.5 * (d[m / 2 - 1] + d[m / 2])
    };
    (med, d[m - 1])
}

/// The markdown summary table of a comparison (docs/accuracy.md, "GEDI").
pub fn summary_markdown(rows: &[ShotComparison]) -> String {
    let mut s = String::from(
        "| metric | shots | median \\|ours − GEDI\\| | worst | median bias (ours − GEDI) |\n|---|---|---|---|---|\n",
    );
    let bias = |f: &dyn Fn(&ShotComparison) -> f64| -> f64 {
        let mut d: Vec<f64> = rows.iter().map(f).filter(|v| v.is_finite()).collect();
        d.sort_by(f64::total_cmp);
        if d.is_empty() {
            f64::NAN
        } else {
            d[d.len() / 2]
        }
    };
    for p in [25usize, 50, 75, 98, 100] {
        let f = move |r: &ShotComparison| f64::from(r.ours.rh[p]) - r.l2a_rh[p];
        let (m, w) = median_and_worst(rows, f);
        s.push_str(&format!(
            "| RH{p} (m) | {} | {m:.2} | {w:.2} | {:+.2} |\n",
            rows.len(),
            bias(&f)
        ));
    }
    let fc = |r: &ShotComparison| f64::from(r.ours.cover) - r.l2b_cover;
    let fp = |r: &ShotComparison| f64::from(r.ours.pai) - r.l2b_pai;
    let ff = |r: &ShotComparison| f64::from(r.ours.fhd) - r.l2b_fhd;
    for (name, f) in [
        ("cover", &fc as &dyn Fn(&ShotComparison) -> f64),
        ("PAI", &fp),
        ("FHD", &ff),
    ] {
        let (m, w) = median_and_worst(rows, f);
        s.push_str(&format!(
            "| {name} | {} | {m:.3} | {w:.3} | {:+.3} |\n",
            rows.len(),
            bias(f)
        ));
    }
    s
}
