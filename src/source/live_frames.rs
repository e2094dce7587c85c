//! The live digitizer stream: digitizer frames as a digitizer (or `fwlidar simulate --live`)
//! sends them over the network, one frame per UDP datagram or back to back on a TCP stream.
//!
//! Each frame is a 28-byte header followed by exactly the payload of a capture DigitizerFrame
//! record ([`crate::format::frame::encode_frame`]); layout in `docs/formats.md` ("Live digitizer
//! stream"). All integers are little-endian. The header carries a sequence number (so a receiver
//! counts lost frames), the payload length (so a TCP receiver finds the next frame) and two
//! CRC-32C values: one over the header itself, so that a false sync pattern inside garbage is
//! rejected before its length is believed, and one over the payload.
//!
//! Everything here is pure and never panics on any input: [`parse_datagram`] checks one
//! datagram, [`StreamDecoder`] splits a byte stream (any split of reads) into frames and skips
//! garbage with a reason, [`SequenceTracker`] counts lost and out-of-order frames.

use std::io::Read;

use crate::format::frame::{FrameError, encode_frame};
use crate::pulse::Pulse;

/// Sync pattern opening every frame header: `F5 57 4C 44` (`0xF5 'W' 'L' 'D'`). No proper suffix
/// of it is a prefix of it, so a resync can skip a whole rejected pattern.
pub const LIVE_MAGIC: [u8; 4] = [0xF5, b'W', b'L', b'D'];
/// Version of the live stream header this code writes and reads.
pub const LIVE_VERSION: u8 = 1;
/// Kind byte of a digitizer frame (the same number as the capture's DigitizerFrame record).
pub const KIND_DIGITIZER_FRAME: u8 = 2;
/// Bytes of the frame header: magic `[u8; 4]`, version u8, kind u8, reserved u16, sequence u64,
/// payload_len u32, payload_crc u32, header_crc u32.
pub const LIVE_HEADER_LEN: usize = 28;
/// Largest payload a header may declare, bytes (16 MiB, as in the capture format); larger is
/// corruption.
pub const LIVE_MAX_PAYLOAD: u32 = 16 * 1024 * 1024;
/// Largest UDP payload over IPv4, bytes: a datagram holds a header and at most this minus
/// [`LIVE_HEADER_LEN`] bytes of frame.
pub const UDP_MAX_DATAGRAM: usize = 65_507;

/// Why bytes are not a valid live frame.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LiveFrameError {
    /// Fewer bytes than a header.
    #[error("live frame is {len} bytes, shorter than its {LIVE_HEADER_LEN}-byte header")]
    TooShort {
        /// Bytes available.
        len: usize,
    },
    /// The first four bytes are not the sync pattern.
    #[error("live frame does not start with the sync pattern F5 57 4C 44")]
    BadMagic,
    /// The header's CRC-32C does not match its bytes.
    #[error("live frame header CRC mismatch (stored {stored:#010x}, computed {computed:#010x})")]
    BadHeaderCrc {
        /// CRC in the header.
        stored: u32,
        /// CRC of the header bytes as received.
        computed: u32,
    },
    /// A header version this code does not read.
    #[error("live frame header version {version}; this program reads version {LIVE_VERSION}")]
    UnsupportedVersion {
        /// The version byte.
        version: u8,
    },
    /// A kind other than a digitizer frame.
    #[error("live frame kind {kind}; only {KIND_DIGITIZER_FRAME} (digitizer frame) is defined")]
    UnknownKind {
        /// The kind byte.
        kind: u8,
    },
    /// The header declares a payload above [`LIVE_MAX_PAYLOAD`].
    #[error(
        "live frame header declares a {len}-byte payload, above the {LIVE_MAX_PAYLOAD}-byte limit"
    )]
    PayloadTooLong {
        /// Declared payload length, bytes.
        len: u32,
    },
    /// A datagram whose length is not its header plus the declared payload.
    #[error("live datagram holds {actual} payload bytes but its header declares {declared}")]
    LengthMismatch {
        /// Declared payload length, bytes.
        declared: u32,
        /// Bytes after the header.
        actual: usize,
    },
    /// The payload's CRC-32C does not match.
    #[error("live frame payload CRC mismatch (stored {stored:#010x}, computed {computed:#010x})")]
    BadPayloadCrc {
        /// CRC in the header.
        stored: u32,
        /// CRC of the payload as received.
        computed: u32,
    },
    /// Bytes that contain no sync pattern (stream garbage).
    #[error("no sync pattern")]
    NoSync,
    /// The stream ended inside a frame.
    #[error("stream ended inside a frame: {have} of {need} bytes")]
    Truncated {
        /// Bytes of the frame received.
        have: usize,
        /// Bytes the frame needs (its header alone when the header itself is incomplete).
        need: usize,
    },
}

