"""The Python blocks of README.md and docs/python.md run as written against the demo's models.

A newcomer pastes the README's "lines to a gradient" into Python with `relreward demo`'s models
on the server; the blocks once used a made-up shape and step ([1, 64, 6], t = 10) that no demo
model takes. This test runs them against a server on which `relreward demo --size tiny` ran.

The rule, for every ```python fence in the two files (indented ones included): the nearest
non-blank line above it must be an HTML comment that says what happens to it, else the test
fails (so a new block cannot escape unnoticed):

- ``<!-- runs against: relreward demo --size tiny ... -->``: the block runs on its own, in a
  fresh interpreter (``sys.executable``) in an empty working directory;
- ``<!-- runs against: relreward demo --size tiny, after the page's first block -->``: the
  page's first runnable block (which must run on its own) runs first, in the same
  interpreter, then this block: the reference's fragments continue from its opening example
  (``client``, ``model``, ``x``), as a reader working down the page would;
- ``<!-- not run: REASON -->``: not run (say why: a checkpoint the test does not have, ...).

The one change made to a block is its address: ``127.0.0.1:50051`` (the server's default, what
the docs show) becomes the test server's ephemeral port. Each block must exit 0 within
``BLOCK_TIMEOUT_S``. The demo's tiny size takes about 10 s on 2 cores (4 goals, T = 10).
"""

from __future__ import annotations

import pathlib
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass

import pytest

from conftest import REPO, start_server

FILES = ("README.md", "docs/python.md")
DOCS_ADDRESS = "127.0.0.1:50051"
BLOCK_TIMEOUT_S = 120
RUNS = "<!-- runs against: relreward demo --size tiny"
AFTER_FIRST = "after the page's first block"
NOT_RUN = "<!-- not run:"


@dataclass
class Block:
    file: str
    line: int  # 1-based line of the opening fence
    source: str
    marker: str  # the comment line above the fence ("" when there is none)

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}"


def python_blocks(file: str) -> list[Block]:
    """Every ```python fence of ``file`` with its (dedented) source and the comment above it."""
    lines = (REPO / file).read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = re.match(r"^(\s*)```python\s*$", lines[i])
        if not m:
            i += 1
            continue
        indent, start = m.group(1), i
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == "```"), None)
        assert end is not None, f"{file}:{i + 1}: a ```python fence that is never closed"
        above = next((lines[j].strip() for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        marker = above if above.startswith("<!--") else ""
        body = "\n".join(ln[len(indent):] if ln.startswith(indent) else ln for ln in lines[start + 1:end])
        blocks.append(Block(file, start + 1, textwrap.dedent(body) + "\n", marker))
        i = end + 1
    return blocks


ALL_BLOCKS = [b for f in FILES for b in python_blocks(f)]


def runnable() -> list[tuple[Block, str]]:
    """(block, the program that runs it) for each block marked to run, in file order."""
    out = []
    for file in FILES:
        first: Block | None = None
        for b in (b for b in ALL_BLOCKS if b.file == file and b.marker.startswith(RUNS)):
            if AFTER_FIRST in b.marker:
                assert first is not None, f"{b.id}: runs after the page's first block, but none comes before it"
                program = first.source + "\n" + b.source
            else:
                if first is None:
                    first = b
                program = b.source
            out.append((b, program))
    return out


def test_every_python_block_says_whether_it_runs():
    assert ALL_BLOCKS, "no ```python blocks found: has the fence syntax changed?"
    unmarked = [b.id for b in ALL_BLOCKS if not (b.marker.startswith(RUNS) or b.marker.startswith(NOT_RUN))]
    assert not unmarked, (f"python blocks without a '{RUNS} -->' or '{NOT_RUN} REASON -->' comment just above "
                          f"their fence: {unmarked} (see this test's docstring)")
    # The opening example of each file is the one a newcomer runs first: it must run.
    for file in FILES:
        assert any(b.file == file and b.marker.startswith(RUNS) for b in ALL_BLOCKS), f"{file}: no block runs"


@pytest.fixture(scope="module")
def demo_server(tmp_path_factory: pytest.TempPathFactory):
    """A server of its own (other tests count the shared one's models) on which `relreward demo
    --size tiny` ran."""
    root = tmp_path_factory.mktemp("readme-demo")
    s = start_server(root / "data")
    try:
        s.cli("demo", "--size", "tiny", "--out", str(root / "demo-out"))
        yield s
    finally:
        s.stop()


RUNNABLE = runnable()


@pytest.mark.parametrize("block,program", RUNNABLE, ids=[b.id for b, _ in RUNNABLE])
def test_block_runs_as_written(block: Block, program: str, demo_server, tmp_path: pathlib.Path):
    assert DOCS_ADDRESS in program, f"{block.id}: the block names no {DOCS_ADDRESS}, so it cannot be pointed at the test server"
    source = program.replace(DOCS_ADDRESS, demo_server.addr)
    p = subprocess.run([sys.executable, "-c", source], cwd=tmp_path, capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=BLOCK_TIMEOUT_S)
    assert p.returncode == 0, (f"{block.id} ({block.marker}) failed ({p.returncode}):\n--- program\n{program}"
                               f"--- stdout\n{p.stdout}\n--- stderr\n{p.stderr}")
