//! Waveform tables for `fwlidar process`: one waveform per row, in CSV or NumPy `.npy`.
//!
//! Values are read as `f32` in whatever unit the file holds (volts, digitizer counts); the
//! table carries no unit. Rows may differ in length (ragged tables).
//!
//! **CSV** (read): comma-separated numbers, one waveform per line (`\n` or `\r\n`). Blank lines
//! are skipped; whitespace around cells is ignored; an optional header row is recognised when
//! the first non-blank line has a non-empty cell that is not a number. Trailing empty cells and
//! trailing `NaN` cells are padding and are dropped (zeros are values, never padding). Every
//! other cell must be a finite number representable as `f32`; an interior empty cell, text,
//! `NaN` or infinity is an error naming the file, the 1-based line and cell, and the text. A
//! line that holds only padding is an error (tables never hold empty waveforms).
//!
//! **CSV** (write): one row per line, cells separated by `,`, each value in the shortest
//! decimal form that reads back to the same `f32`; no header.
//!
//! **NPY** (read): format versions 1.0, 2.0 and 3.0; dtypes `f4`, `f8` (rounded to `f32`),
//! `i2`, `u2`, `i4`, `u1`, `i1`, little-endian (`<`, or `|`/`=` for one-byte types); C or
//! Fortran order; shape `(n,)` is one waveform, `(rows, cols)` is `rows` waveforms. Trailing
//! `NaN` values of a row are padding and dropped; a row of only `NaN` is an error.
//! Big-endian data, other dtypes, more than two dimensions and truncated data are errors.
//!
//! **NPY** (write): version 1.0, `<f4`, C order, shape `(rows, longest row)`; shorter rows are
//! padded with `NaN` at their end (which the reader drops again).

use std::io::Write;
use std::path::Path;

use crate::core::atomic_file::AtomicFile;

/// Why a table could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The file name does not end in `.csv` or `.npy`.
    #[error("{path}: unknown table format (the name must end in .csv or .npy)")]
    UnknownFormat {
        /// The file.
        path: String,
    },
    /// A CSV cell or line is not valid.
    #[error("{path}:{line}: cell {column}: {reason}: {text:?}")]
    Csv {
        /// The file.
        path: String,
        /// Line, 1-based.
        line: usize,
        /// Cell, 1-based (0 when the whole line is at fault).
        column: usize,
        /// The offending text (at most 40 characters).
        text: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// An NPY file is not valid or not supported.
    #[error("{path}: not a supported .npy file: {reason}")]
    Npy {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
}

/// File formats of waveform tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TableFormat {
    /// Comma-separated text.
    Csv,
    /// NumPy `.npy` binary.
    Npy,
}

impl TableFormat {
    /// The format named by the file's extension (`.csv` or `.npy`, any case).
    pub fn from_path(path: &Path) -> Result<Self, TableError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        match ext.as_deref() {
            Some("csv") => Ok(TableFormat::Csv),
            Some("npy") => Ok(TableFormat::Npy),
            _ => Err(TableError::UnknownFormat {
                path: path.display().to_string(),
            }),
        }
    }
}

/// A waveform table: rows of samples in the file's unit, never empty rows.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Table {
    /// The waveforms, one per row.
    pub rows: Vec<Vec<f32>>,
    /// For CSV tables, the 1-based line of each row; empty for NPY tables.
    pub lines: Vec<usize>,
    /// True when a CSV header row was skipped.
    pub had_header: bool,
}

impl Table {
    /// Where row `i` (0-based) came from, for messages: `line 12` for CSV, `row 3` (0-based)
    /// for NPY.
    pub fn row_origin(&self, i: usize) -> String {
        match self.lines.get(i) {
            Some(l) => format!("line {l}"),
            None => format!("row {i}"),
        }
    }

    /// Removes the first `n` values of every row (an index column, for example); a row left
    /// empty is an error naming its origin.
    pub fn skip_columns(&mut self, n: usize, path: &str) -> Result<(), TableError> {
        if n == 0 {
            return Ok(());
        }
        for (i, row) in self.rows.iter_mut().enumerate() {
            if row.len() <= n {
                return Err(match self.lines.get(i) {
                    Some(&line) => TableError::Csv {
                        path: path.to_string(),
                        line,
                        column: 0,
                        text: String::new(),
                        reason: "no values after the skipped columns",
                    },
                    None => TableError::Npy {
                        path: path.to_string(),
                        reason: format!("row {i} has no values after skipping {n} columns"),
                    },
                });
            }
            row.drain(..n);
        }
        Ok(())
    }
}

