//! The "hyper point cloud": every sample of every return segment whose processed signal lies
//! above a threshold, as a LAS 1.4 point of format 6 (`hyper_points.las`), for pulses that carry
//! geometry. The point lies where the sample was taken, `anchor + (start_ns + i · sample_ns) ·
//! direction`; intensity is the sample in digitizer counts normalised to 16 bits (as the
//! returns' intensity); extra f32 values: `signal` (V), the value itself, and `backscatter`,
//! the sample's calibrated backscatter when a `calibrate` stage ran (the LAS no-data value
//! otherwise, or before the emission). GPS time, scan angle from the pulse; return number 1 of
//! 1; classification 0.
//!
//! Written with [`PointCloudWriter`]: `hyper_points.las.partial`, provisional header at open,
//! buffers handed to the OS every `flush_s` seconds of pulse time, renamed into place at the end;
//! a crashed file is completed by `fwlidar repair`. No allocation per pulse.

use std::path::Path;

use crate::format::las_points::{PointCloudWriter, PointSix};
use crate::format::las_write::ExtraDim;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::{Pulse, SegmentKind};
use crate::sink::SinkReport;

/// Name of the file in the output folder.
pub const FILE_NAME: &str = "hyper_points.las";

/// What the hyper point sink wrote and skipped (`summary.json` → `sinks.hyper_points`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct HyperPointReport {
    /// Points written (samples above the threshold).
    pub points: u64,
    /// Pulses that gave at least one point.
    pub pulses_written: u64,
    /// Pulses without geometry: skipped.
    pub pulses_without_geometry: u64,
    /// Return segments without a processed signal (no stage filled it): skipped.
    pub segments_unprocessed: u64,
    /// Samples above the threshold whose position is not finite: skipped.
    pub samples_unrepresentable: u64,
    /// Intensities clipped to 65535.
    pub intensity_clipped: u64,
    /// The threshold, V.
    pub threshold_v: f32,
}

/// Writes `hyper_points.las`.
pub struct HyperPointSink {
    w: PointCloudWriter,
    threshold_v: f32,
    flush_s: f64,
    flushed_gps: f64,
    report: HyperPointReport,
}

impl HyperPointSink {
    /// Starts `dir/hyper_points.las` (as `.partial`): samples above `threshold_v` volts, CRS
    /// `crs_wkt`, buffers handed to the OS every `flush_s` seconds of pulse time (0: when full).
    pub fn create(
        dir: &Path,
        threshold_v: f32,
        crs_wkt: Option<&str>,
        flush_s: f64,
    ) -> Result<Self, SinkError> {
        let extra = [
            ExtraDim::f32("signal", "processed signal (V)"),
            ExtraDim::f32("backscatter", "calibrated backscatter").with_no_data(),
        ];
        Ok(HyperPointSink {
            w: PointCloudWriter::create(&dir.join(FILE_NAME), crs_wkt, &extra)
                .map_err(SinkError::output)?,
            threshold_v,
            flush_s,
            flushed_gps: f64::NAN,
            report: HyperPointReport {
                threshold_v,
                ..Default::default()
            },
        })
    }

    /// What has been written and skipped so far.
    pub fn stats(&self) -> &HyperPointReport {
        &self.report
    }
}

