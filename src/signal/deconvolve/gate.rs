//! Echo-window gating: deconvolve only the parts of a return segment that hold echoes.
//!
//! After the denoise stage the segment's noise level `noise_v` is known (mean
//! `|raw − baseline − smoothed|`, volts, [`crate::pulse::NoiseEstimate`]); most of a 256-sample
//! return is empty air at that level. With the gate on, a segment `y` (volts above baseline) is
//! deconvolved as follows (`m` = kernel taps, `k` = [`Gate::On::threshold_noise`]):
//!
//! 1. **Echo samples**: every sample with `y[i] > k · noise_v` (returns are positive-going, so
//!    only the upper side counts).
//! 2. **Windows**: each run of echo samples is widened by `2·m` samples on both sides and
//!    clipped to the segment. The echo's own flanks below the threshold reach about half a
//!    kernel out; the rest keeps the window's edge (where Richardson-Lucy and Gold see zeros
//!    instead of data, and whose artefacts the iterations spread by up to a kernel per
//!    iteration, decaying) well inside the noise. Measured with `fwlidar tradeoff`: a margin
//!    of one kernel length lost up to 9 of ~2,600 true peaks in the extended 4 and 8 ns cases
//!    (weak canopy peaks near a window's edge); two lose none. Windows closer than the margin
//!    are merged (an edge costs more than the gap it saves).
//! 3. **Deconvolution**: the method runs on each window alone (its own normalisation and
//!    buffers; every window is at least `4·m + 1` samples, longer than the kernel, unless the
//!    segment itself is shorter). Outside the windows the output is **0**: there the data are
//!    noise, `y ≤ k · noise_v` everywhere within a kernel's reach, and the un-gated methods give
//!    noise-level values there (Richardson-Lucy concentrates the positive noise into spikes of
//!    a few `noise_v`; with `k = 3` and the default decomposition threshold of 5 noise levels
//!    none of them is a return).
//! 4. A segment without any echo sample costs one scan and a fill. When the windows cover at
//!    least three quarters of the segment, the method runs on the whole segment, exactly as
//!    without the gate (one window instead of several edges).
//!
//! When the noise level is not a positive finite number (no denoise stage measured it, or a
//! noise-free record), the gate cannot tell echoes from noise and the whole segment is
//! deconvolved. The gate applies to the iterative direct methods (Richardson-Lucy and Gold),
//! whose cost grows with the samples they touch; Wiener (one FFT of the whole segment) and
//! NNLS (an active set over the whole segment) always run un-gated.
//!
//! The same [`Gated`] deconvolver runs in the deconvolve stage, in `fwlidar tradeoff` and in
//! the scene evaluation, so their timings are of the same code.

use std::fmt;

use serde::de::{self, MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::signal::deconvolve::{DeconvError, Deconvolver, MethodConfig, MethodStats};
use crate::signal::kernel::Kernel;

/// Default threshold of the gate, in noise levels (`noise_v`).
pub const DEFAULT_THRESHOLD_NOISE: f32 = 3.0;

/// Margin added on both sides of a run of echo samples, in kernel lengths.
const MARGIN_KERNELS: usize = 2;

/// Fraction of a segment the windows may cover before the whole segment is deconvolved
/// instead (numerator over 4).
const WHOLE_SEGMENT_QUARTERS: usize = 3;

/// The echo-window gate of a deconvolve stage (`gate = ...` in the stage's table).
///
/// TOML: `gate = "off"` (every return segment deconvolved whole, the old path), `gate = "on"`
/// (the default threshold) or `gate = { threshold_noise = 3.0 }`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Gate {
    /// No gating: every return segment is deconvolved whole.
    Off,
    /// Deconvolve only the windows around samples above `threshold_noise × noise_v`.
    On {
        /// Threshold, in noise levels (dimensionless multiple of the pulse's `noise_v`);
        /// positive and finite. Default [`DEFAULT_THRESHOLD_NOISE`].
        threshold_noise: f32,
    },
}

