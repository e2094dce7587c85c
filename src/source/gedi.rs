//! NASA GEDI Level 1B granules (HDF5, [`crate::format::gedi`]) as a [`Source`]: every shot of
//! every beam (beams in name order, shots in file order) becomes one pulse.
//!
//! The mapping (`docs/formats.md`, "GEDI"):
//!
//! - `pulse_id` = `shot_number`;
//! - `gps_time` = `master_time_epoch` + `delta_time` − 10⁹: GPS adjusted standard time (the
//!   LAS convention). The fixture's epoch is 1 198 800 018 GPS s = 2018-01-01T00:00:00 UTC
//!   (13 875 days after the GPS epoch, plus the 18 leap seconds of 2018), [`GEDI_EPOCH_GPS_S`];
//!   the file's own value is used.
//! - samples: GEDI stores `f32` counts (baseline ≈ 200-250, peaks up to ≈ 1400 in the
//!   transmitted pulse). They become `u16` raw counts `round(v × 32)`
//!   ([`COUNTS_SCALE`]) with `gain_v_per_dn` = 1/32, `offset_v` = 0, `bits` = 16, so the signal
//!   after the usual `offset + gain × raw` is in GEDI counts again, to 1/64 count. Values
//!   outside `[0, 65535/32]` (and NaN) are clamped and counted (`clamped_samples`).
//! - segments, 1 ns apart (`sample_ns` = 1: GEDI's digitizer runs at 1 GHz; the geolocation
//!   agrees, bin 0 to the last bin is [`METRES_PER_NS`] per sample on the fixture, c/2 in air):
//!   the return `rxwaveform` starts at t0 = bin 0 (`start_ns` = 0); the outgoing `txwaveform`
//!   (128 samples) is placed so that its highest sample lies at the emission,
//!   `−2 × bounce_time_offset_bin0` (the two-way light time to bin 0, ≈ −2.75 ms), so that
//!   the `calibrate` stage's range from the outgoing peak is the true slant range (≈ 413 km)
//!   and a footprint from the beam divergence is right. Without a usable bounce time the
//!   outgoing segment ends at t0 (`start_ns` = −tx samples), counted `tx_time_unknown`. t0 is
//!   bin 0, not the emission: `t0_is_emission` = false.
//! - geometry: the anchor is bin 0 (longitude, latitude, elevation above the WGS84 ellipsoid)
//!   projected to the WGS84 UTM zone of the file's first located shot, the height kept
//!   ellipsoidal; the direction is (last bin − bin 0) / (samples − 1) in those coordinates, so
//!   the first and last samples land exactly where GEDI geolocated them. A shot with fewer than
//!   two samples points along its `local_beam_azimuth` / `local_beam_elevation` (the vector
//!   towards the instrument, reversed) at [`METRES_PER_NS`].
//! - `stated_noise` = `noise_mean_corrected`, `noise_stddev_corrected` (GEDI counts, which are
//!   the signal units here).
//! - `scan_angle_deg[0]` = the off-nadir angle, 90° − `local_beam_elevation` (0.8-1.3° on the fixture).
//!
//! Shots skipped (counted by reason in the report): stale (`stale_return_flag`: the return is
//! not this shot's — skipped by default, [`GediOptions::keep_stale`]), no received samples,
//! more than [`MAX_SEGMENT_SAMPLES`] samples, geolocation that does not project. Degraded shots
//! (`degrade` flag) pass and are counted.
//!
//! Reading: one beam's records at a time (a few tens of MB for a full beam), the waveforms in
//! blocks of up to [`BLOCK_SHOTS`] shots (one hyperslab per array, at most
//! [`MAX_BLOCK_SAMPLES`] samples), into buffers reused from block to block; nothing is
//! allocated per pulse once the pool is warm.

use crate::source::report::{InputReport, SourceReport};
use std::path::{Path, PathBuf};

use crate::core::facts::SourceFacts;
use crate::core::sensor::SensorProfile;
use crate::format::gedi::{GediBeam, GediError, GediL1b, GediShot};
use crate::geo::crs::OutputCrs;
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::{Pulse, PulseGeometry, PulsePool, SegmentKind, StatedNoise};

/// Raw counts per GEDI count: GEDI's `f32` samples are stored as `round(v × 32)` in the pulse's
/// `u16` raw buffer. 1/32 count resolves the L1B values far below their noise (σ ≈ 3 counts)
/// while the largest value kept, 65535/32 ≈ 2048 counts, is twice the 10-bit digitizer's range
/// plus GEDI's baseline (the fixture's largest sample is 1408).
pub const COUNTS_SCALE: f32 = 32.0;

/// The GEDI epoch of `delta_time`, GPS seconds: 2018-01-01T00:00:00 UTC (what the fixture's
/// `ancillary/master_time_epoch` holds; the reader uses the file's value).
pub const GEDI_EPOCH_GPS_S: f64 = 1_198_800_018.0;

