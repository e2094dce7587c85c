//! `fwlidar simulate --live` end to end, with no mocks: the real binary sends digitizer frames
//! over real loopback sockets (UDP datagrams, a TCP stream it serves) and navigation bytes into
//! real pseudo-terminals; the frames are read back with `source::live_frames` and compared with
//! the capture `fwlidar simulate --out` writes for the same scene.

use std::io::{BufRead, BufReader, ErrorKind, Read};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc::{Receiver, channel};
use std::time::{Duration, Instant};

use fwlidar::format::frame::decode_frame;
use fwlidar::format::{CaptureReader, Record};
use fwlidar::pulse::Pulse;
use fwlidar::source::live_frames::{StreamDecoder, StreamItem, parse_datagram};
use serialport::{SerialPort, TTYPort};

const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");

fn scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes/two_layer.toml")
}

/// What `fwlidar simulate --out` writes for the scene: frame payloads, navigation records.
fn capture(dir: &Path, pulses: u64) -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
    capture_of(&scene(), dir, pulses)
}

/// As [`capture`], for any scene.
fn capture_of(scene: &Path, dir: &Path, pulses: u64) -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let path = dir.join("reference.fwcap");
    let out = Command::new(BIN)
        .args(["simulate", "--no-progress", "--no-truth-voxels", "--scene"])
        .arg(scene)
        .args(["--pulses", &pulses.to_string(), "--out"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let mut reader = CaptureReader::open(&path).unwrap();
    let (mut frames, mut nav) = (Vec::new(), Vec::new());
    while let Some(record) = reader.next_record() {
        match record.unwrap() {
            Record::Frame(f) => frames.push(f.payload().to_vec()),
            Record::Nav { bytes, .. } => nav.push(bytes.to_vec()),
            Record::Header(_) => {}
        }
    }
    assert!(reader.skipped().is_clean());
    assert_eq!(frames.len() as u64, pulses);
    assert!(!nav.is_empty());
    (frames, nav)
}

/// Starts `fwlidar simulate --live` with `args`; its stdout lines arrive on the receiver.
fn spawn_live(pulses: u64, speed: &str, args: &[&str]) -> (Child, Receiver<String>) {
    spawn_live_of(&scene(), pulses, speed, args)
}

/// As [`spawn_live`], for any scene.
fn spawn_live_of(
    scene: &Path,
    pulses: u64,
    speed: &str,
    args: &[&str],
) -> (Child, Receiver<String>) {
    let mut child = Command::new(BIN)
        .args(["simulate", "--live", "--no-progress", "--scene"])
        .arg(scene)
        .args(["--pulses", &pulses.to_string(), "--speed", speed])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

/// Waits for the child; returns its stdout lines after those already taken, and stderr.
fn finish(mut child: Child, lines: Receiver<String>) -> (std::process::ExitStatus, String, String) {
    let status = child.wait().unwrap();
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let out: Vec<String> = lines.iter().collect();
    (status, out.join("\n"), err)
}

fn next_line(lines: &Receiver<String>) -> String {
    lines
        .recv_timeout(Duration::from_secs(30))
        .expect("a line from the emulator within 30 s")
}

/// Checks the frames received against the capture: sequence numbers 0, 1, 2, … complete and in
/// order, every payload decodes, and is byte for byte the capture's.
fn check_frames(got: &[(u64, Vec<u8>)], want: &[Vec<u8>]) {
    let seqs: Vec<u64> = got.iter().map(|f| f.0).collect();
    assert_eq!(seqs, (0..want.len() as u64).collect::<Vec<_>>());
    let mut pulse = Pulse::default();
    for (k, ((_, payload), reference)) in got.iter().zip(want).enumerate() {
        decode_frame(payload, &mut pulse).unwrap_or_else(|e| panic!("frame {k}: {e}"));
        assert_eq!(payload, reference, "frame {k} differs from the capture");
    }
}

/// Reads the master side of a terminal pair on its own thread until `len` bytes came (or 30 s).
fn read_terminal(mut master: TTYPort, len: usize) -> std::thread::JoinHandle<Vec<u8>> {
    master.set_timeout(Duration::from_millis(100)).unwrap();
    std::thread::spawn(move || {
        let (mut got, mut buf) = (Vec::new(), [0u8; 4096]);
        let until = Instant::now() + Duration::from_secs(30);
        while got.len() < len && Instant::now() < until {
            match master.read(&mut buf) {
                Ok(n) => got.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == ErrorKind::TimedOut => {}
                Err(e) => panic!("reading the terminal: {e}"),
            }
        }
        got
    })
}

/// Every frame of a live TCP stream until the emulator closes it, as (sequence, payload);
/// skipped bytes fail the test.
fn read_frames(stream: &mut TcpStream) -> (Vec<(u64, Vec<u8>)>, StreamDecoder) {
    let mut decoder = StreamDecoder::new();
    let mut got = Vec::new();
    while decoder.read_from(stream).unwrap() > 0 {
        while let Some(item) = decoder.next_item() {
            match item {
                StreamItem::Frame(f) => got.push((f.sequence, f.payload.to_vec())),
                StreamItem::Skipped { bytes, reason } => panic!("{bytes} bytes skipped: {reason}"),
            }
        }
    }
    (got, decoder)
}

/// A UDP receiver with a receive buffer large enough for a burst sent as fast as possible.
fn udp_receiver() -> UdpSocket {
    use std::os::fd::AsRawFd;
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let size: libc::c_int = 4 << 20;
    // SAFETY: a valid socket descriptor and a pointer to a c_int of the size given.
    let rc = unsafe {
        libc::setsockopt(
            socket.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&size as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    assert_eq!(rc, 0);
    socket
        .set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    socket
}

#[test]
fn udp_frames_and_tty_navigation_match_the_capture() {
    let dir = tempfile::tempdir().unwrap();
    let (want_frames, want_nav) = capture(dir.path(), 300);
    let socket = udp_receiver();
    let port = socket.local_addr().unwrap().port();
    // The terminal pair a `socat` would make: the emulator writes the slave, we read the master
    // (and hold the slave too, so the terminal stays up when the emulator closes it).
    let (master, slave) = TTYPort::pair().unwrap();
    let slave_name = slave.name().unwrap();
    let nav_reader = read_terminal(master, want_nav.iter().map(Vec::len).sum());

    let target = format!("udp:127.0.0.1:{port}");
    let (child, lines) = spawn_live(300, "0", &["--frames", &target, "--nav-tty", &slave_name]);
    let mut got = Vec::new();
    let until = Instant::now() + Duration::from_secs(60);
    let mut buf = vec![0u8; 65_536];
    while got.len() < want_frames.len() && Instant::now() < until {
        match socket.recv(&mut buf) {
            Ok(n) => {
                let f = parse_datagram(&buf[..n]).expect("a valid datagram");
                got.push((f.sequence, f.payload.to_vec()));
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(e) => panic!("udp receive: {e}"),
        }
    }
    let (status, out, err) = finish(child, lines);
    assert!(status.success(), "{status:?}\n{out}\n{err}");
    assert!(out.contains("sent 300 pulses"), "{out}");
    check_frames(&got, &want_frames);
    let nav = nav_reader.join().unwrap();
    assert_eq!(
        nav,
        want_nav.concat(),
        "navigation bytes differ from the capture's"
    );
    drop(slave);
}

#[test]
fn tcp_stream_and_created_pty_match_the_capture() {
    let dir = tempfile::tempdir().unwrap();
    let (want_frames, want_nav) = capture(dir.path(), 300);
    let link = dir.path().join("gnss0");
    let link_arg = link.to_str().unwrap().to_string();
    let (child, lines) = spawn_live(
        300,
        "0",
        &[
            "--frames",
            "tcp-listen:127.0.0.1:0",
            "--nav-pty-link",
            &link_arg,
        ],
    );
    // The emulator says where the terminal is, then where it listens, and waits for us.
    let nav_line = next_line(&lines);
    assert!(
        nav_line.starts_with("navigation: /dev/") && nav_line.contains(&link_arg),
        "{nav_line}"
    );
    let listen_line = next_line(&lines);
    let addr: SocketAddr = listen_line
        .strip_prefix("digitizer frames: listening on tcp ")
        .and_then(|s| s.split(',').next())
        .unwrap_or_else(|| panic!("{listen_line}"))
        .parse()
        .unwrap();
    // The daemon's side: open the device by its link, then connect.
    let mut tty = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOCTTY)
        .open(&link)
        .unwrap();
    let nav_reader = std::thread::spawn(move || {
        // Until the emulator closes the terminal (EIO on Linux, or end of file).
        let (mut got, mut buf) = (Vec::new(), [0u8; 4096]);
        while let Ok(n) = tty.read(&mut buf) {
            if n == 0 {
                break;
            }
            got.extend_from_slice(&buf[..n]);
        }
        got
    });
    let mut stream = TcpStream::connect(addr).unwrap();
    let (got, mut decoder) = read_frames(&mut stream);
    assert_eq!(decoder.finish(), None);
    assert_eq!(decoder.skipped_bytes(), 0);
    let (status, out, err) = finish(child, lines);
    assert!(status.success(), "{status:?}\n{out}\n{err}");
    assert!(out.contains("sent 300 pulses"), "{out}");
    check_frames(&got, &want_frames);
    let nav = nav_reader.join().unwrap();
    assert_eq!(
        nav,
        want_nav.concat(),
        "navigation bytes differ from the capture's"
    );
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "the link is removed at the end"
    );
}

#[test]
fn real_time_playback_takes_the_stream_time() {
    // 10 000 pulses at the sensor's 50 kHz: 0.2 s of stream.
    let (child, lines) = spawn_live(10_000, "1", &["--frames", "tcp-listen:127.0.0.1:0"]);
    let line = next_line(&lines);
    let addr: SocketAddr = line
        .strip_prefix("digitizer frames: listening on tcp ")
        .and_then(|s| s.split(',').next())
        .unwrap_or_else(|| panic!("{line}"))
        .parse()
        .unwrap();
    let mut stream = TcpStream::connect(addr).unwrap();
    // The emulator's clock starts after it accepts this connection, so the last pulse, due
    // 0.19998 s after the first, cannot arrive sooner than that after `connected`, whatever the
    // load of the machine (measuring from the first frame would not hold: it may come late).
    let connected = Instant::now();
    let mut decoder = StreamDecoder::new();
    let (mut n, mut last) = (0u64, None);
    while decoder.read_from(&mut stream).unwrap() > 0 {
        while let Some(item) = decoder.next_item() {
            let StreamItem::Frame(f) = item else {
                panic!("{item:?}")
            };
            assert_eq!(f.sequence, n);
            n += 1;
            last = Some(Instant::now());
        }
    }
    let (status, out, err) = finish(child, lines);
    assert!(status.success(), "{status:?}\n{out}\n{err}");
    assert_eq!(n, 10_000);
    let took = last.unwrap() - connected;
    assert!(took >= Duration::from_millis(180), "took {took:?}");
    // The emulator's own account: 0.2 s of stream took at least that long to release.
    let report = out
        .lines()
        .find(|l| l.starts_with("sent 10000 pulses"))
        .unwrap_or_else(|| panic!("{out}"));
    let elapsed: f64 = report
        .split(" in ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{report}"));
    assert!(elapsed >= 0.199, "{report}");
    assert!(report.contains("for 0.200 s of stream"), "{report}");
    assert!(report.contains("late (> 1 ms), max lateness"), "{report}");
}

#[test]
fn a_signal_stops_playback_cleanly() {
    let socket = udp_receiver();
    let target = format!("udp:{}", socket.local_addr().unwrap());
    // A million pulses at 50 kHz would take 20 s.
    let (child, lines) = spawn_live(1_000_000, "1", &["--frames", &target]);
    // Wait until frames flow, then ask it to stop.
    let mut buf = vec![0u8; 65_536];
    let until = Instant::now() + Duration::from_secs(30);
    while socket.recv(&mut buf).is_err() {
        assert!(Instant::now() < until, "no frame within 30 s");
    }
    // SAFETY: signalling our own child by its pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let started = Instant::now();
    let (status, out, err) = finish(child, lines);
    assert!(status.success(), "{status:?}\n{out}\n{err}");
    assert!(out.contains("stopped early"), "{out}");
    assert!(started.elapsed() < Duration::from_secs(10));
}

fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(["simulate", "--no-progress", "--scene"])
        .arg(scene())
        .args(["--pulses", "10"])
        .args(args)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn unreachable_outputs_and_bad_arguments_are_named() {
    // A port nobody listens on.
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let o = run(&[
        "--live",
        "--frames",
        &format!("tcp-connect:127.0.0.1:{port}"),
    ]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert!(
        stderr(&o).contains(&format!(
            "error: cannot connect to the daemon at tcp 127.0.0.1:{port}"
        )),
        "{}",
        stderr(&o)
    );

    let o = run(&["--live", "--nav-tty", "/nonexistent/ttyGNSS0"]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert!(
        stderr(&o).contains("error: cannot open navigation terminal /nonexistent/ttyGNSS0"),
        "{}",
        stderr(&o)
    );

    // The port is taken.
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap();
    let o = run(&["--live", "--frames", &format!("tcp-listen:{addr}")]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert!(
        stderr(&o).contains(&format!("cannot listen for the daemon on tcp {addr}")),
        "{}",
        stderr(&o)
    );

    // A link path that is a regular file is not replaced.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("not_a_link");
    std::fs::write(&file, b"keep me").unwrap();
    let o = run(&["--live", "--nav-pty-link", file.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert!(
        stderr(&o).contains("is not a symbolic link"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read(&file).unwrap(), b"keep me");

    // Usage errors: exit 2.
    for args in [
        &["--live", "--out", "x.fwcap", "--frames", "udp:127.0.0.1:9"][..],
        &["--live"][..],
        &["--live", "--frames", "serial:127.0.0.1:9"][..],
        &["--live", "--frames", "udp:127.0.0.1:9", "--speed", "-1"][..],
        &["--frames", "udp:127.0.0.1:9"][..],
    ] {
        let o = run(args);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", stderr(&o));
    }
    let o = run(&["--live", "--frames", "serial:127.0.0.1:9"]);
    assert!(
        stderr(&o).contains("unknown transport \"serial\""),
        "{}",
        stderr(&o)
    );
}

#[test]
fn a_described_scene_plays_live_like_its_capture() {
    // The tree plot (NovAtel binary navigation) over TCP: frames and navigation bytes equal
    // the capture `simulate --out` writes for the same scene.
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes/tree_plot.toml");
    let dir = tempfile::tempdir().unwrap();
    let (want_frames, want_nav) = capture_of(&scene, dir.path(), 400);
    let (master, slave) = TTYPort::pair().unwrap();
    let slave_name = slave.name().unwrap();
    let nav_reader = read_terminal(master, want_nav.iter().map(Vec::len).sum());
    let (child, lines) = spawn_live_of(
        &scene,
        400,
        "0",
        &[
            "--frames",
            "tcp-listen:127.0.0.1:0",
            "--nav-tty",
            &slave_name,
        ],
    );
    let _nav_line = next_line(&lines);
    let listen_line = next_line(&lines);
    let addr: SocketAddr = listen_line
        .strip_prefix("digitizer frames: listening on tcp ")
        .and_then(|s| s.split(',').next())
        .unwrap_or_else(|| panic!("{listen_line}"))
        .parse()
        .unwrap();
    let mut stream = TcpStream::connect(addr).unwrap();
    let (got, _) = read_frames(&mut stream);
    let (status, out, err) = finish(child, lines);
    assert!(status.success(), "{status:?}\n{out}\n{err}");
    check_frames(&got, &want_frames);
    assert_eq!(nav_reader.join().unwrap(), want_nav.concat());
    drop(slave);
}
