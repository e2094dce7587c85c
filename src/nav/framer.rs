//! One resynchronising framer for navigation byte streams that mix NMEA 0183 text and NovAtel
//! OEM binary messages, arriving in pieces of any size (serial reads split records anywhere).
//!
//! Bytes are [`Framer::push`]ed as they come; [`Framer::next_frame`] returns every complete,
//! checksum-verified record in order, and `None` when it needs more bytes. Nothing is ever
//! fatal: bytes that belong to no record are counted as `unframed_bytes`, and candidate records
//! that fail are counted by reason ([`FramerStats::rejected`]) and skipped, the scan resuming
//! right after the failed record's first byte so that a real record hidden behind a false sync
//! is still found. Memory is bounded: a candidate is given up once it exceeds the longest valid
//! record.
//!
//! Record boundaries:
//! - **NMEA**: `$` or `!`, printable ASCII, `*`, two hex digits, then CR and/or LF. A new `$`/`!`
//!   or a control byte before the end means the sentence was cut short (`truncated`).
//! - **NovAtel binary, long header**: sync `AA 44 12`, header length (byte 3), message length
//!   (u16 LE at byte 8), message, CRC-32 (LE) over header and message.
//! - **NovAtel binary, short header**: sync `AA 44 13`, message length (byte 3), 12-byte
//!   header, message, CRC-32.

use std::collections::BTreeMap;

use serde::Serialize;

use super::crc::{nmea_xor, novatel_crc32};

/// Longest NMEA sentence accepted, bytes from `$` to the line end (the standard says 82; some
/// proprietary sentences are longer).
pub const MAX_NMEA: usize = 256;
/// Longest NovAtel binary message accepted, bytes including header and CRC.
pub const MAX_NOVATEL: usize = 8192;

/// A complete, checksum-verified record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Frame<'a> {
    /// An NMEA sentence: the bytes between `$`/`!` and `*` (address and fields).
    Nmea(&'a [u8]),
    /// A NovAtel binary message with a long (usually 28-byte) header.
    Novatel {
        /// The header, sync bytes included.
        header: &'a [u8],
        /// The message body (without the CRC).
        body: &'a [u8],
    },
    /// A NovAtel binary message with the 12-byte short header.
    NovatelShort {
        /// The header, sync bytes included.
        header: &'a [u8],
        /// The message body (without the CRC).
        body: &'a [u8],
    },
}

/// What the framer has seen so far.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct FramerStats {
    /// Bytes pushed.
    pub bytes: u64,
    /// NMEA sentences framed (checksum good).
    pub nmea: u64,
    /// NovAtel binary messages framed (CRC good).
    pub novatel: u64,
    /// Bytes outside any record (comments, command echoes, line noise).
    pub unframed_bytes: u64,
    /// Candidate records given up, by reason: `bad_checksum`, `no_checksum`, `truncated`,
    /// `too_long`, `bad_crc`, `bad_header`.
    pub rejected: BTreeMap<&'static str, u64>,
}

impl FramerStats {
    /// Candidate records rejected, all reasons.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.values().sum()
    }
}

/// The resynchronising framer (see the module documentation).
#[derive(Debug, Default)]
pub struct Framer {
    buf: Vec<u8>,
    /// Start of the unconsumed bytes in `buf`.
    at: usize,
    /// Set by [`Framer::finish`]: no more bytes will come.
    ended: bool,
    stats: FramerStats,
}

enum Step {
    /// Consume `n` bytes as unframed.
    Unframed(usize),
    /// A candidate failed: consume `n` bytes and count `reason`.
    Reject(usize, &'static str),
    /// NMEA sentence: body range relative to `at`, total length.
    Nmea(usize, usize, usize),
    /// NovAtel message: header length, body length, total length, short header.
    Novatel(usize, usize, usize, bool),
    /// More bytes are needed.
    Wait,
}

impl Framer {
    /// A framer with nothing buffered.
    pub fn new() -> Self {
        Framer::default()
    }