fn clip(text: &str) -> String {
    text.chars().take(40).collect()
}

/// Parses a cell as a number (finite or not); `None` when it is not a number at all.
fn parse_cell(cell: &str) -> Option<f32> {
    cell.parse::<f32>().ok()
}

/// Parses CSV bytes (`path` only names the file in errors). Never panics.
pub fn parse_csv(bytes: &[u8], path: &str) -> Result<Table, TableError> {
    let mut table = Table::default();
    let mut seen_first = false;
    let err = |line: usize, column: usize, text: &str, reason: &'static str| TableError::Csv {
        path: path.to_string(),
        line,
        column,
        text: clip(text),
        reason,
    };
    for (i, raw) in bytes.split(|&b| b == b'\n').enumerate() {
        let line_no = i + 1;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        let line = std::str::from_utf8(raw).map_err(|_| {
            err(
                line_no,
                0,
                &String::from_utf8_lossy(raw),
                "line is not valid UTF-8",
            )
        })?;
        if line.trim().is_empty() {
            continue;
        }
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        if !seen_first {
            seen_first = true;
            if cells
                .iter()
                .any(|c| !c.is_empty() && parse_cell(c).is_none())
            {
                table.had_header = true;
                continue;
            }
        }
        // Drop trailing padding: empty cells and NaN cells.
        let mut end = cells.len();
        while end > 0 {
            let c = cells[end - 1];
            if c.is_empty() || parse_cell(c).is_some_and(f32::is_nan) {
                end -= 1;
            } else {
                break;
            }
        }
        if end == 0 {
            return Err(err(line_no, 0, line, "line holds only padding, no values"));
        }
        let mut row = Vec::with_capacity(end);
        for (j, c) in cells[..end].iter().enumerate() {
            let col = j + 1;
            if c.is_empty() {
                return Err(err(line_no, col, c, "empty cell inside the row"));
            }
            match parse_cell(c) {
                None => return Err(err(line_no, col, c, "not a number")),
                Some(v) if v.is_nan() => {
                    return Err(err(line_no, col, c, "NaN inside the row"));
                }
                Some(v) if v.is_infinite() => {
                    return Err(err(
                        line_no,
                        col,
                        c,
                        "not a finite number (infinite or beyond f32 range)",
                    ));
                }
                Some(v) => row.push(v),
            }
        }
        table.rows.push(row);
        table.lines.push(line_no);
    }
    Ok(table)
}

/// Writes rows as CSV (shortest round-trip `f32` text, no header).
pub fn write_csv<W: Write>(rows: &[Vec<f32>], w: &mut W) -> std::io::Result<()> {
    for row in rows {
        let mut first = true;
        for v in row {
            if !first {
                w.write_all(b",")?;
            }
            first = false;
            write!(w, "{v}")?;
        }
        w.write_all(b"\n")?;
    }
    Ok(())
}

/// The NPY magic string.
const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// Element types the reader accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Dtype {
    F4,
    F8,
    I2,
    U2,
    I4,
    U1,
    I1,
}

impl Dtype {
    fn size(self) -> usize {
        match self {
            Dtype::F4 | Dtype::I4 => 4,
            Dtype::F8 => 8,
            Dtype::I2 | Dtype::U2 => 2,
            Dtype::U1 | Dtype::I1 => 1,
        }
    }

    fn parse(descr: &str) -> Result<Self, String> {
        let mut chars = descr.chars();
        let order = chars.next().unwrap_or(' ');
        let code = chars.as_str();
        let t = match code {
            "f4" => Dtype::F4,
            "f8" => Dtype::F8,
            "i2" => Dtype::I2,
            "u2" => Dtype::U2,
            "i4" => Dtype::I4,
            "u1" => Dtype::U1,
            "i1" => Dtype::I1,
            _ => {
                return Err(format!(
                    "dtype {descr:?} is not supported (f4, f8, i2, u2, i4, u1, i1 are)"
                ));
            }
        };
        match order {
            '<' => Ok(t),
            '|' | '=' if t.size() == 1 => Ok(t),
            '>' if t.size() == 1 => Ok(t),
            '>' => Err(format!(
                "dtype {descr:?} is big-endian; only little-endian data is supported"
            )),
            _ => Err(format!(
                "dtype {descr:?} has no explicit little-endian byte order"
            )),
        }
    }

