//! Loading a configuration file with every error reported at once.
//!
//! serde stops at the first error, so the loader works in rounds on a parsed TOML value:
//!
//! 1. Parse the text (all syntax errors, with line and column; nothing else is tried after one).
//! 2. Deserialize with `serde_path_to_error` to learn the path of the first error; record it and
//!    repair the value so the next round gets further: an unknown key is removed; a value of the
//!    wrong type is removed (the field's default, if any, takes its place); a missing required
//!    key gets a placeholder whose consequences are not reported; an entry of a tagged list
//!    (`[[pipeline.stages]]`) with an unknown `type` is removed. Repeat, up to a bound.
//! 3. When the value deserializes, run the semantic checks ([`Validate`]); issues about fields
//!    already reported (or repaired) are left out.
//!
//! Every issue carries the dotted path of the field (`pipeline.stages[0].cutoff_ghz`), a reason,
//! and the line and column of the key or value in the file where it exists there.

use std::fmt::Write as _;
use std::io::ErrorKind;
use std::ops::Range;
use std::path::Path;

use serde::de::DeserializeOwned;
use toml::de::{DeTable, DeValue};
use toml::{Spanned, Table, Value};

use super::config_error::{ConfigErrors, ConfigIssue, IssueKind, Location};
use super::validate::{Validate, Validator};

/// Bound on the repair rounds of one file (each round finds at most one schema error).
const MAX_ROUNDS: usize = 200;

/// Largest configuration file (run, sensor profile, scene) that is read, bytes: far above any
/// real one (a few KiB), low enough that a path naming a device such as `/dev/zero` or a huge
/// file is refused instead of read until memory runs out.
pub const MAX_CONFIG_BYTES: u64 = 1024 * 1024;

/// Reads at most [`MAX_CONFIG_BYTES`] of the file at `path`; a longer file is an
/// [`ErrorKind::InvalidData`] error saying so (without reading the rest).
pub(crate) fn read_bounded(path: &Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read as _;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(MAX_CONFIG_BYTES + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(std::io::Error::new(
            ErrorKind::InvalidData,
            format!("larger than {MAX_CONFIG_BYTES} bytes; not a configuration file"),
        ));
    }
    Ok(bytes)
}

/// Reads, parses, deserializes and validates the file at `path` as a `T`, reporting every
/// problem found (see the module documentation). Never panics.
pub fn load_file<T: DeserializeOwned + Validate>(
    path: impl AsRef<Path>,
) -> Result<T, ConfigErrors> {
    load_file_with(path, &[] as &[&str])
}

/// As [`load_file`], with `--set KEY=VALUE` overrides ([`super::overrides`]) applied to the
/// parsed file before it is checked. A problem with an overridden field is reported like one
/// in the file, without a line and column, its reason ending `(from --set KEY=VALUE)`; an
/// override that cannot be applied (not `KEY=VALUE`, an index past the end of a list) is an
/// issue of kind [`IssueKind::Override`].
pub fn load_file_with<T: DeserializeOwned + Validate>(
    path: impl AsRef<Path>,
    sets: &[impl AsRef<str>],
) -> Result<T, ConfigErrors> {
    let path = path.as_ref();
    let text = read_text(path)?;
    load_str_with(&text, path, sets)
}

/// As [`load_file`], for `text` that came from `origin` (used in messages and to resolve
/// relative references such as `sensor_profile`).
pub fn load_str<T: DeserializeOwned + Validate>(
    text: &str,
    origin: impl AsRef<Path>,
) -> Result<T, ConfigErrors> {
    load_str_with(text, origin, &[] as &[&str])
}

/// As [`load_file_with`], for `text` that came from `origin`.
pub fn load_str_with<T: DeserializeOwned + Validate>(
    text: &str,
    origin: impl AsRef<Path>,
    sets: &[impl AsRef<str>],
) -> Result<T, ConfigErrors> {
    let origin = origin.as_ref();
    let mut doc = parse(text, origin)?;
    let overrides = super::overrides::apply_all(&mut doc.table, sets).map_err(|e| {
        ConfigErrors::single(
            origin,
            IssueKind::Override,
            e.at(),
            format!("--set {e}"),
            None,
        )
    })?;
    let mut loader = Loader::new(text, origin, &doc.spans);
    loader.overrides = overrides
        .iter()
        .map(|o| (o.key(), o.text.clone()))
        .collect();
    loader.run(doc.table)
}

