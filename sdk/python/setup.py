"""Build hook: generate the gRPC stubs from the repository's proto/ before the package is collected.

The stubs are never committed. `pip install ./sdk/python` builds in place, so the protos are found at
../../proto relative to this file; PHONE2ACT_PROTO_DIR overrides that (e.g. for a copied source tree).
A source distribution carries its own copy under ./proto (copied by the sdist command, listed in
MANIFEST.in), so it builds anywhere.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.egg_info import egg_info
from setuptools.command.sdist import sdist

HERE = Path(__file__).resolve().parent
OUT = HERE / "src"


def proto_root() -> Path:
    candidates = [os.environ.get("PHONE2ACT_PROTO_DIR"), HERE.parent.parent / "proto", HERE / "proto"]
    for c in candidates:
        if c and (Path(c) / "phone2act" / "v1").is_dir():
            return Path(c)
    raise SystemExit(
        "phone2act: cannot find the .proto files (looked in ../../proto and ./proto); "
        "set PHONE2ACT_PROTO_DIR to the repository's proto/ directory"
    )


def generate() -> None:
    from grpc_tools import protoc  # build requirement, see pyproject.toml

    root = proto_root()
    protos = sorted(str(p.relative_to(root)) for p in (root / "phone2act" / "v1").glob("*.proto"))
    include = str(Path(protoc.__file__).parent / "_proto")  # google/protobuf well-known types
    # -I root keeps the import path "phone2act/v1/x.proto", so the generated modules import each other as
    # `from phone2act.v1 import common_pb2`, which is where they land under src/.
    args = ["protoc", f"-I{root}", f"-I{include}", f"--python_out={OUT}", f"--pyi_out={OUT}",
            f"--grpc_python_out={OUT}", *protos]
    if protoc.main(args) != 0:
        raise SystemExit(f"phone2act: protoc failed on {root}")
    print(f"phone2act: generated {len(protos)} proto modules from {root}", file=sys.stderr)


class BuildPy(build_py):
    def run(self) -> None:
        generate()
        super().run()


class EggInfo(egg_info):
    # egg_info runs first and lists the package files; generate before it so the stubs are included.
    def run(self) -> None:
        generate()
        super().run()


class Sdist(sdist):
    # Ship the .proto files inside the sdist (at ./proto, the second place proto_root() looks).
    def run(self) -> None:
        root = proto_root()
        bundled = HERE / "proto"
        if root.resolve() != bundled.resolve():
            shutil.rmtree(bundled, ignore_errors=True)
            shutil.copytree(root / "phone2act", bundled / "phone2act", ignore=shutil.ignore_patterns("*.rs"))
        super().run()


setup(cmdclass={"build_py": BuildPy, "egg_info": EggInfo, "sdist": Sdist})
