//! Tiles grouped into shards (`[voxels] shard_tiles`): one file per array holds the height
//! chunks of `G × G` tiles over `K` height chunks, so that a sparse flight line, whose tiles
//! each hold a few pulses, writes a few large files instead of four per tile and height chunk.
//!
//! On disk (Zarr v3, nested `sharding_indexed`): the data arrays' chunk is `[K·H, G·T, G·T]`
//! voxels; it is a shard whose inner chunks are a tile's height chunk, `[H, T, T]`, each itself
//! the shard the per-tile layout writes (inner chunks of `[H, B, B]`, zstd, its own index), back
//! to back in C order `[z, y, x]` of their places, then the outer index: per place
//! `(offset, nbytes)` as little-endian `u64`, `2^64 − 1` twice where nothing is stored. A tile's
//! height chunk is therefore the same bytes in either layout, and a merge copies it without
//! decoding. Groups are counted from the grid's first tile and its bottom height chunk, and the
//! arrays' span is aligned to them, so that fitting the arrays moves whole files.
//!
//! **The journal** (`fwlidar_state/journal`) replaces the per-tile records: one line per batch
//! of shards written, `JSON<TAB>CRC-32C (hex)`, the JSON
//! `{"seq": S, "shards": [paths under the store], "tiles": [[tx, ty, watermark, [height chunks]], …]}`.
//! A batch's shards are written as `PATH.pending.S` and synced, its line is appended and synced
//! (the commit point), then the shards are renamed into place. Opening the store reads the
//! journal (the latest line naming a tile holds its watermark and height chunks), renames the
//! pending shards of committed batches whose renames were cut short, and deletes the pending
//! shards of batches never committed; a torn last line (a crash while appending) is cut off.
//! When a run ends the journal is rewritten as one line holding every tile, numbered 0 (batches
//! count from 1), so that a finished store's bytes do not depend on how many batches wrote it.

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use serde_json::{Value, json};

/// Tiles grouped into one shard file per array.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardGroup {
    /// Tiles along each side of a shard (`G`).
    pub tiles: u32,
    /// Height chunks of a shard (`K`).
    pub height_chunks: u32,
}

/// Columns along each side of a shard's inner chunk (of the tile's `T`; the largest divisor of
/// `T` not above this when 8 does not divide it). Chosen by measurement (docs/performance.md):
/// 8 × 8 columns × `H` levels is 16 KB of `u32`, large enough for zstd and small enough that a
/// sparse flight line's tile chunk encodes only the few blocks its pulses touched.
pub const INNER_COLUMNS: u32 = 8;

/// How a new store is laid out (a store reopened keeps its own layout).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayoutChoice {
    /// Tiles grouped into shard files (`[voxels] shard_tiles`), or a file per tile and height
    /// chunk.
    pub group: Option<ShardGroup>,
    /// Columns along each side of an inner chunk (its greatest common divisor with the tile's
    /// columns is taken).
    pub inner_columns: u32,
}

impl Default for LayoutChoice {
    fn default() -> Self {
        LayoutChoice {
            group: None,
            inner_columns: INNER_COLUMNS,
        }
    }
}

impl From<Option<ShardGroup>> for LayoutChoice {
    fn from(group: Option<ShardGroup>) -> Self {
        LayoutChoice {
            group,
            ..LayoutChoice::default()
        }
    }
}

/// A tile's height chunk inside its group: the group `[gx, gy]` (counted from the grid's first
/// tile), the group's height `gz` (counted from the bottom height chunk) and the place in the
/// shard (C order `[z, y, x]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Place {
    /// The group's columns `[gx, gy]`.
    pub group: [i64; 2],
    /// The group's height.
    pub gz: u32,
    /// Index of the tile's height chunk among the shard's `K·G·G` places.
    pub slot: usize,
}

impl ShardGroup {
    /// Places of a shard (entries of its index).
    pub fn slots(self) -> usize {
        self.tiles as usize * self.tiles as usize * self.height_chunks as usize
    }

    /// Where height chunk `kc` of `tile` lies, on a grid whose first tile is `tile_min`.
    pub fn place(self, tile_min: [i64; 2], tile: [i64; 2], kc: u32) -> Place {
        let g = self.tiles.max(1) as i64;
        let k = self.height_chunks.max(1);
        let (rx, ry) = (tile[0] - tile_min[0], tile[1] - tile_min[1]);
        let slot = ((kc % k) as usize * g as usize + ry.rem_euclid(g) as usize) * g as usize
            + rx.rem_euclid(g) as usize;
        Place {
            group: [rx.div_euclid(g), ry.div_euclid(g)],
            gz: kc / k,
            slot,
        }
    }