/// Reads the file at `path` and parses it as TOML: its text and the names of its top-level
/// keys and tables, for a caller that decides the kind of a file by what it holds (`fwlidar
/// validate`, `cli/validate.rs`) and then loads the text with [`load_str`]. Errors (unreadable,
/// not UTF-8, invalid TOML) are reported as by [`load_file`].
pub fn read_top_level_keys(path: impl AsRef<Path>) -> Result<(String, Vec<String>), ConfigErrors> {
    let path = path.as_ref();
    let text = read_text(path)?;
    let keys = parse(&text, path)?.table.keys().cloned().collect();
    Ok((text, keys))
}

/// Reads a configuration file as UTF-8 text, naming the file in every error.
fn read_text(path: &Path) -> Result<String, ConfigErrors> {
    let io_error = |reason: String| ConfigErrors::single(path, IssueKind::Io, "", reason, None);
    if path.is_dir() {
        return Err(io_error(
            "is a directory; expected a TOML configuration file".into(),
        ));
    }
    let bytes = read_bounded(path).map_err(|e| {
        io_error(match e.kind() {
            ErrorKind::NotFound => "no such file".to_string(),
            ErrorKind::PermissionDenied => "permission denied".to_string(),
            ErrorKind::InvalidData => e.to_string(),
            _ => format!("cannot read: {e}"),
        })
    })?;
    String::from_utf8(bytes).map_err(|e| {
        let valid = e.utf8_error().valid_up_to();
        let text = String::from_utf8_lossy(&e.as_bytes()[..valid]);
        ConfigErrors::single(
            path,
            IssueKind::Io,
            "",
            format!("not UTF-8 text (invalid byte at offset {valid}); TOML files must be UTF-8"),
            Some(Location::from_offset(&text, valid)),
        )
    })
}

/// A parsed document: the value to deserialize, and the spans of its keys and values.
struct Document<'t> {
    table: Table,
    spans: Spanned<DeTable<'t>>,
}

/// Parses TOML text, reporting every syntax error the parser recovers from.
fn parse<'t>(text: &'t str, origin: &Path) -> Result<Document<'t>, ConfigErrors> {
    let (spans, errors) = DeTable::parse_recoverable(text);
    let syntax = |e: &toml::de::Error| ConfigIssue {
        kind: IssueKind::Syntax,
        path: String::new(),
        reason: format!("invalid TOML: {}", e.message().trim_end()),
        location: e.span().map(|s| Location::from_offset(text, s.start)),
    };
    if !errors.is_empty() {
        return Err(ConfigErrors {
            file: origin.to_path_buf(),
            issues: errors.iter().map(syntax).collect(),
        });
    }
    match toml::from_str::<Table>(text) {
        Ok(table) => Ok(Document { table, spans }),
        Err(e) => Err(ConfigErrors {
            file: origin.to_path_buf(),
            issues: vec![syntax(&e)],
        }),
    }
}

/// One step of a field path.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Seg {
    Key(String),
    Index(usize),
}

fn path_string(path: &[Seg]) -> String {
    let mut s = String::new();
    for seg in path {
        match seg {
            Seg::Key(k) if s.is_empty() => s.push_str(k),
            Seg::Key(k) => {
                s.push('.');
                s.push_str(k);
            }
            Seg::Index(i) => {
                let _ = write!(s, "[{i}]");
            }
        }
    }
    s
}

/// Whether the dotted path `path` is `prefix` or lies below it.
fn is_under(path: &str, prefix: &str) -> bool {
    prefix.is_empty()
        || path == prefix
        || (path.starts_with(prefix)
            && matches!(path.as_bytes().get(prefix.len()), Some(b'.' | b'[')))
}

