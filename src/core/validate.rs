//! Semantic checks of a deserialized configuration ([`Validate`]): every problem collected by a
//! [`Validator`] with the dotted path of its field (`pipeline.stages[0].cutoff_ghz`), so that a
//! file's problems are reported at once, before a run starts.

use std::path::{Path, PathBuf};

/// Semantic checks of a deserialized configuration: values in range and consistent.
pub trait Validate {
    /// Reports every problem of `self` to `v`, with field paths below `path` (`""` at the top
    /// of a file; join with [`field`] and [`index`]).
    fn validate(&self, path: &str, v: &mut Validator);
}

/// Collects the problems found by [`Validate`] and carries what the checks need to know beyond
/// the value itself.
#[derive(Debug, Default)]
pub struct Validator {
    base_dir: Option<PathBuf>,
    sample_interval_ns: Option<f64>,
    issues: Vec<(String, String)>,
}

impl Validator {
    /// A validator for a file in `base_dir` (relative references are resolved against it).
    pub fn new(base_dir: Option<PathBuf>) -> Validator {
        Validator {
            base_dir,
            ..Validator::default()
        }
    }

    /// Records a problem of the field at `path`.
    pub fn report(&mut self, path: impl Into<String>, reason: impl Into<String>) {
        self.issues.push((path.into(), reason.into()));
    }

    /// Records `reason` at `path` unless `ok`.
    pub fn require(&mut self, ok: bool, path: impl Into<String>, reason: impl Into<String>) {
        if !ok {
            self.report(path, reason);
        }
    }

    /// Checks that `value` is a finite number greater than zero.
    pub fn positive(&mut self, value: f64, path: impl Into<String>) {
        self.require(
            value.is_finite() && value > 0.0,
            path,
            format!("must be a positive number, got {value}"),
        );
    }

    /// The folder of the file being validated, if it came from a file.
    pub fn base_dir(&self) -> Option<&Path> {
        self.base_dir.as_deref()
    }

    /// The digitizer sample interval in force (from the referenced sensor profile), nanoseconds.
    pub fn sample_interval_ns(&self) -> Option<f64> {
        self.sample_interval_ns
    }

    /// Sets the digitizer sample interval in force, nanoseconds.
    pub fn set_sample_interval_ns(&mut self, ns: Option<f64>) {
        self.sample_interval_ns = ns;
    }

    /// The problems recorded so far, as (path, reason).
    pub fn issues(&self) -> &[(String, String)] {
        &self.issues
    }

    /// The problems recorded, as (path, reason), taken out.
    pub fn into_issues(self) -> Vec<(String, String)> {
        self.issues
    }
}

/// The path of field `name` below `path`.
pub fn field(path: &str, name: &str) -> String {
    if path.is_empty() {
        name.to_string()
    } else {
        format!("{path}.{name}")
    }
}

/// The path of element `i` of the list at `path`.
pub fn index(path: &str, i: usize) -> String {
    format!("{path}[{i}]")
}
