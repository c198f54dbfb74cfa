#!/usr/bin/env python3
"""Prints the module import graph of a crate's `src/` (from `crate::` paths outside `#[cfg(test)]`) and fails
when it has a cycle. Usage: check-module-cycles.py server/src [clients/gateway/src ...]"""

import os
import re
import sys


def modules(root):
    found = {}
    for dirpath, _, files in os.walk(root):
        for name in files:
            if not name.endswith(".rs"):
                continue
            path = os.path.join(dirpath, name)
            module = os.path.relpath(path, root)[:-3].replace(os.sep, "::")
            if module.endswith("::mod"):
                module = module[: -len("::mod")]
            if module in ("lib", "main") or module.startswith("bin::"):
                continue
            found[module] = path
    return found


def targets(source, known):
    """Modules named by `crate::a::b` and `crate::{a::b, c}` paths, longest known prefix first."""
    paths = []
    for match in re.finditer(r"crate::(\{[^}]*\}|[A-Za-z_][\w:]*)", source):
        text = match.group(1)
        if text.startswith("{"):
            paths += [p.strip() for p in text[1:-1].split(",") if p.strip()]
        else:
            paths.append(text)
    for path in paths:
        parts = path.split("::")
        for n in range(len(parts), 0, -1):
            candidate = "::".join(parts[:n])
            if candidate in known:
                yield candidate
                break


def cycles(edges):
    state, stack, out = {}, [], []

    def visit(u):
        state[u] = "open"
        stack.append(u)
        for v in sorted(edges[u]):
            if state.get(v) == "open":
                out.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v)
        stack.pop()
        state[u] = "done"

    for u in sorted(edges):
        if u not in state:
            visit(u)
    return out


def main(roots):
    failed = False
    for root in roots:
        known = modules(root)
        edges = {m: set() for m in known}
        for module, path in known.items():
            with open(path, encoding="utf-8") as f:
                source = f.read().split("#[cfg(test)]")[0]
            parents = {"::".join(module.split("::")[:n]) for n in range(1, module.count("::") + 1)}
            edges[module] = {t for t in targets(source, known) if t != module and t not in parents}
        print(f"{root}:")
        for module in sorted(edges):
            print(f"  {module:26} -> {', '.join(sorted(edges[module])) or '-'}")
        found = cycles(edges)
        for cycle in found:
            print("  CYCLE: " + " -> ".join(cycle))
        if not found:
            print("  no cycle")
        failed |= bool(found)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or ["server/src"]))
