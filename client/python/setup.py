"""Build hook: compiles the relreward.v1 protos into the package ``relreward.v1``.

The protos come from the repository (``../../proto/relreward/v1``) when building from a clone,
or from the copy an sdist carries (``proto/relreward/v1``, put into the sdist's own tree when
the sdist is built). Only ``relreward/v1`` is compiled: ``proto/inference`` is never, as
tritonclient ships its own stubs for it and both would register ``inference.*`` in protobuf's
default pool.

The stubs are protoc's output as it is: the module path (``relreward.v1.jobs_pb2``) and the file
names registered in protobuf's pool (``relreward/v1/jobs.proto``) are the ones that
``python -m grpc_tools.protoc -I proto --python_out=OUT --grpc_python_out=OUT
proto/relreward/v1/*.proto`` gives a user. Code written against such user-compiled stubs thus
runs unchanged with the package installed (Python takes the installed regular package
``relreward`` before a ``relreward/`` folder without ``__init__.py`` in OUT), and a user's copy
loaded under another name registers byte-identical files, which the pool accepts, sharing one
class per message. Message classes report an importable module (pickle needs that).

Building or installing from a checkout writes nothing into it: the stubs are generated into the
build directory (not ``src/``), the sdist's proto copy goes into the sdist's staging tree (not
``proto/`` here), and setuptools' ``build/`` and ``*.egg-info`` go to a temporary directory.
Only an editable install (``pip install -e``) generates the stubs into ``src/relreward/v1``,
since it runs the package from ``src/``.
"""

from __future__ import annotations

import atexit
import pathlib
import shutil
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

HERE = pathlib.Path(__file__).resolve().parent
REPO_PROTO = HERE.parent.parent / "proto"
LOCAL_PROTO = HERE / "proto"


def proto_root() -> pathlib.Path:
    """The directory holding relreward/v1/*.proto: the repository's when building from a clone,
    else the sdist's copy."""
    for root in (REPO_PROTO, LOCAL_PROTO):
        if (root / "relreward" / "v1").is_dir():
            return root
    raise SystemExit(f"no protos: neither {REPO_PROTO} nor {LOCAL_PROTO} holds relreward/v1")


def generate(out: pathlib.Path) -> None:
    """Runs protoc (grpcio-tools) over relreward/v1/*.proto into ``out`` (relreward/v1)."""
    try:
        from grpc_tools import protoc
    except ImportError as e:
        # SystemExit, not the ImportError: setuptools' editable install swallows an Exception from
        # a custom build_py and would install the package without its stubs.
        raise SystemExit("building relreward needs grpcio-tools==1.81.1 (a build requirement: with "
                         "--no-build-isolation, install it first)") from e

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
            shutil.copyfile(path, out / path.name)


class BuildPyWithStubs(build_py):
    """build_py that generates the stubs into the build directory after copying the sources
    (into ``src/`` for an editable install, which imports from there)."""

    def run(self) -> None:
        if self.editable_mode:
            generate(HERE / "src" / "relreward" / "v1")
            super().run()
            return
        super().run()
        generate(pathlib.Path(self.build_lib) / "relreward" / "v1")

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        # The generated files are outputs too (the wheel's RECORD is built from the tree, but
        # `install --record` and editable mappings ask here).
        outputs = list(super().get_outputs(include_bytecode))
        out = pathlib.Path(self.build_lib) / "relreward" / "v1"
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
