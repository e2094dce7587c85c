//! Depositing a pulse into the voxel grid: every return bin at its own position.
//!
//! Bin `i` of a return segment lies `t = start_ns + i·sample_ns` after the pulse's t0 at
//! `anchor + t·direction` (the pulse's geometry in the output CRS). It is deposited in the voxel
//! that contains that point, so an off-nadir beam's bins land in the columns the beam really
//! crossed — the seed's angular rectification, done per bin instead of per waveform. With
//! `footprint = true` a bin is shared equally among the columns whose centres lie within the
//! footprint radius at its range (beam divergence), at least the axis column.
//!
//! The deposited intensity is the bin's signal (volts) times its calibration factor when a
//! `calibrate` stage ran. Each deposit adds to the voxel's intensity sum (integer quanta), its
//! sample count and its maximum; the first bin of a pulse in a voxel also counts the pulse as
//! having passed through it (a straight beam enters a voxel once). Pulses without geometry or
//! with non-finite geometry, and bins outside the extent or the height range, are counted and
//! never deposited.

use crate::geo::dem::Dem;
use crate::pulse::{Pulse, SegmentKind};

use super::grid::{HeightMode, Placer};
use super::tile::{TileData, quantise};
use super::tiles::TileSet;
use super::zarr::StoreError;

/// What the voxeliser did (`summary.json`: `sinks.voxels`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct DepositStats {
    /// Pulses with at least one bin deposited.
    pub pulses_deposited: u64,
    /// Bins deposited.
    pub bins_deposited: u64,
    /// Pulses without geometry (not georeferenced).
    pub pulses_no_geometry: u64,
    /// Pulses whose anchor or direction is not finite.
    pub pulses_non_finite: u64,
    /// Pulses without a processed signal.
    pub pulses_no_signal: u64,
    /// Bins outside the horizontal extent.
    pub bins_outside_extent: u64,
    /// Bins outside the height range.
    pub bins_outside_heights: u64,
    /// Bins where the DEM has no height (`height = "above_dem"`).
    pub bins_outside_dem: u64,
    /// Bins whose intensity is not finite.
    pub bins_non_finite: u64,
    /// Bins already in the store from an interrupted run (skipped on resume).
    pub bins_resumed: u64,
}

/// How bins become deposits.
#[derive(Clone)]
pub struct DepositParams {
    /// Places positions on the grid.
    pub placer: Placer,
    /// Heights absolute or above the DEM.
    pub height: HeightMode,
    /// The DEM for `above_dem`.
    pub dem: Option<std::sync::Arc<Dem>>,
    /// 1 / intensity quantum.
    pub inv_quantum: f64,
    /// Spread over the footprint: full-angle divergence, radians (None: axis column only).
    pub footprint_divergence_rad: Option<f64>,
}

