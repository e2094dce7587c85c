//! The item that flows through the dataflow: one laser shot ([`Pulse`]) with its digitizer
//! segments, and the [`PulsePool`] that recycles pulses so the hot path does not allocate.
//!
//! Units: times in nanoseconds unless a name says otherwise, GPS time in seconds, voltages in
//! volts, raw samples in digitizer counts (DN).

pub mod waveform_metrics;

pub use waveform_metrics::WaveformMetrics;

use std::time::Instant;

use crossbeam_channel::{Receiver, Sender, TrySendError, bounded};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// What a sampled segment of a pulse records.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SegmentKind {
    /// The outgoing (transmitted) pulse as the reference detector saw it.
    Outgoing,
    /// Energy that came back from the scene.
    Return,
}

/// What a per-pulse method made of one pulse; the stage that runs it turns this into the
/// runtime's emit, drop or reject (`pipeline::stage::Emitter`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Processed: pass it on. Each note (at most three) names something left undone on
    /// purpose (e.g. a factor of the calibration the pulse could not have), counted under it.
    Keep([Option<&'static str>; 3]),
    /// Not usable by this method (e.g. no segment): drop it, counted under the reason.
    Drop(&'static str),
    /// Its content is inconsistent (e.g. a segment past its samples): drop it, counted as an
    /// error under the reason.
    Reject(&'static str),
}

impl Verdict {
    /// Processed, nothing left undone.
    pub const DONE: Verdict = Verdict::Keep([None; 3]);

    /// Processed, with one note.
    pub fn noted(note: &'static str) -> Verdict {
        Verdict::Keep([Some(note), None, None])
    }
}

/// One contiguous run of digitizer samples of a pulse.
///
/// The samples themselves live in [`Pulse::raw`] (and, once processed, [`Pulse::signal`]) at
/// `first .. first + len`; all segments of a pulse share those two flat buffers so a pulse can be
/// reused without reallocating.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Outgoing reference or return.
    pub kind: SegmentKind,
    /// Receiver channel (e.g. RIEGL high/low power); 0 when the sensor has one.
    pub channel: u8,
    /// Time of the first sample relative to the pulse's reference time t0, in nanoseconds.
    pub start_ns: f64,
    /// Index of the segment's first sample in [`Pulse::raw`] / [`Pulse::signal`].
    pub first: u32,
    /// Number of samples.
    pub len: u32,
}

impl Segment {
    /// The index range of this segment's samples in the pulse's flat sample buffers.
    pub fn range(&self) -> std::ops::Range<usize> {
        self.first as usize..(self.first as usize + self.len as usize)
    }
}

/// Per-pulse noise figures estimated by the denoise stage.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NoiseEstimate {
    /// Baseline (noise floor) removed from the signal, in volts.
    pub baseline_v: f32,
    /// Noise level: mean absolute difference between the raw and low-passed signal, in volts.
    pub noise_v: f32,
}

/// Noise of the received signal as the input file states it (GEDI Level 1B's
/// `noise_mean_corrected` and `noise_stddev_corrected`), in the units of [`Pulse::signal`] before
/// any stage changes it: `offset_v + gain_v_per_dn × counts` (volts for a digitizer; GEDI's own
/// counts for GEDI input, whose gain makes one unit one GEDI count).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StatedNoise {
    /// Mean of the noise (the baseline), signal units.
    pub mean: f32,
    /// Standard deviation of the noise, signal units.
    pub stddev: f32,
}

/// A discrete return found by Gaussian decomposition of one segment.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct FittedReturn {
    /// Index of the segment in [`Pulse::segments`].
    pub segment: u16,
    /// Centre of the Gaussian, in bins from the segment's first sample (fractional).
    pub position_bins: f32,
    /// Centre as time after the pulse's reference time t0, ns.
    pub time_ns: f64,
    /// Peak amplitude, in the units of the fitted signal (volts after denoise).
    pub amplitude: f32,
    /// Standard deviation, bins.
    pub sigma_bins: f32,
    /// RMS residual of the whole fit over the segment, signal units.
    pub residual: f32,
    /// Calibrated backscatter of the return (the `calibrate` stage's units, see
    /// `docs/calibration.md`): its amplitude times the calibration factor at its range. NaN until
    /// a `calibrate` stage has run.
    pub backscatter: f32,
}

