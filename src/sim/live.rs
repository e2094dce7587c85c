//! Live sensor emulation (`fwlidar simulate --live`): plays any stream of [`SimItem`]s in real
//! time into the inputs of the on-board daemon, as the instruments would feed it in flight.
//!
//! - Digitizer frames go over the network, one frame per pulse, in the live stream format of
//!   [`crate::source::live_frames`] (`docs/formats.md`, "Live digitizer stream"): one UDP
//!   datagram per pulse to a destination ([`FrameTarget::Udp`]), or a TCP stream that the
//!   emulator serves to the first daemon that connects ([`FrameTarget::TcpListen`], as a
//!   digitizer does) or that it opens to a listening daemon ([`FrameTarget::TcpConnect`]). On
//!   TCP the frames due so far leave in one write before the player sleeps (or every 64 KiB,
//!   and before each navigation record), as a digitizer's DMA blocks do, rather than one
//!   segment per frame: at 200 kHz that halved the player's own CPU (0.55 → 0.27 of a core)
//!   and the daemon's receiver's wake-ups.
//! - Navigation bytes (the NMEA a GNSS/INS receiver would send) are written into a terminal:
//!   an existing one ([`NavOutput::open_tty`], e.g. one end of a `socat` pair) or the master of a
//!   pseudo-terminal pair created here whose slave is symlinked at a path the daemon opens as its
//!   serial device ([`NavOutput::create_pty_link`]). Like a serial line, a terminal nobody reads
//!   does not stop the emulator: bytes that do not fit are dropped and counted.
//! - Pacing ([`Pacer`]): an item is released when the wall clock reaches its time relative to
//!   the first item, divided by the speed factor (0 = as fast as possible). Deadlines are
//!   absolute offsets from one start instant, so sleeping late never accumulates into drift: a
//!   late item is followed by items already due, sent at once until the stream is back on time.
//!   While paced, the playing thread's timer slack is 250 µs (`PACED_TIMER_SLACK`): its
//!   sleeps end up to that much late, so frames leave in blocks of ~50 at 200 kHz, one wake-up
//!   each, instead of ~20 (at 200 kHz the player's CPU went 0.24 → 0.16 of a core, and the
//!   daemon beside it on two cores had a p99 of 35–41 ms against 55–78 ms in alternating runs;
//!   docs/performance.md).
//!
//! The sending loop reuses one encode buffer, so it allocates nothing per pulse of its own.

use std::io::{ErrorKind, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs, UdpSocket};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use crate::format::frame::FrameError;
use crate::sim::SimItem;
use crate::source::live_frames::{UDP_MAX_DATAGRAM, encode_live_frame};

/// An item released more than this after its due time counts as late.
pub const LATE_TOLERANCE: Duration = Duration::from_millis(1);
/// Longest single sleep while waiting for a deadline or a connection, so that a stop request
/// (SIGINT/SIGTERM) is seen within this time.
const STOP_POLL: Duration = Duration::from_millis(50);
/// Write timeout of the TCP stream: a blocked write is retried after this, unless stopped.
const TCP_WRITE_POLL: Duration = Duration::from_millis(100);
/// How long a TCP connection to a listening daemon may take.
const TCP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// At the end, how long to wait for the reader of a created pseudo-terminal to take the last
/// navigation bytes before the terminal is closed (closing it discards unread bytes).
const NAV_DRAIN_TIMEOUT: Duration = Duration::from_secs(1);
/// Timer slack of the playing thread while paced (`prctl(PR_SET_TIMERSLACK)`): the kernel may
/// wake a sleep up to this much after its deadline, so that the wake-ups coalesce into one per
/// this interval or so (a digitizer's DMA block) instead of one per few frames. Well inside
/// [`LATE_TOLERANCE`].
const PACED_TIMER_SLACK: Duration = Duration::from_micros(250);
/// How often [`play`] calls its progress callback.
pub const PROGRESS_EVERY: Duration = Duration::from_secs(2);