/// Deposits `pulse` into `tiles`.
pub fn deposit_pulse(
    pulse: &Pulse,
    tiles: &mut TileSet,
    p: &DepositParams,
    stats: &mut DepositStats,
) -> Result<(), StoreError> {
    let Some(g) = pulse.geometry else {
        stats.pulses_no_geometry += 1;
        return Ok(());
    };
    if !g.anchor.iter().chain(&g.direction).all(|v| v.is_finite()) {
        stats.pulses_non_finite += 1;
        return Ok(());
    }
    if pulse.signal.len() != pulse.raw.len() || pulse.signal.is_empty() {
        stats.pulses_no_signal += 1;
        return Ok(());
    }
    if p.footprint_divergence_rad.is_none() {
        return deposit_on_axis(pulse, &g, tiles, p, stats);
    }
    let seq = pulse.seq;
    let now = pulse.gps_time;
    let cal = pulse.calibration;
    let metres_per_ns = (g.direction[0] * g.direction[0]
        + g.direction[1] * g.direction[1]
        + g.direction[2] * g.direction[2])
        .sqrt();
    let mut deposited = 0u64;
    let mut prev: ([i64; 2], u32) = ([i64::MIN; 2], u32::MAX);
    let mut ground_col = [i64::MIN; 2];
    let mut ground = 0.0f64;
    for seg in pulse
        .segments
        .iter()
        .filter(|s| s.kind == SegmentKind::Return)
    {
        let values = &pulse.signal[seg.range()];
        for (i, &v) in values.iter().enumerate() {
            let t = seg.start_ns + i as f64 * pulse.sample_ns;
            let x = g.anchor[0] + t * g.direction[0];
            let y = g.anchor[1] + t * g.direction[1];
            let mut z = g.anchor[2] + t * g.direction[2];
            let Some(col) = p.placer.column(x, y) else {
                stats.bins_outside_extent += 1;
                continue;
            };
            if p.height == HeightMode::AboveDem {
                if col != ground_col {
                    match p.dem.as_ref().and_then(|d| d.height_at(x, y)) {
                        Some(h) => {
                            ground = h;
                            ground_col = col;
                        }
                        None => {
                            stats.bins_outside_dem += 1;
                            continue;
                        }
                    }
                }
                z -= ground;
            }
            let Some(k) = p.placer.level(z) else {
                stats.bins_outside_heights += 1;
                continue;
            };
            let value = match &cal {
                Some(c) => v * c.factor_at(t),
                None => v,
            };
            if !value.is_finite() {
                stats.bins_non_finite += 1;
                continue;
            }
            match p.footprint_divergence_rad {
                None => unreachable!("handled by deposit_on_axis"),
                Some(div) => {
                    let r = (t.max(0.0) * metres_per_ns) * div / 2.0;
                    deposited += spread(
                        tiles,
                        p,
                        stats,
                        (seq, now),
                        [x, y],
                        col,
                        k,
                        r,
                        value,
                        &mut prev,
                    )?;
                }
            }
        }
    }
    if deposited > 0 {
        stats.pulses_deposited += 1;
        stats.bins_deposited += deposited;
    }
    Ok(())
}

/// Deposits every return bin in the voxel of the beam axis. The bins are walked in runs that
/// stay in one column: the tile, its slot, the resume watermark and the DEM height are looked
/// up once per run, and a bin costs its position, a level and the deposit. A bin belongs to the
/// run while its fractional grid coordinates stay inside the run's column, the same test
/// [`Placer::column`] makes, so runs change nothing but the cost.
///
/// Compiled for AVX2 where the CPU has it (four doubles per instruction in the block arithmetic
/// of [`Span::deposit`]; the same IEEE operations in the same order and no fused multiply-add,
/// so the same results): on the survey-line mix ~20 % less time per pulse.
fn deposit_on_axis(
    pulse: &Pulse,
    g: &crate::pulse::PulseGeometry,
    tiles: &mut TileSet,
    p: &DepositParams,
    stats: &mut DepositStats,
) -> Result<(), StoreError> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2.
        return unsafe { deposit_on_axis_avx2(pulse, g, tiles, p, stats) };
    }
    deposit_on_axis_walk(pulse, g, tiles, p, stats)
}

/// [`deposit_on_axis`] for CPUs with AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn deposit_on_axis_avx2(
    pulse: &Pulse,
    g: &crate::pulse::PulseGeometry,
    tiles: &mut TileSet,
    p: &DepositParams,
    stats: &mut DepositStats,
) -> Result<(), StoreError> {
    deposit_on_axis_walk(pulse, g, tiles, p, stats)
}

/// The walk of [`deposit_on_axis`], inlined into each of its compilations.
#[inline(always)]
fn deposit_on_axis_walk(
    pulse: &Pulse,
    g: &crate::pulse::PulseGeometry,
    tiles: &mut TileSet,
    p: &DepositParams,
    stats: &mut DepositStats,
) -> Result<(), StoreError> {
    let mut walk = AxisWalk::new(pulse, g, p);
    let mut scratch = Scratch::new();
    for seg in pulse
        .segments
        .iter()
        .filter(|s| s.kind == SegmentKind::Return)
    {
        let values = &pulse.signal[seg.range()];
        let mut i = 0usize;
        while i < values.len() {
            i = walk.run(seg, values, i, tiles, stats, &mut scratch)?;
        }
    }
    walk.finish(stats);
    Ok(())
}

