"""A real `phone2act serve` (a sim arm and a test-pattern camera) for the LeRobot plugin tests.

Servers are started exactly as tests/python starts them (its conftest, loaded under another module name).
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("phone2act_py_conftest", REPO / "tests" / "python" / "conftest.py")
assert _spec is not None and _spec.loader is not None
py_conftest = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = py_conftest
_spec.loader.exec_module(py_conftest)

Server = py_conftest.Server
wait_until = py_conftest.wait_until

CAMERA = """
[[cameras]]
name = "front"
kind = "test_pattern"
width = 64
height = 48
fps = 20
"""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("server")
    s = py_conftest.start_server(tmp, py_conftest.config_text(tmp / "ds", cameras=CAMERA))
    yield s
    s.stop()
