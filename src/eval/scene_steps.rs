//! The seed's stepwise evaluation on a described scene (`fwlidar tradeoff --scene`): the same
//! simulated pulses scored against their truth after each processing step — raw, denoise, each
//! deconvolution method, and voxelised — with the seed's metrics ([`crate::eval::accuracy`]) and
//! the time per pulse of the step.
//!
//! Units: the received return segment in counts above the scene's baseline (the digitizer's
//! counts over its steps per count, minus `baseline_dn`); the truth is the scene's 2 ns
//! cross-section in the same counts (area preserving). Deconvolved outputs are cross-section
//! estimates; `rmse_2ns` sees them through the truth's 2 ns pulse (as the sweep does).
//!
//! The georeference step writes the simulated stream as a capture and georeferences it as a
//! replay does (navigation decoded, trajectory, lever arm, boresight, scan angles, UTM), scores
//! every surface echo's position against the truth, and times the georeference per pulse (the
//! replay of the capture with it, minus without). The voxel step then deposits the deconvolved
//! waveforms where the georeference put them and the truth where it is, in the same map grid.

use std::time::Instant;

use crate::eval::accuracy::{
    PeakMatch, RmseAccumulator, local_peaks, match_peaks, spectral_angle_deg,
};
use crate::eval::tradeoff::percentile;
use crate::format::{CaptureHeader, CaptureWriter, FlushPolicy};
use crate::geo::crs::OutputCrs;
use crate::pipeline::ports::SourceEvent;
use crate::pulse::{Pulse, PulseGeometry, SegmentKind};
use crate::signal::deconvolve::{
    Deconvolver, Gate, Gated, GoldConfig, MethodConfig, NnlsConfig, NnlsOrRlConfig, RlConfig,
    WienerConfig, choice,
};
use crate::signal::denoise::{Denoise, DenoiseConfig};
use crate::signal::kernel::{Kernel, convolve_same, remove_baseline};
use crate::sim::SimItem;
use crate::sim::truth::gaussian_pulse;
use crate::sim::world::flight::Frames;
use crate::sim::world::scene::Origin;
use crate::sim::world::{ShotTruth, WorldItems};
use crate::source::georeferencing::{GeoreferenceConfig, GeoreferencingSource};
use crate::voxel::grid::{Grid, Placer, VoxelConfig};
use crate::voxel::tiles::TileSet;
use crate::voxel::voxelise::{DepositParams, DepositStats, deposit_pulse};
use crate::voxel::zarr::{StoreInfo, ZarrStore};

/// One step's scores over the scene's pulses.
#[derive(Clone, Debug, PartialEq)]
pub struct StepResult {
    /// The step, e.g. `denoise`, `rl iterations=20`, `voxelise (rl 20)`.
    pub step: String,
    /// Pulses (waveform steps) or columns (the voxel step) scored.
    pub scored: usize,
    /// Pooled eq. 14 RMSE, fraction of the truth's peak.
    pub rmse: f64,
    /// RMSE through the truth's 2 ns pulse (deconvolved outputs), fraction of the truth's peak.
    pub rmse_2ns: f64,
    /// True detections / truth peaks.
    pub detection_rate: f64,
    /// False detections per waveform (or column).
    pub false_per_pulse: f64,
    /// Mean spectral angle, degrees.
    pub sam_deg: f64,
    /// Median time per pulse of the step alone, ns.
    pub median_ns: f64,
    /// 99th percentile, ns.
    pub p99_ns: f64,
    /// Georeference step: RMS of the 3D position error of every surface echo, metres (NaN for
    /// the other steps).
    pub position_rms_m: f64,
    /// Georeference step: largest position error, metres.
    pub position_max_m: f64,
}

/// Why the evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum StepsError {
    /// A step refused a simulated pulse, or the voxel store failed.
    #[error("{step}: {message}")]
    Step {
        /// The step.
        step: String,
        /// What went wrong.
        message: String,
    },
}

fn err(step: &str, e: impl std::fmt::Display) -> StepsError {
    StepsError::Step {
        step: step.to_string(),
        message: e.to_string(),
    }
}