impl PulseSink for HyperPointSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "hyper_points"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        let Some(g) = p.geometry else {
            self.report.pulses_without_geometry += 1;
            return Ok(());
        };
        let gain = f64::from(p.gain_v_per_dn);
        let norm = f64::from(1u32 << (16 - p.bits.clamp(1, 16)));
        let before = self.report.points;
        for (s, seg) in p.segments.iter().enumerate() {
            if seg.kind != SegmentKind::Return {
                continue;
            }
            let sig = p.signal_of(s);
            if sig.is_empty() && seg.len > 0 {
                self.report.segments_unprocessed += 1;
                continue;
            }
            for (i, &v) in sig.iter().enumerate() {
                // Only values above the threshold (NaN never is).
                if v.is_nan() || v <= self.threshold_v {
                    continue;
                }
                let t = seg.start_ns + i as f64 * p.sample_ns;
                let xyz: [f64; 3] = std::array::from_fn(|k| g.anchor[k] + t * g.direction[k]);
                if xyz.iter().any(|c| !c.is_finite()) {
                    self.report.samples_unrepresentable += 1;
                    continue;
                }
                let counts = if gain > 0.0 && gain.is_finite() {
                    (f64::from(v) / gain * norm).round()
                } else {
                    0.0
                };
                let intensity = if counts > 65535.0 {
                    self.report.intensity_clipped += 1;
                    65535
                } else {
                    counts.max(0.0) as u16
                };
                let point = PointSix {
                    xyz,
                    intensity,
                    return_number: 1,
                    number_of_returns: 1,
                    classification: 0,
                    scan_angle_deg: p.scan_angle_deg[0],
                    gps_time: p.gps_time,
                };
                // Calibrated backscatter of the sample when a calibrate stage ran (NaN: no-data).
                let backscatter = p.calibration.map_or(f32::NAN, |c| c.calibrated(v, t));
                self.w
                    .push(&point, &[f64::from(v), f64::from(backscatter)])
                    .map_err(SinkError::output)?;
                self.report.points += 1;
            }
        }
        self.report.pulses_written += u64::from(self.report.points > before);
        let elapsed = p.gps_time - self.flushed_gps;
        if self.flushed_gps.is_nan() {
            self.flushed_gps = p.gps_time;
        } else if self.flush_s > 0.0 && (elapsed >= self.flush_s || elapsed < 0.0) {
            self.flushed_gps = p.gps_time;
            self.w.flush().map_err(SinkError::output)?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        self.w.flush().map_err(SinkError::output)
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        self.w.finish().map_err(SinkError::output)?;
        tracing::info!(points = self.report.points, "hyper_points.las written");
        Ok(())
    }

    fn report(&self) -> SinkReport {
        SinkReport::HyperPoints(self.report.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::PulseGeometry;

    #[test]
    fn samples_above_the_threshold_become_points_where_they_were_taken() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = HyperPointSink::create(dir.path(), 1.0, None, 0.0).unwrap();
        let mut p = Pulse {
            gps_time: 5.0,
            gain_v_per_dn: 0.5,
            bits: 16,
            sample_ns: 2.0,
            geometry: Some(PulseGeometry {
                anchor: [1000.0, 2000.0, 500.0],
                direction: [0.0, 0.0, -0.15],
            }),
            ..Default::default()
        };
        p.push_segment(SegmentKind::Outgoing, 0, 0.0, [0u16; 4]);
        p.push_segment(SegmentKind::Return, 0, 100.0, [0u16; 5]);
        p.signal = vec![9.0, 9.0, 9.0, 9.0, 0.5, 2.0, 1.0, 3.0, -4.0];
        sink.write(&p).unwrap();
        let mut q = Pulse::default();
        q.push_segment(SegmentKind::Return, 0, 0.0, [0u16; 3]);
        sink.write(&q).unwrap();
        sink.finish().unwrap();
        let r = sink.stats();
        assert_eq!(
            (r.points, r.pulses_written, r.pulses_without_geometry),
            (2, 1, 1)
        );
        let b = std::fs::read(dir.path().join(FILE_NAME)).unwrap();
        let off = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
        // 30 bytes of format 6 + two f32 extra bytes (signal, backscatter).
        assert_eq!(b.len(), off + 2 * 38);
        let z = |i: usize| {
            i32::from_le_bytes(b[off + 38 * i + 8..off + 38 * i + 12].try_into().unwrap())
        };
        // Sample 1 at 102 ns: z = 500 - 102 * 0.15 = 484.7; sample 3 at 106 ns: 484.1.
        assert_eq!((z(0), z(1)), (484_700, 484_100));
        let f = |i: usize, e: usize| {
            f32::from_le_bytes(
                b[off + 38 * i + 30 + 4 * e..off + 38 * i + 34 + 4 * e]
                    .try_into()
                    .unwrap(),
            )
        };
        assert_eq!((f(0, 0), f(1, 0)), (2.0, 3.0));
        // No calibrate stage ran: backscatter is the declared no-data value.
        assert_eq!((f(0, 1), f(1, 1)), (-9999.0, -9999.0));
        let inten = u16::from_le_bytes([b[off + 12], b[off + 13]]);
        assert_eq!(inten, 4, "2 V / 0.5 V per count");
    }
}
