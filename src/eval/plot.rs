//! The SVG figure of `fwlidar tradeoff`, written by hand (no plotting dependency): two panels
//! side by side, error against time per pulse on a logarithmic time axis, one marker per
//! setting coloured by method and labelled with its parameter, the Pareto front as a dashed
//! staircase, and vertical lines at the per-pulse time budgets of the checked pulse rates.
//! Left: RMSE (eq. 14); right: the fraction of truth peaks missed (1 − detection rate).

use std::fmt::Write as _;

use crate::eval::report::{RATES_HZ, rate};
use crate::eval::tradeoff::{Setting, SettingSummary, pareto_front};

/// Colour of each method's markers.
fn colour(method: &str) -> &'static str {
    match method {
        "raw" => "#7f7f7f",
        "denoise" => "#17becf",
        "rl" => "#1f77b4",
        "rl_acc" => "#9467bd",
        "gold" => "#ff7f0e",
        "wiener" => "#2ca02c",
        "nnls" => "#d62728",
        "rl_2ns" => "#e377c2",
        "rl_acc_2ns" => "#393b79",
        "wiener_2ns" => "#bcbd22",
        "nnls_2ns" => "#8c564b",
        // A chain (`chain:<name>`) and anything else.
        _ => "#000000",
    }
}

/// Legend names of the methods (the last, `chain`, stands for every `chain:<name>`).
const METHODS: [(&str, &str); 12] = [
    ("raw", "raw (no processing)"),
    ("denoise", "denoise only"),
    ("rl", "Richardson-Lucy (iterations)"),
    ("rl_acc", "RL accelerated, Biggs-Andrews (iterations)"),
    ("gold", "Gold (iterations)"),
    ("wiener", "Wiener (noise scale)"),
    ("nnls", "NNLS (iteration cap)"),
    ("rl_2ns", "RL to the 2 ns pulse (iterations)"),
    (
        "rl_acc_2ns",
        "accelerated RL to the 2 ns pulse, coarse-to-fine start",
    ),
    ("wiener_2ns", "Wiener to the 2 ns pulse (noise scale)"),
    ("nnls_2ns", "NNLS drawn as the 2 ns pulse (cap)"),
    ("chain", "a run configuration's stages (--chain; file name)"),
];

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The short label next to a marker: the parameter's value, or a chain's name.
fn short(set: &Setting) -> String {
    if let Some(name) = set.method.strip_prefix("chain:") {
        return name.to_string();
    }
    set.parameter
        .split_once('=')
        .map(|(_, v)| v.to_string())
        .unwrap_or_default()
}

/// Figure size, px.
const WIDTH: f64 = 1000.0;
const HEIGHT: f64 = 520.0;
/// Panel plot areas: left edges, top, width, height, px.
const PANEL_X: [f64; 2] = [75.0, 575.0];
const TOP: f64 = 60.0;
const PW: f64 = 380.0;
const PH: f64 = 330.0;

/// A round upper bound for a linear axis starting at 0, and its tick step.
fn nice_axis(max: f64) -> (f64, f64) {
    if !(max.is_finite() && max > 0.0) {
        return (1.0, 0.2);
    }
    let mag = 10f64.powf(max.log10().floor());
    for step in [0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 2.5, 5.0, 10.0] {
        let st = step * mag;
        if max / st <= 6.0 {
            return ((max / st).ceil() * st, st);
        }
    }
    (max, max / 5.0)
}

struct Panel<'a> {
    x0: f64,
    title: &'a str,
    y_label: &'a str,
    y_max: f64,
    y_step: f64,
    values: Vec<f64>,
}

/// The logarithmic time axis shared by both panels: decades `dec_lo..=dec_hi` (log10 of µs).
#[derive(Clone, Copy)]
struct TimeAxis {
    dec_lo: f64,
    dec_hi: f64,
}

