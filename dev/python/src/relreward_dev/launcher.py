"""relreward-server as a child process on a loopback port, for tests, experiments and benchmarks.

Module map: ``Binaries`` (where the server and CLI binaries are), ``ServerStartError``,
``Server`` (start, address, log, ``cli``, ``stop``).

The server is started with ``--listen 127.0.0.1:0`` (any free port) and prints
``relreward-server listening on HOST:PORT`` as its first stdout line once it serves; that line
is the only reliable way to learn the port, so ``Server`` waits for it. Every launched server
runs without a metrics port (two servers on one machine would fight over the default one) and
without a shutdown drain (nothing outlives the script that started it); callers add the rest
of the configuration as ``RELREWARD__*`` environment variables.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import threading
from dataclasses import dataclass

LISTENING = "relreward-server listening on "


@dataclass(frozen=True)
class Binaries:
    """The relreward-server and relreward (CLI) binaries."""

    server: pathlib.Path
    cli: pathlib.Path

    @classmethod
    def of_checkout(cls, repo: pathlib.Path) -> Binaries:
        """$RELREWARD_SERVER_BIN and $RELREWARD_CLI_BIN, else the checkout's release build
        (``target/release/``, what ``make build`` and ``make test`` build)."""
        return cls(
            server=pathlib.Path(os.environ.get("RELREWARD_SERVER_BIN", repo / "target/release/relreward-server")),
            cli=pathlib.Path(os.environ.get("RELREWARD_CLI_BIN", repo / "target/release/relreward")),
        )


class ServerStartError(RuntimeError):
    """The server binary is missing, or the server exited or stalled before reporting its address."""


class Server:
    """A running relreward-server: ``addr`` is HOST:PORT, ``cli(...)`` runs the CLI against it.

    ``env`` adds to (and overrides) this process's environment; ``args`` go before ``--listen``
    (e.g. ``["--config", path]``). Its stderr goes to ``log_path`` (default: beside the data
    directory, ``<data_dir name>-server.log``); stdout is drained so that the server never
    blocks on a full pipe. Usable as a context manager (``stop()`` on exit)."""

    def __init__(self, binaries: Binaries, data_dir: pathlib.Path, *, env: dict[str, str] | None = None,
                 args: list[str] | None = None, listen: str = "127.0.0.1:0", log_path: pathlib.Path | None = None,
                 start_secs: float = 60.0):
        if not binaries.server.exists():
            raise ServerStartError(f"{binaries.server} not found: build it (make build) or set RELREWARD_SERVER_BIN")
        self.binaries = binaries
        self.data_dir = data_dir
        self.log_path = log_path or data_dir.parent / f"{data_dir.name}-server.log"
        full_env = dict(os.environ, RELREWARD__METRICS__LISTEN="", RELREWARD__SERVER__SHUTDOWN_DRAIN_SECS="0",
                        **(env or {}))
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen([str(binaries.server), *(args or []), "--listen", listen, "--data-dir",
                                      str(data_dir)], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=self._log, env=full_env)
        line = self._first_line(start_secs)
        if not line.startswith(LISTENING):
            self.stop()
            raise ServerStartError(f"unexpected first line {line!r} from {binaries.server}; log:\n{self.log()}")
        self.addr = line[len(LISTENING):].strip()
        threading.Thread(target=lambda: [None for _ in self.proc.stdout], daemon=True).start()

    def _first_line(self, secs: float) -> str:
        # readline() has no timeout of its own: read on a thread and give up after `secs`.
        out: list[str] = []
        reader = threading.Thread(target=lambda: out.append(self.proc.stdout.readline().decode()), daemon=True)
        reader.start()
        reader.join(secs)
        if not out:
            self.stop()
            raise ServerStartError(f"the server did not report its address within {secs:.0f} s; log:\n{self.log()}")
        return out[0]

    def log(self) -> str:
        """The server's stderr so far."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def cli(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        """Runs ``relreward --endpoint http://ADDR ARGS``; with ``check``, a failure raises
        AssertionError with its output and the server's log."""
        if not self.binaries.cli.exists():
            raise FileNotFoundError(f"{self.binaries.cli} not found: build it (make build) or set RELREWARD_CLI_BIN")
        p = subprocess.run([str(self.binaries.cli), "--endpoint", f"http://{self.addr}", *args], capture_output=True,
                           text=True, stdin=subprocess.DEVNULL)
        if check and p.returncode != 0:
            raise AssertionError(f"relreward {args} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}\nlog:\n{self.log()}")
        return p

    def cli_json(self, *args: str) -> dict:
        """``cli("--json", *args)``, parsed."""
        return json.loads(self.cli("--json", *args).stdout)

    def stop(self, grace: float = 0.0) -> None:
        """grace 0: SIGKILL now (what a crash looks like to the data directory); otherwise
        SIGTERM, and SIGKILL if it has not exited after ``grace`` seconds."""
        if self.proc.poll() is None:
            if grace > 0:
                self.proc.terminate()
                try:
                    self.proc.wait(grace)
                except subprocess.TimeoutExpired:
                    pass
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
        self._log.close()

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *_exc) -> None:
        self.stop()
