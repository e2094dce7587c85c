//! Peak detection on one segment: local maxima found by a sign change of the first difference
//! (the seed's peak detector), above an amplitude threshold, at least a minimum separation
//! apart; and, as an option, *shoulders* (hidden peaks on the flank of a stronger one) found at
//! local minima of the second difference.
//!
//! Positions are bins from the segment's first sample; amplitudes are in the units of the
//! signal. A flat top (a plateau of equal samples between a rise and a fall) counts as one
//! maximum at its middle. The first and last samples are never maxima (no sign change there).
//!
//! Optionally a maximum must also have a topographic *prominence* of at least
//! [`PeakSettings::min_prominence`]: its height above the higher of the two lowest points
//! between it and the nearest higher sample on each side (or the segment's edge). A low-pass
//! filter leaves ripples of a fraction of the noise level on long flanks (a flat spot on the
//! tail of a wide echo becomes a maximum 0.05 units high); they are local maxima, but no echo.
//!
//! Work is linear in the segment length plus a sort of the candidates (prominence: two more
//! linear passes with a stack); the buffers of [`PeakFinder`] are sized once, so detection does
//! not allocate.

/// One detected peak.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Peak {
    /// Index of the sample at (or, for a plateau of even length, just left of) the peak.
    pub index: usize,
    /// Position, bins from the segment's first sample (a plateau's middle).
    pub position_bins: f32,
    /// Sample value at the peak, signal units.
    pub amplitude: f32,
    /// True for a shoulder (second-difference minimum) rather than a local maximum.
    pub shoulder: bool,
}

/// Which samples are local maxima ([`PeakSettings::rule`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PeakRule {
    /// A rise followed, possibly after a plateau of equal samples, by a fall; a plateau counts
    /// once, at its middle. Default.
    #[default]
    RiseAndFall,
    /// Every sample not below its left neighbour and above its right one
    /// (`y[i−1] ≤ y[i] > y[i+1]`): the waveformlidar R package's `lpeak` (a 3-sample window
    /// whose first maximum, in its reversed order, is the middle). A plateau counts at its last
    /// sample, and so does the end of a flat step on a falling flank (two equal samples, then
    /// lower), which is no maximum at all: frequent on a 3-bin running mean of integer counts,
    /// whose values are multiples of ⅓. Only for reproducing the package's products.
    NotBelowLeft,
}

/// Settings of one detection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeakSettings {
    /// Smallest amplitude a peak may have, signal units.
    pub threshold: f32,
    /// Smallest distance between two kept peaks, bins; of two closer ones the higher is kept.
    pub min_separation_bins: usize,
    /// Most peaks kept (the highest ones).
    pub max_peaks: usize,
    /// Also look for shoulders: local minima of the second difference that are negative by at
    /// least `shoulder_curvature` (signal units per bin²) away from every kept maximum.
    pub shoulders: bool,
    /// Smallest `−Δ²y` of a shoulder, signal units per bin².
    pub shoulder_curvature: f32,
    /// Smallest topographic prominence of a local maximum, signal units (0: no test). The
    /// prominence is the height of the maximum above the higher of its two *saddles*: on each
    /// side, the lowest sample between it and the nearest strictly higher sample (or the
    /// segment's edge when there is none).
    pub min_prominence: f32,
    /// Which samples are local maxima. The prominence test and the separation apply to either.
    pub rule: PeakRule,
}

/// Finds peaks; holds the candidate buffer.
pub struct PeakFinder {
    candidates: Vec<Peak>,
    /// Left saddle of each candidate (prominence test), signal units.
    saddles: Vec<f32>,
    /// Monotone stack of the prominence passes: (sample value, lowest sample between the entry
    /// below and this one).
    stack: Vec<(f32, f32)>,
}

impl PeakFinder {
    /// A finder for segments of up to `max_samples` samples.
    pub fn new(max_samples: usize) -> Self {
        PeakFinder {
            candidates: Vec::with_capacity(max_samples / 2 + 2),
            saddles: Vec::with_capacity(max_samples / 2 + 2),
            stack: Vec::with_capacity(max_samples),
        }
    }

