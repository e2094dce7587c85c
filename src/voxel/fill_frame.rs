//! A zstd frame written directly for an inner chunk that is mostly fill value.
//!
//! A sparse flight line leaves most inner chunks with one or a few written columns of 64: the
//! rest is the array's fill value. Through the zstd library each such chunk cost its whole
//! raw length (16–32 KiB arranged, hashed and matched) plus an entropy table built for a few
//! dozen sequences: ~2 µs a chunk, a third of the sparse 7.2 km line's CPU. Here the frame is
//! made from what the chunk holds: runs of equal values (a fill column is one run) become a
//! value stored as a literal and a match one value back; the other values are literals. The
//! result is a standard zstd frame (RFC 8878: one compressed block, raw literals, sequences
//! coded with the predefined distributions), which every zstd reader decodes — zarr-python's
//! and xarray's included; the tests decode it with the zstd library.
//!
//! Formulas from RFC 8878 (§3.1.1: frame and block headers, literals section, sequences
//! section, literal/match length and offset codes, the predefined distributions; §4.1: FSE
//! table construction), the encoder being the inverse of the decoder the RFC specifies.

use std::sync::OnceLock;

/// The zstd frame's magic number.
const MAGIC: u32 = 0xFD2F_B528;

/// Largest content of one zstd block (and so of a frame written here), bytes.
pub const MAX_CONTENT: usize = 128 * 1024;

/// Literal length codes: baseline and extra bits (RFC 8878 §3.1.1.3.2.1.1).
const LL_BASE: [u32; 36] = [
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 18, 20, 22, 24, 28, 32, 40, 48, 64,
    128, 256, 512, 1024, 2048, 4096, 8192, 16384, 32768, 65536,
];
const LL_BITS: [u32; 36] = [
    0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 3, 3, 4, 6, 7, 8, 9, 10, 11,
    12, 13, 14, 15, 16,
];
/// Match length codes: baseline and extra bits.
const ML_BASE: [u32; 53] = [
    3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27,
    28, 29, 30, 31, 32, 33, 34, 35, 37, 39, 41, 43, 47, 51, 59, 67, 83, 99, 131, 259, 515, 1027,
    2051, 4099, 8195, 16387, 32771, 65539,
];
const ML_BITS: [u32; 53] = [
    0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
    1, 1, 1, 1, 2, 2, 3, 3, 4, 4, 5, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16,
];
/// The predefined distributions (RFC 8878 §3.1.1.3.2.2) of literal and match length codes,
/// both of accuracy log 6 (offsets are written in RLE mode, no distribution).
const LL_NORM: [i16; 36] = [
    4, 3, 2, 2, 2, 2, 2, 2, 2, 2, 2, 2, 2, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2, 2, 3, 2, 1, 1, 1, 1, 1,
    -1, -1, -1, -1,
];
const ML_NORM: [i16; 53] = [
    1, 4, 3, 2, 2, 2, 2, 2, 2, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1,
    1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, -1, -1, -1, -1, -1, -1, -1,
];

/// An FSE (tANS) encoding table for one distribution.
struct FseTable {
    /// Accuracy log: the table has `2^log` states.
    log: u32,
    /// The encoder's next state (`2^log + decoder state`), by symbol rank.
    next: Vec<u16>,
    /// Per symbol: (`delta_find`, `delta_bits`): where its states start in `next` (less its
    /// count) and the bias that gives the bits a state sheds when the symbol is encoded.
    symbol: Vec<(i32, u32)>,
    /// Per symbol: the first of its states (an initial state for it).
    first: Vec<u16>,
}

