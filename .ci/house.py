#!/usr/bin/env python3
"""Measures how the house stands (docs/architecture.md, "How the house is measured"): module
cycles and upward edges against the layer list of tests/layering.rs, the modules the runtime
(`pipeline/`) imports, functions over 150 lines outside tests, `serde_json::Value` read by key in
cli/, daemon/ and campaign/, and the definitions of the speed of light.

Usage: python3 .ci/house.py [SRC]   (default: src of this checkout)

It reads the code as text, as tests/layering.rs does (which enforces the layers in the test
suite; clippy's too_many_lines enforces the function length): a measure, not a gate.
"""
import os
import re
import sys
from collections import defaultdict

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SRC = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "src")


def strip(text):
    """Rust source without comments and string or char literals (newlines kept)."""
    out, i, n = [], 0, len(text)
    while i < n:
        if text.startswith("//", i):
            j = text.find("\n", i)
            i = n if j < 0 else j
            continue
        if text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append("\n" * text.count("\n", i, j))
            i = j
            continue
        c = text[i]
        m = re.match(r'r(#*)"', text[i:i + 10]) if c == "r" and (i == 0 or not (text[i - 1].isalnum() or text[i - 1] == "_")) else None
        if m:
            end = '"' + m.group(1)
            j = text.find(end, i + len(m.group(0)))
            j = n if j < 0 else j + len(end)
            out.append('""' + "\n" * text.count("\n", i, j))
            i = j
            continue
        if c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            out.append('""' + "\n" * text.count("\n", i, j))
            i = j + 1
            continue
        if c == "'":
            m = re.match(r"'(\\.|\\x[0-9a-fA-F]{2}|\\u\{[0-9a-fA-F]+\}|[^\\'])'", text[i:i + 12])
            if m:
                out.append("' '")
                i += len(m.group(0))
                continue
        out.append(c)
        i += 1
    return "".join(out)


def match_brace(t, pos):
    d = 0
    for j in range(pos, len(t)):
        if t[j] == "{":
            d += 1
        elif t[j] == "}":
            d -= 1
            if d == 0:
                return j
    return len(t)


def files():
    out = []
    for root, _, fs in os.walk(SRC):
        for f in fs:
            if f.endswith(".rs"):
                out.append(os.path.relpath(os.path.join(root, f), SRC))
    return sorted(out)


def test_ranges(t):
    rs = []
    for m in re.finditer(r"#\[cfg\(\s*test\s*\)\]", t):
        j = m.end()
        nb, ns = t.find("{", j), t.find(";", j)
        if ns != -1 and (nb == -1 or ns < nb):
            rs.append((m.start(), ns))
        else:
            rs.append((m.start(), match_brace(t, nb)))
    return rs


def test_files(texts):
    out = set()
    for rel, t in texts.items():
        for m in re.finditer(r"#\[cfg\(\s*test\s*\)\]\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;", t):
            d, stem = os.path.dirname(rel), os.path.basename(rel)[:-3]
            base = d if stem in ("mod", "lib", "main") else os.path.join(d, stem)
            out.add(os.path.normpath(os.path.join(base, m.group(1) + ".rs")))
            out.add(os.path.normpath(os.path.join(base, m.group(1), "mod.rs")))
    return out


def expand(tree):
    idx = tree.find("{")
    if idx < 0:
        return [tree]
    head, body = tree[:idx], tree[idx + 1:tree.rfind("}")]
    items, depth, cur = [], 0, ""
    for ch in body:
        depth += ch == "{"
        depth -= ch == "}"
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += ch
    items.append(cur)
    return [p for it in items if it.strip() for p in expand(head + it.strip())]


def module_edges(texts, tests):
    """(from, to) -> [(file, line)] over non-test code."""
    edges = defaultdict(list)
    for rel, t in texts.items():
        parts = rel[:-3].split("/")
        if parts[-1] in ("mod", "lib", "main"):
            parts = parts[:-1]
        if not parts:
            continue
        top = parts[0]
        tr = test_ranges(t)
        paths = []
        for m in re.finditer(r"\buse\s+([^;]+);", t):
            for p in expand(re.sub(r"\s+", "", m.group(1))):
                paths.append((m.start(), p))
        for m in re.finditer(r"(?<![\w:])((?:crate|super)(?:::\w+)+)", t):
            paths.append((m.start(), m.group(1)))
        for pos, p in paths:
            if rel in tests or any(a <= pos <= b for a, b in tr):
                continue
            segs = [s for s in p.split(" as ")[0].split("::") if s]
            if not segs:
                continue
            if segs[0] == "crate" and len(segs) > 1:
                to = segs[1]
            elif segs[0] == "super":
                ups = len([s for s in segs if s == "super"])
                base = parts[: max(0, len(parts) - ups)]
                to = base[0] if base else (segs[ups] if len(segs) > ups else None)
            else:
                continue
            if to and to != top and to not in ("self", "*"):
                edges[(top, to)].append((rel, t.count("\n", 0, pos) + 1))
    return edges


