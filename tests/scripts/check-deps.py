#!/usr/bin/env python3
"""Checks that dependencies point the way ARCHITECTURE.md says.

Reads from ARCHITECTURE.md, so the document and the check cannot drift apart:
  - each crate's "may depend on" row (workspace arrows, from `cargo metadata --no-deps`);
  - the third-party rules ("reached only through", "never reached from"; on the resolved graph);
  - the known exceptions, which are reported but not failed, and fail once they no longer exist;
  - every workspace crate builds with the workspace lints (`[lints] workspace = true` in its Cargo.toml), so
    no crate escapes the pedantic lints or `unsafe_code = "deny"`;
  - FFmpeg behind one module per crate: in a crate's sources (library and binaries), only its `av` module
    (`src/av.rs` or `src/av/`) names `ffmpeg_next`, so the rest of the crate sees FFmpeg through it.

Usage: tests/scripts/check-deps.py [--metadata FILE --no-deps-metadata FILE]
(the two files, `cargo metadata --format-version 1` with and without --no-deps, replace running cargo).
Exits 1 with one line per broken rule.
"""

import argparse
import json
import pathlib
import re
import subprocess
import sys
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[2]
TICKED = re.compile(r"`([^`]+)`")


def cells(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]


def parse_architecture(text):
    """Returns (allowed: crate -> set or None for any, rules: [(dep, only_through, never_from)], exceptions)."""
    allowed, rules, exceptions = {}, [], set()
    crate, section = None, None
    for line in text.splitlines():
        if line.startswith("## "):
            section, crate = line[3:].strip().lower(), None
            continue
        if line.startswith("### "):
            names = TICKED.findall(line)
            crate = names[0] if names else None
            continue
        if not line.startswith("|") or set(line) <= set("|- "):
            continue
        row = cells(line)
        if section == "crates" and crate and row[0] == "may depend on":
            allowed[crate] = None if "`*`" in row[1] else set(TICKED.findall(row[1]))
        elif section.startswith("third-party rules") and len(row) >= 3 and TICKED.fullmatch(row[0]):
            rules.append((row[0].strip("`"), set(TICKED.findall(row[1])), set(TICKED.findall(row[2]))))
        elif section == "known exceptions" and len(row) >= 2 and TICKED.fullmatch(row[0]):
            exceptions.add((row[0].strip("`"), row[1].strip("`")))
    return allowed, rules, exceptions


def cargo_metadata(no_deps):
    args = ["cargo", "metadata", "--format-version", "1"]
    if no_deps:
        args.append("--no-deps")
    out = subprocess.run(args, cwd=ROOT, check=True, capture_output=True, text=True).stdout
    return json.loads(out)


def workspace_arrows(meta):
    """(from, to, kind) for every dependency of a workspace crate on another workspace crate."""
    members = {p["name"] for p in meta["packages"]}
    for package in meta["packages"]:
        for dep in package["dependencies"]:
            if dep["name"] in members:
                yield package["name"], dep["name"], dep["kind"] or "normal"


def reachable(graph, start, skip=frozenset()):
    """Package ids reachable from `start`: every edge kind out of `start`, normal and build edges after."""
    seen, stack = set(), [(start, True)]
    while stack:
        node, first = stack.pop()
        for dep, kinds in graph.get(node, ()):
            if dep in seen or dep in skip or not (first or kinds & {"normal", "build"}):
                continue
            seen.add(dep)
            stack.append((dep, False))
    return seen


FFMPEG = re.compile(r"\bffmpeg_next\b")
COMMENT = re.compile(r"//.*")


def ffmpeg_outside_av(no_deps_meta):
    """`path:line` of every mention of `ffmpeg_next` (outside comments) in a crate's `src/` but not in its `av`
    module (`src/av.rs`, `src/av/`)."""
    found = []
    for package in sorted(no_deps_meta["packages"], key=lambda p: p["name"]):
        src = pathlib.Path(package["manifest_path"]).parent / "src"
        for path in sorted(src.rglob("*.rs")):
            inside = path.relative_to(src).parts
            if inside[0] in ("av.rs", "av"):
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if FFMPEG.search(COMMENT.sub("", line)):
                    shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
                    found.append((package["name"], f"{shown}:{number}"))
    return found