impl FseTable {
    /// The table of a normalized distribution (`-1`: a "less than one" probability, one
    /// state), by the RFC's spread of symbols over states.
    fn new(norm: &[i16], log: u32) -> Self {
        let size = 1usize << log;
        let mask = size - 1;
        let mut spread = vec![0u8; size];
        let mut high = size - 1;
        for (s, &n) in norm.iter().enumerate() {
            if n == -1 {
                spread[high] = s as u8;
                high = high.saturating_sub(1);
            }
        }
        let step = (size >> 1) + (size >> 3) + 3;
        let mut pos = 0usize;
        for (s, &n) in norm.iter().enumerate() {
            for _ in 0..n.max(0) {
                spread[pos] = s as u8;
                pos = (pos + step) & mask;
                while pos > high {
                    pos = (pos + step) & mask;
                }
            }
        }
        let count = |n: i16| if n == -1 { 1 } else { n.max(0) as usize };
        let mut start = Vec::with_capacity(norm.len());
        let mut total = 0usize;
        for &n in norm {
            start.push(total);
            total += count(n);
        }
        let mut fill = start.clone();
        let mut next = vec![0u16; size];
        for (u, &s) in spread.iter().enumerate() {
            next[fill[s as usize]] = (size + u) as u16;
            fill[s as usize] += 1;
        }
        let symbol = norm
            .iter()
            .zip(&start)
            .map(|(&n, &at)| {
                let n = count(n) as u32;
                if n == 0 {
                    (0, ((log + 1) << 16) - size as u32)
                } else {
                    // A symbol of n states sheds at most `log − ⌊log2(n − 1)⌋` bits (n > 1).
                    let max_out = if n == 1 {
                        log
                    } else {
                        log - (31 - (n - 1).leading_zeros())
                    };
                    ((at as i32) - n as i32, (max_out << 16) - (n << max_out))
                }
            })
            .collect();
        let first = start
            .iter()
            .map(|&at| next.get(at).copied().unwrap_or(0))
            .collect();
        FseTable {
            log,
            next,
            symbol,
            first,
        }
    }

    /// Encodes symbol `s` from `state`: its bits go to `bits`, the state moves on.
    #[inline]
    fn encode(&self, state: &mut u32, s: usize, bits: &mut BitWriter<'_>) {
        let (find, delta) = self.symbol[s];
        let nb = (*state + delta) >> 16;
        bits.add(u64::from(*state), nb);
        *state = u32::from(self.next[((*state >> nb) as i32 + find) as usize]);
    }
}

/// The predefined tables of literal and match lengths, built once.
fn tables() -> &'static [FseTable; 2] {
    static T: OnceLock<[FseTable; 2]> = OnceLock::new();
    T.get_or_init(|| [FseTable::new(&LL_NORM, 6), FseTable::new(&ML_NORM, 6)])
}

/// Bits written forwards, least significant first (the reader goes backwards).
struct BitWriter<'a> {
    out: &'a mut Vec<u8>,
    acc: u64,
    n: u32,
}

impl BitWriter<'_> {
    /// Appends the low `n` bits of `v` (`n` ≤ 32).
    #[inline]
    fn add(&mut self, v: u64, n: u32) {
        self.acc |= (v & ((1u64 << n) - 1)) << self.n;
        self.n += n;
        if self.n >= 32 {
            self.out.extend_from_slice(&(self.acc as u32).to_le_bytes());
            self.acc >>= 32;
            self.n -= 32;
        }
    }

    /// The end mark (a 1 bit) and the last byte's padding.
    fn close(mut self) {
        self.add(1, 1);
        while self.n > 0 {
            self.out.push(self.acc as u8);
            self.acc >>= 8;
            self.n = self.n.saturating_sub(8);
        }
    }
}

/// The code of a length: the last code whose baseline is not above it.
fn code_of(base: &[u32], v: u32) -> usize {
    base.partition_point(|b| *b <= v) - 1
}

/// A frame being assembled from values of 4 to 8 bytes. One offset serves every match: one
/// value back. A byte equal to the byte one value before it extends the current match (a run
/// of equal values, a fill column, the zero high bytes of small counts and sums); a match of
/// fewer than 3 bytes (zstd's least) goes back to the literals.
#[derive(Default)]
pub struct FillFrame {
    /// Bytes of a value.
    width: usize,
    /// The last value appended (the bytes one value back, little endian), once there is one.
    prev: u64,
    have_prev: bool,
    /// Bytes of the match under way (each equal to the byte one value before it).
    matched: u32,
    /// Literal bytes, and those not yet followed by a match.
    literals: Vec<u8>,
    pending: u32,
    /// (literal bytes, match bytes) per sequence.
    sequences: Vec<(u32, u32)>,
    /// Bytes of content so far.
    content: usize,
}

impl FillFrame {
    /// Starts a frame of values of `width` bytes (4 or 8).
    pub fn begin(&mut self, width: usize) {
        debug_assert!((4..=8).contains(&width));
        self.width = width;
        self.have_prev = false;
        self.matched = 0;
        self.literals.clear();
        self.pending = 0;
        self.sequences.clear();
        self.content = 0;
    }

