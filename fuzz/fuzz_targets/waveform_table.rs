//! Arbitrary bytes through the waveform-table readers of `fwlidar process` (CSV and NPY). The
//! first byte picks the reader (even: CSV, odd: NPY); the rest is the file. Neither may panic;
//! a table either reader accepts must hold only non-empty rows, and must survive a write and a
//! second read unchanged, bit for bit.
#![no_main]

use fwlidar::format::table::{encode_npy, parse_csv, parse_npy, write_csv};
use libfuzzer_sys::fuzz_target;

fn bits(rows: &[Vec<f32>]) -> Vec<Vec<u32>> {
    rows.iter()
        .map(|r| r.iter().map(|v| v.to_bits()).collect())
        .collect()
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, file)) = data.split_first() else {
        return;
    };
    if mode % 2 == 0 {
        let Ok(table) = parse_csv(file, "fuzz.csv") else {
            return;
        };
        assert_eq!(table.rows.len(), table.lines.len());
        assert!(table.lines.windows(2).all(|w| w[0] < w[1]));
        assert!(
            table
                .rows
                .iter()
                .all(|r| !r.is_empty() && r.iter().all(|v| v.is_finite()))
        );
        let mut text = Vec::new();
        write_csv(&table.rows, &mut text).expect("write to a Vec");
        let again = parse_csv(&text, "again.csv").expect("our own CSV reads back");
        assert_eq!(bits(&again.rows), bits(&table.rows));
    } else {
        let Ok(table) = parse_npy(file, "fuzz.npy") else {
            return;
        };
        assert!(table.lines.is_empty());
        assert!(
            table
                .rows
                .iter()
                .all(|r| r.last().is_some_and(|v| !v.is_nan()))
        );
        let again =
            parse_npy(&encode_npy(&table.rows), "again.npy").expect("our own NPY reads back");
        assert_eq!(bits(&again.rows), bits(&table.rows));
    }
});
