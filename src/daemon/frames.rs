//! The frame receiver: digitizer frames from the network (UDP datagrams, or a TCP stream the
//! daemon listens for or connects to), checked (`source::live_frames`) and handed to the
//! recorder over a bounded channel that **blocks** when full — the recording never drops a
//! frame it received; a sender outrunning the disk is slowed by TCP, or overflows the kernel's
//! UDP buffer, and the sequence numbers count what was lost.
//!
//! A UDP input asks the kernel for a 64 MiB receive buffer (beyond `net.core.rmem_max` with
//! CAP_NET_ADMIN, else up to it, with a warning): the default buffer held 5 ms of a 100 kHz
//! stream and lost 9.5 % of its frames before they could be recorded.
//!
//! An input that is not there (nothing listening yet, address in use, peer gone) is reported
//! down and retried every `retry_ms`, forever: on an aircraft, devices power up in any order.
//! Payload buffers come back from the recorder on a free list, so a running receiver does not
//! allocate per frame.

use std::io::ErrorKind;
use std::net::{TcpListener, TcpStream, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, bounded};

use super::{FrameInput, InputState, now_ns};
use crate::core::nap::Napper;
use crate::source::live_frames::{
    LiveFrameError, READ_CHUNK, SequenceTracker, StreamDecoder, StreamItem, UDP_MAX_DATAGRAM,
    parse_datagram,
};

/// One received frame: the digitizer frame payload (header stripped, CRCs checked).
pub struct FrameMsg {
    /// The capture DigitizerFrame payload (`crate::format::frame`).
    pub payload: Vec<u8>,
    /// When it was received (the start of its end-to-end latency).
    pub received: Instant,
    /// Host receive time, ns since the Unix epoch.
    pub receive_ns: u64,
    /// The sender's sequence number.
    pub sequence: u64,
}

/// How long a blocked wait lasts before the stop flag is looked at again.
const POLL: Duration = Duration::from_millis(100);

/// The running receiver.
pub struct FrameReceiver {
    thread: Option<JoinHandle<()>>,
    stop: Arc<AtomicBool>,
}

impl FrameReceiver {
    /// Starts receiving from `input` on a new thread; frames go to `tx`, used payload buffers
    /// come back on `free`.
    pub fn spawn(
        input: FrameInput,
        retry: Duration,
        tx: Sender<FrameMsg>,
        free: Receiver<Vec<u8>>,
        state: Arc<InputState>,
    ) -> std::io::Result<FrameReceiver> {
        let stop = Arc::new(AtomicBool::new(false));
        let mut rx = Reader {
            tx,
            free,
            state,
            stop: stop.clone(),
            seq: SequenceTracker::new(),
            retry,
        };
        let thread = std::thread::Builder::new()
            .name("frames".into())
            .spawn(move || rx.run(input))?;
        Ok(FrameReceiver {
            thread: Some(thread),
            stop,
        })
    }

    /// Stops receiving (within about 100 ms).
    pub fn stop(mut self) {
        self.halt();
    }