    /// Decodes one element from exactly `size()` bytes.
    fn decode(self, b: &[u8]) -> f32 {
        match self {
            Dtype::F4 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            Dtype::F8 => {
                f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
            }
            Dtype::I2 => i16::from_le_bytes([b[0], b[1]]) as f32,
            Dtype::U2 => u16::from_le_bytes([b[0], b[1]]) as f32,
            Dtype::I4 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Dtype::U1 => b[0] as f32,
            Dtype::I1 => b[0] as i8 as f32,
        }
    }
}

/// A value in the NPY header dictionary.
#[derive(Debug, PartialEq)]
enum PyValue {
    Str(String),
    Bool(bool),
    Tuple(Vec<u64>),
}

/// A tiny parser for the Python dict literal of an NPY header.
struct HeaderParser<'a> {
    s: &'a [u8],
    i: usize,
}

impl HeaderParser<'_> {
    fn skip_ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.i).copied()
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.peek() == Some(c) {
            self.i += 1;
            Ok(())
        } else {
            Err(format!(
                "header dictionary: expected '{}' at byte {}",
                c as char, self.i
            ))
        }
    }

    fn string(&mut self) -> Result<String, String> {
        let q = self.peek().ok_or("header dictionary ends early")?;
        if q != b'\'' && q != b'"' {
            return Err(format!(
                "header dictionary: expected a string at byte {}",
                self.i
            ));
        }
        self.i += 1;
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i] != q {
            self.i += 1;
        }
        if self.i >= self.s.len() {
            return Err("header dictionary: unterminated string".into());
        }
        let text = String::from_utf8_lossy(&self.s[start..self.i]).into_owned();
        self.i += 1;
        Ok(text)
    }

    fn value(&mut self) -> Result<PyValue, String> {
        match self.peek() {
            Some(b'\'') | Some(b'"') => Ok(PyValue::Str(self.string()?)),
            Some(b'(') => {
                self.i += 1;
                let mut items = Vec::new();
                loop {
                    match self.peek() {
                        Some(b')') => {
                            self.i += 1;
                            return Ok(PyValue::Tuple(items));
                        }
                        Some(b',') if !items.is_empty() => self.i += 1,
                        Some(c) if c.is_ascii_digit() => {
                            let start = self.i;
                            while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                                self.i += 1;
                            }
                            let text = std::str::from_utf8(&self.s[start..self.i])
                                .map_err(|_| "bad shape".to_string())?;
                            let n: u64 = text
                                .parse()
                                .map_err(|_| format!("shape entry {text} is too large"))?;
                            // Allow a trailing 'L' (Python 2 longs).
                            if self.s.get(self.i) == Some(&b'L') {
                                self.i += 1;
                            }
                            items.push(n);
                        }
                        _ => {
                            return Err(format!(
                                "header dictionary: bad shape tuple at byte {}",
                                self.i
                            ));
                        }
                    }
                }
            }
            Some(_) => {
                let rest = &self.s[self.i..];
                if rest.starts_with(b"True") {
                    self.i += 4;
                    Ok(PyValue::Bool(true))
                } else if rest.starts_with(b"False") {
                    self.i += 5;
                    Ok(PyValue::Bool(false))
                } else {
                    Err(format!(
                        "header dictionary: unexpected value at byte {}",
                        self.i
                    ))
                }
            }
            None => Err("header dictionary ends early".into()),
        }
    }

    fn dict(&mut self) -> Result<Vec<(String, PyValue)>, String> {
        self.expect(b'{')?;
        let mut entries = Vec::new();
        loop {
            if self.peek() == Some(b'}') {
                self.i += 1;
                return Ok(entries);
            }
            let key = self.string()?;
            self.expect(b':')?;
            let value = self.value()?;
            entries.push((key, value));
            match self.peek() {
                Some(b',') => self.i += 1,
                Some(b'}') => {}
                _ => {
                    return Err(format!(
                        "header dictionary: expected ',' or '}}' at byte {}",
                        self.i
                    ));
                }
            }
        }
    }
}