impl Default for FittedReturn {
    fn default() -> Self {
        FittedReturn {
            segment: 0,
            position_bins: 0.0,
            time_ns: 0.0,
            amplitude: 0.0,
            sigma_bins: 0.0,
            residual: 0.0,
            backscatter: f32::NAN,
        }
    }
}

/// Where a pulse's time axis lies in space, when the input file carries it (LAS waveform
/// packets, PulseWaves): the point at the pulse's reference time t0 and the distance travelled
/// per nanosecond along the beam, in the file's coordinate reference system.
///
/// A sample at time `t` ns after t0 (see [`Segment::start_ns`]) lies at
/// `anchor + t · direction`. Pulses that carry it skip the navigation path and go straight to
/// georeferencing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PulseGeometry {
    /// Position at the reference time t0 `[x, y, z]`, in the file's CRS units (metres, or degrees
    /// for geographic x/y with metres in z).
    pub anchor: [f64; 3],
    /// Displacement per nanosecond of the time axis `[dx, dy, dz]`, CRS units per ns (for a
    /// two-way range measurement this is half the speed of light in air along the beam).
    pub direction: [f64; 3],
}

impl PulseGeometry {
    /// Position `[x, y, z]` at `t_ns` ns on the pulse's time axis: `anchor + t_ns × direction`.
    pub fn at(&self, t_ns: f64) -> [f64; 3] {
        [
            self.anchor[0] + t_ns * self.direction[0],
            self.anchor[1] + t_ns * self.direction[1],
            self.anchor[2] + t_ns * self.direction[2],
        ]
    }
}

/// How to turn any bin of a pulse's [`Pulse::signal`] (volts) into calibrated backscatter,
/// attached to the pulse by the `calibrate` stage (`src/signal/calibrate.rs`; the formula, its
/// assumptions and units in `docs/calibration.md`). The signal itself stays in volts.
///
/// The calibrated value of a bin at time `t_ns` (ns after the pulse's t0, as
/// [`Segment::start_ns`]) holding `v` volts is `v × factor_at(t_ns)`, with
///
/// `factor_at(t) = scale × (R(t) / reference_range_m)²`, `R(t) = (t − emission_ns) ×
/// metres_per_ns`
///
/// when `range_normalised`, else `scale` for every bin. `scale` gathers the factors common to
/// every bin of the shot: the system constant divided by the shot's relative outgoing energy.
/// A bin at or before the emission (`R ≤ 0`) has no calibrated value: NaN.
///
/// A few flops per bin and no branch on data but the emission test: cheap enough to call for
/// every bin of every pulse.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Calibration {
    /// Factor common to every bin: `C / (E_out / E_ref)` with the factors switched off left
    /// out, in calibrated units per volt (`docs/calibration.md`).
    pub scale: f32,
    /// Time of emission on the pulse's time axis, ns after t0 (the outgoing pulse's peak, or 0
    /// when the input times from emission). Meaningless when `range_normalised` is false.
    pub emission_ns: f64,
    /// Metres of range per nanosecond of two-way travel time, `c / (2 n)`.
    pub metres_per_ns: f64,
    /// Range at which the range factor is 1, metres.
    pub reference_range_m: f64,
    /// Whether the `(R / R_ref)²` factor applies (false: range switched off, or the range of the
    /// pulse is unknown and the stage's policy passed it unscaled).
    pub range_normalised: bool,
}

impl Calibration {
    /// The calibration factor of a bin `t_ns` after the pulse's t0: calibrated units per volt;
    /// NaN at or before the emission when the range factor applies.
    #[inline]
    pub fn factor_at(&self, t_ns: f64) -> f32 {
        if !self.range_normalised {
            return self.scale;
        }
        let q = (t_ns - self.emission_ns) * (self.metres_per_ns / self.reference_range_m);
        if q > 0.0 {
            self.scale * (q * q) as f32
        } else {
            f32::NAN
        }
    }

    /// Calibrated backscatter of `value_v` volts at `t_ns` after t0.
    #[inline]
    pub fn calibrated(&self, value_v: f32, t_ns: f64) -> f32 {
        value_v * self.factor_at(t_ns)
    }

    /// Range of a bin `t_ns` after t0, metres (negative before the emission; meaningless when
    /// `range_normalised` is false).
    #[inline]
    pub fn range_m(&self, t_ns: f64) -> f64 {
        (t_ns - self.emission_ns) * self.metres_per_ns
    }
}