fn get<'v>(root: &'v Value, path: &[Seg]) -> Option<&'v Value> {
    path.iter().try_fold(root, |v, seg| match (seg, v) {
        (Seg::Key(k), Value::Table(t)) => t.get(k),
        (Seg::Index(i), Value::Array(a)) => a.get(*i),
        _ => None,
    })
}

fn get_mut<'v>(root: &'v mut Value, path: &[Seg]) -> Option<&'v mut Value> {
    path.iter().try_fold(root, |v, seg| match (seg, v) {
        (Seg::Key(k), Value::Table(t)) => t.get_mut(k),
        (Seg::Index(i), Value::Array(a)) => a.get_mut(*i),
        _ => None,
    })
}

/// Removes the value at `path`; false if there is none (or `path` is the root).
fn remove(root: &mut Value, path: &[Seg]) -> bool {
    let Some((last, parent)) = path.split_last() else {
        return false;
    };
    match (last, get_mut(root, parent)) {
        (Seg::Key(k), Some(Value::Table(t))) => t.remove(k).is_some(),
        (Seg::Index(i), Some(Value::Array(a))) if *i < a.len() => {
            a.remove(*i);
            true
        }
        _ => false,
    }
}

/// Sets the key at `path` (whose parent must be a table) to `value`.
fn set(root: &mut Value, path: &[Seg], value: Value) -> bool {
    let Some((Seg::Key(k), parent)) = path.split_last() else {
        return false;
    };
    match get_mut(root, parent) {
        Some(Value::Table(t)) => {
            t.insert(k.clone(), value);
            true
        }
        _ => false,
    }
}

/// The name between the first pair of backticks of a serde message.
fn quoted_name(message: &str) -> Option<&str> {
    let start = message.find('`')? + 1;
    let len = message[start..].find('`')?;
    Some(&message[start..start + len])
}

/// If `path` is the `type` key of a table that is an element of a list, the element's path.
fn tag_of_list_entry(root: &Value, path: &[Seg]) -> Option<Vec<Seg>> {
    let (last, entry) = path.split_last()?;
    if *last != Seg::Key("type".into()) || !matches!(entry.last(), Some(Seg::Index(_))) {
        return None;
    }
    matches!(get(root, entry), Some(Value::Table(_))).then(|| entry.to_vec())
}

/// Values tried, in order, in place of a missing required key so later errors can be found.
fn placeholders() -> [Value; 5] {
    [
        Value::Integer(0),
        Value::String(String::new()),
        Value::Boolean(false),
        Value::Table(Table::new()),
        Value::Array(Vec::new()),
    ]
}

/// Deserializes a whole document as the loader's target type: the path and message of the first
/// error.
type Probe<'p> = &'p dyn Fn(Value) -> Result<(), (Vec<Seg>, String)>;

fn probe<T: DeserializeOwned>(value: Value) -> Result<(), (Vec<Seg>, String)> {
    serde_path_to_error::deserialize::<_, T>(value)
        .map(|_| ())
        .map_err(|e| (to_segs(e.path()), e.inner().message().to_string()))
}

/// What a round's error tells the loader to do.
enum Repair {
    /// Remove the value at this (current) path.
    Remove(Vec<Seg>),
    /// Put placeholder number `n` at this (current) path.
    Placeholder(Vec<Seg>, usize),
}

/// The rounds of deserialization and repair for one document.
struct Loader<'a, 't> {
    text: &'a str,
    origin: &'a Path,
    spans: &'a Spanned<DeTable<'t>>,
    /// Original indices removed from each list, by the list's original dotted path.
    removed: Vec<(String, Vec<usize>)>,
    /// Placeholders in force: original dotted path, current path, candidate number.
    placed: Vec<(String, Vec<Seg>, usize)>,
    /// The `--set` overrides applied: dotted key path, override as given.
    overrides: Vec<(String, String)>,
    issues: Vec<ConfigIssue>,
}

impl<'a, 't> Loader<'a, 't> {
    fn new(text: &'a str, origin: &'a Path, spans: &'a Spanned<DeTable<'t>>) -> Self {
        Loader {
            text,
            origin,
            spans,
            removed: Vec::new(),
            placed: Vec::new(),
            overrides: Vec::new(),
            issues: Vec::new(),
        }
    }

