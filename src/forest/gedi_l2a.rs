//! NASA's GEDI L2A waveform interpretation, per algorithm setting group (a1-a6), from an L1B
//! received waveform: the noise thresholds, the signal's search window, the smoothing on a
//! quarter-sample grid, the signal start and end (`toploc`, `botloc`), the modes, the lowest
//! mode (`zcross`), the cumulative energy (`rx_cumulative`) and the relative heights (`rh_aN`,
//! cm). The algorithm and every constant are in `docs/gedi_l2a.md` (each step checked against
//! the intermediates the L2A fixture stores; `tests/gedi_l2a.rs`).
//!
//! Locations are in samples from the first sample of the shot's received waveform (0-based), on
//! a grid of [`SUBBIN`] samples. [`process_groups`] runs the six groups of a shot sharing their
//! two smoothings (43 µs per fixture shot, `benches/forest.rs`). Not yet built (issue 56): the a2 group's local-energy test
//! (`energy_thresh`, never deciding a case of the fixture), flag 4 (`botlocdist_limit`), the
//! choice of `selected_algorithm`, and the L2B products.

/// Grid step of every location, samples (`rx_subbin_resolution = 4`).
pub const SUBBIN: f64 = 0.25;
/// Grid points per sample.
const PER_SAMPLE: usize = 4;
/// Samples added before and after the samples above the preprocessor threshold
/// (`rx_searchsize`).
pub const SEARCH_SIZE: usize = 100;
/// Noise σ above the mean a raw sample must rise to start the search window
/// (`preprocessor_threshold`).
pub const PREPROCESSOR_THRESHOLD: f64 = 4.0;
/// Most modes kept (`rx_max_mode_count`).
pub const MAX_MODES: usize = 20;
/// a2's mode selection: nearest a mode may lie above `botloc`, samples (`pulse_sep_thresh`).
pub const PULSE_SEP_THRESH: f64 = 8.0;
/// a2's mode selection: amplitude above the mean that selects a mode, counts (`amp_thresh`).
pub const AMP_THRESH: f64 = 50.0;

/// One algorithm setting group (`rx_processing_aN/ancillary`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SettingGroup {
    /// Group number, 1-6.
    pub number: u8,
    /// Smoothing width for `toploc`/`botloc`, samples (`smoothwidth`).
    pub smoothwidth: f64,
    /// Smoothing width for the modes and the energy, samples (`smoothwidth_zcross`).
    pub smoothwidth_zcross: f64,
    /// Signal start threshold, noise σ above the mean (`front_threshold` = mean + this × σ).
    pub front_sigma: f64,
    /// Signal end threshold, noise σ above the mean.
    pub back_sigma: f64,
    /// The lowest-mode selection (`enable_select_mode`, a2 only): with it, the
    /// `cumulative_energy_minimum` and `cumulative_energy_thresh`, percent.
    pub select_mode: Option<(f64, f64)>,
}

/// The six groups of the L2A product (values from the fixture's `ancillary`).
pub const GROUPS: [SettingGroup; 6] = [
    group(1, 6.5, 6.5, 3.0, 6.0, None),
    group(2, 6.5, 3.5, 3.0, 3.0, Some((1.5, 2.5))),
    group(3, 6.5, 3.5, 3.0, 6.0, None),
    group(4, 6.5, 6.5, 6.0, 6.0, None),
    group(5, 6.5, 3.5, 3.0, 2.0, None),
    group(6, 6.5, 3.5, 3.0, 4.0, None),
];

const fn group(
    number: u8,
    smoothwidth: f64,
    smoothwidth_zcross: f64,
    front_sigma: f64,
    back_sigma: f64,
    select_mode: Option<(f64, f64)>,
) -> SettingGroup {
    SettingGroup {
        number,
        smoothwidth,
        smoothwidth_zcross,
        front_sigma,
        back_sigma,
        select_mode,
    }
}

