//! Forest metrics of the rows of a waveform table (`fwlidar process --metrics`): the same
//! [`WaveformMetrics`] and the same `pulse_metrics.csv` columns as the replay's `metrics` stage
//! and sink, for waveforms that come as a table (one per row) rather than as pulses.
//!
//! A table states no time, no noise and usually no geometry, so:
//!
//! - **Time axis**: sample 0 of a row (after `--skip-columns`) is 0 ns; `top_ns`, `ground_ns`
//!   and `bottom_ns` are `bin × sample interval`; `gps_time` is empty and `pulse_id` is the
//!   0-based row index (as in `--returns`).
//! - **Noise**: for the raw row, the metrics stage's robust estimate (upper-clipped median and
//!   1.4826 × MAD, [`RobustNoise`]); for the processed row after denoise, mean 0 and
//!   σ = √(π/2) × the denoise noise level, as the stage does.
//! - **Geometry**: from a geometry table ([`read_geometry`]) when given, one row per waveform:
//!   the position of sample 0 and the displacement per ns, which give the vertical metres per
//!   ns, the zenith angle and the ground `x, y, z`; without it heights use the nominal vertical
//!   scale, c/2 = 0.1499 m per ns (a nadir beam), and `x, y, z` are empty.

use std::path::Path;

use crate::forest::products::{format_row, header};
use crate::forest::pulse_metrics::{MetricsComputer, MetricsConfig, WaveformInput};
use crate::pulse::PulseGeometry;
use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
use crate::signal::robust_noise::RobustNoise;

/// Errors of the geometry table.
#[derive(Debug, thiserror::Error)]
pub enum GeometryTableError {
    /// The file could not be read.
    #[error("geometry {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A column the geometry needs is missing from the header.
    #[error("geometry {path}: no column {column} in the header (line 1){hint}")]
    MissingColumn {
        /// The file.
        path: String,
        /// The column name.
        column: &'static str,
        /// What else would do.
        hint: &'static str,
    },
    /// A cell is not a finite number, or a line is short.
    #[error("geometry {path}: line {line}, column {column}: {reason}")]
    Cell {
        /// The file.
        path: String,
        /// 1-based line.
        line: usize,
        /// The column name.
        column: String,
        /// What is wrong.
        reason: String,
    },
    /// The table has no data rows, or not one per waveform.
    #[error("geometry {path}: {reason}")]
    Rows {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
}

/// The geometry columns: names accepted for each of x0, y0, z0, dx, dy, dz (ours first, then
/// the waveformlidar R package's `geo` table: `V9`–`V11` are the position of return bin 0).
const GEOMETRY_COLUMNS: [(&str, &[&str]); 6] = [
    ("x0", &["x0", "V9"]),
    ("y0", &["y0", "V10"]),
    ("z0", &["z0", "V11"]),
    ("dx", &["dx"]),
    ("dy", &["dy"]),
    ("dz", &["dz"]),
];

/// Reads a geometry table: a CSV with a header naming `x0,y0,z0` (position of the waveform's
/// sample 0, in a projected CRS: metres) and `dx,dy,dz` (displacement per ns of the time axis,
/// m/ns; for two-way ranging half the speed of light along the beam, `dz` < 0 pointing down),
/// in any order among other columns; the waveformlidar package's `geo` table (NEON's
/// `geo.csv`: `V9,V10,V11` the position of return bin 0) is read as it is. One data row per
/// waveform, in the same order. `path` names the file in errors.
pub fn parse_geometry(text: &str, path: &str) -> Result<Vec<PulseGeometry>, GeometryTableError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r')))
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, head)) = lines.next() else {
        return Err(GeometryTableError::Rows {
            path: path.to_string(),
            reason: "the file is empty (a header and one row per waveform expected)".into(),
        });
    };
    let names: Vec<String> = head
        .split(',')
        .map(|c| c.trim().trim_matches('"').to_string())
        .collect();
    let mut index = [0usize; 6];
    for (k, (name, accepted)) in GEOMETRY_COLUMNS.iter().enumerate() {
        index[k] = accepted
            .iter()
            .find_map(|a| names.iter().position(|n| n == a))
            .ok_or_else(|| GeometryTableError::MissingColumn {
                path: path.to_string(),
                column: name,
                hint: match *name {
                    "x0" | "y0" | "z0" => {
                        " (nor V9, V10, V11 of the waveformlidar geo table): the position of sample 0"
                    }
                    _ => ": the displacement per ns along the beam",
                },
            })?;
    }
    let mut out = Vec::new();
    for (line, l) in lines {
        let cells: Vec<&str> = l.split(',').map(str::trim).collect();
        let mut v = [0.0f64; 6];
        for (k, &j) in index.iter().enumerate() {
            let column = names[j].clone();
            let cell = cells.get(j).ok_or_else(|| GeometryTableError::Cell {
                path: path.to_string(),
                line,
                column: column.clone(),
                reason: format!("the line has only {} cells", cells.len()),
            })?;
            v[k] = match cell.trim_matches('"').parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => {
                    return Err(GeometryTableError::Cell {
                        path: path.to_string(),
                        line,
                        column,
                        reason: format!("'{cell}' is not a finite number"),
                    });
                }
            };
        }
        if v[3] == 0.0 && v[4] == 0.0 && v[5] == 0.0 {
            return Err(GeometryTableError::Cell {
                path: path.to_string(),
                line,
                column: "dx,dy,dz".into(),
                reason: "the displacement per ns is zero".into(),
            });
        }
        out.push(PulseGeometry {
            anchor: [v[0], v[1], v[2]],
            direction: [v[3], v[4], v[5]],
        });
    }
    if out.is_empty() {
        return Err(GeometryTableError::Rows {
            path: path.to_string(),
            reason: "no data rows after the header".into(),
        });
    }
    Ok(out)
}

