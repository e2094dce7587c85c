//! `--set KEY=VALUE` overrides of a TOML configuration, shared by `fwlidar replay`, `fwlidar run`
//! (run configurations, through [`crate::config::load_run_config_with`]) and `fwlidar simulate` /
//! `fwlidar tradeoff` (described scenes).
//!
//! - `KEY` is a path of bare keys joined by `.`, each key optionally followed by list indices
//!   counted from 0: `output.las`, `voxels.enabled`, `pipeline.stages[1].max_taps`. Keys are
//!   made of letters, digits, `_` and `-` (every key of this project's schemas is); quoted keys
//!   are not read.
//! - `VALUE` is a TOML value (`true`, `128`, `8.5`, `"text"`, `[1, 2]`, `{ a = 1 }`); text that is
//!   not one TOML value is taken as a string, so `--set output.dir=out/run1` needs no quotes.
//! - Overrides apply in the order given (a later one wins) to the parsed TOML before it is
//!   deserialized, so a misspelt key or a value of the wrong type is found by the same checks as
//!   in a file. A table missing along the path is created; a list index must name an element that
//!   exists (`pipeline.stages[5]` of a three-stage chain is refused).

use std::fmt::Write as _;

use toml::{Table, Value};

/// One step of an override's key path.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum KeySeg {
    /// A key of a table.
    Key(String),
    /// An element of a list, from 0.
    Index(usize),
}

/// One parsed `KEY=VALUE` override.
#[derive(Clone, Debug, PartialEq)]
pub struct Override {
    /// The key path (never empty; starts with a key).
    pub path: Vec<KeySeg>,
    /// The value to put there.
    pub value: Value,
    /// The override as given, for messages.
    pub text: String,
}

/// Why an override cannot be read or applied. The message starts with the override as given;
/// callers prefix `--set `.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum OverrideError {
    /// No `=` in the text.
    #[error("`{text}` is not KEY=VALUE")]
    NotKeyValue {
        /// The override as given.
        text: String,
    },
    /// The key is not a path of bare keys and indices.
    #[error(
        "`{text}`: `{key}` is not a key path (keys of letters, digits, `_` or `-` joined by `.`, \
         each optionally followed by list indices, e.g. pipeline.stages[1].max_taps)"
    )]
    BadKey {
        /// The override as given.
        text: String,
        /// The key part.
        key: String,
    },
    /// A step of the path goes through a value that is not a table.
    #[error("`{text}`: `{at}` is {found}, not a table")]
    NotATable {
        /// The override as given.
        text: String,
        /// The path up to the value in the way.
        at: String,
        /// What the value is (`an integer`, `a list`, ...).
        found: &'static str,
    },
    /// An index step goes through a value that is not a list.
    #[error("`{text}`: `{at}` is {found}, not a list")]
    NotAList {
        /// The override as given.
        text: String,
        /// The path up to the value in the way.
        at: String,
        /// What the value is (`absent`, `a table`, ...).
        found: &'static str,
    },
    /// An index past the end of a list.
    #[error("`{text}`: `{at}` has {len} entries; there is no index {index}")]
    OutOfRange {
        /// The override as given.
        text: String,
        /// The list's path.
        at: String,
        /// Its length.
        len: usize,
        /// The index asked for.
        index: usize,
    },
}

impl OverrideError {
    /// The dotted key path the error concerns, where there is one (empty otherwise).
    pub fn at(&self) -> &str {
        match self {
            OverrideError::NotKeyValue { .. } | OverrideError::BadKey { .. } => "",
            OverrideError::NotATable { at, .. }
            | OverrideError::NotAList { at, .. }
            | OverrideError::OutOfRange { at, .. } => at,
        }
    }
}

/// The dotted form of a key path, as the configuration loader names fields:
/// `pipeline.stages[1].max_taps`.
pub fn dotted(path: &[KeySeg]) -> String {
    let mut s = String::new();
    for seg in path {
        match seg {
            KeySeg::Key(k) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(k);
            }
            KeySeg::Index(i) => {
                let _ = write!(s, "[{i}]");
            }
        }
    }
    s
}

fn is_bare_key(k: &str) -> bool {
    !k.is_empty()
        && k.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// Parses a key path such as `pipeline.stages[1].max_taps`; `None` if it is not one.
fn parse_key(key: &str) -> Option<Vec<KeySeg>> {
    let mut path = Vec::new();
    for part in key.split('.') {
        let (name, mut rest) = part.split_at(part.find('[').unwrap_or(part.len()));
        if !is_bare_key(name) {
            return None;
        }
        path.push(KeySeg::Key(name.to_string()));
        while !rest.is_empty() {
            let inner = rest.strip_prefix('[')?;
            let close = inner.find(']')?;
            let digits = &inner[..close];
            if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                return None;
            }
            path.push(KeySeg::Index(digits.parse().ok()?));
            rest = &inner[close + 1..];
        }
    }
    Some(path)
}