    /// Appends `count` copies of the value `v` (`N` = the frame's width).
    #[inline]
    pub fn push_run<const N: usize>(&mut self, v: [u8; N], count: usize) {
        if count == 0 {
            return;
        }
        self.push(v);
        let rest = (count - 1) * N;
        self.matched += rest as u32;
        self.content += rest;
    }

    /// Appends one value (`N` = the frame's width).
    #[inline]
    pub fn push<const N: usize>(&mut self, v: [u8; N]) {
        debug_assert_eq!(N, self.width);
        let mut b = [0u8; 8];
        b[..N].copy_from_slice(&v);
        let x = u64::from_le_bytes(b);
        self.content += N;
        if !self.have_prev {
            self.literals.extend_from_slice(&v);
            self.pending += N as u32;
            self.prev = x;
            self.have_prev = true;
            return;
        }
        let d = x ^ self.prev;
        if d == 0 {
            self.matched += N as u32;
            return;
        }
        // Bit i: byte i equals the byte one value back.
        let mut eq = 0u32;
        for i in 0..N {
            eq |= u32::from((d >> (8 * i)) as u8 == 0) << i;
        }
        let mut at = 0;
        while at < N {
            let ahead = eq >> at;
            if ahead & 1 == 1 {
                let r = ((!ahead).trailing_zeros() as usize).min(N - at);
                self.matched += r as u32;
                at += r;
            } else {
                let r = (ahead.trailing_zeros() as usize).min(N - at);
                self.end_match(&v, at);
                self.literals.extend_from_slice(&v[at..at + r]);
                self.pending += r as u32;
                at += r;
            }
        }
        self.prev = x;
    }

    /// Ends the match under way before byte `i` of the value `v` being appended: a sequence,
    /// or (under 3 bytes) its bytes back to the literals — the last bytes before byte `i`,
    /// in `v` or at the end of the previous value.
    fn end_match(&mut self, v: &[u8], i: usize) {
        let m = self.matched as usize;
        if m >= 3 {
            self.sequences.push((self.pending, m as u32));
            self.pending = 0;
        } else if m > 0 {
            let w = self.width;
            let prev = self.prev.to_le_bytes();
            for k in i as isize - m as isize..i as isize {
                let byte = if k < 0 {
                    prev[(w as isize + k) as usize]
                } else {
                    v[k as usize]
                };
                self.literals.push(byte);
            }
            self.pending += m as u32;
        }
        self.matched = 0;
    }

    /// Writes the frame to `out` (cleared). `false` (and `out` to be ignored) when this frame
    /// cannot hold the content (more than [`MAX_CONTENT`] bytes) or would not be smaller than
    /// it: the caller compresses the arranged bytes instead.
    pub fn finish(&mut self, out: &mut Vec<u8>) -> bool {
        self.end_match(&[], 0);
        out.clear();
        if self.content > MAX_CONTENT {
            return false;
        }
        out.extend_from_slice(&MAGIC.to_le_bytes());
        // Frame header: content size in 4 bytes, single segment, no checksum, no dictionary.
        out.push(0b1010_0000);
        out.extend_from_slice(&(self.content as u32).to_le_bytes());
        let block_at = out.len();
        out.extend_from_slice(&[0; 3]);
        self.literals_section(out);
        self.sequences_section(out);
        let size = out.len() - block_at - 3;
        if size >= self.content {
            return false;
        }
        // Last block, compressed (type 2), its size.
        let header = 1 | (2 << 1) | ((size as u32) << 3);
        out[block_at..block_at + 3].copy_from_slice(&header.to_le_bytes()[..3]);
        true
    }

    /// Raw literals with their size header.
    fn literals_section(&self, out: &mut Vec<u8>) {
        let n = self.literals.len() as u32;
        if n < 32 {
            out.push((n << 3) as u8);
        } else if n < 4096 {
            out.extend_from_slice(&((n << 4) | 0b0100).to_le_bytes()[..2]);
        } else {
            out.extend_from_slice(&((n << 4) | 0b1100).to_le_bytes()[..3]);
        }
        out.extend_from_slice(&self.literals);
    }