impl TimeAxis {
    /// Decades covering every positive finite time and budget (µs), at least one wide;
    /// 10⁻²..10⁴ µs when there is none.
    fn covering(times: &[f64], budgets: &[f64]) -> Self {
        let finite_pos = times
            .iter()
            .chain(budgets)
            .copied()
            .filter(|t| t.is_finite() && *t > 0.0);
        let lo = finite_pos.clone().fold(f64::INFINITY, f64::min);
        let hi = finite_pos.fold(0.0f64, f64::max);
        let (dec_lo, dec_hi) = if lo.is_finite() && hi > 0.0 {
            (
                lo.log10().floor(),
                hi.log10().ceil().max(lo.log10().floor() + 1.0),
            )
        } else {
            (-2.0, 4.0)
        };
        TimeAxis { dec_lo, dec_hi }
    }

    /// x (px) of time `t` (µs; the axis' start when not positive) in the panel at `x0` (px).
    fn x(&self, x0: f64, t: f64) -> f64 {
        let t = if t > 0.0 { t } else { 10f64.powf(self.dec_lo) };
        x0 + (t.log10() - self.dec_lo) / (self.dec_hi - self.dec_lo) * PW
    }
}

impl Panel<'_> {
    /// y (px) of value `v`, clamped to the panel's range.
    fn y(&self, v: f64) -> f64 {
        TOP + PH - (v.clamp(0.0, self.y_max) / self.y_max) * PH
    }
}

/// The SVG document. `workers` sets the time budget lines (budget = workers / rate).
pub fn svg(settings: &[Setting], summary: &[SettingSummary], workers: usize) -> String {
    let times: Vec<f64> = summary.iter().map(|s| s.mean_ns / 1e3).collect();
    let budgets: Vec<f64> = RATES_HZ.iter().map(|&r| workers as f64 / r * 1e6).collect();
    let axis = TimeAxis::covering(&times, &budgets);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<?xml version="1.0" encoding="UTF-8"?>
<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" font-family="sans-serif" font-size="12">
<rect x="0" y="0" width="{WIDTH}" height="{HEIGHT}" fill="white"/>
<text x="{}" y="24" text-anchor="middle" font-size="15" font-weight="bold">fwlidar tradeoff: accuracy against time per pulse (pooled over pulse widths and truth families)</text>"#,
        WIDTH / 2.0
    );
    for p in &panels(summary) {
        panel_frame(&mut s, p, axis);
        budget_lines(&mut s, p, axis, &budgets);
        // Pareto front of this panel: a staircase through the non-dominated settings.
        let points: Vec<(f64, f64)> = times
            .iter()
            .copied()
            .zip(p.values.iter().copied())
            .collect();
        let front = pareto_front(&points);
        front_path(&mut s, p, axis, &points, &front);
        markers(&mut s, p, axis, settings, &points, &front);
        let _ = writeln!(s, "</g>");
    }
    legend(&mut s, workers);
    s
}

/// The two panels: RMSE (axis rounded up from 1.05 × the largest) and missed peaks (0..1),
/// one value per setting.
fn panels(summary: &[SettingSummary]) -> [Panel<'static>; 2] {
    let rmse: Vec<f64> = summary.iter().map(|s| s.rmse).collect();
    let missed: Vec<f64> = summary.iter().map(|s| 1.0 - s.detection_rate).collect();
    let rmax = rmse
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let (r_max, r_step) = nice_axis(rmax * 1.05);
    [
        Panel {
            x0: PANEL_X[0],
            title: "RMSE against time per pulse",
            y_label: "RMSE (eq. 14, fraction of truth peak)",
            y_max: r_max,
            y_step: r_step,
            values: rmse,
        },
        Panel {
            x0: PANEL_X[1],
            title: "Missed peaks against time per pulse",
            y_label: "1 − detection rate (eq. 15)",
            y_max: 1.0,
            y_step: 0.2,
            values: missed,
        },
    ]
}

/// Opens panel `p`'s group: its title and frame, the time axis (decades with minor ticks at
/// 2..9, and its label) and the value axis (grid lines, ticks and label).
fn panel_frame(s: &mut String, p: &Panel, axis: TimeAxis) {
    let x0 = p.x0;
    let (dec_lo, dec_hi) = (axis.dec_lo, axis.dec_hi);
    let _ = writeln!(
        s,
        r##"<g><text x="{}" y="{}" text-anchor="middle" font-weight="bold">{}</text>
<rect x="{x0}" y="{TOP}" width="{PW}" height="{PH}" fill="none" stroke="#333"/>"##,
        x0 + PW / 2.0,
        TOP - 8.0,
        escape(p.title)
    );
    // Time axis: decades, with minor ticks at 2..9.
    let mut d = dec_lo;
    while d <= dec_hi + 1e-9 {
        let x = x0 + (d - dec_lo) / (dec_hi - dec_lo) * PW;
        let _ = writeln!(
            s,
            r##"<line x1="{x:.1}" y1="{TOP}" x2="{x:.1}" y2="{}" stroke="#ddd"/><text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
            TOP + PH,
            TOP + PH + 16.0,
            format_decade(d)
        );
        if d < dec_hi - 1e-9 {
            for m in 2..10 {
                let xm = x0 + (d + (m as f64).log10() - dec_lo) / (dec_hi - dec_lo) * PW;
                let _ = writeln!(
                    s,
                    r##"<line x1="{xm:.1}" y1="{}" x2="{xm:.1}" y2="{}" stroke="#333"/>"##,
                    TOP + PH - 4.0,
                    TOP + PH
                );
            }
        }
        d += 1.0;
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">time per pulse (µs, mean, one core; log scale)</text>"#,
        x0 + PW / 2.0,
        TOP + PH + 36.0
    );
    // Value axis.
    let mut v = 0.0;
    while v <= p.y_max + 1e-12 {
        let y = p.y(v);
        let _ = writeln!(
            s,
            r##"<line x1="{x0}" y1="{y:.1}" x2="{}" y2="{y:.1}" stroke="#eee"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
            x0 + PW,
            x0 - 6.0,
            y + 4.0,
            trim_float(v)
        );
        v += p.y_step;
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle" transform="rotate(-90 {} {})">{}</text>"#,
        x0 - 52.0,
        TOP + PH / 2.0,
        x0 - 52.0,
        TOP + PH / 2.0,
        escape(p.y_label)
    );
}

/// Panel `p`'s dotted vertical lines at the pulse-rate `budgets` (µs per pulse, one per
/// [`RATES_HZ`]), labelled with their rates.
fn budget_lines(s: &mut String, p: &Panel, axis: TimeAxis, budgets: &[f64]) {
    for (&b, &r) in budgets.iter().zip(&RATES_HZ) {
        let x = axis.x(p.x0, b);
        let _ = writeln!(
            s,
            r##"<line x1="{x:.1}" y1="{TOP}" x2="{x:.1}" y2="{}" stroke="#999" stroke-dasharray="2 3"/><text x="{:.1}" y="{}" font-size="9" fill="#666" text-anchor="end" transform="rotate(-90 {:.1} {})">{}</text>"##,
            TOP + PH,
            x - 2.0,
            TOP + 4.0,
            x - 2.0,
            TOP + 4.0,
            escape(&rate(r)).replace(' ', "\u{a0}"),
        );
    }
}

/// Panel `p`'s Pareto front (indices `front` into `points`, (time µs, value) per setting) as
/// a dashed staircase; nothing when it is empty.
fn front_path(s: &mut String, p: &Panel, axis: TimeAxis, points: &[(f64, f64)], front: &[usize]) {
    if front.is_empty() {
        return;
    }
    let mut path = String::new();
    for (k, &i) in front.iter().enumerate() {
        let (x, y) = (axis.x(p.x0, points[i].0), p.y(points[i].1));
        if k == 0 {
            let _ = write!(path, "M{x:.1},{y:.1}");
        } else {
            let _ = write!(path, " H{x:.1} V{y:.1}");
        }
    }
    let _ = writeln!(
        s,
        r##"<path d="{path}" fill="none" stroke="#000" stroke-width="1.2" stroke-dasharray="6 3"/>"##
    );
}