/// One laser shot and everything the chain has learnt about it so far.
#[derive(Clone, Debug)]
pub struct Pulse {
    /// Order of arrival assigned by the source (0, 1, 2, ...); used to restore order after
    /// parallel workers.
    pub seq: u64,
    /// Pulse identifier as the digitizer numbered it.
    pub pulse_id: u64,
    /// Time of emission, GPS seconds (the capture header states the time base).
    pub gps_time: f64,
    /// Scan angles in degrees: primary (mirror) and secondary (NaN when the scanner has one axis).
    pub scan_angle_deg: [f32; 2],
    /// Sample interval, nanoseconds.
    pub sample_ns: f64,
    /// Digitizer gain: volts per count (volts = offset + gain * counts).
    pub gain_v_per_dn: f32,
    /// Digitizer offset, volts.
    pub offset_v: f32,
    /// Bits per sample as digitized: 8 or 16.
    pub bits: u8,
    /// Anchor and direction of the time axis, when the input carries them (`None` for digitizer
    /// frames, which are georeferenced from navigation).
    pub geometry: Option<PulseGeometry>,
    /// Segments (outgoing and returns) in recording order.
    pub segments: Vec<Segment>,
    /// Raw digitizer counts of every segment, concatenated.
    pub raw: Vec<u16>,
    /// Processed signal, same layout as `raw`; volts after denoise, filled by the stages.
    pub signal: Vec<f32>,
    /// Noise figures from the denoise stage.
    pub noise: NoiseEstimate,
    /// Noise as the input file states it (GEDI), `None` for inputs that do not.
    pub stated_noise: Option<StatedNoise>,
    /// Returns found by the decomposition stage (empty before it).
    pub returns: Vec<FittedReturn>,
    /// Forest structure metrics from the `metrics` stage (`None` before it).
    pub metrics: Option<WaveformMetrics>,
    /// How to turn the signal's volts into calibrated backscatter, from the `calibrate` stage
    /// (`None` before it, or when it did not run).
    pub calibration: Option<Calibration>,
    /// Marked by the pipeline's source for the QC page's waveform viewer (live runs only, about
    /// four pulses a second; `pipeline::runner`): the pulse the viewer will show. Work that only
    /// the viewer uses is done for these alone (a `decompose` stage with `pulses =
    /// "qc_sampled"`). False otherwise, and always in replay.
    pub qc_sample: bool,
    /// When the pulse entered the process (for latency measurement).
    pub arrived: Instant,
}

impl Default for Pulse {
    fn default() -> Self {
        Pulse {
            seq: 0,
            pulse_id: 0,
            gps_time: 0.0,
            scan_angle_deg: [0.0, f32::NAN],
            sample_ns: 1.0,
            gain_v_per_dn: 1.0,
            offset_v: 0.0,
            bits: 16,
            geometry: None,
            segments: Vec::with_capacity(4),
            raw: Vec::new(),
            signal: Vec::new(),
            noise: NoiseEstimate::default(),
            stated_noise: None,
            returns: Vec::new(),
            metrics: None,
            calibration: None,
            qc_sample: false,
            arrived: Instant::now(),
        }
    }
}

impl Pulse {
    /// Makes `self` a copy of `other`, reusing `self`'s buffers (no allocation once they are
    /// large enough).
    pub fn copy_from(&mut self, other: &Pulse) {
        self.seq = other.seq;
        self.pulse_id = other.pulse_id;
        self.gps_time = other.gps_time;
        self.scan_angle_deg = other.scan_angle_deg;
        self.sample_ns = other.sample_ns;
        self.gain_v_per_dn = other.gain_v_per_dn;
        self.offset_v = other.offset_v;
        self.bits = other.bits;
        self.geometry = other.geometry;
        self.segments.clone_from(&other.segments);
        self.raw.clone_from(&other.raw);
        self.signal.clone_from(&other.signal);
        self.noise = other.noise;
        self.stated_noise = other.stated_noise;
        self.returns.clone_from(&other.returns);
        self.metrics = other.metrics;
        self.calibration = other.calibration;
        self.qc_sample = other.qc_sample;
        self.arrived = other.arrived;
    }