/// One shot through one group.
#[derive(Clone, Debug, PartialEq)]
pub struct GroupResult {
    /// `front_threshold`, counts (float32 as stored).
    pub front_threshold: f32,
    /// `back_threshold`, counts.
    pub back_threshold: f32,
    /// First and last sample of the search window.
    pub search: (usize, usize),
    /// Signal start, samples.
    pub toploc: f64,
    /// Signal end, samples.
    pub botloc: f64,
    /// The modes, top to bottom, samples (at most [`MAX_MODES`]).
    pub modes: Vec<f64>,
    /// The lowest mode (the ground), samples; `None` without a mode.
    pub zcross: Option<f64>,
    /// Index of `zcross` in `modes`.
    pub selected_mode: Option<usize>,
    /// `selected_mode_flag`: 0 the lowest mode, 3 chosen by a2's rules.
    pub selected_mode_flag: u8,
    /// Where the cumulative energy from `botloc` up reaches p % (p = 0..=100), samples.
    pub cumulative: Vec<f64>,
    /// Relative heights above `zcross`, cm (p = 0..=100; truncated toward zero).
    pub rh_cm: Vec<i32>,
}

/// The two passes of a truncated Gaussian that smooth a waveform of width `w` samples: (σ,
/// half-width) of each, samples. Fitted to the fixture for 6.5 and 3.5 (`docs/gedi_l2a.md`
/// §2.3: every discrete output exact); σ = w/√2 with the same proportions otherwise.
fn smoothing_passes(w: f64) -> [(f64, f64); 2] {
    if (w - 6.5).abs() < 1e-9 {
        [(4.6255, 8.5), (4.6182, 9.75)]
    } else if (w - 3.5).abs() < 1e-9 {
        [(2.6425, 3.25), (2.6707, 5.5)]
    } else {
        let s = w / std::f64::consts::SQRT_2;
        [(s, 1.31 * w), (s, 1.5 * w)]
    }
}

/// One pass's taps on the quarter grid: a Gaussian of `sigma` samples cut at `half` samples,
/// unit sum; with its half-length in grid points.
fn pass_taps(sigma: f64, half: f64) -> (Vec<f64>, isize) {
    let h = (half / SUBBIN).round() as isize;
    let taps: Vec<f64> = (-h..=h)
        .map(|k| {
            let x = k as f64 * SUBBIN / sigma;
            (-0.5 * x * x).exp()
        })
        .collect();
    let sum: f64 = taps.iter().sum();
    (taps.into_iter().map(|t| t / sum).collect(), h)
}

/// `w` linearly interpolated onto the quarter-sample grid, then smoothed by the two passes for
/// width `width` (edges padded with the end values).
pub fn smooth(w: &[f32], width: f64) -> Vec<f64> {
    if w.is_empty() {
        return Vec::new();
    }
    let m = (w.len() - 1) * PER_SAMPLE + 1;
    let mut grid: Vec<f64> = (0..m)
        .map(|q| {
            let i = q / PER_SAMPLE;
            let f = (q % PER_SAMPLE) as f64 * SUBBIN;
            let a = f64::from(w[i]);
            let b = f64::from(*w.get(i + 1).unwrap_or(&w[i]));
            a + (b - a) * f
        })
        .collect();
    for (sigma, half) in smoothing_passes(width) {
        let (taps, h) = pass_taps(sigma, half);
        let last = m as isize - 1;
        grid = (0..m as isize)
            .map(|q| {
                taps.iter()
                    .enumerate()
                    .map(|(j, t)| t * grid[(q + j as isize - h).clamp(0, last) as usize])
                    .sum::<f64>()
            })
            .collect();
    }
    grid
}

/// The search window of a shot: from [`SEARCH_SIZE`] samples before the first raw sample above
/// `mean + 4 σ` to as many after the last, within the record; `None` when none is above.
pub fn search_window(w: &[f32], mean: f32, sd: f32) -> Option<(usize, usize)> {
    let limit = f64::from(mean) + PREPROCESSOR_THRESHOLD * f64::from(sd);
    let above = |v: &f32| f64::from(*v) > limit;
    let first = w.iter().position(above)?;
    let last = w.iter().rposition(above)?;
    Some((
        first.saturating_sub(SEARCH_SIZE),
        (last + SEARCH_SIZE).min(w.len() - 1),
    ))
}

/// The two passes of [`smoothing_passes`] for `width` as one kernel on the quarter grid (their
/// convolution, unit sum), with its half-length in grid points.
fn composite_kernel(width: f64) -> (Vec<f64>, usize) {
    let mut c = vec![1.0];
    for (sigma, half) in smoothing_passes(width) {
        let (taps, _) = pass_taps(sigma, half);
        let mut next = vec![0.0; c.len() + taps.len() - 1];
        for (i, a) in c.iter().enumerate() {
            for (j, t) in taps.iter().enumerate() {
                next[i + j] += a * t;
            }
        }
        c = next;
    }
    let half = c.len() / 2;
    (c, half)
}

