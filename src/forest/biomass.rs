//! Biomass models from per-pulse waveform metrics (`fwlidar biomass`, `docs/forest.md`,
//! "Biomass"): field plots with their above-ground biomass, the pulse metrics of
//! `pulse_metrics.csv` aggregated per plot, a forward-backward stepwise linear regression chosen
//! by BIC, leave-one-out cross-validation, and the prediction per raster cell.
//!
//! - **Plots** ([`read_plots`]): a CSV with a header, either squares/rectangles
//!   `plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha` or circles `plot_id,x,y,radius_m,biomass_mg_ha`
//!   (columns found by name, in any order; other columns ignored). Coordinates in the CRS of the
//!   pulse metrics (metres), biomass in Mg/ha.
//! - **Aggregation** ([`aggregate`]): per plot, over the pulses with `status` `ok` whose ground
//!   position (x, y) lies in the plot, each candidate predictor `<stat>_<column>` (stat `mean`,
//!   `p50`, `p75`, `p90`: the mean or a percentile, linear interpolation between order
//!   statistics) and its square `<stat>_<column>^2`. A plot with fewer than `min_pulses` such
//!   pulses has no predictors and is left out of the fit (listed).
//! - **Selection** ([`fit`]): forward-backward stepwise least squares. Each step adds the
//!   candidate that lowers the BIC = n ln(RSS/n) + k ln n (k = coefficients, intercept included)
//!   the most, then removes any chosen predictor whose removal lowers it; it stops when no move
//!   lowers the BIC or at `max_predictors` (default ⌊n/5⌋, at least 1: five plots per
//!   coefficient). A candidate that is constant over the plots, or (nearly) a linear
//!   combination of those chosen (singular values of the column-scaled design below 1e-8 of
//!   the largest), is skipped, never fitted.
//! - **Least squares**: the SVD of the design matrix with its columns scaled to unit length
//!   (nalgebra), so that collinear or badly scaled metrics give a clear skip, not noise.
//! - **Validation**: R², adjusted R², RMSE of the fit; leave-one-out R² and RMSE with the whole
//!   selection repeated on each n−1 plots (the honest figure: selection bias included).

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::Path;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// The statistics of a metric over a plot's pulses that may become predictors.
pub const STATS: [&str; 4] = ["mean", "p50", "p75", "p90"];

/// The `pulse_metrics.csv` columns used by default.
pub const DEFAULT_COLUMNS: [&str; 6] = ["rh50", "rh75", "rh98", "cover", "pai", "fhd"];

/// Relative singular-value threshold below which a design is taken as rank-deficient.
const RANK_TOL: f64 = 1e-8;

/// Errors of the biomass models; every message names the file and the field or line.
#[derive(Debug, thiserror::Error)]
pub enum BiomassError {
    /// Reading or writing a file failed.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: String,
        /// The operating-system error.
        source: std::io::Error,
    },
    /// A column the command needs is not in the file's header.
    #[error("{file}: no column `{column}` in the header ({have})")]
    MissingColumn {
        /// The file.
        file: String,
        /// The missing column.
        column: String,
        /// What the header has, or what was expected.
        have: String,
    },
    /// A field could not be read.
    #[error("{file}: line {line}: field `{field}`: {what}")]
    Field {
        /// The file.
        file: String,
        /// Line number (1 = header).
        line: usize,
        /// The column.
        field: String,
        /// What is wrong.
        what: String,
    },
    /// The file holds nothing usable.
    #[error("{file}: {what}")]
    Empty {
        /// The file.
        file: String,
        /// What is missing.
        what: String,
    },
    /// The model cannot be fitted.
    #[error("cannot fit a biomass model: {0}")]
    Fit(String),
    /// A model file is not one we wrote.
    #[error("{file}: not a biomass model: {what}")]
    Model {
        /// The file.
        file: String,
        /// What is wrong.
        what: String,
    },
}

/// The area of a plot, in the CRS of the pulse metrics (metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case")]
pub enum PlotShape {
    /// `x_min ≤ x < x_max`, `y_min ≤ y < y_max`.
    Rectangle {
        /// West edge.
        x_min: f64,
        /// South edge.
        y_min: f64,
        /// East edge.
        x_max: f64,
        /// North edge.
        y_max: f64,
    },
    /// Within `radius_m` of (x, y).
    Circle {
        /// Centre x.
        x: f64,
        /// Centre y.
        y: f64,
        /// Radius, metres.
        radius_m: f64,
    },
}

impl PlotShape {
    /// Whether (x, y) lies in the plot.
    pub fn contains(&self, px: f64, py: f64) -> bool {
        match *self {
            PlotShape::Rectangle {
                x_min,
                y_min,
                x_max,
                y_max,
            } => px >= x_min && px < x_max && py >= y_min && py < y_max,
            PlotShape::Circle { x, y, radius_m } => {
                (px - x).powi(2) + (py - y).powi(2) <= radius_m * radius_m
            }
        }
    }

    /// The bounding box `[x_min, y_min, x_max, y_max]`.
    pub fn bounds(&self) -> [f64; 4] {
        match *self {
            PlotShape::Rectangle {
                x_min,
                y_min,
                x_max,
                y_max,
            } => [x_min, y_min, x_max, y_max],
            PlotShape::Circle { x, y, radius_m } => {
                [x - radius_m, y - radius_m, x + radius_m, y + radius_m]
            }
        }
    }
}

/// A field plot.
#[derive(Clone, Debug, PartialEq)]
pub struct Plot {
    /// Identifier (unique in its file).
    pub id: String,
    /// Its area.
    pub shape: PlotShape,
    /// Above-ground biomass, Mg/ha.
    pub biomass_mg_ha: f64,
}