/// A valid frame, borrowing its payload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LiveFrame<'a> {
    /// Sequence number: 0 for the sender's first frame, one more for each frame after.
    pub sequence: u64,
    /// The digitizer frame payload (decode with [`crate::format::frame::decode_frame`]).
    pub payload: &'a [u8],
}

/// A checked header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Header {
    kind: u8,
    sequence: u64,
    payload_len: u32,
    payload_crc: u32,
}

fn le_u32(b: &[u8]) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[..4]);
    u32::from_le_bytes(a)
}

fn le_u64(b: &[u8]) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    u64::from_le_bytes(a)
}

/// Checks the header at the start of `b` (magic, header CRC, version, payload limit).
fn parse_header(b: &[u8]) -> Result<Header, LiveFrameError> {
    let Some(h) = b.get(..LIVE_HEADER_LEN) else {
        return Err(LiveFrameError::TooShort { len: b.len() });
    };
    if h[..4] != LIVE_MAGIC {
        return Err(LiveFrameError::BadMagic);
    }
    let stored = le_u32(&h[24..28]);
    let computed = crc32c::crc32c(&h[..24]);
    if stored != computed {
        return Err(LiveFrameError::BadHeaderCrc { stored, computed });
    }
    if h[4] != LIVE_VERSION {
        return Err(LiveFrameError::UnsupportedVersion { version: h[4] });
    }
    let payload_len = le_u32(&h[16..20]);
    if payload_len > LIVE_MAX_PAYLOAD {
        return Err(LiveFrameError::PayloadTooLong { len: payload_len });
    }
    Ok(Header {
        kind: h[5],
        sequence: le_u64(&h[8..16]),
        payload_len,
        payload_crc: le_u32(&h[20..24]),
    })
}

fn check_payload(h: &Header, payload: &[u8]) -> Result<(), LiveFrameError> {
    let computed = crc32c::crc32c(payload);
    if computed != h.payload_crc {
        return Err(LiveFrameError::BadPayloadCrc {
            stored: h.payload_crc,
            computed,
        });
    }
    if h.kind != KIND_DIGITIZER_FRAME {
        return Err(LiveFrameError::UnknownKind { kind: h.kind });
    }
    Ok(())
}

/// Writes one live frame (header and the frame payload of `pulse`) into `out`, replacing what it
/// held; `out`'s capacity is reused, so a sender that keeps one buffer does not allocate per
/// pulse once it has held its largest frame. On error `out` is left empty.
pub fn encode_live_frame(
    sequence: u64,
    pulse: &Pulse,
    out: &mut Vec<u8>,
) -> Result<(), FrameError> {
    out.clear();
    out.resize(LIVE_HEADER_LEN, 0);
    if let Err(e) = encode_frame(pulse, out) {
        out.clear();
        return Err(e);
    }
    let payload_len = (out.len() - LIVE_HEADER_LEN) as u32;
    let payload_crc = crc32c::crc32c(&out[LIVE_HEADER_LEN..]);
    out[..4].copy_from_slice(&LIVE_MAGIC);
    out[4] = LIVE_VERSION;
    out[5] = KIND_DIGITIZER_FRAME;
    out[6..8].copy_from_slice(&[0, 0]);
    out[8..16].copy_from_slice(&sequence.to_le_bytes());
    out[16..20].copy_from_slice(&payload_len.to_le_bytes());
    out[20..24].copy_from_slice(&payload_crc.to_le_bytes());
    let header_crc = crc32c::crc32c(&out[..24]);
    out[24..28].copy_from_slice(&header_crc.to_le_bytes());
    Ok(())
}