/// Reads `VALUE` as one TOML value, else as a string.
fn parse_value(text: &str) -> Value {
    toml::from_str::<Table>(&format!("v = {text}"))
        .ok()
        .filter(|t| t.len() == 1)
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| Value::String(text.to_string()))
}

impl Override {
    /// Parses `KEY=VALUE` (split at the first `=`; spaces around the key are ignored).
    pub fn parse(text: &str) -> Result<Override, OverrideError> {
        let (key, value) = text
            .split_once('=')
            .ok_or_else(|| OverrideError::NotKeyValue {
                text: text.to_string(),
            })?;
        let path = parse_key(key.trim()).ok_or_else(|| OverrideError::BadKey {
            text: text.to_string(),
            key: key.trim().to_string(),
        })?;
        Ok(Override {
            path,
            value: parse_value(value.trim()),
            text: text.to_string(),
        })
    }

    /// The key path in dotted form ([`dotted`]).
    pub fn key(&self) -> String {
        dotted(&self.path)
    }

    /// Puts the value at the key path in `table`, creating missing tables on the way.
    pub fn apply(&self, table: &mut Table) -> Result<(), OverrideError> {
        let mut root = Value::Table(std::mem::take(table));
        let result = self.put(&mut root);
        if let Value::Table(t) = root {
            *table = t;
        }
        result
    }

    fn put(&self, root: &mut Value) -> Result<(), OverrideError> {
        let mut node = root;
        // Whether `node` is a table this walk created (so absent from the configuration).
        let mut created = false;
        for (n, seg) in self.path.iter().enumerate() {
            let last = n + 1 == self.path.len();
            let at = dotted(&self.path[..n]);
            let found = if created { "absent" } else { kind_of(node) };
            node = match seg {
                KeySeg::Key(k) => {
                    let Value::Table(t) = node else {
                        return Err(OverrideError::NotATable {
                            text: self.text.clone(),
                            at,
                            found,
                        });
                    };
                    if last {
                        t.insert(k.clone(), self.value.clone());
                        return Ok(());
                    }
                    created = !t.contains_key(k);
                    t.entry(k.clone())
                        .or_insert_with(|| Value::Table(Table::new()))
                }
                KeySeg::Index(i) => {
                    let Value::Array(a) = node else {
                        return Err(OverrideError::NotAList {
                            text: self.text.clone(),
                            at,
                            found,
                        });
                    };
                    let len = a.len();
                    let Some(slot) = a.get_mut(*i) else {
                        return Err(OverrideError::OutOfRange {
                            text: self.text.clone(),
                            at,
                            len,
                            index: *i,
                        });
                    };
                    if last {
                        *slot = self.value.clone();
                        return Ok(());
                    }
                    slot
                }
            };
        }
        // Only reached for an empty path, which `parse` never makes.
        Err(OverrideError::BadKey {
            text: self.text.clone(),
            key: String::new(),
        })
    }
}

/// What a TOML value is, in words.
fn kind_of(v: &Value) -> &'static str {
    match v {
        Value::String(_) => "a string",
        Value::Integer(_) => "an integer",
        Value::Float(_) => "a float",
        Value::Boolean(_) => "a boolean",
        Value::Datetime(_) => "a date-time",
        Value::Array(_) => "a list",
        Value::Table(_) => "a table",
    }
}

