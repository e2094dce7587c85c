//! The house's layers, checked: every `crate::` and `super::` path in `src/` that leads from one
//! top-level module (a folder or file directly under `src/`) to another must go down the layer
//! list below, and no module may depend on itself through others (no cycle). A failure prints
//! the file and line of each offending path and the rule it breaks.
//!
//! The rule is for test code too (a module's tests use only what its code may use), with one
//! exception: tests may use `fixtures` (where the real-instrument files are) from any layer.
//!
//! This is the guard rail of every later change: adding a module means adding it to a layer
//! here, with a line saying what it is; moving an edge up the list means moving code, not this
//! list.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The layers, bottom first. A module may use the modules of the layers below its own, never
/// those of its own layer or above. Each entry: (modules, what the layer is).
const LAYERS: &[(&[&str], &str)] = &[
    (
        &["core", "fixtures"],
        "the ground floor: units and c, Validate, the TOML loader and --set, the sensor \
         profile, an input's facts, atomic files; where the test data is",
    ),
    (
        &["pulse"],
        "the item that flows: a laser shot, its segments and what stages add",
    ),
    (
        &["pipeline", "format"],
        "the runtime (stage contract, edges, runner, telemetry, its ports) and the raw file \
         and wire formats (capture, frames, LAS, PulseWaves, GEDI HDF5)",
    ),
    (
        &["nav", "raster", "signal"],
        "maths over the formats: navigation decoding and trajectories, raster grids and COGs, \
         the signal processing of one waveform",
    ),
    (
        &["geo"],
        "geodesy: CRS, DEM, direct georeferencing from the trajectory",
    ),
    (
        &["voxel"],
        "the voxel grid, deposits, tiles and the Zarr store",
    ),
    (
        &["forest"],
        "forest structure from waveforms and voxels: metrics, products, biomass",
    ),
    (
        &["trees", "source", "sink", "stages"],
        "tree reconstruction; the runtime's components: sources, sinks and stages",
    ),
    (
        &["qc"],
        "the QC snapshot, the Prometheus text and the QC server",
    ),
    (
        &["daemon"],
        "the on-board daemon's parts: live inputs, recorder, sampler, [daemon]",
    ),
    (
        &["config"],
        "the run configuration, composed of the components' sections",
    ),
    (&["run", "sim"], "a run put together; the scene simulator"),
    (
        &["eval", "campaign"],
        "accuracy against simulated truth; campaigns on a cluster",
    ),
    (&["cli"], "the command line: parse, run, print"),
];

/// Modules any test code may use, whatever its layer.
const TEST_ANYWHERE: &[&str] = &["fixtures"];

/// One path from a file of module `from` to module `to`.
#[derive(Clone, Debug)]
struct Ref {
    from: String,
    to: String,
    file: PathBuf,
    line: usize,
    test: bool,
}