fn io_err(file: &Path, source: std::io::Error) -> BiomassError {
    BiomassError::Io {
        file: file.display().to_string(),
        source,
    }
}

fn find(header: &[&str], name: &str) -> Option<usize> {
    header.iter().position(|h| h.trim() == name)
}

fn number(file: &Path, line: usize, field: &str, text: Option<&str>) -> Result<f64, BiomassError> {
    let t = text.map(str::trim).unwrap_or("");
    let err = |what: String| BiomassError::Field {
        file: file.display().to_string(),
        line,
        field: field.to_string(),
        what,
    };
    if t.is_empty() {
        return Err(err("missing value".into()));
    }
    let v: f64 = t
        .parse()
        .map_err(|_| err(format!("cannot read {t:?} as a number")))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(err(format!("{t:?} is not a finite number")))
    }
}

/// Reads a plot table (module documentation: rectangles or circles, biomass in Mg/ha).
pub fn read_plots(path: &Path) -> Result<Vec<Plot>, BiomassError> {
    let text = std::fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    let file = path.display().to_string();
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, head)) = lines.next() else {
        return Err(BiomassError::Empty {
            file,
            what: "empty file: expected a header `plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha`"
                .into(),
        });
    };
    let header: Vec<&str> = head.split(',').map(str::trim).collect();
    let need = |name: &str, have: &str| {
        find(&header, name).ok_or_else(|| BiomassError::MissingColumn {
            file: file.clone(),
            column: name.to_string(),
            have: have.to_string(),
        })
    };
    const RECT: &str = "expected plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha or \
                        plot_id,x,y,radius_m,biomass_mg_ha";
    let c_id = need("plot_id", RECT)?;
    let c_bio = need("biomass_mg_ha", RECT)?;
    let rect = find(&header, "x_min").is_some();
    let cols: Vec<usize> = if rect {
        ["x_min", "y_min", "x_max", "y_max"]
            .iter()
            .map(|n| need(n, RECT))
            .collect::<Result<_, _>>()?
    } else {
        ["x", "y", "radius_m"]
            .iter()
            .map(|n| need(n, RECT))
            .collect::<Result<_, _>>()?
    };
    let names: Vec<&str> = cols.iter().map(|&c| header[c]).collect();
    let mut plots: Vec<Plot> = Vec::new();
    for (i, l) in lines {
        let line = i + 1;
        let f: Vec<&str> = l.split(',').map(str::trim).collect();
        let id = f.get(c_id).copied().unwrap_or("");
        if id.is_empty() {
            return Err(BiomassError::Field {
                file,
                line,
                field: "plot_id".into(),
                what: "missing value".into(),
            });
        }
        if plots.iter().any(|p| p.id == id) {
            return Err(BiomassError::Field {
                file,
                line,
                field: "plot_id".into(),
                what: format!("plot {id:?} appears twice"),
            });
        }
        let mut v = [0.0; 4];
        for (k, (&c, name)) in cols.iter().zip(&names).enumerate() {
            v[k] = number(path, line, name, f.get(c).copied())?;
        }
        let bad = |field: &str, what: &str| BiomassError::Field {
            file: file.clone(),
            line,
            field: field.into(),
            what: what.into(),
        };
        let shape = if rect {
            if v[2] <= v[0] {
                return Err(bad("x_max", "must be greater than x_min"));
            }
            if v[3] <= v[1] {
                return Err(bad("y_max", "must be greater than y_min"));
            }
            PlotShape::Rectangle {
                x_min: v[0],
                y_min: v[1],
                x_max: v[2],
                y_max: v[3],
            }
        } else {
            if v[2] <= 0.0 {
                return Err(bad("radius_m", "must be positive"));
            }
            PlotShape::Circle {
                x: v[0],
                y: v[1],
                radius_m: v[2],
            }
        };
        let biomass_mg_ha = number(path, line, "biomass_mg_ha", f.get(c_bio).copied())?;
        if biomass_mg_ha < 0.0 {
            return Err(bad("biomass_mg_ha", "must not be negative"));
        }
        plots.push(Plot {
            id: id.to_string(),
            shape,
            biomass_mg_ha,
        });
    }
    if plots.is_empty() {
        return Err(BiomassError::Empty {
            file,
            what: "no plots after the header".into(),
        });
    }
    Ok(plots)
}

/// The pulses with metrics (`status` `ok`) of a `pulse_metrics.csv`: ground position and the
/// asked columns.
#[derive(Clone, Debug, Default)]
pub struct PulseTable {
    /// The metric columns held, in order.
    pub columns: Vec<String>,
    /// Ground x of each pulse (CRS units).
    pub x: Vec<f64>,
    /// Ground y of each pulse.
    pub y: Vec<f64>,
    /// `values[c][i]`: column `c` of pulse `i`.
    pub values: Vec<Vec<f64>>,
    /// Rows skipped: status not `ok`, or a value not finite.
    pub skipped: usize,
}