/// Why live emulation could not start or continue.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// A `--frames` value that is not `udp:HOST:PORT`, `tcp-listen:HOST:PORT` or
    /// `tcp-connect:HOST:PORT`.
    #[error("--frames {text:?}: {reason}")]
    BadTarget {
        /// The value given.
        text: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The UDP socket towards the destination could not be opened.
    #[error("cannot open a UDP socket towards {addr}: {source}")]
    Udp {
        /// Destination.
        addr: SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// The TCP port to serve frames on could not be bound.
    #[error("cannot listen for the daemon on tcp {addr}: {source}")]
    Bind {
        /// Address to listen on.
        addr: SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// Accepting the daemon's connection failed.
    #[error("accepting the daemon's connection on tcp {addr} failed: {source}")]
    Accept {
        /// Listening address.
        addr: SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// No daemon listens at the address (or it cannot be reached).
    #[error("cannot connect to the daemon at tcp {addr}: {source}")]
    Connect {
        /// Address of the daemon.
        addr: SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// Sending frames failed (e.g. the daemon closed the TCP connection).
    #[error("sending digitizer frames to {target} failed after {sent} frames: {source}")]
    Send {
        /// Where frames were going (e.g. `tcp 127.0.0.1:5000`).
        target: String,
        /// Frames sent before the failure.
        sent: u64,
        /// The OS error.
        source: std::io::Error,
    },
    /// A pulse could not be encoded as a frame.
    #[error("pulse {pulse_id} cannot be encoded as a digitizer frame: {source}")]
    Encode {
        /// The digitizer's pulse id.
        pulse_id: u64,
        /// Why.
        source: FrameError,
    },
    /// A pulse's frame is larger than a UDP datagram can carry.
    #[error(
        "pulse {pulse_id} encodes to a {bytes}-byte datagram, above the UDP limit of {UDP_MAX_DATAGRAM} bytes; use --frames tcp-listen:HOST:PORT"
    )]
    DatagramTooLarge {
        /// The digitizer's pulse id.
        pulse_id: u64,
        /// Bytes of the datagram.
        bytes: usize,
    },
    /// The navigation terminal could not be opened.
    #[error("cannot open navigation terminal {path}: {source}")]
    TtyOpen {
        /// The device path.
        path: PathBuf,
        /// The error.
        source: serialport::Error,
    },
    /// A pseudo-terminal pair could not be created.
    #[error("cannot create a pseudo-terminal pair for the navigation output: {source}")]
    Pty {
        /// The error.
        source: serialport::Error,
    },
    /// The link to the pseudo-terminal could not be made.
    #[error("cannot link the navigation terminal {target} at {path}: {source}")]
    Link {
        /// The link path.
        path: PathBuf,
        /// The terminal the link would point at.
        target: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The link path exists and is not a symbolic link.
    #[error(
        "{path} exists and is not a symbolic link; refusing to replace it with the navigation terminal link"
    )]
    LinkExists {
        /// The link path.
        path: PathBuf,
    },
    /// Writing navigation bytes failed (other than for a full terminal buffer).
    #[error("writing navigation bytes to {name} failed: {source}")]
    NavWrite {
        /// The terminal.
        name: String,
        /// The OS error.
        source: std::io::Error,
    },
}

/// Where digitizer frames go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameTarget {
    /// One datagram per pulse to this destination (`udp:HOST:PORT`).
    Udp(SocketAddr),
    /// Serve one TCP stream on this address to the first daemon that connects
    /// (`tcp-listen:HOST:PORT`; port 0 picks a free port, printed at start).
    TcpListen(SocketAddr),
    /// Connect to a daemon listening at this address (`tcp-connect:HOST:PORT`).
    TcpConnect(SocketAddr),
}

impl std::str::FromStr for FrameTarget {
    type Err = LiveError;

    fn from_str(text: &str) -> Result<Self, LiveError> {
        let bad = |reason: String| LiveError::BadTarget {
            text: text.to_string(),
            reason,
        };
        let (scheme, addr) = text.split_once(':').ok_or_else(|| {
            bad("expected udp:HOST:PORT, tcp-listen:HOST:PORT or tcp-connect:HOST:PORT".into())
        })?;
        let resolved = addr
            .to_socket_addrs()
            .map_err(|e| bad(format!("address {addr:?}: {e}")))?
            .next()
            .ok_or_else(|| bad(format!("address {addr:?} resolves to nothing")))?;
        match scheme {
            "udp" => Ok(FrameTarget::Udp(resolved)),
            "tcp-listen" => Ok(FrameTarget::TcpListen(resolved)),
            "tcp-connect" => Ok(FrameTarget::TcpConnect(resolved)),
            other => Err(bad(format!(
                "unknown transport {other:?}; expected udp, tcp-listen or tcp-connect"
            ))),
        }
    }
}

impl std::fmt::Display for FrameTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameTarget::Udp(a) => write!(f, "udp:{a}"),
            FrameTarget::TcpListen(a) => write!(f, "tcp-listen:{a}"),
            FrameTarget::TcpConnect(a) => write!(f, "tcp-connect:{a}"),
        }
    }
}

/// The pacing schedule: when each item is due, as an offset from the start of playback.
///
/// The offset of an item stamped `t` seconds is `(t - t_first) / speed`, computed from the
/// item's own time (never by adding up intervals), so rounding and late wake-ups do not
/// accumulate. Offsets never go backwards: an item stamped before its predecessor (or with a
/// non-finite time) is due with it.
#[derive(Clone, Debug)]
pub struct Pacer {
    speed: f64,
    first_s: Option<f64>,
    last: Duration,
}

impl Pacer {
    /// A schedule at `speed` × real time; 0 (or anything not finite and positive) means as
    /// fast as possible.
    pub fn new(speed: f64) -> Self {
        Pacer {
            speed,
            first_s: None,
            last: Duration::ZERO,
        }
    }