#[test]
fn every_module_edge_goes_down_the_layer_list_and_none_forms_a_cycle() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let refs = module_refs(&src);
    assert!(
        refs.len() > 100,
        "found only {} cross-module paths",
        refs.len()
    );
    let level: BTreeMap<&str, usize> = LAYERS
        .iter()
        .enumerate()
        .flat_map(|(i, (mods, _))| mods.iter().map(move |m| (*m, i)))
        .collect();
    let mut problems = Vec::new();
    let tops = top_modules(&src);
    for m in &tops {
        if !level.contains_key(m.as_str()) {
            problems.push(format!(
                "src/{m}: module `{m}` is in no layer of tests/layering.rs; add it to one"
            ));
        }
    }
    for r in &refs {
        if r.test && TEST_ANYWHERE.contains(&r.to.as_str()) {
            continue;
        }
        let (Some(&a), Some(&b)) = (level.get(r.from.as_str()), level.get(r.to.as_str())) else {
            continue; // reported above
        };
        if b >= a {
            problems.push(format!(
                "{}:{}: `{}` (layer {a}) uses `{}` (layer {b}){}: a module may use only the \
                 layers below its own",
                r.file.display(),
                r.line,
                r.from,
                r.to,
                if r.test { " in test code" } else { "" }
            ));
        }
    }
    for cycle in cycles(&refs) {
        problems.push(format!("cycle of modules: {}", cycle.join(" -> ")));
    }
    assert!(
        problems.is_empty(),
        "{} layering problem(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

/// The checker finds the paths it must: a `use` tree, an inline path, a `super::` path out of a
/// folder, and test code.
#[test]
fn the_checker_reads_use_trees_inline_paths_super_and_tests() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path();
    std::fs::create_dir_all(src.join("b")).unwrap();
    std::fs::write(
        src.join("a.rs"),
        "use crate::{b::{x, y}, c::z};\n// crate::d::ignored\nfn f() { let s = \"crate::e\"; \
         crate::f::g(); }\n#[cfg(test)]\nmod tests {\n    use crate::h::k;\n}\n",
    )
    .unwrap();
    std::fs::write(src.join("b/mod.rs"), "pub mod inner;\n").unwrap();
    std::fs::write(
        src.join("b/inner.rs"),
        "use super::super::c::w;\nuse super::q;\n",
    )
    .unwrap();
    let refs = module_refs(src);
    let mut got: Vec<(String, String, usize, bool)> = refs
        .iter()
        .map(|r| (r.from.clone(), r.to.clone(), r.line, r.test))
        .collect();
    got.sort();
    let want = [
        ("a", "b", 1, false),
        ("a", "c", 1, false),
        ("a", "f", 3, false),
        ("a", "h", 6, true),
        ("b", "c", 1, false),
    ];
    let want: Vec<(String, String, usize, bool)> = want
        .iter()
        .map(|(a, b, l, t)| (a.to_string(), b.to_string(), *l, *t))
        .collect();
    assert_eq!(got, want);
    let cyc = cycles(&[
        Ref {
            from: "a".into(),
            to: "b".into(),
            file: "x".into(),
            line: 1,
            test: false,
        },
        Ref {
            from: "b".into(),
            to: "a".into(),
            file: "y".into(),
            line: 1,
            test: false,
        },
    ]);
    assert_eq!(cyc, [vec!["a", "b", "a"]]);
}

/// Names of the top-level modules under `src` (folders and files but `lib.rs`, `main.rs`).
fn top_modules(src: &Path) -> BTreeSet<String> {
    std::fs::read_dir(src)
        .unwrap()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().to_string();
            let p = e.path();
            if p.is_dir() {
                Some(name)
            } else {
                let stem = name.strip_suffix(".rs")?;
                (!matches!(stem, "lib" | "main")).then(|| stem.to_string())
            }
        })
        .collect()
}

/// Every path from one top-level module into another, found in the `.rs` files under `src`.
fn module_refs(src: &Path) -> Vec<Ref> {
    let mut files = Vec::new();
    collect_rs(src, &mut files);
    files.sort();
    let test_files = test_files(src, &files);
    let mut refs = Vec::new();
    for file in &files {
        let rel = file.strip_prefix(src).unwrap();
        let module = module_path(rel);
        let Some(top) = module.first().cloned() else {
            continue; // lib.rs, main.rs
        };
        let text = strip(&std::fs::read_to_string(file).unwrap());
        let tests = test_ranges(&text);
        let inline = inline_mods(&text);
        for (pos, path) in paths(&text) {
            let segs: Vec<&str> = path.split("::").filter(|s| !s.is_empty()).collect();
            let target = match segs.first() {
                Some(&"crate") => segs.get(1).map(|s| s.to_string()),
                Some(&"super") => {
                    let nest = inline.iter().filter(|(a, b)| *a < pos && pos < *b).count();
                    let mut base: Vec<String> = module.clone();
                    base.extend(std::iter::repeat_n("<inline>".to_string(), nest));
                    let ups = segs.iter().take_while(|s| **s == "super").count();
                    base.truncate(base.len().saturating_sub(ups));
                    base.retain(|s| s != "<inline>");
                    base.first()
                        .cloned()
                        .or_else(|| segs.get(ups).map(|s| s.to_string()))
                }
                _ => None,
            };
            let Some(to) = target else { continue };
            if to == top || to == "*" || to == "self" {
                continue;
            }
            let line = text[..pos].matches('\n').count() + 1;
            let test =
                test_files.contains(file) || tests.iter().any(|(a, b)| *a <= pos && pos <= *b);
            refs.push(Ref {
                from: top.clone(),
                to,
                file: Path::new("src").join(rel),
                line,
                test,
            });
        }
    }
    // A `use` line is seen both as a tree and as inline paths: once each.
    let mut seen = BTreeSet::new();
    refs.retain(|r| seen.insert((r.from.clone(), r.to.clone(), r.file.clone(), r.line, r.test)));
    refs
}

