"""The package builds as `python -m build` does (sdist, then the wheel from the sdist), the
stubs are generated at build time under relreward._proto, and the wheel imports next to
tritonclient."""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
import zipfile

import pytest

from conftest import REPO


@pytest.fixture(scope="module")
def dists(tmp_path_factory):
    pytest.importorskip("build")
    out = tmp_path_factory.mktemp("dist")
    # --no-isolation: the build requirements (setuptools, grpcio-tools) come from this
    # environment, so the test needs no index; `python -m build client/python` fetches them.
    p = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out),
                        str(REPO / "client/python")], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    sdist = next(out.glob("relreward-*.tar.gz"))
    wheel = next(out.glob("relreward-*.whl"))
    return sdist, wheel


def test_sdist_carries_the_protos_and_no_stubs(dists):
    sdist, _ = dists
    names = tarfile.open(sdist).getnames()
    protos = sorted(n.split("/", 1)[1] for n in names if n.endswith(".proto"))
    assert protos == [f"proto/relreward/v1/{p}.proto" for p in ("datasets", "jobs", "models", "reward", "tensor")]
    assert not any(n.endswith("_pb2.py") for n in names)


def test_wheel_holds_generated_private_stubs(dists):
    _, wheel = dists
    names = zipfile.ZipFile(wheel).namelist()
    for module in ("datasets", "jobs", "models", "reward", "tensor"):
        assert f"relreward/_proto/{module}_pb2.py" in names and f"relreward/_proto/{module}_pb2_grpc.py" in names
    assert "relreward/py.typed" in names and "relreward/_proto/reward_pb2.pyi" in names
    assert not any(n.startswith(("relreward/v1", "inference")) or "inference" in n for n in names)
    text = zipfile.ZipFile(wheel).read("relreward/_proto/reward_pb2_grpc.py").decode()
    assert "from relreward._proto import reward_pb2" in text and "from relreward.v1" not in text


def test_wheel_installs_and_imports_with_tritonclient(dists, tmp_path):
    _, wheel = dists
    target = tmp_path / "site"
    p = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
                        str(wheel)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    code = ("import relreward, sys; import tritonclient.grpc; "
            "assert relreward.__file__.startswith(sys.argv[1]), relreward.__file__; print('ok')")
    env = dict(os.environ, PYTHONPATH=str(target))
    p = subprocess.run([sys.executable, "-c", code, str(target)], capture_output=True, text=True, env=env,
                       cwd=tmp_path)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr
