//! GPS time for navigation samples: NMEA times carry a UTC time of day and no date; the date
//! comes from ZDA and RMC sentences, and UTC becomes GPS time by adding the leap seconds
//! (configurable; 18 since 2017-01-01).
//!
//! Rules, in order of arrival:
//! - a dated sample (ZDA, RMC with a date) sets the current date and time of day;
//! - an undated time of day more than 12 h *before* the current one has crossed midnight (next
//!   day); more than 12 h *after* it belongs to the day before (a late record);
//! - a sample without any time (HDT, VTG) takes the time of the last timed NMEA sample, the
//!   epoch it was sent in;
//! - samples that arrive before any date are held (at most `max_pending`, the oldest dropped and
//!   counted as `undated`) and dated when the first date comes;
//! - dates before `earliest` are taken for a receiver's 10-bit GPS week rollover (its calendar
//!   fell back by 1024 weeks) and moved forward by 1024 weeks until they are not.

use std::collections::VecDeque;

use serde::Serialize;

use super::nmea::days_from_civil;
use super::{NavSample, NavTime};

/// Seconds in a GPS week.
pub const WEEK_S: f64 = 604_800.0;
/// Days from 1970-01-01 to the GPS epoch 1980-01-06.
pub const GPS_EPOCH_DAYS: i64 = 3657;
/// Days in 1024 GPS weeks (one 10-bit week rollover).
pub const ROLLOVER_DAYS: i64 = 1024 * 7;

/// A time on the GPS time scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GpsTime {
    /// Full GPS week number.
    pub week: u32,
    /// Seconds of the week.
    pub sow: f64,
}

impl GpsTime {
    /// GPS time of a UTC instant given as days since 1970-01-01 and seconds of that day.
    /// `None` before the GPS epoch.
    pub fn from_utc(days: i64, seconds: f64, leap_seconds: f64) -> Option<GpsTime> {
        let total = (days - GPS_EPOCH_DAYS) as f64 * 86_400.0 + seconds + leap_seconds;
        if total.is_nan() || total < 0.0 || !total.is_finite() {
            return None;
        }
        let week = (total / WEEK_S).floor();
        if week > u32::MAX as f64 {
            return None;
        }
        Some(GpsTime {
            week: week as u32,
            sow: total - week * WEEK_S,
        })
    }

    /// Seconds since the GPS epoch.
    pub fn seconds(&self) -> f64 {
        self.week as f64 * WEEK_S + self.sow
    }
}

/// What the dater counted.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct DaterStats {
    /// Samples dropped because no date came while they were held.
    pub undated: u64,
    /// Dates moved forward by 1024 weeks (receiver week rollover).
    pub rollover_corrected: u64,
}

/// Dates NMEA samples and converts them to GPS time (see the module documentation).
#[derive(Debug)]
pub struct NmeaDater {
    leap_seconds: f64,
    earliest_days: Option<i64>,
    max_pending: usize,
    /// Current UTC date (days since 1970) and time of day (s).
    day: Option<(i64, f64)>,
    /// Time of day of the last timed sample (for HDT/VTG), s.
    last_tod: Option<f64>,
    pending: VecDeque<NavSample>,
    stats: DaterStats,
}

impl NmeaDater {
    /// A dater adding `leap_seconds` (GPS − UTC), holding at most `max_pending` undated
    /// samples, correcting dates before `earliest` (days since 1970) for week rollover.
    pub fn new(leap_seconds: f64, max_pending: usize, earliest: Option<i64>) -> Self {
        NmeaDater {
            leap_seconds,
            earliest_days: earliest,
            max_pending: max_pending.max(1),
            day: None,
            last_tod: None,
            pending: VecDeque::new(),
            stats: DaterStats::default(),
        }
    }

    /// Counts so far.
    pub fn stats(&self) -> &DaterStats {
        &self.stats
    }

    /// Takes one sample; calls `out` with every sample that can now be dated, in order.
    /// Samples with GPS time pass straight through.
    pub fn push(&mut self, mut s: NavSample, out: &mut impl FnMut(NavSample, Option<GpsTime>)) {
        match s.time {
            NavTime::Gps { week, sow } => return out(s, Some(GpsTime { week, sow })),
            NavTime::GpsSecondsOfWeek { .. } => return out(s, None),
            NavTime::Utc { days, seconds } => {
                let days = self.unroll(days);
                s.time = NavTime::Utc { days, seconds };
                self.day = Some((days, seconds));
                self.last_tod = Some(seconds);
                self.release(days, seconds, out);
            }
            NavTime::UtcTimeOfDay { seconds } => self.last_tod = Some(seconds),
            NavTime::None => {
                if let Some(t) = self.last_tod {
                    s.time = NavTime::UtcTimeOfDay { seconds: t };
                }
            }
        }
        if self.day.is_none() || matches!(s.time, NavTime::None) {
            if self.pending.len() == self.max_pending {
                self.pending.pop_front();
                self.stats.undated += 1;
            }
            self.pending.push_back(s);
            return;
        }
        let t = self.date(&s);
        out(s, t)
    }

    /// Drops what is still held (end of stream), counting it as undated.
    pub fn finish(&mut self) {
        self.stats.undated += self.pending.len() as u64;
        self.pending.clear();
    }

    fn unroll(&mut self, mut days: i64) -> i64 {
        if let Some(e) = self.earliest_days {
            let mut moved = false;
            while days < e {
                days += ROLLOVER_DAYS;
                moved = true;
            }
            self.stats.rollover_corrected += u64::from(moved);
        }
        days
    }