    /// Whether items are paced at all (speed > 0).
    pub fn paced(&self) -> bool {
        self.speed.is_finite() && self.speed > 0.0
    }

    /// Offset from the start of playback at which an item stamped `time_s` (seconds, any
    /// epoch) is due; `None` when not paced.
    pub fn due(&mut self, time_s: f64) -> Option<Duration> {
        if !self.paced() {
            return None;
        }
        if !time_s.is_finite() {
            return Some(self.last);
        }
        let first = *self.first_s.get_or_insert(time_s);
        let offset = Duration::try_from_secs_f64((time_s - first) / self.speed).ok();
        if let Some(o) = offset
            && o > self.last
        {
            self.last = o;
        }
        Some(self.last)
    }
}

/// The time of an item, seconds: a pulse's `gps_time`, a navigation record's receive time.
pub fn item_time_s(item: &SimItem) -> f64 {
    match item {
        SimItem::Pulse(p) => p.gps_time,
        SimItem::Nav {
            receive_time_ns, ..
        } => *receive_time_ns as f64 * 1e-9,
    }
}

/// What a playback did, so far or in the end.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LiveReport {
    /// Pulses sent as frames.
    pub pulses_sent: u64,
    /// Bytes of frames sent (headers included).
    pub frame_bytes: u64,
    /// UDP datagrams the destination refused (nothing listening there yet: ICMP port
    /// unreachable); they are lost, as they would be from a real digitizer.
    pub datagrams_refused: u64,
    /// Pulses not sent because no frame output was given.
    pub pulses_skipped: u64,
    /// Navigation records written.
    pub nav_records: u64,
    /// Navigation bytes written.
    pub nav_bytes: u64,
    /// Navigation bytes dropped because the terminal's buffer was full (nobody reading).
    pub nav_bytes_dropped: u64,
    /// Navigation records not written because no navigation output was given.
    pub nav_skipped: u64,
    /// Items released more than [`LATE_TOLERANCE`] after their due time.
    pub late: u64,
    /// Largest lateness of any item, seconds (0 when not paced).
    pub max_lateness_s: f64,
    /// Wall time from the first item to the last, seconds.
    pub elapsed_s: f64,
    /// Item time covered (last item's time minus the first's), seconds.
    pub stream_s: f64,
    /// Whether a stop request (SIGINT/SIGTERM) ended playback before the stream did.
    pub stopped_early: bool,
}

impl LiveReport {
    /// Items delivered: pulses sent plus navigation records written (wholly or in part).
    pub fn items(&self) -> u64 {
        self.pulses_sent + self.nav_records
    }
}

impl std::fmt::Display for LiveReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} pulses ({} bytes of frames), {} navigation records ({} bytes) in {:.3} s for {:.3} s of stream; {} late (> {} ms), max lateness {:.4} s",
            self.pulses_sent,
            self.frame_bytes,
            self.nav_records,
            self.nav_bytes,
            self.elapsed_s,
            self.stream_s,
            self.late,
            LATE_TOLERANCE.as_millis(),
            self.max_lateness_s
        )?;
        if self.datagrams_refused > 0 {
            write!(
                f,
                "; {} datagrams refused (nothing listening)",
                self.datagrams_refused
            )?;
        }
        if self.nav_bytes_dropped > 0 {
            write!(
                f,
                "; {} navigation bytes dropped (terminal not read)",
                self.nav_bytes_dropped
            )?;
        }
        if self.pulses_skipped > 0 {
            write!(f, "; {} pulses not sent (no --frames)", self.pulses_skipped)?;
        }
        if self.nav_skipped > 0 {
            write!(
                f,
                "; {} navigation records not sent (no navigation output)",
                self.nav_skipped
            )?;
        }
        if self.stopped_early {
            write!(f, "; stopped early")?;
        }
        Ok(())
    }
}

enum FrameConn {
    Udp(UdpSocket),
    Tcp(TcpStream),
}

/// A connected frame output: encodes each pulse into one reused buffer and sends it with the
/// next sequence number.
pub struct FrameOutput {
    conn: FrameConn,
    target: String,
    sequence: u64,
    buf: Vec<u8>,
    /// TCP: encoded frames not yet written (one write for the frames due together).
    pending: Vec<u8>,
    /// Frames in `pending`.
    pending_frames: u64,
    warned_refused: bool,
}

/// TCP: pending frames are written once they reach this many bytes, or before the player
/// sleeps, whichever comes first.
const TCP_BATCH_BYTES: usize = 64 * 1024;

/// A TCP port the emulator serves frames on, waiting for the daemon.
pub struct FrameListener {
    listener: TcpListener,
    addr: SocketAddr,
}