/// Reads `x`, `y`, `status` and `columns` of a `pulse_metrics.csv`, keeping the pulses whose
/// status is `ok` and whose values are all finite.
pub fn read_pulse_metrics(path: &Path, columns: &[String]) -> Result<PulseTable, BiomassError> {
    let f = std::fs::File::open(path).map_err(|e| io_err(path, e))?;
    let file = path.display().to_string();
    let mut r = BufReader::new(f);
    let mut head = String::new();
    r.read_line(&mut head).map_err(|e| io_err(path, e))?;
    let header: Vec<&str> = head.trim_end().split(',').collect();
    let need = |name: &str| {
        find(&header, name).ok_or_else(|| BiomassError::MissingColumn {
            file: file.clone(),
            column: name.to_string(),
            have: "a pulse_metrics.csv written by `fwlidar replay` has it (docs/forest.md)".into(),
        })
    };
    let (cx, cy, cs) = (need("x")?, need("y")?, need("status")?);
    let cols: Vec<usize> = columns.iter().map(|c| need(c)).collect::<Result<_, _>>()?;
    let mut t = PulseTable {
        columns: columns.to_vec(),
        values: vec![Vec::new(); columns.len()],
        ..PulseTable::default()
    };
    let mut line = String::new();
    let mut n = 1usize;
    let mut row = vec![0.0; cols.len()];
    loop {
        line.clear();
        if r.read_line(&mut line).map_err(|e| io_err(path, e))? == 0 {
            break;
        }
        n += 1;
        let l = line.trim_end();
        if l.is_empty() {
            continue;
        }
        let fields: Vec<&str> = l.split(',').collect();
        if fields.len() != header.len() {
            return Err(BiomassError::Field {
                file,
                line: n,
                field: "(row)".into(),
                what: format!("{} fields, the header has {}", fields.len(), header.len()),
            });
        }
        if fields[cs] != "ok" {
            t.skipped += 1;
            continue;
        }
        let parse = |c: usize| fields[c].trim().parse::<f64>().ok();
        let (Some(x), Some(y)) = (parse(cx), parse(cy)) else {
            t.skipped += 1;
            continue;
        };
        let mut finite = x.is_finite() && y.is_finite();
        for (k, &c) in cols.iter().enumerate() {
            match parse(c) {
                Some(v) if v.is_finite() => row[k] = v,
                _ => finite = false,
            }
        }
        if !finite {
            t.skipped += 1;
            continue;
        }
        t.x.push(x);
        t.y.push(y);
        for (k, v) in row.iter().enumerate() {
            t.values[k].push(*v);
        }
    }
    if t.x.is_empty() {
        return Err(BiomassError::Empty {
            file,
            what: "no pulse with status `ok` and finite metrics".into(),
        });
    }
    Ok(t)
}

/// One candidate predictor: a statistic of a column, to a power (1 or 2).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Term {
    /// The `pulse_metrics.csv` column.
    pub column: String,
    /// `mean`, `p50`, `p75` or `p90`.
    pub stat: String,
    /// 1 or 2.
    pub power: u32,
}

impl Term {
    /// `<stat>_<column>` or `<stat>_<column>^2`.
    pub fn name(&self) -> String {
        if self.power == 1 {
            format!("{}_{}", self.stat, self.column)
        } else {
            format!("{}_{}^{}", self.stat, self.column, self.power)
        }
    }
}

/// The candidate terms for `columns`: every statistic of [`STATS`], to the powers 1 and 2.
pub fn candidate_terms(columns: &[String]) -> Vec<Term> {
    let mut v = Vec::new();
    for c in columns {
        for s in STATS {
            for power in [1, 2] {
                v.push(Term {
                    column: c.clone(),
                    stat: s.to_string(),
                    power,
                });
            }
        }
    }
    v
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let pos = q / 100.0 * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// The statistic `stat` of `values` (not empty); `None` for an unknown name.
pub fn statistic(stat: &str, values: &mut [f64]) -> Option<f64> {
    if stat == "mean" {
        return Some(values.iter().sum::<f64>() / values.len() as f64);
    }
    let q: f64 = stat.strip_prefix('p')?.parse().ok()?;
    if !(0.0..=100.0).contains(&q) {
        return None;
    }
    values.sort_by(f64::total_cmp);
    Some(percentile(values, q))
}

/// The values of `terms` over the pulses `idx` of `table` (`None` when fewer than
/// `min_pulses`).
pub fn term_values(
    table: &PulseTable,
    idx: &[usize],
    terms: &[Term],
    min_pulses: usize,
) -> Option<Vec<f64>> {
    if idx.len() < min_pulses.max(1) {
        return None;
    }
    let mut buf = Vec::with_capacity(idx.len());
    let mut out = Vec::with_capacity(terms.len());
    for t in terms {
        let c = table.columns.iter().position(|c| *c == t.column)?;
        buf.clear();
        buf.extend(idx.iter().map(|&i| table.values[c][i]));
        let v = statistic(&t.stat, &mut buf)?;
        out.push(v.powi(t.power as i32));
    }
    Some(out)
}

/// The pulses of `table` in each plot (indices), by plot.
pub fn pulses_in_plots(table: &PulseTable, plots: &[Plot]) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); plots.len()];
    for i in 0..table.x.len() {
        let (x, y) = (table.x[i], table.y[i]);
        for (k, p) in plots.iter().enumerate() {
            if p.shape.contains(x, y) {
                out[k].push(i);
            }
        }
    }
    out
}

/// Plot-level predictors: per plot the pulse count and the term values (`None`: too few
/// pulses).
pub fn aggregate(
    table: &PulseTable,
    plots: &[Plot],
    terms: &[Term],
    min_pulses: usize,
) -> Vec<(usize, Option<Vec<f64>>)> {
    pulses_in_plots(table, plots)
        .iter()
        .map(|idx| (idx.len(), term_values(table, idx, terms, min_pulses)))
        .collect()
}

/// A least-squares fit of `y` on an intercept and the columns `cols` of `x`.
#[derive(Clone, Debug)]
struct Ls {
    coef: Vec<f64>,
    rss: f64,
}