fn collect_rs(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            collect_rs(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The module path of a file: `a/b.rs` and `a/b/mod.rs` are `[a, b]`; `lib.rs` is `[]`.
fn module_path(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> = rel
        .with_extension("")
        .components()
        .map(|c| c.as_os_str().to_string_lossy().to_string())
        .collect();
    if matches!(
        parts.last().map(String::as_str),
        Some("mod" | "lib" | "main")
    ) {
        parts.pop();
    }
    parts
}

/// Files that are test modules themselves (`#[cfg(test)] mod tests;` next to them).
fn test_files(src: &Path, files: &[PathBuf]) -> BTreeSet<PathBuf> {
    let mut out = BTreeSet::new();
    for file in files {
        let text = strip(&std::fs::read_to_string(file).unwrap());
        let rel = file.strip_prefix(src).unwrap();
        let stem = rel.file_stem().unwrap().to_string_lossy().to_string();
        let dir = file.parent().unwrap();
        let base = if matches!(stem.as_str(), "mod" | "lib" | "main") {
            dir.to_path_buf()
        } else {
            dir.join(&stem)
        };
        let mut rest = text.as_str();
        while let Some(i) = rest.find("#[cfg(test)]") {
            rest = &rest[i + "#[cfg(test)]".len()..];
            let after = skip_attributes(rest).trim_start();
            let after = after
                .strip_prefix("pub(crate)")
                .or_else(|| after.strip_prefix("pub"))
                .unwrap_or(after)
                .trim_start();
            if let Some(m) = after.strip_prefix("mod") {
                let name: String = m
                    .trim_start()
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                let tail = m.trim_start()[name.len()..].trim_start();
                if tail.starts_with(';') {
                    out.insert(base.join(format!("{name}.rs")));
                    out.insert(base.join(&name).join("mod.rs"));
                }
            }
        }
    }
    out
}

fn skip_attributes(mut s: &str) -> &str {
    loop {
        let t = s.trim_start();
        if t.starts_with("#[") {
            match t.find(']') {
                Some(i) => s = &t[i + 1..],
                None => return t,
            }
        } else {
            return t;
        }
    }
}

/// Byte ranges of items under `#[cfg(test)]` (a braced item, or up to the `;` of `mod x;`).
fn test_ranges(text: &str) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(i) = text[from..].find("#[cfg(test)]") {
        let start = from + i;
        let after = start + "#[cfg(test)]".len();
        let brace = text[after..].find('{').map(|j| after + j);
        let semi = text[after..].find(';').map(|j| after + j);
        let end = match (brace, semi) {
            (Some(b), Some(s)) if s < b => s,
            (Some(b), _) => matching(text, b),
            (None, Some(s)) => s,
            (None, None) => text.len(),
        };
        out.push((start, end));
        from = after;
    }
    out
}

/// Byte ranges of inline `mod name { ... }` bodies (for `super::` inside them).
fn inline_mods(text: &str) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let b = text.as_bytes();
    let mut from = 0;
    while let Some(i) = text[from..].find("mod ") {
        let at = from + i;
        from = at + 4;
        if at > 0 && (b[at - 1].is_ascii_alphanumeric() || b[at - 1] == b'_') {
            continue;
        }
        let rest = &text[at + 4..];
        let name_len = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .count();
        let tail = rest[name_len..].trim_start();
        if name_len > 0 && tail.starts_with('{') {
            let open = at + 4 + rest.len() - tail.len();
            out.push((open, matching(text, open)));
        }
    }
    out
}