impl Default for Gate {
    fn default() -> Self {
        Gate::On {
            threshold_noise: DEFAULT_THRESHOLD_NOISE,
        }
    }
}

/// Why a gate setting is unusable.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum GateError {
    /// The threshold is zero, negative or not a number.
    #[error("threshold_noise must be a positive finite number of noise levels, got {0}")]
    BadThreshold(f32),
    /// The method does not support gating.
    #[error(
        "the echo-window gate applies to richardson_lucy and gold only ({0} works on the whole \
         segment); remove `gate` or set gate = \"off\""
    )]
    Unsupported(&'static str),
}

impl Gate {
    /// True for the methods the gate applies to (Richardson-Lucy and Gold).
    pub fn supports(method: &MethodConfig) -> bool {
        matches!(
            method,
            MethodConfig::RichardsonLucy(_) | MethodConfig::Gold(_)
        )
    }

    /// The gate a stage uses when its configuration names none: on (default threshold) for the
    /// methods that support it, off for the others.
    pub fn default_for(method: &MethodConfig) -> Gate {
        if Gate::supports(method) {
            Gate::default()
        } else {
            Gate::Off
        }
    }

    /// Checks the gate as configured for `method`.
    pub fn validate(&self, method: &MethodConfig) -> Result<(), GateError> {
        match *self {
            Gate::Off => Ok(()),
            Gate::On { threshold_noise } => {
                if !(threshold_noise.is_finite() && threshold_noise > 0.0) {
                    Err(GateError::BadThreshold(threshold_noise))
                } else if !Gate::supports(method) {
                    Err(GateError::Unsupported(method.name()))
                } else {
                    Ok(())
                }
            }
        }
    }
}

impl Serialize for Gate {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match *self {
            Gate::Off => s.serialize_str("off"),
            Gate::On { threshold_noise } => {
                let mut map = s.serialize_map(Some(1))?;
                map.serialize_entry("threshold_noise", &threshold_noise)?;
                map.end()
            }
        }
    }
}

impl<'de> Deserialize<'de> for Gate {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct GateVisitor;
        impl<'de> Visitor<'de> for GateVisitor {
            type Value = Gate;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("\"off\", \"on\" or a table { threshold_noise = K }")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Gate, E> {
                match v {
                    "off" => Ok(Gate::Off),
                    "on" => Ok(Gate::default()),
                    other => Err(E::invalid_value(de::Unexpected::Str(other), &self)),
                }
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Gate, A::Error> {
                let mut threshold = None;
                while let Some(key) = map.next_key::<String>()? {
                    match key.as_str() {
                        "threshold_noise" => {
                            if threshold.is_some() {
                                return Err(de::Error::duplicate_field("threshold_noise"));
                            }
                            threshold = Some(map.next_value::<f32>()?);
                        }
                        other => return Err(de::Error::unknown_field(other, &["threshold_noise"])),
                    }
                }
                Ok(Gate::On {
                    threshold_noise: threshold.unwrap_or(DEFAULT_THRESHOLD_NOISE),
                })
            }
        }
        d.deserialize_any(GateVisitor)
    }
}

/// What the gate did with the last segment (for tests and benchmarks).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GateStats {
    /// Windows deconvolved (0: no echo; 1 with `whole`: the whole segment).
    pub windows: usize,
    /// Samples inside the windows.
    pub samples: usize,
    /// True when the whole segment was deconvolved (gate off, no noise level, or the windows
    /// covered most of it).
    pub whole: bool,
}

/// A deconvolution method behind the echo-window gate (see the module documentation). With
/// [`Gate::Off`] it is the method itself.
pub struct Gated {
    method: Box<dyn Deconvolver>,
    gate: Gate,
    max_samples: usize,
    max_taps: usize,
    /// Windows `[start, end)` of the current segment; capacity `max_samples / 2 + 1` (windows
    /// are at least two samples apart), never grown.
    windows: Vec<(usize, usize)>,
    last: GateStats,
}

