//! The accumulators of one tile: per voxel the sum of deposited intensity (in integer quanta),
//! the number of samples, their maximum, and the number of pulses whose beam passed through it.
//!
//! Sums are integers of the grid's intensity quantum, so adding partial results is exact and
//! independent of order (floating-point sums are not associative); counts add, maxima take the
//! larger. That is what lets a tile touched by a later flight line, a resumed run or
//! `fwlidar merge` end bit-identical to processing everything at once.
//!
//! **Sparse in height.** A tile's `L` levels are cut into height chunks of `H` levels (`H` a
//! power of two, the store's chunk height): a chunk holds the `T × T × H` voxels of the tile's
//! columns between levels `kc·H` and `(kc+1)·H`, and exists only once a bin or a pass landed in
//! it. Memory and the bytes written follow the data, not the grid's height range. Inside a
//! chunk a voxel of column `col = j·T + i` at level `kk` sits at `col·H + kk` (a column is
//! contiguous). Offsets across the tile ([`VoxelIndex`](super::grid::VoxelIndex)) are
//! `col·L + k`.

/// The accumulators of one height chunk of a tile: per column of the tile written since the
/// chunk was last cleared, its `H` levels (contiguous, level `kk` at `kk`); a column never
/// written holds fill values (0, NaN) and takes no memory. A sparse flight line touches a few
/// columns of a tile, so memory, clearing, finding the occupied blocks and encoding follow the
/// columns written, not the tile (the store's bytes do not depend on it).
#[derive(Clone, Debug)]
pub struct Chunk {
    /// Per column of the tile, its slot in the arrays below (`NONE`: not written).
    slots: Vec<u32>,
    /// The column of each slot, in the order they were written.
    cols: Vec<u32>,
    /// Sum of deposited intensity, in quanta of the grid's `intensity_quantum`; slot `s`,
    /// level `kk` at `s·H + kk` (as the three below).
    sum_q: Vec<i64>,
    /// Samples (bins) deposited.
    samples: Vec<u32>,
    /// Largest deposited intensity (NaN where nothing was deposited).
    max: Vec<f32>,
    /// Pulses whose beam passed through the voxel (counted once per pulse).
    pulses: Vec<u32>,
    /// Levels per column, `H`.
    height: usize,
}

/// A column of a chunk not written.
const NONE: u32 = u32::MAX;

/// One column's `H` levels of a chunk, read.
#[derive(Clone, Copy, Debug)]
pub struct Column<'a> {
    /// Sums, quanta.
    pub sum_q: &'a [i64],
    /// Samples.
    pub samples: &'a [u32],
    /// Maxima (NaN: none).
    pub max: &'a [f32],
    /// Pulses passed.
    pub pulses: &'a [u32],
}

/// One column's `H` levels of a chunk, to write.
#[derive(Debug)]
pub struct ColumnMut<'a> {
    /// Sums, quanta.
    pub sum_q: &'a mut [i64],
    /// Samples.
    pub samples: &'a mut [u32],
    /// Maxima (NaN: none).
    pub max: &'a mut [f32],
    /// Pulses passed.
    pub pulses: &'a mut [u32],
}

/// The values of one voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Voxel {
    /// Sum, quanta.
    pub sum_q: i64,
    /// Samples.
    pub samples: u32,
    /// Maximum (NaN: none).
    pub max: f32,
    /// Pulses passed.
    pub pulses: u32,
}

impl PartialEq for Chunk {
    fn eq(&self, other: &Self) -> bool {
        // The values, column by column; a column not written equals one holding fill values.
        let fill = |c: Option<Column>| {
            c.is_none_or(|c| {
                c.samples.iter().all(|s| *s == 0)
                    && c.pulses.iter().all(|p| *p == 0)
                    && c.sum_q.iter().all(|q| *q == 0)
                    && c.max.iter().all(|m| m.is_nan())
            })
        };
        self.slots.len() == other.slots.len()
            && (0..self.slots.len()).all(|col| match (self.column(col), other.column(col)) {
                (Some(a), Some(b)) => {
                    a.sum_q == b.sum_q
                        && a.samples == b.samples
                        && a.pulses == b.pulses
                        && a.max
                            .iter()
                            .zip(b.max)
                            .all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
                }
                (a, b) => fill(a) && fill(b),
            })
    }
}

