//! The figure of `fwlidar metrics-plot`: relative heights and cover of every waveform of a
//! `pulse_metrics.csv` (the replay's, or `fwlidar process --metrics`), as an SVG written by
//! hand (no plotting dependency, like the tradeoff figure in `src/eval/plot.rs`).
//!
//! Top: one column per waveform, the ground (lowest mode) at 0 m, a grey bar from RH25 to RH98
//! (the element of class `wf`, one per waveform with metrics) and dots at RH25, RH50, RH75 and
//! RH98; waveforms sorted by RH98 or in file order (along the scan). Right of it the histogram
//! of RH98 on the same height axis. Bottom: the cover of each waveform at the same place, and
//! its histogram. Rows whose `status` is not `ok` have no metrics and are counted in the title
//! (in file order they leave a gap).

use std::fmt::Write as _;
use std::path::Path;

/// The columns the figure reads.
const COLUMNS: [&str; 7] = [
    "pulse_id", "status", "rh25", "rh50", "rh75", "rh98", "cover",
];

/// Errors reading a metrics CSV.
#[derive(Debug, thiserror::Error)]
pub enum MetricsPlotError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A column is missing from the header.
    #[error(
        "{path}: no column {column} in the header (line 1); a pulse_metrics.csv of fwlidar replay \
         or fwlidar process --metrics is expected"
    )]
    MissingColumn {
        /// The file.
        path: String,
        /// The column.
        column: &'static str,
    },
    /// A cell is not what it should be.
    #[error("{path}: line {line}, column {column}: {reason}")]
    Cell {
        /// The file.
        path: String,
        /// 1-based line.
        line: usize,
        /// The column.
        column: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// No waveform has metrics.
    #[error("{path}: {reason}")]
    Empty {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
}

/// One row of the metrics CSV.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MetricsRow {
    /// `pulse_id`.
    pub pulse_id: u64,
    /// Whether `status` is `ok`.
    pub ok: bool,
    /// RH25, RH50, RH75, RH98, m above the ground (NaN without metrics).
    pub rh: [f64; 4],
    /// Cover, 0..1 (NaN without metrics).
    pub cover: f64,
}

/// Parses the columns of [`COLUMNS`] from a metrics CSV (`path` names the file in errors).
/// Rows with `status` `ok` must have every value; the others are kept with NaN values.
pub fn parse_metrics(text: &str, path: &str) -> Result<Vec<MetricsRow>, MetricsPlotError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r')))
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, head)) = lines.next() else {
        return Err(MetricsPlotError::Empty {
            path: path.into(),
            reason: "the file is empty".into(),
        });
    };
    let names: Vec<&str> = head.split(',').map(str::trim).collect();
    let mut idx = [0usize; 7];
    for (k, c) in COLUMNS.iter().enumerate() {
        idx[k] = names
            .iter()
            .position(|n| n == c)
            .ok_or(MetricsPlotError::MissingColumn {
                path: path.into(),
                column: c,
            })?;
    }
    let mut rows = Vec::new();
    for (line, l) in lines {
        let cells: Vec<&str> = l.split(',').map(str::trim).collect();
        let cell = |k: usize| -> Result<&str, MetricsPlotError> {
            cells
                .get(idx[k])
                .copied()
                .ok_or_else(|| MetricsPlotError::Cell {
                    path: path.into(),
                    line,
                    column: COLUMNS[k],
                    reason: format!("the line has only {} cells", cells.len()),
                })
        };
        let id_text = cell(0)?;
        let pulse_id = id_text.parse::<u64>().map_err(|_| MetricsPlotError::Cell {
            path: path.into(),
            line,
            column: COLUMNS[0],
            reason: format!("'{id_text}' is not a pulse number"),
        })?;
        let ok = cell(1)? == "ok";
        let mut vals = [f64::NAN; 5];
        if ok {
            for (j, v) in vals.iter_mut().enumerate() {
                let k = j + 2;
                let t = cell(k)?;
                *v = match t.parse::<f64>() {
                    Ok(x) if x.is_finite() => x,
                    _ => {
                        return Err(MetricsPlotError::Cell {
                            path: path.into(),
                            line,
                            column: COLUMNS[k],
                            reason: format!(
                                "'{t}' is not a finite number (the row's status is ok)"
                            ),
                        });
                    }
                };
            }
        }
        rows.push(MetricsRow {
            pulse_id,
            ok,
            rh: [vals[0], vals[1], vals[2], vals[3]],
            cover: vals[4],
        });
    }
    if !rows.iter().any(|r| r.ok) {
        return Err(MetricsPlotError::Empty {
            path: path.into(),
            reason: format!(
                "none of its {} rows has status ok: nothing to plot",
                rows.len()
            ),
        });
    }
    Ok(rows)
}