/// Least squares through the SVD of the column-scaled design; `None` if the design is
/// rank-deficient (a constant or collinear predictor).
fn least_squares(x: &[Vec<f64>], y: &[f64], rows: &[usize], cols: &[usize]) -> Option<Ls> {
    let n = rows.len();
    let p = cols.len() + 1;
    if n < p {
        return None;
    }
    let mut a = DMatrix::<f64>::zeros(n, p);
    for (r, &i) in rows.iter().enumerate() {
        a[(r, 0)] = 1.0;
        for (k, &c) in cols.iter().enumerate() {
            a[(r, k + 1)] = x[i][c];
        }
    }
    let mut scale = vec![1.0; p];
    for (k, s) in scale.iter_mut().enumerate() {
        let norm = a.column(k).norm();
        if !(norm.is_finite() && norm > 0.0) {
            return None;
        }
        *s = norm;
        a.column_mut(k).scale_mut(1.0 / norm);
    }
    let b = DVector::from_iterator(n, rows.iter().map(|&i| y[i]));
    let svd = a.clone().svd(true, true);
    let smax = svd.singular_values.max();
    let smin = svd.singular_values.min();
    if smax.is_nan() || smax <= 0.0 || smin < RANK_TOL * smax {
        return None;
    }
    let sol = svd.solve(&b, RANK_TOL * smax).ok()?;
    let resid = &b - &a * &sol;
    let coef: Vec<f64> = sol.iter().zip(&scale).map(|(v, s)| v / s).collect();
    if !coef.iter().all(|c| c.is_finite()) {
        return None;
    }
    Some(Ls {
        coef,
        rss: resid.norm_squared(),
    })
}

/// BIC = n ln(RSS/n) + k ln n, with RSS floored at `floor` (a 1e-12 share of the total sum of
/// squares): once a fit is exact to rounding, more terms only add their penalty.
fn bic(n: usize, rss: f64, k: usize, floor: f64) -> f64 {
    let n = n as f64;
    n * (rss.max(floor).max(1e-300) / n).ln() + k as f64 * n.ln()
}

/// One step of the selection, for the record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// `add` or `remove`.
    pub action: String,
    /// The term's name.
    pub term: String,
    /// BIC after the step.
    pub bic: f64,
}

/// The result of stepwise selection on some plots.
#[derive(Clone, Debug)]
pub struct Selection {
    /// Indices of the chosen terms, in the order they entered.
    pub chosen: Vec<usize>,
    /// Intercept then one coefficient per chosen term.
    pub coef: Vec<f64>,
    /// Residual sum of squares.
    pub rss: f64,
    /// The moves made.
    pub steps: Vec<Step>,
    /// Candidates skipped at least once as constant or collinear.
    pub skipped: Vec<usize>,
}

/// Forward-backward stepwise selection by BIC on `rows` of (x, y), at most `max_terms` terms.
pub fn stepwise(
    x: &[Vec<f64>],
    y: &[f64],
    rows: &[usize],
    names: &[String],
    max_terms: usize,
) -> Result<Selection, BiomassError> {
    let n = rows.len();
    if n < 3 {
        return Err(BiomassError::Fit(format!(
            "{n} plots with predictors; at least 3 are needed"
        )));
    }
    let ncand = x.first().map_or(0, Vec::len);
    let base = least_squares(x, y, rows, &[])
        .ok_or_else(|| BiomassError::Fit("the intercept alone cannot be fitted".into()))?;
    let mut cur = Selection {
        chosen: Vec::new(),
        coef: base.coef,
        rss: base.rss,
        steps: Vec::new(),
        skipped: Vec::new(),
    };
    let mean = rows.iter().map(|&i| y[i]).sum::<f64>() / n as f64;
    let floor = 1e-12 * rows.iter().map(|&i| (y[i] - mean).powi(2)).sum::<f64>();
    let mut cur_bic = bic(n, cur.rss, 1, floor);
    // Each state is visited once at most: BIC strictly decreases with every move.
    for _ in 0..(4 * ncand + 4) {
        let mut moved = false;
        // Forward.
        if cur.chosen.len() < max_terms && cur.chosen.len() + 2 < n {
            let mut best: Option<(usize, Ls, f64)> = None;
            for c in 0..ncand {
                if cur.chosen.contains(&c) {
                    continue;
                }
                let mut cols = cur.chosen.clone();
                cols.push(c);
                let Some(ls) = least_squares(x, y, rows, &cols) else {
                    if !cur.skipped.contains(&c) {
                        cur.skipped.push(c);
                    }
                    continue;
                };
                let b = bic(n, ls.rss, cols.len() + 1, floor);
                if b < cur_bic - 1e-9 && best.as_ref().is_none_or(|(_, _, bb)| b < *bb) {
                    best = Some((c, ls, b));
                }
            }
            if let Some((c, ls, b)) = best {
                cur.chosen.push(c);
                cur.coef = ls.coef;
                cur.rss = ls.rss;
                cur_bic = b;
                cur.steps.push(Step {
                    action: "add".into(),
                    term: names[c].clone(),
                    bic: b,
                });
                moved = true;
            }
        }
        // Backward.
        loop {
            let mut best: Option<(usize, Ls, f64)> = None;
            for k in 0..cur.chosen.len() {
                let mut cols = cur.chosen.clone();
                cols.remove(k);
                let Some(ls) = least_squares(x, y, rows, &cols) else {
                    continue;
                };
                let b = bic(n, ls.rss, cols.len() + 1, floor);
                if b < cur_bic - 1e-9 && best.as_ref().is_none_or(|(_, _, bb)| b < *bb) {
                    best = Some((k, ls, b));
                }
            }
            let Some((k, ls, b)) = best else { break };
            let c = cur.chosen.remove(k);
            cur.coef = ls.coef;
            cur.rss = ls.rss;
            cur_bic = b;
            cur.steps.push(Step {
                action: "remove".into(),
                term: names[c].clone(),
                bic: b,
            });
            moved = true;
        }
        if !moved {
            break;
        }
    }
    Ok(cur)
}