/// Reads the geometry table at `path` ([`parse_geometry`]).
pub fn read_geometry(path: &Path) -> Result<Vec<PulseGeometry>, GeometryTableError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| GeometryTableError::Io {
        path: name.clone(),
        source,
    })?;
    parse_geometry(&text, &name)
}

/// One waveform of a table to measure.
#[derive(Clone, Copy, Debug)]
pub struct TableWaveform<'a> {
    /// 0-based row index (`pulse_id`).
    pub row: usize,
    /// Samples in the table's unit, padding removed.
    pub samples: &'a [f32],
    /// Sample interval, ns.
    pub sample_ns: f64,
    /// Noise mean and σ when known (the denoised signal), else `None` for the robust estimate.
    pub noise: Option<(f64, f64)>,
    /// Smoothing σ, ns (0: none).
    pub smoothing_ns: f64,
    /// Position of sample 0 and displacement per ns, if known.
    pub geometry: Option<PulseGeometry>,
}

/// Measures table rows and collects `pulse_metrics.csv` in memory (the job writes it only when
/// every row succeeded). Buffers are reused from row to row.
pub struct TableMetrics {
    config: MetricsConfig,
    computer: MetricsComputer,
    noise: RobustNoise,
    line: String,
    csv: String,
    by_status: [usize; 5],
}

impl TableMetrics {
    /// A collector for waveforms of up to `max_samples` samples, with `config`.
    pub fn new(config: MetricsConfig, max_samples: usize) -> Self {
        let mut csv = header(false, config.profile_bins, config.profile_bin_m);
        csv.push('\n');
        TableMetrics {
            computer: MetricsComputer::with_capacity(max_samples),
            noise: RobustNoise::with_capacity(max_samples),
            line: String::with_capacity(4096),
            csv,
            by_status: [0; 5],
            config,
        }
    }

    /// Measures one waveform, appends its row and returns its metrics.
    pub fn measure(&mut self, w: &TableWaveform<'_>) -> WaveformMetrics {
        let (mean, sd) = match w.noise {
            Some(n) => n,
            None => {
                let (l, s) = self.noise.level_and_sigma(w.samples);
                (f64::from(l), f64::from(s))
            }
        };
        let input = WaveformInput {
            samples: w.samples,
            // The leading edge (`top = "leading_edge"`) then corrects for the smoothing only.
            pulse_sigma_ns: 0.0,
            start_ns: 0.0,
            sample_ns: w.sample_ns,
            noise_mean: mean,
            noise_sd: sd,
            smoothing_ns: w.smoothing_ns,
            geometry: w.geometry,
            geographic: false,
        };
        let m = self.computer.compute(&self.config, &input);
        format_row(
            &mut self.line,
            w.row as u64,
            None,
            false,
            &m,
            self.config.profile_bins,
            f32::NAN,
        );
        self.csv.push_str(&self.line);
        self.by_status[match m.status {
            MetricsStatus::Ok => 0,
            MetricsStatus::NoSignal => 1,
            MetricsStatus::NoGround => 2,
            MetricsStatus::NoWaveform => 3,
            MetricsStatus::NonFinite => 4,
        }] += 1;
        m
    }

    /// The CSV text so far (header and one line per measured waveform).
    pub fn csv(&self) -> &str {
        &self.csv
    }

    /// Waveforms measured with status `ok`.
    pub fn ok(&self) -> usize {
        self.by_status[0]
    }