    /// Appends bytes as they arrived.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.at > 0 && (self.at >= self.buf.len() / 2 || self.buf.len() > 1 << 16) {
            self.buf.drain(..self.at);
            self.at = 0;
        }
        self.buf.extend_from_slice(bytes);
        self.stats.bytes += bytes.len() as u64;
    }

    /// Declares the end of the stream: what remains is framed if complete, otherwise counted
    /// (`truncated` for a started record, unframed bytes for the rest).
    pub fn finish(&mut self) {
        self.ended = true;
    }

    /// Counts so far.
    pub fn stats(&self) -> &FramerStats {
        &self.stats
    }

    /// Bytes held waiting for the rest of a record.
    pub fn pending(&self) -> usize {
        self.buf.len() - self.at
    }

    /// The next complete record, or `None` when more bytes are needed (or, after
    /// [`Framer::finish`], when everything has been accounted for).
    pub fn next_frame(&mut self) -> Option<Frame<'_>> {
        loop {
            let rest = &self.buf[self.at..];
            if rest.is_empty() {
                return None;
            }
            match scan(rest, self.ended) {
                Step::Unframed(n) => {
                    self.stats.unframed_bytes += n as u64;
                    self.at += n;
                }
                Step::Reject(n, why) => {
                    *self.stats.rejected.entry(why).or_insert(0) += 1;
                    self.at += n;
                }
                Step::Wait => return None,
                Step::Nmea(b, e, n) => {
                    self.stats.nmea += 1;
                    let start = self.at;
                    self.at += n;
                    return Some(Frame::Nmea(&self.buf[start + b..start + e]));
                }
                Step::Novatel(h, b, n, short) => {
                    self.stats.novatel += 1;
                    let start = self.at;
                    self.at += n;
                    let header = &self.buf[start..start + h];
                    let body = &self.buf[start + h..start + h + b];
                    return Some(if short {
                        Frame::NovatelShort { header, body }
                    } else {
                        Frame::Novatel { header, body }
                    });
                }
            }
        }
    }
}

fn is_sync(b: u8) -> bool {
    b == b'$' || b == b'!' || b == 0xAA
}

/// Decides what the bytes at the start of `rest` are. `ended`: no more bytes will come.
fn scan(rest: &[u8], ended: bool) -> Step {
    match rest[0] {
        b'$' | b'!' => scan_nmea(rest, ended),
        0xAA => scan_novatel(rest, ended),
        _ => {
            let n = rest.iter().position(|&b| is_sync(b)).unwrap_or(rest.len());
            Step::Unframed(n)
        }
    }
}

fn hex(b: u8) -> Option<u8> {
    match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'A'..=b'F' => Some(b - b'A' + 10),
        b'a'..=b'f' => Some(b - b'a' + 10),
        _ => None,
    }
}

fn scan_nmea(rest: &[u8], ended: bool) -> Step {
    // Find the line end; a new sentence start or a control byte first means a cut sentence.
    let limit = rest.len().min(MAX_NMEA);
    let mut end = None;
    for (i, &b) in rest.iter().enumerate().take(limit).skip(1) {
        match b {
            b'\r' | b'\n' => {
                end = Some(i);
                break;
            }
            b'$' | b'!' => {
                // A complete `*HH` right before the new start: a sentence whose line end was
                // lost (seen from receivers that drop the CR LF under load). Keep it when its
                // checksum holds.
                if i >= 4 && rest[i - 3] == b'*' {
                    let line = &rest[1..i - 3];
                    if let (Some(a), Some(b)) = (hex(rest[i - 2]), hex(rest[i - 1]))
                        && a << 4 | b == nmea_xor(line)
                    {
                        return Step::Nmea(1, i - 3, i);
                    }
                }
                return Step::Reject(i, "truncated");
            }
            0x20..=0x7e => {}
            _ => return Step::Reject(i, "truncated"),
        }
    }
    let Some(end) = end else {
        if rest.len() >= MAX_NMEA {
            return Step::Reject(1, "too_long");
        }
        return if ended {
            Step::Reject(rest.len(), "truncated")
        } else {
            Step::Wait
        };
    };
    // Consume the line terminator(s): CR, LF or CRLF.
    let mut total = end + 1;
    if rest[end] == b'\r' && rest.get(end + 1) == Some(&b'\n') {
        total += 1;
    } else if rest[end] == b'\r' && end + 1 == rest.len() && !ended {
        // A CR at the end of what we have: wait for a possible LF so it is not left behind.
        return Step::Wait;
    }
    let line = &rest[1..end];
    let Some(star) = line.iter().rposition(|&b| b == b'*') else {
        return Step::Reject(total, "no_checksum");
    };
    let tail = &line[star + 1..];
    let given = match tail {
        [a, b] => hex(*a).zip(hex(*b)).map(|(a, b)| a << 4 | b),
        _ => None,
    };
    match given {
        Some(g) if g == nmea_xor(&line[..star]) => Step::Nmea(1, 1 + star, total),
        Some(_) => Step::Reject(total, "bad_checksum"),
        None => Step::Reject(total, "no_checksum"),
    }
}