/// Reads a metrics CSV ([`parse_metrics`]).
pub fn read_metrics(path: &Path) -> Result<Vec<MetricsRow>, MetricsPlotError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| MetricsPlotError::Io {
        path: name.clone(),
        source,
    })?;
    parse_metrics(&text, &name)
}

/// Order of the waveforms along the x axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PlotOrder {
    /// Sorted by RH98, lowest first.
    Rh98,
    /// In file order (along the track or scan); rows without metrics leave a gap.
    Track,
}

/// Figure size and panels, px.
const WIDTH: f64 = 1000.0;
const HEIGHT: f64 = 660.0;
const LEFT: f64 = 70.0;
const PW: f64 = 700.0;
const TOP_A: f64 = 80.0;
const PH_A: f64 = 330.0;
const TOP_B: f64 = 470.0;
const PH_B: f64 = 130.0;
const HIST_X: f64 = 800.0;
const HIST_W: f64 = 170.0;

/// Colours of RH25, RH50, RH75, RH98 (a diverging scheme readable in print).
const RH_COLOURS: [&str; 4] = ["#74add1", "#4575b4", "#f46d43", "#a50026"];
const RH_NAMES: [&str; 4] = ["RH25", "RH50", "RH75", "RH98"];
const COVER_COLOUR: &str = "#1b7837";

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A round step for an axis spanning `span` with about `ticks` ticks.
fn nice_step(span: f64, ticks: f64) -> f64 {
    if !(span.is_finite() && span > 0.0) {
        return 1.0;
    }
    let raw = span / ticks;
    let mag = 10f64.powf(raw.log10().floor());
    for m in [1.0, 2.0, 2.5, 5.0, 10.0] {
        if m * mag >= raw {
            return m * mag;
        }
    }
    10.0 * mag
}

/// Median of `v` (the mean of the middle two for an even count), NaN when empty.
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The SVG document for `rows` (at least one `ok`), titled `title`.
pub fn svg(rows: &[MetricsRow], order: PlotOrder, title: &str) -> String {
    let ok: Vec<&MetricsRow> = rows.iter().filter(|r| r.ok).collect();
    let layout = Layout::new(rows, &ok, order);
    let mut s = String::with_capacity(256 * ok.len() + 8192);
    heading(&mut s, rows, &ok, title);
    height_axis(&mut s, &layout);
    height_marks(&mut s, &layout);
    cover_panel(&mut s, &layout);
    waveform_axis(&mut s, &layout, rows, order);
    histograms(&mut s, &layout, &ok);
    s.push_str("</svg>\n");
    s
}

/// Where the waveforms and heights go in the figure.
struct Layout<'a> {
    /// Waveforms with metrics and their x slot.
    placed: Vec<(usize, &'a MetricsRow)>,
    /// Number of x slots: waveforms with metrics (sorted by RH98) or rows (file order).
    slots: usize,
    /// Width of one slot, px.
    slot_w: f64,
    /// Lowest tick of the height axis, m above the ground.
    y_lo: f64,
    /// Highest tick of the height axis, m above the ground.
    y_hi: f64,
    /// Step between the height axis' ticks, m.
    step: f64,
}

impl<'a> Layout<'a> {
    /// The layout of `rows` (`ok` those with metrics) in `order`: the x slot of each
    /// waveform, and a height axis from below the lowest RH25 (and 0) to above the highest
    /// RH98.
    fn new(rows: &'a [MetricsRow], ok: &[&'a MetricsRow], order: PlotOrder) -> Self {
        let (placed, slots): (Vec<(usize, &MetricsRow)>, usize) = match order {
            PlotOrder::Rh98 => {
                let mut v = ok.to_vec();
                v.sort_by(|a, b| a.rh[3].total_cmp(&b.rh[3]));
                (v.into_iter().enumerate().collect(), ok.len())
            }
            PlotOrder::Track => (
                rows.iter()
                    .enumerate()
                    .filter(|(_, r)| r.ok)
                    .collect::<Vec<_>>(),
                rows.len(),
            ),
        };
        let slot_w = PW / slots.max(1) as f64;
        let lo = ok.iter().map(|r| r.rh[0]).fold(0.0f64, f64::min).min(-0.5);
        let hi = ok.iter().map(|r| r.rh[3]).fold(1.0f64, f64::max);
        let step = nice_step(hi - lo, 6.0);
        Layout {
            placed,
            slots,
            slot_w,
            y_lo: (lo / step).floor() * step,
            y_hi: (hi / step).ceil() * step,
            step,
        }
    }

    /// x of the centre of slot `i`, px.
    fn x(&self, i: usize) -> f64 {
        LEFT + (i as f64 + 0.5) * self.slot_w
    }

    /// y of height `h` (m above the ground) in the height panel, px.
    fn y_height(&self, h: f64) -> f64 {
        TOP_A + PH_A - (h - self.y_lo) / (self.y_hi - self.y_lo) * PH_A
    }

    /// Diameter of a waveform's dots, px.
    fn dot(&self) -> f64 {
        (1.2 * self.slot_w).clamp(1.6, 5.0)
    }
}

