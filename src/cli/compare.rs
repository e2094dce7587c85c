//! `fwlidar compare OURS.las REFERENCE.las`: our returns against another processor's points of
//! the same pulses, matched by GPS time ([`crate::eval::point_match`]): the share of its echoes
//! found, the share of ours that are its echoes, returns per pulse, offsets by return number,
//! how our intensity ranks its amplitude; a figure on request.

use std::fmt::Write as _;
use std::path::PathBuf;

use crate::cli::Failure;
use crate::core::atomic_file::write_atomic;
use crate::eval::point_match::{CompareOptions, Comparison, compare, read_points};

/// Arguments of `fwlidar compare`.
#[derive(Debug, clap::Args)]
pub struct CompareArgs {
    /// Our returns (`returns.las` of a replay; LAS or LAZ).
    pub ours: PathBuf,
    /// The other processor's points of the same pulses (e.g. the instrument maker's).
    pub reference: PathBuf,
    /// Largest 3D distance of a match, m.
    #[arg(long, default_value_t = 0.15)]
    pub within: f64,
    /// Points whose GPS times differ by at most this are one pulse, µs.
    #[arg(long, default_value_t = 1.0)]
    pub time_tolerance_us: f64,
    /// Print the figures as one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Draw the matched pairs' offsets and intensities (SVG; never written over).
    #[arg(long)]
    pub figure: Option<PathBuf>,
}

/// Runs `fwlidar compare`.
pub fn run(args: CompareArgs) -> Result<(), Failure> {
    if !(args.within.is_finite() && args.within > 0.0) {
        return Err(Failure::usage(format!(
            "--within must be a positive number of metres, got {}",
            args.within
        )));
    }
    if !(args.time_tolerance_us.is_finite() && args.time_tolerance_us >= 0.0) {
        return Err(Failure::usage(format!(
            "--time-tolerance-us must be a non-negative number, got {}",
            args.time_tolerance_us
        )));
    }
    if let Some(f) = &args.figure
        && f.exists()
    {
        return Err(Failure::usage(format!(
            "{}: already exists; a figure is never written over",
            f.display()
        )));
    }
    let ours = read_points(&args.ours).map_err(Failure::job)?;
    let reference = read_points(&args.reference).map_err(Failure::job)?;
    let c = compare(
        &ours,
        &reference,
        &CompareOptions {
            within_m: args.within,
            time_tolerance_s: args.time_tolerance_us * 1e-6,
        },
    );
    if c.pulses_in_both == 0 {
        return Err(Failure::job(format!(
            "{} and {} share no pulse (no GPS time within {} µs of another): not the same pulses",
            args.ours.display(),
            args.reference.display(),
            args.time_tolerance_us
        )));
    }
    if let Some(f) = &args.figure {
        write_atomic(f, comparison_svg(&c).as_bytes())
            .map_err(|e| Failure::job(format!("{}: {e}", f.display())))?;
    }
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&c).unwrap_or_else(|_| "{}".into())
        );
    } else {
        print!("{}", words(&c));
        if let Some(f) = &args.figure {
            println!("  figure: {}", f.display());
        }
    }
    Ok(())
}

/// The comparison in a few lines.
pub fn words(c: &Comparison) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "fwlidar compare  {}  against  {}  (within {} m in the same pulse)",
        c.ours_file, c.reference_file, c.within_m
    );
    let _ = writeln!(
        s,
        "  pulses: {} in both, {} only in the reference, {} only in ours",
        c.pulses_in_both, c.pulses_only_reference, c.pulses_only_ours
    );
    let _ = writeln!(
        s,
        "  reference points: {}, {:.1} % found (median distance {:.3} m)",
        c.reference_points,
        100.0 * c.reference_found,
        c.median_distance_m
    );
    let _ = writeln!(
        s,
        "  our points: {}, {:.1} % are reference points; returns per pulse {:.2} × the \
         reference's",
        c.our_points,
        100.0 * c.ours_are_reference,
        c.returns_ratio
    );
    for (rn, b) in &c.by_return {
        let _ = writeln!(
            s,
            "  reference return {rn}: {} points, {:.1} % found, z offset (ours − reference) \
             median {:+.3} m, median |offset| {:.3} m",
            b.reference,
            if b.reference > 0 {
                100.0 * b.found as f64 / b.reference as f64
            } else {
                f64::NAN
            },
            b.median_offset_m,
            b.median_abs_offset_m
        );
    }
    let _ = writeln!(
        s,
        "  intensity: rank correlation {:.3} with the reference's {} over {} matched pairs; {} \
         of ours at 65535 (clipped)",
        c.intensity_rank_correlation, c.reference_amplitude, c.matched, c.our_intensity_clipped
    );
    s
}