    fn run<T: DeserializeOwned + Validate>(mut self, table: Table) -> Result<T, ConfigErrors> {
        let mut root = Value::Table(table);
        let mut parsed = None;
        for _ in 0..MAX_ROUNDS {
            match serde_path_to_error::deserialize::<_, T>(root.clone()) {
                Ok(value) => {
                    parsed = Some(value);
                    break;
                }
                Err(e) => {
                    let path = to_segs(e.path());
                    let message = e.inner().message().to_string();
                    if !self.repair(&mut root, path, &message, &probe::<T>) {
                        break;
                    }
                }
            }
        }
        let Some(value) = parsed else {
            if self.issues.is_empty() {
                // Only reachable if a repair could not be made for an error already reported
                // as a consequence; say so rather than return nothing.
                self.issues.push(ConfigIssue {
                    kind: IssueKind::Schema,
                    path: String::new(),
                    reason: "the file does not fit the schema".into(),
                    location: None,
                });
            }
            return Err(self.finish());
        };
        let mut v = Validator::new(self.origin.parent().map(Path::to_path_buf));
        value.validate("", &mut v);
        let skip: Vec<String> = self
            .issues
            .iter()
            .map(|i| i.path.clone())
            .chain(self.placed.iter().map(|p| p.0.clone()))
            .collect();
        for (path, reason) in v.into_issues() {
            // Paths of the validated value are current paths: map them back to the file's.
            let path = self.original(&dotted_to_segs(&path));
            // A field already reported (or filled in) is not judged again, nor is a list or
            // table that lost entries to a reported problem.
            if skip
                .iter()
                .any(|s| !s.is_empty() && (is_under(&path, s) || is_under(s, &path)))
            {
                continue;
            }
            let (location, reason) = self.origin_of(&path, reason, false);
            self.issues.push(ConfigIssue {
                kind: IssueKind::Invalid,
                path,
                reason,
                location,
            });
        }
        if self.issues.is_empty() {
            Ok(value)
        } else {
            Err(self.finish())
        }
    }

    fn finish(mut self) -> ConfigErrors {
        self.issues.sort_by_key(|i| {
            i.location
                .map_or((usize::MAX, usize::MAX), |l| (l.line, l.column))
        });
        ConfigErrors {
            file: self.origin.to_path_buf(),
            issues: self.issues,
        }
    }

    /// Records the error of one round and repairs `root`; false when no progress is possible.
    fn repair(
        &mut self,
        root: &mut Value,
        mut path: Vec<Seg>,
        message: &str,
        probe: Probe,
    ) -> bool {
        let mut message = message.to_string();
        // Inside an internally tagged enum (`type = "..."`) serde buffers the table, so the path
        // stops at the table: find the culprit key.
        if let Some((key, msg)) = self.narrow_tagged(root, &path, &message, probe) {
            path.push(Seg::Key(key));
            message = msg;
        }
        let action;
        let reason;
        if let Some(name) = message
            .strip_prefix("unknown field ")
            .and_then(|_| quoted_name(&message))
        {
            if path.last() != Some(&Seg::Key(name.to_string())) {
                path.push(Seg::Key(name.to_string()));
            }
            reason = message.replacen("unknown field", "unknown key", 1);
            action = Repair::Remove(path.clone());
        } else if let Some(name) = message
            .strip_prefix("missing field ")
            .and_then(|_| quoted_name(&message))
        {
            let name = name.to_string();
            let tag_missing = name == "type"
                && matches!(get(root, &path), Some(Value::Table(t)) if !t.contains_key("type"));
            reason = format!("missing required key `{name}`");
            if tag_missing {
                action = Repair::Remove(path.clone());
                path.push(Seg::Key(name));
            } else {
                path.push(Seg::Key(name));
                action = Repair::Placeholder(path.clone(), 0);
            }
        } else if let Some(entry) = tag_of_list_entry(root, &path) {
            // The `type` of a tagged list entry (`[[pipeline.stages]]`) is unknown or not a
            // string: the entry is unusable; drop it.
            action = Repair::Remove(entry);
            reason = message.clone();
        } else if message.starts_with("unknown variant") && self.is_tagged(root, &path) {
            action = Repair::Remove(path.clone());
            path.push(Seg::Key("type".into()));
            reason = message.clone();
        } else if let Some(n) = self.placeholder_at(&path) {
            // Our own placeholder has the wrong type: try the next one, report nothing.
            return self.place(root, path, n + 1);
        } else {
            reason = message.clone();
            action = Repair::Remove(path.clone());
        }

        let original = self.original(&path);
        let consequence = self
            .issues
            .iter()
            .map(|i| i.path.as_str())
            .chain(self.placed.iter().map(|p| p.0.as_str()))
            .any(|p| !p.is_empty() && is_under(&original, p));
        if !consequence {
            let want_key = reason.starts_with("unknown key");
            let (location, reason) = self.origin_of(&original, reason, want_key);
            self.issues.push(ConfigIssue {
                kind: IssueKind::Schema,
                path: original,
                reason,
                location,
            });
        }
        match action {
            Repair::Remove(p) => self.remove(root, &p),
            Repair::Placeholder(p, n) => self.place(root, p, n),
        }
    }

