//! The accumulators of one tile: per voxel the sum of deposited intensity (in integer quanta),
//! the number of samples, their maximum, and the number of pulses whose beam passed through it.
//!
//! Sums are integers of the grid's intensity quantum, so adding partial results is exact and
//! independent of order (floating-point sums are not associative); counts add, maxima take the
//! larger. That is what lets a tile touched by a later flight line, a resumed run or
//! `fwlidar merge` end bit-identical to processing everything at once.

/// Accumulators of one tile, each `levels · T · T` long in `(k·T + j)·T + i` order.
#[derive(Clone, Debug, PartialEq)]
pub struct TileData {
    /// Sum of deposited intensity, in quanta of the grid's `intensity_quantum`.
    pub sum_q: Vec<i64>,
    /// Samples (bins) deposited.
    pub samples: Vec<u32>,
    /// Largest deposited intensity (NaN where nothing was deposited).
    pub max: Vec<f32>,
    /// Pulses whose beam passed through the voxel (counted once per pulse).
    pub pulses: Vec<u32>,
}

impl TileData {
    /// Empty accumulators for `voxels` voxels.
    pub fn new(voxels: usize) -> TileData {
        TileData {
            sum_q: vec![0; voxels],
            samples: vec![0; voxels],
            max: vec![f32::NAN; voxels],
            pulses: vec![0; voxels],
        }
    }

    /// Voxels held.
    pub fn len(&self) -> usize {
        self.sum_q.len()
    }

    /// Whether the tile holds no voxel at all (zero-sized).
    pub fn is_empty(&self) -> bool {
        self.sum_q.is_empty()
    }

    /// Back to empty, keeping the allocations.
    pub fn clear(&mut self) {
        self.sum_q.fill(0);
        self.samples.fill(0);
        self.max.fill(f32::NAN);
        self.pulses.fill(0);
    }

    /// Adds `other` (same size) into `self`: sums and counts add, maxima take the larger.
    pub fn merge(&mut self, other: &TileData) {
        debug_assert_eq!(self.len(), other.len());
        for (a, b) in self.sum_q.iter_mut().zip(&other.sum_q) {
            *a = a.saturating_add(*b);
        }
        for (a, b) in self.samples.iter_mut().zip(&other.samples) {
            *a = a.saturating_add(*b);
        }
        for (a, b) in self.max.iter_mut().zip(&other.max) {
            // f32::max returns the other operand when one is NaN.
            *a = a.max(*b);
        }
        for (a, b) in self.pulses.iter_mut().zip(&other.pulses) {
            *a = a.saturating_add(*b);
        }
    }

    /// Deposits one sample of `value_q` quanta (`value` itself for the maximum) at `offset`.
    #[inline]
    pub fn deposit(&mut self, offset: usize, value_q: i64, value: f32) {
        self.sum_q[offset] = self.sum_q[offset].saturating_add(value_q);
        self.samples[offset] = self.samples[offset].saturating_add(1);
        self.max[offset] = self.max[offset].max(value);
    }

    /// The accumulators of one column: `levels` voxels from `base` (sum, samples, max, pulses).
    #[inline]
    pub fn column_mut(&mut self, base: usize, levels: usize) -> ColumnMut<'_> {
        let r = base..base + levels;
        ColumnMut {
            sum_q: &mut self.sum_q[r.clone()],
            samples: &mut self.samples[r.clone()],
            max: &mut self.max[r.clone()],
            pulses: &mut self.pulses[r],
        }
    }

    /// Counts one pulse passing through the voxel at `offset`.
    #[inline]
    pub fn pass(&mut self, offset: usize) {
        self.pulses[offset] = self.pulses[offset].saturating_add(1);
    }

    /// Voxels holding at least one sample or pass.
    pub fn occupied(&self) -> usize {
        self.samples
            .iter()
            .zip(&self.pulses)
            .filter(|(s, p)| **s > 0 || **p > 0)
            .count()
    }

    /// Whether nothing was ever deposited.
    pub fn is_blank(&self) -> bool {
        self.samples.iter().all(|s| *s == 0) && self.pulses.iter().all(|p| *p == 0)
    }

    /// Bytes of memory the accumulators take.
    pub fn bytes(&self) -> usize {
        self.len() * (8 + 4 + 4 + 4)
    }
}

