//! The tile lifecycle: open tiles live in memory up to a bound; a tile closes when the flight
//! has left it, is written to the store atomically and its memory reused; a tile touched again
//! (a later flight line, or a resumed run) is read back and merged exactly.
//!
//! A tile closes when no bin has been deposited in it for `close_after_s` of pulse time **and**
//! it lies outside the current swath (the bounding box of everything deposited during the last
//! `close_after_s` to `2·close_after_s`). When `max_open_tiles` are open and another is
//! needed, the one deposited least recently closes early (counted `closed_early`), and so do
//! tiles while the open ones' columns take more than `max_open_mib` (checked when a tile opens
//! and every 256 pulses; `closed_over_budget`): memory stays bounded whatever the flight's
//! length. The rule alone is
//! [`CloseRule`], which the metrics rasters' tiles follow too (`src/sink/metrics_rasters.rs`).

use std::collections::HashMap;

use super::grid::Grid;
use super::tile::TileData;
use super::zarr::{Committed, StoreError, ZarrStore};

/// Counters of the lifecycle (`summary.json`: `sinks.voxels.tiles`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TileStats {
    /// Tiles opened in memory.
    pub opened: u64,
    /// Tiles written and freed.
    pub closed: u64,
    /// Of those, closed because `max_open_tiles` were open or their memory passed
    /// `max_open_mib`.
    pub closed_early: u64,
    /// Of the tiles closed early, those closed for the memory budget (`max_open_mib`).
    pub closed_over_budget: u64,
    /// Tiles opened that were already in the store and merged with it.
    pub merged: u64,
    /// Most tiles open at once.
    pub peak_open: usize,
    /// Memory of one height chunk of a tile, bytes (a tile holds the chunks it was deposited
    /// in).
    pub chunk_bytes: usize,
    /// Most height chunks allocated at once over the open tiles.
    pub peak_chunks: usize,
    /// Most memory the open tiles' columns took at once, bytes (measured when a tile opens or
    /// closes).
    pub peak_open_bytes: usize,
    /// Tile writer threads.
    pub writers: usize,
    /// Tile LAS files written (`[voxels] las`).
    pub las_files: u64,
}

struct Slot {
    tile: [i64; 2],
    data: TileData,
    /// Pulse time of the latest deposit, GPS seconds.
    last_deposit_s: f64,
    /// Deposits of pulses numbered below this are already in the tile (resume).
    skip_below: u64,
    /// The latest pulse that asked for the tile.
    last_seq: u64,
}

/// Work for a writer thread.
enum WriteJob {
    /// A closed tile to write.
    Tile {
        tile: [i64; 2],
        data: TileData,
        watermark: u64,
    },
    /// Groups of tiles to write out (the grouped layout: the flight has left them, or a tile of
    /// them is to be read back).
    Flush(Vec<[i64; 2]>),
}

/// What a writer thread hands back.
enum WriteDone {
    /// A tile's buffer, for reuse (its data is encoded).
    Buffer(TileData),
    /// A tile made durable.
    Committed(Committed),
    /// A write failed: the run stops.
    Failed(StoreError),
}

/// The writer threads: tiles closed on the sink thread are written (compressed, synced,
/// committed) there, so that a row of tiles closing at once does not stall the deposits. Tiles
/// are partitioned among the threads by their numbers: a tile always goes to the same thread,
/// so its writes happen in the order they were handed over.
struct Writer {
    jobs: Vec<crossbeam_channel::Sender<WriteJob>>,
    done: crossbeam_channel::Receiver<WriteDone>,
    threads: Vec<std::thread::JoinHandle<()>>,
    /// Tiles handed over and not yet durable.
    in_flight: std::collections::HashSet<[i64; 2]>,
    /// The store's grouping of tiles into shards: tiles of one group go to one thread.
    grouped: bool,
    /// Buffers of written tiles, for the next tile that closes.
    spare: Vec<TileData>,
}