/// Checks one UDP datagram: exactly one header and the payload it declares.
pub fn parse_datagram(datagram: &[u8]) -> Result<LiveFrame<'_>, LiveFrameError> {
    let h = parse_header(datagram)?;
    let actual = datagram.len() - LIVE_HEADER_LEN;
    if actual != h.payload_len as usize {
        return Err(LiveFrameError::LengthMismatch {
            declared: h.payload_len,
            actual,
        });
    }
    let payload = &datagram[LIVE_HEADER_LEN..];
    check_payload(&h, payload)?;
    Ok(LiveFrame {
        sequence: h.sequence,
        payload,
    })
}

/// What [`StreamDecoder::next_item`] found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum StreamItem<'a> {
    /// A valid frame.
    Frame(LiveFrame<'a>),
    /// Bytes skipped while looking for the next frame, and why (`NoSync` for bytes before a sync
    /// pattern; a header or payload error for a rejected pattern or frame).
    Skipped {
        /// Bytes skipped.
        bytes: usize,
        /// Why.
        reason: LiveFrameError,
    },
}

/// Incremental decoder of a live TCP stream: feed it bytes as they arrive, in reads of any size,
/// and take frames out. Garbage before or between frames is skipped up to the next sync pattern
/// whose header checks; a frame whose payload CRC fails is skipped by its sync pattern only, so
/// a frame inside it can still be found. Memory is the largest frame seen plus one read.
#[derive(Debug, Default)]
pub struct StreamDecoder {
    buf: Vec<u8>,
    start: usize,
    skipped: u64,
    frames: u64,
}

/// Bytes a [`StreamDecoder::read_from`] asks the reader for at most.
pub const READ_CHUNK: usize = 64 * 1024;

impl StreamDecoder {
    /// An empty decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Drops the bytes already consumed so the buffer holds only pending data.
    fn compact(&mut self) {
        if self.start > 0 {
            self.buf.drain(..self.start);
            self.start = 0;
        }
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.compact();
        self.buf.extend_from_slice(bytes);
    }

    /// Reads once from `reader` straight into the buffer; returns the bytes read (0 at the end
    /// of the stream), as [`Read::read`] does.
    pub fn read_from<R: Read + ?Sized>(&mut self, reader: &mut R) -> std::io::Result<usize> {
        self.compact();
        let len = self.buf.len();
        self.buf.resize(len + READ_CHUNK, 0);
        let result = reader.read(&mut self.buf[len..]);
        let n = *result.as_ref().unwrap_or(&0);
        self.buf.truncate(len + n.min(READ_CHUNK));
        result
    }

    /// Bytes received and not yet consumed.
    pub fn pending(&self) -> usize {
        self.buf.len() - self.start
    }

    /// Bytes skipped so far (garbage, rejected headers and frames).
    pub fn skipped_bytes(&self) -> u64 {
        self.skipped
    }

    /// Frames returned so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    fn skip(&mut self, bytes: usize, reason: LiveFrameError) -> StreamItem<'static> {
        self.start += bytes;
        self.skipped += bytes as u64;
        StreamItem::Skipped { bytes, reason }
    }

    /// The next frame or skipped run from the bytes received so far; `None` when more bytes are
    /// needed. Call until `None` after each [`push`](Self::push).
    pub fn next_item(&mut self) -> Option<StreamItem<'_>> {
        let avail = &self.buf[self.start..];
        if avail.is_empty() {
            return None;
        }
        let Some(at) = find_magic(avail) else {
            // Keep a tail that may be the start of a sync pattern split across reads.
            let keep = partial_magic_suffix(avail);
            let garbage = avail.len() - keep;
            return (garbage > 0).then(|| self.skip(garbage, LiveFrameError::NoSync));
        };
        if at > 0 {
            return Some(self.skip(at, LiveFrameError::NoSync));
        }
        if avail.len() < LIVE_HEADER_LEN {
            return None;
        }
        let header = match parse_header(avail) {
            Ok(h) => h,
            Err(reason) => return Some(self.skip(LIVE_MAGIC.len(), reason)),
        };
        let total = LIVE_HEADER_LEN + header.payload_len as usize;
        if avail.len() < total {
            return None;
        }
        match check_payload(&header, &avail[LIVE_HEADER_LEN..total]) {
            Ok(()) => {}
            // A well-formed frame of another kind: skip it whole.
            Err(reason @ LiveFrameError::UnknownKind { .. }) => {
                return Some(self.skip(total, reason));
            }
            Err(reason) => return Some(self.skip(LIVE_MAGIC.len(), reason)),
        }
        let from = self.start + LIVE_HEADER_LEN;
        self.start += total;
        self.frames += 1;
        Some(StreamItem::Frame(LiveFrame {
            sequence: header.sequence,
            payload: &self.buf[from..self.start],
        }))
    }

    /// At the end of the stream: what is left unconsumed, as an error (`Truncated` when it starts
    /// with a valid header, `NoSync` otherwise); `None` when the stream ended between frames.
    /// Call after [`next_item`](Self::next_item) has returned `None`. Clears the decoder.
    pub fn finish(&mut self) -> Option<LiveFrameError> {
        let avail = &self.buf[self.start..];
        if avail.is_empty() {
            return None;
        }
        let have = avail.len();
        let err = if avail.starts_with(&LIVE_MAGIC) || LIVE_MAGIC.starts_with(avail) {
            let need = parse_header(avail).map_or(LIVE_HEADER_LEN, |h| {
                LIVE_HEADER_LEN + h.payload_len as usize
            });
            LiveFrameError::Truncated { have, need }
        } else {
            LiveFrameError::NoSync
        };
        self.skipped += have as u64;
        self.buf.clear();
        self.start = 0;
        Some(err)
    }
}

