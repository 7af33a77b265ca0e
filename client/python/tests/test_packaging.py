"""The package builds as `python -m build` does (sdist, then the wheel from the sdist), the
stubs are generated at build time as relreward.v1 (protoc's own output), the wheel imports next
to tritonclient and next to stubs a user compiles from proto/, and its requirements resolve
together with grpcio-tools, -health-checking and -reflection 1.85 (protobuf 7)."""

from __future__ import annotations

import json
import os
import re
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


MODULES = ("autoencoder", "datasets", "jobs", "models", "reward", "tensor")


def test_sdist_carries_the_protos_and_no_stubs(dists):
    sdist, _ = dists
    names = tarfile.open(sdist).getnames()
    protos = sorted(n.split("/", 1)[1] for n in names if n.endswith(".proto"))
    assert protos == [f"proto/relreward/v1/{p}.proto" for p in MODULES]
    assert not any(n.endswith("_pb2.py") for n in names)



def compile_like_a_user(out):
    """The repository's proto/ compiled as a user does (docs/python.md), into ``out``."""
    out.mkdir(parents=True, exist_ok=True)  # protoc writes into an existing folder only
    protos = sorted(str(p.relative_to(REPO)) for p in (REPO / "proto/relreward/v1").glob("*.proto"))
    p = subprocess.run([sys.executable, "-m", "grpc_tools.protoc", "-I", "proto", f"--python_out={out}",
                        f"--grpc_python_out={out}", *protos], capture_output=True, text=True, cwd=REPO)
    assert p.returncode == 0, p.stderr
    return out / "relreward" / "v1"


def test_wheel_holds_protocs_own_stubs_as_relreward_v1(dists, tmp_path):
    _, wheel = dists
    zf = zipfile.ZipFile(wheel)
    names = zf.namelist()
    for module in MODULES:
        assert f"relreward/v1/{module}_pb2.py" in names and f"relreward/v1/{module}_pb2_grpc.py" in names
    assert "relreward/py.typed" in names and "relreward/v1/reward_pb2.pyi" in names
    assert not any(n.startswith("relreward/_proto/") for n in names)  # the old private copy is gone
    assert not any("inference" in n for n in names)
    # Byte for byte what protoc gives a user (this environment's grpcio-tools built the wheel):
    # same module paths, same imports, same serialized files for protobuf's pool.
    user = compile_like_a_user(tmp_path)
    generated = sorted(p.name for p in user.iterdir())
    assert generated == sorted(n.rsplit("/", 1)[1] for n in names
                               if n.startswith("relreward/v1/") and n.endswith(("_pb2.py", "_pb2_grpc.py")))
    for name in generated:
        assert zf.read(f"relreward/v1/{name}") == (user / name).read_bytes(), name


def install_wheel(wheel, target):
    p = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
                        str(wheel)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return target


# Run in a fresh interpreter: imports the user's stubs (``relreward.v1`` with the user's folder
# first on sys.path) and the package in the order argv[2] says, loads the user's generated file
# itself as well (its descriptors must be accepted as identical duplicates), and round-trips
# messages between the package's classes and the user's.
COEXIST = r"""
import importlib.util, json, pickle, sys
site, out, order = sys.argv[1], sys.argv[2], sys.argv[3]
if order == "user-first":
    from relreward.v1 import jobs_pb2, reward_pb2_grpc
    import relreward
else:
    import relreward
    from relreward.v1 import jobs_pb2, reward_pb2_grpc
spec = importlib.util.spec_from_file_location("users_jobs_pb2", out + "/relreward/v1/jobs_pb2.py")
users = importlib.util.module_from_spec(spec)
spec.loader.exec_module(users)
mine = users.JobSpec(output_model="m", seed=3)
mine.optimization.steps = 7
theirs = relreward.pb.jobs.JobSpec.FromString(mine.SerializeToString())
back = users.JobSpec.FromString(theirs.SerializeToString())
print(json.dumps({
    "package_from_site": relreward.__file__.startswith(site),
    "same_module": jobs_pb2 is relreward.pb.jobs,
    "stub_has_service": hasattr(reward_pb2_grpc, "RewardServiceStub"),
    "same_file_descriptor": users.DESCRIPTOR is relreward.pb.jobs.DESCRIPTOR,
    "same_class": users.JobSpec is relreward.pb.jobs.JobSpec,
    "round_trip": [theirs.output_model, theirs.seed, theirs.optimization.steps, back == mine],
    "pickles": pickle.loads(pickle.dumps(theirs)) == mine,
    "module": type(theirs).__module__,
}))
"""