def check(allowed, rules, exceptions, no_deps_meta, meta):
    errors, used_exceptions = [], set()
    members = sorted({p["name"] for p in no_deps_meta["packages"]})
    for name in members:
        if name not in allowed:
            errors.append(f"{name}: workspace crate with no section (and no 'may depend on' row) in ARCHITECTURE.md")
    for source, target, kind in sorted(set(workspace_arrows(no_deps_meta))):
        if source == target:
            # A crate's dev-dependency on itself switches on a test-only feature for its own tests.
            continue
        permitted = allowed.get(source)
        if source not in allowed or permitted is None or target in permitted:
            continue
        if (source, target) in exceptions:
            used_exceptions.add((source, target))
            continue
        errors.append(
            f"bad arrow: {source} -> {target} ({kind} dependency); ARCHITECTURE.md lets {source} depend on "
            f"{', '.join(sorted(permitted)) or 'nothing in the workspace'}"
        )
    for package in sorted(no_deps_meta["packages"], key=lambda p: p["name"]):
        manifest = pathlib.Path(package["manifest_path"])
        lints = tomllib.loads(manifest.read_text()).get("lints", {})
        if lints.get("workspace") is not True:
            errors.append(
                f"{package['name']}: {manifest.relative_to(ROOT) if manifest.is_relative_to(ROOT) else manifest} "
                f"has no `[lints] workspace = true`: every crate builds with the workspace lints"
            )
    for name, where in ffmpeg_outside_av(no_deps_meta):
        errors.append(
            f"{name}: {where} names ffmpeg_next outside the crate's `av` module (src/av.rs or src/av/), "
            f"the one place each crate reaches FFmpeg"
        )
    for source, target in sorted(exceptions - used_exceptions):
        errors.append(
            f"known exception {source} -> {target} no longer exists: remove it from ARCHITECTURE.md"
        )

    ids = {p["id"]: p["name"] for p in meta["packages"]}
    by_name = {}
    for package_id, name in ids.items():
        by_name.setdefault(name, set()).add(package_id)
    graph = {
        node["id"]: [
            (dep["pkg"], {k["kind"] or "normal" for k in dep["dep_kinds"]}) for dep in node["deps"]
        ]
        for node in meta["resolve"]["nodes"]
    }
    workspace_ids = {i for i in meta["workspace_members"]}
    for dependency, only_through, never_from in rules:
        targets = by_name.get(dependency, set())
        through_ids = {i for i in workspace_ids if ids[i] in only_through}
        for member in sorted(workspace_ids, key=ids.get):
            name = ids[member]
            if only_through and name not in only_through and reachable(graph, member, through_ids) & targets:
                errors.append(
                    f"bad arrow: {name} reaches {dependency} other than through "
                    f"{', '.join(sorted(only_through))} (ARCHITECTURE.md, third-party rules)"
                )
            if name in never_from and reachable(graph, member) & targets:
                errors.append(
                    f"bad arrow: {name} reaches {dependency}, which it must never depend on, even "
                    f"indirectly (ARCHITECTURE.md, third-party rules)"
                )
    return errors, sorted(used_exceptions)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--metadata", type=pathlib.Path)
    parser.add_argument("--no-deps-metadata", type=pathlib.Path)
    args = parser.parse_args()
    allowed, rules, exceptions = parse_architecture((ROOT / "ARCHITECTURE.md").read_text())
    if not allowed or not rules:
        sys.exit("check-deps: found no crate sections or no third-party rules in ARCHITECTURE.md")
    if args.metadata and args.no_deps_metadata:
        meta = json.loads(args.metadata.read_text())
        no_deps_meta = json.loads(args.no_deps_metadata.read_text())
    else:
        meta, no_deps_meta = cargo_metadata(no_deps=False), cargo_metadata(no_deps=True)
    errors, used_exceptions = check(allowed, rules, exceptions, no_deps_meta, meta)
    for source, target in used_exceptions:
        print(f"check-deps: known exception {source} -> {target} (see ARCHITECTURE.md, Known exceptions)")
    for error in errors:
        print(f"check-deps: {error}", file=sys.stderr)
    if errors:
        sys.exit(1)
    print(f"check-deps: {len(allowed)} crates, {len(rules)} third-party rules: dependencies point the right way")


if __name__ == "__main__":
    main()