/// Two panels: the histogram of the matched pairs' z offsets (cm), and our intensity against
/// the reference's amplitude.
pub fn comparison_svg(c: &Comparison) -> String {
    let (w, h) = (820.0, 380.0);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"{w}\" height=\"{h}\" \
         fill=\"white\"/>"
    );
    let _ = writeln!(
        s,
        "<text x=\"20\" y=\"22\" font-size=\"14\">{:.1} % of the reference's {} points found, \
         {:.1} % of our {} are reference points, {:.2} × its returns per pulse</text>",
        100.0 * c.reference_found,
        c.reference_points,
        100.0 * c.ours_are_reference,
        c.our_points,
        c.returns_ratio
    );
    // Panel 1: offsets, bins of 1 cm within ±within.
    let (x0, y0, pw, ph) = (60.0, 50.0, 320.0, 270.0);
    let lim = (c.within_m * 100.0).ceil().max(1.0) as i64;
    let mut bins = vec![0u64; (2 * lim + 1) as usize];
    for o in &c.offsets_m {
        let k = ((o * 100.0).round() as i64).clamp(-lim, lim) + lim;
        bins[k as usize] += 1;
    }
    let top = bins.iter().copied().max().unwrap_or(1).max(1) as f64;
    let bw = pw / bins.len() as f64;
    let _ = writeln!(
        s,
        "<rect x=\"{x0}\" y=\"{y0}\" width=\"{pw}\" height=\"{ph}\" fill=\"none\" stroke=\"#888\"/>"
    );
    for (k, &n) in bins.iter().enumerate() {
        let bh = ph * n as f64 / top;
        let _ = writeln!(
            s,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{bh:.1}\" fill=\"#1f77b4\"/>",
            x0 + k as f64 * bw,
            y0 + ph - bh,
            (bw - 1.0).max(0.5)
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">z offset of matched pairs, ours − \
         reference (cm, {} pairs)</text>",
        x0 + pw / 2.0,
        y0 + ph + 36.0,
        c.matched
    );
    for t in [-lim, 0, lim] {
        let _ = writeln!(
            s,
            "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{t}</text>",
            x0 + (t + lim) as f64 * bw + bw / 2.0,
            y0 + ph + 16.0
        );
    }
    // Panel 2: intensity vs the reference's amplitude.
    let (x1, pw2) = (460.0, 320.0);
    let _ = writeln!(
        s,
        "<rect x=\"{x1}\" y=\"{y0}\" width=\"{pw2}\" height=\"{ph}\" fill=\"none\" \
         stroke=\"#888\"/>"
    );
    let (mut amin, mut amax, mut imax) = (f64::MAX, f64::MIN, 1.0f64);
    for &(i, a) in &c.intensity_pairs {
        if a.is_finite() {
            amin = amin.min(a);
            amax = amax.max(a);
        }
        imax = imax.max(i);
    }
    if amax <= amin {
        amax = amin + 1.0;
    }
    for &(i, a) in &c.intensity_pairs {
        if !a.is_finite() {
            continue;
        }
        let _ = writeln!(
            s,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"1.5\" fill=\"#d62728\" fill-opacity=\"0.4\"/>",
            x1 + pw2 * (a - amin) / (amax - amin),
            y0 + ph - ph * i / imax
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">reference {} ({:.1} to {:.1})</text>",
        x1 + pw2 / 2.0,
        y0 + ph + 36.0,
        c.reference_amplitude,
        amin,
        amax
    );
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"{}\" transform=\"rotate(-90 {} {})\" text-anchor=\"middle\">our \
         intensity (0 to {imax:.0}); rank correlation {:.3}</text>",
        x1 - 12.0,
        y0 + ph / 2.0,
        x1 - 12.0,
        y0 + ph / 2.0,
        c.intensity_rank_correlation
    );
    s.push_str("</svg>\n");
    s
}
