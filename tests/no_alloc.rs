//! No allocation per pulse on the hot path: the number of heap allocations of a whole run
//! (source → denoise worker → sink; source → calibrate worker, which fills the signal itself,
//! → sink) must not grow with the number of pulses. A counting global
//! allocator sees every allocation of this test process.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use fwlidar::nav::consumer::NavTally;
use fwlidar::pipeline::edge::FullPolicy;
use fwlidar::pipeline::ports::NullSink;
use fwlidar::pipeline::runner::{PipelineSpec, StageFactory};
use fwlidar::pipeline::testing::SyntheticSource;
use fwlidar::pipeline::{RunControl, Stage, run};
use fwlidar::signal::{Calibrate, CalibrateConfig, Denoise, DenoiseConfig};

struct Counting;
static ALLOCS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// This thread's allocations only: a single-threaded measurement is then untouched by
    /// what the test harness allocates on its own threads meanwhile.
    static THIS_THREAD: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

fn count() {
    ALLOCS.fetch_add(1, Ordering::Relaxed);
    let _ = THIS_THREAD.try_with(|c| c.set(c.get() + 1));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// The counter is global: the tests of this file take turns so that one does not count another's
/// allocations.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn allocations_for(pulses: u64, workers: usize) -> u64 {
    let factory: StageFactory =
        Arc::new(|| vec![Box::new(Denoise::new(DenoiseConfig::default())) as Box<dyn Stage>]);
    allocations_with(factory, vec!["denoise"], pulses, workers)
}

fn allocations_with(
    factory: StageFactory,
    stage_names: Vec<&'static str>,
    pulses: u64,
    workers: usize,
) -> u64 {
    let spec = PipelineSpec {
        workers,
        queue_capacity: 8,
        input_policy: FullPolicy::Block,
        stages: factory,
        stage_names,
    };
    allocations_and_report(spec, pulses).0
}

fn allocations_and_report(
    spec: PipelineSpec,
    pulses: u64,
) -> (
    u64,
    fwlidar::pipeline::RunReport<(), (), fwlidar::nav::consumer::TallyReport>,
) {
    let before = ALLOCS.load(Ordering::SeqCst);
    let report = run(
        &spec,
        Box::new(SyntheticSource::new(pulses)),
        Box::new(NullSink),
        Box::new(NavTally::default()),
        &RunControl::default(),
        |_| {},
    );
    assert_eq!(report.pulses_out, pulses);
    (ALLOCS.load(Ordering::SeqCst) - before, report)
}

#[test]
fn allocations_do_not_grow_with_pulses() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    for workers in [1, 2] {
        let small = allocations_for(10_000, workers);
        let large = allocations_for(100_000, workers);
        // 90 000 more pulses may fill the bounded pulse pool further (at most
        // workers × (2 × 8 + 8) + 8 pulses of ~5 buffers each), never cost one allocation each.
        assert!(
            large.saturating_sub(small) < 1_000,
            "workers={workers}: {small} allocations for 10 000 pulses, {large} for 100 000"
        );
    }
}

#[test]
fn calibrate_allocates_nothing_per_pulse() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let factory: StageFactory = Arc::new(|| {
        vec![Box::new(Calibrate::new(CalibrateConfig {
            t0_is_emission: Some(true),
            ..Default::default()
        })) as Box<dyn Stage>]
    });
    let small = allocations_with(factory.clone(), vec!["calibrate"], 10_000, 1);
    let large = allocations_with(factory, vec!["calibrate"], 100_000, 1);
    assert!(
        large.saturating_sub(small) < 1_000,
        "{small} allocations for 10 000 pulses, {large} for 100 000"
    );
}