impl Chunk {
    fn new(columns: usize, height: usize) -> Chunk {
        Chunk {
            slots: vec![NONE; columns],
            cols: Vec::new(),
            sum_q: Vec::new(),
            samples: Vec::new(),
            max: Vec::new(),
            pulses: Vec::new(),
            height,
        }
    }

    /// Columns of the tile, `T²`.
    pub fn columns(&self) -> usize {
        self.slots.len()
    }

    /// Levels per column, `H`.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Column `col`'s levels, if it was written.
    #[inline]
    pub fn column(&self, col: usize) -> Option<Column<'_>> {
        let s = *self.slots.get(col)?;
        if s == NONE {
            return None;
        }
        let r = s as usize * self.height..(s as usize + 1) * self.height;
        Some(Column {
            sum_q: &self.sum_q[r.clone()],
            samples: &self.samples[r.clone()],
            max: &self.max[r.clone()],
            pulses: &self.pulses[r],
        })
    }

    /// Column `col`'s levels to write (below [`columns`](Self::columns)), given fill values when
    /// it is written for the first time.
    #[inline]
    pub fn column_mut(&mut self, col: usize) -> ColumnMut<'_> {
        let mut s = self.slots[col];
        if s == NONE {
            s = self.add_column(col);
        }
        let r = s as usize * self.height..(s as usize + 1) * self.height;
        ColumnMut {
            sum_q: &mut self.sum_q[r.clone()],
            samples: &mut self.samples[r.clone()],
            max: &mut self.max[r.clone()],
            pulses: &mut self.pulses[r],
        }
    }

    /// Index of level `kk` of column `col` in the arrays, the column given fill values when it
    /// is written for the first time.
    #[inline]
    fn at(&mut self, col: usize, kk: usize) -> usize {
        let mut s = self.slots[col];
        if s == NONE {
            s = self.add_column(col);
        }
        s as usize * self.height + kk
    }

    /// Deposits one sample at level `kk` of column `col` (see [`TileData::deposit`]).
    #[inline]
    pub fn deposit_at(&mut self, col: usize, kk: usize, value_q: i64, value: f32) {
        let i = self.at(col, kk);
        self.sum_q[i] = self.sum_q[i].saturating_add(value_q);
        self.samples[i] = self.samples[i].saturating_add(1);
        self.max[i] = self.max[i].max(value);
    }

    /// Counts one pulse through level `kk` of column `col`.
    #[inline]
    pub fn pass_at(&mut self, col: usize, kk: usize) {
        let i = self.at(col, kk);
        self.pulses[i] = self.pulses[i].saturating_add(1);
    }

    #[cold]
    fn add_column(&mut self, col: usize) -> u32 {
        let s = self.cols.len() as u32;
        self.slots[col] = s;
        self.cols.push(col as u32);
        let n = self.sum_q.len() + self.height;
        self.sum_q.resize(n, 0);
        self.samples.resize(n, 0);
        self.max.resize(n, f32::NAN);
        self.pulses.resize(n, 0);
        s
    }

    /// Whether column `col` was written since the chunk was last cleared.
    #[inline]
    pub fn is_touched(&self, col: usize) -> bool {
        self.slots.get(col).is_some_and(|s| *s != NONE)
    }

    /// How many of columns `cols` hold a sample or a pass at some level (0 for a range outside
    /// the chunk). A column deposited in always does; one read back from the store may be all
    /// fill, and is not counted: the count follows the values, not how they got here.
    pub fn live_in(&self, cols: std::ops::Range<usize>) -> u32 {
        let Some(slots) = self.slots.get(cols) else {
            return 0;
        };
        let h = self.height;
        slots
            .iter()
            .filter(|s| **s != NONE)
            .filter(|s| {
                let r = **s as usize * h..(**s as usize + 1) * h;
                self.samples[r.clone()].iter().any(|n| *n != 0)
                    || self.pulses[r].iter().any(|n| *n != 0)
            })
            .count() as u32
    }

    /// The columns written, in the order they were first written.
    pub fn touched_columns(&self) -> impl Iterator<Item = usize> + '_ {
        self.cols.iter().map(|c| *c as usize)
    }

    /// Back to fill values: the columns written are forgotten, their memory kept for reuse.
    fn clear(&mut self) {
        for &c in &self.cols {
            self.slots[c as usize] = NONE;
        }
        self.cols.clear();
        self.sum_q.clear();
        self.samples.clear();
        self.max.clear();
        self.pulses.clear();
    }

    /// Voxels held (`T² · H`, written or not).
    pub fn len(&self) -> usize {
        self.slots.len() * self.height
    }

    /// Whether the chunk holds no voxel (zero-sized).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes of memory the columns take (capacity kept for reuse included).
    pub fn bytes(&self) -> usize {
        self.sum_q.capacity() * 8
            + (self.samples.capacity() + self.max.capacity() + self.pulses.capacity()) * 4
            + self.slots.capacity() * 4
            + self.cols.capacity() * 4
    }

    /// Bytes the written columns and the column map use (lengths, not capacities: the same
    /// for the same deposits whatever memory was reused).
    pub fn used_bytes(&self) -> usize {
        self.sum_q.len() * 8
            + (self.samples.len() + self.max.len() + self.pulses.len()) * 4
            + self.slots.len() * 4
            + self.cols.len() * 4
    }

    /// Adds `other` (same shape): sums and counts add, maxima take the larger (the columns
    /// `other` wrote; the others hold fill values, which change nothing).
    pub fn merge(&mut self, other: &Chunk) {
        for col in other.touched_columns() {
            let (Some(b), true) = (other.column(col), col < self.columns()) else {
                continue;
            };
            let a = self.column_mut(col);
            for (a, b) in a.sum_q.iter_mut().zip(b.sum_q) {
                *a = a.saturating_add(*b);
            }
            for (a, b) in a.samples.iter_mut().zip(b.samples) {
                *a = a.saturating_add(*b);
            }
            for (a, b) in a.max.iter_mut().zip(b.max) {
                // f32::max returns the other operand when one is NaN.
                *a = a.max(*b);
            }
            for (a, b) in a.pulses.iter_mut().zip(b.pulses) {
                *a = a.saturating_add(*b);
            }
        }
    }

    /// Whether nothing was deposited in it (no column written: a written column holds a
    /// sample or a pass).
    pub fn is_blank(&self) -> bool {
        self.cols.is_empty()
    }
}

