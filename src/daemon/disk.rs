//! Free space on the file system the recording goes to (`statvfs`), and the alarm rule: below a
//! fixed floor, or fewer minutes of recording left at the current rate than configured — well
//! before the disk is full.

use std::ffi::CString;
use std::path::Path;

/// Space on one file system.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DiskSpace {
    /// Bytes available to this user.
    pub free_bytes: u64,
    /// Bytes in the file system.
    pub total_bytes: u64,
}

/// Free and total space of the file system holding `path`.
pub fn space(path: &Path) -> std::io::Result<DiskSpace> {
    use std::os::unix::ffi::OsStrExt;
    let c = CString::new(path.as_os_str().as_bytes())
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidInput, "path holds a NUL"))?;
    // SAFETY: `c` is a valid NUL-terminated string and `st` a properly sized, writable struct
    // that statvfs fills in; nothing is kept after the call.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::statvfs(c.as_ptr(), &mut st) };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let frsize = st.f_frsize as u64;
    Ok(DiskSpace {
        free_bytes: (st.f_bavail as u64).saturating_mul(frsize),
        total_bytes: (st.f_blocks as u64).saturating_mul(frsize),
    })
}

/// Seconds of recording left at `rate_bytes_per_s` (`None` when not recording).
pub fn seconds_left(space: DiskSpace, rate_bytes_per_s: f64) -> Option<f64> {
    (rate_bytes_per_s > 0.0).then(|| space.free_bytes as f64 / rate_bytes_per_s)
}

/// Whether the disk alarm is raised: less than `floor_gb` free, or less than `minutes` of
/// recording left at the current rate.
pub fn alarm(space: DiskSpace, rate_bytes_per_s: f64, floor_gb: f64, minutes: f64) -> bool {
    (space.free_bytes as f64) < floor_gb * 1e9
        || seconds_left(space, rate_bytes_per_s).is_some_and(|s| s < minutes * 60.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn space_of_a_real_folder_is_plausible() {
        let dir = tempfile::tempdir().unwrap();
        let s = space(dir.path()).unwrap();
        assert!(s.total_bytes > 0 && s.free_bytes <= s.total_bytes);
        assert!(space(Path::new("/no/such/folder/anywhere")).is_err());
    }

    #[test]
    fn the_alarm_rises_before_the_disk_is_full() {
        let s = DiskSpace {
            free_bytes: 50_000_000_000,
            total_bytes: 100_000_000_000,
        };
        // 50 GB free: fine when idle or at 10 MB/s (83 min left)...
        assert!(!alarm(s, 0.0, 2.0, 15.0));
        assert!(!alarm(s, 10e6, 2.0, 15.0));
        // ...but at 100 MB/s only 8.3 minutes are left.
        assert!(alarm(s, 100e6, 2.0, 15.0));
        assert_eq!(seconds_left(s, 100e6), Some(500.0));
        // Below the floor whatever the rate.
        let low = DiskSpace {
            free_bytes: 1_000_000_000,
            ..s
        };
        assert!(alarm(low, 0.0, 2.0, 15.0));
    }
}