    /// The group `[gx, gy]` of `tile`.
    pub fn group_of(self, tile_min: [i64; 2], tile: [i64; 2]) -> [i64; 2] {
        self.place(tile_min, tile, 0).group
    }

    /// The tiles of group `g`: `[tx0, ty0, tx1, ty1]` inclusive.
    pub fn tiles_of(self, tile_min: [i64; 2], g: [i64; 2]) -> [i64; 4] {
        let n = self.tiles.max(1) as i64;
        let (x0, y0) = (tile_min[0] + g[0] * n, tile_min[1] + g[1] * n);
        [x0, y0, x0 + n - 1, y0 + n - 1]
    }
}

/// Reads the place `slot` of the shard at `path` (`slots` places, the index at the end) into
/// `out`: false when the file or the place holds nothing.
pub fn read_place(
    path: &Path,
    slots: usize,
    slot: usize,
    out: &mut Vec<u8>,
) -> Result<bool, String> {
    match open_indexed(path, slots)? {
        Some((f, data_len, index)) => read_indexed(&f, data_len, &index, slot, out),
        None => Ok(false),
    }
}

/// Reads place `slot` of an opened shard (`data_len` bytes of data, then `index`) into `out`:
/// false when the place holds nothing; an error when the index points outside the data.
fn read_indexed(
    f: &File,
    data_len: u64,
    index: &[u8],
    slot: usize,
    out: &mut Vec<u8>,
) -> Result<bool, String> {
    use std::os::unix::fs::FileExt;
    let Some(e) = index.get(slot * 16..slot * 16 + 16) else {
        return Err(format!(
            "no place {slot} in a shard of {} places",
            index.len() / 16
        ));
    };
    let (off, n) = entry(e);
    if off == u64::MAX && n == u64::MAX {
        return Ok(false);
    }
    if off.checked_add(n).is_none_or(|end| end > data_len) {
        return Err(format!(
            "shard index: place {slot} at {off} + {n} bytes lies outside the shard's {data_len} \
             bytes of data"
        ));
    }
    out.clear();
    out.resize(n as usize, 0);
    f.read_exact_at(out, off).map_err(|e| e.to_string())?;
    Ok(true)
}

/// Shard files of other stores kept open, with their index, while places are read from them
/// one after another (`fwlidar merge` reads every tile of its inputs' groups: opening the
/// file and reading its index entry per place took ~250 000 `openat`, `statx` and `close` and
/// ~500 000 `pread` for the sparse 7.2 km line's halves). Only for stores nothing writes while
/// they are read: a file renamed over after it was opened would be read as it was.
#[derive(Default)]
pub struct OpenShards {
    /// Per path: the file, its data's length and its index (`None`: no such file).
    files: std::collections::HashMap<std::path::PathBuf, Option<(File, u64, Vec<u8>)>>,
}

/// Shard files [`OpenShards`] keeps open at most (then it starts again).
const OPEN_SHARDS: usize = 256;

impl OpenShards {
    /// As [`read_place`], the file opened and its index read once.
    pub fn read_place(
        &mut self,
        path: &Path,
        slots: usize,
        slot: usize,
        out: &mut Vec<u8>,
    ) -> Result<bool, String> {
        if !self.files.contains_key(path) {
            if self.files.len() >= OPEN_SHARDS {
                self.files.clear();
            }
            let opened = open_indexed(path, slots)?;
            self.files.insert(path.to_path_buf(), opened);
        }
        match self.files.get(path) {
            Some(Some((f, data_len, index))) => read_indexed(f, *data_len, index, slot, out),
            _ => Ok(false),
        }
    }
}

/// The shard at `path` opened, with the length of its data and its index (`slots` entries);
/// `None` when there is no such file.
fn open_indexed(path: &Path, slots: usize) -> Result<Option<(File, u64, Vec<u8>)>, String> {
    use std::os::unix::fs::FileExt;
    let f = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e.to_string()),
    };
    let len = f.metadata().map_err(|e| e.to_string())?.len();
    let index_len = slots as u64 * 16;
    let Some(data_len) = len.checked_sub(index_len) else {
        return Err(format!(
            "shard of {len} bytes is shorter than its index ({index_len} bytes)"
        ));
    };
    let mut index = vec![0u8; slots * 16];
    f.read_exact_at(&mut index, data_len)
        .map_err(|e| e.to_string())?;
    Ok(Some((f, data_len, index)))
}