/// Position of the first sync pattern in `b`.
fn find_magic(b: &[u8]) -> Option<usize> {
    let mut from = 0;
    while let Some(off) = b.get(from..)?.iter().position(|&x| x == LIVE_MAGIC[0]) {
        let at = from + off;
        if b.get(at..at + LIVE_MAGIC.len()) == Some(&LIVE_MAGIC[..]) {
            return Some(at);
        }
        from = at + 1;
    }
    None
}

/// Length of the longest proper suffix of `b` that is a prefix of the sync pattern.
fn partial_magic_suffix(b: &[u8]) -> usize {
    (1..LIVE_MAGIC.len())
        .rev()
        .find(|&k| b.len() >= k && b[b.len() - k..] == LIVE_MAGIC[..k])
        .unwrap_or(0)
}

/// Counts lost and out-of-order frames from their sequence numbers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SequenceTracker {
    next: Option<u64>,
    /// Frames received.
    pub received: u64,
    /// Frames missing: sequence numbers skipped over.
    pub lost: u64,
    /// Frames that came with a sequence number below the next expected one (duplicated or
    /// reordered; a restarted sender counts here once and is then followed).
    pub out_of_order: u64,
}

impl SequenceTracker {
    /// A tracker that has seen nothing (the first frame may have any sequence number).
    pub fn new() -> Self {
        Self::default()
    }

