//! Shared with `benches/compare/signal_python.py`: when `FWLIDAR_BENCH_WAVEFORMS` names a
//! directory, every benchmark writes the exact inputs it times there (raw little-endian `f32`
//! or `u16`, one file per array) and prints an FNV-1a 64 checksum of the bytes; the Python
//! script reads the same files and prints the same checksum, so both sides time the same
//! waveforms. Without the variable nothing is written.

#![allow(dead_code)]

use std::io::Write;

/// FNV-1a 64 of `bytes` (the checksum both sides print).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn dump_bytes(name: &str, bytes: &[u8]) {
    let Some(dir) = std::env::var_os("FWLIDAR_BENCH_WAVEFORMS") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    std::fs::create_dir_all(&dir).expect("waveform directory");
    let path = dir.join(name);
    let mut f = std::fs::File::create(&path).expect("waveform file");
    f.write_all(bytes).expect("write waveform");
    println!(
        "waveform {name}: {} bytes, fnv1a64 {:016x}",
        bytes.len(),
        fnv1a64(bytes)
    );
}

/// Writes `values` as little-endian `f32` to `<dir>/<name>` (when the variable is set).
pub fn dump_f32(name: &str, values: &[f32]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    dump_bytes(name, &bytes);
}

/// Writes `values` as little-endian `u16` to `<dir>/<name>` (when the variable is set).
pub fn dump_u16(name: &str, values: &[u16]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    dump_bytes(name, &bytes);
}