impl FrameListener {
    /// Listens on `addr` (port 0: any free port; see [`local_addr`](Self::local_addr)).
    pub fn bind(addr: SocketAddr) -> Result<Self, LiveError> {
        let bind_err = |source| LiveError::Bind { addr, source };
        let listener = TcpListener::bind(addr).map_err(bind_err)?;
        let addr = listener.local_addr().map_err(bind_err)?;
        listener.set_nonblocking(true).map_err(bind_err)?;
        Ok(FrameListener { listener, addr })
    }

    /// The address actually listened on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Waits for the daemon to connect; `Ok(None)` when `stop` was set first.
    pub fn accept(&self, stop: &AtomicBool) -> Result<Option<FrameOutput>, LiveError> {
        let accept_err = |source| LiveError::Accept {
            addr: self.addr,
            source,
        };
        loop {
            match self.listener.accept() {
                Ok((stream, peer)) => {
                    stream.set_nonblocking(false).map_err(accept_err)?;
                    return tcp_output(stream, format!("tcp {peer} (served on {})", self.addr))
                        .map(Some)
                        .map_err(accept_err);
                }
                Err(e)
                    if e.kind() == ErrorKind::WouldBlock || e.kind() == ErrorKind::Interrupted =>
                {
                    if stop.load(Ordering::Relaxed) {
                        return Ok(None);
                    }
                    std::thread::sleep(STOP_POLL / 2);
                }
                Err(e) => return Err(accept_err(e)),
            }
        }
    }
}

fn tcp_output(stream: TcpStream, target: String) -> std::io::Result<FrameOutput> {
    stream.set_nodelay(true)?;
    stream.set_write_timeout(Some(TCP_WRITE_POLL))?;
    Ok(FrameOutput::new(FrameConn::Tcp(stream), target))
}

impl FrameOutput {
    fn new(conn: FrameConn, target: String) -> Self {
        FrameOutput {
            conn,
            target,
            sequence: 0,
            buf: Vec::new(),
            pending: Vec::new(),
            pending_frames: 0,
            warned_refused: false,
        }
    }

    /// Datagrams to `dest`, from a socket bound to any port of the same address family.
    pub fn udp(dest: SocketAddr) -> Result<Self, LiveError> {
        let err = |source| LiveError::Udp { addr: dest, source };
        let local: SocketAddr = if dest.is_ipv4() {
            (std::net::Ipv4Addr::UNSPECIFIED, 0).into()
        } else {
            (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
        };
        let socket = UdpSocket::bind(local).map_err(err)?;
        socket.connect(dest).map_err(err)?;
        Ok(Self::new(FrameConn::Udp(socket), format!("udp {dest}")))
    }

    /// A TCP stream to a daemon listening at `addr`.
    pub fn tcp_connect(addr: SocketAddr) -> Result<Self, LiveError> {
        let err = |source| LiveError::Connect { addr, source };
        let stream = TcpStream::connect_timeout(&addr, TCP_CONNECT_TIMEOUT).map_err(err)?;
        tcp_output(stream, format!("tcp {addr}")).map_err(err)
    }

    /// Where frames go, for messages.
    pub fn target(&self) -> &str {
        &self.target
    }

    /// Frames sent so far (the next sequence number).
    pub fn sent(&self) -> u64 {
        self.sequence
    }

    /// Encodes one pulse and sends it (UDP: one datagram) or queues it for the next write
    /// ([`FrameOutput::flush`], TCP). Returns `Ok(false)` for a datagram the destination
    /// refused (counted by the caller).
    fn send(&mut self, pulse: &crate::pulse::Pulse) -> Result<bool, LiveError> {
        encode_live_frame(self.sequence, pulse, &mut self.buf).map_err(|source| {
            LiveError::Encode {
                pulse_id: pulse.pulse_id,
                source,
            }
        })?;
        let send_err = |target: &str, sent, source| LiveError::Send {
            target: target.to_string(),
            sent,
            source,
        };
        let delivered = match &mut self.conn {
            FrameConn::Udp(socket) => {
                if self.buf.len() > UDP_MAX_DATAGRAM {
                    return Err(LiveError::DatagramTooLarge {
                        pulse_id: pulse.pulse_id,
                        bytes: self.buf.len(),
                    });
                }
                match socket.send(&self.buf) {
                    Ok(_) => true,
                    Err(e) if e.kind() == ErrorKind::ConnectionRefused => {
                        if !self.warned_refused {
                            tracing::warn!(
                                "{}: nothing listening (datagrams refused); still sending",
                                self.target
                            );
                            self.warned_refused = true;
                        }
                        false
                    }
                    Err(e) => return Err(send_err(&self.target, self.sequence, e)),
                }
            }
            FrameConn::Tcp(_) => {
                // Frames due together go out in one write (a wake-up of the daemon's receiver
                // per batch, not per frame, as a digitizer's DMA blocks arrive).
                self.pending.extend_from_slice(&self.buf);
                self.pending_frames += 1;
                true
            }
        };
        // The sequence advances for refused datagrams too: they are frames lost on the way.
        self.sequence += 1;
        Ok(delivered)
    }

    fn bytes_in_buffer(&self) -> usize {
        self.buf.len()
    }

    /// Whether the pending frames fill a batch (then they are written before the next item).
    fn batch_full(&self) -> bool {
        self.pending.len() >= TCP_BATCH_BYTES
    }

    /// TCP: writes the pending frames. Returns how many of them were not written because
    /// `stop` cut the write short (0 otherwise, and always for UDP, which sends at once).
    fn flush(&mut self, stop: &AtomicBool) -> Result<u64, LiveError> {
        let FrameConn::Tcp(stream) = &mut self.conn else {
            return Ok(0);
        };
        let frames = std::mem::take(&mut self.pending_frames);
        let mut off = 0;
        let result = loop {
            if off >= self.pending.len() {
                break Ok(0);
            }
            match stream.write(&self.pending[off..]) {
                Ok(0) => break Err(ErrorKind::WriteZero.into()),
                Ok(n) => off += n,
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                    ) =>
                {
                    if stop.load(Ordering::Relaxed) {
                        break Ok(frames);
                    }
                }
                Err(e) => break Err(e),
            }
        };
        self.pending.clear();
        result.map_err(|source| LiveError::Send {
            target: self.target.clone(),
            sent: self.sequence - frames,
            source,
        })
    }
}