/// One simulated pulse as the steps see it.
struct Shot {
    /// The pulse's id in the capture.
    id: u64,
    /// Ranges (m) and scene-frame positions of the surfaces the beam met.
    surfaces: Vec<(f64, [f64; 3])>,
    received: Vec<f32>,
    outgoing: Vec<f32>,
    truth: Vec<f32>,
    geometry: PulseGeometry,
    start_ns: f64,
}

/// Scores `pulses` pulses of `sim` after every step. `peak_floor`, `tolerance_bins`: as the
/// sweep's. Voxels go to a temporary store under `scratch_dir`.
pub fn run_scene_steps(
    mut items: WorldItems,
    pulses: usize,
    peak_floor: f32,
    tolerance_bins: usize,
    scratch_dir: &std::path::Path,
) -> Result<Vec<StepResult>, StepsError> {
    let mpn = items.sim().metres_per_ns();
    // The stream is also written as a capture, for the georeference step.
    let capture = scratch_dir.join("scene.fwcap");
    let (shots, sample_ns) = collect_shots(&mut items, pulses, &capture)?;
    if shots.is_empty() {
        return Err(err("scene", "the scene has no pulses"));
    }
    let origin = items.sim().scene().origin.clone();
    let bins = shots.iter().map(|s| s.received.len()).max().unwrap_or(0);
    let taps = shots.iter().map(|s| s.outgoing.len()).max().unwrap_or(1);
    let truth_kernel = gaussian_pulse(2.0, sample_ns).map_err(|e| err("truth kernel", e))?;
    let mut truth_peaks: Vec<Vec<usize>> = Vec::with_capacity(shots.len());
    for s in &shots {
        let mut v = Vec::new();
        local_peaks(&s.truth, peak_floor, &mut v);
        truth_peaks.push(v);
    }
    let mut results = Vec::new();
    let mut rl_outputs: Vec<Vec<f32>> = Vec::new();
    let mut work = StepWork {
        shots: &shots,
        truth_peaks: &truth_peaks,
        truth_kernel: &truth_kernel,
        sample_ns,
        peak_floor,
        tolerance_bins,
        bins,
        taps,
        kernel: Kernel::with_capacity(taps),
        denoised: vec![0.0f32; bins],
        output: vec![0.0f32; bins],
        reblurred: vec![0.0f32; bins],
        detected: Vec::with_capacity(bins),
    };
    for (si, (name, method)) in step_methods().iter().enumerate() {
        // The RL step's outputs (seen through the 2 ns pulse) feed the voxel step.
        let keep = (si == 2).then_some(&mut rl_outputs);
        results.push(work.score_step(name, si == 0, method.as_ref(), keep)?);
    }
    let placed = georeference_step(&origin, mpn, &shots, &results[2], &capture)?;
    let georef = placed.result;
    results.push(georef);
    results.push(voxel_step(
        &shots,
        &placed.map_geometry,
        &placed.true_map_geometry,
        &rl_outputs,
        sample_ns,
        peak_floor,
        tolerance_bins,
        scratch_dir,
    )?);
    Ok(results)
}

/// Takes the first `pulses` pulses of `items` (and the navigation that brackets them), writes
/// the stream to `capture`, and returns the shots with a return and an outgoing segment, and
/// the sample interval (ns) of the last pulse.
fn collect_shots(
    items: &mut WorldItems,
    pulses: usize,
    capture: &std::path::Path,
) -> Result<(Vec<Shot>, f64), StepsError> {
    let baseline = items.sim().scene().sensor.baseline_dn as f32;
    let mpn = items.sim().metres_per_ns();
    let sensor = items.sim().sensor().clone();
    let header = CaptureHeader::simulated(&sensor, None, "simulated");
    let mut writer = CaptureWriter::create(capture, &header.to_text(), FlushPolicy::default())
        .map_err(|e| err("capture", e))?;
    let mut shots: Vec<Shot> = Vec::with_capacity(pulses);
    let mut sample_ns = 1.0;
    let mut last_time = f64::NEG_INFINITY;
    while let Some(item) = items.next() {
        let p = match item {
            SimItem::Nav {
                receive_time_ns,
                bytes,
            } => {
                writer
                    .write_nav(0, receive_time_ns, &bytes)
                    .map_err(|e| err("capture", e))?;
                // Once the pulses are in, one epoch at or after the last brackets them all.
                if shots.len() >= pulses && receive_time_ns as f64 * 1e-9 >= last_time {
                    break;
                }
                continue;
            }
            SimItem::Pulse(p) => p,
        };
        if shots.len() >= pulses {
            continue;
        }
        last_time = p.gps_time;
        writer.write_pulse(&p).map_err(|e| err("capture", e))?;
        sample_ns = p.sample_ns;
        let steps_per_count = sensor.digitizer_gain_v_per_dn / p.gain_v_per_dn as f64;
        if let Some(shot) = shot_of(&p, items.last_truth(), steps_per_count, baseline, mpn) {
            shots.push(shot);
        }
    }
    writer.finish().map_err(|e| err("capture", e))?;
    Ok((shots, sample_ns))
}