    /// Detects peaks of `y` (at most as many samples as the finder was built for; beyond that
    /// candidates past the buffer are ignored) into `out` (cleared first; at most `settings.max_peaks`,
    /// sorted by position).
    pub fn find(&mut self, y: &[f32], settings: &PeakSettings, out: &mut Vec<Peak>) {
        out.clear();
        self.candidates.clear();
        // A local maximum or a second-difference minimum takes at least two samples, so the
        // buffer sized in `new` holds every candidate; the check below only guards misuse.
        let cap = self.candidates.capacity();
        let n = y.len();
        if n < 3 || settings.max_peaks == 0 {
            return;
        }
        if settings.rule == PeakRule::NotBelowLeft {
            for i in 1..n - 1 {
                if y[i] >= y[i - 1]
                    && y[i] > y[i + 1]
                    && y[i] >= settings.threshold
                    && self.candidates.len() < cap
                {
                    self.candidates.push(Peak {
                        index: i,
                        position_bins: i as f32,
                        amplitude: y[i],
                        shoulder: false,
                    });
                }
            }
        }
        // Local maxima: a rise followed, possibly after a plateau, by a fall.
        let mut i = 1;
        while settings.rule == PeakRule::RiseAndFall && i + 1 < n {
            if y[i] > y[i - 1] {
                let mut j = i;
                while j + 1 < n && y[j + 1] == y[i] {
                    j += 1;
                }
                if j + 1 < n && y[j + 1] < y[i] {
                    if y[i] >= settings.threshold && self.candidates.len() < cap {
                        self.candidates.push(Peak {
                            index: (i + j) / 2,
                            position_bins: 0.5 * (i + j) as f32,
                            amplitude: y[i],
                            shoulder: false,
                        });
                    }
                    i = j + 1;
                    continue;
                }
                i = j.max(i) + 1;
                continue;
            }
            i += 1;
        }
        if settings.min_prominence > 0.0 && !self.candidates.is_empty() {
            self.keep_prominent(y, settings.min_prominence);
        }
        select(&mut self.candidates, settings, out);
        if !settings.shoulders || out.len() >= settings.max_peaks || n < 5 {
            return;
        }
        // Shoulders: minima of the second difference, negative enough, not near a maximum.
        self.candidates.clear();
        let d2 = |i: usize| y[i - 1] - 2.0 * y[i] + y[i + 1];
        #[allow(clippy::needless_range_loop)] // i indexes y at i − 1, i and i + 1
        for i in 2..n - 2 {
            let c = d2(i);
            if c < -settings.shoulder_curvature
                && c < d2(i - 1)
                && c <= d2(i + 1)
                && y[i] >= settings.threshold
                && self.candidates.len() < cap
                && !out
                    .iter()
                    .any(|p| p.index.abs_diff(i) < settings.min_separation_bins.max(1))
            {
                self.candidates.push(Peak {
                    index: i,
                    position_bins: i as f32,
                    amplitude: y[i],
                    shoulder: true,
                });
            }
        }
        let kept = out.len();
        let rest = PeakSettings {
            max_peaks: settings.max_peaks - kept,
            ..*settings
        };
        // `select` clears its output, so collect shoulders behind the maxima by hand.
        self.candidates
            .sort_unstable_by(|a, b| b.amplitude.total_cmp(&a.amplitude));
        for c in self.candidates.iter() {
            if out.len() - kept >= rest.max_peaks {
                break;
            }
            if out
                .iter()
                .all(|p| p.index.abs_diff(c.index) >= settings.min_separation_bins.max(1))
            {
                out.push(*c);
            }
        }
        out.sort_unstable_by_key(|p| p.index);
    }
}

impl PeakFinder {
    /// Drops the candidates (sorted by index) whose topographic prominence in `y` is below
    /// `min_prominence`. Two passes (left to right for the left saddles, right to left for the
    /// right ones), each keeping a stack of strictly decreasing samples with the lowest sample
    /// between neighbouring entries: popping the entries not higher than the current sample
    /// leaves the nearest higher one on top, with the lowest sample in between. Linear in `n`.
    fn keep_prominent(&mut self, y: &[f32], min_prominence: f32) {
        let n = y.len();
        self.saddles.clear();
        // The stack can hold every sample; segments longer than the finder was built for only
        // happen on misuse, where growing it once is acceptable.
        self.stack.clear();
        self.stack.reserve(n);
        let mut c = 0;
        for (i, &v) in y.iter().enumerate() {
            let low = Self::push(&mut self.stack, v);
            if c < self.candidates.len() && self.candidates[c].index == i {
                self.saddles.push(low);
                c += 1;
            }
        }
        self.stack.clear();
        let mut c = self.candidates.len();
        for (i, &v) in y.iter().enumerate().rev() {
            let low = Self::push(&mut self.stack, v);
            if c > 0 && self.candidates[c - 1].index == i {
                c -= 1;
                // The higher of the two saddles.
                self.saddles[c] = self.saddles[c].max(low);
            }
        }
        let mut kept = 0;
        for c in 0..self.candidates.len() {
            let p = self.candidates[c];
            if y[p.index] - self.saddles[c] >= min_prominence {
                self.candidates[kept] = p;
                kept += 1;
            }
        }
        self.candidates.truncate(kept);
    }

