//! The serial navigation input through real pseudo-terminals (no mock): a receiver writes NMEA
//! into the master side, the reader opens the slave by a stable symlink (as udev names a USB
//! receiver), decodes every sentence, notices the "unplug" (master closed), and reconnects when
//! the link points at a new terminal, reporting the gap.

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use crossbeam_channel::{Receiver, bounded};
use fwlidar::nav::decoder::NavDecoder;
use fwlidar::source::serial::{Parity, SerialConfig, SerialEvent, SerialReader};
use serialport::{SerialPort, TTYPort};

fn sentence(body: &str) -> String {
    let x = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("${body}*{x:02X}\r\n")
}

/// A pseudo-terminal pair whose slave is reachable as `link`. Returns the master.
fn plug(link: &Path) -> TTYPort {
    let (master, slave) = TTYPort::pair().expect("a pseudo-terminal pair");
    let name = slave.name().expect("slave name");
    drop(slave);
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(&name, link).unwrap();
    master
}

fn next_event(rx: &Receiver<SerialEvent>) -> SerialEvent {
    rx.recv_timeout(Duration::from_secs(10))
        .expect("an event from the serial reader within 10 s")
}

/// Reads events until `want` bytes have arrived; returns them.
fn collect(rx: &Receiver<SerialEvent>, want: usize) -> Vec<u8> {
    let mut got = Vec::new();
    while got.len() < want {
        match next_event(rx) {
            SerialEvent::Data(c) => {
                assert_eq!(c.port, 3);
                got.extend_from_slice(&c.bytes);
            }
            other => panic!("unexpected {other:?} after {} bytes", got.len()),
        }
    }
    got
}

#[test]
fn nmea_through_a_real_tty_survives_unplug_and_replug() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("gnss0");
    // The device is absent at start: the reader waits for it.
    let (tx, rx) = bounded(64);
    let reader = SerialReader::spawn(
        SerialConfig {
            device: link.clone(),
            baud: 115_200,
            parity: Parity::None,
            port: 3,
            reconnect_ms: 50,
            read_timeout_ms: 20,
        },
        tx,
    )
    .unwrap();
    std::thread::sleep(Duration::from_millis(150));
    let mut master = plug(&link);
    assert_eq!(
        next_event(&rx),
        SerialEvent::Connected {
            port: 3,
            gap_ms: None
        }
    );

    let mut first = String::new();
    for k in 0..50 {
        first += &sentence(&format!(
            "GPGGA,1200{:02}.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,",
            k % 60
        ));
    }
    first += &sentence("GPZDA,120049.00,23,11,2026,00,00");
    master.write_all(first.as_bytes()).unwrap();
    let got = collect(&rx, first.len());
    assert_eq!(got, first.as_bytes(), "every byte, in order");

    // Unplug: the receiver's side goes away.
    drop(master);
    match next_event(&rx) {
        SerialEvent::Disconnected { port: 3, reason } => assert!(!reason.is_empty()),
        other => panic!("expected a disconnection, got {other:?}"),
    }
    std::thread::sleep(Duration::from_millis(200));

    // Replug: a new terminal behind the same name.
    let mut master = plug(&link);
    match next_event(&rx) {
        SerialEvent::Connected {
            port: 3,
            gap_ms: Some(g),
        } => assert!(g >= 150, "gap {g} ms"),
        other => panic!("expected a reconnection, got {other:?}"),
    }
    let second = sentence("PASHR,120050.000,090.00,T,+01.00,-02.00,+00.00,0.1,0.1,0.2,1,1");
    master.write_all(second.as_bytes()).unwrap();
    let got2 = collect(&rx, second.len());

    let stats = reader.stop();
    assert_eq!(stats.connects, 2);
    assert_eq!(stats.disconnects, 1);
    assert!(
        stats.failed_opens >= 1,
        "absent at start, and during the gap"
    );
    assert_eq!(stats.bytes, (first.len() + second.len()) as u64);

    // The bytes decode: 50 GGA + ZDA before the unplug, the PASHR after.
    let mut dec = NavDecoder::new(18.0, 512, None);
    let mut n = 0;
    for b in [&got[..], &got2[..]] {
        dec.push(b, &mut |_, t| {
            assert!(t.is_some());
            n += 1
        });
    }
    dec.finish(&mut |_, _| n += 1);
    assert_eq!(n, 52);
    assert_eq!(dec.summary().rejected, 0);
}