/// Pulse `p` (truth `t`) as the steps see it: its return and outgoing segments in counts
/// above `baseline` (digitizer steps over `steps_per_count`), its truth, the surfaces on the
/// beam's axis and its geometry (`mpn`: metres per ns); `None` without both segments.
fn shot_of(
    p: &Pulse,
    t: &ShotTruth,
    steps_per_count: f64,
    baseline: f32,
    mpn: f64,
) -> Option<Shot> {
    let counts = |seg: usize| -> Vec<f32> {
        p.raw_of(seg)
            .iter()
            .map(|&r| (r as f64 / steps_per_count) as f32 - baseline)
            .collect()
    };
    let ret = p
        .segments
        .iter()
        .position(|s| s.kind == SegmentKind::Return)?;
    let out = p
        .segments
        .iter()
        .position(|s| s.kind == SegmentKind::Outgoing)?;
    Some(Shot {
        id: p.pulse_id,
        surfaces: t
            .scatterers
            .iter()
            // Surfaces on the beam's axis (the georeference places the axis).
            .filter(|s| s.range_m == s.range_end_m && s.ray == 0)
            .map(|s| (s.range_m, s.position))
            .collect(),
        received: counts(ret),
        outgoing: counts(out),
        truth: t.truth.iter().map(|&v| v as f32).collect(),
        geometry: PulseGeometry {
            anchor: t.origin,
            direction: [t.beam[0] * mpn, t.beam[1] * mpn, t.beam[2] * mpn],
        },
        start_ns: p.segments[ret].start_ns,
    })
}

/// The waveform steps, named as the results name them: raw, denoise, then each deconvolution
/// method behind the denoise.
fn step_methods() -> Vec<(String, Option<MethodConfig>)> {
    vec![
        ("raw".into(), None),
        ("denoise".into(), None),
        (
            "rl iterations=20".into(),
            Some(MethodConfig::RichardsonLucy(RlConfig {
                iterations: 20,
                early_stop: None,
                accelerate: false,
                stop_at_noise: None,
                ..RlConfig::default()
            })),
        ),
        (
            "rl_wiener iterations=12".into(),
            Some(MethodConfig::RichardsonLucy(RlConfig::onboard())),
        ),
        (
            "gold iterations=20".into(),
            Some(MethodConfig::Gold(GoldConfig {
                iterations: 20,
                ..GoldConfig::default()
            })),
        ),
        (
            "wiener".into(),
            Some(MethodConfig::Wiener(WienerConfig::default())),
        ),
        (
            "nnls max_iterations=100".into(),
            Some(MethodConfig::Nnls(NnlsConfig::default())),
        ),
        (
            format!("nnls_or_rl threshold={}", choice::DEFAULT_THRESHOLD),
            Some(MethodConfig::NnlsOrRl(NnlsOrRlConfig::default())),
        ),
    ]
}

/// The shots, their truth and the buffers the waveform steps share.
struct StepWork<'a> {
    shots: &'a [Shot],
    /// The truth's peaks of each shot.
    truth_peaks: &'a [Vec<usize>],
    /// The truth's 2 ns pulse.
    truth_kernel: &'a Kernel,
    /// Sample interval, ns.
    sample_ns: f64,
    peak_floor: f32,
    tolerance_bins: usize,
    /// The longest return segment, samples.
    bins: usize,
    /// The longest outgoing segment, samples.
    taps: usize,
    kernel: Kernel,
    denoised: Vec<f32>,
    output: Vec<f32>,
    reblurred: Vec<f32>,
    detected: Vec<usize>,
}