/// GPS adjusted standard time = GPS seconds − 10⁹.
const ADJUSTED_STANDARD_OFFSET_S: f64 = 1e9;

/// Shots per waveform read.
pub const BLOCK_SHOTS: usize = 1024;

/// Most samples of one array read at once (a block ends earlier if its shots span more).
pub const MAX_BLOCK_SAMPLES: u64 = 1 << 22;

/// Longest received or transmitted waveform accepted, samples (GEDI records ≈ 700-1400
/// received and 128 transmitted); longer shots are skipped as `too_long`.
pub const MAX_SEGMENT_SAMPLES: u32 = 1 << 16;

/// Metres along the beam per nanosecond of the time axis, for shots whose own geolocation
/// cannot give it (fewer than two samples): c / (2 n) with the refractive index n = 1.000 24
/// that the fixture's bin 0 to last bin geolocation measures (0.149 86 m/ns).
pub const METRES_PER_NS: f64 = crate::core::units::half_c_in_m_per_ns(1.000_24);

/// GEDI's outgoing pulse width used in the sensor profile, ns: the median full width at half
/// maximum of the fixture's 32 transmitted waveforms, 14.9 ns (coverage beam 0001: 15.8-18.8,
/// median 17.0; power beam 1011: 12.7-14.0, median 13.3). gedi.umd.edu states "14 ns".
pub const PULSE_FWHM_NS: f64 = 14.9;

/// What the source does with some shots.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GediOptions {
    /// Pass stale shots (`stale_return_flag` set: the received waveform belongs to an earlier
    /// shot) instead of skipping them. Default false.
    pub keep_stale: bool,
}

/// The sensor profile of GEDI. Sources: gedi.umd.edu/instrument/specifications (1064 nm
/// Nd:YAG, 242 pulses per second, 14 ns pulses, "a beam divergence of 56 mrad, resulting in
/// footprints averaging 25 m in diameter" — the unit must be µrad: 25 m from the ISS's ≈ 413 km
/// slant range is 0.06 mrad); the pulse width as measured here ([`PULSE_FWHM_NS`]); 1 ns
/// samples; 16 bits and 1/32 per count after this source's scaling ([`COUNTS_SCALE`]).
pub fn gedi_sensor() -> SensorProfile {
    SensorProfile {
        name: "NASA GEDI (ISS), Level 1B waveforms".into(),
        wavelength_nm: 1064.0,
        pulse_fwhm_ns: PULSE_FWHM_NS,
        pulse_rate_hz: 242.0,
        beam_divergence_mrad: 0.056,
        sample_interval_ns: 1.0,
        bits_per_sample: 16,
        digitizer_gain_v_per_dn: 1.0 / f64::from(COUNTS_SCALE),
        digitizer_offset_v: 0.0,
        noise_level_dn: None,
        nominal_altitude_m: Some(413_000.0),
        max_scan_angle_deg: Some(6.0),
        lever_arm_m: [0.0; 3],
        boresight_deg: [0.0; 3],
        calibration_constant: 1.0,
    }
}

/// A GEDI source's report (`summary.json` → `source`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct GediReport {
    /// The granule.
    pub file: String,
    /// What it is.
    pub product: &'static str,
    /// The output CRS (`EPSG:<code>`).
    pub crs: String,
    /// The granule's time epoch, GPS seconds.
    pub time_epoch_gps_s: f64,
    /// Shots in the granule.
    pub shots: u64,
    /// Shots read (handed out or skipped).
    pub shots_read: u64,
    /// Pulses handed out.
    pub pulses: u64,
    /// Shots skipped: stale return.
    pub skipped_stale: u64,
    /// Shots skipped: no received samples.
    pub skipped_no_samples: u64,
    /// Shots skipped: too many samples.
    pub skipped_too_long: u64,
    /// Shots skipped: geolocation that does not project.
    pub skipped_bad_geolocation: u64,
    /// Degraded shots passed.
    pub degraded: u64,
    /// Samples clamped to the counts' range.
    pub clamped_samples: u64,
    /// Shots without a usable bounce time.
    pub tx_time_unknown: u64,
    /// Mean noise level, counts.
    pub noise_mean_counts: Option<f64>,
    /// Mean noise σ, counts.
    pub noise_stddev_counts: Option<f64>,
    /// Mean outgoing FWHM, ns.
    pub tx_fwhm_ns: Option<f64>,
    /// Per beam.
    pub beams: Vec<BeamStats>,
    /// Ranges of what was read.
    pub extent: GediExtent,
    /// The error that ended reading, if any.
    pub error: Option<String>,
}