def layers():
    text = open(os.path.join(ROOT, "tests", "layering.rs"), encoding="utf-8").read()
    block = text[text.index("const LAYERS"):text.index("];", text.index("const LAYERS"))]
    level = {}
    for i, m in enumerate(re.finditer(r"&\[([^\]]*)\]", block)):
        for name in re.findall(r'"(\w+)"', m.group(1)):
            level[name] = i
    return level


def sccs(nodes, adj):
    index, low, on, st, res, c = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = c[0]
        c[0] += 1
        st.append(v)
        on.add(v)
        for w in adj.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = st.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            res.append(comp)

    sys.setrecursionlimit(10000)
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return [sorted(x) for x in res if len(x) > 1]


def long_functions(texts, tests, limit=150):
    out = []
    for rel, t in texts.items():
        tr = test_ranges(t)
        for m in re.finditer(r"\bfn\s+(\w+)", t):
            j, depth, body = m.end(), 0, None
            while j < len(t):
                ch = t[j]
                if ch in "(<[":
                    depth += 1
                elif ch in ")>]":
                    depth -= 1
                elif ch == ";" and depth <= 0:
                    break
                elif ch == "{" and depth <= 0:
                    body = j
                    break
                j += 1
            if body is None:
                continue
            end = match_brace(t, body)
            lines = t.count("\n", m.start(), end) + 1
            in_test = rel in tests or any(a <= m.start() <= b for a, b in tr)
            if lines > limit and not in_test:
                out.append((lines, rel, m.group(1)))
    return sorted(out, reverse=True)


def value_reads(texts):
    """`serde_json::Value` read by key: `v["key"]`, `.get("key")` on a JSON value."""
    n = 0
    for rel, t in texts.items():
        if not rel.split("/")[0] in ("cli", "daemon", "campaign"):
            continue
        raw = open(os.path.join(SRC, rel), encoding="utf-8").read()
        code = strip(raw)
        tr = test_ranges(code)
        for m in re.finditer(r'\[\s*"[A-Za-z_0-9]+"\s*\]|\.get\(\s*"[A-Za-z_0-9]+"\s*\)', raw):
            if any(a <= m.start() <= b for a, b in tr):
                continue
            line = raw[raw.rfind("\n", 0, m.start()) + 1:raw.find("\n", m.start())]
            before = raw[max(0, m.start() - 200):m.start()]
            # Comments, assertions, keys written (`v["k"] = …`) and TOML tables are not reads
            # of a JSON value.
            if (line.strip().startswith("//") or "assert" in line or "toml" in before
                    or re.match(r"\s*=[^=]", raw[m.end():m.end() + 3])):
                continue
            n += 1
    return n


def c_definitions(texts):
    pat = re.compile(r"(?:const|static)\s+\w+\s*:\s*f64\s*=\s*(?:0\.299_?792|299_?792_?458|0\.149_?896|0\.14986)")
    return sum(len(pat.findall(open(os.path.join(SRC, rel), encoding="utf-8").read())) for rel in texts)


def main():
    texts = {rel: strip(open(os.path.join(SRC, rel), encoding="utf-8").read()) for rel in files()}
    tests = test_files(texts)
    edges = module_edges(texts, tests)
    adj = defaultdict(set)
    for a, b in edges:
        adj[a].add(b)
    nodes = {a for a, _ in edges} | {b for _, b in edges}
    cyc = sccs(nodes, adj)
    level = layers()
    upward = [(a, b) for (a, b) in edges if level.get(b, 99) >= level.get(a, -1)]
    runtime = sorted(adj.get("pipeline", ()))
    longs = long_functions(texts, tests)
    print("| measure (non-test code) | now |")
    print("|---|---|")
    print(f"| module cycles | {len(cyc)}{' (' + '; '.join(', '.join(c) for c in cyc) + ')' if cyc else ''} |")
    print(f"| upward or same-layer module edges (tests/layering.rs) | {len(upward)} |")
    print(f"| modules the runtime (`pipeline/`) imports | {len(runtime)}: {', '.join(runtime)} |")
    print(f"| functions over 150 lines | {len(longs)} |")
    print(f"| `serde_json::Value` read by key in cli/, daemon/, campaign/ | {value_reads(texts)} |")
    print(f"| definitions of c | {c_definitions(texts)} |")
    for a, b in sorted(upward):
        f, line = edges[(a, b)][0]
        print(f"  up: {a} -> {b} at src/{f}:{line}")
    for lines, rel, name in longs:
        print(f"  long: src/{rel} {name} {lines} lines")


if __name__ == "__main__":
    main()