/// What [`deposit_on_axis`] counted so far, added to [`DepositStats`] once the pulse is done.
#[derive(Default)]
struct AxisCounts {
    /// Bins deposited.
    deposited: u64,
    /// Bins outside the height range.
    outside_heights: u64,
    /// Bins whose intensity is not finite.
    non_finite: u64,
    /// Bins already in the store (resume), not deposited.
    resumed: u64,
}

impl AxisCounts {
    /// Adds `other`'s counts to these.
    #[inline(always)]
    fn add(&mut self, other: &AxisCounts) {
        self.deposited += other.deposited;
        self.outside_heights += other.outside_heights;
        self.non_finite += other.non_finite;
        self.resumed += other.resumed;
    }
}

/// The counts and the last voxel of [`AxisWalk::deposit_edge`], kept in locals while it walks.
struct EdgeState {
    /// What the edge bins counted.
    counts: AxisCounts,
    /// The tile and offset of the voxel the last bin landed in.
    prev: ([i64; 2], u32),
}

/// The pulse-wide constants of [`deposit_on_axis`] and the state it carries from one run of
/// bins (bins in one column) to the next.
struct AxisWalk<'a> {
    /// The pulse's geometry: anchor (metres, output CRS) and direction (metres per ns).
    g: &'a crate::pulse::PulseGeometry,
    /// How bins become deposits.
    p: &'a DepositParams,
    /// The pulse's order of arrival.
    seq: u64,
    /// The pulse's GPS time, seconds.
    now: f64,
    /// Bin spacing, ns.
    sample_ns: f64,
    /// The pulse's calibration, if a `calibrate` stage ran.
    cal: Option<crate::pulse::Calibration>,
    /// Columns along a tile's side.
    side: i64,
    /// Levels of a column.
    levels: i64,
    /// Levels per metre.
    inv_z: f64,
    /// Bottom of level 0, metres.
    z_bottom: f64,
    /// Whether heights are above the DEM.
    above_dem: bool,
    /// The beam's horizontal slope in columns per bin, x and y.
    slope: [f64; 2],
    /// Bins per column along x and y (the slope's reciprocal; 0: vertical).
    per_column: [f64; 2],
    /// The tile of the previous run, its slot and resume mark (a pulse opens no tile twice: a
    /// slot closed early is never one the current pulse has touched).
    cur: ([i64; 2], usize, u64),
    /// The tile and offset of the voxel the last bin landed in (its pass is counted once).
    prev: ([i64; 2], u32),
    /// What was counted so far.
    counts: AxisCounts,
}

/// The column one run of bins stays in.
struct AxisRun {
    /// The column's tile.
    tile: [i64; 2],
    /// The tile's resume mark: pulses with a lower `seq` are already in the store.
    skip: u64,
    /// Offset of the column's level 0 in its tile.
    base: usize,
    /// The column's global index, x and y, as floats (the column's low edge in grid units).
    col: [f64; 2],
    /// Ground height under the column, metres (0 unless heights are above the DEM).
    ground: f64,
}