/// Reads a number written as `null` (serde_json writes NaN so) as NaN.
fn nan_or_f64<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Goodness of fit of predictions against observations.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// Plots.
    pub plots: usize,
    /// 1 − SS_res / SS_tot (SS_tot about these plots' own mean).
    #[serde(deserialize_with = "nan_or_f64")]
    pub r2: f64,
    /// Root mean square error, Mg/ha.
    #[serde(deserialize_with = "nan_or_f64")]
    pub rmse: f64,
}

/// R² and RMSE of `pred` against `obs`.
pub fn scores(obs: &[f64], pred: &[f64]) -> Scores {
    let n = obs.len();
    let mean = obs.iter().sum::<f64>() / n.max(1) as f64;
    let ss_tot: f64 = obs.iter().map(|o| (o - mean).powi(2)).sum();
    let ss_res: f64 = obs.iter().zip(pred).map(|(o, p)| (o - p).powi(2)).sum();
    Scores {
        plots: n,
        r2: if ss_tot > 0.0 {
            1.0 - ss_res / ss_tot
        } else {
            f64::NAN
        },
        rmse: (ss_res / n.max(1) as f64).sqrt(),
    }
}

/// A chosen predictor and its coefficient.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Predictor {
    /// `<stat>_<column>[^2]`.
    pub name: String,
    /// The term.
    #[serde(flatten)]
    pub term: Term,
    /// Coefficient, Mg/ha per unit of the term.
    pub coefficient: f64,
}

/// Fit statistics of a model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitStats {
    /// Plots fitted.
    pub plots: usize,
    /// R² of the fit.
    #[serde(deserialize_with = "nan_or_f64")]
    pub r2: f64,
    /// Adjusted R²: 1 − (1 − R²)(n − 1)/(n − p − 1).
    #[serde(deserialize_with = "nan_or_f64")]
    pub adj_r2: f64,
    /// RMSE of the fit, Mg/ha.
    #[serde(deserialize_with = "nan_or_f64")]
    pub rmse: f64,
    /// Leave-one-out R² (selection repeated in each fold).
    #[serde(deserialize_with = "nan_or_f64")]
    pub loo_r2: f64,
    /// Leave-one-out RMSE, Mg/ha.
    #[serde(deserialize_with = "nan_or_f64")]
    pub loo_rmse: f64,
}

/// One plot's observation and prediction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlotResult {
    /// Plot id.
    pub plot_id: String,
    /// `train`, `holdout` or `excluded` (too few pulses).
    pub set: String,
    /// Pulses with metrics in the plot.
    pub pulses: usize,
    /// Field (true) biomass, Mg/ha.
    pub observed: f64,
    /// Model prediction, Mg/ha (`null` when excluded).
    pub predicted: Option<f64>,
    /// Leave-one-out prediction (training plots).
    pub loo_predicted: Option<f64>,
}

/// A fitted biomass model (`fwlidar biomass fit` writes it as JSON; `predict` reads it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BiomassModel {
    /// Always `fwlidar-biomass-model`.
    pub kind: String,
    /// fwlidar version that fitted it.
    pub fwlidar_version: String,
    /// The response: `biomass_mg_ha`.
    pub response: String,
    /// Selection criterion: `BIC`.
    pub criterion: String,
    /// The cap on the number of predictors.
    pub max_predictors: usize,
    /// Least pulses with metrics for a plot (or cell) to have predictors.
    pub min_pulses: usize,
    /// The candidate columns.
    pub columns: Vec<String>,
    /// Intercept, Mg/ha.
    pub intercept: f64,
    /// Chosen predictors, in the order they entered.
    pub predictors: Vec<Predictor>,
    /// Fit statistics on the training plots.
    pub fit: FitStats,
    /// Scores on the hold-out plots, when some were held out.
    pub holdout: Option<Scores>,
    /// The selection's moves.
    pub steps: Vec<Step>,
    /// Candidate terms skipped as constant or collinear.
    pub skipped_terms: Vec<String>,
    /// Every plot.
    pub plots: Vec<PlotResult>,
}

impl BiomassModel {
    /// The chosen terms.
    pub fn terms(&self) -> Vec<Term> {
        self.predictors.iter().map(|p| p.term.clone()).collect()
    }

    /// The prediction (Mg/ha) from the chosen terms' values.
    pub fn predict(&self, values: &[f64]) -> f64 {
        self.intercept
            + self
                .predictors
                .iter()
                .zip(values)
                .map(|(p, v)| p.coefficient * v)
                .sum::<f64>()
    }

    /// Reads a model written by `fwlidar biomass fit`.
    pub fn read(path: &Path) -> Result<BiomassModel, BiomassError> {
        let text = std::fs::read_to_string(path).map_err(|e| io_err(path, e))?;
        let m: BiomassModel = serde_json::from_str(&text).map_err(|e| BiomassError::Model {
            file: path.display().to_string(),
            what: e.to_string(),
        })?;
        if m.kind != "fwlidar-biomass-model" {
            return Err(BiomassError::Model {
                file: path.display().to_string(),
                what: format!("field `kind` is {:?}", m.kind),
            });
        }
        for p in &m.predictors {
            if statistic(&p.term.stat, &mut [1.0]).is_none() || !(1..=2).contains(&p.term.power) {
                return Err(BiomassError::Model {
                    file: path.display().to_string(),
                    what: format!("field `predictors`: unknown term {:?}", p.name),
                });
            }
        }
        Ok(m)
    }
}

/// What to fit.
#[derive(Clone, Debug)]
pub struct FitOptions {
    /// Candidate `pulse_metrics.csv` columns.
    pub columns: Vec<String>,
    /// Cap on predictors (`None`: ⌊n/5⌋, at least 1).
    pub max_predictors: Option<usize>,
    /// Least pulses for a plot to enter.
    pub min_pulses: usize,
    /// Plots held out of the fit (by index in the plot table).
    pub holdout: Vec<bool>,
}