impl Writer {
    /// The thread writing `tile` (`key`: the tile, or its group when grouped).
    fn of(&self, key: [i64; 2]) -> usize {
        let tile = key;
        let h = (tile[0] as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (tile[1] as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        ((h >> 32) % self.jobs.len().max(1) as u64) as usize
    }
}

impl Drop for Writer {
    fn drop(&mut self) {
        self.jobs.clear();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// The closing rule of [`TileSet`], on its own so that other products tiled behind the flight
/// close by the same rule (the metrics rasters, `src/sink/metrics_rasters.rs`): a tile closes
/// when nothing has been deposited in it for `close_after_s` of pulse time and it lies outside
/// the swath, the bounding box of the tiles deposited in during the last `close_after_s` to
/// `2·close_after_s`. Tiles are numbered `[ix, iy]` in the caller's tiling.
#[derive(Clone, Debug)]
pub struct CloseRule {
    close_after_s: f64,
    /// Swath boxes `[cx0, cy0, cx1, cy1]` (tiles) of the current and the previous period.
    swath: [[i64; 4]; 2],
    period_end_s: f64,
    next_check_s: f64,
}

impl CloseRule {
    /// The rule closing tiles idle for `close_after_s` seconds of pulse time.
    pub fn new(close_after_s: f64) -> CloseRule {
        CloseRule {
            close_after_s,
            swath: [EMPTY_BOX; 2],
            period_end_s: f64::NEG_INFINITY,
            next_check_s: f64::NEG_INFINITY,
        }
    }

    /// Notes a deposit into `tile` (it joins the current swath).
    #[inline]
    pub fn touched(&mut self, tile: [i64; 2]) {
        let b = &mut self.swath[0];
        b[0] = b[0].min(tile[0]);
        b[1] = b[1].min(tile[1]);
        b[2] = b[2].max(tile[0]);
        b[3] = b[3].max(tile[1]);
    }

    /// Advances the rule's clock to pulse time `now_s` (GPS seconds). Returns the swath when the
    /// open tiles are due to be examined (at most eight times per `close_after_s`), `None`
    /// otherwise or when `now_s` is not finite.
    pub fn due(&mut self, now_s: f64) -> Option<[i64; 4]> {
        if !now_s.is_finite() {
            return None;
        }
        if now_s >= self.period_end_s {
            self.swath[1] = self.swath[0];
            self.swath[0] = EMPTY_BOX;
            self.period_end_s = now_s + self.close_after_s;
        }
        if now_s < self.next_check_s {
            return None;
        }
        self.next_check_s = now_s + self.close_after_s / 8.0;
        Some([
            self.swath[0][0].min(self.swath[1][0]),
            self.swath[0][1].min(self.swath[1][1]),
            self.swath[0][2].max(self.swath[1][2]),
            self.swath[0][3].max(self.swath[1][3]),
        ])
    }

    /// Whether `tile`, last deposited in at `last_deposit_s`, closes at `now_s` given the
    /// `swath` that [`CloseRule::due`] returned.
    #[inline]
    pub fn closes(
        &self,
        swath: &[i64; 4],
        tile: [i64; 2],
        last_deposit_s: f64,
        now_s: f64,
    ) -> bool {
        let inside = tile[0] >= swath[0]
            && tile[0] <= swath[2]
            && tile[1] >= swath[1]
            && tile[1] <= swath[3];
        now_s - last_deposit_s > self.close_after_s && !inside
    }
}

/// Open tiles over a store.
pub struct TileSet {
    store: ZarrStore,
    slots: Vec<Slot>,
    free: Vec<usize>,
    open: HashMap<[i64; 2], usize>,
    max_open: usize,
    /// Memory the open tiles' columns may take, bytes (checked when a tile opens and every
    /// `BUDGET_CHECK_PULSES` pulses).
    budget_bytes: usize,
    since_budget_check: u32,
    rule: CloseRule,
    stats: TileStats,
    /// Reused list of the slots to close.
    idle: Vec<usize>,
    /// Write each closed tile's occupied voxels as LAS into this folder (with this CRS WKT).
    las: Option<(std::path::PathBuf, Option<String>)>,
    /// Writes closed tiles on a thread of its own (`with_writer_thread`); `None`: here.
    writer: Option<Writer>,
    /// Groups (the grouped layout) with tiles written since the group was last written out.
    unflushed: std::collections::HashSet<[i64; 2]>,
}

const EMPTY_BOX: [i64; 4] = [i64::MAX, i64::MAX, i64::MIN, i64::MIN];

/// Pulses between two checks of the open tiles' memory against the budget (besides the check
/// when a tile opens): a pulse adds at most a few columns, ~20 bytes a level each.
const BUDGET_CHECK_PULSES: u32 = 256;

impl TileSet {
    /// Tiles over `store`.
    pub fn new(store: ZarrStore, max_open: usize, close_after_s: f64) -> TileSet {
        let chunk_bytes = store.grid().chunk_voxels() * 20;
        TileSet {
            store,
            slots: Vec::new(),
            free: Vec::new(),
            open: HashMap::with_capacity(max_open + 1),
            max_open: max_open.max(1),
            budget_bytes: usize::MAX,
            since_budget_check: 0,
            rule: CloseRule::new(close_after_s),
            stats: TileStats {
                chunk_bytes,
                ..TileStats::default()
            },
            idle: Vec::with_capacity(max_open + 1),
            las: None,
            writer: None,
            unflushed: Default::default(),
        }
    }

    /// Bounds the memory of the open tiles (their written columns, `Chunk::used_bytes`) to
    /// `bytes`: when a tile opens (and every `BUDGET_CHECK_PULSES` pulses) and the open ones
    /// take more, the tiles deposited least recently are closed early until they fit (never
    /// one the current pulse touched).
    pub fn with_memory_budget(mut self, bytes: usize) -> Self {
        self.budget_bytes = bytes.max(1);
        self
    }

    /// Memory the open tiles' columns use, bytes (`TileData::used_bytes`).
    fn open_bytes(&self) -> usize {
        self.open
            .values()
            .map(|&s| self.slots[s].data.used_bytes())
            .sum()
    }

    /// Closes the tiles deposited least recently (not one the pulse `seq` touched) while the
    /// open tiles take more than the memory budget.
    fn keep_to_budget(&mut self, seq: u64) -> Result<(), StoreError> {
        if self.budget_bytes == usize::MAX {
            return Ok(());
        }
        let mut bytes = self.open_bytes();
        self.stats.peak_open_bytes = self.stats.peak_open_bytes.max(bytes);
        while bytes > self.budget_bytes
            && let Some(oldest) = self.least_recent(seq)
        {
            bytes -= self.slots[oldest].data.used_bytes();
            self.close_slot(oldest, seq)?;
            self.stats.closed_early += 1;
            self.stats.closed_over_budget += 1;
        }
        Ok(())
    }

    /// The open tile deposited least recently among those the pulse `seq` has not touched.
    fn least_recent(&self, seq: u64) -> Option<usize> {
        self.open
            .values()
            .copied()
            .filter(|s| self.slots[*s].last_seq < seq)
            .min_by(|a, b| {
                self.slots[*a]
                    .last_deposit_s
                    .total_cmp(&self.slots[*b].last_deposit_s)
            })
    }

    /// Writes closed tiles on a thread of its own, at most `queue` waiting (then closing waits
    /// for the writer: memory stays bounded by `max_open_tiles + queue + 1` tiles). The store
    /// ends up the same (each tile's commit is atomic and independent of the others); a tile
    /// reopened while its write is under way waits for it before it is read back.
    pub fn with_writer_thread(self, queue: usize) -> Self {
        self.with_writer_threads(queue, 1)
    }

    /// Writes closed tiles on `threads` threads, each tile always on the same one, at most
    /// `queue` waiting per thread (see [`with_writer_thread`](Self::with_writer_thread)).
    pub fn with_writer_threads(mut self, queue: usize, threads: usize) -> Self {
        let (done_tx, done_rx) = crossbeam_channel::unbounded::<WriteDone>();
        let mut jobs = Vec::new();
        let mut handles = Vec::new();
        for n in 0..threads.max(1) {
            let (jobs_tx, jobs_rx) = crossbeam_channel::bounded::<WriteJob>(queue.max(1));
            let mut store = self.store.tile_writer();
            let done_tx = done_tx.clone();
            let thread = std::thread::Builder::new()
                .name(format!("tile-writer-{n}"))
                .spawn(move || {
                    for job in jobs_rx.iter() {
                        if !write_job(&mut store, job, &done_tx) {
                            break;
                        }
                    }
                });
            match thread {
                Ok(t) => {
                    jobs.push(jobs_tx);
                    handles.push(t);
                }
                Err(e) => tracing::warn!("tile writer thread {n} not started ({e})"),
            }
        }
        if jobs.is_empty() {
            tracing::warn!("no tile writer thread; tiles are written inline");
            return self;
        }
        self.stats.writers = jobs.len();
        self.writer = Some(Writer {
            jobs,
            done: done_rx,
            threads: handles,
            in_flight: std::collections::HashSet::new(),
            grouped: self.store.group_of([0, 0]).is_some(),
            spare: Vec::new(),
        });
        self
    }

    /// Asks for `groups` (the grouped layout) to be written out: by their writer threads, or
    /// here.
    fn flush_groups(&mut self, groups: Vec<[i64; 2]>) -> Result<(), StoreError> {
        if groups.is_empty() {
            return Ok(());
        }
        for g in &groups {
            self.unflushed.remove(g);
        }
        let Some(w) = self.writer.as_ref() else {
            return self.store.flush_groups(groups);
        };
        let mut per: Vec<Vec<[i64; 2]>> = vec![Vec::new(); w.jobs.len()];
        for g in groups {
            per[w.of(g)].push(g);
        }
        for (n, gs) in per.into_iter().enumerate() {
            if !gs.is_empty() && w.jobs[n].send(WriteJob::Flush(gs)).is_err() {
                return Err(writer_stopped(self.store.root()));
            }
        }
        Ok(())
    }

    /// Writes out the groups the flight has left (the grouped layout): those with tiles written
    /// since they were last written, none of them open, none of them in `swath`.
    fn flush_left_groups(&mut self, swath: &[i64; 4]) -> Result<(), StoreError> {
        if self.unflushed.is_empty() {
            return Ok(());
        }
        let open: std::collections::HashSet<[i64; 2]> = self
            .open
            .keys()
            .filter_map(|t| self.store.group_of(*t))
            .collect();
        let mut left: Vec<[i64; 2]> = self
            .unflushed
            .iter()
            .copied()
            .filter(|g| {
                let Some(b) = self.store.group_tiles(*g) else {
                    return false;
                };
                let apart =
                    b[2] < swath[0] || b[0] > swath[2] || b[3] < swath[1] || b[1] > swath[3];
                apart && !open.contains(g)
            })
            .collect();
        left.sort_unstable();
        self.flush_groups(left)
    }

    /// Takes the writer's reports: commits recorded in the store, buffers kept for reuse. With
    /// `until`, waits until that tile is no longer being written; with `all`, until none is.
    fn collect_writes(&mut self, until: Option<[i64; 2]>, all: bool) -> Result<(), StoreError> {
        let Some(w) = self.writer.as_mut() else {
            return Ok(());
        };
        let mut result = Ok(());
        loop {
            let must_wait =
                all && !w.in_flight.is_empty() || until.is_some_and(|t| w.in_flight.contains(&t));
            let next = if must_wait {
                match w.done.recv() {
                    Ok(d) => d,
                    Err(_) => break,
                }
            } else {
                match w.done.try_recv() {
                    Ok(d) => d,
                    Err(_) => break,
                }
            };
            match next {
                WriteDone::Buffer(data) => w.spare.push(data),
                WriteDone::Committed(c) => {
                    w.in_flight.remove(&c.tile);
                    self.store
                        .note_committed(c.tile, c.watermark, c.chunks, c.cost);
                }
                WriteDone::Failed(e) => {
                    // Nothing more will be reported for the tiles in flight: stop waiting.
                    w.in_flight.clear();
                    if result.is_ok() {
                        result = Err(e);
                    }
                }
            }
        }
        result
    }

    /// Also writes every closed tile's occupied voxels as `DIR/tile_<tx>_<ty>.las` (rewritten,
    /// complete, when the tile closes again).
    pub fn with_las(mut self, dir: std::path::PathBuf, crs_wkt: Option<String>) -> Self {
        self.las = Some((dir, crs_wkt));
        self
    }

    /// The grid.
    pub fn grid(&self) -> &Grid {
        self.store.grid()
    }

    /// The store.
    pub fn store(&self) -> &ZarrStore {
        &self.store
    }

    /// The counters.
    pub fn stats(&self) -> &TileStats {
        &self.stats
    }

    /// The tiles open now (global numbering), in no particular order.
    pub fn open_tiles(&self) -> Vec<[i64; 2]> {
        self.open.keys().copied().collect()
    }

    /// Tiles open now.
    pub fn open_count(&self) -> usize {
        self.open.len()
    }

    /// The slot of `tile`, opening it (and closing another when full) if needed; `seq` is the
    /// pulse about to deposit, `now_s` its time. Returns the slot and the sequence number below
    /// which deposits are already in the tile.
    pub fn slot_for(
        &mut self,
        tile: [i64; 2],
        seq: u64,
        now_s: f64,
    ) -> Result<(usize, u64), StoreError> {
        if let Some(&s) = self.open.get(&tile) {
            self.slots[s].last_seq = seq;
            return Ok((s, self.slots[s].skip_below));
        }
        // The tile deposited least recently, among those the current pulse has not touched:
        // its watermark must not split a pulse, and the caller may hold the slots of this
        // pulse's tiles. When every open tile is this pulse's, the bounds give way.
        if self.open.len() >= self.max_open
            && let Some(oldest) = self.least_recent(seq)
        {
            self.close_slot(oldest, seq)?;
            self.stats.closed_early += 1;
        }
        self.keep_to_budget(seq)?;
        // A tile whose write is under way is read back only once it is committed (grouped: its
        // group written out first).
        let pending = self
            .writer
            .as_ref()
            .is_some_and(|w| w.grouped && w.in_flight.contains(&tile));
        if pending && let Some(g) = self.store.group_of(tile) {
            self.flush_groups(vec![g])?;
        }
        self.collect_writes(Some(tile), false)?;
        let s = match self.free.pop() {
            Some(s) => s,
            None => {
                self.slots.push(Slot {
                    tile,
                    data: TileData::for_grid(self.store.grid()),
                    last_deposit_s: now_s,
                    skip_below: 0,
                    last_seq: seq,
                });
                self.slots.len() - 1
            }
        };
        let slot = &mut self.slots[s];
        slot.tile = tile;
        slot.last_deposit_s = now_s;
        slot.skip_below = 0;
        slot.last_seq = seq;
        let reopened = self.store.read_tile(tile, &mut slot.data)?;
        if reopened {
            slot.skip_below = self.store.watermark(tile).unwrap_or(0);
            self.stats.merged += 1;
        }
        self.open.insert(tile, s);
        self.stats.opened += 1;
        self.stats.peak_open = self.stats.peak_open.max(self.open.len());
        Ok((s, self.slots[s].skip_below))
    }

    /// The accumulators of an open slot.
    #[inline]
    pub fn data(&mut self, slot: usize) -> &mut TileData {
        &mut self.slots[slot].data
    }

    /// Notes a deposit into `slot` at pulse time `now_s` (for closing and the swath).
    #[inline]
    pub fn touched(&mut self, slot: usize, now_s: f64) {
        let s = &mut self.slots[slot];
        s.last_deposit_s = now_s;
        self.rule.touched(s.tile);
    }

    fn close_slot(&mut self, s: usize, watermark: u64) -> Result<(), StoreError> {
        let slot = &self.slots[s];
        let tile = slot.tile;
        let w = watermark.max(slot.skip_below);
        let chunks: usize = self
            .open
            .values()
            .map(|s| self.slots[*s].data.present_count())
            .sum();
        self.stats.peak_chunks = self.stats.peak_chunks.max(chunks);
        self.stats.peak_open_bytes = self.stats.peak_open_bytes.max(self.open_bytes());
        if self.writer.is_none() {
            self.store.write_tile(tile, &slot.data, w)?;
        }
        if let Some((dir, wkt)) = &self.las {
            let path = dir.join(format!("tile_{}_{}.las", tile[0], tile[1]));
            tile_las(&path, wkt.as_deref(), self.store.grid(), tile, &slot.data).map_err(|e| {
                StoreError::Io {
                    path: path.display().to_string(),
                    source: std::io::Error::other(e.to_string()),
                }
            })?;
            self.stats.las_files += 1;
        }
        if self.writer.is_some() {
            self.collect_writes(None, false)?;
            let grid = self.store.grid();
            if let Some(wr) = self.writer.as_mut() {
                let fresh = match wr.spare.pop() {
                    Some(mut d) => {
                        d.clear();
                        d
                    }
                    None => TileData::for_grid(grid),
                };
                let data = std::mem::replace(&mut self.slots[s].data, fresh);
                wr.in_flight.insert(tile);
                let key = self.store.group_of(tile).unwrap_or(tile);
                let sent = wr.jobs.get(wr.of(key)).map(|j| {
                    j.send(WriteJob::Tile {
                        tile,
                        data,
                        watermark: w,
                    })
                });
                if !matches!(sent, Some(Ok(()))) {
                    return Err(writer_stopped(self.store.root()));
                }
            }
        }
        if let Some(g) = self.store.group_of(tile) {
            self.unflushed.insert(g);
        }
        self.open.remove(&tile);
        self.free.push(s);
        self.stats.closed += 1;
        Ok(())
    }

    /// Closes the tiles the flight has left, given the time of the pulse about to be processed
    /// (`seq`, everything before it deposited). Cheap when called per pulse: the open tiles are
    /// examined at most eight times per `close_after_s`.
    pub fn close_idle(&mut self, seq: u64, now_s: f64) -> Result<(), StoreError> {
        // Open tiles grow between openings: the memory budget is checked every
        // `BUDGET_CHECK_PULSES` pulses too (a sum over the open tiles' height chunks).
        self.since_budget_check += 1;
        if self.since_budget_check >= BUDGET_CHECK_PULSES {
            self.since_budget_check = 0;
            self.keep_to_budget(seq)?;
        }
        let Some(swath) = self.rule.due(now_s) else {
            return Ok(());
        };
        let mut idle = std::mem::take(&mut self.idle);
        idle.clear();
        for &s in self.open.values() {
            let slot = &self.slots[s];
            if self
                .rule
                .closes(&swath, slot.tile, slot.last_deposit_s, now_s)
            {
                idle.push(s);
            }
        }
        // Deterministic order (the store's content does not depend on it; its files' order does).
        idle.sort_unstable_by_key(|s| self.slots[*s].tile);
        let mut result = Ok(());
        for &s in &idle {
            if let Err(e) = self.close_slot(s, seq) {
                result = Err(e);
                break;
            }
        }
        self.idle = idle;
        result?;
        self.flush_left_groups(&swath)
    }

    /// Closes every open tile and fits the store's arrays to the tiles written (end of the
    /// run: nothing may be deposited afterwards); `next_seq` is one past the last pulse.
    pub fn close_all(&mut self, next_seq: u64) -> Result<(), StoreError> {
        let mut all: Vec<usize> = self.open.values().copied().collect();
        all.sort_by_key(|s| self.slots[*s].tile);
        for s in all {
            self.close_slot(s, next_seq)?;
        }
        let mut groups: Vec<[i64; 2]> = self.unflushed.iter().copied().collect();
        groups.sort_unstable();
        self.flush_groups(groups)?;
        self.collect_writes(None, true)?;
        self.store.fit()
    }

    /// Takes the store back (after `close_all`).
    pub fn into_store(self) -> ZarrStore {
        self.store
    }
}

/// The error of a tile writer thread that has stopped.
fn writer_stopped(root: &std::path::Path) -> StoreError {
    StoreError::Io {
        path: root.display().to_string(),
        source: std::io::Error::other("the tile writer thread has stopped"),
    }
}

/// Does one job on a writer thread's `store` and reports to `done`; false when nobody listens.
fn write_job(
    store: &mut ZarrStore,
    job: WriteJob,
    done: &crossbeam_channel::Sender<WriteDone>,
) -> bool {
    let r = match job {
        WriteJob::Tile {
            tile,
            data,
            watermark,
        } => {
            let r = store.write_tile(tile, &data, watermark);
            if done.send(WriteDone::Buffer(data)).is_err() {
                return false;
            }
            r.map(|(chunks, cost)| {
                // Ungrouped, the tile is durable now; grouped, when its group is written.
                if store.group_of(tile).is_none() {
                    store.note_written(Committed {
                        tile,
                        watermark,
                        chunks,
                        cost,
                    });
                }
            })
        }
        WriteJob::Flush(groups) => store.flush_groups(groups),
    };
    let mut reports: Vec<WriteDone> = store
        .take_committed()
        .into_iter()
        .map(WriteDone::Committed)
        .collect();
    if let Err(e) = r {
        reports.push(WriteDone::Failed(e));
    }
    reports.into_iter().all(|d| done.send(d).is_ok())
}

/// Writes the occupied voxels of a tile (at least one sample) as a LAS 1.4 point format 6 file:
/// a point at each voxel's centre (z as the grid measures it: absolute, or above the DEM), with
/// extra dimensions `mean` (intensity sum / samples), `maximum`, `samples` and `pulses`;
/// intensity is the mean scaled to 16 bits over the tile's largest mean.
pub fn tile_las(
    path: &std::path::Path,
    crs_wkt: Option<&str>,
    grid: &Grid,
    tile: [i64; 2],
    data: &TileData,
) -> Result<(), crate::format::las_points::LasFileError> {
    use crate::format::las_points::{PointSix, write_point_cloud};
    use crate::format::las_write::ExtraDim;
    let t = grid.tile_columns as usize;
    let tm = grid.tile_m();
    let west = grid.origin_m[0] + tile[0] as f64 * tm[0];
    let south = grid.origin_m[1] + tile[1] as f64 * tm[1];
    let v = grid.voxel_size_m;
    let q = grid.intensity_quantum;
    // (column, level, mean, max, samples, pulses) of every voxel holding a sample.
    let mut voxels = Vec::new();
    data.for_each_sampled(|col, k, v| {
        let mean = v.sum_q as f64 * q / v.samples as f64;
        voxels.push((col, k, mean, v.max, v.samples, v.pulses));
    });
    let top = voxels.iter().map(|x| x.2).fold(0.0f64, f64::max);
    let points = voxels.into_iter().map(move |(col, k, m, mx, n, p)| {
        let (j, i) = (col / t, col % t);
        let point = PointSix {
            xyz: [
                west + (i as f64 + 0.5) * v[0],
                south + (j as f64 + 0.5) * v[1],
                grid.z_bottom_m + (k as f64 + 0.5) * v[2],
            ],
            intensity: if top > 0.0 {
                (m.max(0.0) / top * 65535.0).round() as u16
            } else {
                0
            },
            ..PointSix::default()
        };
        (point, [m, f64::from(mx), f64::from(n), f64::from(p)])
    });
    let extra = [
        ExtraDim::f32("mean", "mean deposited intensity"),
        ExtraDim::f32("maximum", "largest deposited intensity"),
        ExtraDim::f32("samples", "bins deposited"),
        ExtraDim::f32("pulses", "pulses passed through"),
    ];
    write_point_cloud(path, crs_wkt, &extra, points)?;
    Ok(())
}