    /// Records one received sequence number; returns how many frames were lost just before it.
    pub fn observe(&mut self, sequence: u64) -> u64 {
        self.received += 1;
        let gap = match self.next {
            Some(next) if sequence >= next => sequence - next,
            Some(_) => {
                self.out_of_order += 1;
                0
            }
            None => 0,
        };
        self.lost += gap;
        self.next = Some(sequence.wrapping_add(1));
        gap
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::frame::decode_frame;
    use crate::pulse::testing::framed_pulse;
    use proptest::prelude::*;

    fn frame_bytes(seq: u64, id: u64, n: u32) -> Vec<u8> {
        let mut out = Vec::new();
        encode_live_frame(seq, &framed_pulse(id, n), &mut out).unwrap();
        out
    }

    /// Every frame the decoder yields from `bytes` fed in the given pieces, and the skipped total.
    fn decode_in_pieces(bytes: &[u8], cuts: &[usize]) -> (Vec<(u64, Vec<u8>)>, u64) {
        let mut d = StreamDecoder::new();
        let mut frames = Vec::new();
        let mut from = 0;
        for &cut in cuts.iter().chain(std::iter::once(&bytes.len())) {
            d.push(&bytes[from..cut]);
            from = cut;
            while let Some(item) = d.next_item() {
                if let StreamItem::Frame(f) = item {
                    frames.push((f.sequence, f.payload.to_vec()));
                }
            }
        }
        assert_eq!(d.finish(), None);
        (frames, d.skipped_bytes())
    }

    #[test]
    fn a_datagram_round_trips_to_the_same_pulse() {
        let p = framed_pulse(42, 30);
        let mut buf = Vec::new();
        encode_live_frame(7, &p, &mut buf).unwrap();
        let f = parse_datagram(&buf).unwrap();
        assert_eq!(f.sequence, 7);
        let mut q = Pulse::default();
        decode_frame(f.payload, &mut q).unwrap();
        assert_eq!(q.pulse_id, 42);
        assert_eq!(q.gps_time, p.gps_time);
        assert_eq!(q.raw, p.raw);
        assert_eq!(q.segments, p.segments);
        // The buffer is reused: a second, smaller frame replaces the first.
        let cap = buf.capacity();
        encode_live_frame(8, &framed_pulse(43, 10), &mut buf).unwrap();
        assert_eq!(buf.capacity(), cap);
        assert_eq!(parse_datagram(&buf).unwrap().sequence, 8);
    }

    #[test]
    fn damaged_datagrams_are_rejected_with_their_reason() {
        let good = frame_bytes(1, 1, 20);
        assert_eq!(
            parse_datagram(&good[..10]),
            Err(LiveFrameError::TooShort { len: 10 })
        );
        let mut bad = good.clone();
        bad[0] = 0;
        assert_eq!(parse_datagram(&bad), Err(LiveFrameError::BadMagic));
        let mut bad = good.clone();
        bad[9] ^= 1;
        assert!(matches!(
            parse_datagram(&bad),
            Err(LiveFrameError::BadHeaderCrc { .. })
        ));
        let mut bad = good.clone();
        *bad.last_mut().unwrap() ^= 1;
        assert!(matches!(
            parse_datagram(&bad),
            Err(LiveFrameError::BadPayloadCrc { .. })
        ));
        assert_eq!(
            parse_datagram(&good[..good.len() - 1]),
            Err(LiveFrameError::LengthMismatch {
                declared: (good.len() - LIVE_HEADER_LEN) as u32,
                actual: good.len() - LIVE_HEADER_LEN - 1,
            })
        );
        // A newer version (with its header CRC made valid) is refused by name.
        let mut newer = good.clone();
        newer[4] = 2;
        let crc = crc32c::crc32c(&newer[..24]);
        newer[24..28].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(
            parse_datagram(&newer),
            Err(LiveFrameError::UnsupportedVersion { version: 2 })
        );
    }

    #[test]
    fn the_stream_decoder_survives_a_split_at_every_byte_boundary() {
        let mut stream = Vec::new();
        for k in 0..3 {
            stream.extend(frame_bytes(k, 100 + k, 5 + k as u32 * 9));
        }
        let (whole, skipped) = decode_in_pieces(&stream, &[]);
        assert_eq!(skipped, 0);
        assert_eq!(whole.iter().map(|f| f.0).collect::<Vec<_>>(), vec![0, 1, 2]);
        for cut in 0..=stream.len() {
            assert_eq!(
                decode_in_pieces(&stream, &[cut]),
                (whole.clone(), 0),
                "cut {cut}"
            );
        }
        // One byte at a time.
        let every: Vec<usize> = (1..stream.len()).collect();
        assert_eq!(decode_in_pieces(&stream, &every), (whole, 0));
    }

    #[test]
    fn garbage_before_and_between_frames_is_skipped_and_counted() {
        let a = frame_bytes(0, 1, 12);
        let b = frame_bytes(1, 2, 12);
        // Garbage holding a false sync pattern (its header CRC fails) and a partial one.
        let mut garbage = b"noise\xF5WLDxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx\xF5W".to_vec();
        let mut stream = garbage.clone();
        stream.extend(&a);
        garbage.truncate(7);
        stream.extend(&garbage);
        stream.extend(&b);
        let skipped_expected = (stream.len() - a.len() - b.len()) as u64;
        for cut in 0..=stream.len() {
            let (frames, skipped) = decode_in_pieces(&stream, &[cut]);
            assert_eq!(frames.len(), 2, "cut {cut}");
            assert_eq!(frames[0].1, a[LIVE_HEADER_LEN..]);
            assert_eq!(frames[1].1, b[LIVE_HEADER_LEN..]);
            assert_eq!(skipped, skipped_expected, "cut {cut}");
        }
    }

    #[test]
    fn a_frame_with_a_damaged_payload_is_skipped_and_the_next_one_found() {
        let mut a = frame_bytes(0, 1, 40);
        let b = frame_bytes(1, 2, 12);
        let n = a.len();
        a[n - 3] ^= 0xFF;
        let mut stream = a.clone();
        stream.extend(&b);
        let (frames, skipped) = decode_in_pieces(&stream, &[]);
        assert_eq!(frames, vec![(1, b[LIVE_HEADER_LEN..].to_vec())]);
        assert_eq!(skipped, a.len() as u64);
    }

    #[test]
    fn a_truncated_frame_is_reported_at_the_end_of_the_stream() {
        let a = frame_bytes(0, 1, 20);
        let b = frame_bytes(1, 2, 20);
        for cut in 1..b.len() {
            let mut d = StreamDecoder::new();
            d.push(&a);
            d.push(&b[..cut]);
            let mut frames = 0;
            while let Some(item) = d.next_item() {
                assert!(matches!(item, StreamItem::Frame(_)), "cut {cut}: {item:?}");
                frames += 1;
            }
            assert_eq!(frames, 1);
            let need = if cut < LIVE_HEADER_LEN {
                LIVE_HEADER_LEN
            } else {
                b.len()
            };
            assert_eq!(
                d.finish(),
                Some(LiveFrameError::Truncated { have: cut, need }),
                "cut {cut}"
            );
            assert_eq!(d.pending(), 0);
        }
    }

    #[test]
    fn read_from_fills_the_decoder_from_a_reader() {
        let mut stream = Vec::new();
        for k in 0..4 {
            stream.extend(frame_bytes(k, k, 300));
        }
        let mut reader = std::io::Cursor::new(stream);
        let mut d = StreamDecoder::new();
        let mut seqs = Vec::new();
        while d.read_from(&mut reader).unwrap() > 0 {
            while let Some(item) = d.next_item() {
                if let StreamItem::Frame(f) = item {
                    seqs.push(f.sequence);
                }
            }
        }
        assert_eq!(seqs, vec![0, 1, 2, 3]);
        assert_eq!(d.frames(), 4);
        assert_eq!(d.finish(), None);
    }

    #[test]
    fn sequence_tracker_counts_losses_and_reordering() {
        let mut t = SequenceTracker::new();
        assert_eq!(t.observe(10), 0);
        assert_eq!(t.observe(11), 0);
        assert_eq!(t.observe(14), 2);
        assert_eq!(t.observe(12), 0);
        assert_eq!(t.observe(13), 0);
        assert_eq!((t.received, t.lost, t.out_of_order), (5, 2, 1));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn parsing_arbitrary_bytes_never_panics(
            bytes in proptest::collection::vec(any::<u8>(), 0..400),
            cuts in proptest::collection::vec(0usize..400, 0..6),
        ) {
            let _ = parse_datagram(&bytes);
            let mut d = StreamDecoder::new();
            let mut cuts: Vec<usize> = cuts.into_iter().filter(|&c| c <= bytes.len()).collect();
            cuts.sort_unstable();
            let mut from = 0;
            let mut seen = 0u64;
            for cut in cuts.into_iter().chain(std::iter::once(bytes.len())) {
                d.push(&bytes[from..cut]);
                from = cut;
                while let Some(item) = d.next_item() {
                    match item {
                        StreamItem::Frame(f) => seen += (LIVE_HEADER_LEN + f.payload.len()) as u64,
                        StreamItem::Skipped { bytes, .. } => prop_assert!(bytes > 0),
                    }
                }
            }
            let _ = d.finish();
            // Every byte is either in a frame or skipped.
            prop_assert_eq!(seen + d.skipped_bytes(), bytes.len() as u64);
        }

        #[test]
        fn frames_inside_arbitrary_garbage_are_all_found(
            before in proptest::collection::vec(any::<u8>(), 0..80),
            between in proptest::collection::vec(any::<u8>(), 0..80),
            cut in 0usize..400,
        ) {
            let a = frame_bytes(5, 1, 17);
            let b = frame_bytes(6, 2, 3);
            let mut stream = before.clone();
            stream.extend(&a);
            stream.extend(&between);
            stream.extend(&b);
            let cut = cut.min(stream.len());
            let (frames, _) = decode_in_pieces(&stream, &[cut]);
            let seqs: Vec<u64> = frames.iter().map(|f| f.0).collect();
            // Garbage cannot forge a header CRC and a payload CRC by chance (2^-64).
            prop_assert_eq!(seqs, vec![5, 6]);
        }
    }
}