/// Panel `p`'s markers (one per setting with a finite time and value in `points`) and their
/// parameter labels; members of `front` ringed in black.
fn markers(
    s: &mut String,
    p: &Panel,
    axis: TimeAxis,
    settings: &[Setting],
    points: &[(f64, f64)],
    front: &[usize],
) {
    for (i, set) in settings.iter().enumerate().take(points.len()) {
        let (t, v) = points[i];
        if !(t.is_finite() && v.is_finite()) {
            continue;
        }
        let (x, y) = (axis.x(p.x0, t), p.y(v));
        let on_front = front.contains(&i);
        let _ = writeln!(
            s,
            r##"<circle cx="{x:.1}" cy="{y:.1}" r="{}" fill="{}" stroke="{}" stroke-width="{}"><title>{}: {:.4} at {:.3} µs</title></circle>"##,
            if on_front { 5.5 } else { 4.5 },
            colour(&set.method),
            if on_front { "#000" } else { "#fff" },
            if on_front { 1.5 } else { 0.8 },
            escape(&set.label()),
            v,
            t
        );
        let label = short(set);
        if !label.is_empty() {
            let _ = writeln!(
                s,
                r##"<text x="{:.1}" y="{:.1}" font-size="9" fill="{}">{}</text>"##,
                x + 6.0,
                y - 5.0,
                colour(&set.method),
                escape(&label)
            );
        }
    }
}

/// The legend under the panels: the methods' colours, the front and budget line styles, and
/// what the budget lines mean for `workers` threads; closes the document.
fn legend(s: &mut String, workers: usize) {
    let ly = TOP + PH + 62.0;
    for (k, (m, name)) in METHODS.iter().enumerate() {
        let x = 40.0 + (k % 3) as f64 * 270.0;
        let y = ly + (k / 3) as f64 * 20.0;
        let _ = writeln!(
            s,
            r##"<circle cx="{x}" cy="{y}" r="5" fill="{}"/><text x="{}" y="{}">{}</text>"##,
            colour(m),
            x + 10.0,
            y + 4.0,
            escape(name)
        );
    }
    let _ = writeln!(
        s,
        r##"<path d="M840,{ly} H870" stroke="#000" stroke-dasharray="6 3"/><text x="876" y="{}">Pareto front</text>
<path d="M840,{} H870" stroke="#999" stroke-dasharray="2 3"/><text x="876" y="{}">rate budget</text>
<text x="40" y="{}" font-size="10" fill="#555">Dotted verticals: time per pulse that {workers} worker thread(s) can afford at that pulse rate. Marker labels: iterations, noise scale or cap.</text>
</svg>"##,
        ly + 4.0,
        ly + 20.0,
        ly + 24.0,
        ly + 44.0
    );
}

fn format_decade(d: f64) -> String {
    let v = 10f64.powf(d);
    if d >= 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.*}", (-d) as usize)
    }
}

fn trim_float(v: f64) -> String {
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s.is_empty() { "0".into() } else { s.into() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_axes() {
        let (m, st) = nice_axis(0.27);
        assert!((m - 0.3).abs() < 1e-9 && (st - 0.05).abs() < 1e-12);
        let (m, st) = nice_axis(0.042);
        assert!(m >= 0.042 && m / st <= 6.0 + 1e-9);
        assert_eq!(nice_axis(f64::NAN), (1.0, 0.2));
        assert_eq!(format_decade(-2.0), "0.01");
        assert_eq!(format_decade(3.0), "1000");
        assert_eq!(trim_float(0.25), "0.25");
        assert_eq!(trim_float(0.0), "0");
    }
}