impl Gated {
    /// Wraps `method` (built for segments of up to `max_samples` and kernels of up to
    /// `max_taps`) behind `gate`.
    pub fn new(
        method: Box<dyn Deconvolver>,
        gate: Gate,
        max_samples: usize,
        max_taps: usize,
    ) -> Self {
        Gated {
            method,
            gate,
            max_samples,
            max_taps,
            windows: Vec::with_capacity(max_samples / 2 + 1),
            last: GateStats::default(),
        }
    }

    /// Builds `method` with its gate for segments of up to `max_samples` and kernels of up to
    /// `max_taps`.
    pub fn build(method: &MethodConfig, gate: Gate, max_samples: usize, max_taps: usize) -> Self {
        Gated::new(
            method.build(max_samples, max_taps),
            gate,
            max_samples,
            max_taps,
        )
    }

    /// The gate in force.
    pub fn gate(&self) -> Gate {
        self.gate
    }

    /// What the gate did with the last segment.
    pub fn last_stats(&self) -> GateStats {
        self.last
    }

    /// Capacity of the window list (for the no-allocation test).
    #[cfg(test)]
    pub(crate) fn windows_capacity(&self) -> usize {
        self.windows.capacity()
    }

    /// Fills `self.windows` with the merged windows of `y` for threshold `level` (volts) and
    /// margin `margin` samples; returns the samples they cover.
    fn find_windows(&mut self, y: &[f32], level: f32, margin: usize) -> usize {
        self.windows.clear();
        let n = y.len();
        let mut covered = 0;
        let mut i = 0;
        while i < n {
            if y[i] <= level {
                i += 1;
                continue;
            }
            let run_start = i;
            while i < n && y[i] > level {
                i += 1;
            }
            let start = run_start.saturating_sub(margin);
            let end = (i + margin).min(n);
            match self.windows.last_mut() {
                Some(last) if start <= last.1 + margin => {
                    covered += end.saturating_sub(last.1);
                    last.1 = last.1.max(end);
                }
                _ => {
                    // Windows start at least margin + 1 ≥ 2 samples apart: the capacity of
                    // max_samples / 2 + 1 is never exceeded.
                    self.windows.push((start, end));
                    covered += end - start;
                }
            }
        }
        covered
    }
}

impl Gated {
    /// The method on the whole segment or on each echo window, with the flagged samples (as
    /// long as `y`) left out where the method can.
    fn run_with(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: Option<&[bool]>,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let n = y.len();
        let excluded = excluded.filter(|e| e.len() == n);
        let whole = |s: &mut Self, out: &mut [f32]| {
            s.last = GateStats {
                windows: 1,
                samples: n,
                whole: true,
            };
            super::run_flagged(s.method.as_mut(), y, k, noise_v, sample_ns, excluded, out)
        };
        let threshold = match self.gate {
            Gate::On { threshold_noise } if noise_v.is_finite() && noise_v > 0.0 => {
                threshold_noise * noise_v
            }
            _ => return whole(self, out),
        };
        // The checks the method would make on the whole segment (a NaN outside every window
        // must still reject the pulse).
        super::check_inputs(y, k, out, self.max_samples, self.max_taps)?;
        let margin = MARGIN_KERNELS * k.len();
        let covered = self.find_windows(y, threshold, margin);
        if covered * 4 >= n * WHOLE_SEGMENT_QUARTERS {
            return whole(self, out);
        }
        out.fill(0.0);
        let mut stats = MethodStats::default();
        for wi in 0..self.windows.len() {
            let (a, b) = self.windows[wi];
            let flags = excluded.map(|e| &e[a..b]);
            let s = super::run_flagged(
                self.method.as_mut(),
                &y[a..b],
                k,
                noise_v,
                sample_ns,
                flags,
                &mut out[a..b],
            )?;
            stats.iterations = stats.iterations.max(s.iterations);
            stats.stopped_early |= s.stopped_early;
        }
        self.last = GateStats {
            windows: self.windows.len(),
            samples: covered,
            whole: false,
        };
        Ok(stats)
    }
}