@pytest.mark.parametrize("order", ["user-first", "package-first"])
def test_user_compiled_stubs_and_the_installed_package_coexist(dists, tmp_path, order):
    """docs/python.md: stubs a user compiles from proto/ import as relreward.v1 next to the package
    (they used to be hidden: `No module named 'relreward.v1'`)."""
    _, wheel = dists
    site = install_wheel(wheel, tmp_path / "site")
    out = tmp_path / "out"
    compile_like_a_user(out)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(out), str(site)]))  # the user's folder first
    p = subprocess.run([sys.executable, "-c", COEXIST, str(site), str(out), order], capture_output=True,
                       text=True, env=env, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout) == {
        "package_from_site": True, "same_module": True, "stub_has_service": True, "same_file_descriptor": True,
        "same_class": True, "round_trip": ["m", 3, 7, True], "pickles": True, "module": "relreward.v1.jobs_pb2"}


def requirement(wheel, name):
    """The wheel's Requires-Dist specifier for ``name``."""
    from packaging.requirements import Requirement

    meta = next(n for n in zipfile.ZipFile(wheel).namelist() if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(meta).decode()
    reqs = [Requirement(line.split(":", 1)[1].strip()) for line in text.splitlines() if line.startswith("Requires-Dist:")]
    return next(r.specifier for r in reqs if r.name == name)


def test_requirements_fit_the_generated_code_and_protobuf_7(dists):
    """The run-time bounds are what the generated code needs: protobuf from its gencode version
    (runtime must not be older), grpcio from its GRPC_GENERATED_VERSION; and protobuf 7, which
    grpcio-tools / -health-checking / -reflection 1.85 require (>= 7.35.1), is admitted (the pin
    used to be < 7), as is tritonclient[grpc]'s < 7."""
    _, wheel = dists
    zf = zipfile.ZipFile(wheel)
    gencode = re.search(r"^# Protobuf Python Version: (\S+)$", zf.read("relreward/v1/jobs_pb2.py").decode(), re.M)[1]
    grpc_gen = re.search(r"^GRPC_GENERATED_VERSION = '(\S+)'$", zf.read("relreward/v1/jobs_pb2_grpc.py").decode(), re.M)[1]
    protobuf, grpcio = requirement(wheel, "protobuf"), requirement(wheel, "grpcio")
    assert {s.operator + s.version for s in protobuf if s.operator == ">="} == {">=" + gencode}
    assert {s.operator + s.version for s in grpcio if s.operator == ">="} == {">=" + grpc_gen}
    major = int(gencode.split(".")[0])
    # protobuf N+1 still loads gencode of major N; N+2 is not promised.
    for version in (gencode, f"{major}.99", "7.35.1", "7.36.2"):
        assert protobuf.contains(version), (str(protobuf), version)
    assert not protobuf.contains(f"{major + 2}.0.0")
    assert grpcio.contains("1.85.1")


def test_resolves_with_grpcio_tools_health_checking_and_reflection_1_85(dists, tmp_path):
    """pip's resolver, against the package index, accepts the wheel together with grpcio-tools,
    grpcio-health-checking and grpcio-reflection 1.85 (ResolutionImpossible with protobuf < 7), and
    the package's stubs load on the protobuf 7 it picks."""
    _, wheel = dists
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--retries", "1", "--timeout", "15"]
    probe = subprocess.run([*pip, "index", "versions", "grpcio-tools"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip("the package index is not reachable: " + probe.stderr.strip()[-200:])
    report = tmp_path / "report.json"
    p = subprocess.run([*pip, "install", "--dry-run", "--ignore-installed", "--only-binary", ":all:", "--quiet",
                        "--report", str(report), str(wheel), "grpcio-tools==1.85.1",
                        "grpcio-health-checking==1.85.1", "grpcio-reflection==1.85.1"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    picked = {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in json.loads(report.read_text())["install"]}
    assert picked["relreward"] == "0.1.0" and picked["protobuf"].startswith("7."), picked
    # The wheel's stubs (protobuf 6 gencode) on that protobuf 7 runtime, with this grpcio.
    pb7 = tmp_path / "pb7"
    p = subprocess.run([*pip, "install", "--quiet", "--no-deps", "--only-binary", ":all:", "--target", str(pb7),
                        "protobuf==" + picked["protobuf"]], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    site = install_wheel(wheel, tmp_path / "site")
    code = ("import warnings; warnings.simplefilter('error'); "
            "import google.protobuf as g, relreward, relreward.v1.reward_pb2_grpc; "
            "m = relreward.pb.jobs.JobSpec(output_model='m'); assert type(m).FromString(m.SerializeToString()) == m; "
            "print(g.__version__)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(pb7), str(site)]))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert p.returncode == 0 and p.stdout.strip() == picked["protobuf"], p.stdout + p.stderr


def test_wheel_installs_and_imports_with_tritonclient(dists, tmp_path):
    _, wheel = dists
    target = install_wheel(wheel, tmp_path / "site")
    code = ("import relreward, sys; import tritonclient.grpc; "
            "assert relreward.__file__.startswith(sys.argv[1]), relreward.__file__; print('ok')")
    env = dict(os.environ, PYTHONPATH=str(target))
    p = subprocess.run([sys.executable, "-c", code, str(target)], capture_output=True, text=True, env=env,
                       cwd=tmp_path)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr
