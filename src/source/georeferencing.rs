//! Georeferencing of a pulse stream from its navigation stream, before the worker fan-out.
//!
//! [`GeoreferencingSource`] wraps the input's [`Source`]. It sees pulses and navigation bytes
//! in the order they were recorded, so it needs no locks: navigation bytes of every port go
//! through the navigation decoder into a [`Trajectory`] (and are passed on unchanged, for the
//! navigation thread's report), and each pulse without geometry waits in a bounded queue until
//! the trajectory brackets its time, is georeferenced ([`crate::geo::direct_georeference::georeference`]) and
//! handed on, in its original order. Pulses that already carry their geometry (LAS, PulseWaves)
//! skip the navigation path.
//!
//! A pulse the trajectory cannot place is counted by reason — `before_navigation` (earlier than
//! the first sample kept), `navigation_gap` (bracketing samples further apart than
//! `max_gap_s`), `navigation_late` (still not bracketed when `max_pending` pulses wait or a
//! pulse `max_wait_s` later has arrived),
//! `no_navigation_after` (the input ended first) — and dropped, or passed on without geometry
//! (`on_missing = "pass"`).

use crate::source::DynSource;
use crate::source::report::{GeoreferenceReport, SourceReport};
use std::collections::{BTreeMap, VecDeque};

use serde::{Deserialize, Serialize};

use crate::core::facts::SourceFacts;
use crate::core::validate::{Validate, Validator, field};
use crate::geo::crs::OutputCrs;
use crate::geo::dem::Dem;
use crate::geo::direct_georeference::{Mounting, georeference, georeference_local};
use crate::geo::local_projection::LocalProjection;
use crate::nav::dating::{GpsTime, WEEK_S};
use crate::nav::decoder::{LEAP_SECONDS_NOW, NavDecoder};
use crate::nav::trajectory::{Interpolation, Miss, Trajectory, TrajectoryConfig};
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::{Pulse, PulsePool, SegmentKind};

/// What to do with a pulse the trajectory cannot place.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnMissing {
    /// Drop it (counted by reason). Default.
    #[default]
    Drop,
    /// Pass it on without geometry (counted by reason).
    Pass,
}

/// How a pulse's chord is taken into the output CRS (`[georeference] projection`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Projection {
    /// Both ends of every pulse's chord converted exactly (WGS84, then the map projection).
    /// Default.
    #[default]
    PerPulse,
    /// From a quadratic model of the projection rebuilt once per kilometre of travel
    /// ([`crate::geo::local_projection`]): the source thread's cost per pulse falls, the
    /// coordinates move by a few µm (docs/navigation.md).
    PerSpan,
}

impl Projection {
    /// The default, exact path.
    fn is_per_pulse(&self) -> bool {
        *self == Projection::PerPulse
    }
}

/// `[georeference]` of a run configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeoreferenceConfig {
    /// Georeference pulses that carry no geometry from the navigation stream. Default false.
    #[serde(default)]
    pub enabled: bool,
    /// Output CRS as an EPSG code of a projected CRS; default: the WGS84 UTM zone of the first
    /// position fix.
    #[serde(default)]
    pub output_epsg: Option<u32>,
    /// Group refractive index of the air along the beam (1 = vacuum). Default 1.00027.
    #[serde(default = "default_n")]
    pub refractive_index: f64,
    /// GPS − UTC leap seconds for NMEA times. Default 18.
    #[serde(default = "default_leap")]
    pub leap_seconds: f64,
    /// Longest interval between navigation samples that is interpolated, seconds. Default 0.5.
    #[serde(default = "default_gap")]
    pub max_gap_s: f64,
    /// Pulses waiting for navigation at most (then the oldest is `navigation_late`). Default
    /// 65536.
    #[serde(default = "default_pending")]
    pub max_pending: usize,
    /// Longest wait for navigation, seconds of pulse time: a pulse still not bracketed when a
    /// pulse this much later has arrived is `navigation_late`. Default 1.
    #[serde(default = "default_wait")]
    pub max_wait_s: f64,
    /// What happens to a pulse that cannot be placed. Default "drop".
    #[serde(default)]
    pub on_missing: OnMissing,
    /// A GeoTIFF DEM (path as given, relative to the working directory): adds
    /// `height_above_ground` to `returns.csv`. Its CRS becomes the output CRS unless
    /// `output_epsg` names one, which must then be the DEM's. Default none.
    #[serde(default)]
    pub dem: Option<String>,
    /// Added to each pulse's time before the trajectory lookup, seconds: the digitizer clock's
    /// offset from GPS time (as its PPS discipline measured it; GPS = digitizer + offset).
    /// Default 0.
    #[serde(default)]
    pub pulse_time_offset_s: f64,
    /// How the chord reaches the output CRS: exactly per pulse, or from a local model per span
    /// of a kilometre. Default "per_pulse" (left out of the configuration written into outputs,
    /// so that their configuration text and run key stay those of earlier versions).
    #[serde(default, skip_serializing_if = "Projection::is_per_pulse")]
    pub projection: Projection,
}

fn default_n() -> f64 {
    1.00027
}
fn default_leap() -> f64 {
    LEAP_SECONDS_NOW
}
fn default_gap() -> f64 {
    0.5
}
fn default_pending() -> usize {
    65_536
}
fn default_wait() -> f64 {
    1.0
}

impl Default for GeoreferenceConfig {
    fn default() -> Self {
        GeoreferenceConfig {
            enabled: false,
            output_epsg: None,
            refractive_index: default_n(),
            leap_seconds: default_leap(),
            max_gap_s: default_gap(),
            max_pending: default_pending(),
            max_wait_s: default_wait(),
            on_missing: OnMissing::Drop,
            dem: None,
            pulse_time_offset_s: 0.0,
            projection: Projection::PerPulse,
        }
    }
}

impl Validate for GeoreferenceConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.require(
            (1.0..=1.001).contains(&self.refractive_index),
            field(path, "refractive_index"),
            format!("must be in 1..=1.001 (air), got {}", self.refractive_index),
        );
        v.require(
            (0.0..=100.0).contains(&self.leap_seconds),
            field(path, "leap_seconds"),
            format!("must be in 0..=100 s, got {}", self.leap_seconds),
        );
        v.require(
            self.max_gap_s > 0.0 && self.max_gap_s <= 60.0,
            field(path, "max_gap_s"),
            format!("must be in (0, 60] s, got {}", self.max_gap_s),
        );
        v.require(
            self.pulse_time_offset_s.abs() <= 604_800.0,
            field(path, "pulse_time_offset_s"),
            format!(
                "must be within a GPS week (±604800 s), got {}",
                self.pulse_time_offset_s
            ),
        );
        v.require(
            self.max_wait_s > 0.0 && self.max_wait_s <= 3600.0,
            field(path, "max_wait_s"),
            format!("must be in (0, 3600] s, got {}", self.max_wait_s),
        );
        v.require(
            (1..=1 << 22).contains(&self.max_pending),
            field(path, "max_pending"),
            format!("must be in 1..=4194304 pulses, got {}", self.max_pending),
        );
        if let Some(code) = self.output_epsg
            && let Err(e) = OutputCrs::from_epsg(code)
        {
            v.report(field(path, "output_epsg"), e.to_string());
        }
        if let Some(dem) = &self.dem {
            match Dem::open(std::path::Path::new(dem)) {
                Err(e) => v.report(field(path, "dem"), e.to_string()),
                Ok(d) => {
                    if let Some(code) = self.output_epsg
                        && let Err(e) = d.check_crs(dem, code)
                    {
                        v.report(field(path, "dem"), e.to_string());
                    }
                }
            }
        }
    }
}

/// Counts for the report.
#[derive(Clone, Debug, Default, Serialize)]
struct Stats {
    georeferenced: u64,
    with_own_geometry: u64,
    missed: BTreeMap<&'static str, u64>,
    largest_wait: usize,
}

/// The wrapper (see the module documentation).
pub struct GeoreferencingSource {
    inner: Box<DynSource>,
    cfg: GeoreferenceConfig,
    decoders: BTreeMap<u8, NavDecoder>,
    trajectory: Trajectory,
    crs: Option<OutputCrs>,
    /// The local model of the projection (`projection = "per_span"`).
    local: Option<LocalProjection>,
    mount: Option<Mounting>,
    pending: VecDeque<Box<Pulse>>,
    ready: VecDeque<Box<Pulse>>,
    ended: bool,
    stats: Stats,
    samples: Vec<(crate::nav::NavSample, Option<GpsTime>)>,
    /// The DEM whose CRS must be the output CRS, and its file name.
    dem: Option<(std::sync::Arc<Dem>, String)>,
    /// Set when the DEM turned out to be in another CRS than the output's.
    failed: Option<String>,
    /// Earliest valid receiver date (days since 1970), for week-rollover correction.
    earliest_days: Option<i64>,
    /// Time of the latest pulse taken from the input, GPS seconds as the input states them.
    latest_pulse_time: f64,
    /// The input's time base is adjusted standard GPS time (cached from its facts).
    adjusted_time: Option<bool>,
    /// The output CRS once decided (WKT, or `EPSG:<code>`), for outputs created during the run.
    decided: std::sync::Arc<std::sync::OnceLock<String>>,
}

impl GeoreferencingSource {
    /// Wraps `inner`; the output CRS is built now when the configuration names one.
    pub fn new(inner: Box<DynSource>, cfg: GeoreferenceConfig) -> Result<Self, String> {
        let crs = match cfg.output_epsg {
            Some(code) => Some(OutputCrs::from_epsg(code).map_err(|e| e.to_string())?),
            None => None,
        };
        let local = (cfg.projection == Projection::PerSpan).then(LocalProjection::new);
        Ok(GeoreferencingSource {
            inner,
            trajectory: Trajectory::new(TrajectoryConfig {
                capacity: 1 << 16,
                max_gap_s: cfg.max_gap_s,
                interpolation: Interpolation::Hermite,
            }),
            cfg,
            decoders: BTreeMap::new(),
            crs,
            local,
            mount: None,
            pending: VecDeque::new(),
            ready: VecDeque::new(),
            ended: false,
            stats: Stats::default(),
            samples: Vec::new(),
            dem: None,
            failed: None,
            earliest_days: None,
            latest_pulse_time: f64::NEG_INFINITY,
            adjusted_time: None,
            decided: Default::default(),
        }
        .decide_crs())
    }

    /// Publishes the output CRS, once known, to [`GeoreferencingSource::decided_crs`].
    fn decide_crs(self) -> Self {
        if let Some(c) = &self.crs {
            let code = c.epsg();
            let _ = self
                .decided
                .set(crate::geo::crs::utm_wkt(code).unwrap_or_else(|| format!("EPSG:{code}")));
        }
        self
    }

    /// The output CRS as OGC WKT (UTM zones) or `EPSG:<code>`, set when it is decided: at once
    /// when the configuration names it, else at the first position fix (before any pulse is
    /// georeferenced). Sinks created before the run read it at their first pulse.
    pub fn decided_crs(&self) -> std::sync::Arc<std::sync::OnceLock<String>> {
        self.decided.clone()
    }

    /// NMEA dates before `days` (since 1970-01-01) are taken for a 10-bit week rollover and
    /// moved forward by 1024 weeks (`[navigation] earliest_date`).
    pub fn with_earliest_date(mut self, days: Option<i64>) -> Self {
        self.earliest_days = days;
        self
    }

    /// Checks `dem` against the output CRS as soon as that is known (now, when configured;
    /// otherwise at the first fix): a mismatch stops the run with the DEM's error.
    pub fn with_dem(mut self, dem: std::sync::Arc<Dem>, file: String) -> Self {
        self.dem = Some((dem, file));
        self.check_dem();
        self
    }

    fn check_dem(&mut self) {
        if let (Some((dem, file)), Some(crs)) = (&self.dem, &self.crs)
            && self.failed.is_none()
            && let Err(e) = dem.check_crs(file, crs.epsg())
        {
            self.failed = Some(e.to_string());
        }
    }

    fn take_nav(&mut self, port: u8, bytes: &[u8]) {
        let (leap, earliest) = (self.cfg.leap_seconds, self.earliest_days);
        let dec = self
            .decoders
            .entry(port)
            .or_insert_with(|| NavDecoder::new(leap, 4096, earliest));
        let samples = &mut self.samples;
        dec.push(bytes, &mut |s, t| samples.push((s, t)));
        let mut batch = std::mem::take(&mut self.samples);
        for (s, t) in batch.drain(..) {
            let t = match (t, s.time) {
                (Some(t), _) => t,
                (None, crate::nav::NavTime::GpsSecondsOfWeek { sow }) => GpsTime { week: 0, sow },
                _ => continue,
            };
            if self.crs.is_none()
                && let (Some(lat), Some(lon)) = (s.lat, s.lon)
            {
                match OutputCrs::utm_at(lat, lon) {
                    Ok(c) => {
                        let code = c.epsg();
                        self.crs = Some(c);
                        let _ = self.decided.set(
                            crate::geo::crs::utm_wkt(code)
                                .unwrap_or_else(|| format!("EPSG:{code}")),
                        );
                        self.check_dem();
                    }
                    Err(e) => tracing::warn!("no UTM zone for the first fix: {e}"),
                }
            }
            self.trajectory.push(t, &s);
        }
        self.samples = batch;
    }

    /// Whether the input's pulse times are adjusted standard GPS time; asked of the input once
    /// (its facts are complete after its first record, before any pulse is placed).
    fn adjusted_time(&mut self) -> bool {
        *self.adjusted_time.get_or_insert_with(|| {
            self.inner.facts().time_base.as_deref() == Some("gps_adjusted_standard")
        })
    }

    /// The pulse's time on the trajectory's scale.
    fn trajectory_time(&self, p: &Pulse, adjusted: bool) -> Option<f64> {
        let newest = self.trajectory.newest()?;
        let time = p.gps_time + self.cfg.pulse_time_offset_s;
        let g = if adjusted {
            let s = time + 1e9;
            let week = (s / WEEK_S).floor();
            GpsTime {
                week: week.max(0.0) as u32,
                sow: s - week * WEEK_S,
            }
        } else {
            // Seconds of the week: the week the trajectory is in (the buffer's time counts from
            // the start of its first week), or the neighbouring one when the pulse is across
            // a week's end from the newest navigation.
            let mut t = (newest / WEEK_S).floor() * WEEK_S + time;
            if t - newest > WEEK_S / 2.0 {
                t -= WEEK_S;
            } else if newest - t > WEEK_S / 2.0 {
                t += WEEK_S;
            }
            return Some(t);
        };
        self.trajectory.time_of(g)
    }

    fn mounting(&mut self) -> Mounting {
        if let Some(m) = self.mount {
            return m;
        }
        let m = match self.inner.facts().sensor {
            Some(s) => Mounting {
                lever_arm_m: s.lever_arm_m,
                boresight_deg: s.boresight_deg,
                refractive_index: self.cfg.refractive_index,
            },
            None => {
                tracing::warn!("the input states no sensor: lever arm and boresight taken as zero");
                Mounting {
                    lever_arm_m: [0.0; 3],
                    boresight_deg: [0.0; 3],
                    refractive_index: self.cfg.refractive_index,
                }
            }
        };
        self.mount = Some(m);
        m
    }

    fn miss(&mut self, p: Box<Pulse>, why: &'static str, pool: &PulsePool) {
        *self.stats.missed.entry(why).or_insert(0) += 1;
        match self.cfg.on_missing {
            OnMissing::Drop => pool.give(p),
            OnMissing::Pass => self.ready.push_back(p),
        }
    }