impl StepWork<'_> {
    /// Runs step `name` on every shot (`raw`: the received waveform as it is; else denoised,
    /// then deconvolved by `method` when there is one) and scores its outputs against the
    /// truth, timing the step alone (ns per pulse). `keep` gets each output seen through the
    /// truth's 2 ns pulse.
    fn score_step(
        &mut self,
        name: &str,
        raw: bool,
        method: Option<&MethodConfig>,
        mut keep: Option<&mut Vec<Vec<f32>>>,
    ) -> Result<StepResult, StepsError> {
        let (bins, taps, sample_ns) = (self.bins, self.taps, self.sample_ns);
        let shots = self.shots;
        let mut denoise = Denoise::new(DenoiseConfig {
            max_samples: bins.max(16),
            ..DenoiseConfig::default()
        });
        // The deconvolve stage's own code: the method behind its default echo-window gate.
        let mut deconv: Option<Gated> =
            method.map(|m| Gated::build(m, Gate::default_for(m), bins, taps));
        let (mut rmse, mut rmse_2ns) = (RmseAccumulator::default(), RmseAccumulator::default());
        let (mut peaks, mut n_truth, mut sam) = (PeakMatch::default(), 0u64, 0.0);
        let mut times = Vec::with_capacity(shots.len());
        for (s, tp) in shots.iter().zip(self.truth_peaks) {
            let n = s.received.len();
            let out = &mut self.output[..n];
            let outgoing = remove_baseline(&s.outgoing);
            self.kernel
                .set_from_outgoing(&outgoing, taps)
                .map_err(|e| err(name, e))?;
            let t0 = Instant::now();
            if raw {
                out.copy_from_slice(&s.received);
            } else {
                let den = &mut self.denoised[..n];
                let noise = denoise
                    .denoise_segment(&s.received, sample_ns, den)
                    .map_err(|e| err(name, e))?;
                match deconv.as_mut() {
                    None => out.copy_from_slice(den),
                    Some(d) => {
                        d.run(den, &self.kernel, noise.noise_v, sample_ns, out)
                            .map_err(|e| err(name, e))?;
                    }
                }
            }
            times.push(t0.elapsed().as_secs_f64() * 1e9);
            rmse.add(&s.truth, out);
            let rb = &mut self.reblurred[..n];
            if deconv.is_some() {
                convolve_same(out, self.truth_kernel, rb);
                rmse_2ns.add(&s.truth, rb);
            } else {
                rmse_2ns.add(&s.truth, out);
            }
            sam += spectral_angle_deg(&s.truth, out);
            local_peaks(out, self.peak_floor, &mut self.detected);
            let m = match_peaks(tp, &self.detected, self.tolerance_bins);
            peaks.true_detections += m.true_detections;
            peaks.false_detections += m.false_detections;
            n_truth += tp.len() as u64;
            if let Some(k) = keep.as_mut() {
                k.push(rb.to_vec());
            }
        }
        Ok(StepResult {
            step: name.to_string(),
            scored: shots.len(),
            rmse: rmse.rmse(),
            rmse_2ns: rmse_2ns.rmse(),
            detection_rate: peaks.true_detections as f64 / n_truth.max(1) as f64,
            false_per_pulse: peaks.false_detections as f64 / shots.len() as f64,
            sam_deg: sam / shots.len() as f64,
            median_ns: percentile(&times, 0.5),
            p99_ns: percentile(&times, 0.99),
            position_rms_m: f64::NAN,
            position_max_m: f64::NAN,
        })
    }
}

/// The georeference step's outcome: its scores and both geometries of every shot in the map.
struct Placed {
    result: StepResult,
    /// Each shot's geometry from the navigation stream (replay's georeference).
    map_geometry: Vec<PulseGeometry>,
    /// Each shot's true geometry, in the same map CRS.
    true_map_geometry: Vec<PulseGeometry>,
}