/// Parses NPY bytes (`path` only names the file in errors). Never panics; never allocates more
/// than the data the file actually holds.
pub fn parse_npy(bytes: &[u8], path: &str) -> Result<Table, TableError> {
    let fail = |reason: String| TableError::Npy {
        path: path.to_string(),
        reason,
    };
    if bytes.len() < 10 || &bytes[..6] != NPY_MAGIC {
        return Err(fail(
            "missing the \\x93NUMPY magic (truncated or not an .npy file)".into(),
        ));
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (header_len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(fail("truncated before the header length".into()));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        _ => {
            return Err(fail(format!(
                "format version {major}.{minor} is not supported"
            )));
        }
    };
    let data_start = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| fail(format!("truncated header ({header_len} bytes announced)")))?;
    let header = &bytes[start..data_start];
    if major < 3 && !header.is_ascii() {
        return Err(fail("header is not ASCII".into()));
    }
    let entries = HeaderParser { s: header, i: 0 }.dict().map_err(fail)?;
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    for (k, v) in entries {
        match (k.as_str(), v) {
            ("descr", PyValue::Str(s)) => descr = Some(s),
            ("fortran_order", PyValue::Bool(b)) => fortran = Some(b),
            ("shape", PyValue::Tuple(t)) => shape = Some(t),
            (k @ ("descr" | "fortran_order" | "shape"), _) => {
                return Err(fail(format!("header key '{k}' has the wrong type")));
            }
            _ => {}
        }
    }
    let descr = descr.ok_or_else(|| fail("header has no 'descr'".into()))?;
    let fortran = fortran.ok_or_else(|| fail("header has no 'fortran_order'".into()))?;
    let shape = shape.ok_or_else(|| fail("header has no 'shape'".into()))?;
    let dtype = Dtype::parse(&descr).map_err(fail)?;
    let (rows, cols) = match shape.as_slice() {
        [n] => (1u64, *n),
        [r, c] => (*r, *c),
        other => {
            return Err(fail(format!(
                "{} dimensions; only 1-D and 2-D arrays are waveform tables",
                other.len()
            )));
        }
    };
    let data = &bytes[data_start..];
    let expected = rows
        .checked_mul(cols)
        .and_then(|n| n.checked_mul(dtype.size() as u64))
        .filter(|&n| n <= usize::MAX as u64)
        .ok_or_else(|| fail(format!("shape {shape:?} is too large")))? as usize;
    if data.len() < expected {
        return Err(fail(format!(
            "truncated data: shape {shape:?} of {descr} needs {expected} bytes, the file holds {}",
            data.len()
        )));
    }
    if data.len() > expected {
        return Err(fail(format!(
            "{} unexpected bytes after the data of shape {shape:?}",
            data.len() - expected
        )));
    }
    let (rows, cols) = (rows as usize, cols as usize);
    let size = dtype.size();
    let at = |r: usize, c: usize| {
        let idx = if fortran { c * rows + r } else { r * cols + c };
        dtype.decode(&data[idx * size..(idx + 1) * size])
    };
    let mut table = Table::default();
    if cols == 0 {
        return Ok(table);
    }
    for r in 0..rows {
        let mut row: Vec<f32> = (0..cols).map(|c| at(r, c)).collect();
        while row.last().is_some_and(|v| v.is_nan()) {
            row.pop();
        }
        if row.is_empty() {
            return Err(fail(format!("row {r} holds only NaN padding, no values")));
        }
        table.rows.push(row);
    }
    Ok(table)
}