/// The ranges (smallest, largest) of the shots handed out; `None` before the first.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct GediExtent {
    /// GPS time, s.
    pub gps_time: Option<[f64; 2]>,
    /// Longitude, degrees.
    pub longitude_deg: Option<[f64; 2]>,
    /// Latitude, degrees.
    pub latitude_deg: Option<[f64; 2]>,
    /// Easting in the output CRS, m.
    pub x_m: Option<[f64; 2]>,
    /// Northing in the output CRS, m.
    pub y_m: Option<[f64; 2]>,
    /// Elevation of bin 0, m.
    pub elevation_m: Option<[f64; 2]>,
    /// Received samples per shot.
    pub rx_samples: Option<[u64; 2]>,
    /// Noise σ, counts.
    pub noise_stddev_counts: Option<[f64; 2]>,
    /// Outgoing FWHM, ns.
    pub tx_fwhm_ns: Option<[f64; 2]>,
}

/// Counts of one beam.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct BeamStats {
    /// The beam's name (`BEAM0101`).
    pub name: String,
    /// Shots in the beam.
    pub shots: u64,
    /// Pulses handed out.
    pub pulses: u64,
    /// Skipped: stale return.
    pub stale: u64,
    /// Skipped: no received samples.
    pub no_samples: u64,
    /// Skipped: too many samples.
    pub too_long: u64,
    /// Skipped: geolocation that does not project.
    pub bad_geolocation: u64,
    /// Degraded, passed.
    pub degraded: u64,
}

/// Running figures over the pulses handed out (no allocation).
#[derive(Clone, Copy, Debug)]
struct Running {
    gps_time: [f64; 2],
    lon: [f64; 2],
    lat: [f64; 2],
    x: [f64; 2],
    y: [f64; 2],
    elevation: [f64; 2],
    rx_samples: [u64; 2],
    noise_mean_sum: f64,
    noise_stddev_sum: f64,
    noise_stddev: [f64; 2],
    noise_n: u64,
    tx_fwhm_sum: f64,
    tx_fwhm: [f64; 2],
    tx_fwhm_n: u64,
}

impl Default for Running {
    fn default() -> Self {
        let e = [f64::INFINITY, f64::NEG_INFINITY];
        Running {
            gps_time: e,
            lon: e,
            lat: e,
            x: e,
            y: e,
            elevation: e,
            rx_samples: [u64::MAX, 0],
            noise_mean_sum: 0.0,
            noise_stddev_sum: 0.0,
            noise_stddev: e,
            noise_n: 0,
            tx_fwhm_sum: 0.0,
            tx_fwhm: e,
            tx_fwhm_n: 0,
        }
    }
}

fn widen(r: &mut [f64; 2], v: f64) {
    if v.is_finite() {
        r[0] = r[0].min(v);
        r[1] = r[1].max(v);
    }
}

fn range(r: [f64; 2]) -> Option<[f64; 2]> {
    (r[0] <= r[1]).then_some(r)
}

/// Reads a GEDI L1B granule as a [`Source`].
pub struct GediSource {
    l1b: GediL1b,
    path: PathBuf,
    options: GediOptions,
    epoch_gps_s: f64,
    crs: OutputCrs,
    /// Index of the next beam to load.
    next_beam: usize,
    /// The beam being read.
    beam: Option<GediBeam>,
    /// Its index in `stats`.
    beam_index: usize,
    /// Next shot of `beam` to hand out, and the end of the block read.
    cursor: usize,
    block_end: usize,
    /// First rx / tx sample (0-based, in the beam's flat arrays) of the block read.
    rx_base: u64,
    tx_base: u64,
    rx: Vec<f32>,
    tx: Vec<f32>,
    stats: Vec<BeamStats>,
    total_shots: u64,
    shots_read: u64,
    clamped_samples: u64,
    tx_time_unknown: u64,
    running: Running,
    failed: Option<String>,
}

impl GediSource {
    /// Opens `path` with the default options (stale shots skipped).
    pub fn open(path: &Path) -> Result<Self, GediError> {
        Self::open_with(path, GediOptions::default())
    }

    /// Opens `path`: checks that it is a Level 1B granule, reads the epoch, counts the shots of
    /// every beam and chooses the UTM zone from the first located shot.
    pub fn open_with(path: &Path, options: GediOptions) -> Result<Self, GediError> {
        let l1b = GediL1b::open(path)?;
        Self::from_l1b(l1b, options)
    }