impl Deconvolver for Gated {
    fn name(&self) -> &'static str {
        self.method.name()
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, None, out)
    }

    fn run_excluding(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: &[bool],
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, Some(excluded), out)
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        // The windows never cover more than the segment; the worst case is the whole segment.
        self.method.worst_case_flops(n, m) + n as u64
    }

    fn take_target(&mut self, fwhm_ns: f64) -> bool {
        self.method.take_target(fwhm_ns)
    }

    fn choice_counts(&self) -> Option<super::ChoiceCounts> {
        self.method.choice_counts()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::deconvolve::{GoldConfig, RlConfig, WienerConfig};

    fn kernel(fwhm: f32) -> Kernel {
        let sigma = fwhm / 2.354_82;
        let half = (3.0 * sigma).ceil() as usize;
        let taps: Vec<f32> = (0..=2 * half)
            .map(|j| (-0.5 * ((j as f32 - half as f32) / sigma).powi(2)).exp())
            .collect();
        let mut k = Kernel::default();
        k.set_from_taps(&taps, half, 256).unwrap();
        k
    }

    /// Echoes `(centre, amplitude)` of the kernel's shape on `n` samples plus uniform noise of
    /// half-width `noise`; returns the record.
    fn record(n: usize, k: &Kernel, echoes: &[(usize, f32)], noise: f32, seed: u32) -> Vec<f32> {
        let mut x = seed.wrapping_mul(2_654_435_761).max(1);
        (0..n)
            .map(|i| {
                let mut v = 0.0;
                for &(c, a) in echoes {
                    let j = i as i64 - c as i64 + k.center as i64;
                    if (0..k.len() as i64).contains(&j) {
                        v += a * k.taps[j as usize] / k.taps[k.center];
                    }
                }
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                v + noise * ((x as f32 / u32::MAX as f32) * 2.0 - 1.0)
            })
            .collect()
    }

    fn rl() -> MethodConfig {
        MethodConfig::RichardsonLucy(RlConfig::default())
    }

    #[test]
    fn excluded_samples_reach_the_method_through_the_gate() {
        use crate::signal::deconvolve::NnlsConfig;
        let k = kernel(8.0);
        let mut y = record(128, &k, &[(40, 1.0), (80, 0.4)], 0.01, 3);
        // The strong echo clipped at 0.6: its top samples flagged.
        let excluded: Vec<bool> = y.iter().map(|&v| v >= 0.6).collect();
        y.iter_mut().for_each(|v| *v = v.min(0.6));
        assert!(excluded.iter().filter(|&&e| e).count() >= 3);
        let method = MethodConfig::Nnls(NnlsConfig::default());
        let mut direct = method.build(128, 64);
        let mut gated = Gated::build(&method, Gate::Off, 128, 64);
        let (mut a, mut b, mut c) = (vec![0.0; 128], vec![0.0; 128], vec![0.0; 128]);
        direct
            .run_excluding(&y, &k, 0.01, 1.0, &excluded, &mut a)
            .unwrap();
        gated
            .run_excluding(&y, &k, 0.01, 1.0, &excluded, &mut b)
            .unwrap();
        assert_eq!(a, b, "the gate passes the flags on");
        gated.run(&y, &k, 0.01, 1.0, &mut c).unwrap();
        let (left_out, fitted): (f32, f32) = (b.iter().sum(), c.iter().sum());
        assert!(left_out > fitted + 0.5, "{left_out} vs {fitted}");
        // Every sample flagged, or flags of the wrong length: finite, never a panic.
        let all = vec![true; 128];
        gated
            .run_excluding(&y, &k, 0.01, 1.0, &all, &mut b)
            .unwrap();
        assert!(b.iter().all(|v| v.is_finite()));
        gated
            .run_excluding(&y, &k, 0.01, 1.0, &all[..5], &mut b)
            .unwrap();
        assert_eq!(b, c, "flags of another length are ignored");
    }

    #[test]
    fn gate_config_parses_with_clear_errors() {
        #[derive(Deserialize, Serialize, Debug, PartialEq)]
        struct T {
            gate: Gate,
        }
        let p = |s: &str| toml::from_str::<T>(s).map(|t| t.gate);
        assert_eq!(p("gate = \"off\"").unwrap(), Gate::Off);
        assert_eq!(p("gate = \"on\"").unwrap(), Gate::default());
        assert_eq!(
            p("gate = { threshold_noise = 4.5 }").unwrap(),
            Gate::On {
                threshold_noise: 4.5
            }
        );
        assert_eq!(p("gate = {}").unwrap(), Gate::default());
        let e = p("gate = \"maybe\"").unwrap_err().to_string();
        assert!(e.contains("\"off\", \"on\""), "{e}");
        let e = p("gate = { threshold = 3.0 }").unwrap_err().to_string();
        assert!(e.contains("threshold_noise"), "{e}");
        assert!(p("gate = 3.0").is_err());
        for g in [
            Gate::Off,
            Gate::default(),
            Gate::On {
                threshold_noise: 2.0,
            },
        ] {
            let text = toml::to_string(&T { gate: g }).unwrap();
            assert_eq!(p(&text).unwrap(), g, "{text}");
        }
    }

    #[test]
    fn gate_validation_names_the_problem() {
        assert!(Gate::default().validate(&rl()).is_ok());
        assert!(
            Gate::Off
                .validate(&MethodConfig::Wiener(WienerConfig::default()))
                .is_ok()
        );
        for t in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert_eq!(
                Gate::On { threshold_noise: t }
                    .validate(&rl())
                    .map_err(|e| matches!(e, GateError::BadThreshold(_))),
                Err(true)
            );
        }
        assert_eq!(
            Gate::default().validate(&MethodConfig::Wiener(WienerConfig::default())),
            Err(GateError::Unsupported("wiener"))
        );
        assert_eq!(Gate::default_for(&rl()), Gate::default());
        assert_eq!(
            Gate::default_for(&MethodConfig::Nnls(Default::default())),
            Gate::Off
        );
    }

    #[test]
    fn an_empty_segment_deconvolves_to_zeros_without_running_the_method() {
        let k = kernel(8.0);
        let y = record(256, &k, &[], 0.01, 1);
        let mut g = Gated::build(&rl(), Gate::default(), 1024, 96);
        let mut out = vec![1.0; 256];
        let s = g.run(&y, &k, 0.006, 1.0, &mut out).unwrap();
        assert_eq!(s.iterations, 0);
        assert_eq!(g.last_stats(), GateStats::default());
        assert!(out.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn gated_output_matches_the_whole_segment_within_the_noise() {
        // Two separated echoes and noise of ±0.01 (noise level ≈ 0.006 after a denoise); the
        // gated result agrees with the un-gated one inside the windows to a small fraction
        // of the echo and outside them to within a few noise levels.
        let k = kernel(8.0);
        for method in [rl(), MethodConfig::Gold(GoldConfig::default())] {
            for seed in 1..6 {
                let y = record(512, &k, &[(100, 0.8), (380, 0.3)], 0.01, seed);
                let noise_v = 0.006;
                let mut whole = method.build(1024, 96);
                let mut gated = Gated::build(&method, Gate::default(), 1024, 96);
                let (mut a, mut b) = (vec![0.0; 512], vec![0.0; 512]);
                whole.run(&y, &k, noise_v, 1.0, &mut a).unwrap();
                gated.run(&y, &k, noise_v, 1.0, &mut b).unwrap();
                let st = gated.last_stats();
                assert!(!st.whole && st.windows == 2 && st.samples < 300, "{st:?}");
                let peak = a.iter().fold(0.0f32, |m, &v| m.max(v));
                for (i, (&p, &q)) in a.iter().zip(&b).enumerate() {
                    let inside = (i as i64 - 100).abs() < 15 || (i as i64 - 380).abs() < 15;
                    let tol = if inside { 0.02 * peak } else { 6.0 * noise_v };
                    assert!(
                        (p - q).abs() <= tol,
                        "{}: sample {i}: whole {p}, gated {q} (peak {peak})",
                        method.name()
                    );
                }
                // The echoes' energy is kept.
                let sum = |v: &[f32]| v.iter().sum::<f32>();
                assert!((sum(&b[80..120]) / sum(&a[80..120]) - 1.0).abs() < 0.02);
                assert!((sum(&b[360..400]) / sum(&a[360..400]) - 1.0).abs() < 0.05);
            }
        }
    }

    #[test]
    fn close_echoes_share_a_window_and_a_full_segment_runs_whole() {
        let k = kernel(8.0);
        let m = k.len();
        let y = record(256, &k, &[(100, 0.8), (100 + m + 5, 0.5)], 0.01, 3);
        let mut g = Gated::build(&rl(), Gate::default(), 1024, 96);
        let mut out = vec![0.0; 256];
        g.run(&y, &k, 0.006, 1.0, &mut out).unwrap();
        assert_eq!(g.last_stats().windows, 1);
        // Echoes everywhere: the whole segment, the same bits as the method alone.
        let echoes: Vec<(usize, f32)> = (0..8).map(|i| (16 + 30 * i, 0.5)).collect();
        let y = record(256, &k, &echoes, 0.01, 4);
        g.run(&y, &k, 0.006, 1.0, &mut out).unwrap();
        assert!(g.last_stats().whole);
        let mut alone = vec![0.0; 256];
        rl().build(1024, 96)
            .run(&y, &k, 0.006, 1.0, &mut alone)
            .unwrap();
        assert_eq!(out, alone);
    }

    #[test]
    fn gate_off_or_unknown_noise_is_the_method_itself_and_bad_input_is_still_rejected() {
        let k = kernel(8.0);
        let y = record(256, &k, &[(60, 0.8)], 0.01, 5);
        let mut alone = vec![0.0; 256];
        rl().build(1024, 96)
            .run(&y, &k, 0.006, 1.0, &mut alone)
            .unwrap();
        for (gate, noise) in [
            (Gate::Off, 0.006),
            (Gate::default(), 0.0),
            (Gate::default(), f32::NAN),
        ] {
            let mut g = Gated::build(&rl(), gate, 1024, 96);
            let mut out = vec![0.0; 256];
            g.run(&y, &k, noise, 1.0, &mut out).unwrap();
            assert_eq!(out, alone, "{gate:?}, noise {noise}");
            assert!(g.last_stats().whole);
        }
        let mut bad = y.clone();
        bad[250] = f32::NAN; // outside every window
        let mut g = Gated::build(&rl(), Gate::default(), 1024, 96);
        let mut out = vec![0.0; 256];
        assert_eq!(
            g.run(&bad, &k, 0.006, 1.0, &mut out),
            Err(DeconvError::NonFiniteInput)
        );
        assert!(matches!(
            g.run(&y, &k, 0.006, 1.0, &mut out[..10]),
            Err(DeconvError::LengthMismatch { .. })
        ));
    }

    #[test]
    fn the_window_list_never_grows() {
        // Alternating single samples above the threshold: the most windows a segment can hold.
        let mut k = Kernel::default();
        k.set_from_taps(&[1.0], 0, 8).unwrap();
        let mut g = Gated::build(&rl(), Gate::default(), 64, 8);
        let cap = g.windows_capacity();
        // Margin 2: windows [i − 2, i + 3) every 8 samples, 5 of every 8 samples covered.
        let y: Vec<f32> = (0..64)
            .map(|i| if i % 8 == 0 { 1.0 } else { 0.0 })
            .collect();
        let mut out = vec![0.0; 64];
        g.run(&y, &k, 0.01, 1.0, &mut out).unwrap();
        assert_eq!(g.last_stats().windows, 8);
        assert_eq!(g.last_stats().samples, 3 + 7 * 5);
        assert_eq!(g.windows_capacity(), cap);
    }
}
