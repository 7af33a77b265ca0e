"""Fixtures: the real relreward-server on an ephemeral loopback port, and a tiny trained reward.

Binaries: $RELREWARD_SERVER_BIN and $RELREWARD_CLI_BIN, defaulting to the repository's
target/release/relreward-server and target/release/relreward (what `make test` builds). The
server is started as tests/src/lib.rs does (`--listen 127.0.0.1:0`, a temporary data dir, no
metrics port, no shutdown drain, one intra-op thread) and its address read from the first line
of its stdout.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[3]
SERVER_BIN = pathlib.Path(os.environ.get("RELREWARD_SERVER_BIN", REPO / "target/release/relreward-server"))
CLI_BIN = pathlib.Path(os.environ.get("RELREWARD_CLI_BIN", REPO / "target/release/relreward"))

TINY_DIFFUSION_CONFIG = """[optimization]
steps = 12
batch_size = 8
log_every = 4
[diffusion]
horizon = 8
n_timesteps = 10
architecture = { kind = "temporal_unet", dim = 8, dim_mults = [1, 2] }
"""


class Server:
    """A running relreward-server; ``addr`` is host:port, ``cli(...)`` runs the CLI against it."""

    def __init__(self, data_dir: pathlib.Path, env: dict[str, str] | None = None, args: list[str] | None = None,
                 listen: str = "127.0.0.1:0"):
        assert SERVER_BIN.exists(), f"{SERVER_BIN} not found: build it (make test) or set RELREWARD_SERVER_BIN"
        self.data_dir = data_dir
        self.log_path = data_dir.parent / f"{data_dir.name}-server.log"
        full_env = dict(os.environ, RELREWARD__ENGINE__INTRA_OP_THREADS="1", RELREWARD__METRICS__LISTEN="",
                        RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS="0", **(env or {}))
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen([str(SERVER_BIN), *(args or []), "--listen", listen, "--data-dir",
                                      str(data_dir)], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=self._log, env=full_env)
        line = self._first_line(60)
        prefix = "relreward-server listening on "
        if not line.startswith(prefix):
            self.stop()
            raise RuntimeError(f"unexpected first line {line!r}; log:\n{self.log()}")
        self.addr = line[len(prefix):].strip()
        # Keep draining stdout so the server never blocks on a full pipe.
        threading.Thread(target=lambda: [None for _ in self.proc.stdout], daemon=True).start()

    def _first_line(self, secs: float) -> str:
        out: list[str] = []
        t = threading.Thread(target=lambda: out.append(self.proc.stdout.readline().decode()), daemon=True)
        t.start()
        t.join(secs)
        if not out:
            self.stop()
            raise RuntimeError(f"server did not report its address; log:\n{self.log()}")
        return out[0]

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def cli(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        """Runs ``relreward --endpoint http://ADDR ARGS``."""
        assert CLI_BIN.exists(), f"{CLI_BIN} not found: build it (make test) or set RELREWARD_CLI_BIN"
        p = subprocess.run([str(CLI_BIN), "--endpoint", f"http://{self.addr}", *args], capture_output=True,
                           text=True, stdin=subprocess.DEVNULL)
        if check and p.returncode != 0:
            raise AssertionError(f"relreward {args} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}\nlog:\n{self.log()}")
        return p

    def cli_json(self, *args: str) -> dict:
        return json.loads(self.cli("--json", *args).stdout)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory):
    # TorchScript upload is off by default (a TorchScript file is a program); on for the tests.
    s = Server(tmp_path_factory.mktemp("server") / "data", env={"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true"})
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