/// Deconvolution by each pulse's outgoing pulse cut to its support allocates nothing per pulse,
/// whether the support fits `max_taps` or is cut to it (the synthetic outgoing ramp stands
/// above its noise over more than 16 samples).
#[test]
fn deconvolve_by_the_outgoing_support_allocates_nothing_per_pulse() {
    use fwlidar::signal::deconvolve::{MethodConfig, NnlsConfig, NnlsOrRlConfig, RlConfig};
    use fwlidar::stages::deconvolve::DeconvolveConfig;
    use fwlidar::stages::deconvolve::{Deconvolve, KERNEL_OVER_MAX_TAPS};
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // Plain RL, and accelerated RL with the coarse-to-fine start (a coarse FWHM of 1 sample:
    // a decimation factor of ≥ 2 for any outgoing pulse at least 2 samples wide); RL stopping
    // by the noise and delivering its result as seen by a 2 ns target pulse (a reduced kernel
    // per shot), NNLS drawn as the target pulse (also with its noise-weighted refit), and the
    // on-board RL from a Wiener start; the per-pulse choice between NNLS and RL.
    let rl = |coarse_iterations: u32, stop_at_noise: Option<f32>| {
        MethodConfig::RichardsonLucy(RlConfig {
            iterations: 2,
            early_stop: None,
            accelerate: coarse_iterations > 0,
            stop_at_noise,
            coarse_iterations,
            coarse_fwhm_samples: 1.0,
            ..RlConfig::default()
        })
    };
    let nnls = MethodConfig::Nnls(NnlsConfig {
        max_iterations: 3,
        ..NnlsConfig::default()
    });
    // NNLS with the noise-weighted refit (`fwlidar process`'s setting).
    let nnls_weighted = MethodConfig::Nnls(NnlsConfig {
        max_iterations: 20,
        noise_weights: true,
        ..NnlsConfig::default()
    });
    // NNLS with spikes only near echoes (`fwlidar process`'s default).
    let nnls_near = MethodConfig::Nnls(NnlsConfig {
        max_iterations: 20,
        support_at_noise: Some(4.0),
        ..NnlsConfig::default()
    });
    // NNLS run on every segment (`nnls_above_noise = 0`): the choice's longest path.
    let choice = MethodConfig::NnlsOrRl(NnlsOrRlConfig {
        nnls: NnlsConfig {
            max_iterations: 10,
            support_at_noise: Some(4.0),
            ..NnlsConfig::default()
        },
        nnls_above_noise: 0.0,
        ..NnlsOrRlConfig::default()
    });
    for (max_taps, method, target_fwhm_ns) in [
        (256usize, rl(0, None), None),
        (16, rl(0, None), None),
        (256, rl(3, None), None),
        (16, rl(3, None), None),
        (256, rl(0, Some(1.0)), Some(2.0)),
        (16, nnls, Some(2.0)),
        (256, nnls_weighted, Some(2.0)),
        (256, nnls_near, None),
        // The on-board setting: the Wiener start (its FFT plans per window length) and the
        // output's noise floor.
        (96, MethodConfig::RichardsonLucy(RlConfig::onboard()), None),
        // The per-pulse choice between NNLS and RL, as it is and to a 2 ns target.
        (96, choice.clone(), None),
        (96, choice, Some(2.0)),
    ] {
        let factory: StageFactory = Arc::new(move || {
            vec![
                Box::new(Denoise::new(DenoiseConfig::default())) as Box<dyn Stage>,
                Box::new(
                    Deconvolve::new(DeconvolveConfig {
                        max_taps,
                        target_fwhm_ns,
                        ..DeconvolveConfig::with_method(method.clone())
                    })
                    .unwrap(),
                ),
            ]
        });
        let spec = |factory: &StageFactory| PipelineSpec {
            workers: 1,
            queue_capacity: 8,
            input_policy: FullPolicy::Block,
            stages: factory.clone(),
            stage_names: vec!["denoise", "deconvolve"],
        };
        let (small, _) = allocations_and_report(spec(&factory), 5_000);
        let (large, report) = allocations_and_report(spec(&factory), 50_000);
        let cut = report.stages[1].notes.get(KERNEL_OVER_MAX_TAPS).copied();
        assert_eq!(
            cut,
            (max_taps == 16).then_some(50_000),
            "max_taps {max_taps}"
        );
        assert!(
            large.saturating_sub(small) < 1_000,
            "max_taps {max_taps}: {small} allocations for 5 000 pulses, {large} for 50 000"
        );
    }
}

/// The voxeliser deposits pulses into open tiles without allocating: 20 000 and 200 000 pulses
/// along a line over the same open tiles cost the same number of allocations.
#[test]
fn voxel_deposits_allocate_nothing_per_pulse() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    use fwlidar::pulse::{Pulse, PulseGeometry, SegmentKind};
    use fwlidar::voxel::grid::{Grid, Placer, VoxelConfig};
    use fwlidar::voxel::tiles::TileSet;
    use fwlidar::voxel::voxelise::{DepositParams, DepositStats, deposit_pulse};
    use fwlidar::voxel::zarr::{StoreInfo, ZarrStore};

    let run = |pulses: u64| -> u64 {
        let dir = tempfile::tempdir().unwrap();
        let cfg = VoxelConfig {
            enabled: true,
            extent_m: Some([0.0, 0.0, 64.0, 64.0]),
            z_range_m: [-5.0, 30.0],
            ..VoxelConfig::default()
        };
        let grid = Grid::new(&cfg, [0.0, 0.0]);
        let store = ZarrStore::create_or_open(
            &dir.path().join("v.zarr"),
            grid.clone(),
            StoreInfo {
                crs_wkt: None,
                epsg: None,
                intensity_units: "V".into(),
                run_key: "t".into(),
                configuration: String::new(),
            },
        )
        .unwrap();
        let mut tiles = TileSet::new(store, 16, 1e9);
        let params = DepositParams {
            placer: Placer::new(&grid),
            height: grid.height,
            dem: None,
            inv_quantum: 1e6,
            footprint_divergence_rad: None,
        };
        let mut stats = DepositStats::default();
        let mut p = Pulse {
            sample_ns: 1.0,
            geometry: Some(PulseGeometry {
                anchor: [1.0, 1.0, 30.0],
                direction: [0.01, 0.0, -0.1499],
            }),
            ..Default::default()
        };
        p.push_segment(SegmentKind::Return, 0, 0.0, 0..225u16);
        p.signal = (0..225).map(|i| i as f32 * 0.01).collect();
        let before = ALLOCS.load(Ordering::SeqCst);
        for i in 0..pulses {
            p.seq = i;
            p.gps_time = i as f64 * 1e-6;
            // Back and forth over 60 m: the tiles stay open (close_after_s is large).
            let x = 2.0 + (i % 600) as f64 * 0.1;
            p.geometry.as_mut().unwrap().anchor[0] = x;
            deposit_pulse(&p, &mut tiles, &params, &mut stats).unwrap();
            tiles.close_idle(i, p.gps_time).unwrap();
        }
        let n = ALLOCS.load(Ordering::SeqCst) - before;
        assert!(stats.bins_deposited > pulses * 200);
        n
    };
    let (small, large) = (run(20_000), run(200_000));
    assert_eq!(
        small, large,
        "{small} allocations for 20 000 pulses, {large} for 200 000"
    );
}