    /// Dates the held samples against the first date seen.
    fn release(&mut self, days: i64, tod: f64, out: &mut impl FnMut(NavSample, Option<GpsTime>)) {
        while let Some(mut p) = self.pending.pop_front() {
            match p.time {
                NavTime::UtcTimeOfDay { seconds } => {
                    let d = if seconds > tod + 43_200.0 {
                        days - 1
                    } else {
                        days
                    };
                    let g = GpsTime::from_utc(d, seconds, self.leap_seconds);
                    p.time = NavTime::Utc { days: d, seconds };
                    out(p, g);
                }
                _ => {
                    // A sample held without any time: it gets the date's own time.
                    p.time = NavTime::Utc { days, seconds: tod };
                    out(p, GpsTime::from_utc(days, tod, self.leap_seconds));
                }
            }
        }
    }

    fn date(&mut self, s: &NavSample) -> Option<GpsTime> {
        let (days, tod) = self.day?;
        match s.time {
            NavTime::Utc { days, seconds } => GpsTime::from_utc(days, seconds, self.leap_seconds),
            NavTime::UtcTimeOfDay { seconds } => {
                let d = if seconds + 43_200.0 < tod {
                    // Midnight passed since the date was set.
                    self.day = Some((days + 1, seconds));
                    days + 1
                } else if seconds > tod + 43_200.0 {
                    days - 1
                } else {
                    if seconds > tod {
                        self.day = Some((days, seconds));
                    }
                    days
                };
                GpsTime::from_utc(d, seconds, self.leap_seconds)
            }
            _ => None,
        }
    }
}

/// Civil date (year, month, day) of days since 1970-01-01 (proleptic Gregorian); the inverse
/// of [`days_from_civil`].
pub fn civil_of_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

/// Days since 1970-01-01 of a civil date; see [`days_from_civil`].
pub fn civil_days(y: i64, m: u32, d: u32) -> i64 {
    days_from_civil(y, m, d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nav::NavKind;

    fn tod(kind: NavKind, s: f64) -> NavSample {
        NavSample::new(kind, NavTime::UtcTimeOfDay { seconds: s })
    }

    fn run(d: &mut NmeaDater, samples: Vec<NavSample>) -> Vec<(NavKind, Option<GpsTime>)> {
        let mut out = Vec::new();
        for s in samples {
            d.push(s, &mut |s, t| out.push((s.kind, t)));
        }
        out
    }

    #[test]
    fn gps_time_of_known_instants() {
        // The GPS epoch, and 2017-01-01 00:00:00 UTC = week 1930, sow 18 (+ 18 leap seconds).
        assert_eq!(
            GpsTime::from_utc(GPS_EPOCH_DAYS, 0.0, 0.0),
            Some(GpsTime { week: 0, sow: 0.0 })
        );
        let t = GpsTime::from_utc(civil_days(2017, 1, 1), 0.0, 18.0).unwrap();
        assert_eq!(t.week, 1930);
        assert!((t.sow - 18.0).abs() < 1e-9);
        assert_eq!(
            GpsTime::from_utc(0, 0.0, 18.0),
            None,
            "before the GPS epoch"
        );
    }

    #[test]
    fn samples_before_the_first_date_wait_for_it_and_midnight_is_crossed() {
        let mut d = NmeaDater::new(18.0, 16, None);
        let day = civil_days(2014, 2, 19);
        let out = run(
            &mut d,
            vec![
                tod(NavKind::Pashr, 86_399.0),
                NavSample::new(NavKind::Hdt, NavTime::None),
                NavSample::new(
                    NavKind::Zda,
                    NavTime::Utc {
                        days: day,
                        seconds: 86_399.5,
                    },
                ),
                tod(NavKind::Gga, 0.5),
                NavSample::new(NavKind::Hdt, NavTime::None),
            ],
        );
        let secs: Vec<f64> = out.iter().map(|(_, t)| t.unwrap().seconds()).collect();
        let base = GpsTime::from_utc(day, 0.0, 18.0).unwrap().seconds();
        assert_eq!(out.len(), 5);
        assert_eq!(secs[0] - base, 86_399.0);
        assert_eq!(secs[1] - base, 86_399.0, "HDT takes its epoch's time");
        assert_eq!(secs[2] - base, 86_399.5);
        assert_eq!(secs[3] - base, 86_400.5, "next day after midnight");
        assert_eq!(secs[4] - base, 86_400.5);
    }

    #[test]
    fn held_samples_are_bounded_and_counted() {
        let mut d = NmeaDater::new(18.0, 3, None);
        let out = run(
            &mut d,
            (0..10).map(|i| tod(NavKind::Gga, i as f64)).collect(),
        );
        assert!(out.is_empty());
        assert_eq!(d.stats().undated, 7);
        d.finish();
        assert_eq!(d.stats().undated, 10);
    }

    #[test]
    fn a_rolled_over_receiver_date_is_moved_forward_1024_weeks() {
        // 1999-08-22 is the first day of a 1024-week cycle; a receiver with the rollover bug
        // reports it 1024 weeks after 1999-08-22 was true: 2019-04-07.
        let mut d = NmeaDater::new(18.0, 4, Some(civil_days(2010, 1, 1)));
        let out = run(
            &mut d,
            vec![NavSample::new(
                NavKind::Zda,
                NavTime::Utc {
                    days: civil_days(1999, 8, 22),
                    seconds: 0.0,
                },
            )],
        );
        let want = GpsTime::from_utc(civil_days(2019, 4, 7), 0.0, 18.0).unwrap();
        assert_eq!(out[0].1, Some(want));
        assert_eq!(d.stats().rollover_corrected, 1);
    }
}
