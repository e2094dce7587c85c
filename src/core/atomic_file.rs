//! Output files that appear complete or not at all: written under `NAME.partial`, then flushed,
//! synced and renamed over `NAME`. A crash or a failed run never leaves a half-written `NAME`,
//! and the previous run's `NAME` survives until the new one is complete.

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// A buffered file written under a temporary name and moved into place by [`AtomicFile::commit`].
pub struct AtomicFile {
    path: PathBuf,
    tmp: PathBuf,
    out: Option<BufWriter<File>>,
}

/// A file that could not be written: which file, and the operating system's error.
#[derive(Debug, thiserror::Error)]
#[error("cannot write {path}: {source}")]
pub struct WriteError {
    /// The file being written.
    pub path: String,
    /// The I/O error.
    pub source: std::io::Error,
}

impl WriteError {
    /// The error of writing `path`.
    pub fn new(path: &Path, source: std::io::Error) -> Self {
        WriteError {
            path: path.display().to_string(),
            source,
        }
    }
}

fn io_err(path: &Path, source: std::io::Error) -> WriteError {
    WriteError::new(path, source)
}

impl AtomicFile {
    /// Starts writing `path` (as `path.partial`).
    pub fn create(path: impl Into<PathBuf>) -> Result<Self, WriteError> {
        let path = path.into();
        let mut tmp = path.clone().into_os_string();
        tmp.push(".partial");
        let tmp = PathBuf::from(tmp);
        let file = OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(&tmp)
            .map_err(|e| io_err(&tmp, e))?;
        Ok(AtomicFile {
            path,
            tmp,
            out: Some(BufWriter::with_capacity(1 << 20, file)),
        })
    }

    /// The final path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The writer (until committed).
    pub fn writer(&mut self) -> Result<&mut BufWriter<File>, WriteError> {
        match self.out.as_mut() {
            Some(w) => Ok(w),
            None => Err(io_err(
                &self.path,
                std::io::Error::other("file already committed"),
            )),
        }
    }

    /// Flushes buffered bytes to the operating system (the file stays under its temporary name).
    pub fn flush(&mut self) -> Result<(), WriteError> {
        if let Some(w) = self.out.as_mut() {
            w.flush().map_err(|e| io_err(&self.tmp, e))?;
        }
        Ok(())
    }

    /// Flushes, syncs and renames the file into place. Idempotent.
    pub fn commit(&mut self) -> Result<(), WriteError> {
        let Some(w) = self.out.take() else {
            return Ok(());
        };
        let file = w
            .into_inner()
            .map_err(|e| io_err(&self.tmp, e.into_error()))?;
        file.sync_all().map_err(|e| io_err(&self.tmp, e))?;
        drop(file);
        std::fs::rename(&self.tmp, &self.path).map_err(|e| io_err(&self.path, e))
    }
}

/// Writes `bytes` to `path` atomically (temporary file, sync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    let mut f = AtomicFile::create(path)?;
    f.writer()?.write_all(bytes).map_err(|e| io_err(path, e))?;
    f.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn old_file_survives_until_commit() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        std::fs::write(&p, "old").unwrap();
        let mut f = AtomicFile::create(&p).unwrap();
        f.writer().unwrap().write_all(b"new").unwrap();
        f.flush().unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "old");
        f.commit().unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new");
        assert!(!dir.path().join("a.csv.partial").exists());
        f.commit().unwrap();
    }
}