/// The terminal navigation bytes are written to.
pub struct NavOutput {
    port: TTYPort,
    /// The slave of a created pair, held open so the terminal stays up (and keeps its raw
    /// settings) while daemons open and close it; also tells how much is left unread.
    slave: Option<TTYPort>,
    /// The symlink made for a created pair, removed at the end.
    link: Option<PathBuf>,
    name: String,
}

impl NavOutput {
    /// Opens an existing terminal device (e.g. one end of a `socat` pty pair) for writing at
    /// `baud` (bits per second; meaningless for a pseudo-terminal but set on a real port).
    pub fn open_tty(path: &Path, baud: u32) -> Result<Self, LiveError> {
        let err = |source| LiveError::TtyOpen {
            path: path.to_path_buf(),
            source,
        };
        let mut port = serialport::new(path.to_string_lossy(), baud)
            .timeout(Duration::ZERO)
            .open_native()
            .map_err(err)?;
        // Do not keep other openers of the device out.
        port.set_exclusive(false).map_err(err)?;
        Ok(NavOutput {
            port,
            slave: None,
            link: None,
            name: path.display().to_string(),
        })
    }

    /// Creates a pseudo-terminal pair (raw mode) and symlinks its slave at `link`, which a
    /// daemon then opens as its serial device. An existing symlink at `link` (from an earlier
    /// run) is replaced; any other existing file is refused.
    pub fn create_pty_link(link: &Path) -> Result<Self, LiveError> {
        let (mut master, slave) = TTYPort::pair().map_err(|source| LiveError::Pty { source })?;
        master
            .set_timeout(Duration::ZERO)
            .map_err(|source| LiveError::Pty { source })?;
        let slave_name = slave.name().unwrap_or_default();
        let link_err = |source| LiveError::Link {
            path: link.to_path_buf(),
            target: slave_name.clone(),
            source,
        };
        match std::fs::symlink_metadata(link) {
            Ok(m) if m.file_type().is_symlink() => std::fs::remove_file(link).map_err(link_err)?,
            Ok(_) => {
                return Err(LiveError::LinkExists {
                    path: link.to_path_buf(),
                });
            }
            Err(e) if e.kind() == ErrorKind::NotFound => {}
            Err(e) => return Err(link_err(e)),
        }
        std::os::unix::fs::symlink(&slave_name, link).map_err(link_err)?;
        Ok(NavOutput {
            port: master,
            slave: Some(slave),
            link: Some(link.to_path_buf()),
            name: format!("{} (linked at {})", slave_name, link.display()),
        })
    }

    /// The terminal, for messages (the slave's name and its link for a created pair).
    pub fn describe(&self) -> &str {
        &self.name
    }

    /// Writes what fits now; returns the bytes dropped because the terminal's buffer is full.
    fn write(&mut self, bytes: &[u8]) -> Result<u64, LiveError> {
        let mut off = 0;
        while off < bytes.len() {
            match self.port.write(&bytes[off..]) {
                Ok(0) => break,
                Ok(n) => off += n,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => break,
                Err(source) => {
                    return Err(LiveError::NavWrite {
                        name: self.name.clone(),
                        source,
                    });
                }
            }
        }
        Ok((bytes.len() - off) as u64)
    }