fn entry(e: &[u8]) -> (u64, u64) {
    let word = |i: usize| u64::from_le_bytes(e[i..i + 8].try_into().unwrap_or([0xff; 8]));
    (word(0), word(8))
}

/// The places of a shard's bytes `shard` (`slots` places): per place its byte range, `None`
/// where nothing is stored; an error saying what is wrong.
pub fn places(shard: &[u8], slots: usize) -> Result<Vec<Option<std::ops::Range<usize>>>, String> {
    let Some(data_len) = shard.len().checked_sub(slots * 16) else {
        return Err(format!(
            "shard of {} bytes is shorter than its index ({} bytes)",
            shard.len(),
            slots * 16
        ));
    };
    shard[data_len..]
        .chunks_exact(16)
        .enumerate()
        .map(|(slot, e)| {
            let (off, n) = entry(e);
            if off == u64::MAX && n == u64::MAX {
                return Ok(None);
            }
            usize::try_from(off)
                .ok()
                .zip(usize::try_from(n).ok())
                .and_then(|(o, n)| Some(o..o.checked_add(n)?))
                .filter(|r| r.end <= data_len)
                .map(Some)
                .ok_or_else(|| {
                    format!(
                        "shard index: place {slot} at {off} + {n} bytes lies outside the \
                         shard's {data_len} bytes of data"
                    )
                })
        })
        .collect()
}

/// Assembles a shard of `slots` places into `out` (cleared): each place's bytes from `new`,
/// else from the shard `old` holds there, else nothing; then the index. The bytes depend only on
/// what each place holds, not on the order of the writes.
pub fn assemble<'a>(
    old: Option<&[u8]>,
    slots: usize,
    new: impl Fn(usize) -> Option<&'a [u8]>,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    let old_places = match old {
        Some(b) => places(b, slots)?,
        None => vec![None; slots],
    };
    out.clear();
    let mut index = Vec::with_capacity(slots);
    for (slot, was) in old_places.into_iter().enumerate() {
        let bytes = new(slot).or_else(|| Some(&old?[was?]));
        match bytes {
            Some(b) => {
                index.push((out.len() as u64, b.len() as u64));
                out.extend_from_slice(b);
            }
            None => index.push((u64::MAX, u64::MAX)),
        }
    }
    for (o, n) in index {
        out.extend_from_slice(&o.to_le_bytes());
        out.extend_from_slice(&n.to_le_bytes());
    }
    Ok(())
}

/// A tile as the journal records it: its watermark and height chunks.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JournalTile {
    /// The tile `[tx, ty]`.
    pub tile: [i64; 2],
    /// First pulse sequence number not in the tile.
    pub watermark: u64,
    /// Height chunks it holds, ascending.
    pub chunks: Vec<u32>,
}

/// One committed batch.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Batch {
    /// Its number (pending shards are named `PATH.pending.SEQ`).
    pub seq: u64,
    /// The shards it wrote, paths under the store with `/`.
    pub shards: Vec<String>,
    /// The tiles it holds.
    pub tiles: Vec<JournalTile>,
}

impl Batch {
    /// The journal line: JSON, a tab, its CRC-32C in hex, a newline.
    pub fn line(&self) -> Vec<u8> {
        let tiles: Vec<Value> = self
            .tiles
            .iter()
            .map(|t| json!([t.tile[0], t.tile[1], t.watermark, t.chunks]))
            .collect();
        let text = json!({"seq": self.seq, "shards": self.shards, "tiles": tiles}).to_string();
        format!("{text}\t{:08x}\n", crc32c::crc32c(text.as_bytes())).into_bytes()
    }

    fn parse(line: &str) -> Result<Batch, String> {
        let (text, crc) = line.rsplit_once('\t').ok_or("no checksum")?;
        let crc = u32::from_str_radix(crc, 16).map_err(|_| "the checksum is not hex")?;
        if crc32c::crc32c(text.as_bytes()) != crc {
            return Err("the checksum does not match".into());
        }
        let v: Value = serde_json::from_str(text).map_err(|e| format!("not JSON: {e}"))?;
        let seq = v.get("seq").and_then(Value::as_u64).ok_or("no `seq`")?;
        let shards = v
            .get("shards")
            .and_then(Value::as_array)
            .ok_or("no `shards`")?
            .iter()
            .map(|s| s.as_str().map(str::to_string))
            .collect::<Option<Vec<_>>>()
            .ok_or("`shards`: not a list of paths")?;
        let tiles = v
            .get("tiles")
            .and_then(Value::as_array)
            .ok_or("no `tiles`")?
            .iter()
            .map(|t| {
                let a = t.as_array()?;
                let chunks = a
                    .get(3)?
                    .as_array()?
                    .iter()
                    .map(|k| k.as_u64().and_then(|k| u32::try_from(k).ok()))
                    .collect::<Option<Vec<u32>>>()?;
                Some(JournalTile {
                    tile: [a.first()?.as_i64()?, a.get(1)?.as_i64()?],
                    watermark: a.get(2)?.as_u64()?,
                    chunks,
                })
            })
            .collect::<Option<Vec<_>>>()
            .ok_or("`tiles`: not a list of [tx, ty, watermark, [height chunks]]")?;
        Ok(Batch { seq, shards, tiles })
    }
}

