"""Build hook: compiles the relreward.v1 protos into the private package ``relreward._proto``.

The protos come from the repository (``../../proto/relreward/v1``) when building from a clone,
or from the copy an sdist carries (``proto/relreward/v1``, put into the sdist's own tree when
the sdist is built). Only ``relreward/v1`` is compiled: ``proto/inference`` is never, as
tritonclient ships its own stubs for it and both would register ``inference.*`` in protobuf's
default pool.

The generated modules import each other as ``from relreward.v1 import x_pb2``; that is rewritten
to ``from relreward._proto import x_pb2`` so the stubs live under this package alone and cannot
clash with another package's ``relreward`` (or anyone's top-level ``relreward.v1``).

Building or installing from a checkout writes nothing into it: the stubs are generated into the
build directory (not ``src/``), the sdist's proto copy goes into the sdist's staging tree (not
``proto/`` here), and setuptools' ``build/`` and ``*.egg-info`` go to a temporary directory.
Only an editable install (``pip install -e``) generates the stubs into ``src/relreward/_proto``,
since it runs the package from ``src/``.
"""

from __future__ import annotations

import atexit
import pathlib
import re
import shutil
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

HERE = pathlib.Path(__file__).resolve().parent
REPO_PROTO = HERE.parent.parent / "proto"
LOCAL_PROTO = HERE / "proto"
IMPORT = re.compile(r"^from relreward\.v1 import ", re.MULTILINE)


def proto_root() -> pathlib.Path:
    """The directory holding relreward/v1/*.proto: the repository's when building from a clone,
    else the sdist's copy."""
    for root in (REPO_PROTO, LOCAL_PROTO):
        if (root / "relreward" / "v1").is_dir():
            return root
    raise SystemExit(f"no protos: neither {REPO_PROTO} nor {LOCAL_PROTO} holds relreward/v1")


def generate(out: pathlib.Path) -> None:
    """Runs protoc (grpcio-tools) over relreward/v1/*.proto into ``out`` (relreward/_proto)."""
    from grpc_tools import protoc

    root = proto_root()
    files = sorted(str(p.relative_to(root)) for p in (root / "relreward" / "v1").glob("*.proto"))
    include = pathlib.Path(protoc.__file__).parent / "_proto"
    with tempfile.TemporaryDirectory() as tmp:
        args = ["protoc", f"-I{root}", f"-I{include}", f"--python_out={tmp}", f"--pyi_out={tmp}",
                f"--grpc_python_out={tmp}", *files]
        if protoc.main(args) != 0:
            raise SystemExit("protoc failed on " + ", ".join(files))
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("*_pb2*.py*"):
            old.unlink()
        for path in sorted((pathlib.Path(tmp) / "relreward" / "v1").iterdir()):
            text = IMPORT.sub("from relreward._proto import ", path.read_text())
            (out / path.name).write_text(text)


class BuildPyWithStubs(build_py):
    """build_py that generates the stubs into the build directory after copying the sources
    (into ``src/`` for an editable install, which imports from there)."""

    def run(self) -> None:
        if self.editable_mode:
            generate(HERE / "src" / "relreward" / "_proto")
            super().run()
            return
        super().run()
        generate(pathlib.Path(self.build_lib) / "relreward" / "_proto")

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        # The generated files are outputs too (the wheel's RECORD is built from the tree, but
        # `install --record` and editable mappings ask here).
        outputs = list(super().get_outputs(include_bytecode))
        out = pathlib.Path(self.build_lib) / "relreward" / "_proto"
        outputs += [str(p) for p in sorted(out.glob("*_pb2*.py*")) if str(p) not in outputs]
        return outputs


class SdistWithProtos(sdist):
    """sdist that puts a copy of the repository's protos into the sdist's staging tree (so a
    wheel can be built from the sdist alone) without writing them into the checkout."""

    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        src = proto_root() / "relreward" / "v1"
        dest = pathlib.Path(base_dir) / "proto" / "relreward" / "v1"
        dest.mkdir(parents=True, exist_ok=True)
        for proto in sorted(src.glob("*.proto")):
            shutil.copyfile(proto, dest / proto.name)


# setuptools' intermediate folders (build/, the egg-info) in a temporary directory, so that a
# build leaves no folder in the source tree; removed when this process ends.
_SCRATCH = tempfile.mkdtemp(prefix="relreward-build-")
atexit.register(shutil.rmtree, _SCRATCH, True)

setup(cmdclass={"build_py": BuildPyWithStubs, "sdist": SdistWithProtos},
      options={"build": {"build_base": str(pathlib.Path(_SCRATCH) / "build")},
               "egg_info": {"egg_base": _SCRATCH}})