    /// Waits (up to [`NAV_DRAIN_TIMEOUT`], or until `stop`) for the reader to take what was
    /// written, so that closing the terminal does not discard the last bytes. Bytes written
    /// reach the terminal's input queue asynchronously (the kernel pushes them from a work
    /// queue), so an empty queue counts only when seen empty on several polls after a settling
    /// time.
    fn drain(&self, stop: &AtomicBool) {
        const SETTLE: Duration = Duration::from_millis(50);
        const POLL: Duration = Duration::from_millis(10);
        const EMPTY_POLLS: u32 = 3;
        let began = Instant::now();
        let pending = || match &self.slave {
            Some(s) => s.bytes_to_read().unwrap_or(0),
            None => self.port.bytes_to_write().unwrap_or(0),
        };
        let mut empty = 0;
        while began.elapsed() < NAV_DRAIN_TIMEOUT && !stop.load(Ordering::Relaxed) {
            empty = if pending() == 0 { empty + 1 } else { 0 };
            if empty >= EMPTY_POLLS && began.elapsed() >= SETTLE {
                return;
            }
            std::thread::sleep(POLL);
        }
    }
}

impl Drop for NavOutput {
    fn drop(&mut self) {
        // Remove the link only if it still points at this terminal.
        if let (Some(link), Some(slave)) = (&self.link, &self.slave)
            && let (Ok(target), Some(name)) = (std::fs::read_link(link), slave.name())
            && target == Path::new(&name)
        {
            let _ = std::fs::remove_file(link);
        }
    }
}

/// Sleeps until `deadline` in slices of at most [`STOP_POLL`]; returns false when `stop` was
/// set first.
fn wait_until(deadline: Instant, stop: &AtomicBool) -> bool {
    loop {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let now = Instant::now();
        if now >= deadline {
            return true;
        }
        std::thread::sleep((deadline - now).min(STOP_POLL));
    }
}

/// Sets the calling thread's timer slack (how late the kernel may end its sleeps). Best effort:
/// on failure the default slack (50 µs) stays, which only costs more wake-ups.
fn set_timer_slack(slack: Duration) {
    // SAFETY: prctl(PR_SET_TIMERSLACK) takes an integer and affects only the calling thread.
    unsafe {
        libc::prctl(
            libc::PR_SET_TIMERSLACK,
            slack.as_nanos() as libc::c_ulong,
            0 as libc::c_ulong,
            0 as libc::c_ulong,
            0 as libc::c_ulong,
        );
    }
}

