"""Fixtures: the real relreward-server on an ephemeral loopback port, and a tiny trained reward.

Binaries: $RELREWARD_SERVER_BIN and $RELREWARD_CLI_BIN, defaulting to the repository's
target/release/relreward-server and target/release/relreward (what `make test` builds). The
server is started by the development package's launcher (relreward_dev.launcher, dev/python)
as tests/src/lib.rs does (`--listen 127.0.0.1:0`, a temporary data dir, no metrics port, no
shutdown drain, one intra-op thread) and its address read from the first line of its stdout.

The tests of the locomotion experiment and of examples/ import those folders' scripts as
modules: both folders are put on sys.path here, the one place that does it.
"""

from __future__ import annotations

import pathlib
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from relreward_dev.launcher import Binaries, Server

REPO = pathlib.Path(__file__).resolve().parents[3]
BINARIES = Binaries.of_checkout(REPO)
SERVER_BIN = BINARIES.server
# Scripts the tests import: experiments/locomotion's (steer, planner, data, common, diagnose;
# they import each other as siblings, as when run by path), experiments/pointmaze's (rl.py
# imports generate.py) and examples/'.
for folder in ("experiments/locomotion", "experiments/pointmaze", "examples"):
    sys.path.insert(0, str(REPO / folder))

TINY_DIFFUSION_CONFIG = """[optimization]
steps = 12
batch_size = 8
log_every = 4
[diffusion]
horizon = 8
n_timesteps = 10
architecture = { kind = "temporal_unet", dim = 8, dim_mults = [1, 2] }
"""


def start_server(data_dir: pathlib.Path, env: dict[str, str] | None = None, **kwargs) -> Server:
    """relreward-server as tests/src/lib.rs starts it (one intra-op thread); ``env``, ``args``
    and ``listen`` as relreward_dev.launcher.Server takes them. ``stop()`` kills it."""
    return Server(BINARIES, data_dir, env={"RELREWARD__ENGINE__INTRA_OP_THREADS": "1", **(env or {})}, **kwargs)


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory):
    # TorchScript upload is off by default (a TorchScript file is a program); on for the tests.
    s = start_server(tmp_path_factory.mktemp("server") / "data",
                     env={"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true"})
    yield s
    s.stop()


@pytest.fixture(scope="session")
def client(server: Server):
    import relreward

    with relreward.Client(server.addr) as c:
        yield c


@dataclass
class Tiny:
    dataset: str
    base: str
    expert: str
    reward: str
    horizon: int
    transition_dim: int
    n_timesteps: int
    npz: pathlib.Path


def tiny_trajectories(seed: int = 0) -> dict[str, np.ndarray]:
    """5 episodes (lengths 30, 5, 40, 12, 25), obs along sin/cos curves with noise, random
    actions; the first episode ends in a terminal, the others in timeouts (as tests/src/lib.rs
    train_tiny_reward)."""
    rng = np.random.default_rng(seed)
    lengths = [30, 5, 40, 12, 25]
    n = sum(lengths)
    i = np.arange(n, dtype=np.float32)
    obs = np.stack([np.sin(i / 7) + 0.1 * (rng.random(n) - 0.5), np.cos(i / 5) + 0.1 * (rng.random(n) - 0.5)], 1)
    act = 2 * (rng.random((n, 2)) - 0.5)
    terminals, timeouts = np.zeros(n, bool), np.zeros(n, bool)
    ends = np.cumsum(lengths) - 1
    terminals[ends[0]] = True
    timeouts[ends[1:]] = True
    return {"observations": obs.astype(np.float32), "actions": act.astype(np.float32), "terminals": terminals,
            "timeouts": timeouts}


@pytest.fixture(scope="session")
def tiny(server: Server, tmp_path_factory: pytest.TempPathFactory) -> Tiny:
    """Uploads the tiny dataset with the CLI as `traj` and trains `base`, `expert` (diffusion,
    T = 10, horizon 8) and the windowed-MLP reward `rw` through the CLI, as train_tiny_reward."""
    d = tmp_path_factory.mktemp("tiny")
    path = d / "traj.npz"
    np.savez(path, **tiny_trajectories())
    server.cli("dataset", "upload", str(path), "--name", "traj")
    config = d / "diffusion.toml"
    config.write_text(TINY_DIFFUSION_CONFIG)
    for name, seed in (("base", "1"), ("expert", "2")):
        server.cli("train", "diffusion", "--name", name, "--dataset", "traj", "--config", str(config), "--seed", seed,
                   "--watch")
    server.cli("train", "reward", "--name", "rw", "--base", "base", "--expert", "expert", "--dataset", "traj",
               "--arch", "windowed_mlp", "--window", "4", "--hidden", "16,16", "--seed", "3", "--watch", "--steps", "8",
               "--batch-size", "8")
    return Tiny("traj", "base", "expert", "rw", 8, 4, 10, path)