/// The index of the brace closing the one at `open`.
fn matching(text: &str, open: usize) -> usize {
    let mut depth = 0usize;
    for (j, c) in text[open..].char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return open + j;
                }
            }
            _ => {}
        }
    }
    text.len()
}

/// Every `crate::…` or `super::…` path (expanded out of `use` trees) with its byte offset.
fn paths(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    // `use` declarations, whole trees.
    let mut from = 0;
    while let Some(i) = text[from..].find("use ") {
        let at = from + i;
        from = at + 4;
        let b = text.as_bytes();
        if at > 0 && (b[at - 1].is_ascii_alphanumeric() || b[at - 1] == b'_' || b[at - 1] == b':') {
            continue;
        }
        let Some(end) = text[at..].find(';') else {
            break;
        };
        let tree: String = text[at + 4..at + end]
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect();
        if tree.starts_with("crate::") || tree.starts_with("super::") {
            for p in expand(&tree) {
                out.push((at, p));
            }
        }
        from = at + end;
    }
    // Inline paths.
    for start in ["crate::", "super::"] {
        let mut from = 0;
        while let Some(i) = text[from..].find(start) {
            let at = from + i;
            from = at + start.len();
            let b = text.as_bytes();
            if at > 0
                && (b[at - 1].is_ascii_alphanumeric() || b[at - 1] == b'_' || b[at - 1] == b':')
            {
                continue;
            }
            let p: String = text[at..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
                .collect();
            out.push((at, p));
        }
    }
    out
}

/// `a::{b, c::{d, e}}` into `a::b`, `a::c::d`, `a::c::e`.
fn expand(tree: &str) -> Vec<String> {
    let Some(open) = tree.find('{') else {
        return vec![tree.split(" as ").next().unwrap_or(tree).to_string()];
    };
    let head = &tree[..open];
    let body = &tree[open + 1..tree.rfind('}').unwrap_or(tree.len())];
    let mut items = Vec::new();
    let (mut depth, mut cur) = (0, String::new());
    for c in body.chars() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                items.push(std::mem::take(&mut cur));
                continue;
            }
            _ => {}
        }
        cur.push(c);
    }
    items.push(cur);
    items
        .iter()
        .filter(|i| !i.is_empty())
        .flat_map(|i| expand(&format!("{head}{i}")))
        .collect()
}