/// Plays `items` in real time (see the module documentation) into the given outputs until the
/// stream ends or `stop` is set. `progress` is called every [`PROGRESS_EVERY`] with the report
/// so far. The clock starts at the first item.
pub fn play<I>(
    items: I,
    mut frames: Option<&mut FrameOutput>,
    mut nav: Option<&mut NavOutput>,
    speed: f64,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(&LiveReport),
) -> Result<LiveReport, LiveError>
where
    I: IntoIterator<Item = SimItem>,
{
    let mut pacer = Pacer::new(speed);
    if pacer.paced() {
        set_timer_slack(PACED_TIMER_SLACK);
    }
    let mut report = LiveReport::default();
    let mut start: Option<Instant> = None;
    let mut first_s: Option<f64> = None;
    let mut next_progress = PROGRESS_EVERY;
    let mut max_lateness = Duration::ZERO;
    for item in items {
        if stop.load(Ordering::Relaxed) {
            report.stopped_early = true;
            break;
        }
        let t = item_time_s(&item);
        let start = *start.get_or_insert_with(Instant::now);
        if t.is_finite() {
            let first = *first_s.get_or_insert(t);
            report.stream_s = report.stream_s.max(t - first);
        }
        if let Some(offset) = pacer.due(t) {
            let deadline = start + offset;
            if Instant::now() < deadline
                && let Some(out) = frames.as_deref_mut()
            {
                // Everything due so far goes out before the player sleeps.
                report.pulses_sent -= out.flush(stop)?;
            }
            if !wait_until(deadline, stop) {
                report.stopped_early = true;
                break;
            }
            let lateness = Instant::now().saturating_duration_since(deadline);
            if lateness > LATE_TOLERANCE {
                report.late += 1;
            }
            max_lateness = max_lateness.max(lateness);
        }
        match item {
            SimItem::Pulse(pulse) => match frames.as_deref_mut() {
                Some(out) => {
                    if out.send(&pulse)? {
                        report.pulses_sent += 1;
                        report.frame_bytes += out.bytes_in_buffer() as u64;
                        if out.batch_full() {
                            report.pulses_sent -= out.flush(stop)?;
                        }
                    } else if stop.load(Ordering::Relaxed) {
                        report.stopped_early = true;
                        break;
                    } else {
                        report.datagrams_refused += 1;
                    }
                }
                None => report.pulses_skipped += 1,
            },
            SimItem::Nav { bytes, .. } => match nav.as_deref_mut() {
                Some(out) => {
                    // The frames before this record leave first, as they were due.
                    if let Some(f) = frames.as_deref_mut() {
                        report.pulses_sent -= f.flush(stop)?;
                    }
                    let dropped = out.write(&bytes)?;
                    report.nav_records += 1;
                    report.nav_bytes += bytes.len() as u64 - dropped;
                    report.nav_bytes_dropped += dropped;
                }
                None => report.nav_skipped += 1,
            },
        }
        let elapsed = start.elapsed();
        if elapsed >= next_progress {
            report.elapsed_s = elapsed.as_secs_f64();
            report.max_lateness_s = max_lateness.as_secs_f64();
            progress(&report);
            next_progress = elapsed + PROGRESS_EVERY;
        }
    }
    if let Some(out) = frames {
        report.pulses_sent -= out.flush(stop)?;
    }
    report.elapsed_s = start.map_or(0.0, |s| s.elapsed().as_secs_f64());
    report.max_lateness_s = max_lateness.as_secs_f64();
    if let Some(out) = nav.as_deref() {
        out.drain(stop);
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn secs(d: Option<Duration>) -> f64 {
        d.expect("paced").as_secs_f64()
    }

    #[test]
    fn due_times_are_relative_to_the_first_item_and_scaled_by_speed() {
        let mut p = Pacer::new(1.0);
        assert_eq!(secs(p.due(345_600.0)), 0.0);
        assert!((secs(p.due(345_600.25)) - 0.25).abs() < 1e-9);
        assert!((secs(p.due(345_601.0)) - 1.0).abs() < 1e-9);
        let mut fast = Pacer::new(4.0);
        fast.due(10.0);
        assert!((secs(fast.due(12.0)) - 0.5).abs() < 1e-12);
        let mut slow = Pacer::new(0.5);
        slow.due(10.0);
        assert!((secs(slow.due(12.0)) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn speed_zero_is_unpaced() {
        for speed in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let mut p = Pacer::new(speed);
            assert!(!p.paced());
            assert_eq!(p.due(1.0), None);
            assert_eq!(p.due(2.0), None);
        }
    }

    #[test]
    fn due_times_never_go_backwards_and_survive_bad_times() {
        let mut p = Pacer::new(1.0);
        p.due(100.0);
        assert!((secs(p.due(101.0)) - 1.0).abs() < 1e-9);
        // Earlier, NaN, infinite: due with the previous item.
        assert!((secs(p.due(100.5)) - 1.0).abs() < 1e-9);
        assert!((secs(p.due(f64::NAN)) - 1.0).abs() < 1e-9);
        assert!((secs(p.due(f64::INFINITY)) - 1.0).abs() < 1e-9);
        assert!((secs(p.due(-1e300)) - 1.0).abs() < 1e-9);
        // A time too far ahead for a Duration does not panic either.
        assert!((secs(p.due(1e300)) - 1.0).abs() < 1e-9);
        assert!((secs(p.due(102.0)) - 2.0).abs() < 1e-9);
    }

    #[test]
    fn the_schedule_does_not_drift_over_many_items() {
        // 50 kHz for 10 minutes: the due time of the last pulse is its own time, exactly as
        // computed from it, with no error accumulated over 30 million intervals.
        let mut p = Pacer::new(1.0);
        let t0 = 345_600.0;
        let n = 30_000_000u64;
        p.due(t0);
        let mut last = Duration::ZERO;
        for k in (0..n).step_by(9973) {
            last = p.due(t0 + k as f64 / 50_000.0).unwrap();
        }
        let k_last = (0..n).step_by(9973).last().unwrap();
        let want = k_last as f64 / 50_000.0;
        assert!(
            (last.as_secs_f64() - want).abs() < 1e-6,
            "{last:?} vs {want}"
        );
    }

    #[test]
    fn frame_targets_parse_and_bad_ones_name_the_problem() {
        assert_eq!(
            "udp:127.0.0.1:9000".parse::<FrameTarget>().unwrap(),
            FrameTarget::Udp("127.0.0.1:9000".parse().unwrap())
        );
        assert_eq!(
            "tcp-listen:127.0.0.1:0".parse::<FrameTarget>().unwrap(),
            FrameTarget::TcpListen("127.0.0.1:0".parse().unwrap())
        );
        let t = "tcp-connect:[::1]:7".parse::<FrameTarget>().unwrap();
        assert_eq!(t.to_string(), "tcp-connect:[::1]:7");
        for bad in [
            "127.0.0.1:9000",
            "serial:127.0.0.1:9",
            "udp:nonsense",
            "udp",
        ] {
            let e = bad.parse::<FrameTarget>().unwrap_err().to_string();
            assert!(e.starts_with(&format!("--frames {bad:?}")), "{e}");
        }
    }

    #[test]
    fn play_paces_items_and_counts_what_it_could_not_send() {
        // No outputs: everything is counted as skipped, and pacing still holds the clock.
        let items = (0..5u64).map(|k| SimItem::Nav {
            receive_time_ns: 1_000_000_000 + k * 10_000_000,
            bytes: b"$GPGGA\r\n".to_vec(),
        });
        let stop = AtomicBool::new(false);
        let t = Instant::now();
        let r = play(items, None, None, 1.0, &stop, &mut |_| {}).unwrap();
        assert!(t.elapsed() >= Duration::from_millis(40));
        assert_eq!(r.nav_skipped, 5);
        assert!((r.stream_s - 0.04).abs() < 1e-9);
        assert!(!r.stopped_early);
        // A stop request ends playback before the next item.
        stop.store(true, Ordering::Relaxed);
        let items = (0..5u64).map(|k| SimItem::Nav {
            receive_time_ns: k,
            bytes: Vec::new(),
        });
        let r = play(items, None, None, 0.0, &stop, &mut |_| {}).unwrap();
        assert!(r.stopped_early);
        assert_eq!(r.items() + r.nav_skipped, 0);
    }

    #[test]
    fn paced_play_lets_the_kernel_coalesce_its_wake_ups_and_unpaced_does_not() {
        // SAFETY: PR_GET_TIMERSLACK reads the calling thread's slack.
        let slack = || unsafe { libc::prctl(libc::PR_GET_TIMERSLACK, 0, 0, 0, 0) } as u128;
        let play_in_thread = |speed: f64| {
            std::thread::spawn(move || {
                let stop = AtomicBool::new(false);
                let items = (0..2u64).map(|k| SimItem::Nav {
                    receive_time_ns: k * 1_000_000,
                    bytes: Vec::new(),
                });
                play(items, None, None, speed, &stop, &mut |_| {}).unwrap();
                slack()
            })
            .join()
            .unwrap()
        };
        assert_eq!(play_in_thread(1.0), PACED_TIMER_SLACK.as_nanos());
        assert_eq!(play_in_thread(0.0), Duration::from_micros(50).as_nanos());
    }

    /// A framed test pulse stamped `t` s.
    fn pulse_at(id: u64, t: f64) -> crate::pulse::Pulse {
        crate::pulse::Pulse {
            gps_time: t,
            ..crate::pulse::testing::framed_pulse(id, 32)
        }
    }

    /// Frames read from `s` until `want` arrived or 5 s passed, with how many reads it took.
    fn read_frames(s: &mut TcpStream, want: usize) -> (Vec<u64>, usize) {
        use crate::source::live_frames::{StreamDecoder, StreamItem};
        s.set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        let mut dec = StreamDecoder::new();
        let (mut seqs, mut reads) = (Vec::new(), 0);
        let t = Instant::now();
        while seqs.len() < want && t.elapsed() < Duration::from_secs(5) {
            match dec.read_from(s) {
                Ok(0) => break,
                Ok(_) => reads += 1,
                Err(_) => continue,
            }
            while let Some(item) = dec.next_item() {
                if let StreamItem::Frame(f) = item {
                    seqs.push(f.sequence);
                }
            }
        }
        (seqs, reads)
    }

    #[test]
    fn tcp_frames_wait_for_the_flush_and_leave_together() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let mut out = FrameOutput::tcp_connect(listener.local_addr().unwrap()).unwrap();
        let (mut rx, _) = listener.accept().unwrap();
        for k in 0..3 {
            assert!(out.send(&pulse_at(k, 100.0)).unwrap());
        }
        // Queued, not written: nothing to read yet.
        rx.set_nonblocking(true).unwrap();
        let mut b = [0u8; 16];
        let e = std::io::Read::read(&mut rx, &mut b).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::WouldBlock);
        rx.set_nonblocking(false).unwrap();
        assert_eq!(out.flush(&AtomicBool::new(false)).unwrap(), 0);
        assert_eq!(read_frames(&mut rx, 3).0, vec![0, 1, 2]);
    }

    #[test]
    fn play_writes_what_is_due_before_it_sleeps_and_the_rest_at_the_end() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let mut out = FrameOutput::tcp_connect(listener.local_addr().unwrap()).unwrap();
        let (mut rx, _) = listener.accept().unwrap();
        // Ten pulses due at once, then one a second later.
        let items: Vec<SimItem> = (0..10u64)
            .map(|k| SimItem::Pulse(pulse_at(k, 100.0)))
            .chain(std::iter::once(SimItem::Pulse(pulse_at(10, 101.0))))
            .collect();
        let stop = AtomicBool::new(false);
        let started = Instant::now();
        let reader = std::thread::spawn(move || {
            let first = read_frames(&mut rx, 10).0;
            let first_at = started.elapsed();
            (first, first_at, read_frames(&mut rx, 1).0)
        });
        let r = play(items, Some(&mut out), None, 1.0, &stop, &mut |_| {}).unwrap();
        assert_eq!(r.pulses_sent, 11);
        let (first, first_at, rest) = reader.join().unwrap();
        assert_eq!(first, (0..10).collect::<Vec<u64>>());
        // The ten went out while the player waited for the eleventh, not at the end.
        assert!(first_at < Duration::from_millis(900), "{first_at:?}");
        assert_eq!(rest, vec![10]);
    }
}