    /// A source over an opened granule (e.g. [`GediL1b::from_bytes`] for fuzzing).
    pub fn from_l1b(l1b: GediL1b, options: GediOptions) -> Result<Self, GediError> {
        l1b.check_level1b()?;
        let name = l1b.path().display().to_string();
        let epoch_gps_s = l1b.time_epoch_gps_s()?;
        if !epoch_gps_s.is_finite() {
            return Err(GediError::Dataset {
                file: name,
                dataset: format!("{}/ancillary/master_time_epoch", l1b.beams()[0]),
                reason: format!("not a time: {epoch_gps_s}"),
            });
        }
        let mut stats = Vec::with_capacity(l1b.beams().len());
        let mut total_shots = 0;
        for beam in l1b.beams() {
            let shots = l1b.shot_count(beam)?;
            total_shots += shots;
            stats.push(BeamStats {
                name: beam.clone(),
                shots,
                ..Default::default()
            });
        }
        let crs = first_zone(&l1b)?.ok_or_else(|| GediError::Dataset {
            file: name.clone(),
            dataset: "BEAMxxxx/geolocation/latitude_bin0".into(),
            reason: "no shot has a usable bin 0 position (to choose the UTM zone)".into(),
        })?;
        let crs = OutputCrs::utm_at(crs[1], crs[0]).map_err(|e| GediError::Dataset {
            file: name.clone(),
            dataset: "BEAMxxxx/geolocation/latitude_bin0".into(),
            reason: format!("no UTM zone: {e}"),
        })?;
        tracing::info!(
            file = %name,
            beams = l1b.beams().len(),
            shots = total_shots,
            crs = %format!("EPSG:{}", crs.epsg()),
            "GEDI L1B input"
        );
        Ok(GediSource {
            path: l1b.path().to_path_buf(),
            l1b,
            options,
            epoch_gps_s,
            crs,
            next_beam: 0,
            beam: None,
            beam_index: 0,
            cursor: 0,
            block_end: 0,
            rx_base: 0,
            tx_base: 0,
            rx: Vec::new(),
            tx: Vec::new(),
            stats,
            total_shots,
            shots_read: 0,
            clamped_samples: 0,
            tx_time_unknown: 0,
            running: Running::default(),
            failed: None,
        })
    }

    /// The output CRS's EPSG code (the UTM zone of the first located shot).
    pub fn epsg(&self) -> u32 {
        self.crs.epsg()
    }

    /// The granule underneath.
    pub fn granule(&self) -> &GediL1b {
        &self.l1b
    }

    /// Makes `cursor..block_end` a block of shots whose waveforms are in `rx`/`tx`; loads the
    /// next beam when this one is done. `Ok(false)` at the end of the file.
    fn load_block(&mut self) -> Result<bool, GediError> {
        loop {
            let Some(beam) = &self.beam else {
                if self.next_beam >= self.l1b.beams().len() {
                    return Ok(false);
                }
                let name = self.l1b.beams()[self.next_beam].clone();
                self.beam = Some(self.l1b.read_beam(&name)?);
                self.beam_index = self.next_beam;
                self.next_beam += 1;
                self.cursor = 0;
                self.block_end = 0;
                continue;
            };
            let shots = &beam.shots;
            // Shots too long to read are skipped before forming the block.
            while let Some(s) = shots.get(self.cursor) {
                if !too_long(s) {
                    break;
                }
                self.stats[self.beam_index].too_long += 1;
                self.shots_read += 1;
                self.cursor += 1;
            }
            if self.cursor >= shots.len() {
                self.beam = None;
                continue;
            }
            let start = self.cursor;
            let (mut rx_lo, mut rx_hi) = (u64::MAX, 0u64);
            let (mut tx_lo, mut tx_hi) = (u64::MAX, 0u64);
            let mut end = start;
            while end < shots.len() && end - start < BLOCK_SHOTS {
                let s = &shots[end];
                if too_long(s) {
                    break;
                }
                let (rl, rh) = (
                    rx_lo.min(s.rx_start),
                    rx_hi.max(s.rx_start + u64::from(s.rx_count)),
                );
                let (tl, th) = (
                    tx_lo.min(s.tx_start),
                    tx_hi.max(s.tx_start + u64::from(s.tx_count)),
                );
                if end > start && (rh - rl > MAX_BLOCK_SAMPLES || th - tl > MAX_BLOCK_SAMPLES) {
                    break;
                }
                (rx_lo, rx_hi, tx_lo, tx_hi) = (rl, rh, tl, th);
                end += 1;
            }
            self.l1b
                .read_waveforms(beam, start..end, &mut self.rx, &mut self.tx)?;
            self.rx_base = rx_lo;
            self.tx_base = tx_lo;
            self.block_end = end;
            return Ok(true);
        }
    }