    /// Waveforms measured in all.
    pub fn measured(&self) -> usize {
        self.by_status.iter().sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometry_reads_our_names_and_the_waveformlidar_table() {
        let ours = "id,dz,x0,y0,z0,dx,dy\n1,-0.15,10,20,300,0,0.01\n";
        let g = parse_geometry(ours, "g.csv").unwrap();
        assert_eq!(g.len(), 1);
        assert_eq!(g[0].anchor, [10.0, 20.0, 300.0]);
        assert_eq!(g[0].direction, [0.0, 0.01, -0.15]);
        let neon = "index,x,y,z,dx,dy,dz,or,fr,V9,V10,V11,V12\n\
                    1,731126.6,4712693,334.69,0.0002,0.0202,-0.1485,18.5,23.1,731126.6,4712693,339.09,0\n";
        let g = parse_geometry(neon, "geo.csv").unwrap();
        assert_eq!(g[0].anchor, [731126.6, 4712693.0, 339.09]);
        assert_eq!(g[0].direction[2], -0.1485);
    }

    #[test]
    fn geometry_errors_name_the_file_line_and_column() {
        let e = parse_geometry("x0,y0,z0,dx,dy\n1,2,3,4,5\n", "g.csv").unwrap_err();
        assert!(
            e.to_string().contains("g.csv") && e.to_string().contains("dz"),
            "{e}"
        );
        let e = parse_geometry(
            "x0,y0,z0,dx,dy,dz\n1,2,3,0,0,-0.15\n1,2,abc,0,0,-0.15\n",
            "g.csv",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("g.csv")
                && e.contains("line 3")
                && e.contains("column z0")
                && e.contains("abc"),
            "{e}"
        );
        let e = parse_geometry("x0,y0,z0,dx,dy,dz\n1,2,3\n", "g.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("column dx"), "{e}");
        let e = parse_geometry("x0,y0,z0,dx,dy,dz\n1,2,3,0,0,0\n", "g.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("zero"), "{e}");
        assert!(parse_geometry("x0,y0,z0,dx,dy,dz\n", "g.csv").is_err());
        assert!(parse_geometry("", "g.csv").is_err());
    }

    /// A canopy echo 10 m above a ground echo: RH98 near 10 m at nadir without geometry, and
    /// the same heights scaled by the vertical component with a slanted geometry.
    #[test]
    fn heights_use_c_over_2_without_geometry_and_the_vertical_with_it() {
        let n = 200;
        let gauss = |i: usize, c: f64, a: f64| a * (-0.5 * ((i as f64 - c) / 2.0).powi(2)).exp();
        let ground_bin = 150.0;
        let canopy_bin = ground_bin - 10.0 / crate::core::units::HALF_C_M_PER_NS;
        let mut y: Vec<f32> = (0..n)
            .map(|i| (200.0 + gauss(i, canopy_bin, 60.0) + gauss(i, ground_bin, 120.0)) as f32)
            .collect();
        // A little deterministic noise so that the noise σ is not zero.
        for (i, v) in y.iter_mut().enumerate() {
            *v += [0.0, 1.0, -1.0, 0.5][i % 4];
        }
        let mut t = TableMetrics::new(MetricsConfig::default(), n);
        let w = TableWaveform {
            row: 0,
            samples: &y,
            sample_ns: 1.0,
            noise: None,
            smoothing_ns: 2.0,
            geometry: None,
        };
        let m = t.measure(&w);
        assert_eq!(m.status, MetricsStatus::Ok);
        assert!((m.ground_ns - ground_bin).abs() < 0.5, "{}", m.ground_ns);
        assert!((m.rh[98] - 10.0).abs() < 1.0, "{}", m.rh[98]);
        assert!(m.cover > 0.0 && m.cover < 1.0);
        // 30° off nadir: vertical metres per ns = c/2 cos 30°.
        let c2 = crate::core::units::HALF_C_M_PER_NS;
        let th = 30f64.to_radians();
        let g = PulseGeometry {
            anchor: [100.0, 200.0, 500.0],
            direction: [c2 * th.sin(), 0.0, -c2 * th.cos()],
        };
        let m2 = t.measure(&TableWaveform {
            row: 1,
            geometry: Some(g),
            ..w
        });
        assert!((m2.rh[98] / m.rh[98] - th.cos() as f32).abs() < 1e-3);
        assert!((m2.zenith_deg - 30.0).abs() < 0.01);
        let z = 500.0 - c2 * th.cos() * m2.ground_ns;
        assert!((m2.ground_xyz[2] - z).abs() < 1e-9);
        // Two rows after the header, each with the header's column count; no gps_time.
        let lines: Vec<&str> = t.csv().lines().collect();
        assert_eq!(lines.len(), 3);
        let cols = lines[0].split(',').count();
        assert!(lines[1..].iter().all(|l| l.split(',').count() == cols));
        assert!(lines[1].starts_with("0,,,,,ok,"), "{}", lines[1]);
        // x moves along the beam: 100 m + the ground's time × dx.
        let x = 100.0 + m2.ground_ns * c2 * th.sin();
        assert!(
            lines[2].starts_with(&format!("1,,{x:.3},200.000,")),
            "{}",
            lines[2]
        );
        assert_eq!((t.ok(), t.measured()), (2, 2));
    }
}