/// `w` smoothed for `width` where the search window `search` needs it: the quarter grid over
/// the whole record, its values within the window (and a grid point either side), 0 outside.
/// The linear interpolation onto the grid and the two smoothing passes are folded into one
/// weight per sample for each of the four grid phases, so a grid point costs ~37 products
/// (width 6.5) instead of 148 on the interpolated grid, and only the window is computed: the
/// six groups of a fixture shot took 276 µs by [`smooth`] over the window's samples, 106 µs
/// this way, 87 µs with the weights built once (`benches/forest.rs`,
/// `gedi_l2a/shot_six_groups`). Within the window the values equal
/// [`smooth`]'s to rounding (the edge padding of the record is the same; that of the first
/// pass is not, which matters only within a kernel's reach of the record's ends).
fn smooth_window(w: &[f32], width: f64, search: (usize, usize)) -> Vec<f64> {
    let n = w.len();
    let m = (n - 1) * PER_SAMPLE + 1;
    let mut grid = vec![0.0; m];
    let fresh;
    let phases = match cached_phases(width) {
        Some(p) => p,
        None => {
            fresh = PhaseWeights::new(width);
            &fresh
        }
    };
    let last = n as isize - 1;
    let q0 = (search.0 * PER_SAMPLE).saturating_sub(1);
    let q1 = (search.1 * PER_SAMPLE + 1).min(m - 1);
    // The samples the window's grid points reach, the record's end values repeated beyond it.
    let first = (q0 / PER_SAMPLE) as isize + phases.jmin;
    let span = phases.weights[0].len();
    let reach = (q1 / PER_SAMPLE) as isize + phases.jmin + span as isize;
    let samples: Vec<f64> = (first..=reach)
        .map(|k| f64::from(w[k.clamp(0, last) as usize]))
        .collect();
    for (q, out) in grid.iter_mut().enumerate().take(q1 + 1).skip(q0) {
        let at = ((q / PER_SAMPLE) as isize + phases.jmin - first) as usize;
        let weights = &phases.weights[q % PER_SAMPLE];
        *out = weights
            .iter()
            .zip(&samples[at..at + span])
            .map(|(a, b)| a * b)
            .sum();
    }
    grid
}

/// The weight of each sample in a grid point of each phase (q mod 4), for one width: the
/// linear interpolation and [`composite_kernel`] folded together.
struct PhaseWeights {
    /// Offset of the first weight from the grid point's sample (q / 4), samples.
    jmin: isize,
    /// Per phase, the weights of the samples from `jmin` on (all the same length).
    weights: [Vec<f64>; PER_SAMPLE],
}

impl PhaseWeights {
    fn new(width: f64) -> Self {
        let (c, half) = composite_kernel(width);
        let h = half as isize;
        let per = PER_SAMPLE as isize;
        let jmin = (-h).div_euclid(per);
        let jmax = (per - 1 + h).div_euclid(per) + 1;
        let span = (jmax - jmin + 1) as usize;
        let weights = std::array::from_fn(|phi| {
            let mut weights = vec![0.0; span];
            for (k, ck) in c.iter().enumerate() {
                let u = phi as isize + k as isize - h;
                let a = u.div_euclid(per);
                let f = u.rem_euclid(per) as f64 * SUBBIN;
                weights[(a - jmin) as usize] += ck * (1.0 - f);
                if f > 0.0 {
                    weights[(a + 1 - jmin) as usize] += ck * f;
                }
            }
            weights
        });
        PhaseWeights { jmin, weights }
    }
}

/// The weights of the product's two widths (6.5 and 3.5 samples), built once.
fn cached_phases(width: f64) -> Option<&'static PhaseWeights> {
    static WIDE: std::sync::OnceLock<PhaseWeights> = std::sync::OnceLock::new();
    static NARROW: std::sync::OnceLock<PhaseWeights> = std::sync::OnceLock::new();
    if width == 6.5 {
        Some(WIDE.get_or_init(|| PhaseWeights::new(6.5)))
    } else if width == 3.5 {
        Some(NARROW.get_or_init(|| PhaseWeights::new(3.5)))
    } else {
        None
    }
}

/// One shot's received waveform `w` (counts) through `group`: `mean` and `sd` are L1B's
/// `noise_mean_corrected` and `noise_stddev_corrected`, `dz` the elevation step per sample
/// (m). `None` when no sample stands above the preprocessor threshold or the signal has no
/// start or end.
pub fn process(
    w: &[f32],
    mean: f32,
    sd: f32,
    dz: f64,
    group: &SettingGroup,
) -> Option<GroupResult> {
    process_groups(w, mean, sd, dz, std::slice::from_ref(group)).remove(0)
}