/// y of cover `c` (0..1, clamped) in the cover panel, px.
fn y_cover(c: f64) -> f64 {
    TOP_B + PH_B - c.clamp(0.0, 1.0) * PH_B
}

/// The document's opening, the title, and a line with the counts of waveforms with and without
/// metrics and the medians of RH98, RH50 (m) and cover; then what the heights are.
fn heading(s: &mut String, rows: &[MetricsRow], ok: &[&MetricsRow], title: &str) {
    let med98 = median(ok.iter().map(|r| r.rh[3]).collect());
    let med50 = median(ok.iter().map(|r| r.rh[1]).collect());
    let medc = median(ok.iter().map(|r| r.cover).collect());
    let _ = write!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" font-family="sans-serif" font-size="12">"#
    );
    let _ = write!(
        s,
        r#"<title>{}</title><rect width="{WIDTH}" height="{HEIGHT}" fill="white"/>"#,
        escape(title)
    );
    let _ = write!(
        s,
        r#"<text x="{LEFT}" y="24" font-size="15" font-weight="bold">{}</text>"#,
        escape(title)
    );
    let _ = write!(
        s,
        r#"<text x="{LEFT}" y="44">{} waveforms with metrics of {} ({} without: no signal or no ground); median RH98 {:.2} m, RH50 {:.2} m, cover {:.2}</text>"#,
        ok.len(),
        rows.len(),
        rows.len() - ok.len(),
        med98,
        med50,
        medc
    );
    let _ = write!(
        s,
        r##"<text x="{LEFT}" y="62" fill="#555">Heights above the ground (the lowest mode of each waveform) at 0 m; grey bar RH25–RH98.</text>"##
    );
}

/// The height panel's frame, grid lines with their labels (m) and axis title.
fn height_axis(s: &mut String, l: &Layout<'_>) {
    let _ = write!(
        s,
        r##"<rect x="{LEFT}" y="{TOP_A}" width="{PW}" height="{PH_A}" fill="none" stroke="#999"/>"##
    );
    let mut h = l.y_lo;
    while h <= l.y_hi + l.step * 1e-6 {
        let y = l.y_height(h);
        let _ = write!(
            s,
            r##"<line x1="{LEFT}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#eee"/><text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"##,
            LEFT + PW,
            LEFT - 6.0,
            y + 4.0,
            fmt_tick(h, l.step)
        );
        h += l.step;
    }
    let _ = write!(
        s,
        r#"<text transform="translate(22 {:.1}) rotate(-90)" text-anchor="middle">height above ground, m</text>"#,
        TOP_A + PH_A / 2.0
    );
}

