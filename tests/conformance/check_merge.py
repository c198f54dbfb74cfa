"""Checks a dataset made by `phone2act dataset merge` (or `compact`) against the real lerobot library.

usage: check_merge.py MERGED INPUT... [--lerobot-aggregate DIR]

- MERGED loads with LeRobotDataset and holds every frame of every input, in input order: the same state,
  action and task text, the episode renumbered by the episodes before it, and every camera frame pixel-equal
  after decode to the input's (videos are stream-copied, never re-encoded);
- its meta/stats.json (v3.0: lerobot's; v2.1: GR00T's) agrees with the merged rows themselves (min, max, mean, std, count exactly; the
  quantiles as numpy computes them over the rows, within the sketch's tolerance);
- with --lerobot-aggregate DIR: lerobot's own `aggregate_datasets` is run on the same inputs into DIR, and
  its result has the same frames (pixel-equal), the same tasks, and statistics within lerobot's own
  tolerance (its quantiles are count-weighted averages, so only mean/std/min/max/count are compared, and not
  for the columns lerobot does not renumber in its dataset-level stats).

Prints PASS/FAIL lines and exits non-zero on any failure.
"""

import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq


failures = []


def fail(msg):
    failures.append(msg)
    print("FAIL", msg)


def load(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset("local/" + root.name, root=root)


def video_keys(ds):
    return [k for k, f in ds.meta.features.items() if f["dtype"] == "video"]


def same_frame(a, b, keys, where):
    import torch

    for k in ["observation.state", "action"]:
        if not torch.equal(a[k], b[k]):
            fail(f"{where}: {k} {a[k]} != {b[k]}")
            return False
    if a["task"] != b["task"]:
        fail(f"{where}: task {a['task']!r} != {b['task']!r}")
        return False
    for k in keys:
        if not torch.equal(a[k], b[k]):
            diff = (a[k] - b[k]).abs().max().item()
            fail(f"{where}: {k} differs after decode (max |diff| {diff})")
            return False
    return True


def merged_rows(root: Path):
    files = sorted((root / "data").glob("*/*.parquet"))
    return pq.read_table(files[0]).schema, [pq.read_table(f) for f in files]


def column(tables, col):
    import pyarrow as pa

    t = pa.concat_tables(tables)
    v = t.column(col).to_pylist()
    return np.array(v, dtype=np.float64).reshape(len(v), -1)


def check_stats(root: Path):
    stats = json.loads((root / "meta/stats.json").read_text())
    schema, tables = merged_rows(root)
    for col in schema.names:
        if col not in stats:
            fail(f"stats.json lacks {col}")
            continue
        data = column(tables, col)
        entry = stats[col]
        for name, want in [
            ("min", data.min(axis=0)),
            ("max", data.max(axis=0)),
            ("mean", data.mean(axis=0)),
            ("std", data.std(axis=0)),
        ]:
            got = np.array(entry[name], dtype=np.float64).reshape(-1)
            if not np.allclose(got, want, rtol=1e-6, atol=1e-6):
                fail(f"stats.json {col}.{name} {got} where the rows give {want}")
        if "count" in entry and entry["count"][0] != len(data):
            fail(f"stats.json {col}.count {entry['count']} where there are {len(data)} rows")
        for q, name in [(0.01, "q01"), (0.5, "q50"), (0.99, "q99")]:
            if name not in entry:  # GR00T's stats.json (v2.1) keeps q01 and q99 only
                continue
            got = np.array(entry[name], dtype=np.float64).reshape(-1)
            want = np.quantile(data, q, axis=0)
            # Exact below the sketch's level capacity (4096 values a dimension); the tests stay below it.
            if len(data) <= 4096 and not np.allclose(got, want, rtol=1e-6, atol=1e-6):
                fail(f"stats.json {col}.{name} {got} where numpy gives {want}")


def main(argv):
    aggregate_dir = None
    if "--lerobot-aggregate" in argv:
        i = argv.index("--lerobot-aggregate")
        aggregate_dir = Path(argv[i + 1])
        argv = argv[:i] + argv[i + 2 :]
    merged_root, input_roots = Path(argv[0]), [Path(a) for a in argv[1:]]
    merged = load(merged_root)
    inputs = [load(r) for r in input_roots]
    keys = video_keys(merged)
    total = sum(len(d) for d in inputs)
    if len(merged) != total:
        fail(f"merged dataset has {len(merged)} frames, the inputs {total}")
    if merged.meta.total_episodes != sum(d.meta.total_episodes for d in inputs):
        fail(f"merged dataset has {merged.meta.total_episodes} episodes")
    offset, episodes = 0, 0
    for src_root, src in zip(input_roots, inputs):
        for j in range(len(src)):
            a, b = merged[offset + j], src[j]
            where = f"merged frame {offset + j} ({src_root.name} frame {j})"
            if int(a["episode_index"]) != episodes + int(b["episode_index"]):
                fail(f"{where}: episode_index {int(a['episode_index'])}")
                break
            if not same_frame(a, b, keys, where):
                break
        offset += len(src)
        episodes += src.meta.total_episodes
    print(("FAIL" if failures else "PASS"), f"{merged_root.name}: {len(merged)} frames from {len(inputs)} input(s)")
    check_stats(merged_root)

    if aggregate_dir is not None:
        from lerobot.datasets.aggregate import aggregate_datasets

        aggregate_datasets(
            repo_ids=["local/" + r.name for r in input_roots],
            aggr_repo_id="local/" + aggregate_dir.name,
            roots=input_roots,
            aggr_root=aggregate_dir,
        )
        theirs = load(aggregate_dir)
        if len(theirs) != len(merged):
            fail(f"lerobot's aggregate has {len(theirs)} frames, the merge {len(merged)}")
        for i in range(min(len(theirs), len(merged))):
            a, b = merged[i], theirs[i]
            if int(a["episode_index"]) != int(b["episode_index"]) or int(a["index"]) != int(b["index"]):
                fail(f"frame {i}: episode/index {int(a['episode_index'])}/{int(a['index'])} where lerobot has "
                     f"{int(b['episode_index'])}/{int(b['index'])}")
                break
            if not same_frame(a, b, keys, f"frame {i} against lerobot's aggregate"):
                break
        if list(merged.meta.tasks.index) != list(theirs.meta.tasks.index):
            fail(f"tasks {list(merged.meta.tasks.index)} where lerobot has {list(theirs.meta.tasks.index)}")
        ours_stats = json.loads((merged_root / "meta/stats.json").read_text())
        their_stats = json.loads((aggregate_dir / "meta/stats.json").read_text())
        for col, entry in their_stats.items():
            # lerobot aggregates the inputs' own stats of these without renumbering them.
            if col in ("episode_index", "index", "task_index"):
                continue
            if col not in ours_stats:
                fail(f"stats.json lacks {col}, which lerobot's aggregate has")
                continue
            for name in ["min", "max", "mean", "std", "count"]:
                got = np.array(ours_stats[col][name], dtype=np.float64).reshape(-1)
                want = np.array(entry[name], dtype=np.float64).reshape(-1)
                if not np.allclose(got, want, rtol=1e-5, atol=1e-6):
                    fail(f"stats {col}.{name}: {got} where lerobot's aggregate has {want}")
        print(("FAIL" if failures else "PASS"), f"{merged_root.name} against lerobot's aggregate_datasets")

    if failures:
        print(f"0 passed, {len(failures)} failed")
        return 1
    print("1 passed, 0 failed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