/// One shot through each of `groups` ([`process`]), each smoothing computed once for the
/// groups that share its width.
pub fn process_groups(
    w: &[f32],
    mean: f32,
    sd: f32,
    dz: f64,
    groups: &[SettingGroup],
) -> Vec<Option<GroupResult>> {
    let Some(search) = search_window(w, mean, sd) else {
        return vec![None; groups.len()];
    };
    let mut smoothed: Vec<(f64, Vec<f64>)> = Vec::with_capacity(2);
    for g in groups {
        for width in [g.smoothwidth, g.smoothwidth_zcross] {
            if !smoothed.iter().any(|(x, _)| *x == width) {
                smoothed.push((width, smooth_window(w, width, search)));
            }
        }
    }
    let get = |width: f64| {
        smoothed
            .iter()
            .find(|(x, _)| *x == width)
            .map(|(_, v)| v.as_slice())
            .unwrap_or(&[])
    };
    groups
        .iter()
        .map(|g| {
            interpret(
                (mean, sd, dz),
                search,
                get(g.smoothwidth),
                get(g.smoothwidth_zcross),
                g,
            )
        })
        .collect()
}

/// The steps after the smoothing for one group: thresholds, toploc and botloc on `s`, the
/// modes, the lowest mode and the energy on `sz`.
fn interpret(
    (mean, sd, dz): (f32, f32, f64),
    search: (usize, usize),
    s: &[f64],
    sz: &[f64],
    group: &SettingGroup,
) -> Option<GroupResult> {
    let (mean64, sd32) = (f64::from(mean), f64::from(sd));
    let front_threshold = (mean64 + group.front_sigma * sd32) as f32;
    let back_threshold = (mean64 + group.back_sigma * sd32) as f32;
    let (q0, q1) = (search.0 * PER_SAMPLE, search.1 * PER_SAMPLE);
    let front = f64::from(front_threshold);
    let back = f64::from(back_threshold);
    let top_q = (q0..=q1).find(|&q| s[q] > front)?;
    let bot_q = (q0..=q1).rev().find(|&q| s[q] > back)?;
    if bot_q < top_q {
        return None;
    }
    let modes_q: Vec<usize> = (top_q.max(1)..bot_q)
        .filter(|&q| q + 1 < sz.len())
        .filter(|&q| sz[q] - sz[q - 1] > 0.0 && sz[q + 1] - sz[q] <= 0.0 && sz[q] > back)
        .take(MAX_MODES)
        .collect();
    let (selected, flag) = select_mode(sz, &modes_q, bot_q, top_q, mean64, back, group);
    let loc = |q: usize| q as f64 * SUBBIN;
    let cumulative = cumulative_energy(sz, top_q, bot_q, mean64);
    let zcross = selected.map(|i| loc(modes_q[i]));
    let rh_cm = match zcross {
        Some(z) => cumulative
            .iter()
            .map(|c| {
                let v = 100.0 * (z - c) * dz;
                ((v * 1e6).round() / 1e6).trunc() as i32
            })
            .collect(),
        None => Vec::new(),
    };
    Some(GroupResult {
        front_threshold,
        back_threshold,
        search,
        toploc: loc(top_q),
        botloc: loc(bot_q),
        modes: modes_q.iter().map(|&q| loc(q)).collect(),
        zcross,
        selected_mode: selected,
        selected_mode_flag: flag,
        cumulative,
        rh_cm,
    })
}

/// The lowest mode: the last one, or with a2's selection and two modes or more the lowest that
/// passes its rules (`docs/gedi_l2a.md` §2.6; the local-energy test is not built); with the
/// flag.
fn select_mode(
    sz: &[f64],
    modes: &[usize],
    bot_q: usize,
    top_q: usize,
    mean: f64,
    back: f64,
    group: &SettingGroup,
) -> (Option<usize>, u8) {
    let lowest = modes.len().checked_sub(1);
    let Some((minimum, thresh)) = group.select_mode else {
        return (lowest, 0);
    };
    // One mode is the lowest, flag 0 (20 single-mode shots of the fixture's a2).
    if modes.len() < 2 {
        return (lowest, 0);
    }
    let total: f64 = (top_q..bot_q).map(|q| sz[q] - mean).sum();
    for (i, &q) in modes.iter().enumerate().rev() {
        let iwave = if total > 0.0 {
            (q..bot_q).map(|k| sz[k] - mean).sum::<f64>() / total
        } else {
            0.0
        };
        let amp = sz[q] - mean;
        if ((bot_q - q) as f64) * SUBBIN < PULSE_SEP_THRESH
            || amp < back - mean
            || 100.0 * iwave < minimum
        {
            continue;
        }
        if amp > AMP_THRESH || 100.0 * iwave > thresh {
            return (Some(i), 3);
        }
    }
    (lowest, 0)
}