impl<'a> AxisWalk<'a> {
    /// The constants of `pulse` on the grid of `p`, nothing counted yet.
    #[inline]
    fn new(pulse: &Pulse, g: &'a crate::pulse::PulseGeometry, p: &'a DepositParams) -> Self {
        let placer = &p.placer;
        // The beam's horizontal slope in columns per bin, and its reciprocal (0: vertical).
        let slope = [
            pulse.sample_ns * g.direction[0] * placer.inv(0),
            pulse.sample_ns * g.direction[1] * placer.inv(1),
        ];
        AxisWalk {
            g,
            p,
            seq: pulse.seq,
            now: pulse.gps_time,
            sample_ns: pulse.sample_ns,
            cal: pulse.calibration,
            side: placer.side(),
            levels: placer.levels(),
            inv_z: placer.inv(2),
            z_bottom: placer.z_bottom(),
            above_dem: p.height == HeightMode::AboveDem,
            slope,
            per_column: slope.map(|s| if s != 0.0 { 1.0 / s.abs() } else { 0.0 }),
            cur: ([i64::MIN; 2], 0, 0),
            prev: ([i64::MIN; 2], u32::MAX),
            counts: AxisCounts::default(),
        }
    }

    /// Deposits the run of bins of `values` (the return segment `seg`) that starts at bin `i`
    /// and stays in one column; returns the first bin after it. A first bin outside the extent
    /// or the DEM is counted and makes a run of its own.
    #[inline(always)]
    fn run(
        &mut self,
        seg: &crate::pulse::Segment,
        values: &[f32],
        i: usize,
        tiles: &mut TileSet,
        stats: &mut DepositStats,
        scratch: &mut Scratch,
    ) -> Result<usize, StoreError> {
        // The first bin of a run: its column, tile, slot and ground.
        let t = seg.start_ns + i as f64 * self.sample_ns;
        let x = self.g.anchor[0] + t * self.g.direction[0];
        let y = self.g.anchor[1] + t * self.g.direction[1];
        let Some((col, ground)) = self.locate(x, y, stats) else {
            return Ok(i + 1);
        };
        let placer = &self.p.placer;
        let tile = placer.tile_of(col);
        let (slot, skip) = self.open_tile(tile, tiles)?;
        let side = self.side;
        let base = placer.offset(col[0] - tile[0] * side, col[1] - tile[1] * side, 0) as usize;
        let run = AxisRun {
            tile,
            skip,
            base,
            col: [col[0] as f64, col[1] as f64],
            ground,
        };
        let safe_end = self.safe_end(&run, x, y, i, values.len());
        let data = tiles.data(slot);
        if self.prev.0 != tile {
            self.prev = (tile, u32::MAX);
        }
        self.deposit_inside(data, scratch, &run, seg, &values[..safe_end], i);
        let j = self.deposit_edge(data, &run, seg, values, safe_end.max(i));
        Ok(j.max(i + 1))
    }

    /// The column of a bin at `(x, y)` (metres) and the ground height under it (metres; 0
    /// unless heights are above the DEM); None, counted, when the bin is outside the extent or
    /// the DEM.
    #[inline(always)]
    fn locate(&self, x: f64, y: f64, stats: &mut DepositStats) -> Option<([i64; 2], f64)> {
        let Some(col) = self.p.placer.column(x, y) else {
            stats.bins_outside_extent += 1;
            return None;
        };
        let ground = if self.above_dem {
            match self.p.dem.as_ref().and_then(|d| d.height_at(x, y)) {
                Some(h) => h,
                None => {
                    stats.bins_outside_dem += 1;
                    return None;
                }
            }
        } else {
            0.0
        };
        Some((col, ground))
    }

    /// The slot of `tile` and its resume mark, looked up only when the tile is not the previous
    /// run's; the slot is marked as touched at the pulse's time.
    #[inline(always)]
    fn open_tile(
        &mut self,
        tile: [i64; 2],
        tiles: &mut TileSet,
    ) -> Result<(usize, u64), StoreError> {
        if tile != self.cur.0 {
            let (slot, skip) = tiles.slot_for(tile, self.seq, self.now)?;
            tiles.touched(slot, self.now);
            self.cur = (tile, slot, skip);
        }
        Ok((self.cur.1, self.cur.2))
    }

