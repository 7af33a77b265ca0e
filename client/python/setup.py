"""Build hook: compiles the relreward.v1 protos into the private package ``relreward._proto``.

The protos come from the repository (``../../proto/relreward/v1``) when building from a clone,
or from the copy an sdist carries (``proto/relreward/v1``, made here when the sdist is built).
Only ``relreward/v1`` is compiled: ``proto/inference`` is never, as tritonclient ships its
own stubs for it and both would register ``inference.*`` in protobuf's default pool.

The generated modules import each other as ``from relreward.v1 import x_pb2``; that is rewritten
to ``from relreward._proto import x_pb2`` so the stubs live under this package alone and cannot
clash with another package's ``relreward`` (or anyone's top-level ``relreward.v1``).
"""

from __future__ import annotations

import pathlib
import re
import shutil
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent
REPO_PROTO = HERE.parent.parent / "proto"
LOCAL_PROTO = HERE / "proto"
OUT = HERE / "src" / "relreward" / "_proto"
IMPORT = re.compile(r"^from relreward\.v1 import ", re.MULTILINE)


def proto_root() -> pathlib.Path:
    """The directory holding relreward/v1/*.proto; refreshes the local copy from the repo."""
    if (REPO_PROTO / "relreward" / "v1").is_dir():
        dest = LOCAL_PROTO / "relreward" / "v1"
        dest.mkdir(parents=True, exist_ok=True)
        for old in dest.glob("*.proto"):
            old.unlink()
        for src in sorted((REPO_PROTO / "relreward" / "v1").glob("*.proto")):
            shutil.copyfile(src, dest / src.name)
    if not (LOCAL_PROTO / "relreward" / "v1").is_dir():
        raise SystemExit(f"no protos: neither {REPO_PROTO} nor {LOCAL_PROTO} holds relreward/v1")
    return LOCAL_PROTO


def generate() -> None:
    """Runs protoc (grpcio-tools) over relreward/v1/*.proto into relreward/_proto/."""
    from grpc_tools import protoc

    root = proto_root()
    files = sorted(str(p.relative_to(root)) for p in (root / "relreward" / "v1").glob("*.proto"))
    include = pathlib.Path(protoc.__file__).parent / "_proto"
    with tempfile.TemporaryDirectory() as tmp:
        args = ["protoc", f"-I{root}", f"-I{include}", f"--python_out={tmp}", f"--pyi_out={tmp}",
                f"--grpc_python_out={tmp}", *files]
        if protoc.main(args) != 0:
            raise SystemExit("protoc failed on " + ", ".join(files))
        for old in OUT.glob("*_pb2*.py*"):
            old.unlink()
        for path in sorted((pathlib.Path(tmp) / "relreward" / "v1").iterdir()):
            text = IMPORT.sub("from relreward._proto import ", path.read_text())
            (OUT / path.name).write_text(text)


class BuildPyWithStubs(build_py):
    """build_py that first generates the stubs (also in editable installs)."""

    def run(self) -> None:
        generate()
        super().run()


# Copy the protos at every invocation from a clone, so that an sdist built now carries them.
if (REPO_PROTO / "relreward" / "v1").is_dir():
    proto_root()

setup(cmdclass={"build_py": BuildPyWithStubs})