    /// Moves every pulse that can now be decided from `pending` to `ready`, in order.
    fn drain(&mut self, pool: &PulsePool) {
        if self.pending.is_empty() {
            return;
        }
        let adjusted = self.adjusted_time();
        while let Some(p) = self.pending.front() {
            if p.geometry.is_some() {
                let p = self.pending.pop_front().expect("front exists");
                self.ready.push_back(p);
                continue;
            }
            let t = self.trajectory_time(p, adjusted);
            let pose = t.ok_or(Miss::Empty).and_then(|t| {
                Ok((
                    self.trajectory.position_at(t)?,
                    self.trajectory.attitude_at(t)?,
                ))
            });
            let outcome = match pose {
                Ok(pose) => Ok(pose),
                Err(Miss::After | Miss::Empty) if !self.ended => {
                    let waited = self.latest_pulse_time - p.gps_time;
                    if self.pending.len() <= self.cfg.max_pending && waited <= self.cfg.max_wait_s {
                        return;
                    }
                    Err("navigation_late")
                }
                Err(Miss::After | Miss::Empty) => Err("no_navigation_after"),
                Err(Miss::Before) => Err("before_navigation"),
                Err(Miss::Gap) => Err("navigation_gap"),
            };
            let mut p = self.pending.pop_front().expect("front exists");
            let placed = outcome.and_then(|(pos, att)| {
                let mount = self.mounting();
                let crs = self.crs.as_ref().ok_or("no_output_crs")?;
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for s in p.segments.iter().filter(|s| s.kind == SegmentKind::Return) {
                    lo = lo.min(s.start_ns);
                    hi = hi.max(s.start_ns + s.len as f64 * p.sample_ns);
                }
                if !lo.is_finite() {
                    (lo, hi) = (0.0, 1.0);
                }
                let window = (lo, hi);
                match self.local.as_mut() {
                    None => georeference(crs, pos, &att, p.scan_angle_deg, &mount, window),
                    Some(local) => {
                        georeference_local(crs, local, pos, &att, p.scan_angle_deg, &mount, window)
                    }
                }
                .map_err(|_| "projection_failed")
            });
            match placed {
                Ok(g) => {
                    p.geometry = Some(g.geometry);
                    self.stats.georeferenced += 1;
                    self.ready.push_back(p);
                }
                Err(why) => self.miss(p, why, pool),
            }
        }
    }
}