    /// The sequences: count, modes (all predefined), then the bitstream, written last
    /// sequence first.
    fn sequences_section(&self, out: &mut Vec<u8>) {
        let n = self.sequences.len();
        if n < 128 {
            out.push(n as u8);
        } else if n < 0x7F00 {
            out.push(((n >> 8) + 128) as u8);
            out.push(n as u8);
        } else {
            out.push(0xFF);
            out.extend_from_slice(&((n - 0x7F00) as u16).to_le_bytes());
        }
        if n == 0 {
            return;
        }
        let [ll_t, ml_t] = tables();
        let offset = self.width as u32 + 3;
        let of_code = (31 - offset.leading_zeros()) as usize;
        // Literal and match lengths by the predefined distributions; offsets all one code
        // (RLE mode: the code once, no state bits).
        out.push(0b0001_0000);
        out.push(of_code as u8);
        let codes = |(lit, mat): (u32, u32)| {
            let ll = code_of(&LL_BASE, lit);
            let ml = code_of(&ML_BASE, mat);
            (ll, ml)
        };
        let mut bits = BitWriter { out, acc: 0, n: 0 };
        let extras = |bits: &mut BitWriter<'_>, (lit, mat): (u32, u32), ll: usize, ml: usize| {
            bits.add(u64::from(lit - LL_BASE[ll]), LL_BITS[ll]);
            bits.add(u64::from(mat - ML_BASE[ml]), ML_BITS[ml]);
            bits.add(u64::from(offset), of_code as u32);
        };
        let last = self.sequences[n - 1];
        let (ll, ml) = codes(last);
        let mut ll_s = u32::from(ll_t.first[ll]);
        let mut ml_s = u32::from(ml_t.first[ml]);
        extras(&mut bits, last, ll, ml);
        for &seq in self.sequences[..n - 1].iter().rev() {
            let (ll, ml) = codes(seq);
            ml_t.encode(&mut ml_s, ml, &mut bits);
            ll_t.encode(&mut ll_s, ll, &mut bits);
            extras(&mut bits, seq, ll, ml);
        }
        bits.add(u64::from(ml_s), ml_t.log);
        bits.add(u64::from(ll_s), ll_t.log);
        bits.close();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Builds the frame of `values` (little-endian `width`-byte values) through `FillFrame`,
    /// value by value, and decodes it with the zstd library.
    fn round_trip(values: &[u64], width: usize) -> (Vec<u8>, Vec<u8>) {
        let raw: Vec<u8> = values
            .iter()
            .flat_map(|v| v.to_le_bytes()[..width].to_vec())
            .collect();
        let mut f = FillFrame::default();
        f.begin(width);
        for v in values {
            push_width(&mut f, *v, width);
        }
        let mut out = Vec::new();
        assert!(f.finish(&mut out), "frame not smaller than its content");
        let back = zstd::bulk::decompress(&out, raw.len() + 1).expect("zstd decodes the frame");
        (raw, back)
    }

    /// Appends the low `width` (4 or 8) bytes of `v`.
    fn push_width(f: &mut FillFrame, v: u64, width: usize) {
        if width == 4 {
            f.push((v as u32).to_le_bytes());
        } else {
            f.push(v.to_le_bytes());
        }
    }

    /// A small deterministic generator (xorshift).
    fn next(s: &mut u64) -> u64 {
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        *s
    }

    #[test]
    fn a_mostly_fill_block_decodes_to_its_values() {
        // 64 columns × 64 levels, column order; columns 3 and 40 hold data.
        for width in [4, 8] {
            let fill = if width == 4 { 0x7FC0_0000u64 } else { 0 };
            let mut v = vec![fill; 4096];
            for k in 0..64 {
                v[3 * 64 + k] = 1000 + k as u64 % 7;
                v[40 * 64 + k] = if k % 3 == 0 { fill } else { 5 };
            }
            let (raw, back) = round_trip(&v, width);
            assert_eq!(raw, back);
        }
    }