/// Georeferences the capture of the scene as a replay does (navigation decoded, trajectory,
/// lever arm, boresight, scan angles, UTM of the scene's origin) and scores every surface echo's
/// position against the truth. The waveform scores are those of `after` (placing bins moves
/// them, it does not change their values).
fn georeference_step(
    origin: &Origin,
    mpn: f64,
    shots: &[Shot],
    after: &StepResult,
    capture: &std::path::Path,
) -> Result<Placed, StepsError> {
    let name = "georeference";
    let frames = Frames::new(origin.lat_deg, origin.lon_deg, origin.height_m);
    let crs = OutputCrs::utm_at(origin.lat_deg, origin.lon_deg).map_err(|e| err(name, e))?;
    let cfg = GeoreferenceConfig {
        enabled: true,
        output_epsg: Some(crs.epsg()),
        ..GeoreferenceConfig::default()
    };
    let pool = crate::pulse::PulsePool::new(64);
    // Decoding alone, then decoding and georeferencing: the difference is the step's cost.
    let pass = |georef: bool| -> Result<(Vec<Option<PulseGeometry>>, f64), StepsError> {
        let inner = crate::source::open_file(capture).map_err(|e| err(name, e))?;
        let mut source: Box<crate::source::DynSource> = if georef {
            Box::new(GeoreferencingSource::new(inner, cfg.clone()).map_err(|e| err(name, e))?)
        } else {
            inner
        };
        let index: std::collections::HashMap<u64, usize> =
            shots.iter().enumerate().map(|(k, s)| (s.id, k)).collect();
        let mut out = vec![None; shots.len()];
        let t0 = Instant::now();
        loop {
            match source.next(&pool).map_err(|e| err(name, e))? {
                SourceEvent::Pulse(p) => {
                    if let Some(&k) = index.get(&p.pulse_id) {
                        out[k] = p.geometry;
                    }
                    pool.give(p);
                }
                SourceEvent::Nav(_) | SourceEvent::Idle => {}
                SourceEvent::End => break,
            }
        }
        Ok((out, t0.elapsed().as_secs_f64() * 1e9 / shots.len() as f64))
    };
    // Alternated three times, the fastest pass of each kind (the one least disturbed by other
    // work on the machine): one pass each let a slow first read outweigh the georeference's
    // cost on a loaded machine, and the step was timed at 0.
    let (mut read_ns, mut all_ns, mut placed) = (f64::INFINITY, f64::INFINITY, Vec::new());
    for _ in 0..3 {
        read_ns = read_ns.min(pass(false)?.1);
        let (p, ns) = pass(true)?;
        all_ns = all_ns.min(ns);
        placed = p;
    }
    let to_map = |p: [f64; 3]| -> Result<[f64; 3], StepsError> {
        let g = frames.geodetic(p);
        crs.project(g.lat_deg, g.lon_deg, g.height_m)
            .map_err(|e| err(name, e))
    };
    let (mut sum_sq, mut n, mut worst) = (0.0f64, 0u64, 0.0f64);
    let mut map_geometry = Vec::with_capacity(shots.len());
    let mut true_map_geometry = Vec::with_capacity(shots.len());
    for (k, s) in shots.iter().enumerate() {
        let Some(g) = placed[k] else {
            return Err(err(name, format!("pulse {} was not georeferenced", s.id)));
        };
        for &(range, pos) in &s.surfaces {
            let t = range / mpn;
            let got = [
                g.anchor[0] + t * g.direction[0],
                g.anchor[1] + t * g.direction[1],
                g.anchor[2] + t * g.direction[2],
            ];
            let want = to_map(pos)?;
            let e2 = (0..3).map(|i| (got[i] - want[i]).powi(2)).sum::<f64>();
            sum_sq += e2;
            n += 1;
            worst = worst.max(e2.sqrt());
        }
        // The true chord through the recorded window, in the map.
        let (ta, tb) = (s.start_ns, s.start_ns + s.received.len().max(2) as f64);
        let at = |t: f64| {
            let a = s.geometry.anchor;
            let d = s.geometry.direction;
            [a[0] + t * d[0], a[1] + t * d[1], a[2] + t * d[2]]
        };
        let (pa, pb) = (to_map(at(ta))?, to_map(at(tb))?);
        let dir = [
            (pb[0] - pa[0]) / (tb - ta),
            (pb[1] - pa[1]) / (tb - ta),
            (pb[2] - pa[2]) / (tb - ta),
        ];
        true_map_geometry.push(PulseGeometry {
            anchor: [
                pa[0] - ta * dir[0],
                pa[1] - ta * dir[1],
                pa[2] - ta * dir[2],
            ],
            direction: dir,
        });
        map_geometry.push(g);
    }
    Ok(Placed {
        result: StepResult {
            step: name.into(),
            median_ns: (all_ns - read_ns).max(0.0),
            p99_ns: f64::NAN,
            position_rms_m: (sum_sq / n.max(1) as f64).sqrt(),
            position_max_m: worst,
            ..after.clone()
        },
        map_geometry,
        true_map_geometry,
    })
}