    fn remove(&mut self, root: &mut Value, path: &[Seg]) -> bool {
        if let Some((Seg::Index(i), list)) = path.split_last() {
            let list_orig = self.original(list);
            let orig_index = self.original_index(&list_orig, *i);
            if !remove(root, path) {
                return false;
            }
            match self.removed.iter_mut().find(|(p, _)| *p == list_orig) {
                Some((_, idx)) => idx.push(orig_index),
                None => self.removed.push((list_orig, vec![orig_index])),
            }
            true
        } else {
            remove(root, path)
        }
    }

    fn place(&mut self, root: &mut Value, path: Vec<Seg>, n: usize) -> bool {
        let Some(value) = placeholders().into_iter().nth(n) else {
            return false;
        };
        if !set(root, &path, value) {
            return false;
        }
        let original = self.original(&path);
        self.placed.retain(|p| p.1 != path);
        self.placed.push((original, path, n));
        true
    }

    fn placeholder_at(&self, path: &[Seg]) -> Option<usize> {
        self.placed.iter().find(|p| p.1 == path).map(|p| p.2)
    }

    fn is_tagged(&self, root: &Value, path: &[Seg]) -> bool {
        matches!(get(root, path), Some(Value::Table(t)) if matches!(t.get("type"), Some(Value::String(_))))
    }

    /// For an error reported at a tagged table (`type = "..."`), finds the key that causes it by
    /// deserializing the table with one key at a time. Returns the key and its own message.
    fn narrow_tagged(
        &self,
        root: &Value,
        path: &[Seg],
        message: &str,
        probe: Probe,
    ) -> Option<(String, String)> {
        if message.starts_with("unknown field")
            || message.starts_with("missing field")
            || !self.is_tagged(root, path)
        {
            return None;
        }
        let Some(Value::Table(table)) = get(root, path) else {
            return None;
        };
        let tag = table.get("type")?;
        // An unknown variant is the tag's own (an unknown `type`) unless it names another value:
        // then it is a key's enumerated value (e.g. `start_values = "guess"`), found below.
        if message.starts_with("unknown variant")
            && quoted_name(message).is_none_or(|name| Some(name) == tag.as_str())
        {
            return None;
        }
        // Deserialize the whole document with the entry cut down to its tag and one key: the
        // key whose error reappears at the entry is the culprit. No error before the entry can
        // occur (this error was the first), so an error at the entry is the entry's own.
        for (key, value) in table.iter().filter(|(k, _)| k.as_str() != "type") {
            let mut alone = Table::new();
            alone.insert("type".into(), tag.clone());
            alone.insert(key.clone(), value.clone());
            let mut trial = root.clone();
            if let Some(slot) = get_mut(&mut trial, path) {
                *slot = Value::Table(alone);
            }
            if let Err((at, msg)) = probe(trial)
                && at == path
                && !msg.starts_with("missing field")
            {
                return Some((key.clone(), msg));
            }
        }
        None
    }