    /// Fills `pulse` from shot `i` of the current beam; `false` when its geolocation does not
    /// project (counted by the caller).
    fn fill(&mut self, pulse: &mut Pulse, i: usize) -> bool {
        let Some(beam) = &self.beam else {
            return false;
        };
        let s = &beam.shots[i];
        let (lon0, lat0, h0) = (s.bin0[0], s.bin0[1], s.bin0[2]);
        let (lon1, lat1, h1) = (s.lastbin[0], s.lastbin[1], s.lastbin[2]);
        if !located(s) {
            return false;
        }
        let Ok([a, b]) = self.crs.project_pair([lat0, lon0, h0], [lat1, lon1, h1]) else {
            return false;
        };
        if !(a.iter().chain(b.iter()).all(|v| v.is_finite())) {
            return false;
        }
        let direction = if s.rx_count >= 2 {
            let k = 1.0 / f64::from(s.rx_count - 1);
            [(b[0] - a[0]) * k, (b[1] - a[1]) * k, (b[2] - a[2]) * k]
        } else {
            // The local beam vector points from the footprint to the instrument.
            let (az, el) = (s.beam_azimuth_rad, s.beam_elevation_rad);
            let v = [
                -el.cos() * az.sin() * METRES_PER_NS,
                -el.cos() * az.cos() * METRES_PER_NS,
                -el.sin() * METRES_PER_NS,
            ];
            if !v.iter().all(|x| x.is_finite()) {
                return false;
            }
            v
        };
        let rx_off = (s.rx_start - self.rx_base) as usize;
        let tx_off = (s.tx_start - self.tx_base) as usize;
        let (Some(rx), Some(tx)) = (
            self.rx.get(rx_off..rx_off + s.rx_count as usize),
            self.tx.get(tx_off..tx_off + s.tx_count as usize),
        ) else {
            return false;
        };

        pulse.pulse_id = s.shot_number;
        pulse.gps_time = self.epoch_gps_s + s.delta_time_s - ADJUSTED_STANDARD_OFFSET_S;
        let off_nadir = 90.0 - s.beam_elevation_rad.to_degrees();
        pulse.scan_angle_deg = [off_nadir as f32, f32::NAN];
        pulse.sample_ns = 1.0;
        pulse.gain_v_per_dn = 1.0 / COUNTS_SCALE;
        pulse.offset_v = 0.0;
        pulse.bits = 16;
        pulse.geometry = Some(PulseGeometry {
            anchor: a,
            direction,
        });
        let mut clamped = 0u64;
        if !tx.is_empty() {
            let peak = tx
                .iter()
                .enumerate()
                .fold((0usize, f32::NEG_INFINITY), |best, (k, &v)| {
                    if v > best.1 { (k, v) } else { best }
                })
                .0;
            let bounce = s.bounce_time_bin0_s;
            let start_ns = if bounce.is_finite() && bounce > 0.0 && bounce < 0.1 {
                -2.0 * bounce * 1e9 - peak as f64
            } else {
                self.tx_time_unknown += 1;
                -f64::from(s.tx_count)
            };
            pulse.push_segment(
                SegmentKind::Outgoing,
                0,
                start_ns,
                tx.iter().map(|&v| quantise(v, &mut clamped)),
            );
            if let Some(w) = fwhm_ns(tx) {
                let r = &mut self.running;
                r.tx_fwhm_sum += w;
                r.tx_fwhm_n += 1;
                widen(&mut r.tx_fwhm, w);
            }
        }
        pulse.push_segment(
            SegmentKind::Return,
            0,
            0.0,
            rx.iter().map(|&v| quantise(v, &mut clamped)),
        );
        self.clamped_samples += clamped;
        pulse.stated_noise =
            (s.noise_mean.is_finite() && s.noise_stddev.is_finite() && s.noise_stddev >= 0.0)
                .then_some(StatedNoise {
                    mean: s.noise_mean as f32,
                    stddev: s.noise_stddev as f32,
                });

        let r = &mut self.running;
        widen(&mut r.gps_time, pulse.gps_time);
        widen(&mut r.lon, lon0);
        widen(&mut r.lat, lat0);
        widen(&mut r.x, a[0]);
        widen(&mut r.y, a[1]);
        widen(&mut r.elevation, h0);
        widen(&mut r.elevation, h1);
        r.rx_samples[0] = r.rx_samples[0].min(u64::from(s.rx_count));
        r.rx_samples[1] = r.rx_samples[1].max(u64::from(s.rx_count));
        if let Some(n) = pulse.stated_noise {
            r.noise_mean_sum += f64::from(n.mean);
            r.noise_stddev_sum += f64::from(n.stddev);
            widen(&mut r.noise_stddev, f64::from(n.stddev));
            r.noise_n += 1;
        }
        true
    }