/// The accumulators of one tile: its height chunks, allocated when first touched.
#[derive(Clone, Debug)]
pub struct TileData {
    /// Columns of the tile, `T²`.
    columns: usize,
    /// Levels of the grid, `L`.
    levels: usize,
    /// log2 of the chunk height `H`.
    shift: u32,
    /// Chunk `kc`, if allocated (`ceil(L / H)` entries).
    chunks: Vec<Option<Box<Chunk>>>,
    /// Indices of the allocated chunks, in allocation order.
    present: Vec<u32>,
    /// Cleared chunks kept for reuse.
    pool: Vec<Box<Chunk>>,
}

impl PartialEq for TileData {
    fn eq(&self, other: &Self) -> bool {
        self.columns == other.columns
            && self.levels == other.levels
            && self.shift == other.shift
            && (0..self.chunks.len().max(other.chunks.len())).all(|kc| {
                match (self.chunk(kc), other.chunk(kc)) {
                    (Some(a), Some(b)) => a == b || (a.is_blank() && b.is_blank()),
                    (Some(a), None) | (None, Some(a)) => a.is_blank(),
                    (None, None) => true,
                }
            })
    }
}

/// Prefetches the cache lines of `values` (a hint; nothing on other architectures).
#[inline(always)]
fn prefetch_range<T>(values: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        const LINE: usize = 64;
        let start = values.as_ptr() as usize;
        let end = start + std::mem::size_of_val(values);
        let mut a = start & !(LINE - 1);
        while a < end {
            // SAFETY: a prefetch is a hint that never faults; every address is inside or at
            // the start of the line of an element of `values`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(a as *const i8) };
            a += LINE;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = values;
}

/// A tile's accumulators laid out densely, `T² · L` long in `col·L + k` order (tests, small
/// grids, evaluation).
#[derive(Clone, Debug, PartialEq)]
pub struct Dense {
    /// Sums, quanta.
    pub sum_q: Vec<i64>,
    /// Samples.
    pub samples: Vec<u32>,
    /// Maxima (NaN: none).
    pub max: Vec<f32>,
    /// Pulses passed.
    pub pulses: Vec<u32>,
}

impl TileData {
    /// Empty accumulators for a tile of `columns` (`T²`) columns of `levels` levels, cut into
    /// height chunks of `chunk_levels` (a power of two) levels.
    pub fn new(columns: usize, levels: usize, chunk_levels: usize) -> TileData {
        let h = chunk_levels.max(1).next_power_of_two();
        TileData {
            columns,
            levels,
            shift: h.trailing_zeros(),
            chunks: vec![None; levels.div_ceil(h)],
            present: Vec::new(),
            pool: Vec::new(),
        }
    }

    /// Empty accumulators for a tile of `grid`.
    pub fn for_grid(grid: &super::grid::Grid) -> TileData {
        let t = grid.tile_columns as usize;
        TileData::new(t * t, grid.levels as usize, grid.chunk_levels() as usize)
    }

    /// Levels per height chunk, `H`.
    #[inline]
    pub fn chunk_levels(&self) -> usize {
        1 << self.shift
    }

    /// log2 of the chunk height.
    #[inline]
    pub fn chunk_shift(&self) -> u32 {
        self.shift
    }

    /// Columns, `T²`.
    pub fn columns(&self) -> usize {
        self.columns
    }

    /// Levels, `L`.
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Height chunks of the grid, allocated or not.
    pub fn chunk_count(&self) -> usize {
        self.chunks.len()
    }

    /// Voxels of the whole tile (allocated or not), `T² · L`.
    pub fn len(&self) -> usize {
        self.columns * self.levels
    }

    /// Whether the tile has no voxel at all (zero-sized).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Chunk `kc`, if allocated.
    #[inline]
    pub fn chunk(&self, kc: usize) -> Option<&Chunk> {
        self.chunks.get(kc).and_then(|c| c.as_deref())
    }

    /// Asks the CPU to bring the accumulators of levels `lo ..= hi` of column `column` into
    /// cache (allocated chunks only; a hint, no effect on the values). A beam's bins in one
    /// column are known before their levels are computed, so the loads of a column last
    /// touched thousands of pulses ago overlap that arithmetic instead of stalling the updates.
    #[inline]
    pub fn prefetch_column(&self, column: usize, lo: usize, hi: usize) {
        if lo > hi || hi >= self.levels {
            return;
        }
        for kc in lo >> self.shift..=hi >> self.shift {
            let Some(c) = self.chunk(kc).and_then(|c| c.column(column)) else {
                continue;
            };
            let first = lo.max(kc << self.shift) - (kc << self.shift);
            let last = hi.min(((kc + 1) << self.shift) - 1) - (kc << self.shift);
            if last >= c.sum_q.len() {
                continue;
            }
            prefetch_range(&c.sum_q[first..=last]);
            prefetch_range(&c.samples[first..=last]);
            prefetch_range(&c.max[first..=last]);
            prefetch_range(&c.pulses[first..=last]);
        }
    }

    /// Chunk `kc` (below [`chunk_count`](Self::chunk_count)), allocated (or taken from the
    /// pool) when absent.
    #[inline]
    pub fn chunk_mut(&mut self, kc: usize) -> &mut Chunk {
        if self.chunks[kc].is_none() {
            self.alloc(kc);
        }
        self.chunks[kc].as_deref_mut().expect("allocated above")
    }

    #[cold]
    fn alloc(&mut self, kc: usize) {
        let h = 1usize << self.shift;
        let c = self
            .pool
            .pop()
            .unwrap_or_else(|| Box::new(Chunk::new(self.columns, h)));
        self.chunks[kc] = Some(c);
        self.present.push(kc as u32);
    }

    /// Indices of the allocated chunks, ascending.
    pub fn present(&self) -> Vec<u32> {
        let mut p = self.present.clone();
        p.sort_unstable();
        p
    }

    /// Allocated chunks.
    pub fn present_count(&self) -> usize {
        self.present.len()
    }

    /// Back to empty: chunks go to the pool (cleared), nothing is freed.
    pub fn clear(&mut self) {
        for kc in self.present.drain(..) {
            if let Some(mut c) = self.chunks[kc as usize].take() {
                c.clear();
                self.pool.push(c);
            }
        }
    }

    /// Adds `other` (same shape) into `self`: sums and counts add, maxima take the larger.
    pub fn merge(&mut self, other: &TileData) {
        debug_assert_eq!(self.len(), other.len());
        for &kc in &other.present {
            if let Some(b) = other.chunk(kc as usize) {
                self.chunk_mut(kc as usize).merge(b);
            }
        }
    }

    /// Where offset `col·L + k` lies: chunk, column, level inside the chunk.
    #[inline]
    fn locate(&self, offset: usize) -> (usize, usize, usize) {
        let (col, k) = (offset / self.levels, offset % self.levels);
        let h = 1usize << self.shift;
        (k >> self.shift, col, k & (h - 1))
    }

    /// Deposits one sample of `value_q` quanta (`value` itself for the maximum) at offset
    /// `col·L + k`.
    #[inline]
    pub fn deposit(&mut self, offset: usize, value_q: i64, value: f32) {
        let (kc, col, i) = self.locate(offset);
        self.chunk_mut(kc).deposit_at(col, i, value_q, value);
    }

    /// Counts one pulse passing through the voxel at offset `col·L + k`.
    #[inline]
    pub fn pass(&mut self, offset: usize) {
        let (kc, col, i) = self.locate(offset);
        self.chunk_mut(kc).pass_at(col, i);
    }

    /// Voxels holding at least one sample or pass.
    pub fn occupied(&self) -> usize {
        self.present
            .iter()
            .filter_map(|&kc| self.chunk(kc as usize))
            .map(|c| {
                c.touched_columns()
                    .filter_map(|col| c.column(col))
                    .map(|v| {
                        v.samples
                            .iter()
                            .zip(v.pulses)
                            .filter(|(s, p)| **s > 0 || **p > 0)
                            .count()
                    })
                    .sum::<usize>()
            })
            .sum()
    }

    /// Whether nothing was ever deposited.
    pub fn is_blank(&self) -> bool {
        self.present
            .iter()
            .filter_map(|&kc| self.chunk(kc as usize))
            .all(Chunk::is_blank)
    }

    /// Bytes of memory the allocated chunks take (pooled ones included).
    pub fn bytes(&self) -> usize {
        self.present
            .iter()
            .filter_map(|&kc| self.chunk(kc as usize))
            .chain(self.pool.iter().map(|c| &**c))
            .map(Chunk::bytes)
            .sum()
    }

    /// Bytes the height chunks deposited in use ([`Chunk::used_bytes`]; the memory budget of
    /// open tiles counts this, so that which tiles close early does not depend on reuse).
    pub fn used_bytes(&self) -> usize {
        self.present
            .iter()
            .filter_map(|&kc| self.chunk(kc as usize))
            .map(Chunk::used_bytes)
            .sum()
    }

    /// Calls `f(col, k, voxel)` for every voxel holding a sample: chunk by chunk (ascending),
    /// column by column (ascending), level by level.
    pub fn for_each_sampled(&self, mut f: impl FnMut(usize, usize, Voxel)) {
        let h = 1usize << self.shift;
        for kc in self.present() {
            let Some(c) = self.chunk(kc as usize) else {
                continue;
            };
            for col in 0..c.columns() {
                let Some(v) = c.column(col) else { continue };
                for kk in 0..h.min(v.samples.len()) {
                    let k = kc as usize * h + kk;
                    if v.samples[kk] > 0 && k < self.levels {
                        f(
                            col,
                            k,
                            Voxel {
                                sum_q: v.sum_q[kk],
                                samples: v.samples[kk],
                                max: v.max[kk],
                                pulses: v.pulses[kk],
                            },
                        );
                    }
                }
            }
        }
    }

    /// The whole tile laid out densely (`T² · L` voxels: small grids only).
    pub fn dense(&self) -> Dense {
        let n = self.len();
        let mut d = Dense {
            sum_q: vec![0; n],
            samples: vec![0; n],
            max: vec![f32::NAN; n],
            pulses: vec![0; n],
        };
        let h = 1usize << self.shift;
        for kc in self.present() {
            let Some(c) = self.chunk(kc as usize) else {
                continue;
            };
            for col in c.touched_columns() {
                let Some(v) = c.column(col) else { continue };
                for kk in 0..h.min(v.samples.len()) {
                    let k = kc as usize * h + kk;
                    if k < self.levels {
                        let o = col * self.levels + k;
                        d.sum_q[o] = v.sum_q[kk];
                        d.samples[o] = v.samples[kk];
                        d.max[o] = v.max[kk];
                        d.pulses[o] = v.pulses[kk];
                    }
                }
            }
        }
        d
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
            let mut t = TileData::new(4, 16, 4);
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
                let mut t = TileData::new(4, 16, 4);
                for &(o, v) in c {
                    t.deposit(o, quantise(v, inv_q), v);
                    t.pass(o);
                }
                t
            })
            .collect();
        for order in [[0, 1, 2], [2, 1, 0], [1, 0, 2], [2, 0, 1]] {
            let mut m = TileData::new(4, 16, 4);
            for i in order {
                m.merge(&parts[i]);
            }
            let (m, all) = (m.dense(), all.dense());
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
        let mut t = TileData::new(1, 4, 2);
        t.deposit(1, 5, 5.0);
        let d = t.dense();
        assert!(d.max[0].is_nan() && d.max[1] == 5.0);
        assert_eq!(t.occupied(), 1);
        t.clear();
        assert!(t.is_blank());
    }

    #[test]
    fn only_the_height_chunks_touched_are_allocated() {
        // 4 columns, 1000 levels in chunks of 8: a deposit at level 997 allocates chunk 124.
        let mut t = TileData::new(4, 1000, 8);
        assert_eq!(t.chunk_count(), 125);
        assert_eq!(t.present_count(), 0);
        assert!(t.is_blank() && t.bytes() == 0);
        let off = 3 * 1000 + 997;
        t.deposit(off, 7, 7.0);
        t.pass(off);
        assert_eq!(t.present(), vec![124]);
        let c = t.chunk(124).unwrap();
        assert_eq!(c.len(), 4 * 8);
        assert_eq!(
            c.column(3).unwrap().samples[5],
            1,
            "column 3, level 997 = 124·8 + 5"
        );
        assert!(c.column(0).is_none(), "columns not written take no memory");
        assert_eq!(t.dense().samples[off], 1);
        // Cleared chunks are pooled, and reused without allocating new memory.
        t.clear();
        assert_eq!(t.present_count(), 0);
        t.deposit(5, 1, 1.0);
        assert_eq!(t.present(), vec![0]);
        // One column's 8 levels (20 bytes a voxel) and the column map, not the chunk's 4.
        assert!(t.bytes() <= 8 * 20 + 4 * 4 + 4 * 4, "{}", t.bytes());
    }
}