/// The journal of a store: appended to by every writer handle of the store (under one lock),
/// batches numbered from one counter.
#[derive(Clone, Debug)]
pub struct Journal {
    path: PathBuf,
    lock: Arc<Mutex<()>>,
    next_seq: Arc<AtomicU64>,
}

impl Journal {
    /// The journal at `path`, numbering batches from `next_seq`.
    pub fn new(path: PathBuf, next_seq: u64) -> Journal {
        Journal {
            path,
            lock: Arc::new(Mutex::new(())),
            next_seq: Arc::new(AtomicU64::new(next_seq)),
        }
    }

    /// Its file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// A number for the next batch.
    pub fn next_seq(&self) -> u64 {
        self.next_seq.fetch_add(1, Ordering::Relaxed)
    }

    /// Appends `batch` (synced when `durable`): the commit point of its shards.
    pub fn append(&self, batch: &Batch, durable: bool) -> std::io::Result<()> {
        let _held = self.lock.lock().unwrap_or_else(|p| p.into_inner());
        let mut f = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)?;
        f.write_all(&batch.line())?;
        if durable {
            f.sync_data()?;
        }
        Ok(())
    }

    /// The committed batches of the journal at `path` (none when it does not exist) and, when
    /// its last line is torn, the length of the part before it (to cut the file to); an error
    /// naming the line when one before the last is damaged.
    pub fn read(path: &Path) -> Result<(Vec<Batch>, Option<u64>), String> {
        let text = match std::fs::read(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((Vec::new(), None)),
            Err(e) => return Err(e.to_string()),
        };
        let mut batches = Vec::new();
        let mut at = 0usize;
        let mut n = 0;
        while at < text.len() {
            n += 1;
            let end = text[at..].iter().position(|b| *b == b'\n').map(|p| at + p);
            let parsed = end
                .ok_or_else(|| "no end of line".to_string())
                .and_then(|e| {
                    std::str::from_utf8(&text[at..e])
                        .map_err(|_| "not UTF-8".to_string())
                        .and_then(Batch::parse)
                });
            match parsed {
                Ok(b) => batches.push(b),
                // The last line without its end, torn by a crash while it was appended: never
                // committed. A complete line that does not check is damage, not a crash.
                Err(_) if end.is_none() => {
                    return Ok((batches, Some(at as u64)));
                }
                Err(what) => return Err(format!("line {n}: {what}")),
            }
            at = end.map_or(text.len(), |e| e + 1);
        }
        Ok((batches, None))
    }
}