    /// The end of the bins from `i` on (of `len`) certainly inside the run's column, from the
    /// beam's slope in grid units (a margin of 1e-6 column keeps rounding from deciding): no
    /// horizontal test needed for them. `(x, y)` is bin `i`'s position, metres.
    #[inline(always)]
    fn safe_end(&self, run: &AxisRun, x: f64, y: f64, i: usize, len: usize) -> usize {
        let [gx, gy] = self.p.placer.grid_xy(x, y);
        let safe = self
            .steps(gx, run.col[0], 0)
            .min(self.steps(gy, run.col[1], 1))
            .max(0.0);
        if safe >= (len - i) as f64 {
            len
        } else {
            i + safe as usize
        }
    }

    /// Bins until the beam, at fractional grid coordinate `g` along `axis`, leaves the column
    /// whose low edge is `c` along that axis (infinite when the beam is vertical).
    #[inline(always)]
    fn steps(&self, g: f64, c: f64, axis: usize) -> f64 {
        if self.slope[axis] > 0.0 {
            (c + 1.0 - 1e-6 - g) * self.per_column[axis]
        } else if self.slope[axis] < 0.0 {
            (g - c - 1e-6) * self.per_column[axis]
        } else {
            f64::INFINITY
        }
    }

    /// Deposits bins `first..values.len()`, all certainly inside the run's column, in blocks
    /// ([`Span::deposit`]); on resume they are only counted.
    #[inline(always)]
    fn deposit_inside(
        &mut self,
        data: &mut TileData,
        scratch: &mut Scratch,
        run: &AxisRun,
        seg: &crate::pulse::Segment,
        values: &[f32],
        first: usize,
    ) {
        let column_index = run.base / self.levels as usize;
        let span = Span {
            values,
            first,
            start_ns: seg.start_ns,
            sample_ns: self.sample_ns,
            // Fractional level of a bin t ns after t0: c0 + c1·t.
            c0: (self.g.anchor[2] - run.ground - self.z_bottom) * self.inv_z,
            c1: self.g.direction[2] * self.inv_z,
            inv_q: self.p.inv_quantum,
            base: run.base as u32,
        };
        if self.seq >= run.skip && first < values.len() {
            // The levels the span's bins can reach (their level is linear in time).
            let levels = self.levels as f64;
            let t_first = seg.start_ns + first as f64 * self.sample_ns;
            let t_last = seg.start_ns + (values.len() - 1) as f64 * self.sample_ns;
            let (a, b) = (span.c0 + t_first * span.c1, span.c0 + t_last * span.c1);
            let (lo, hi) = (a.min(b).max(0.0), a.max(b).min(levels - 1.0));
            if lo <= hi {
                data.prefetch_column(column_index, lo as usize, hi as usize);
            }
        }
        let mut counts = SpanCounts::default();
        if self.seq < run.skip {
            // Already in the store (resume): count, do not deposit.
            self.counts.resumed += (values.len() - first) as u64;
        } else if let Some(c) = &self.cal {
            span.deposit(
                data,
                column_index,
                &mut self.prev.1,
                &mut counts,
                scratch,
                |t| c.factor_at(t),
            );
        } else {
            span.deposit(
                data,
                column_index,
                &mut self.prev.1,
                &mut counts,
                scratch,
                |_| 1.0,
            );
        }
        self.counts.deposited += counts.deposited;
        self.counts.outside_heights += counts.outside_heights;
        self.counts.non_finite += counts.non_finite;
    }

