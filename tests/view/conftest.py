"""Fixtures: a real `phone2act serve` (the Python suite's launcher, tests/python/conftest.py), and a reader of
the view's .rrd files built on rerun-sdk's own `RrdReader`."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from collections import defaultdict
from pathlib import Path
from typing import Any

import pyarrow as pa

REPO = Path(__file__).resolve().parents[2]

# One server launcher for every Python suite: loaded under its own name so pytest does not see two conftests.
_spec = importlib.util.spec_from_file_location("phone2act_python_suite", REPO / "tests" / "python" / "conftest.py")
assert _spec is not None and _spec.loader is not None
suite = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = suite  # dataclasses look their module up there
_spec.loader.exec_module(suite)


def read_rrd(path: Path) -> dict[str, dict[str, list[Any]]]:
    """Every entity of the first recording in `path`: column name ("Transform3D:translation",
    "server_time" in ns, ...) -> values, rows in the order they were logged (static rows have no time)."""
    try:
        from rerun.chunk import RrdReader  # rerun-sdk >= 0.41
    except ImportError:
        from rerun.experimental import RrdReader  # 0.32 .. 0.40
    out: dict[str, dict[str, list[Any]]] = defaultdict(lambda: defaultdict(list))
    with warnings.catch_warnings():
        # The view's --save file has no footer (see phone2act_view.__main__); reading it whole needs none.
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        reader = RrdReader(path)
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        cols = out[chunk.entity_path]
        for name in batch.schema.names:
            if name == "rerun.controls.RowId":
                continue
            col = batch.column(name)
            if pa.types.is_temporal(col.type):  # timelines as integer nanoseconds
                col = col.cast(pa.int64())
            cols[name].extend(col.to_pylist())
    return out


def texts(rrd: dict[str, dict[str, list[Any]]], entity: str) -> list[str]:
    """The `TextLog` messages of `entity`, in order."""
    return [t[0] for t in rrd[entity]["TextLog:text"]]
