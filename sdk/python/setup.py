"""Build hook: generate the gRPC stubs from the repository's proto/ before the package is collected.

The stubs are never committed. `pip install ./sdk/python` builds from this directory, so the protos are
found at ../../proto relative to this file; PHONE2ACT_PROTO_DIR overrides that (e.g. for a copied source
tree). A source distribution carries its own copy under ./proto (added to the release tree by the sdist
command), so it builds anywhere.

A build leaves the checkout as it was: the stubs are generated into the build's own library directory, and
setuptools' build and egg-info directories live in a scratch directory removed when the build ends. Only an
editable install (`pip install -e`) writes the stubs under src/, where the editable package must find them.
"""

from __future__ import annotations

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

HERE = Path(__file__).resolve().parent
SCRATCH = Path(tempfile.mkdtemp(prefix="phone2act-sdk-build-"))
atexit.register(shutil.rmtree, SCRATCH, ignore_errors=True)


def proto_root() -> Path:
    candidates = [os.environ.get("PHONE2ACT_PROTO_DIR"), HERE.parent.parent / "proto", HERE / "proto"]
    for c in candidates:
        if c and (Path(c) / "phone2act" / "v1").is_dir():
            return Path(c)
    raise SystemExit(
        "phone2act: cannot find the .proto files (looked in ../../proto and ./proto); "
        "set PHONE2ACT_PROTO_DIR to the repository's proto/ directory"
    )


def generate(out: Path) -> None:
    from grpc_tools import protoc  # build requirement, see pyproject.toml

    root = proto_root()
    protos = sorted(str(p.relative_to(root)) for p in (root / "phone2act" / "v1").glob("*.proto"))
    include = str(Path(protoc.__file__).parent / "_proto")  # google/protobuf well-known types
    # -I root keeps the import path "phone2act/v1/x.proto", so the generated modules import each other as
    # `from phone2act.v1 import common_pb2`, which is where they land under src/.
    out.mkdir(parents=True, exist_ok=True)
    args = ["protoc", f"-I{root}", f"-I{include}", f"--python_out={out}", f"--pyi_out={out}",
            f"--grpc_python_out={out}", *protos]
    if protoc.main(args) != 0:
        raise SystemExit(f"phone2act: protoc failed on {root}")
    print(f"phone2act: generated {len(protos)} proto modules from {root} into {out}", file=sys.stderr)


class BuildPy(build_py):
    def run(self) -> None:
        super().run()
        if self.editable_mode:
            # The editable package is src/ itself: the stubs must be there (they are git-ignored).
            generate(HERE / "src")
        else:
            generate(Path(self.build_lib))


class Sdist(sdist):
    # Ship the .proto files inside the sdist (at ./proto, the second place proto_root() looks), written into
    # the release tree rather than the checkout.
    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        root = proto_root()
        shutil.copytree(root / "phone2act", Path(base_dir) / "proto" / "phone2act",
                        ignore=shutil.ignore_patterns("*.rs"), dirs_exist_ok=True)


setup(
    cmdclass={"build_py": BuildPy, "sdist": Sdist},
    options={"build": {"build_base": str(SCRATCH / "build")}, "egg_info": {"egg_base": str(SCRATCH)}},
)