    /// Deposits the bins from `j` on near the column's edge, tested one by one, until one
    /// leaves the run's column; returns the first bin not deposited.
    #[inline(always)]
    fn deposit_edge(
        &mut self,
        data: &mut TileData,
        run: &AxisRun,
        seg: &crate::pulse::Segment,
        values: &[f32],
        mut j: usize,
    ) -> usize {
        let g = self.g;
        let [cx, cy] = run.col;
        // The counts and the last voxel, kept locally while the bins are walked.
        let mut edge = EdgeState {
            counts: AxisCounts::default(),
            prev: self.prev,
        };
        while j < values.len() {
            let t = seg.start_ns + j as f64 * self.sample_ns;
            let x = g.anchor[0] + t * g.direction[0];
            let y = g.anchor[1] + t * g.direction[1];
            let [gx, gy] = self.p.placer.grid_xy(x, y);
            if !(gx >= cx && gx < cx + 1.0 && gy >= cy && gy < cy + 1.0) {
                break;
            }
            let z = g.anchor[2] + t * g.direction[2] - run.ground;
            let kf = (z - self.z_bottom) * self.inv_z;
            self.edge_bin(data, run, &mut edge, values[j], t, kf);
            j += 1;
        }
        self.prev = edge.prev;
        self.counts.add(&edge.counts);
        j
    }

    /// One bin of the run, of signal `v` (volts) `t` ns after t0 at fractional level `kf`:
    /// the deposit and its counts.
    #[inline(always)]
    fn edge_bin(
        &self,
        data: &mut TileData,
        run: &AxisRun,
        edge: &mut EdgeState,
        v: f32,
        t: f64,
        kf: f64,
    ) {
        // In range, truncation is the floor.
        if !(kf >= 0.0 && kf < self.levels as f64) {
            edge.counts.outside_heights += 1;
            return;
        }
        let value = match &self.cal {
            Some(c) => v * c.factor_at(t),
            None => v,
        };
        if !value.is_finite() {
            edge.counts.non_finite += 1;
            return;
        }
        if self.seq < run.skip {
            edge.counts.resumed += 1;
            return;
        }
        let k = kf as usize;
        data.deposit(run.base + k, quantise(value, self.p.inv_quantum), value);
        let off = (run.base + k) as u32;
        if edge.prev.1 != off || edge.prev.0 != run.tile {
            data.pass(run.base + k);
            edge.prev = (run.tile, off);
        }
        edge.counts.deposited += 1;
    }

    /// Adds what the pulse's bins counted to `stats`, and the pulse when a bin was deposited.
    #[inline]
    fn finish(&self, stats: &mut DepositStats) {
        let c = &self.counts;
        stats.bins_outside_heights += c.outside_heights;
        stats.bins_non_finite += c.non_finite;
        stats.bins_resumed += c.resumed;
        if c.deposited > 0 {
            stats.pulses_deposited += 1;
            stats.bins_deposited += c.deposited;
        }
    }
}

/// Bins `first..values.len()` of a return segment, all in one column.
struct Span<'a> {
    values: &'a [f32],
    first: usize,
    start_ns: f64,
    sample_ns: f64,
    c0: f64,
    c1: f64,
    inv_q: f64,
    /// Offset of the column's level 0 in its tile.
    base: u32,
}

/// Bins handled per block by [`Span::deposit`].
const BLOCK: usize = 64;

/// The per-block arrays of [`Span::deposit`], made once per pulse.
struct Scratch {
    ks: [u32; BLOCK],
    qs: [i64; BLOCK],
    vs: [f32; BLOCK],
    kfs: [f64; BLOCK],
}

impl Scratch {
    fn new() -> Self {
        Scratch {
            ks: [0; BLOCK],
            qs: [0; BLOCK],
            vs: [0.0; BLOCK],
            kfs: [0.0; BLOCK],
        }
    }
}

/// What a span did.
#[derive(Default)]
struct SpanCounts {
    deposited: u64,
    outside_heights: u64,
    non_finite: u64,
}