/// Voxelises the RL outputs (through the 2 ns pulse) and the truth with the real depositor and
/// compares the grids: RMSE over the voxels (fraction of the largest truth voxel), and per
/// column (its vertical profile as the waveform) the spectral angle and the peaks.
#[allow(clippy::too_many_arguments)]
fn voxel_step(
    shots: &[Shot],
    placed: &[PulseGeometry],
    truth_placed: &[PulseGeometry],
    processed: &[Vec<f32>],
    sample_ns: f64,
    peak_floor: f32,
    tolerance_bins: usize,
    scratch_dir: &std::path::Path,
) -> Result<StepResult, StepsError> {
    let name = "voxelise (rl 20 through 2 ns; georeferenced)";
    let cfg = VoxelConfig {
        enabled: true,
        z_range_m: [-5.0, 40.0],
        ..VoxelConfig::default()
    };
    let first = truth_placed[0];
    let ground_xy = [first.anchor[0], first.anchor[1]];
    let grid = Grid::new(&cfg, ground_xy);
    let info = StoreInfo {
        crs_wkt: None,
        epsg: None,
        intensity_units: "counts".into(),
        run_key: "scene-steps".into(),
        configuration: String::new(),
    };
    let params = DepositParams {
        placer: Placer::new(&grid),
        height: grid.height,
        dem: None,
        inv_quantum: 1.0 / cfg.intensity_quantum,
        footprint_divergence_rad: None,
    };
    let mut grids = Vec::new();
    let mut times = Vec::with_capacity(shots.len());
    for (which, values) in [("processed", true), ("truth", false)] {
        let dir = scratch_dir.join(format!("{which}.zarr"));
        let store = ZarrStore::create_or_open(&dir, grid.clone(), info.clone())
            .map_err(|e| err(name, e))?;
        let mut tiles = TileSet::new(store, 256, 1e12);
        let mut stats = DepositStats::default();
        let mut pulse = Pulse::default();
        for (k, s) in shots.iter().enumerate() {
            pulse.reset();
            pulse.seq = k as u64;
            pulse.gps_time = k as f64 * 1e-6;
            pulse.sample_ns = sample_ns;
            // The processed waveform where the georeference put it; the truth where it is.
            pulse.geometry = Some(if values { placed[k] } else { truth_placed[k] });
            let sig: &[f32] = if values { &processed[k] } else { &s.truth };
            let first = pulse.raw.len();
            pulse.raw.extend(std::iter::repeat_n(0u16, sig.len()));
            let seg = pulse.push_segment(SegmentKind::Return, 0, s.start_ns, []);
            pulse.segments[seg].first = first as u32;
            pulse.segments[seg].len = sig.len() as u32;
            pulse.signal.extend_from_slice(sig);
            let t0 = Instant::now();
            deposit_pulse(&pulse, &mut tiles, &params, &mut stats).map_err(|e| err(name, e))?;
            if values {
                times.push(t0.elapsed().as_secs_f64() * 1e9);
            }
        }
        tiles
            .close_all(shots.len() as u64)
            .map_err(|e| err(name, e))?;
        let mut store = tiles.into_store();
        let mut all = store.read_all().map_err(|e| err(name, e))?;
        all.sort_by_key(|(t, _)| *t);
        grids.push(all);
    }
    let (proc, truth) = (&grids[0], &grids[1]);
    let levels = grid.shape()[0] as usize;
    let q = cfg.intensity_quantum as f32;
    // RMSE over every voxel of the scored columns, as a fraction of the largest truth voxel
    // (per-column scaling would blow up on edge columns a beam barely crosses).
    let (mut sum_sq, mut n_vox, mut max_truth) = (0.0f64, 0u64, 0.0f32);
    let (mut sam, mut cols) = (0.0, 0usize);
    let (mut peaks, mut n_truth) = (PeakMatch::default(), 0u64);
    let (mut tcol, mut pcol) = (vec![0f32; levels], vec![0f32; levels]);
    let (mut tp, mut dp) = (Vec::new(), Vec::new());
    for ((tt, td), (pt, pd)) in truth.iter().zip(proc) {
        if tt != pt {
            return Err(err(name, "the two grids hold different tiles"));
        }
        let (td, pd) = (td.dense(), pd.dense());
        for c in 0..td.sum_q.len() / levels {
            let range = c * levels..(c + 1) * levels;
            if td.samples[range.clone()].iter().all(|&s| s == 0) {
                continue;
            }
            for (k, i) in range.enumerate() {
                tcol[k] = td.sum_q[i] as f32 * q;
                pcol[k] = pd.sum_q[i] as f32 * q;
            }
            if !tcol.iter().any(|&v| v > 0.0) {
                continue;
            }
            cols += 1;
            for (t, p) in tcol.iter().zip(&pcol) {
                sum_sq += ((t - p) as f64).powi(2);
                max_truth = max_truth.max(*t);
            }
            n_vox += levels as u64;
            sam += spectral_angle_deg(&tcol, &pcol);
            local_peaks(&tcol, peak_floor, &mut tp);
            local_peaks(&pcol, peak_floor, &mut dp);
            let m = match_peaks(&tp, &dp, tolerance_bins);
            peaks.true_detections += m.true_detections;
            peaks.false_detections += m.false_detections;
            n_truth += tp.len() as u64;
        }
    }
    let rmse = (sum_sq / n_vox.max(1) as f64).sqrt() / max_truth.max(f32::MIN_POSITIVE) as f64;
    Ok(StepResult {
        step: name.into(),
        scored: cols,
        rmse,
        rmse_2ns: rmse,
        detection_rate: peaks.true_detections as f64 / n_truth.max(1) as f64,
        false_per_pulse: peaks.false_detections as f64 / cols.max(1) as f64,
        sam_deg: sam / cols.max(1) as f64,
        median_ns: percentile(&times, 0.5),
        p99_ns: percentile(&times, 0.99),
        position_rms_m: f64::NAN,
        position_max_m: f64::NAN,
    })
}