/// The latest record of every tile in `batches`, in journal order.
pub fn latest_tiles(batches: &[Batch]) -> BTreeMap<[i64; 2], (u64, Vec<u32>)> {
    let mut out = BTreeMap::new();
    for b in batches {
        for t in &b.tiles {
            out.insert(t.tile, (t.watermark, t.chunks.clone()));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn places_count_in_c_order_from_the_grids_first_tile() {
        let g = ShardGroup {
            tiles: 4,
            height_chunks: 2,
        };
        let p = g.place([-10, 5], [-10, 5], 0);
        assert_eq!((p.group, p.gz, p.slot), ([0, 0], 0, 0));
        let p = g.place([-10, 5], [-5, 7], 3);
        // rx = 5 -> group 1, x 1; ry = 2 -> group 0, y 2; kc 3 -> gz 1, z 1.
        assert_eq!((p.group, p.gz, p.slot), ([1, 0], 1, (4 + 2) * 4 + 1));
        assert_eq!(g.tiles_of([-10, 5], [1, 0]), [-6, 5, -3, 8]);
        assert_eq!(g.slots(), 32);
    }

    #[test]
    fn a_shard_keeps_old_places_takes_new_ones_and_reads_back_by_place() {
        let mut a = Vec::new();
        assemble(None, 4, |s| (s == 1).then_some(&b"one"[..]), &mut a).unwrap();
        let mut b = Vec::new();
        assemble(Some(&a), 4, |s| (s == 3).then_some(&b"three"[..]), &mut b).unwrap();
        let p = places(&b, 4).unwrap();
        assert_eq!(&b[p[1].clone().unwrap()], b"one");
        assert_eq!(&b[p[3].clone().unwrap()], b"three");
        assert!(p[0].is_none() && p[2].is_none());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s");
        std::fs::write(&path, &b).unwrap();
        let mut out = Vec::new();
        assert!(read_place(&path, 4, 3, &mut out).unwrap());
        assert_eq!(out, b"three");
        assert!(!read_place(&path, 4, 0, &mut out).unwrap());
        assert!(!read_place(&dir.path().join("none"), 4, 0, &mut out).unwrap());
        // A damaged index is an error, not a panic.
        let mut bad = b.clone();
        let n = bad.len();
        bad[n - 16] = 0x70;
        assert!(places(&bad, 4).is_err());
        assert!(places(&bad[..10], 4).is_err());
    }

    #[test]
    fn open_shards_read_every_place_as_a_fresh_open_does_and_refuse_a_damaged_index() {
        let mut shard = Vec::new();
        let bodies: Vec<Vec<u8>> = (0..40u8).map(|s| vec![s; s as usize * 3]).collect();
        assemble(
            None,
            40,
            |s| (s % 3 != 0).then_some(&bodies[s][..]),
            &mut shard,
        )
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let mut open = OpenShards::default();
        // More files than are kept open: the cache starts again and still reads right.
        let paths: Vec<_> = (0..OPEN_SHARDS + 3)
            .map(|i| {
                let p = dir.path().join(format!("s{i}"));
                std::fs::write(&p, &shard).unwrap();
                p
            })
            .collect();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for round in 0..2 {
            for (i, p) in paths.iter().enumerate() {
                let slot = (i * 7 + round) % 40;
                let fresh = read_place(p, 40, slot, &mut a).unwrap();
                let kept = open.read_place(p, 40, slot, &mut b).unwrap();
                assert_eq!(fresh, kept, "{i} {slot}");
                assert_eq!(fresh, slot % 3 != 0);
                if fresh {
                    assert_eq!(a, b);
                    assert_eq!(b, bodies[slot]);
                }
            }
        }
        assert!(
            !open
                .read_place(&dir.path().join("none"), 40, 1, &mut b)
                .unwrap()
        );
        let bad = dir.path().join("bad");
        let mut damaged = shard.clone();
        let n = damaged.len();
        damaged[n - 40 * 16 + 16 + 15] = 0x70; // the high byte of place 1's length
        std::fs::write(&bad, &damaged).unwrap();
        assert!(open.read_place(&bad, 40, 1, &mut b).is_err());
        assert!(open.read_place(&bad, 40, 40, &mut b).is_err());
        std::fs::write(dir.path().join("short"), [0u8; 10]).unwrap();
        assert!(
            open.read_place(&dir.path().join("short"), 40, 0, &mut b)
                .is_err()
        );
    }

    #[test]
    fn the_journal_keeps_committed_lines_and_cuts_a_torn_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("journal");
        let j = Journal::new(path.clone(), 7);
        let b = |seq| Batch {
            seq,
            shards: vec!["sample_count/c/0/0/0".into()],
            tiles: vec![JournalTile {
                tile: [-3, 4],
                watermark: seq * 10,
                chunks: vec![1, 2],
            }],
        };
        j.append(&b(j.next_seq()), true).unwrap();
        j.append(&b(j.next_seq()), false).unwrap();
        let (got, torn) = Journal::read(&path).unwrap();
        assert_eq!(got, vec![b(7), b(8)]);
        assert_eq!(torn, None);
        assert_eq!(latest_tiles(&got)[&[-3, 4]].0, 80);
        let good = std::fs::metadata(&path).unwrap().len();
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(&b(9).line()[..20]).unwrap();
        let (got, torn) = Journal::read(&path).unwrap();
        assert_eq!(got.len(), 2);
        assert_eq!(torn, Some(good));
        // A damaged line before the last is an error naming it.
        let mut text = std::fs::read(&path).unwrap();
        text[3] ^= 1;
        std::fs::write(&path, &text).unwrap();
        assert!(Journal::read(&path).unwrap_err().starts_with("line 1"));
    }
}