/// Rust source without comments, string and character literals (newlines kept, so lines and
/// offsets still count).
fn strip(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if text[i..].starts_with("//") {
            let end = text[i..].find('\n').map_or(b.len(), |j| i + j);
            out.extend(std::iter::repeat_n(' ', end - i));
            i = end;
        } else if text[i..].starts_with("/*") {
            let (mut depth, mut j) = (1, i + 2);
            while j < b.len() && depth > 0 {
                if text[j..].starts_with("/*") {
                    depth += 1;
                    j += 2;
                } else if text[j..].starts_with("*/") {
                    depth -= 1;
                    j += 2;
                } else {
                    j += 1;
                }
            }
            out.extend(
                text[i..j]
                    .chars()
                    .map(|c| if c == '\n' { '\n' } else { ' ' }),
            );
            i = j;
        } else if c == b'r'
            && (i == 0 || !(b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_'))
            && raw_string_hashes(&text[i + 1..]).is_some()
        {
            let hashes = raw_string_hashes(&text[i + 1..]).unwrap();
            let close = format!("\"{}", "#".repeat(hashes));
            let body = i + 2 + hashes;
            let end = text[body..]
                .find(&close)
                .map_or(b.len(), |j| body + j + close.len());
            out.extend(
                text[i..end]
                    .chars()
                    .map(|c| if c == '\n' { '\n' } else { ' ' }),
            );
            i = end;
        } else if c == b'"' {
            let mut j = i + 1;
            while j < b.len() && b[j] != b'"' {
                j += if b[j] == b'\\' { 2 } else { 1 };
            }
            let end = (j + 1).min(b.len());
            out.extend(
                text[i..end]
                    .chars()
                    .map(|c| if c == '\n' { '\n' } else { ' ' }),
            );
            i = end;
        } else if c == b'\'' && char_literal_len(&text[i..]).is_some() {
            let n = char_literal_len(&text[i..]).unwrap();
            out.extend(std::iter::repeat_n(' ', text[i..i + n].chars().count()));
            i += n;
        } else {
            let ch = text[i..].chars().next().unwrap();
            out.push(ch);
            i += ch.len_utf8();
        }
    }
    out
}

/// `Some(n)` when `s` (after an `r`) opens a raw string with `n` hashes.
fn raw_string_hashes(s: &str) -> Option<usize> {
    let n = s.chars().take_while(|c| *c == '#').count();
    s[n..].starts_with('"').then_some(n)
}

/// The byte length of a character literal at the start of `s` (`'a'`, `'\n'`, `'\u{..}'`);
/// `None` for a lifetime.
fn char_literal_len(s: &str) -> Option<usize> {
    let rest = &s[1..];
    if let Some(esc) = rest.strip_prefix('\\') {
        let close = esc.find('\'')?;
        return (close <= 10).then_some(close + 3);
    }
    let ch = rest.chars().next()?;
    rest[ch.len_utf8()..]
        .starts_with('\'')
        .then_some(1 + ch.len_utf8() + 1)
}

/// The cycles among modules (each as `a -> … -> a`), from the strongly connected components of
/// the module graph.
fn cycles(refs: &[Ref]) -> Vec<Vec<String>> {
    let mut adj: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for r in refs {
        if r.test && TEST_ANYWHERE.contains(&r.to.as_str()) {
            continue;
        }
        adj.entry(r.from.as_str())
            .or_default()
            .insert(r.to.as_str());
        adj.entry(r.to.as_str()).or_default();
    }
    let nodes: Vec<&str> = adj.keys().copied().collect();
    let mut out = Vec::new();
    let mut done: BTreeSet<&str> = BTreeSet::new();
    for &start in &nodes {
        if done.contains(start) {
            continue;
        }
        // A shortest path from each successor back to `start` closes a cycle through it.
        if let Some(path) = path_back(&adj, start) {
            for m in &path {
                done.insert(m);
            }
            let mut cyc: Vec<String> = path.iter().map(|s| s.to_string()).collect();
            cyc.push(start.to_string());
            out.push(cyc);
        }
    }
    out
}

/// A shortest path `start -> … ` that returns to `start`, without the final `start`.
fn path_back<'a>(
    adj: &BTreeMap<&'a str, BTreeSet<&'a str>>,
    start: &'a str,
) -> Option<Vec<&'a str>> {
    let mut prev: BTreeMap<&str, &str> = BTreeMap::new();
    let mut queue = std::collections::VecDeque::from([start]);
    while let Some(n) = queue.pop_front() {
        for &m in &adj[n] {
            if m == start {
                let mut path = vec![n];
                let mut cur = n;
                while cur != start {
                    cur = prev[cur];
                    path.push(cur);
                }
                path.reverse();
                return Some(path);
            }
            if !prev.contains_key(m) && m != start {
                prev.insert(m, n);
                queue.push_back(m);
            }
        }
    }
    None
}