/// The height panel's content: per waveform the RH25–RH98 bar (one element each), the ground
/// line, the dots of each RH level (one path per level) and their legend.
fn height_marks(s: &mut String, l: &Layout<'_>) {
    let bar_w = (0.8 * l.slot_w).clamp(0.4, 6.0);
    let _ = write!(s, r##"<g stroke="#c8c8c8" stroke-width="{bar_w:.2}">"##);
    for (i, r) in &l.placed {
        let x = l.x(*i);
        let _ = write!(
            s,
            r#"<path class="wf" d="M{x:.1} {:.1}V{:.1}"/>"#,
            l.y_height(r.rh[0]),
            l.y_height(r.rh[3])
        );
    }
    s.push_str("</g>");
    // Ground line.
    let _ = write!(
        s,
        r##"<line x1="{LEFT}" y1="{0:.1}" x2="{1:.1}" y2="{0:.1}" stroke="#8c510a" stroke-width="1.5"/><text x="{2:.1}" y="{3:.1}" fill="#8c510a">ground</text>"##,
        l.y_height(0.0),
        LEFT + PW,
        LEFT + 4.0,
        l.y_height(0.0) + 14.0
    );
    // Dots: one path per RH level (round caps of zero-length segments).
    let dot = l.dot();
    for (k, colour) in RH_COLOURS.iter().enumerate() {
        let _ = write!(
            s,
            r#"<path fill="none" stroke="{colour}" stroke-width="{dot:.2}" stroke-linecap="round" d=""#
        );
        for (i, r) in &l.placed {
            let _ = write!(s, "M{:.1} {:.1}h0", l.x(*i), l.y_height(r.rh[k]));
        }
        s.push_str(r#""/>"#);
    }
    // Legend.
    for (k, (name, colour)) in RH_NAMES.iter().zip(RH_COLOURS).enumerate() {
        let x = LEFT + 10.0 + 70.0 * k as f64;
        let y = TOP_A + 14.0;
        let _ = write!(
            s,
            r#"<circle cx="{x:.1}" cy="{y:.1}" r="4" fill="{colour}"/><text x="{:.1}" y="{:.1}">{name}</text>"#,
            x + 8.0,
            y + 4.0
        );
    }
}

/// The cover panel: frame, grid lines at quarters with labels, axis title and the cover of
/// each waveform as a dot.
fn cover_panel(s: &mut String, l: &Layout<'_>) {
    let _ = write!(
        s,
        r##"<rect x="{LEFT}" y="{TOP_B}" width="{PW}" height="{PH_B}" fill="none" stroke="#999"/>"##
    );
    for c in [0.0, 0.25, 0.5, 0.75, 1.0] {
        let y = y_cover(c);
        let _ = write!(
            s,
            r##"<line x1="{LEFT}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#eee"/><text x="{:.1}" y="{:.1}" text-anchor="end">{c}</text>"##,
            LEFT + PW,
            LEFT - 6.0,
            y + 4.0
        );
    }
    let _ = write!(
        s,
        r#"<text transform="translate(22 {:.1}) rotate(-90)" text-anchor="middle">cover</text>"#,
        TOP_B + PH_B / 2.0
    );
    let dot = l.dot();
    let _ = write!(
        s,
        r#"<path fill="none" stroke="{COVER_COLOUR}" stroke-width="{dot:.2}" stroke-linecap="round" d=""#
    );
    for (i, r) in &l.placed {
        let _ = write!(s, "M{:.1} {:.1}h0", l.x(*i), y_cover(r.cover));
    }
    s.push_str(r#""/>"#);
}

/// The x axis under the cover panel: ticks labelled with the rank (sorted by RH98) or the
/// pulse id (file order), and the axis title.
fn waveform_axis(s: &mut String, l: &Layout<'_>, rows: &[MetricsRow], order: PlotOrder) {
    let xstep = nice_step(l.slots as f64, 8.0).max(1.0);
    let mut t = 0.0;
    while t < l.slots as f64 {
        let i = t as usize;
        let x = l.x(i);
        let label = match order {
            PlotOrder::Rh98 => format!("{}", i + 1),
            PlotOrder::Track => format!("{}", rows[i].pulse_id),
        };
        let _ = write!(
            s,
            r##"<line x1="{x:.1}" y1="{0:.1}" x2="{x:.1}" y2="{1:.1}" stroke="#999"/><text x="{x:.1}" y="{2:.1}" text-anchor="middle">{label}</text>"##,
            TOP_B + PH_B,
            TOP_B + PH_B + 4.0,
            TOP_B + PH_B + 17.0
        );
        t += xstep;
    }
    let _ = write!(
        s,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
        LEFT + PW / 2.0,
        TOP_B + PH_B + 36.0,
        match order {
            PlotOrder::Rh98 => "waveform, sorted by RH98 (rank)",
            PlotOrder::Track => "waveform in file order (pulse_id, along the scan)",
        }
    );
}

/// The histograms right of the panels: RH98 of the waveforms `ok` on the height panel's axis
/// (bins of half a tick step), cover on the cover panel's (bins of 0.1).
fn histograms(s: &mut String, l: &Layout<'_>, ok: &[&MetricsRow]) {
    let hbin = l.step / 2.0;
    let nh = ((l.y_hi - l.y_lo) / hbin).round().max(1.0) as usize;
    let mut counts = vec![0usize; nh];
    for r in ok {
        let b = (((r.rh[3] - l.y_lo) / hbin).floor().max(0.0) as usize).min(nh - 1);
        counts[b] += 1;
    }
    histogram(s, &counts, TOP_A, PH_A, "RH98", RH_COLOURS[3]);
    let mut cc = [0usize; 10];
    for r in ok {
        cc[((r.cover * 10.0).floor().max(0.0) as usize).min(9)] += 1;
    }
    histogram(s, &cc, TOP_B, PH_B, "cover", COVER_COLOUR);
}

/// Horizontal bars of `counts` (lowest bin at the bottom) in the column right of a panel.
fn histogram(s: &mut String, counts: &[usize], top: f64, height: f64, what: &str, colour: &str) {
    let max = counts.iter().copied().max().unwrap_or(0).max(1) as f64;
    let bh = height / counts.len() as f64;
    let _ = write!(
        s,
        r##"<rect x="{HIST_X}" y="{top}" width="{HIST_W}" height="{height}" fill="none" stroke="#999"/><g fill="{colour}" fill-opacity="0.8">"##
    );
    for (b, &c) in counts.iter().enumerate() {
        if c == 0 {
            continue;
        }
        let y = top + height - (b + 1) as f64 * bh;
        let _ = write!(
            s,
            r#"<rect x="{HIST_X}" y="{y:.1}" width="{:.1}" height="{:.1}"/>"#,
            c as f64 / max * (HIST_W - 10.0),
            (bh - 0.5).max(0.5)
        );
    }
    let _ = write!(
        s,
        r#"</g><text x="{:.1}" y="{:.1}" text-anchor="middle">{what} histogram (max {})</text>"#,
        HIST_X + HIST_W / 2.0,
        top + height + 17.0,
        max as usize
    );
}

fn fmt_tick(v: f64, step: f64) -> String {
    if step >= 1.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.1}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CSV: &str = "pulse_id,gps_time,status,canopy_height,rh25,rh50,rh75,rh98,cover\n\
        0,,ok,21,2,8,15,20,0.8\n\
        1,,no_signal,,,,,,\n\
        2,,ok,11,-0.5,1,6,10,0.4\n";

    #[test]
    fn reads_rows_and_draws_one_bar_per_waveform_with_metrics() {
        let rows = parse_metrics(CSV, "m.csv").unwrap();
        assert_eq!(rows.len(), 3);
        assert!(rows[0].ok && !rows[1].ok && rows[2].ok);
        assert_eq!(rows[2].rh, [-0.5, 1.0, 6.0, 10.0]);
        for order in [PlotOrder::Rh98, PlotOrder::Track] {
            let svg = svg(&rows, order, "a <test> & more");
            assert_eq!(svg.matches(r#"class="wf""#).count(), 2);
            assert!(svg.contains("a &lt;test&gt; &amp; more"));
            assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        }
        // Sorted by RH98: the 10 m waveform's bar comes first (left), reaching higher (smaller
        // y) for the 20 m one.
        let s = svg(&rows, PlotOrder::Rh98, "t");
        let bars: Vec<&str> = s.split(r#"class="wf" d="M"#).skip(1).collect();
        let top = |b: &str| -> f64 {
            b.split('V')
                .nth(1)
                .unwrap()
                .split('"')
                .next()
                .unwrap()
                .parse()
                .unwrap()
        };
        assert!(top(bars[0]) > top(bars[1]));
    }

    #[test]
    fn errors_name_the_file_line_and_column() {
        let e = parse_metrics("pulse_id,status,rh25\n", "m.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("m.csv") && e.contains("rh50"), "{e}");
        let bad = CSV.replace("0,,ok,21,2,8,15,20,0.8", "0,,ok,21,2,x,15,20,0.8");
        let e = parse_metrics(&bad, "m.csv").unwrap_err().to_string();
        assert!(
            e.contains("line 2") && e.contains("column rh50") && e.contains("'x'"),
            "{e}"
        );
        let none = "pulse_id,status,rh25,rh50,rh75,rh98,cover\n0,no_signal,,,,,\n";
        assert!(
            parse_metrics(none, "m.csv")
                .unwrap_err()
                .to_string()
                .contains("nothing to plot")
        );
        let e = parse_metrics(
            "pulse_id,status,rh25,rh50,rh75,rh98,cover\nabc,ok,1,2,3,4,0.5\n",
            "m.csv",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("column pulse_id"), "{e}");
    }
}
