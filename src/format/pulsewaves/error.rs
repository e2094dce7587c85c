//! The errors of the PulseWaves reader. Every message starts with the file it is about and names
//! the field (and the pulse, sampling and segment where there is one).

/// What can go wrong reading a PulseWaves `.pls` + `.wvs` pair.
#[derive(Debug, thiserror::Error)]
pub enum PulseWavesError {
    /// The operating system refused a read or seek.
    #[error("{file}: cannot read: {source}")]
    Io {
        /// The file (as the caller named it).
        file: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// The first 16 bytes are not the expected signature.
    #[error(
        "{file}: not a PulseWaves {what} file: the signature is {found:?}, expected {expected:?}"
    )]
    Signature {
        /// The file.
        file: String,
        /// `.pls` or `.wvs`.
        what: &'static str,
        /// The bytes found, as text.
        found: String,
        /// The signature expected.
        expected: &'static str,
    },
    /// A structure needs bytes past the end of the file.
    #[error("{file}: truncated: {what} needs bytes {start}..{end} but the file has {len} bytes")]
    Truncated {
        /// The file.
        file: String,
        /// The structure (and field) that does not fit.
        what: String,
        /// First byte needed.
        start: u64,
        /// One past the last byte needed.
        end: u64,
        /// The file's length, bytes.
        len: u64,
    },
    /// A field holds a value the reader cannot make sense of.
    #[error("{file}: {field}: {reason}")]
    Invalid {
        /// The file.
        file: String,
        /// The field, with where it is (e.g. `descriptor 3: sampling 1: bits_per_sample`).
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A valid feature of the format that this reader does not implement (compression).
    #[error("{file}: {field}: {reason} is not supported by this reader")]
    Unsupported {
        /// The file.
        file: String,
        /// The field.
        field: String,
        /// The value and what it means.
        reason: String,
    },
    /// A pulse names a pulse descriptor the file does not define.
    #[error("{file}: pulse {pulse}: descriptor index {index} points nowhere (file has {defined})")]
    DescriptorIndex {
        /// The `.pls` file.
        file: String,
        /// Index of the pulse record (0-based).
        pulse: u64,
        /// The descriptor index the pulse holds.
        index: u8,
        /// The descriptors the file defines, as text: `2 descriptors: 1, 2`.
        defined: String,
    },
    /// The `.wvs` file beside the `.pls` file does not exist.
    #[error("{pls}: no waves file beside it: neither {lower} nor {upper} exists")]
    MissingWaves {
        /// The `.pls` path.
        pls: String,
        /// The lower-case `.wvs` path looked for.
        lower: String,
        /// The upper-case `.WVS` path looked for.
        upper: String,
    },
}

impl PulseWavesError {
    pub(crate) fn invalid(file: &str, field: impl Into<String>, reason: impl Into<String>) -> Self {
        PulseWavesError::Invalid {
            file: file.to_string(),
            field: field.into(),
            reason: reason.into(),
        }
    }

    pub(crate) fn unsupported(
        file: &str,
        field: impl Into<String>,
        reason: impl Into<String>,
    ) -> Self {
        PulseWavesError::Unsupported {
            file: file.to_string(),
            field: field.into(),
            reason: reason.into(),
        }
    }

    pub(crate) fn truncated(
        file: &str,
        what: impl Into<String>,
        start: u64,
        end: u64,
        len: u64,
    ) -> Self {
        PulseWavesError::Truncated {
            file: file.to_string(),
            what: what.into(),
            start,
            end,
            len,
        }
    }

    pub(crate) fn io(file: &str, source: std::io::Error) -> Self {
        PulseWavesError::Io {
            file: file.to_string(),
            source,
        }
    }
}