/// The noise-aware detector (`fwlidar process --peaks`) allocates nothing per waveform once
/// built: the same count for 10 and for 1000 waveforms of two echoes and noise (counted on
/// this thread: the detector runs on the caller's).
#[test]
fn echo_detection_allocates_nothing_per_waveform() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    use fwlidar::signal::echo_strength::EchoDetector;
    let taps: Vec<f32> = (-14..=14)
        .map(|j| (-0.5 * (j as f32 / 3.4).powi(2)).exp())
        .collect();
    let run = |waveforms: u64| -> u64 {
        let mut d = EchoDetector::new(256, taps.len());
        let mut out = Vec::with_capacity(256);
        let mut x = vec![0.0f32; 256];
        let before = THIS_THREAD.with(|c| c.get());
        for w in 0..waveforms {
            for (i, v) in x.iter_mut().enumerate() {
                let wiggle = ((i as u64 * 7919 + w * 104_729) % 97) as f32 / 97.0;
                *v = 0.02 * wiggle;
            }
            x[60 + (w % 50) as usize] += 1.0;
            x[150] += 0.4;
            d.set_pulse(&taps);
            d.detect(&x, 0.01, 5.0, &mut out);
            assert!(out.len() >= 2, "both echoes");
        }
        THIS_THREAD.with(|c| c.get()) - before
    };
    let (few, many) = (run(10), run(1000));
    assert_eq!(
        few, many,
        "allocations grow with waveforms: {few} vs {many}"
    );
}

/// The deconvolve stage with NNLS on pulses whose return reaches the 8-bit digitizer's full
/// scale (the samples flagged and left out of the fit, through the gate and a 2 ns target)
/// allocates nothing per pulse: the same count for 10 and for 1000 pulses (this thread).
#[test]
fn nnls_leaving_out_full_scale_samples_allocates_nothing_per_pulse() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    use fwlidar::pulse::{Pulse, SegmentKind};
    use fwlidar::signal::deconvolve::{MethodConfig, NnlsConfig};
    use fwlidar::stages::deconvolve::{CLIPPED_SAMPLES, Deconvolve, DeconvolveConfig};
    let gauss = |n: usize, c: f32, s: f32, a: f32| -> Vec<u16> {
        (0..n)
            .map(|i| {
                (a * (-0.5 * ((i as f32 - c) / s).powi(2)).exp())
                    .round()
                    .min(255.0) as u16
            })
            .collect()
    };
    let mut pulse = Pulse {
        bits: 8,
        sample_ns: 1.0,
        ..Default::default()
    };
    pulse.push_segment(SegmentKind::Outgoing, 0, -20.0, gauss(41, 20.0, 3.4, 200.0));
    pulse.push_segment(SegmentKind::Return, 0, 900.0, gauss(225, 90.0, 3.4, 600.0));
    assert!(pulse.raw.contains(&255));
    let volts: Vec<f32> = pulse.raw.iter().map(|&c| c as f32 * 1e-3).collect();
    pulse.signal = volts.clone();
    pulse.noise.noise_v = 1e-3;
    let mut stage = Deconvolve::new(DeconvolveConfig {
        target_fwhm_ns: Some(2.0),
        ..DeconvolveConfig::with_method(MethodConfig::Nnls(NnlsConfig::default()))
    })
    .unwrap();
    let mut run = |pulses: u32| -> u64 {
        let before = THIS_THREAD.with(|c| c.get());
        for _ in 0..pulses {
            pulse.signal.copy_from_slice(&volts);
            let verdict = stage.deconvolve_pulse(&mut pulse);
            assert_eq!(verdict, fwlidar::pulse::Verdict::noted(CLIPPED_SAMPLES));
        }
        THIS_THREAD.with(|c| c.get()) - before
    };
    let _warm = run(2);
    let (few, many) = (run(10), run(1000));
    assert_eq!(few, many, "allocations grow with pulses: {few} vs {many}");
}