    fn halt(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for FrameReceiver {
    fn drop(&mut self) {
        self.halt();
    }
}

/// Both ends of a bounded channel.
pub type Channel<T> = (Sender<T>, Receiver<T>);

/// A pair of bounded channels for frames and their recycled buffers, `capacity` frames.
pub fn channels(capacity: usize) -> (Channel<FrameMsg>, Channel<Vec<u8>>) {
    (bounded(capacity), bounded(capacity))
}

struct Reader {
    tx: Sender<FrameMsg>,
    free: Receiver<Vec<u8>>,
    state: Arc<InputState>,
    stop: Arc<AtomicBool>,
    seq: SequenceTracker,
    retry: Duration,
}

impl Reader {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    fn run(&mut self, input: FrameInput) {
        while !self.stopped() {
            let result = match input {
                FrameInput::Udp(addr) => self.udp(addr),
                FrameInput::TcpListen(addr) => self.tcp_listen(addr),
                FrameInput::TcpConnect(addr) => self.tcp_connect(addr),
            };
            self.state.up.store(false, Ordering::Relaxed);
            if let Err(e) = result {
                self.state.failed.fetch_add(1, Ordering::Relaxed);
                self.state.error(format!("frame input {input}: {e}"));
                self.sleep(self.retry);
            }
        }
    }

    fn sleep(&self, d: Duration) {
        let until = Instant::now() + d;
        while !self.stopped() && Instant::now() < until {
            std::thread::sleep(POLL.min(until.saturating_duration_since(Instant::now())));
        }
    }

    fn udp(&mut self, addr: std::net::SocketAddr) -> std::io::Result<()> {
        let sock = UdpSocket::bind(addr)?;
        sock.set_read_timeout(Some(POLL))?;
        let rcvbuf = enlarge_receive_buffer(&sock);
        if rcvbuf < UDP_RECEIVE_BUFFER / 2 {
            tracing::warn!(
                %addr,
                bytes = rcvbuf,
                "the kernel gave the UDP socket a small receive buffer: frames are lost when \
                 the receiver is held up for more than a few ms (raise net.core.rmem_max, or run \
                 with CAP_NET_ADMIN)"
            );
        } else {
            tracing::info!(%addr, bytes = rcvbuf, "UDP receive buffer");
        }
        self.state.connects.fetch_add(1, Ordering::Relaxed);
        self.state.up.store(true, Ordering::Relaxed);
        tracing::info!(%addr, "receiving digitizer frames (UDP)");
        let mut buf = vec![0u8; UDP_MAX_DATAGRAM];
        // As for TCP (`core::nap`): when the socket is drained the receiver naps instead of
        // blocking, so that the datagrams of the next half millisecond gather in the kernel's
        // buffer and are read back to back, instead of a wake-up per datagram (measured: 27 000
        // context switches a second at 200 kHz). The datagrams read right after a nap are
        // stamped received when it began (overstated by at most a nap, never understated).
        let mut napper = Napper::new();
        let mut napped_at: Option<Instant> = None;
        while !self.stopped() {
            let got = if napper.quiet() {
                sock.recv(&mut buf)
            } else {
                recv_now(&sock, &mut buf)
            };
            let n = match got {
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock && !napper.quiet() => {
                    napped_at = Some(Instant::now());
                    napper.nap();
                    continue;
                }
                Err(e) => {
                    napped_at = None;
                    retryable(e)?;
                    continue;
                }
            };
            napper.active();
            let now = Instant::now();
            let received = match napped_at {
                Some(t) if now.duration_since(t) <= 2 * crate::core::nap::NAP => t,
                _ => {
                    napped_at = None;
                    now
                }
            };
            self.state.data(n);
            match parse_datagram(&buf[..n]) {
                Ok(f) => {
                    let payload = recycled(&self.free, f.payload);
                    if !self.deliver(f.sequence, payload, received) {
                        return Ok(());
                    }
                }
                Err(e) => {
                    self.state
                        .skipped_bytes
                        .fetch_add(n as u64, Ordering::Relaxed);
                    self.state
                        .error(format!("frame input udp {addr}: datagram rejected: {e}"));
                }
            }
        }
        Ok(())
    }

    /// Hands one frame to the recorder, waiting for room (never dropping). False when stopped.
    fn deliver(&mut self, sequence: u64, payload: Vec<u8>, received: Instant) -> bool {
        self.seq.observe(sequence);
        self.state.lost.store(self.seq.lost, Ordering::Relaxed);
        self.state.frames.fetch_add(1, Ordering::Relaxed);
        let mut msg = FrameMsg {
            payload,
            received,
            receive_ns: now_ns(),
            sequence,
        };
        loop {
            match self.tx.send_timeout(msg, POLL) {
                Ok(()) => return true,
                Err(crossbeam_channel::SendTimeoutError::Timeout(m)) => {
                    if self.stopped() {
                        return false;
                    }
                    msg = m;
                }
                Err(crossbeam_channel::SendTimeoutError::Disconnected(_)) => return false,
            }
        }
    }

    fn tcp_listen(&mut self, addr: std::net::SocketAddr) -> std::io::Result<()> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        tracing::info!(%addr, "waiting for the digitizer's TCP connection");
        while !self.stopped() {
            match listener.accept() {
                Ok((stream, peer)) => {
                    tracing::info!(%peer, "digitizer connected");
                    let r = self.stream(stream, &format!("tcp-listen {addr} (peer {peer})"));
                    self.state.up.store(false, Ordering::Relaxed);
                    if let Err(e) = r {
                        self.state
                            .error(format!("frame input tcp-listen {addr}: peer {peer}: {e}"));
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(POLL),
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    fn tcp_connect(&mut self, addr: std::net::SocketAddr) -> std::io::Result<()> {
        let stream = TcpStream::connect_timeout(&addr, self.retry.max(POLL))?;
        tracing::info!(%addr, "connected to the digitizer");
        let r = self.stream(stream, &format!("tcp-connect {addr}"));
        self.state.up.store(false, Ordering::Relaxed);
        r?;
        // The digitizer closed the stream: try again after the retry interval.
        if !self.stopped() {
            self.state.error(format!(
                "frame input tcp-connect {addr}: the digitizer closed the stream"
            ));
            self.sleep(self.retry);
        }
        Ok(())
    }

    /// Reads frames from one TCP stream until it ends, fails or the receiver is stopped.
    fn stream(&mut self, mut s: TcpStream, what: &str) -> std::io::Result<()> {
        s.set_nonblocking(false)?;
        s.set_read_timeout(Some(POLL))?;
        let _ = s.set_nodelay(true);
        self.state.connects.fetch_add(1, Ordering::Relaxed);
        self.state.up.store(true, Ordering::Relaxed);
        let mut dec = StreamDecoder::new();
        // After a read that drained the socket, a nap lets the next frames gather so that one
        // read takes a batch, instead of a wake-up per TCP segment (`core::nap`); the frames of
        // a read after a nap are stamped received when the nap began (the latency overstated
        // by at most a nap, never understated).
        let mut napper = Napper::new();
        let mut napped_at: Option<Instant> = None;
        while !self.stopped() {
            let n = match dec.read_from(&mut s) {
                Ok(0) => {
                    if let Some(e) = dec.finish() {
                        self.note_skip(e, what);
                    }
                    return Ok(());
                }
                Ok(n) => n,
                Err(e) => {
                    napped_at = None;
                    retryable(e)?;
                    continue;
                }
            };
            let received = napped_at.take().unwrap_or_else(Instant::now);
            self.state.data(n);
            loop {
                let (seq, buf) = match dec.next_item() {
                    None => break,
                    Some(StreamItem::Frame(f)) => (f.sequence, recycled(&self.free, f.payload)),
                    Some(StreamItem::Skipped { bytes, reason }) => {
                        self.state
                            .skipped_bytes
                            .fetch_add(bytes as u64, Ordering::Relaxed);
                        self.note_skip(reason, what);
                        continue;
                    }
                };
                if !self.deliver(seq, buf, received) {
                    return Ok(());
                }
            }
            napper.active();
            if n < READ_CHUNK {
                napped_at = Some(Instant::now());
                napper.nap();
            }
        }
        Ok(())
    }

    fn note_skip(&self, e: LiveFrameError, what: &str) {
        self.state
            .error(format!("frame input {what}: bytes skipped: {e}"));
    }
}

/// One datagram from `sock` if one is waiting, else `WouldBlock` at once (the socket stays in
/// blocking mode for the reads after the input has gone quiet).
fn recv_now(sock: &UdpSocket, buf: &mut [u8]) -> std::io::Result<usize> {
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: `buf` is valid for `buf.len()` bytes of writes; the descriptor is `sock`'s.
        let n = unsafe {
            libc::recv(
                sock.as_raw_fd(),
                buf.as_mut_ptr().cast(),
                buf.len(),
                libc::MSG_DONTWAIT,
            )
        };
        if n < 0 {
            Err(std::io::Error::last_os_error())
        } else {
            Ok(n as usize)
        }
    }
    #[cfg(not(unix))]
    {
        sock.recv(buf)
    }
}

/// Receive buffer asked of the kernel for a UDP frame input, bytes: 64 MiB hold ~0.4 s of frames
/// at 400 kHz (~400 bytes a frame). The default (~208 KiB) holds 5 ms at 100 kHz, and measured
/// on this project's 2-core machine, 9.5 % of the frames of a 100 kHz stream were lost in the
/// kernel before the receiver read them (docs/performance.md).
const UDP_RECEIVE_BUFFER: usize = 64 << 20;

/// Asks for [`UDP_RECEIVE_BUFFER`] bytes of receive buffer on `sock` — beyond
/// `net.core.rmem_max` when the process may (`SO_RCVBUFFORCE`, CAP_NET_ADMIN), else up to it —
/// and returns what the kernel gave (bytes; 0 when it cannot be read).
fn enlarge_receive_buffer(sock: &UdpSocket) -> usize {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let fd = sock.as_raw_fd();
        let want = UDP_RECEIVE_BUFFER as libc::c_int;
        let len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
        let set = |opt: libc::c_int| {
            // SAFETY: setsockopt(2) on our own open socket with a pointer to an int we own.
            unsafe {
                libc::setsockopt(
                    fd,
                    libc::SOL_SOCKET,
                    opt,
                    (&want as *const libc::c_int).cast(),
                    len,
                )
            }
        };
        if set(libc::SO_RCVBUFFORCE) != 0 {
            let _ = set(libc::SO_RCVBUF);
        }
    }
    receive_buffer(sock)
}

/// The receive buffer the kernel gives `sock`, bytes as `SO_RCVBUF` reports it (twice what was
/// set: its bookkeeping included); 0 when it cannot be read.
fn receive_buffer(sock: &UdpSocket) -> usize {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let mut got: libc::c_int = 0;
        let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
        // SAFETY: getsockopt(2) on our own open socket into an int we own, its size given.
        let rc = unsafe {
            libc::getsockopt(
                sock.as_raw_fd(),
                libc::SOL_SOCKET,
                libc::SO_RCVBUF,
                (&mut got as *mut libc::c_int).cast(),
                &mut len,
            )
        };
        if rc == 0 { got.max(0) as usize } else { 0 }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = sock;
        0
    }
}

/// What a read that failed means: `Ok(())` to read again (timeout, interruption), the error
/// otherwise.
fn retryable(e: std::io::Error) -> std::io::Result<()> {
    match e.kind() {
        ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted => Ok(()),
        _ => Err(e),
    }
}

/// `bytes` in a buffer from the free list (allocated only while the list is empty).
fn recycled(free: &Receiver<Vec<u8>>, bytes: &[u8]) -> Vec<u8> {
    let mut buf = free.try_recv().unwrap_or_default();
    buf.clear();
    buf.extend_from_slice(bytes);
    buf
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn a_udp_frame_input_asks_for_a_large_receive_buffer() {
        let plain = UdpSocket::bind("127.0.0.1:0").unwrap();
        let before = receive_buffer(&plain);
        assert!(before > 0, "SO_RCVBUF readable");
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        let got = enlarge_receive_buffer(&sock);
        assert!(got >= before, "{got} < the default {before}");
        // With CAP_NET_ADMIN (root, as CI runs) the kernel's cap does not apply: the whole
        // request is given (reported doubled).
        // SAFETY: geteuid(2) has no preconditions.
        if unsafe { libc::geteuid() } == 0 {
            assert!(got >= UDP_RECEIVE_BUFFER, "{got} < {UDP_RECEIVE_BUFFER}");
        }
    }
}