    /// Clears the pulse for reuse, keeping the buffers' capacity.
    pub fn reset(&mut self) {
        self.seq = 0;
        self.pulse_id = 0;
        self.gps_time = 0.0;
        self.scan_angle_deg = [0.0, f32::NAN];
        self.sample_ns = 1.0;
        self.gain_v_per_dn = 1.0;
        self.offset_v = 0.0;
        self.bits = 16;
        self.geometry = None;
        self.segments.clear();
        self.raw.clear();
        self.signal.clear();
        self.noise = NoiseEstimate::default();
        self.stated_noise = None;
        self.returns.clear();
        self.metrics = None;
        self.calibration = None;
        self.qc_sample = false;
        self.arrived = Instant::now();
    }

    /// Appends a segment whose raw samples are `samples`; returns its index.
    pub fn push_segment(
        &mut self,
        kind: SegmentKind,
        channel: u8,
        start_ns: f64,
        samples: impl IntoIterator<Item = u16>,
    ) -> usize {
        let first = self.raw.len();
        self.raw.extend(samples);
        let len = self.raw.len() - first;
        self.segments.push(Segment {
            kind,
            channel,
            start_ns,
            first: first as u32,
            len: len as u32,
        });
        self.segments.len() - 1
    }

    /// Raw counts of segment `i`.
    pub fn raw_of(&self, i: usize) -> &[u16] {
        &self.raw[self.segments[i].range()]
    }

    /// Processed signal of segment `i` (empty before a stage has filled `signal`).
    pub fn signal_of(&self, i: usize) -> &[f32] {
        let r = self.segments[i].range();
        self.signal.get(r).unwrap_or(&[])
    }

    /// Index of the first outgoing segment, if the pulse recorded one.
    pub fn outgoing(&self) -> Option<usize> {
        self.segments
            .iter()
            .position(|s| s.kind == SegmentKind::Outgoing)
    }

    /// Converts raw counts to volts with the pulse's digitizer gain and offset.
    pub fn counts_to_volts(&self, counts: u16) -> f32 {
        self.offset_v + self.gain_v_per_dn * counts as f32
    }

    /// The digitizer's full scale, counts: `2^bits − 1` (a sample there is clipped: the
    /// receiver saturated); `None` for a bit depth outside 1..=16.
    pub fn full_scale_dn(&self) -> Option<u16> {
        (1..=16)
            .contains(&self.bits)
            .then(|| ((1u32 << self.bits) - 1) as u16)
    }
}

/// A bounded free list of pulses shared by sources (which take) and by stages and sinks (which
/// give back). After warm-up every pulse is a recycled one: the hot path does not allocate.
#[derive(Clone)]
pub struct PulsePool {
    free_tx: Sender<Box<Pulse>>,
    free_rx: Receiver<Box<Pulse>>,
    allocated: Arc<AtomicU64>,
}

impl PulsePool {
    /// A pool that keeps at most `capacity` idle pulses.
    pub fn new(capacity: usize) -> Self {
        let (free_tx, free_rx) = bounded(capacity.max(1));
        PulsePool {
            free_tx,
            free_rx,
            allocated: Arc::new(AtomicU64::new(0)),
        }
    }

    /// A cleared pulse: a recycled one when available, otherwise a new allocation (counted).
    pub fn take(&self) -> Box<Pulse> {
        match self.free_rx.try_recv() {
            Ok(mut p) => {
                p.reset();
                p
            }
            Err(_) => {
                self.allocated.fetch_add(1, Ordering::Relaxed);
                Box::default()
            }
        }
    }

    /// Returns a pulse to the pool; if the pool is full the pulse is freed.
    pub fn give(&self, pulse: Box<Pulse>) {
        match self.free_tx.try_send(pulse) {
            Ok(()) | Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {}
        }
    }