    fn next_pulse(&mut self, pool: &PulsePool) -> Result<SourceEvent, GediError> {
        loop {
            if self.beam.is_none() || self.cursor >= self.block_end {
                if !self.load_block()? {
                    return Ok(SourceEvent::End);
                }
                continue;
            }
            let i = self.cursor;
            self.cursor += 1;
            self.shots_read += 1;
            let Some(shot) = self.beam.as_ref().and_then(|b| b.shots.get(i)) else {
                continue;
            };
            let (stale, empty, degraded) = (shot.stale, shot.rx_count == 0, shot.degraded);
            let st = &mut self.stats[self.beam_index];
            if stale && !self.options.keep_stale {
                st.stale += 1;
                continue;
            }
            if empty {
                st.no_samples += 1;
                continue;
            }
            let mut pulse = pool.take();
            if self.fill(&mut pulse, i) {
                let st = &mut self.stats[self.beam_index];
                st.pulses += 1;
                st.degraded += u64::from(degraded);
                return Ok(SourceEvent::Pulse(pulse));
            }
            pool.give(pulse);
            self.stats[self.beam_index].bad_geolocation += 1;
        }
    }
}

/// Too long to read as one waveform.
fn too_long(s: &GediShot) -> bool {
    s.rx_count > MAX_SEGMENT_SAMPLES || s.tx_count > MAX_SEGMENT_SAMPLES
}

/// A shot's bin 0 and last bin are positions on Earth.
fn located(s: &GediShot) -> bool {
    let ok = |p: [f64; 3]| {
        p.iter().all(|v| v.is_finite())
            && p[1].abs() <= 90.0
            && p[0].abs() <= 360.0
            && p[2].abs() < 1e5
    };
    ok(s.bin0) && ok(s.lastbin)
}

/// The bin 0 position (lon, lat) of the first located shot of the granule, beam by beam.
fn first_zone(l1b: &GediL1b) -> Result<Option<[f64; 2]>, GediError> {
    for beam in l1b.beams() {
        let b = l1b.read_beam(beam)?;
        if let Some(s) = b.shots.iter().find(|s| located(s)) {
            return Ok(Some([s.bin0[0], s.bin0[1]]));
        }
    }
    Ok(None)
}

/// A GEDI count as raw `u16` (`round(v × 32)`), clamped to `0..=65535` (NaN to 0), counting
/// the clamped samples.
#[inline]
pub fn quantise(v: f32, clamped: &mut u64) -> u16 {
    let r = (v * COUNTS_SCALE).round();
    if (0.0..=65535.0).contains(&r) {
        r as u16
    } else {
        *clamped += 1;
        if r > 65535.0 { 65535 } else { 0 }
    }
}

/// Full width at half maximum of a pulse above the median of its first 8 samples, ns at 1 ns
/// per sample (linear interpolation at the half-maximum crossings); `None` when it has no
/// crossing on both sides of the peak.
pub fn fwhm_ns(x: &[f32]) -> Option<f64> {
    const HEAD: usize = 8;
    if x.len() < HEAD + 3 {
        return None;
    }
    let mut head = [0.0f32; HEAD];
    head.copy_from_slice(&x[..HEAD]);
    head.sort_unstable_by(f32::total_cmp);
    let base = 0.5 * (f64::from(head[HEAD / 2 - 1]) + f64::from(head[HEAD / 2]));
    let (k, peak) =
        x.iter().enumerate().fold(
            (0, f32::NEG_INFINITY),
            |b, (i, &v)| if v > b.1 { (i, v) } else { b },
        );
    let half = base + (f64::from(peak) - base) / 2.0;
    if !(half.is_finite() && f64::from(peak) > base) {
        return None;
    }
    match crate::core::half_max::crossings(x.len(), |i| f64::from(x[i]), k, half) {
        (Ok(left), Ok(right)) => Some(right - left),
        _ => None,
    }
}