    /// Translates a current path (after removals of list elements) to the path in the file.
    fn original(&self, path: &[Seg]) -> String {
        let mut out: Vec<Seg> = Vec::with_capacity(path.len());
        for seg in path {
            match seg {
                Seg::Index(i) => {
                    let list = path_string(&out);
                    out.push(Seg::Index(self.original_index(&list, *i)));
                }
                Seg::Key(k) => out.push(Seg::Key(k.clone())),
            }
        }
        path_string(&out)
    }

    /// The original index of the element now at `i` of the list at original path `list`.
    fn original_index(&self, list: &str, i: usize) -> usize {
        let Some((_, gone)) = self.removed.iter().find(|(p, _)| p == list) else {
            return i;
        };
        let mut survivors = 0;
        let mut j = 0;
        loop {
            if !gone.contains(&j) {
                if survivors == i {
                    return j;
                }
                survivors += 1;
            }
            j += 1;
        }
    }

    /// Where an issue at the (original) dotted `path` comes from, and its reason: a field set
    /// by a `--set` override (at or below its key; the last such override) has no place in the
    /// file and the reason names the override; any other field is located in the file
    /// ([`Loader::location`]).
    fn origin_of(&self, path: &str, reason: String, want_key: bool) -> (Option<Location>, String) {
        match self
            .overrides
            .iter()
            .rev()
            .find(|(key, _)| is_under(path, key))
        {
            Some((_, text)) => (None, format!("{reason} (from --set {text})")),
            None => (self.location(&dotted_to_segs(path), want_key), reason),
        }
    }

    /// The line and column of the field at `path` in the file (of its key when `want_key`,
    /// else of its value); for a field absent from the file, of the nearest enclosing table
    /// written in the file; `None` at the top level.
    fn location(&self, path: &[Seg], want_key: bool) -> Option<Location> {
        let span = span_of(self.spans, path, want_key)?;
        Some(Location::from_offset(self.text, span.start))
    }
}

fn span_of(doc: &Spanned<DeTable<'_>>, path: &[Seg], want_key: bool) -> Option<Range<usize>> {
    enum Node<'d, 'i> {
        Table(&'d DeTable<'i>),
        Array(&'d [Spanned<DeValue<'i>>]),
        Leaf,
    }
    let mut node = Node::Table(doc.get_ref());
    let mut best = None;
    for (n, seg) in path.iter().enumerate() {
        let value = match (seg, node) {
            (Seg::Key(k), Node::Table(t)) => {
                match t
                    .iter()
                    .find(|(key, _)| key.get_ref().as_ref() == k.as_str())
                {
                    Some((key, value)) => {
                        if n + 1 == path.len() && want_key {
                            return Some(key.span());
                        }
                        value
                    }
                    None => break,
                }
            }
            (Seg::Index(i), Node::Array(a)) => match a.get(*i) {
                Some(v) => v,
                None => break,
            },
            _ => break,
        };
        best = Some(value.span());
        node = match value.get_ref() {
            DeValue::Table(t) => Node::Table(t),
            DeValue::Array(a) => Node::Array(&a[..]),
            _ => Node::Leaf,
        };
    }
    best
}

fn to_segs(path: &serde_path_to_error::Path) -> Vec<Seg> {
    path.iter()
        .filter_map(|seg| match seg {
            serde_path_to_error::Segment::Seq { index } => Some(Seg::Index(*index)),
            serde_path_to_error::Segment::Map { key } => Some(Seg::Key(key.clone())),
            _ => None,
        })
        .collect()
}

/// Parses a path written by [`path_string`] (keys of this project's schemas contain no `.`,
/// `[` or `]`).
fn dotted_to_segs(path: &str) -> Vec<Seg> {
    let mut segs = Vec::new();
    for part in path.split('.').filter(|p| !p.is_empty()) {
        let (key, rest) = part.split_at(part.find('[').unwrap_or(part.len()));
        if !key.is_empty() {
            segs.push(Seg::Key(key.to_string()));
        }
        for idx in rest.split('[').filter(|s| !s.is_empty()) {
            if let Ok(i) = idx.trim_end_matches(']').parse() {
                segs.push(Seg::Index(i));
            }
        }
    }
    segs
}