/// `rx_cumulative`: for p = 0..=100, the location just below the one where the energy summed
/// from `botloc` up (botloc itself left out) first reaches p % of the whole; `botloc` at 0 and
/// `toploc` at 100.
fn cumulative_energy(sz: &[f64], top_q: usize, bot_q: usize, mean: f64) -> Vec<f64> {
    let botloc = bot_q as f64 * SUBBIN;
    let mut c = Vec::with_capacity(bot_q.saturating_sub(top_q));
    let mut run = 0.0;
    for q in (top_q..bot_q).rev() {
        run += sz[q] - mean;
        c.push(run);
    }
    let total = c.last().copied().unwrap_or(0.0);
    // The first index reaching a target never moves back as the target grows (total ≥ 0), so
    // one sweep serves every p; a negative total (targets falling) scans from the start.
    let mut j = 0;
    (0..=100)
        .map(|p| match p {
            0 => botloc,
            100 => top_q as f64 * SUBBIN,
            _ => {
                let target = total * f64::from(p) / 100.0;
                if total < 0.0 {
                    j = 0;
                }
                while j < c.len() && c[j] < target {
                    j += 1;
                }
                botloc - SUBBIN - j.saturating_sub(1) as f64 * SUBBIN
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smoothing_keeps_a_constant_and_the_area() {
        let flat = vec![200.0f32; 50];
        assert!(smooth(&flat, 6.5).iter().all(|v| (v - 200.0).abs() < 1e-9));
        let mut spike = vec![0.0f32; 101];
        spike[50] = 4.0;
        let s = smooth(&spike, 3.5);
        let area: f64 = s.iter().sum::<f64>() * SUBBIN;
        assert!((area - 4.0).abs() < 1e-6, "{area}");
        assert_eq!(s.len(), 401);
    }

    #[test]
    fn the_folded_smoothing_equals_the_two_passes_within_the_window() {
        let w: Vec<f32> = (0..400)
            .map(|i| 200.0 + ((i * 37 % 11) as f32) + 30.0 * (i == 200) as i32 as f32)
            .collect();
        for width in [6.5, 3.5, 5.0] {
            let full = smooth(&w, width);
            let part = smooth_window(&w, width, (120, 300));
            for q in 120 * 4..=300 * 4 {
                assert!((full[q] - part[q]).abs() < 1e-9, "{width} {q}");
            }
        }
    }

    #[test]
    fn one_echo_on_noise_gives_its_start_end_mode_and_heights() {
        // A 20-count echo at sample 300 of 600 on a mean of 200, σ 2: one mode there, the
        // signal from a few samples above to a few below it, RH 0 at the mode.
        let w: Vec<f32> = (0..600)
            .map(|i| {
                let x = (i as f32 - 300.0) / 4.0;
                200.0 + 40.0 * (-0.5 * x * x).exp()
            })
            .collect();
        let r = process(&w, 200.0, 2.0, 0.15, &GROUPS[0]).unwrap();
        // Raw samples above 208 from 293 to 307, 100 more either side.
        assert_eq!(r.search, (193, 407));
        assert_eq!(r.modes, vec![300.0]);
        assert_eq!(r.zcross, Some(300.0));
        assert!(r.toploc < 300.0 && r.botloc > 300.0, "{r:?}");
        assert_eq!(r.cumulative[0], r.botloc);
        assert_eq!(r.cumulative[100], r.toploc);
        // The median energy within a sample of the mode (the start threshold is lower than the
        // end's, so the signal starts further from the mode than it ends: RH50 a little above).
        assert!((0..=15).contains(&r.rh_cm[50]), "{:?}", r.rh_cm[50]);
        assert!(r.rh_cm[100] > 0 && r.rh_cm[0] < 0);
        // Nothing above the noise: no result.
        assert!(process(&[200.0; 100], 200.0, 2.0, 0.15, &GROUPS[0]).is_none());
    }
}