/// Parses every `KEY=VALUE` of `sets` and applies them in order to `table`; returns them parsed.
/// On an error `table` may hold the overrides before the failing one.
pub fn apply_all(
    table: &mut Table,
    sets: &[impl AsRef<str>],
) -> Result<Vec<Override>, OverrideError> {
    let mut applied = Vec::with_capacity(sets.len());
    for set in sets {
        let o = Override::parse(set.as_ref())?;
        o.apply(table)?;
        applied.push(o);
    }
    Ok(applied)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(text: &str) -> Table {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn overrides_parse_keys_indices_and_values() {
        let o = Override::parse("pipeline.stages[1].max_taps=128").unwrap();
        assert_eq!(
            o.path,
            vec![
                KeySeg::Key("pipeline".into()),
                KeySeg::Key("stages".into()),
                KeySeg::Index(1),
                KeySeg::Key("max_taps".into()),
            ]
        );
        assert_eq!(o.value, Value::Integer(128));
        assert_eq!(o.key(), "pipeline.stages[1].max_taps");
        assert_eq!(
            Override::parse(" output.las = true").unwrap().value,
            Value::Boolean(true)
        );
        assert_eq!(Override::parse("x=8.5").unwrap().value, Value::Float(8.5));
        // Not TOML: a string, `=` after the first belongs to the value.
        assert_eq!(
            Override::parse("output.dir=out/a=b").unwrap().value,
            Value::String("out/a=b".into())
        );
        assert_eq!(
            Override::parse("s=\"quoted\"").unwrap().value,
            Value::String("quoted".into())
        );
        // Text that would smuggle in a second key is not one value: kept as a string.
        assert_eq!(
            Override::parse("a=1\nb = 2").unwrap().value,
            Value::String("1\nb = 2".into())
        );
        assert_eq!(
            Override::parse("a.b[0][2]=[1, 2]").unwrap().key(),
            "a.b[0][2]"
        );
    }

    #[test]
    fn overrides_refuse_malformed_keys() {
        assert!(matches!(
            Override::parse("output.las"),
            Err(OverrideError::NotKeyValue { .. })
        ));
        for bad in [
            "=1",
            "a..b=1",
            ".a=1",
            "a.=1",
            "a[]=1",
            "a[x]=1",
            "a[1=1",
            "a[1]b=1",
            "[1]=1",
            "a.[1]=1",
            "\"a.b\"=1",
            "a b=1",
            "a[-1]=1",
        ] {
            let e = Override::parse(bad).unwrap_err();
            assert!(
                matches!(e, OverrideError::BadKey { .. }),
                "{bad:?} gave {e:?}"
            );
            assert!(e.to_string().contains("not a key path"), "{e}");
        }
    }

    #[test]
    fn overrides_set_existing_and_create_missing_tables() {
        let mut t = table(
            "[output]\nlas = false\n[[pipeline.stages]]\ntype = \"a\"\n[[pipeline.stages]]\ntype = \"b\"\n",
        );
        apply_all(
            &mut t,
            &[
                "output.las=true",
                "voxels.enabled=false",
                "pipeline.stages[1].max_taps=128",
                "top=3",
                "top=4",
            ],
        )
        .unwrap();
        assert_eq!(t["output"]["las"], Value::Boolean(true));
        assert_eq!(t["voxels"]["enabled"], Value::Boolean(false));
        assert_eq!(t["pipeline"]["stages"][1]["max_taps"], Value::Integer(128));
        assert_eq!(
            t["pipeline"]["stages"][1]["type"],
            Value::String("b".into())
        );
        assert!(t["pipeline"]["stages"][0].get("max_taps").is_none());
        assert_eq!(t["top"], Value::Integer(4), "a later override wins");
        // A whole list element can be replaced.
        let mut t2 = t.clone();
        Override::parse("pipeline.stages[0]={ type = \"c\" }")
            .unwrap()
            .apply(&mut t2)
            .unwrap();
        assert_eq!(
            t2["pipeline"]["stages"][0]["type"],
            Value::String("c".into())
        );
    }

    #[test]
    fn overrides_name_what_is_in_the_way() {
        let mut t = table("[output]\nlas = false\n[[pipeline.stages]]\ntype = \"a\"\n");
        let e = Override::parse("output.las.x=1")
            .unwrap()
            .apply(&mut t)
            .unwrap_err();
        assert_eq!(
            e,
            OverrideError::NotATable {
                text: "output.las.x=1".into(),
                at: "output.las".into(),
                found: "a boolean"
            }
        );
        assert_eq!(e.at(), "output.las");
        let e = Override::parse("pipeline.stages[3].x=1")
            .unwrap()
            .apply(&mut t)
            .unwrap_err();
        assert_eq!(e.at(), "pipeline.stages");
        assert_eq!(
            e.to_string(),
            "`pipeline.stages[3].x=1`: `pipeline.stages` has 1 entries; there is no index 3"
        );
        let e = Override::parse("output[0]=1")
            .unwrap()
            .apply(&mut t)
            .unwrap_err();
        assert!(
            e.to_string().contains("`output` is a table, not a list"),
            "{e}"
        );
        let e = Override::parse("nothing.here[0]=1")
            .unwrap()
            .apply(&mut t)
            .unwrap_err();
        assert!(
            e.to_string()
                .contains("`nothing.here` is absent, not a list"),
            "{e}"
        );
        let e = apply_all(&mut t, &["nokeyvalue"]).unwrap_err();
        assert_eq!(e.at(), "");
    }
}