impl Span<'_> {
    /// The hot loop: per bin its time, level, calibrated value, and the four accumulators of
    /// the height chunk it lands in (allocated when the first bin lands there). `factor` is the
    /// calibration (a constant 1 without one, which the compiler folds).
    #[inline(always)]
    fn deposit(
        &self,
        data: &mut TileData,
        column: usize,
        prev_off: &mut u32,
        counts: &mut SpanCounts,
        scratch: &mut Scratch,
        factor: impl Fn(f64) -> f32,
    ) {
        let levels = data.levels();
        let shift = data.chunk_shift();
        let h = 1usize << shift;
        let mask = (h - 1) as u32;
        let levels_f = levels as f64;
        let mut prev = *prev_off;
        // Two passes over blocks of bins: the arithmetic without branches (level, calibrated
        // value, quantum; the compiler vectorises it), then the updates, in runs of bins that
        // stay in one height chunk (a beam crosses a chunk's levels in order).
        const OUTSIDE: u32 = u32::MAX;
        const NON_FINITE: u32 = u32::MAX - 1;
        let Scratch { ks, qs, vs, kfs } = scratch;
        let mut j0 = self.first;
        while j0 < self.values.len() {
            let len = (self.values.len() - j0).min(BLOCK);
            let block = &self.values[j0..j0 + len];
            let t0 = self.start_ns + j0 as f64 * self.sample_ns;
            let (c0, c1, dt, inv_q) = (self.c0, self.c1, self.sample_ns, self.inv_q);
            // Loops of one element type each, so that they vectorise.
            for (b, kf) in kfs[..len].iter_mut().enumerate() {
                *kf = c0 + (t0 + (b as i32) as f64 * dt) * c1;
            }
            for (b, (out, &v)) in vs[..len].iter_mut().zip(block).enumerate() {
                *out = v * factor(t0 + (b as i32) as f64 * dt);
            }
            for (q, &v) in qs[..len].iter_mut().zip(&vs[..len]) {
                *q = quantise(v, inv_q);
            }
            for ((k, &kf), &v) in ks[..len].iter_mut().zip(&kfs[..len]).zip(&vs[..len]) {
                let inside = kf >= 0.0 && kf < levels_f;
                let level = if inside {
                    floor_in_range(kf) as u32
                } else {
                    OUTSIDE
                };
                *k = if v.is_finite() || !inside {
                    level
                } else {
                    NON_FINITE
                };
            }
            let mut b = 0;
            while b < len {
                let k0 = ks[b];
                if k0 as usize >= levels {
                    if k0 == NON_FINITE {
                        counts.non_finite += 1;
                    } else {
                        counts.outside_heights += 1;
                    }
                    b += 1;
                    continue;
                }
                let kc = k0 >> shift;
                // The run: bins of this height chunk (OUTSIDE and NON_FINITE never match),
                // found first so that the update loop below has no test but its own bound.
                let mut e = b + 1;
                while e < len && ks[e] >> shift == kc {
                    e += 1;
                }
                let chunk = data.chunk_mut(kc as usize);
                if column >= chunk.columns() {
                    // Not reached: a column of the tile is below T².
                    counts.outside_heights += (e - b) as u64;
                    b = e;
                    continue;
                }
                // This column's `h` levels of the chunk (the mask below bounds every index).
                let c = chunk.column_mut(column);
                let (sum_q, samples, max, pulses) = (c.sum_q, c.samples, c.max, c.pulses);
                for ((&k, &q), &value) in ks[b..e].iter().zip(&qs[b..e]).zip(&vs[b..e]) {
                    let i = (k & mask) as usize & (h - 1);
                    // Plain adds: 2^63 quanta or 2^32 samples in one voxel are out of reach;
                    // merging saturates.
                    sum_q[i] = sum_q[i].wrapping_add(q);
                    samples[i] = samples[i].wrapping_add(1);
                    // NaN (nothing yet) fails the comparison and takes the value.
                    let m = max[i];
                    max[i] = if m >= value { m } else { value };
                    let off = self.base + k;
                    if off != prev {
                        pulses[i] = pulses[i].wrapping_add(1);
                        prev = off;
                    }
                }
                counts.deposited += (e - b) as u64;
                b = e;
            }
            j0 += len;
        }
        *prev_off = prev;
    }
}