impl Source for GeoreferencingSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        self.inner.name()
    }

    /// The pulses waiting for navigation (at most `max_pending` + 1) and those placed but not
    /// yet handed out (one drain's worth, bounded by the same), plus what the inner source holds.
    fn held_pulses(&self) -> usize {
        2 * (self.cfg.max_pending + 1) + self.inner.held_pulses()
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        loop {
            if let Some(e) = &self.failed {
                return Err(SourceError::Fatal(e.clone()));
            }
            if let Some(p) = self.ready.pop_front() {
                return Ok(SourceEvent::Pulse(p));
            }
            if self.ended {
                if self.pending.is_empty() {
                    return Ok(SourceEvent::End);
                }
                self.drain(pool);
                continue;
            }
            match self.inner.next(pool)? {
                SourceEvent::Pulse(p) => {
                    if p.geometry.is_some() {
                        self.stats.with_own_geometry += 1;
                    } else if p.gps_time > self.latest_pulse_time {
                        self.latest_pulse_time = p.gps_time;
                    }
                    self.pending.push_back(p);
                    self.stats.largest_wait = self.stats.largest_wait.max(self.pending.len());
                    self.drain(pool);
                }
                SourceEvent::Nav(chunk) => {
                    self.take_nav(chunk.port, &chunk.bytes);
                    self.drain(pool);
                    return Ok(SourceEvent::Nav(chunk));
                }
                SourceEvent::Idle => return Ok(SourceEvent::Idle),
                SourceEvent::End => {
                    for dec in self.decoders.values_mut() {
                        let samples = &mut self.samples;
                        dec.finish(&mut |s, t| samples.push((s, t)));
                    }
                    let held = std::mem::take(&mut self.samples);
                    for (s, t) in held {
                        if let Some(t) = t {
                            self.trajectory.push(t, &s);
                        }
                    }
                    self.ended = true;
                    self.drain(pool);
                }
            }
        }
    }

    fn progress(&self) -> Option<(u64, u64)> {
        self.inner.progress()
    }

    fn report(&self) -> SourceReport {
        let mut r = self.inner.report();
        r.georeference = Some(GeoreferenceReport {
            georeferenced: self.stats.georeferenced,
            with_own_geometry: self.stats.with_own_geometry,
            missed: self
                .stats
                .missed
                .iter()
                .map(|(k, n)| (k.to_string(), *n))
                .collect(),
            largest_wait_pulses: self.stats.largest_wait as u64,
            output_crs: self.crs.as_ref().map(|c| format!("EPSG:{}", c.epsg())),
            trajectory: self.trajectory.stats().clone(),
        });
        r
    }

    fn facts(&self) -> SourceFacts {
        let mut f = self.inner.facts();
        if let Some(c) = &self.crs {
            f.crs = Some(
                crate::geo::crs::utm_wkt(c.epsg()).unwrap_or_else(|| format!("EPSG:{}", c.epsg())),
            );
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::ports::NavChunk;

    /// A source replaying a list of events.
    struct Script(VecDeque<Ev>);
    enum Ev {
        Pulse(f64),
        Nav(f64),
    }

    fn sentence(body: &str) -> String {
        format!(
            "${body}*{:02X}\r\n",
            crate::nav::crc::nmea_xor(body.as_bytes())
        )
    }

    /// GGA + PASHR + ZDA of GPS second-of-week `sow` in week 1690 (UTC = GPS − 18 s).
    fn nav_bytes(sow: f64) -> Vec<u8> {
        let utc = sow - 18.0;
        let tod = utc.rem_euclid(86_400.0);
        let day = 27 + (utc / 86_400.0).floor() as u32; // 27 May 2012 was the week's Sunday
        let (h, m, s) = ((tod / 3600.0) as u32, (tod / 60.0) as u32 % 60, tod % 60.0);
        let t = format!("{h:02}{m:02}{s:05.2}");
        let mut out = sentence(&format!(
            "GPGGA,{t},2459.400000,S,03135.400000,E,1,12,0.8,1000.000,M,0.000,M,,"
        ));
        out += &sentence(&format!(
            "PASHR,{t},090.00,T,+00.00,+00.00,+0.00,0.01,0.01,0.02,1,1"
        ));
        out += &sentence(&format!("GPZDA,{t},{day:02},05,2012,00,00"));
        out.into_bytes()
    }

    impl Source for Script {
        type Report = SourceReport;

        fn name(&self) -> &'static str {
            "script"
        }
        fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
            Ok(match self.0.pop_front() {
                None => SourceEvent::End,
                Some(Ev::Nav(t)) => SourceEvent::Nav(NavChunk {
                    port: 0,
                    receive_time_ns: 0,
                    bytes: nav_bytes(t),
                }),
                Some(Ev::Pulse(t)) => {
                    let mut p = pool.take();
                    p.gps_time = t;
                    p.scan_angle_deg = [0.0, f32::NAN];
                    p.push_segment(SegmentKind::Return, 0, 6000.0, [0u16; 100]);
                    SourceEvent::Pulse(p)
                }
            })
        }
    }

    fn run(events: Vec<Ev>, cfg: GeoreferenceConfig) -> (Vec<(f64, bool)>, serde_json::Value) {
        let mut src = GeoreferencingSource::new(Box::new(Script(events.into())), cfg).unwrap();
        let pool = PulsePool::new(16);
        let mut out = Vec::new();
        loop {
            match src.next(&pool).unwrap() {
                SourceEvent::Pulse(p) => out.push((p.gps_time, p.geometry.is_some())),
                SourceEvent::Nav(_) | SourceEvent::Idle => {}
                SourceEvent::End => break,
            }
        }
        (out, src.report().to_json()["georeference"].clone())
    }

    fn cfg() -> GeoreferenceConfig {
        GeoreferenceConfig {
            enabled: true,
            refractive_index: 1.0,
            max_gap_s: 0.5,
            max_pending: 4,
            ..GeoreferenceConfig::default()
        }
    }

    #[test]
    fn pulses_wait_for_navigation_keep_their_order_and_misses_are_counted() {
        let base = 345_600.0;
        let events = vec![
            Ev::Pulse(base - 1.0), // before any navigation: held, then before_navigation
            Ev::Nav(base),
            Ev::Pulse(base + 0.05), // waits for the next epoch
            Ev::Pulse(base + 0.08),
            Ev::Nav(base + 0.1),
            Ev::Nav(base + 2.0),   // a 1.9 s gap
            Ev::Pulse(base + 1.0), // inside the gap
            Ev::Pulse(base + 2.5), // after the last navigation: never bracketed
        ];
        let (out, report) = run(events, cfg());
        let placed: Vec<f64> = out.iter().filter(|p| p.1).map(|p| p.0).collect();
        assert_eq!(placed, vec![base + 0.05, base + 0.08], "{report}");
        assert_eq!(out.len(), 2, "dropped by default");
        assert_eq!(report["missed"]["before_navigation"], 1, "{report}");
        assert_eq!(report["missed"]["navigation_gap"], 1, "{report}");
        assert_eq!(report["missed"]["no_navigation_after"], 1, "{report}");
        assert_eq!(report["georeferenced"], 2);
    }

    #[test]
    fn a_pulse_waits_at_most_max_wait_s_of_pulse_time() {
        // Navigation stops at base + 0.1; pulses keep coming for 3 s: the early ones are late
        // once a pulse 1 s younger arrives, not only at the end of the input.
        let base = 345_600.0;
        let mut events = vec![Ev::Nav(base), Ev::Nav(base + 0.1)];
        for k in 0..30 {
            events.push(Ev::Pulse(base + 0.2 + 0.1 * k as f64));
        }
        let (_, report) = run(
            events,
            GeoreferenceConfig {
                max_pending: 1000,
                max_wait_s: 1.0,
                ..cfg()
            },
        );
        let late = report["missed"]["navigation_late"].as_u64().unwrap();
        let end = report["missed"]["no_navigation_after"].as_u64().unwrap();
        assert_eq!(late + end, 30, "{report}");
        assert!((19..=21).contains(&late), "{report}");
        assert!(
            report["largest_wait_pulses"].as_u64().unwrap() <= 12,
            "{report}"
        );
    }

    #[test]
    fn the_digitizer_clock_offset_moves_pulses_onto_gps_time() {
        // Pulse times 10 s behind GPS (a digitizer clock offset): without the offset they fall
        // before the navigation; with it they are placed.
        let base = 345_600.0;
        let events = || {
            vec![
                Ev::Nav(base),
                Ev::Pulse(base - 10.0 + 0.05),
                Ev::Nav(base + 0.1),
            ]
        };
        let (out, report) = run(events(), cfg());
        assert!(
            out.is_empty() && report["missed"]["before_navigation"] == 1,
            "{report}"
        );
        let (out, report) = run(
            events(),
            GeoreferenceConfig {
                pulse_time_offset_s: 10.0,
                ..cfg()
            },
        );
        assert_eq!(out, vec![(base - 10.0 + 0.05, true)], "{report}");
    }

    #[test]
    fn pass_keeps_every_pulse_in_order_and_the_queue_is_bounded() {
        let base = 345_600.0;
        let mut events = vec![Ev::Nav(base)];
        for k in 0..10 {
            events.push(Ev::Pulse(base + 0.01 * (k + 1) as f64));
        }
        events.push(Ev::Nav(base + 0.2));
        let (out, report) = run(
            events,
            GeoreferenceConfig {
                on_missing: OnMissing::Pass,
                ..cfg()
            },
        );
        let times: Vec<f64> = out.iter().map(|p| p.0).collect();
        let mut sorted = times.clone();
        sorted.sort_by(f64::total_cmp);
        assert_eq!(times, sorted, "order kept");
        assert_eq!(out.len(), 10);
        // At most 4 wait: the oldest ones went on without geometry as navigation_late.
        let late = report["missed"]["navigation_late"].as_u64().unwrap();
        assert!(late >= 5, "{report}");
        assert_eq!(out.iter().filter(|p| !p.1).count() as u64, late);
        assert!(report["largest_wait_pulses"].as_u64().unwrap() <= 5);
    }
}
