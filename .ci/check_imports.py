#!/usr/bin/env python3
"""Checks the crate's module graph: no import cycles between source files, and the
core's layer order (math, error -> mesh -> material -> fem -> solver -> body -> contact
-> scene). A file depends on the module file that a `use` path (or a `crate::`/`super::`
path in code) names; a re-export does not count as the defining file, so children
import the sibling file that defines an item, not their parent's re-export."""
import os, re, sys

ROOT = os.path.join(os.path.dirname(__file__), "..", "src")
LAYERS = ["math", "error", "mesh", "material", "fem", "solver", "body", "contact", "scene", "haptics"]
RANK = {m: i for i, m in enumerate(LAYERS)}
RANK["error"] = RANK["math"]

def module_of(path):
    rel = os.path.relpath(path, ROOT)[:-3].split(os.sep)
    if rel[-1] in ("mod", "lib"):
        rel = rel[:-1]
    return tuple(rel)

files = {}
for d, _, fs in os.walk(ROOT):
    for f in fs:
        if f.endswith(".rs"):
            p = os.path.join(d, f)
            files[module_of(p)] = p
mods = set(files)

def resolve(cur, parts):
    if parts[0] == "crate":
        base, parts = (), parts[1:]
    elif parts[0] == "super":
        base = cur
        while parts and parts[0] == "super":
            base, parts = base[:-1], parts[1:]
    elif parts[0] == "self":
        base, parts = cur, parts[1:]
    elif cur + (parts[0],) in mods:
        base = cur
    else:
        return None
    best = None
    for i in range(len(parts) + 1):
        m = base + tuple(parts[:i])
        if m in mods:
            best = m
    return best

def expand(tree):
    """Paths of a `use` tree: a::{b, c::{d}} -> a::b, a::c::d."""
    tree = tree.replace(" ", "").replace("\n", "")
    out = []
    def rec(prefix, t):
        depth, start, items = 0, 0, []
        for i, ch in enumerate(t):
            if ch == "{":
                depth += 1
            elif ch == "}":
                depth -= 1
            elif ch == "," and depth == 0:
                items.append(t[start:i]); start = i + 1
        items.append(t[start:])
        for it in items:
            if not it:
                continue
            if "{" in it:
                head, rest = it.split("{", 1)
                rec(prefix + [x for x in head.split("::") if x], rest[:-1])
            else:
                out.append(prefix + [x for x in it.split(" as ")[0].split("::") if x])
    rec([], tree)
    return out

edges = {}
for m, p in files.items():
    src = open(p).read()
    src = re.sub(r"//.*", "", src)
    # A visibility restriction (`pub(in crate::a::b)`) names a module without
    # depending on it.
    src = re.sub(r"\bpub\s*\(\s*in\s+[\w:]+\s*\)", "pub", src)
    # Inline modules (`mod tests { .. }` and the like): their `super` is this file.
    inline = []
    for mm in re.finditer(r"\bmod\s+\w+\s*\{", src):
        depth, i = 0, mm.end() - 1
        while i < len(src):
            depth += {"{": 1, "}": -1}.get(src[i], 0)
            if depth == 0:
                break
            i += 1
        inline.append((mm.end(), i))
    def here(pos):
        return m + ("<inline>",) * sum(a <= pos < b for a, b in inline)
    deps = set()
    for u in re.finditer(r"\buse\s+([^;]+);", src):
        cur = here(u.start())
        for path in expand(u.group(1)):
            if path and path[-1] == "*":
                path = path[:-1]
            if path:
                r = resolve(cur, path)
                if r is not None and r != m:
                    deps.add(r)
    for u in re.finditer(r"\b((?:crate|super)(?:::\w+)+)", src):
        r = resolve(here(u.start()), u.group(1).split("::"))
        if r is not None and r != m:
            deps.add(r)
    edges[m] = deps

bad = []
# Cycles (Tarjan).
index, low, stack, on, comps, n = {}, {}, [], set(), [], [0]
def strong(v):
    index[v] = low[v] = n[0]; n[0] += 1; stack.append(v); on.add(v)
    for w in edges.get(v, ()):
        if w not in index:
            strong(w); low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        comp = []
        while True:
            w = stack.pop(); on.discard(w); comp.append(w)
            if w == v:
                break
        if len(comp) > 1:
            comps.append(comp)
sys.setrecursionlimit(10000)
for v in edges:
    if v not in index:
        strong(v)
for c in comps:
    bad.append("import cycle: " + " <-> ".join("::".join(x) or "lib" for x in sorted(c)))
# Layer order of the core.
for m, deps in edges.items():
    if m and m[0] in RANK:
        for d in deps:
            if d and d[0] in RANK and RANK[d[0]] > RANK[m[0]]:
                bad.append(f"layer order: {'::'.join(m)} uses {'::'.join(d)}")
            if d and d[0] not in RANK and d[0] not in ("lib",):
                bad.append(f"core module {'::'.join(m)} uses {'::'.join(d)} (outside the core)")
for b in bad:
    print(b)
print(f"module graph: {len(files)} files, {sum(len(d) for d in edges.values())} edges, {len(bad)} problems")
sys.exit(1 if bad else 0)