fn scan_novatel(rest: &[u8], ended: bool) -> Step {
    // Fewer bytes than the record needs: wait, or at the end of the stream a cut record.
    let need = |_n: usize| {
        if ended {
            Step::Reject(rest.len(), "truncated")
        } else {
            Step::Wait
        }
    };
    if rest.len() < 3 {
        return need(3);
    }
    if rest[1] != 0x44 || (rest[2] != 0x12 && rest[2] != 0x13) {
        return Step::Unframed(1);
    }
    let short = rest[2] == 0x13;
    let (header_len, body_len) = if short {
        if rest.len() < 12 {
            return need(12);
        }
        (12usize, rest[3] as usize)
    } else {
        if rest.len() < 10 {
            return need(10);
        }
        let h = rest[3] as usize;
        if h < 28 {
            return Step::Reject(1, "bad_header");
        }
        (h, u16::from_le_bytes([rest[8], rest[9]]) as usize)
    };
    let total = header_len + body_len + 4;
    if total > MAX_NOVATEL {
        return Step::Reject(1, "bad_header");
    }
    if rest.len() < total {
        return need(total);
    }
    let crc = u32::from_le_bytes([
        rest[total - 4],
        rest[total - 3],
        rest[total - 2],
        rest[total - 1],
    ]);
    if novatel_crc32(&rest[..total - 4]) != crc {
        // Resume one byte on: the sync may have been a coincidence inside other bytes.
        return Step::Reject(1, "bad_crc");
    }
    Step::Novatel(header_len, body_len, total, short)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sentence(body: &str) -> String {
        format!("${body}*{:02X}\r\n", nmea_xor(body.as_bytes()))
    }

    fn novatel(id: u16, body: &[u8]) -> Vec<u8> {
        let mut m = vec![0xAA, 0x44, 0x12, 28];
        m.extend_from_slice(&id.to_le_bytes());
        m.extend_from_slice(&[0, 0]);
        m.extend_from_slice(&(body.len() as u16).to_le_bytes());
        m.resize(28, 0);
        m.extend_from_slice(body);
        let crc = novatel_crc32(&m);
        m.extend_from_slice(&crc.to_le_bytes());
        m
    }

    /// Every frame of `chunks` pushed in order, as owned bytes, plus the final stats.
    fn frames(chunks: &[&[u8]]) -> (Vec<Vec<u8>>, FramerStats) {
        let mut f = Framer::new();
        let mut out = Vec::new();
        for c in chunks {
            f.push(c);
            while let Some(fr) = f.next_frame() {
                out.push(match fr {
                    Frame::Nmea(b) => b.to_vec(),
                    Frame::Novatel { body, .. } | Frame::NovatelShort { body, .. } => body.to_vec(),
                });
            }
        }
        f.finish();
        while let Some(fr) = f.next_frame() {
            out.push(match fr {
                Frame::Nmea(b) => b.to_vec(),
                Frame::Novatel { body, .. } | Frame::NovatelShort { body, .. } => body.to_vec(),
            });
        }
        (out, f.stats().clone())
    }

    #[test]
    fn mixed_stream_split_at_every_byte_gives_the_same_frames() {
        let mut stream = Vec::new();
        stream.extend_from_slice(b"garbage\x00\x01");
        stream.extend_from_slice(sentence("GPGGA,1,2,3").as_bytes());
        stream.extend_from_slice(&novatel(1465, &[7u8; 126]));
        stream.extend_from_slice(b"<OK\r\n");
        stream.extend_from_slice(sentence("PASHR,204132.000,010.51,T").as_bytes());
        let (whole, s1) = frames(&[&stream]);
        assert_eq!(whole.len(), 3);
        assert_eq!(whole[0], b"GPGGA,1,2,3");
        assert_eq!(whole[1], vec![7u8; 126]);
        assert_eq!(s1.nmea, 2);
        assert_eq!(s1.novatel, 1);
        assert_eq!(s1.rejected_total(), 0);
        assert_eq!(s1.unframed_bytes, 9 + 5);
        let pieces: Vec<&[u8]> = stream.chunks(1).collect();
        let (split, s2) = frames(&pieces);
        assert_eq!(split, whole);
        assert_eq!(s2, s1);
    }

    #[test]
    fn bad_checksums_and_cut_sentences_are_counted_and_skipped() {
        let good = sentence("GPHDT,123.4,T");
        let mut bad = sentence("GPHDT,123.5,T");
        bad.replace_range(bad.len() - 4..bad.len() - 2, "00");
        let stream = format!("$GPGGA,12,3{good}{bad}$GPVTG,1,T\r\n{good}$GPZDA,1");
        let (fr, s) = frames(&[stream.as_bytes()]);
        assert_eq!(fr.len(), 2);
        assert_eq!(s.rejected["truncated"], 2, "{s:?}");
        assert_eq!(s.rejected["bad_checksum"], 1);
        assert_eq!(s.rejected["no_checksum"], 1);
    }

    #[test]
    fn a_corrupted_binary_message_does_not_hide_the_next_one() {
        let mut a = novatel(42, &[1u8; 72]);
        a[40] ^= 0xff;
        let b = novatel(101, &[2u8; 44]);
        let mut stream = a.clone();
        stream.extend_from_slice(&b);
        let (fr, s) = frames(&[&stream]);
        assert_eq!(fr, vec![vec![2u8; 44]]);
        assert_eq!(s.rejected["bad_crc"], 1);
    }

    #[test]
    fn a_stream_cut_inside_a_record_counts_it_as_truncated() {
        let m = novatel(42, &[1u8; 72]);
        let (fr, s) = frames(&[&m[..50]]);
        assert!(fr.is_empty());
        assert_eq!(s.rejected["truncated"], 1);
        let (fr, s) = frames(&[b"$GPGGA,1,2"]);
        assert!(fr.is_empty());
        assert_eq!(s.rejected["truncated"], 1);
    }

    #[test]
    fn memory_stays_bounded_on_endless_junk() {
        let mut f = Framer::new();
        let junk: Vec<u8> = (0..4096u32).map(|i| (i * 131 + 7) as u8 | 0x20).collect();
        for _ in 0..200 {
            f.push(&junk);
            while f.next_frame().is_some() {}
            assert!(f.pending() <= MAX_NOVATEL.max(MAX_NMEA));
        }
    }

    proptest::proptest! {
        #[test]
        fn arbitrary_bytes_never_panic_and_are_all_accounted_for(
            data in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..2000),
            cut in 0usize..2000,
        ) {
            let cut = cut.min(data.len());
            let mut f = Framer::new();
            let mut framed = 0u64;
            for part in [&data[..cut], &data[cut..]] {
                f.push(part);
                while let Some(fr) = f.next_frame() {
                    framed += match fr {
                        Frame::Nmea(b) => b.len() as u64 + 5,
                        Frame::Novatel { header, body } | Frame::NovatelShort { header, body } => {
                            (header.len() + body.len() + 4) as u64
                        }
                    };
                }
            }
            f.finish();
            while f.next_frame().is_some() {}
            proptest::prop_assert_eq!(f.pending(), 0);
            proptest::prop_assert!(framed <= data.len() as u64 + 1);
        }
    }
}