/// `floor(x)` as an integer for `0 <= x < 2^50`, without a float-to-int conversion (so that a
/// block of levels converts in vector registers): round to the nearest integer by adding and
/// subtracting 1.5·2^52, step down where that rounded up, and read the integer from the bits.
#[inline(always)]
fn floor_in_range(x: f64) -> i64 {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 · 2^52
    let r = (x + MAGIC) - MAGIC;
    let f = if r > x { r - 1.0 } else { r };
    ((f + MAGIC).to_bits() as i64).wrapping_sub(MAGIC.to_bits() as i64)
}

/// Most columns one bin is spread over (a footprint wider than 8 columns on a side is spread
/// over the 8 × 8 nearest the axis).
const MAX_SPREAD: i64 = 4;

/// Shares one bin among the columns whose centres lie within `r` of `(x, y)`.
#[allow(clippy::too_many_arguments)]
fn spread(
    tiles: &mut TileSet,
    p: &DepositParams,
    stats: &mut DepositStats,
    (seq, now): (u64, f64),
    [x, y]: [f64; 2],
    axis: [i64; 2],
    k: i64,
    r: f64,
    value: f32,
    prev: &mut ([i64; 2], u32),
) -> Result<u64, StoreError> {
    let mut cols = [[0i64; 2]; (2 * MAX_SPREAD * 2 * MAX_SPREAD) as usize];
    let mut n = 0usize;
    let reach_x = ((r * p.placer_inv(0)).ceil() as i64).clamp(0, MAX_SPREAD);
    let reach_y = ((r * p.placer_inv(1)).ceil() as i64).clamp(0, MAX_SPREAD);
    for dy in -reach_y..=reach_y {
        for dx in -reach_x..=reach_x {
            let c = [axis[0] + dx, axis[1] + dy];
            let centre = p.placer.column_centre(c);
            let d2 = (centre[0] - x).powi(2) + (centre[1] - y).powi(2);
            if d2 <= r * r && n < cols.len() {
                cols[n] = c;
                n += 1;
            }
        }
    }
    if n == 0 {
        cols[0] = axis;
        n = 1;
    }
    let share = value / n as f32;
    let q = quantise(share, p.inv_quantum);
    let mut deposited = 0;
    for &c in &cols[..n] {
        // A column of the square may fall outside the extent: place it through its centre.
        let centre = p.placer.column_centre(c);
        if p.placer.column(centre[0], centre[1]).is_none() {
            stats.bins_outside_extent += 1;
            continue;
        }
        let vi = p.placer.voxel(c, k);
        let (s, skip) = tiles.slot_for(vi.tile, seq, now)?;
        tiles.touched(s, now);
        if seq < skip {
            stats.bins_resumed += 1;
            continue;
        }
        tiles.data(s).deposit(vi.offset as usize, q, share);
        deposited = 1;
    }
    // The pass is counted on the beam axis: the voxel of the axis column at this level.
    let vi = p.placer.voxel(axis, k);
    if *prev != (vi.tile, vi.offset) {
        let (s, skip) = tiles.slot_for(vi.tile, seq, now)?;
        tiles.touched(s, now);
        if seq >= skip {
            tiles.data(s).pass(vi.offset as usize);
        }
        *prev = (vi.tile, vi.offset);
    }
    Ok(deposited)
}

impl DepositParams {
    fn placer_inv(&self, axis: usize) -> f64 {
        self.placer.inv(axis)
    }
}

#[cfg(test)]
mod tests {
    use super::floor_in_range;

    #[test]
    fn floor_without_conversion_is_the_floor() {
        let mut x = 0.0f64;
        while x < 500.0 {
            assert_eq!(floor_in_range(x), x.floor() as i64, "{x}");
            x += 0.037;
        }
        for x in [
            0.0,
            1.0,
            2.0,
            2.5,
            3.5,
            1.0 - 1e-12,
            399.999_999_999,
            4.0 - f64::EPSILON * 4.0,
            1e15 + 0.5,
        ] {
            assert_eq!(floor_in_range(x), x.floor() as i64, "{x}");
        }
    }
}