    #[test]
    fn random_runs_of_every_length_decode_to_their_values() {
        // Runs of 1 to 70 000 values (long literal and match lengths use every code), few
        // or many distinct values, both widths.
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        let mut framed = 0;
        for case in 0..400 {
            let width = if case % 2 == 0 { 4 } else { 8 };
            let limit = MAX_CONTENT / width;
            let mut v = Vec::new();
            while v.len() < limit {
                let r = next(&mut s);
                let len = match r % 4 {
                    0 => 1,
                    1 => 1 + (r >> 8) as usize % 8,
                    2 => 1 + (r >> 8) as usize % 300,
                    _ => 1 + (r >> 8) as usize % (limit / 2),
                };
                let value = if (r >> 40).is_multiple_of(3) {
                    0
                } else {
                    next(&mut s) % 5
                };
                let len = len.min(limit - v.len());
                v.extend(std::iter::repeat_n(value, len));
                if case % 7 == 0 && v.len() > 20 {
                    break;
                }
            }
            let mut f = FillFrame::default();
            f.begin(width);
            let mut at = 0;
            while at < v.len() {
                let n = v[at..].iter().take_while(|x| **x == v[at]).count();
                if width == 4 {
                    f.push_run((v[at] as u32).to_le_bytes(), n);
                } else {
                    f.push_run(v[at].to_le_bytes(), n);
                }
                at += n;
            }
            let mut out = Vec::new();
            let raw: Vec<u8> = v
                .iter()
                .flat_map(|x| x.to_le_bytes()[..width].to_vec())
                .collect();
            if f.finish(&mut out) {
                let back = zstd::bulk::decompress(&out, raw.len() + 1).expect("decodes");
                assert_eq!(back, raw, "case {case}");
                assert!(out.len() < raw.len());
                framed += 1;
            }
        }
        assert!(framed > 350, "only {framed} of 400 framed");
    }

    #[test]
    fn values_sharing_some_bytes_decode_and_compress() {
        // Small counts and sums (zero high bytes), values one byte apart, a value whose
        // bytes partly repeat the previous one's at every position: matches of 1 to 7 bytes
        // inside and across values.
        let mut s = 7u64;
        for width in [4, 8] {
            // Half of the block fill (zero), so that the frame is smaller than its content.
            let v: Vec<u64> = (0..8192)
                .map(|k| match if k % 128 < 64 { k % 5 } else { 5 } {
                    0 => next(&mut s) % 300,
                    1 => 0x0101_0101_0101_0101 ^ (next(&mut s) % 3) << (8 * (k % 8)),
                    2 => next(&mut s) % 3,
                    3 => next(&mut s) % 100_000,
                    4 => k as u64 * 0x10001,
                    _ => 0,
                })
                .collect();
            let (raw, back) = round_trip(&v, width);
            assert_eq!(raw, back);
        }
        let counts: Vec<u64> = (0..4096).map(|k| (k * 7919 % 13) as u64).collect();
        let mut f = FillFrame::default();
        f.begin(8);
        for c in &counts {
            f.push(c.to_le_bytes());
        }
        let mut out = Vec::new();
        assert!(f.finish(&mut out));
        assert!(
            out.len() < 4096 * 4,
            "zero high bytes matched: {} bytes",
            out.len()
        );
        let raw: Vec<u8> = counts.iter().flat_map(|c| c.to_le_bytes()).collect();
        assert_eq!(zstd::bulk::decompress(&out, raw.len()).unwrap(), raw);
    }

    #[test]
    fn many_sequences_use_the_long_sequence_count() {
        // Alternating runs of two values: ~21 000 sequences (the three-byte count).
        let mut v = Vec::new();
        for k in 0..32_000u64 {
            v.push(k % 3 / 2);
        }
        let (raw, back) = round_trip(&v, 4);
        assert_eq!(raw, back);
        let few: Vec<u64> = (0..300).map(|k| u64::from(k % 5 == 0)).collect();
        let (raw, back) = round_trip(&few, 8);
        assert_eq!(raw, back);
    }

    #[test]
    fn content_without_runs_or_too_large_is_refused() {
        let mut f = FillFrame::default();
        f.begin(4);
        let mut r = 99u64;
        for _ in 0..100 {
            f.push((next(&mut r) as u32 | 0x8080_8080).to_le_bytes());
        }
        let mut out = Vec::new();
        assert!(!f.finish(&mut out), "all literals: not smaller");
        f.begin(4);
        f.push_run(0u32.to_le_bytes(), MAX_CONTENT / 4 + 1);
        assert!(!f.finish(&mut out), "beyond one block");
        f.begin(8);
        f.push_run(0u64.to_le_bytes(), MAX_CONTENT / 8);
        assert!(f.finish(&mut out));
        assert_eq!(
            zstd::bulk::decompress(&out, MAX_CONTENT).unwrap(),
            vec![0u8; MAX_CONTENT]
        );
    }
}