/// The preamble of an NPY v1.0 file (magic, version, header length, header dictionary) for an
/// array of dtype `descr` (a NumPy dtype description in Python syntax, e.g. `'<f4'` or a list of
/// `('name', '<u8')` fields) and `shape`, C order, padded with spaces to `min_len` bytes or more
/// (always a multiple of 64, as NumPy aligns the data). `None` when the dictionary does not fit
/// the 16-bit header length.
pub fn npy_preamble(descr: &str, shape: &[u64], min_len: usize) -> Option<Vec<u8>> {
    let dims = match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(u64::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!("{{'descr': {descr}, 'fortran_order': False, 'shape': {dims}, }}");
    let unpadded = NPY_MAGIC.len() + 2 + 2 + header.len() + 1;
    let total = unpadded.max(min_len).div_ceil(64) * 64;
    header.extend(std::iter::repeat_n(' ', total - unpadded));
    header.push('\n');
    let len = u16::try_from(header.len()).ok()?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(NPY_MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    Some(out)
}

/// Encodes rows as an NPY v1.0 file: `<f4`, C order, shape `(rows, longest row)`, shorter rows
/// padded with NaN.
pub fn encode_npy(rows: &[Vec<f32>]) -> Vec<u8> {
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    let mut out = npy_preamble("'<f4'", &[rows.len() as u64, cols as u64], 0)
        .expect("a two-dimensional shape fits an NPY header");
    out.reserve(rows.len() * cols * 4);
    for row in rows {
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for _ in row.len()..cols {
            out.extend_from_slice(&f32::NAN.to_le_bytes());
        }
    }
    out
}

/// Reads a table, the format from the file name's extension.
pub fn read_table(path: &Path) -> Result<Table, TableError> {
    let format = TableFormat::from_path(path)?;
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| TableError::Io {
        path: name.clone(),
        source,
    })?;
    match format {
        TableFormat::Csv => parse_csv(&bytes, &name),
        TableFormat::Npy => parse_npy(&bytes, &name),
    }
}

/// Writes a table atomically (complete or not at all), the format from the file name's
/// extension.
pub fn write_table(path: &Path, rows: &[Vec<f32>]) -> Result<(), TableError> {
    let format = TableFormat::from_path(path)?;
    let name = path.display().to_string();
    let io = |source: std::io::Error| TableError::Io {
        path: name.clone(),
        source,
    };
    let sink = |e: crate::core::atomic_file::WriteError| TableError::Io {
        path: name.clone(),
        source: std::io::Error::other(e.to_string()),
    };
    let mut file = AtomicFile::create(path).map_err(sink)?;
    let w = file.writer().map_err(sink)?;
    match format {
        TableFormat::Csv => write_csv(rows, w).map_err(io)?,
        TableFormat::Npy => w.write_all(&encode_npy(rows)).map_err(io)?,
    }
    file.commit().map_err(sink)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn csv(text: &str) -> Result<Table, TableError> {
        parse_csv(text.as_bytes(), "t.csv")
    }

    /// An NPY file with the given header dictionary and data bytes (version 1.0).
    fn npy(dict: &str, data: &[u8]) -> Vec<u8> {
        let mut out = NPY_MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        let header = format!("{dict}\n");
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    #[test]
    fn csv_header_blank_lines_whitespace_and_padding() {
        let t = csv("V1,V2,V3\n\n 1, 2.5 ,3\r\n4,5,,\n  \n6,nan,NaN\n0,0,0\n").unwrap();
        assert!(t.had_header);
        assert_eq!(
            t.rows,
            vec![vec![1.0, 2.5, 3.0], vec![4.0, 5.0], vec![6.0], vec![0.0; 3]]
        );
        assert_eq!(t.lines, vec![3, 4, 6, 7]);
        assert_eq!(t.row_origin(1), "line 4");
        let t = csv("1,2\n3\n").unwrap();
        assert!(!t.had_header);
        assert_eq!(t.rows.len(), 2);
        assert!(csv("").unwrap().rows.is_empty());
        assert!(csv("a,b\n").unwrap().rows.is_empty());
    }

    #[test]
    fn csv_errors_name_line_cell_and_text() {
        let cases = [
            ("1,2\n3,abc,4\n", 2, 2, "abc"),
            ("1,2\n3,,4\n", 2, 2, ""),
            ("1,nan,3\n", 1, 2, "nan"),
            ("1,2\n\n5,inf\n", 3, 2, "inf"),
            ("1,1e39\n", 1, 2, "1e39"),
            ("h\n1,2\n,,\n", 3, 0, ",,"),
        ];
        for (text, line, column, bad) in cases {
            match csv(text) {
                Err(TableError::Csv {
                    path,
                    line: l,
                    column: c,
                    text: t,
                    ..
                }) => {
                    assert_eq!(
                        (path.as_str(), l, c, t.as_str()),
                        ("t.csv", line, column, bad)
                    );
                }
                other => panic!("{text:?}: {other:?}"),
            }
        }
        let e = csv("1,2\n3,x\n").unwrap_err().to_string();
        assert!(
            e.contains("t.csv:2") && e.contains("cell 2") && e.contains("\"x\""),
            "{e}"
        );
        assert!(parse_csv(b"1,2\n\xff\n", "t.csv").is_err());
    }

    #[test]
    fn npy_reads_every_supported_dtype_and_both_orders() {
        let t = parse_npy(
            &npy(
                "{'descr': '<i2', 'fortran_order': False, 'shape': (2, 3), }",
                &[1, 0, 2, 0, 255, 255, 4, 0, 5, 0, 6, 0],
            ),
            "a.npy",
        )
        .unwrap();
        assert_eq!(t.rows, vec![vec![1.0, 2.0, -1.0], vec![4.0, 5.0, 6.0]]);
        assert!(t.lines.is_empty());
        assert_eq!(t.row_origin(1), "row 1");
        // Fortran order: column-major storage of [[1, 2, 3], [4, 5, 6]].
        let t = parse_npy(
            &npy(
                "{'descr': '|u1', 'fortran_order': True, 'shape': (2, 3), }",
                &[1, 4, 2, 5, 3, 6],
            ),
            "a.npy",
        )
        .unwrap();
        assert_eq!(t.rows, vec![vec![1.0, 2.0, 3.0], vec![4.0, 5.0, 6.0]]);
        let one = |descr: &str, bytes: &[u8]| {
            parse_npy(
                &npy(
                    &format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (1,), }}"),
                    bytes,
                ),
                "a.npy",
            )
            .unwrap()
            .rows[0][0]
        };
        assert_eq!(one("<f4", &1.5f32.to_le_bytes()), 1.5);
        assert_eq!(one("<f8", &(-2.25f64).to_le_bytes()), -2.25);
        assert_eq!(one("<u2", &60000u16.to_le_bytes()), 60000.0);
        assert_eq!(one("<i4", &(-70000i32).to_le_bytes()), -70000.0);
        assert_eq!(one("|i1", &[0xfe]), -2.0);
        // 1-D is one waveform; trailing NaN is padding.
        let mut data = Vec::new();
        for v in [1.0f32, 2.0, f32::NAN] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        let t = parse_npy(
            &npy(
                "{'descr': '<f4', 'fortran_order': False, 'shape': (3,), }",
                &data,
            ),
            "a.npy",
        )
        .unwrap();
        assert_eq!(t.rows, vec![vec![1.0, 2.0]]);
        // Zero rows: an empty table.
        let t = parse_npy(
            &npy(
                "{'descr': '<f4', 'fortran_order': False, 'shape': (0, 5), }",
                &[],
            ),
            "a.npy",
        )
        .unwrap();
        assert!(t.rows.is_empty());
    }

    #[test]
    fn npy_malformed_inputs_are_errors() {
        let good = npy(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }",
            &[0u8; 16],
        );
        assert!(parse_npy(&good, "a.npy").is_ok());
        let mut cases: Vec<(Vec<u8>, &str)> = vec![
            (good[..good.len() - 1].to_vec(), "truncated data"),
            (good[..20].to_vec(), "truncated header"),
            (good[..5].to_vec(), "magic"),
            (b"PK\x03\x04 not numpy at all".to_vec(), "magic"),
            ([good.clone(), vec![0]].concat(), "unexpected bytes"),
            (
                npy(
                    "{'descr': '<c8', 'fortran_order': False, 'shape': (1,), }",
                    &[0; 8],
                ),
                "not supported",
            ),
            (
                npy(
                    "{'descr': '>f4', 'fortran_order': False, 'shape': (1,), }",
                    &[0; 4],
                ),
                "big-endian",
            ),
            (
                npy(
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 1, 1), }",
                    &[0; 4],
                ),
                "dimensions",
            ),
            (
                npy("{'descr': '<f4', 'shape': (1,), }", &[0; 4]),
                "fortran_order",
            ),
            (
                npy(
                    "{'descr': '<f4', 'fortran_order': 0, 'shape': (1,), }",
                    &[0; 4],
                ),
                "byte",
            ),
            (npy("{'descr': '<f4'", &[0; 4]), "header"),
            (npy("not a dict", &[0; 4]), "expected '{'"),
            (
                npy(
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999999999,), }",
                    &[],
                ),
                "too large",
            ),
            (
                npy(
                    "{'descr': '<f8', 'fortran_order': False, 'shape': (4294967296, 4294967296), }",
                    &[],
                ),
                "too large",
            ),
            (
                npy(
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 2), }",
                    &[0, 0, 0xc0, 0x7f, 0, 0, 0xc0, 0x7f],
                ),
                "only NaN",
            ),
        ];
        let mut v9 = good.clone();
        v9[6] = 9;
        cases.push((v9, "version 9"));
        for (bytes, want) in cases {
            let e = parse_npy(&bytes, "a.npy").unwrap_err().to_string();
            assert!(e.contains("a.npy") && e.contains(want), "{want}: {e}");
        }
    }

    #[test]
    fn npy_versions_2_and_3_and_our_header_alignment() {
        let rows = vec![vec![1.0f32, 2.0], vec![3.0]];
        let bytes = encode_npy(&rows);
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        assert_eq!(bytes[10 + header_len - 1], b'\n');
        for major in [2u8, 3] {
            let mut v = NPY_MAGIC.to_vec();
            v.extend_from_slice(&[major, 0]);
            v.extend_from_slice(&(header_len as u32).to_le_bytes());
            v.extend_from_slice(&bytes[10..]);
            assert_eq!(parse_npy(&v, "a.npy").unwrap().rows, rows);
        }
    }

    #[test]
    fn files_round_trip_and_unknown_extensions_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let rows = vec![vec![0.1f32, -3e-8, 7.0], vec![1e30]];
        for name in ["a.csv", "a.NPY"] {
            let p = dir.path().join(name);
            write_table(&p, &rows).unwrap();
            assert_eq!(read_table(&p).unwrap().rows, rows);
        }
        let p = dir.path().join("a.txt");
        assert!(matches!(
            write_table(&p, &rows),
            Err(TableError::UnknownFormat { .. })
        ));
        assert!(!p.exists());
        assert!(matches!(
            read_table(&dir.path().join("missing.csv")),
            Err(TableError::Io { .. })
        ));
    }

    #[test]
    fn skip_columns_drops_an_index_column() {
        let mut t = csv("i,a,b\n1,5,6\n2,7\n").unwrap();
        t.skip_columns(1, "t.csv").unwrap();
        assert_eq!(t.rows, vec![vec![5.0, 6.0], vec![7.0]]);
        assert!(t.skip_columns(1, "t.csv").is_err());
    }

    fn finite_f32() -> impl Strategy<Value = f32> {
        prop_oneof![
            any::<f32>().prop_filter("finite", |v| v.is_finite()),
            -1e4f32..1e4,
            Just(0.0f32),
            Just(-0.0f32),
        ]
    }

    fn ragged() -> impl Strategy<Value = Vec<Vec<f32>>> {
        prop::collection::vec(prop::collection::vec(finite_f32(), 1..40), 0..20)
    }

    fn bits(rows: &[Vec<f32>]) -> Vec<Vec<u32>> {
        rows.iter()
            .map(|r| r.iter().map(|v| v.to_bits()).collect())
            .collect()
    }

    proptest! {
        #[test]
        fn csv_round_trips_exactly(rows in ragged()) {
            let mut buf = Vec::new();
            write_csv(&rows, &mut buf).unwrap();
            let t = parse_csv(&buf, "p.csv").unwrap();
            prop_assert_eq!(bits(&t.rows), bits(&rows));
        }

        #[test]
        fn npy_round_trips_exactly(rows in ragged()) {
            let t = parse_npy(&encode_npy(&rows), "p.npy").unwrap();
            let expect: Vec<Vec<f32>> = if rows.iter().all(|r| r.is_empty()) && !rows.is_empty() {
                Vec::new()
            } else {
                rows.clone()
            };
            prop_assert_eq!(bits(&t.rows), bits(&expect));
        }

        #[test]
        fn csv_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
            let _ = parse_csv(&bytes, "f.csv");
        }

        #[test]
        fn csv_text_never_panics(text in "[0-9a-zA-Z.,eE+\\- \r\n]{0,200}") {
            if let Ok(t) = parse_csv(text.as_bytes(), "f.csv") {
                prop_assert!(t.rows.iter().all(|r| !r.is_empty() && r.iter().all(|v| v.is_finite())));
                prop_assert_eq!(t.rows.len(), t.lines.len());
            }
        }

        #[test]
        fn npy_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
            let _ = parse_npy(&bytes, "f.npy");
        }

        #[test]
        fn npy_mutated_never_panics(rows in ragged(), pos in any::<prop::sample::Index>(), byte in any::<u8>(), cut in any::<prop::sample::Index>()) {
            let mut bytes = encode_npy(&rows);
            let i = pos.index(bytes.len());
            bytes[i] = byte;
            let n = cut.index(bytes.len() + 1);
            let _ = parse_npy(&bytes[..n], "f.npy");
            let _ = parse_npy(&bytes, "f.npy");
        }
    }
}