/// The accumulators of one column of a tile, level by level.
pub struct ColumnMut<'a> {
    /// Sums, quanta.
    pub sum_q: &'a mut [i64],
    /// Samples.
    pub samples: &'a mut [u32],
    /// Maxima.
    pub max: &'a mut [f32],
    /// Pulses passed.
    pub pulses: &'a mut [u32],
}

impl ColumnMut<'_> {
    /// Deposits one sample at level `k` (must be below the column's length).
    #[inline]
    pub fn deposit(&mut self, k: usize, value_q: i64, value: f32) {
        // One bounds check for the four arrays of equal length.
        if k < self.sum_q.len() && k < self.samples.len() && k < self.max.len() {
            self.sum_q[k] = self.sum_q[k].saturating_add(value_q);
            self.samples[k] = self.samples[k].saturating_add(1);
            self.max[k] = self.max[k].max(value);
        }
    }

    /// Counts one pulse passing through level `k`.
    #[inline]
    pub fn pass(&mut self, k: usize) {
        if let Some(p) = self.pulses.get_mut(k) {
            *p = p.saturating_add(1);
        }
    }
}

/// Quantises an intensity to the nearest whole quantum (ties to even), clamped to ±2^50 quanta
/// (far beyond any real sum's terms); NaN gives an unspecified value — callers deposit only
/// finite values.
///
/// Adding 1.5·2^52 rounds to an integer in the floating-point unit (round to nearest even),
/// and that integer is then the low bits of the sum's representation: the quantum comes out of
/// an integer subtraction, without a float-to-int conversion, so a block of bins quantises in
/// vector registers.
#[inline]
pub fn quantise(value: f32, inv_quantum: f64) -> i64 {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 · 2^52
    const LIMIT: f64 = 1_125_899_906_842_624.0; // 2^50
    let q = (value as f64 * inv_quantum).clamp(-LIMIT, LIMIT);
    ((q + MAGIC).to_bits() as i64).wrapping_sub(MAGIC.to_bits() as i64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merging_partial_tiles_equals_depositing_everything_at_once() {
        let deposits: Vec<(usize, f32)> = (0..5000)
            .map(|i| ((i * 7919) % 64, ((i as f32) * 0.37).sin() * 3.3))
            .collect();
        let inv_q = 1e6;
        let all = {
            let mut t = TileData::new(64);
            for &(o, v) in &deposits {
                t.deposit(o, quantise(v, inv_q), v);
                t.pass(o);
            }
            t
        };
        // Three parts merged in every order give the same bits.
        let parts: Vec<TileData> = deposits
            .chunks(1700)
            .map(|c| {
                let mut t = TileData::new(64);
                for &(o, v) in c {
                    t.deposit(o, quantise(v, inv_q), v);
                    t.pass(o);
                }
                t
            })
            .collect();
        for order in [[0, 1, 2], [2, 1, 0], [1, 0, 2], [2, 0, 1]] {
            let mut m = TileData::new(64);
            for i in order {
                m.merge(&parts[i]);
            }
            assert_eq!(m.sum_q, all.sum_q);
            assert_eq!(m.samples, all.samples);
            assert_eq!(m.pulses, all.pulses);
            assert_eq!(
                m.max.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                all.max.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn quantisation_rounds_to_nearest_and_clamps() {
        assert_eq!(quantise(1.4e-6, 1e6), 1);
        assert_eq!(quantise(1.6e-6, 1e6), 2);
        assert_eq!(quantise(-1.6e-6, 1e6), -2);
        assert_eq!(quantise(2.5, 1.0), 2, "ties to even");
        assert_eq!(quantise(3.5, 1.0), 4, "ties to even");
        assert_eq!(quantise(-3.5, 1.0), -4);
        assert_eq!(quantise(0.0, 1e6), 0);
        assert_eq!(quantise(123.456_79, 1e6), 123_456_787);
        assert_eq!(quantise(f32::INFINITY, 1e6), 1 << 50);
        assert_eq!(quantise(f32::NEG_INFINITY, 1e6), -(1 << 50));
        for v in [0.37f32, -12.5, 1e-3, 4096.25, -0.000_75] {
            let want = (v as f64 * 1e6).round_ties_even() as i64;
            assert_eq!(quantise(v, 1e6), want, "{v}");
        }
    }

    #[test]
    fn untouched_voxels_have_no_maximum() {
        let mut t = TileData::new(4);
        t.deposit(1, 5, 5.0);
        assert!(t.max[0].is_nan() && t.max[1] == 5.0);
        assert_eq!(t.occupied(), 1);
        t.clear();
        assert!(t.is_blank());
    }
}