/// The deterministic hold-out split: plot `i` (in file order) is held out when
/// ⌊(i+1)·f⌋ > ⌊i·f⌋ — evenly spread; `f` = 0.5 holds out every second plot.
pub fn holdout_by_fraction(n: usize, fraction: f64) -> Vec<bool> {
    (0..n)
        .map(|i| ((i + 1) as f64 * fraction).floor() > (i as f64 * fraction).floor())
        .collect()
}

/// Fits the model: aggregation, stepwise selection on the training plots, LOO, hold-out.
pub fn fit(
    plots: &[Plot],
    table: &PulseTable,
    opt: &FitOptions,
) -> Result<BiomassModel, BiomassError> {
    let terms = candidate_terms(&opt.columns);
    let names: Vec<String> = terms.iter().map(Term::name).collect();
    let agg = aggregate(table, plots, &terms, opt.min_pulses);
    let x: Vec<Vec<f64>> = agg
        .iter()
        .map(|(_, v)| v.clone().unwrap_or_default())
        .collect();
    let y: Vec<f64> = plots.iter().map(|p| p.biomass_mg_ha).collect();
    let usable = |i: usize| agg[i].1.is_some();
    let train: Vec<usize> = (0..plots.len())
        .filter(|&i| usable(i) && !opt.holdout.get(i).copied().unwrap_or(false))
        .collect();
    let hold: Vec<usize> = (0..plots.len())
        .filter(|&i| usable(i) && opt.holdout.get(i).copied().unwrap_or(false))
        .collect();
    let n = train.len();
    let max_terms = opt.max_predictors.unwrap_or((n / 5).max(1));
    let sel = stepwise(&x, &y, &train, &names, max_terms)?;
    let predict = |coef: &[f64], chosen: &[usize], i: usize| {
        coef[0]
            + chosen
                .iter()
                .zip(&coef[1..])
                .map(|(&c, b)| b * x[i][c])
                .sum::<f64>()
    };
    // Leave one out, selection included.
    let mut loo = vec![None; plots.len()];
    for (k, &i) in train.iter().enumerate() {
        let rest: Vec<usize> = train
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .map(|(_, &r)| r)
            .collect();
        if let Ok(s) = stepwise(&x, &y, &rest, &names, max_terms) {
            loo[i] = Some(predict(&s.coef, &s.chosen, i));
        }
    }
    let fit_pred: Vec<f64> = train
        .iter()
        .map(|&i| predict(&sel.coef, &sel.chosen, i))
        .collect();
    let obs: Vec<f64> = train.iter().map(|&i| y[i]).collect();
    let s = scores(&obs, &fit_pred);
    let p = sel.chosen.len() as f64;
    let adj_r2 = if (n as f64) - p - 1.0 > 0.0 {
        1.0 - (1.0 - s.r2) * (n as f64 - 1.0) / (n as f64 - p - 1.0)
    } else {
        f64::NAN
    };
    let (lo_obs, lo_pred): (Vec<f64>, Vec<f64>) = train
        .iter()
        .filter_map(|&i| loo[i].map(|v| (y[i], v)))
        .unzip();
    let ls = scores(&lo_obs, &lo_pred);
    let holdout = (!hold.is_empty()).then(|| {
        let o: Vec<f64> = hold.iter().map(|&i| y[i]).collect();
        let pr: Vec<f64> = hold
            .iter()
            .map(|&i| predict(&sel.coef, &sel.chosen, i))
            .collect();
        scores(&o, &pr)
    });
    let results = plots
        .iter()
        .enumerate()
        .map(|(i, pl)| PlotResult {
            plot_id: pl.id.clone(),
            set: if !usable(i) {
                "excluded".into()
            } else if opt.holdout.get(i).copied().unwrap_or(false) {
                "holdout".into()
            } else {
                "train".into()
            },
            pulses: agg[i].0,
            observed: pl.biomass_mg_ha,
            predicted: usable(i).then(|| predict(&sel.coef, &sel.chosen, i)),
            loo_predicted: loo[i],
        })
        .collect();
    Ok(BiomassModel {
        kind: "fwlidar-biomass-model".into(),
        fwlidar_version: env!("CARGO_PKG_VERSION").into(),
        response: "biomass_mg_ha".into(),
        criterion: "BIC".into(),
        max_predictors: max_terms,
        min_pulses: opt.min_pulses,
        columns: opt.columns.clone(),
        intercept: sel.coef[0],
        predictors: sel
            .chosen
            .iter()
            .zip(&sel.coef[1..])
            .map(|(&c, &b)| Predictor {
                name: names[c].clone(),
                term: terms[c].clone(),
                coefficient: b,
            })
            .collect(),
        fit: FitStats {
            plots: n,
            r2: s.r2,
            adj_r2,
            rmse: s.rmse,
            loo_r2: ls.r2,
            loo_rmse: ls.rmse,
        },
        holdout,
        steps: sel.steps,
        skipped_terms: sel.skipped.iter().map(|&c| names[c].clone()).collect(),
        plots: results,
    })
}

/// Allometry: above-ground biomass of one tree, kg, by Chave et al. (2014), "Improved
/// allometric models to estimate the aboveground biomass of tropical trees", Global Change
/// Biology 20, 3177–3190, eq. 4: `AGB = 0.0673 (ρ D² H)^0.976`, `ρ` wood density g/cm³, `D`
/// diameter at breast height cm, `H` height m.
pub fn chave2014_agb_kg(wood_density: f64, dbh_cm: f64, height_m: f64) -> f64 {
    0.0673 * (wood_density * dbh_cm * dbh_cm * height_m).powf(0.976)
}