    /// One step of a prominence pass: pops the entries not higher than `v`, pushes `v`, and
    /// returns the lowest sample between `v` and the nearest higher one already passed (or all
    /// passed samples when none is higher; +∞ when there are none). Each entry holds its value
    /// and the lowest sample between the entry below it (or the start) and itself, so the
    /// popped entries together cover exactly the samples since the nearest higher one.
    fn push(stack: &mut Vec<(f32, f32)>, v: f32) -> f32 {
        let mut low = f32::INFINITY;
        while let Some(&(top, before)) = stack.last() {
            if top > v {
                break;
            }
            low = low.min(top).min(before);
            stack.pop();
        }
        stack.push((v, low));
        low
    }
}

/// Keeps the highest candidates at least the minimum separation apart, sorted by position.
fn select(candidates: &mut [Peak], settings: &PeakSettings, out: &mut Vec<Peak>) {
    candidates.sort_unstable_by(|a, b| b.amplitude.total_cmp(&a.amplitude));
    for c in candidates.iter() {
        if out.len() >= settings.max_peaks {
            break;
        }
        if out
            .iter()
            .all(|p| p.index.abs_diff(c.index) >= settings.min_separation_bins.max(1))
        {
            out.push(*c);
        }
    }
    out.sort_unstable_by_key(|p| p.index);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(threshold: f32) -> PeakSettings {
        PeakSettings {
            threshold,
            min_separation_bins: 3,
            max_peaks: 8,
            shoulders: false,
            shoulder_curvature: 0.0,
            min_prominence: 0.0,
            rule: PeakRule::RiseAndFall,
        }
    }

    fn find(y: &[f32], s: &PeakSettings) -> Vec<Peak> {
        let mut f = PeakFinder::new(y.len().max(16));
        let mut out = Vec::with_capacity(8);
        f.find(y, s, &mut out);
        out
    }

    #[test]
    fn maxima_above_threshold_and_plateaus() {
        let y = [
            0.0, 1.0, 5.0, 1.0, 0.0, 2.0, 2.0, 2.0, 0.0, 9.0, 9.0, 3.0, 0.0,
        ];
        let p = find(&y, &settings(1.5));
        let pos: Vec<f32> = p.iter().map(|p| p.position_bins).collect();
        assert_eq!(pos, vec![2.0, 6.0, 9.5]);
        let p = find(&y, &settings(3.0));
        assert_eq!(p.len(), 2);
    }

    #[test]
    fn not_below_left_rule_takes_step_ends_and_plateau_ends() {
        // A plateau (6..=7), a flat step on a falling flank (10, 11) and a strict maximum (2).
        let y = [
            0.0, 1.0, 5.0, 1.0, 0.0, 1.0, 2.0, 2.0, 0.0, 9.0, 4.0, 4.0, 3.0, 0.0,
        ];
        let rule = PeakSettings {
            min_separation_bins: 1,
            rule: PeakRule::NotBelowLeft,
            ..settings(0.5)
        };
        let idx: Vec<usize> = find(&y, &rule).iter().map(|p| p.index).collect();
        assert_eq!(idx, vec![2, 7, 9, 11]);
        let idx: Vec<usize> = find(
            &y,
            &PeakSettings {
                rule: PeakRule::RiseAndFall,
                ..rule
            },
        )
        .iter()
        .map(|p| p.index)
        .collect();
        assert_eq!(
            idx,
            vec![2, 6, 9],
            "the plateau's middle (6.5 → 6), no step end"
        );
        // Threshold and separation apply as before.
        assert_eq!(
            find(
                &y,
                &PeakSettings {
                    threshold: 4.5,
                    ..rule
                }
            )
            .len(),
            2
        );
        let sep: Vec<usize> = find(
            &y,
            &PeakSettings {
                min_separation_bins: 3,
                ..rule
            },
        )
        .iter()
        .map(|p| p.index)
        .collect();
        assert_eq!(sep, vec![2, 9], "7 and 11 lie 2 bins from the higher 9");
    }

    #[test]
    fn close_maxima_keep_the_higher_and_edges_are_not_peaks() {
        let y = [9.0, 1.0, 5.0, 4.0, 6.0, 1.0, 0.0, 3.0];
        let p = find(&y, &settings(0.5));
        assert_eq!(p.len(), 1);
        assert_eq!(p[0].index, 4);
        assert!(find(&[1.0, 2.0], &settings(0.0)).is_empty());
        assert!(find(&[], &settings(0.0)).is_empty());
        assert!(find(&[3.0; 50], &settings(0.0)).is_empty());
    }

    #[test]
    fn shoulder_on_a_flank_is_found() {
        let g = |t: f32, mu: f32, s: f32, a: f32| a * (-0.5 * ((t - mu) / s).powi(2)).exp();
        let y: Vec<f32> = (0..100)
            .map(|i| g(i as f32, 40.0, 3.0, 50.0) + g(i as f32, 46.0, 3.0, 20.0))
            .collect();
        assert_eq!(find(&y, &settings(1.0)).len(), 1);
        let s = PeakSettings {
            shoulders: true,
            shoulder_curvature: 0.1,
            ..settings(1.0)
        };
        let p = find(&y, &s);
        assert_eq!(p.len(), 2, "{p:?}");
        assert!(p[1].shoulder && p[1].index.abs_diff(46) <= 1, "{p:?}");
    }

    /// Topographic prominence by its definition (a walk to the nearest higher sample on each
    /// side), for checking the linear passes.
    fn prominence_by_walking(y: &[f32], i: usize) -> f32 {
        let side = |step: isize| {
            let mut j = i as isize;
            let mut low = f32::INFINITY;
            while j + step >= 0 && ((j + step) as usize) < y.len() {
                j += step;
                if y[j as usize] > y[i] {
                    break;
                }
                low = low.min(y[j as usize]);
            }
            low
        };
        y[i] - side(-1).max(side(1))
    }

    #[test]
    fn prominence_drops_flank_ripples_and_keeps_echoes() {
        // A wide echo with a flat spot on its tail (a ripple 0.05 high), a second echo behind a
        // real valley, and a small bump on the far side of the big one.
        let y = [
            0.0, 10.0, 30.0, 50.0, 40.0, 30.0, 29.95, 30.0, 25.0, 12.0, 20.0, 21.0, 15.0, 16.0,
            4.0, 0.0,
        ];
        let close = PeakSettings {
            min_separation_bins: 1,
            ..settings(1.0)
        };
        let all = find(&y, &close);
        assert_eq!(
            all.iter().map(|p| p.index).collect::<Vec<_>>(),
            vec![3, 7, 11, 13]
        );
        let s = PeakSettings {
            min_prominence: 0.5,
            ..close
        };
        let p = find(&y, &s);
        // 7: 0.05 above its saddle (29.95); 11: 9 above 12; 13: 1 above 15; 3: the highest.
        assert_eq!(
            p.iter().map(|p| p.index).collect::<Vec<_>>(),
            vec![3, 11, 13]
        );
        let s = PeakSettings {
            min_prominence: 2.0,
            ..close
        };
        assert_eq!(
            find(&y, &s).iter().map(|p| p.index).collect::<Vec<_>>(),
            vec![3, 11]
        );
        // The linear passes agree with the definition on a noisy signal with plateaus.
        let mut state = 12345u32;
        let y: Vec<f32> = (0..400)
            .map(|i| {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let noise = ((state >> 24) % 4) as f32;
                50.0 * (-((i as f32 - 120.0) / 30.0).powi(2)).exp()
                    + 30.0 * (-((i as f32 - 260.0) / 12.0).powi(2)).exp()
                    + noise
            })
            .collect();
        let candidates = find(
            &y,
            &PeakSettings {
                min_separation_bins: 1,
                max_peaks: 400,
                ..settings(0.0)
            },
        );
        assert!(candidates.len() > 50);
        for limit in [0.5, 1.0, 2.0, 3.5, 20.0] {
            let kept: Vec<usize> = find(
                &y,
                &PeakSettings {
                    min_separation_bins: 1,
                    max_peaks: 400,
                    min_prominence: limit,
                    ..settings(0.0)
                },
            )
            .iter()
            .map(|p| p.index)
            .collect();
            let expected: Vec<usize> = candidates
                .iter()
                .map(|p| p.index)
                .filter(|&i| prominence_by_walking(&y, i) >= limit)
                .collect();
            assert_eq!(kept, expected, "limit {limit}");
        }
    }
}