impl Source for GediSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        "gedi"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        self.next_pulse(pool).map_err(|e| {
            let msg = e.to_string();
            self.failed = Some(msg.clone());
            SourceError::Fatal(msg)
        })
    }

    /// Shots read (handed out or skipped) of the shots in the file.
    fn progress(&self) -> Option<(u64, u64)> {
        Some((self.shots_read, self.total_shots))
    }

    fn report(&self) -> SourceReport {
        let sum = |f: fn(&BeamStats) -> u64| self.stats.iter().map(f).sum::<u64>();
        let r = &self.running;
        let mean = |s: f64, n: u64| (n > 0).then(|| s / n as f64);
        SourceReport::of(InputReport::Gedi(Box::new(GediReport {
            file: self.path.display().to_string(),
            product: "GEDI Level 1B (geolocated waveforms)",
            crs: format!("EPSG:{}", self.crs.epsg()),
            time_epoch_gps_s: self.epoch_gps_s,
            shots: self.total_shots,
            shots_read: self.shots_read,
            pulses: sum(|b| b.pulses),
            skipped_stale: sum(|b| b.stale),
            skipped_no_samples: sum(|b| b.no_samples),
            skipped_too_long: sum(|b| b.too_long),
            skipped_bad_geolocation: sum(|b| b.bad_geolocation),
            degraded: sum(|b| b.degraded),
            clamped_samples: self.clamped_samples,
            tx_time_unknown: self.tx_time_unknown,
            noise_mean_counts: mean(r.noise_mean_sum, r.noise_n),
            noise_stddev_counts: mean(r.noise_stddev_sum, r.noise_n),
            tx_fwhm_ns: mean(r.tx_fwhm_sum, r.tx_fwhm_n),
            beams: self.stats.clone(),
            extent: GediExtent {
                gps_time: range(r.gps_time),
                longitude_deg: range(r.lon),
                latitude_deg: range(r.lat),
                x_m: range(r.x),
                y_m: range(r.y),
                elevation_m: range(r.elevation),
                rx_samples: (r.rx_samples[0] <= r.rx_samples[1]).then_some(r.rx_samples),
                noise_stddev_counts: range(r.noise_stddev),
                tx_fwhm_ns: range(r.tx_fwhm),
            },
            error: self.failed.clone(),
        })))
    }

    fn facts(&self) -> SourceFacts {
        SourceFacts {
            sensor: Some(gedi_sensor()),
            time_base: Some("gps_adjusted_standard".into()),
            crs: Some(format!("EPSG:{}", self.crs.epsg())),
            // t0 is bin 0, the first received sample.
            t0_is_emission: Some(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> PathBuf {
        crate::fixtures::path("waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5")
    }

    fn all_pulses(src: &mut GediSource) -> Vec<Box<Pulse>> {
        let pool = PulsePool::new(64);
        let mut out = Vec::new();
        loop {
            match src.next(&pool).unwrap() {
                SourceEvent::Pulse(p) => out.push(p),
                SourceEvent::End => return out,
                _ => {}
            }
        }
    }

    #[test]
    fn gedi_source_makes_one_pulse_per_shot_where_gedi_put_it() {
        let mut src = GediSource::open(&fixture()).unwrap();
        assert_eq!(src.progress(), Some((0, 32)));
        assert_eq!(src.epsg(), 32723, "-13.x, -44.x is UTM 23 south");
        let pulses = all_pulses(&mut src);
        assert_eq!(pulses.len(), 32);
        assert_eq!(src.progress(), Some((32, 32)));
        let l1b = GediL1b::open(&fixture()).unwrap();
        let epoch = l1b.time_epoch_gps_s().unwrap();
        assert_eq!(epoch, GEDI_EPOCH_GPS_S);
        let crs = OutputCrs::from_epsg(32723).unwrap();
        let shots: Vec<GediShot> = l1b
            .beams()
            .iter()
            .flat_map(|b| l1b.read_beam(b).unwrap().shots)
            .collect();
        let mut rx_all = Vec::new();
        for name in l1b.beams() {
            let beam = l1b.read_beam(name).unwrap();
            let (mut rx, mut tx) = (Vec::new(), Vec::new());
            l1b.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx)
                .unwrap();
            rx_all.extend(rx);
        }
        let mut at = 0usize;
        for (p, s) in pulses.iter().zip(&shots) {
            assert_eq!(p.pulse_id, s.shot_number);
            let want = epoch + s.delta_time_s - 1e9;
            assert!((p.gps_time - want).abs() < 1e-6, "{} vs {want}", p.gps_time);
            // 2019-04-18: adjusted standard GPS time about 2.396e8.
            assert!((2.39e8..2.40e8).contains(&p.gps_time), "{}", p.gps_time);
            let g = p.geometry.unwrap();
            let b0 = crs.project(s.bin0[1], s.bin0[0], s.bin0[2]).unwrap();
            let b1 = crs
                .project(s.lastbin[1], s.lastbin[0], s.lastbin[2])
                .unwrap();
            let ret = p
                .segments
                .iter()
                .position(|g| g.kind == SegmentKind::Return);
            let ret = p.segments[ret.unwrap()];
            assert_eq!(ret.start_ns, 0.0);
            assert_eq!(ret.len, s.rx_count);
            let last_t = ret.start_ns + f64::from(ret.len - 1) * p.sample_ns;
            for (t, want) in [(ret.start_ns, b0), (last_t, b1)] {
                for (k, w) in want.iter().enumerate() {
                    let got = g.anchor[k] + t * g.direction[k];
                    assert!((got - w).abs() < 0.01, "{k}: {got} vs {w}");
                }
            }
            let per_ns = g.direction.iter().map(|d| d * d).sum::<f64>().sqrt();
            assert!((per_ns - METRES_PER_NS).abs() < 2e-4, "{per_ns} m/ns");
            let n = p.stated_noise.unwrap();
            assert_eq!(n.mean, s.noise_mean as f32);
            assert_eq!(n.stddev, s.noise_stddev as f32);
            // Raw ↔ counts within 1/64 count.
            for (k, &raw) in p.raw[ret.range()].iter().enumerate() {
                let v = p.counts_to_volts(raw);
                let want = rx_all[at + k];
                assert!((v - want).abs() <= 1.0 / 64.0, "{v} vs {want}");
            }
            at += s.rx_count as usize;
            // The outgoing pulse's peak is at the emission, 2 × 1.376 ms before bin 0.
            let o = p.outgoing().unwrap();
            let seg = p.segments[o];
            assert_eq!(seg.len, 128);
            let raw = p.raw_of(o);
            let k = (0..raw.len())
                .max_by_key(|&i| (raw[i], usize::MAX - i))
                .unwrap();
            let peak_t = seg.start_ns + k as f64;
            assert!(
                (peak_t + 2.0 * s.bounce_time_bin0_s * 1e9).abs() < 1.0,
                "{peak_t}"
            );
            assert!((-2.76e6..-2.74e6).contains(&peak_t), "{peak_t}");
            assert!(
                (0.5..1.5).contains(&p.scan_angle_deg[0]),
                "{}",
                p.scan_angle_deg[0]
            );
        }
        let r = src.report().to_json();
        assert_eq!(r["pulses"], 32);
        assert_eq!(r["clamped_samples"], 0);
        assert_eq!(r["beams"][1]["name"], "BEAM1011");
        assert_eq!(r["beams"][1]["pulses"], 16);
        let fwhm = r["tx_fwhm_ns"].as_f64().unwrap();
        assert!((fwhm - PULSE_FWHM_NS).abs() < 1.0, "{fwhm}");
        let f = src.facts();
        assert_eq!(f.crs.as_deref(), Some("EPSG:32723"));
        assert_eq!(f.t0_is_emission, Some(false));
        assert_eq!(f.time_base.as_deref(), Some("gps_adjusted_standard"));
        assert_eq!(f.sensor.unwrap().digitizer_gain_v_per_dn, 1.0 / 32.0);
    }

    #[test]
    fn gedi_quantise_rounds_to_a_32nd_and_counts_what_it_clamps() {
        let mut c = 0;
        assert_eq!(quantise(244.40419, &mut c), 7821);
        assert_eq!(quantise(0.0, &mut c), 0);
        assert_eq!(quantise(65535.0 / 32.0, &mut c), 65535);
        assert_eq!(c, 0);
        assert_eq!(quantise(-0.5, &mut c), 0);
        assert_eq!(quantise(3000.0, &mut c), 65535);
        assert_eq!(quantise(f32::NAN, &mut c), 0);
        assert_eq!(c, 3);
    }

    #[test]
    fn gedi_fwhm_of_a_gaussian() {
        let sigma = 6.0f64;
        let x: Vec<f32> = (0..128)
            .map(|i| {
                let t = (i as f64 - 60.3) / sigma;
                (240.0 + 800.0 * (-0.5 * t * t).exp()) as f32
            })
            .collect();
        let w = fwhm_ns(&x).unwrap();
        assert!((w - 2.3548 * sigma).abs() < 0.1, "{w}");
        assert_eq!(fwhm_ns(&[1.0; 20]), None);
    }

    #[test]
    fn gedi_level2_and_damaged_files_are_errors_naming_the_file() {
        let l2a = crate::fixtures::path("waveform/gedi/GEDI02_A_O01964_beams0001_1011.h5");
        let e = GediSource::open(&l2a).err().unwrap().to_string();
        assert!(
            e.contains("GEDI02_A") && e.contains("Level 2A") && e.contains("Level 1B"),
            "{e}"
        );
        let l2b = crate::fixtures::path("waveform/gedi/GEDI02_B_O01964_beams0001_1011.h5");
        let e = GediSource::open(&l2b).err().unwrap().to_string();
        assert!(e.contains("Level 2B"), "{e}");
        // Cut anywhere: an error at open or while reading, never a panic.
        let bytes = std::fs::read(fixture()).unwrap();
        let pool = PulsePool::new(4);
        for cut in [
            100usize,
            10_000,
            200_000,
            bytes.len() / 2,
            bytes.len() - 100,
        ] {
            let Ok(l1b) = GediL1b::from_bytes(&bytes[..cut], "cut.h5") else {
                continue;
            };
            let Ok(mut src) = GediSource::from_l1b(l1b, GediOptions::default()) else {
                continue;
            };
            for _ in 0..100 {
                match src.next(&pool) {
                    Ok(SourceEvent::Pulse(p)) => pool.give(p),
                    Ok(SourceEvent::End) => break,
                    Ok(_) => {}
                    Err(e) => {
                        assert!(e.to_string().contains("cut.h5"), "{e}");
                        break;
                    }
                }
            }
        }
    }
}
