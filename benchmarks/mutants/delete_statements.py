#!/usr/bin/env python3
"""Statement-deletion mutants, which cargo-mutants does not generate (it replaces function bodies and operators).

For each statement of FILE outside its `#[cfg(test)]` module (ending with `;`, or a block statement such as
an `if` ending with its `}`) that is not a `let`, `use`, `return` or item declaration, this deletes the statement in a scratch copy of the workspace, runs the core
crate's unit tests and reports the mutant as caught (a test failed), missed (all passed) or unviable (it does
not compile). A missed deletion is a state change no test notices; it is either a test to write or a
statement to list as equivalent in benchmarks/mutants/EQUIVALENT.md.

    benchmarks/mutants/delete_statements.py server/core/src/arbiter.rs
    benchmarks/mutants/delete_statements.py server/core/src/joint_limit.rs joint_limit   # only the limiter's tests

A second argument is a test-name filter (as for `cargo test`): the core crate's other tests then do not run,
which for a small file is most of the time.

Not in CI: one build and test run per statement (about 10 s each on two cores, niced).
"""

import os
import re
import shutil
import subprocess
import sys
import tempfile

SKIP = re.compile(r"^\s*(let |use |return\b|pub |fn |const |static |type |mod |impl |#|//|\.|\)|\]|\})")


def statements(lines):
    """(first, last) line indices of each candidate statement before the test module."""
    end = next((i for i, l in enumerate(lines) if l.strip() == "#[cfg(test)]"), len(lines))
    found = []
    i = 0
    while i < end:
        line = lines[i]
        prev = lines[i - 1].rstrip() if i else ""
        starts = prev.endswith((";", "{", "}")) or prev.strip().startswith("//") or prev.strip() == ""
        if starts and line.strip() and not SKIP.match(line) and "=>" not in line:
            depth, j = 0, i
            while j < end:
                depth += lines[j].count("(") + lines[j].count("[") + lines[j].count("{")
                depth -= lines[j].count(")") + lines[j].count("]") + lines[j].count("}")
                # A statement ends with `;`, a block statement (`if`, `match`, `for`) with its closing `}`.
                if depth == 0 and lines[j].rstrip().endswith((";", "}")):
                    break
                if depth < 0:
                    j = end
                    break
                j += 1
            if j < end and j - i < 12:
                found.append((i, j))
                # A block statement's own statements are candidates too.
                if not lines[j].rstrip().endswith("}"):
                    i = j + 1
                    continue
        i += 1
    return found


def main():
    if len(sys.argv) not in (2, 3):
        sys.exit(__doc__)
    rel = sys.argv[1]
    root = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, check=True).stdout.strip()
    scratch = tempfile.mkdtemp(prefix="phone2act-deletions-")
    files = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        dst = os.path.join(scratch, f)
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        if os.path.isfile(os.path.join(root, f)):
            shutil.copy2(os.path.join(root, f), dst)
    target = os.path.join(root, "target", "mutants", "deletions")
    env = dict(os.environ, CARGO_TARGET_DIR=target, CARGO_PROFILE_DEV_DEBUG="0", CARGO_PROFILE_TEST_DEBUG="0")
    cmd = ["nice", "-n", "19", "cargo", "test", "-q", "-p", "phone2act-core", "--lib"] + sys.argv[2:]
    path = os.path.join(scratch, rel)
    # copy2 kept the file's old time; an interrupted earlier run may have left the shared target dir built from
    # a mutated copy with a newer one, which cargo would take as up to date.
    os.utime(path)
    original = open(path).read()
    lines = original.split("\n")
    base = subprocess.run(cmd, cwd=scratch, env=env, capture_output=True, text=True)
    if base.returncode != 0:
        sys.exit("the unmutated tests fail:\n" + base.stdout[-2000:] + base.stderr[-2000:])
    counts = {"caught": 0, "missed": 0, "unviable": 0}
    for first, last in statements(lines):
        mutated = lines[:first] + [""] * (last - first + 1) + lines[last + 1 :]
        open(path, "w").write("\n".join(mutated))
        r = subprocess.run(cmd, cwd=scratch, env=env, capture_output=True, text=True)
        if r.returncode == 0:
            outcome = "missed"
        elif "error[E" in r.stderr or "error: could not compile" in r.stderr:
            outcome = "unviable"
        else:
            outcome = "caught"
        counts[outcome] += 1
        text = " ".join(l.strip() for l in lines[first : last + 1])
        print(f"{outcome:<9} {rel}:{first + 1}: {text[:110]}", flush=True)
    open(path, "w").write(original)
    shutil.rmtree(scratch)
    print(f"{rel}: {counts['caught']} caught, {counts['missed']} missed, {counts['unviable']} unviable")


if __name__ == "__main__":
    main()
