//! Telemetry every stage reports: pulses received, sent, dropped (by reason), errors, and two
//! latency histograms — the stage's own service time and the time since the pulse arrived when
//! it left the stage (which includes queueing).

use std::collections::BTreeMap;

use hdrhistogram::Histogram;
use serde::Serialize;

use crate::pipeline::stage::DropCounts;

/// Highest latency a histogram records, nanoseconds (larger values are clamped): one hour.
const MAX_TRACKABLE_NS: u64 = 3_600_000_000_000;

/// A latency histogram in nanoseconds (3 significant figures).
#[derive(Clone, Debug)]
pub struct LatencyHistogram(Histogram<u64>);

impl Default for LatencyHistogram {
    fn default() -> Self {
        LatencyHistogram(
            Histogram::new_with_bounds(1, MAX_TRACKABLE_NS, 3).expect("static histogram bounds"),
        )
    }
}

impl LatencyHistogram {
    /// Records one latency, nanoseconds (clamped to 1 ns .. 1 h). Does not allocate.
    pub fn record(&mut self, ns: u64) {
        self.0.saturating_record(ns.clamp(1, MAX_TRACKABLE_NS));
    }

    /// Adds every sample of `other`.
    pub fn merge(&mut self, other: &LatencyHistogram) {
        // Same bounds on both sides: cannot fail.
        let _ = self.0.add(&other.0);
    }

    /// The samples recorded since `earlier`, a copy of this histogram taken before (for rates
    /// and percentiles over an interval).
    pub fn since(&self, earlier: &LatencyHistogram) -> LatencyHistogram {
        let mut h = self.clone();
        // `earlier` is a past state of `self`: its counts are never larger.
        let _ = h.0.subtract(&earlier.0);
        h
    }

    /// Samples at or below `ns` nanoseconds (for cumulative histogram buckets).
    pub fn count_at_or_below(&self, ns: u64) -> u64 {
        if self.0.is_empty() {
            return 0;
        }
        self.0.count_between(0, ns.min(MAX_TRACKABLE_NS))
    }

    /// Number of samples.
    pub fn count(&self) -> u64 {
        self.0.len()
    }

    /// Summary percentiles.
    pub fn summary(&self) -> LatencySummary {
        let h = &self.0;
        if h.is_empty() {
            return LatencySummary::default();
        }
        LatencySummary {
            count: h.len(),
            mean_ns: h.mean(),
            p50_ns: h.value_at_quantile(0.50),
            p99_ns: h.value_at_quantile(0.99),
            p999_ns: h.value_at_quantile(0.999),
            max_ns: h.max(),
        }
    }
}

/// Percentiles of a latency histogram, nanoseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Samples recorded.
    pub count: u64,
    /// Mean, ns.
    pub mean_ns: f64,
    /// Median, ns.
    pub p50_ns: u64,
    /// 99th percentile, ns.
    pub p99_ns: u64,
    /// 99.9th percentile, ns.
    pub p999_ns: u64,
    /// Maximum, ns.
    pub max_ns: u64,
}

/// What one stage (on one worker, or merged over workers) has done.
#[derive(Clone, Debug)]
pub struct StageTelemetry {
    /// Stage kind name.
    pub name: &'static str,
    /// Pulses given to the stage.
    pub received: u64,
    /// Pulses the stage emitted.
    pub sent: u64,
    /// Pulses the stage dropped, by reason (errors included).
    pub dropped: DropCounts,
    /// Pulses rejected as errors.
    pub errors: u64,
    /// Pulses passed on partly unprocessed on purpose, by note ([`super::Emitter::emit_noted`]).
    pub notes: DropCounts,
    /// The stage's own processing time per pulse, ns.
    pub service: LatencyHistogram,
    /// Time from the pulse's arrival to its leaving this stage, ns.
    pub since_arrival: LatencyHistogram,
}

impl StageTelemetry {
    /// Empty telemetry for a stage.
    pub fn new(name: &'static str) -> Self {
        StageTelemetry {
            name,
            received: 0,
            sent: 0,
            dropped: DropCounts::default(),
            errors: 0,
            notes: DropCounts::default(),
            service: LatencyHistogram::default(),
            since_arrival: LatencyHistogram::default(),
        }
    }

    /// Adds another worker's telemetry of the same stage.
    pub fn merge(&mut self, other: &StageTelemetry) {
        self.received += other.received;
        self.sent += other.sent;
        self.dropped.merge(&other.dropped);
        self.errors += other.errors;
        self.notes.merge(&other.notes);
        self.service.merge(&other.service);
        self.since_arrival.merge(&other.since_arrival);
    }

    /// The stage's part of a run report.
    pub fn report(&self) -> StageReport {
        StageReport {
            name: self.name.to_string(),
            received: self.received,
            sent: self.sent,
            dropped: self
                .dropped
                .iter()
                .map(|(r, c)| (r.to_string(), c))
                .collect(),
            errors: self.errors,
            notes: self.notes.iter().map(|(r, c)| (r.to_string(), c)).collect(),
            service: self.service.summary(),
            since_arrival: self.since_arrival.summary(),
        }
    }
}

/// A stage's telemetry as written into `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct StageReport {
    /// Stage kind name.
    pub name: String,
    /// Pulses given to the stage.
    pub received: u64,
    /// Pulses it emitted.
    pub sent: u64,
    /// Pulses it dropped, by reason.
    pub dropped: BTreeMap<String, u64>,
    /// Pulses rejected as errors.
    pub errors: u64,
    /// Pulses passed on partly unprocessed on purpose, by note (included in `sent`).
    pub notes: BTreeMap<String, u64>,
    /// Its own processing time per pulse.
    pub service: LatencySummary,
    /// Time from arrival to leaving this stage.
    pub since_arrival: LatencySummary,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_and_merge() {
        let mut a = LatencyHistogram::default();
        let mut b = LatencyHistogram::default();
        for v in 1..=1000u64 {
            a.record(v * 1000);
        }
        b.record(5_000_000);
        a.merge(&b);
        let s = a.summary();
        assert_eq!(s.count, 1001);
        assert!((s.p50_ns as f64 - 500_000.0).abs() / 500_000.0 < 0.01);
        assert!(s.max_ns >= 4_990_000);
        assert!(s.p999_ns >= 999_000);
    }

    #[test]
    fn stage_telemetry_merges_counts() {
        let mut a = StageTelemetry::new("x");
        a.received = 3;
        a.sent = 2;
        a.dropped.add("bad", 1);
        let mut b = StageTelemetry::new("x");
        b.received = 5;
        b.sent = 5;
        b.dropped.add("bad", 2);
        b.dropped.add("other", 1);
        a.merge(&b);
        let r = a.report();
        assert_eq!((r.received, r.sent), (8, 7));
        assert_eq!(r.dropped["bad"], 3);
        assert_eq!(r.dropped["other"], 1);
    }
}