/// The pulses (indices) of each raster cell (column, row of the anchored grid).
pub type CellPulses = HashMap<(i64, i64), Vec<usize>>;

/// Groups pulses by raster cell: the cell (col, row) of each pulse on a grid of `cell` metres
/// anchored at multiples of `cell`, with the grid's bounds.
pub fn cells_of(table: &PulseTable, cell: f64) -> (CellPulses, [i64; 4]) {
    let mut m: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    let mut b = [i64::MAX, i64::MAX, i64::MIN, i64::MIN];
    for i in 0..table.x.len() {
        let (cx, cy) = (
            (table.x[i] / cell).floor() as i64,
            (table.y[i] / cell).floor() as i64,
        );
        b = [b[0].min(cx), b[1].min(cy), b[2].max(cx), b[3].max(cy)];
        m.entry((cx, cy)).or_default().push(i);
    }
    (m, b)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Plots of 10 x 10 m in a row, pulses on a 1 m grid in each; column `h` of a pulse in
    /// plot k is `hk[k]` plus a pattern that averages to zero; `c` another column.
    fn synthetic(hk: &[f64], ck: &[f64]) -> (Vec<Plot>, PulseTable) {
        let mut t = PulseTable {
            columns: vec!["h".into(), "c".into()],
            values: vec![Vec::new(), Vec::new()],
            ..PulseTable::default()
        };
        let mut plots = Vec::new();
        for (k, (&h, &c)) in hk.iter().zip(ck).enumerate() {
            let x0 = 10.0 * k as f64;
            plots.push(Plot {
                id: format!("p{k}"),
                shape: PlotShape::Rectangle {
                    x_min: x0,
                    y_min: 0.0,
                    x_max: x0 + 10.0,
                    y_max: 10.0,
                },
                biomass_mg_ha: 0.0,
            });
            for i in 0..10 {
                for j in 0..10 {
                    t.x.push(x0 + i as f64 + 0.5);
                    t.y.push(j as f64 + 0.5);
                    let wiggle = if (i + j) % 2 == 0 { 0.5 } else { -0.5 };
                    t.values[0].push(h + wiggle);
                    t.values[1].push(c);
                }
            }
        }
        (plots, t)
    }

    fn opts(n: usize) -> FitOptions {
        FitOptions {
            columns: vec!["h".into(), "c".into()],
            max_predictors: None,
            min_pulses: 10,
            holdout: vec![false; n],
        }
    }

    #[test]
    fn recovers_a_known_linear_relation() {
        let hk: Vec<f64> = (0..20).map(|k| 5.0 + 1.3 * k as f64).collect();
        // c varies independently of h (a deterministic scramble).
        let ck: Vec<f64> = (0..20).map(|k| ((k * 7) % 11) as f64 / 10.0).collect();
        let (mut plots, t) = synthetic(&hk, &ck);
        for (p, (&h, &c)) in plots.iter_mut().zip(hk.iter().zip(&ck)) {
            p.biomass_mg_ha = 12.0 + 8.0 * h + 30.0 * c;
        }
        let m = fit(&plots, &t, &opts(20)).unwrap();
        assert!(m.fit.r2 > 0.999_999, "{:?}", m.fit);
        assert!(m.fit.rmse < 1e-6);
        assert!(m.fit.loo_rmse < 1e-6, "{:?}", m.fit);
        assert_eq!(m.predictors.len(), 2, "{:?}", m.predictors);
        let b_h = m
            .predictors
            .iter()
            .find(|p| p.term.column == "h" && p.term.power == 1)
            .expect("a linear term in h");
        let b_c = m
            .predictors
            .iter()
            .find(|p| p.term.column == "c" && p.term.power == 1)
            .expect("a linear term in c");
        assert!((b_h.coefficient - 8.0).abs() < 1e-6, "{b_h:?}");
        assert!((b_c.coefficient - 30.0).abs() < 1e-6, "{b_c:?}");
        // The intercept is 12 for the mean or p50 of h (the wiggle cancels), 12 − 8 · 0.5 for
        // its p75 or p90 (h + 0.5): equally exact fits.
        let off = if ["mean", "p50"].contains(&b_h.term.stat.as_str()) {
            0.0
        } else {
            4.0
        };
        assert!(
            (m.intercept - (12.0 - off)).abs() < 1e-5,
            "{} {b_h:?}",
            m.intercept
        );
        for p in &m.plots {
            assert!((p.predicted.unwrap() - p.observed).abs() < 1e-6, "{p:?}");
        }
    }

    #[test]
    fn a_noisy_relation_scores_below_one_and_holdout_is_scored() {
        let hk: Vec<f64> = (0..20).map(|k| 5.0 + k as f64).collect();
        let ck = vec![0.5; 20];
        let (mut plots, t) = synthetic(&hk, &ck);
        for (k, (p, &h)) in plots.iter_mut().zip(&hk).enumerate() {
            let noise = if k % 3 == 0 { 6.0 } else { -3.0 };
            p.biomass_mg_ha = 10.0 * h + noise;
        }
        let mut o = opts(20);
        o.holdout = holdout_by_fraction(20, 0.5);
        assert_eq!(o.holdout.iter().filter(|h| **h).count(), 10);
        assert!(!o.holdout[0] && o.holdout[1]);
        let m = fit(&plots, &t, &o).unwrap();
        assert_eq!(m.fit.plots, 10);
        assert!(m.fit.r2 > 0.95 && m.fit.r2 < 1.0, "{:?}", m.fit);
        assert!(m.fit.loo_rmse >= m.fit.rmse, "{:?}", m.fit);
        let h = m.holdout.unwrap();
        assert_eq!(h.plots, 10);
        assert!(h.r2 > 0.9 && h.rmse > 1.0 && h.rmse < 10.0, "{h:?}");
        // The constant column c is never chosen: skipped as collinear with the intercept.
        assert!(m.predictors.iter().all(|p| p.term.column != "c"));
        assert!(
            m.skipped_terms.iter().any(|s| s == "mean_c"),
            "{:?}",
            m.skipped_terms
        );
    }

    #[test]
    fn collinear_and_degenerate_inputs_do_not_panic() {
        // Two identical columns: only one can enter.
        let hk: Vec<f64> = (0..12).map(|k| 3.0 + k as f64).collect();
        let (mut plots, mut t) = synthetic(&hk, &hk);
        t.values[1] = t.values[0].clone();
        for (p, &h) in plots.iter_mut().zip(&hk) {
            p.biomass_mg_ha = 4.0 * h;
        }
        let mut o = opts(12);
        o.max_predictors = Some(4);
        let m = fit(&plots, &t, &o).unwrap();
        let linear: Vec<&Predictor> = m
            .predictors
            .iter()
            .filter(|p| p.term.power == 1 && p.term.stat == "mean")
            .collect();
        assert!(linear.len() <= 1, "{:?}", m.predictors);
        assert!(m.fit.r2 > 0.999);
        // Constant response: the intercept alone (BIC cannot improve), R² undefined, no panic.
        for p in plots.iter_mut() {
            p.biomass_mg_ha = 50.0;
        }
        let m = fit(&plots, &t, &o).unwrap();
        assert!((m.intercept - 50.0).abs() < 1e-9);
        assert!(m.predictors.is_empty(), "{:?}", m.predictors);
        // Too few plots: an error, not a panic.
        let (plots2, t2) = synthetic(&[1.0, 2.0], &[0.0, 1.0]);
        let e = fit(&plots2, &t2, &opts(2)).unwrap_err();
        assert!(e.to_string().contains("at least 3"), "{e}");
        // Plots without pulses are excluded, not fitted.
        let mut far = plots.clone();
        far[0].shape = PlotShape::Circle {
            x: -1000.0,
            y: 0.0,
            radius_m: 5.0,
        };
        let m = fit(&far, &t, &o).unwrap();
        assert_eq!(m.plots[0].set, "excluded");
        assert_eq!(m.fit.plots, 11);
        // All-NaN or infinite columns never reach the fit (read_pulse_metrics drops them);
        // a design of huge values is rank-checked, not inverted blindly.
        let x = vec![vec![1e300, 1e300], vec![1e300, 1e300], vec![1e300, 1e300]];
        assert!(least_squares(&x, &[1.0, 2.0, 3.0], &[0, 1, 2], &[0, 1]).is_none());
    }

    #[test]
    fn plot_tables_and_their_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("plots.csv");
        std::fs::write(
            &p,
            "plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha,trees\na,0,0,30,30,120.5,4\nb,30,0,60,30,80,2\n",
        )
        .unwrap();
        let plots = read_plots(&p).unwrap();
        assert_eq!(plots.len(), 2);
        assert!(plots[0].shape.contains(29.9, 0.0) && !plots[0].shape.contains(30.0, 0.0));
        std::fs::write(&p, "plot_id,x,y,radius_m,biomass_mg_ha\nc,10,10,5,33\n").unwrap();
        let plots = read_plots(&p).unwrap();
        assert!(plots[0].shape.contains(13.0, 13.9) && !plots[0].shape.contains(14.0, 14.0));
        std::fs::write(&p, "plot_id,x_min,y_min,x_max,y_max\na,0,0,1,1\n").unwrap();
        let e = read_plots(&p).unwrap_err().to_string();
        assert!(
            e.contains("plots.csv") && e.contains("`biomass_mg_ha`"),
            "{e}"
        );
        std::fs::write(
            &p,
            "plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha\na,0,0,1,1,12\nb,0,0,1,x,3\n",
        )
        .unwrap();
        let e = read_plots(&p).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("`y_max`"), "{e}");
        let e = read_plots(&dir.path().join("none.csv"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("none.csv"), "{e}");
    }

    #[test]
    fn pulse_metrics_reading_keeps_ok_pulses_and_names_missing_columns() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("pulse_metrics.csv");
        std::fs::write(
            &p,
            "pulse_id,x,y,z,status,rh98\n0,1,2,0,ok,10.5\n1,1,2,0,no_ground,\n2,3,4,0,ok,nan\n",
        )
        .unwrap();
        let t = read_pulse_metrics(&p, &["rh98".into()]).unwrap();
        assert_eq!(t.x, [1.0]);
        assert_eq!(t.values[0], [10.5]);
        assert_eq!(t.skipped, 2);
        let e = read_pulse_metrics(&p, &["cover".into()])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("pulse_metrics.csv") && e.contains("`cover`"),
            "{e}"
        );
    }

    #[test]
    fn statistics_and_allometry() {
        let mut v = [4.0, 1.0, 3.0, 2.0, 5.0];
        assert_eq!(statistic("mean", &mut v), Some(3.0));
        assert_eq!(statistic("p50", &mut v), Some(3.0));
        assert_eq!(statistic("p75", &mut v), Some(4.0));
        assert!((statistic("p90", &mut v).unwrap() - 4.6).abs() < 1e-12);
        assert_eq!(statistic("sd", &mut v), None);
        // Chave et al. 2014 eq. 4: ρ 0.6, D 30 cm, H 20 m: 0.0673 · 10800^0.976.
        let agb = chave2014_agb_kg(0.6, 30.0, 20.0);
        assert!((agb - 0.0673 * 10800f64.powf(0.976)).abs() < 1e-9);
        assert!((500.0..600.0).contains(&agb), "{agb}");
    }
}
