//! Errors of loading a configuration file: every problem found, each with the field's path, the
//! reason and, where known, its line and column in the file.

use std::fmt;
use std::path::PathBuf;

/// What kind of problem a [`ConfigIssue`] is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IssueKind {
    /// The file could not be read (missing, a directory, unreadable, not UTF-8).
    Io,
    /// The file is not valid TOML.
    Syntax,
    /// The file is valid TOML but does not fit the schema (unknown key, wrong type, missing key).
    Schema,
    /// The values fit the schema but are not acceptable (out of range, inconsistent).
    Invalid,
    /// The file's kind (which schema it follows) is not one this build validates.
    UnknownKind,
    /// A `--set KEY=VALUE` override cannot be applied (not `KEY=VALUE`, not a key path, or a
    /// path through a value that is not a table or list, or past the end of a list).
    Override,
}

/// A position in a file, both 1-based; the column counts characters, not bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Location {
    /// Line, starting at 1.
    pub line: usize,
    /// Column in characters, starting at 1.
    pub column: usize,
}

impl Location {
    /// The location of byte `offset` in `text` (clamped to the text's end).
    pub fn from_offset(text: &str, offset: usize) -> Location {
        let mut offset = offset.min(text.len());
        while !text.is_char_boundary(offset) {
            offset -= 1;
        }
        let before = &text[..offset];
        let line = before.matches('\n').count() + 1;
        let line_start = before.rfind('\n').map_or(0, |i| i + 1);
        let column = before[line_start..].chars().count() + 1;
        Location { line, column }
    }
}

/// One problem in a configuration file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigIssue {
    /// What kind of problem this is.
    pub kind: IssueKind,
    /// The field's path, dotted with indices, e.g. `pipeline.stages[0].cutoff_ghz`; empty when
    /// the problem concerns the whole file.
    pub path: String,
    /// Why it is a problem, in words.
    pub reason: String,
    /// Where in the file, when known.
    pub location: Option<Location>,
}

/// Every problem found in one configuration file (never empty when returned as an error).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct ConfigErrors {
    /// The file, as given to the loader.
    pub file: PathBuf,
    /// The problems, in the order of their position in the file (unknown positions last).
    pub issues: Vec<ConfigIssue>,
}

impl ConfigErrors {
    /// Errors of `file` consisting of one issue.
    pub fn single(
        file: impl Into<PathBuf>,
        kind: IssueKind,
        path: impl Into<String>,
        reason: impl Into<String>,
        location: Option<Location>,
    ) -> ConfigErrors {
        ConfigErrors {
            file: file.into(),
            issues: vec![ConfigIssue {
                kind,
                path: path.into(),
                reason: reason.into(),
                location,
            }],
        }
    }
}

/// One line per issue: `FILE:LINE:COL: field.path: reason` (`LINE:COL` omitted when unknown, the
/// path omitted when the issue concerns the whole file).
impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, issue) in self.issues.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{}:", self.file.display())?;
            if let Some(loc) = issue.location {
                write!(f, "{}:{}:", loc.line, loc.column)?;
            }
            if !issue.path.is_empty() {
                write!(f, " {}:", issue.path)?;
            }
            write!(f, " {}", issue.reason)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn location_counts_lines_and_characters() {
        let text = "a = 1\nbé = 2\n";
        assert_eq!(
            Location::from_offset(text, 0),
            Location { line: 1, column: 1 }
        );
        // 'b' 'é' ' ' '=' : byte offset of '=' is 6 + 1 + 2 + 1 = 10, column 4.
        assert_eq!(
            Location::from_offset(text, 10),
            Location { line: 2, column: 4 }
        );
        assert_eq!(
            Location::from_offset(text, 999),
            Location { line: 3, column: 1 }
        );
    }

    #[test]
    fn display_is_one_line_per_issue() {
        let errors = ConfigErrors {
            file: "x.toml".into(),
            issues: vec![
                ConfigIssue {
                    kind: IssueKind::Schema,
                    path: "a.b".into(),
                    reason: "bad".into(),
                    location: Some(Location { line: 3, column: 7 }),
                },
                ConfigIssue {
                    kind: IssueKind::Invalid,
                    path: "c".into(),
                    reason: "worse".into(),
                    location: None,
                },
                ConfigIssue {
                    kind: IssueKind::Io,
                    path: String::new(),
                    reason: "gone".into(),
                    location: None,
                },
            ],
        };
        assert_eq!(
            errors.to_string(),
            "x.toml:3:7: a.b: bad\nx.toml: c: worse\nx.toml: gone"
        );
    }
}