    /// How many pulses this pool has allocated in total (a bound on memory; flat after warm-up).
    pub fn allocated(&self) -> u64 {
        self.allocated.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segments_share_flat_buffers() {
        let mut p = Pulse::default();
        let o = p.push_segment(SegmentKind::Outgoing, 0, -5.0, [1, 2, 3]);
        let r = p.push_segment(SegmentKind::Return, 1, 900.0, [7, 8]);
        assert_eq!(p.raw_of(o), &[1, 2, 3]);
        assert_eq!(p.raw_of(r), &[7, 8]);
        assert_eq!(p.outgoing(), Some(0));
        assert!(p.signal_of(r).is_empty());
    }

    #[test]
    fn full_scale_follows_the_bit_depth() {
        let at = |bits| {
            Pulse {
                bits,
                ..Default::default()
            }
            .full_scale_dn()
        };
        assert_eq!(at(8), Some(255));
        assert_eq!(at(12), Some(4095));
        assert_eq!(at(16), Some(u16::MAX));
        assert_eq!(at(0), None);
        assert_eq!(at(17), None);
    }

    #[test]
    fn pool_recycles_instead_of_allocating() {
        let pool = PulsePool::new(4);
        for _ in 0..100 {
            let mut p = pool.take();
            p.push_segment(SegmentKind::Return, 0, 0.0, [1, 2, 3]);
            pool.give(p);
        }
        assert_eq!(pool.allocated(), 1);
        let p = pool.take();
        assert!(p.raw.is_empty() && p.segments.is_empty());
        assert!(p.raw.capacity() >= 3, "buffer capacity is kept");
    }
}

/// Applying a per-pulse method to owned pulses in unit tests, as a stage would (the methods'
/// own tests, below the runtime: `pipeline::testing::run_stage` runs a whole stage).
#[cfg(test)]
pub(crate) mod testing {
    use super::{Pulse, Verdict};

    /// Counts by reason.
    #[derive(Debug, Default)]
    pub struct Counts(Vec<(&'static str, u64)>);

    impl Counts {
        fn add(&mut self, reason: &'static str) {
            match self.0.iter_mut().find(|(r, _)| *r == reason) {
                Some((_, n)) => *n += 1,
                None => self.0.push((reason, 1)),
            }
        }

        /// The count of one reason.
        pub fn get(&self, reason: &str) -> u64 {
            self.0
                .iter()
                .find(|(r, _)| *r == reason)
                .map_or(0, |(_, n)| *n)
        }
    }

    /// What a method made of the pulses it was given.
    #[derive(Debug, Default)]
    pub struct Applied {
        /// Pulses kept, in order.
        pub emitted: Vec<Box<Pulse>>,
        /// Pulses dropped or rejected, by reason.
        pub dropped: Counts,
        /// Pulses rejected.
        pub errors: u64,
        /// Notes of the pulses kept, by note.
        pub notes: Counts,
    }

    /// A pulse as a digitizer frame carries it: pulse `id` at GPS time `345 600 + id · 2e-5` s,
    /// an 8-sample outgoing segment and an `n_return`-sample return at 6.6 µs, 8-bit counts
    /// (the live stream's and the player's tests).
    pub fn framed_pulse(id: u64, n_return: u32) -> Pulse {
        use super::{Segment, SegmentKind};
        Pulse {
            pulse_id: id,
            gps_time: 345_600.0 + id as f64 * 2e-5,
            scan_angle_deg: [1.5, -0.25],
            sample_ns: 1.0,
            gain_v_per_dn: 0.01,
            bits: 8,
            raw: (0..8 + n_return).map(|i| (i * 7 % 251) as u16).collect(),
            segments: vec![
                Segment {
                    kind: SegmentKind::Outgoing,
                    channel: 0,
                    start_ns: 0.0,
                    first: 0,
                    len: 8,
                },
                Segment {
                    kind: SegmentKind::Return,
                    channel: 0,
                    start_ns: 6600.0,
                    first: 8,
                    len: n_return,
                },
            ],
            ..Pulse::default()
        }
    }

    /// Applies `method` to each pulse and sorts them by its [`Verdict`].
    pub fn apply(
        pulses: impl IntoIterator<Item = Pulse>,
        mut method: impl FnMut(&mut Pulse) -> Verdict,
    ) -> Applied {
        let mut out = Applied::default();
        for (seq, mut p) in pulses.into_iter().enumerate() {
            p.seq = seq as u64;
            match method(&mut p) {
                Verdict::Keep(notes) => {
                    for n in notes.into_iter().flatten() {
                        out.notes.add(n);
                    }
                    out.emitted.push(Box::new(p));
                }
                Verdict::Drop(r) => out.dropped.add(r),
                Verdict::Reject(r) => {
                    out.errors += 1;
                    out.dropped.add(r);
                }
            }
        }
        out
    }
}
