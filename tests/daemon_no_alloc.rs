//! No allocation per frame on the daemon's input path: real UDP datagrams on loopback → the frame
//! receiver thread (recycled payload buffers) → the recorder (`LiveSource`: the frame appended
//! to a real capture file, then decoded into a pooled pulse). A counting global allocator sees
//! every thread of this test process; the allocations of 20 000 frames after warm-up must not
//! grow with the number of frames.

use std::alloc::{GlobalAlloc, Layout, System};
use std::collections::BTreeMap;
use std::net::UdpSocket;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use fwlidar::core::facts::SourceFacts;
use fwlidar::daemon::frames::{FrameReceiver, channels};
use fwlidar::daemon::recorder::{LiveInputs, LiveSource, RecorderState};
use fwlidar::daemon::{FrameInput, InputState};
use fwlidar::format::capture::FlushPolicy;
use fwlidar::format::capture_writer::CaptureWriter;
use fwlidar::pipeline::ports::{Source, SourceEvent};
use fwlidar::pulse::{Pulse, PulsePool, Segment, SegmentKind};
use fwlidar::source::live_frames::encode_live_frame;

struct Counting;
static ALLOCS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);

        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A digitizer frame: outgoing pulse and one 256-sample return segment.
fn frame(id: u64) -> Pulse {
    let mut p = Pulse {
        pulse_id: id,
        gps_time: 345_600.0 + id as f64 * 1e-5,
        sample_ns: 1.0,
        gain_v_per_dn: 0.01,
        bits: 8,
        ..Pulse::default()
    };
    p.segments.push(Segment {
        kind: SegmentKind::Outgoing,
        channel: 0,
        start_ns: -8.0,
        first: 0,
        len: 16,
    });
    p.segments.push(Segment {
        kind: SegmentKind::Return,
        channel: 0,
        start_ns: 6000.0,
        first: 16,
        len: 256,
    });
    p.raw = (0..272)
        .map(|i| (10 + (i * 7 + id as usize) % 50) as u16)
        .collect();
    p
}

#[test]
fn the_input_path_does_not_allocate_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    let port = UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let addr = format!("127.0.0.1:{port}");
    let ((tx, rx), (free_tx, free_rx)) = channels(1024);
    let state = Arc::new(InputState::default());
    let receiver = FrameReceiver::spawn(
        FrameInput::parse(&format!("udp:{addr}")).unwrap(),
        Duration::from_millis(50),
        tx,
        free_rx,
        state.clone(),
    )
    .unwrap();
    let segment = dir.path().join("noalloc_0000.fwcap");
    let writer = CaptureWriter::create(&segment, "[capture]\n", FlushPolicy::default()).unwrap();
    let (_serial_tx, serial_rx) = crossbeam_channel::bounded(4);
    let stop = Arc::new(AtomicBool::new(false));
    let recorder = Arc::new(RecorderState::default());
    let mut source = LiveSource::new(
        LiveInputs {
            frames: Some((rx, free_tx, receiver)),
            serial: serial_rx,
            serial_readers: Vec::new(),
            serial_states: BTreeMap::new(),
        },
        writer,
        segment.clone(),
        recorder.clone(),
        stop.clone(),
        SourceFacts::default(),
    );
    let pool = PulsePool::new(16);
    let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
    // A parsed address: sending to a string would resolve (and allocate) each time.
    let to: std::net::SocketAddr = addr.parse().unwrap();
    // Every datagram encoded up front: the sender's encoding is not the daemon's cost.
    let total = 22_000u64;
    let datagrams: Vec<Vec<u8>> = (0..total)
        .map(|i| {
            let mut out = Vec::new();
            encode_live_frame(i, &frame(i), &mut out).unwrap();
            out
        })
        .collect();
    // Wait for the receiver to be bound.
    let until = Instant::now() + Duration::from_secs(10);
    while !state.up.load(Ordering::Relaxed) {
        assert!(Instant::now() < until, "the UDP receiver did not start");
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut counted_from = 0;
    let mut received = 0u64;
    for (i, d) in datagrams.iter().enumerate() {
        if i == 2000 {
            counted_from = ALLOCS.load(Ordering::Relaxed);
        }
        sender.send_to(d, to).unwrap();
        // Lockstep: take the pulse before sending the next, so no datagram is lost.
        loop {
            match source.next(&pool).unwrap() {
                SourceEvent::Pulse(p) => {
                    assert_eq!(p.pulse_id, i as u64);
                    received += 1;
                    pool.give(p);
                    break;
                }
                SourceEvent::Idle => {}
                _ => panic!("expected a pulse"),
            }
        }
    }
    let allocs = ALLOCS.load(Ordering::Relaxed) - counted_from;
    eprintln!("{allocs} allocations for 20 000 frames");
    stop.store(true, Ordering::Relaxed);
    assert!(matches!(source.next(&pool).unwrap(), SourceEvent::End));
    drop(source);
    assert_eq!(received, total);
    assert_eq!(recorder.frames_recorded.load(Ordering::Relaxed), total);
    // 20 000 frames after warm-up: a handful of allocations at most (the capture writer's
    // flushes and the recorder's bookkeeping are allocation-free; an allocation per frame would
    // be 20 000).
    assert!(
        allocs < 50,
        "{allocs} allocations for 20 000 frames on the daemon's input path"
    );
}