/// The results as a Markdown table.
pub fn markdown(results: &[StepResult]) -> String {
    let mut s = String::from(
        "| step | scored | RMSE | RMSE through 2 ns | peaks found | false peaks / waveform | SAM (deg) | position error RMS / max (mm) | median time / pulse (µs) | p99 (µs) |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        s.push_str(&format!(
            "| {} | {} | {:.4} | {:.4} | {:.1} % | {:.2} | {:.2} | {} | {:.2} | {} |\n",
            r.step,
            r.scored,
            r.rmse,
            r.rmse_2ns,
            100.0 * r.detection_rate,
            r.false_per_pulse,
            r.sam_deg,
            if r.position_rms_m.is_nan() {
                "—".to_string()
            } else {
                format!(
                    "{:.3} / {:.3}",
                    1e3 * r.position_rms_m,
                    1e3 * r.position_max_m
                )
            },
            r.median_ns / 1e3,
            if r.p99_ns.is_nan() {
                "—".to_string()
            } else {
                format!("{:.2}", r.p99_ns / 1e3)
            }
        ));
    }
    s
}

/// The results as CSV.
pub fn csv(results: &[StepResult]) -> String {
    let mut s = String::from(
        "step,scored,rmse,rmse_2ns,detection_rate,false_per_waveform,sam_deg,median_ns,p99_ns,position_rms_m,position_max_m\n",
    );
    for r in results {
        s.push_str(&format!(
            "{},{},{:.6},{:.6},{:.6},{:.6},{:.4},{:.1},{:.1},{:.7},{:.7}\n",
            r.step,
            r.scored,
            r.rmse,
            r.rmse_2ns,
            r.detection_rate,
            r.false_per_pulse,
            r.sam_deg,
            r.median_ns,
            r.p99_ns,
            r.position_rms_m,
            r.position_max_m
        ));
    }
    s
}
