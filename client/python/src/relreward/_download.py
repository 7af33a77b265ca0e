"""Writing a ``DownloadModel`` stream into a directory, checked and all-or-nothing.

What the sync and asyncio clients share (they differ only in how they iterate the stream):
:class:`ModelDownload` takes the stream's messages one by one (``feed``): the header names
every file (name, size, sha256), then the files' bytes follow in that order. Each file goes to
a hidden part file beside its target, hashed as it arrives; ``finish`` checks that every file
arrived whole with its digest, renames the part files into place and writes the stored
manifest as ``manifest.json``. ``close`` removes whatever part files are left, so a failed
download leaves nothing behind. The Rust client's ``download.rs`` does the same.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, BinaryIO

from relreward.v1 import models_pb2

if TYPE_CHECKING:  # the record the client swaps in (results imports nothing from here)
    from relreward.results import Model

#: Where the stored manifest goes, beside the files.
MANIFEST_FILE = "manifest.json"


@dataclass(frozen=True)
class DownloadedModel:
    """A model written by ``download_model``.

    ``path``: the model file (``weights.safetensors`` for native weights, which
    ``safetensors.torch.load_file`` reads; ``module.pt`` for a TorchScript module, which
    ``torch.jit.load`` reads). ``model``: its record (``GetModel``'s). ``manifest``: the stored
    manifest as a dict (architecture and sizes, space, normalizer, n_timesteps, ...; see
    ``DownloadModelHeader.manifest_json`` in models.proto), also written to ``manifest_path``.
    ``files``: every file written, the model file first (an Algorithm 2 reward's
    ``step_norm.safetensors`` after it).
    """

    path: pathlib.Path
    model: Model
    manifest: dict[str, Any]
    files: tuple[pathlib.Path, ...]
    manifest_path: pathlib.Path

    @property
    def module(self) -> pathlib.Path | None:
        """The TorchScript module (``module.pt``): an export's traced module, or a TorchScript
        model's stored file; None for a plain download of native weights."""
        return next((f for f in self.files if f.name == "module.pt"), None)


def _plain(name: str) -> bool:
    return bool(name) and name not in (".", "..", MANIFEST_FILE) and not any(ch in name for ch in "/\\\0")


class ModelDownload:
    """Receives one ``DownloadModel`` stream into ``out_dir`` (see the module docstring)."""

    def __init__(self, name: str, out_dir: str | os.PathLike, overwrite: bool) -> None:
        self.name = name
        self.dir = pathlib.Path(out_dir)
        self.overwrite = overwrite
        self._header: models_pb2.DownloadModelHeader | None = None
        self._parts: list[pathlib.Path] = []
        self._index = -1  # the file being received
        self._left = 0
        self._out: BinaryIO | None = None
        self._digest: Any = None

    def _fail(self, what: str) -> ValueError:
        return ValueError(f"DownloadModel {self.name!r}: {what}; nothing was written")

    def feed(self, message: models_pb2.DownloadModelResponse) -> None:
        """Takes the stream's next message."""
        kind = message.WhichOneof("message")
        if kind == "header":
            if self._header is not None:
                raise self._fail("a second header")
            self._start(message.header)
        elif kind == "chunk":
            if self._header is None:
                raise self._fail("the stream did not start with a header")
            self._write(message.chunk)
        else:
            raise self._fail("a message with neither header nor chunk")

    def _start(self, header: models_pb2.DownloadModelHeader) -> None:
        files = list(header.files)
        if not files:
            raise self._fail("the header lists no files")
        if files[0].sha256 != header.model.sha256 or files[0].size_bytes != header.model.size_bytes:
            raise self._fail(f"the header's first file {files[0].name} is not the model's")
        names = [f.name for f in files]
        bad = [n for n in names if not _plain(n)]
        if bad or len(set(names)) != len(names):
            raise self._fail(f"the server named files {names!r}, not distinct plain file names")
        self.dir.mkdir(parents=True, exist_ok=True)
        if not self.overwrite:
            for target in [*(self.dir / n for n in names), self.dir / MANIFEST_FILE]:
                if target.exists():
                    raise FileExistsError(f"{target}: exists; nothing was downloaded (pass overwrite=True to "
                                          "replace it, or choose another directory)")
        self._header = header
        self._parts = [self.dir / f".{n}.{os.getpid()}.part" for n in names]
        self._next_file()

    def _next_file(self) -> None:
        """Closes the current part file (checking its digest) and opens the next one(s); empty
        files are complete at once."""
        assert self._header is not None
        files = self._header.files
        while True:
            if self._out is not None:
                self._out.close()
                self._out = None
                got, want = self._digest.hexdigest(), files[self._index].sha256.lower()
                if got != want:
                    raise self._fail(f"{files[self._index].name} arrived with sha256 {got}, the server's is {want}")
            self._index += 1
            if self._index >= len(files):
                return
            self._out = open(self._parts[self._index], "wb")
            self._digest = hashlib.sha256()
            self._left = files[self._index].size_bytes
            if self._left > 0:
                return

    def _write(self, chunk: bytes) -> None:
        assert self._header is not None
        if self._out is None:
            raise self._fail("bytes after the last file")
        if len(chunk) > self._left:
            raise self._fail(f"a chunk runs past the end of {self._header.files[self._index].name}")
        self._out.write(chunk)
        self._digest.update(chunk)
        self._left -= len(chunk)
        if self._left == 0:
            self._next_file()

    def finish(self) -> DownloadedModel:
        """After the stream ended: puts the files in place and returns them."""
        header = self._header
        if header is None:
            raise self._fail("the stream ended without a header")
        if self._out is not None:
            raise self._fail(f"the stream ended {self._left} bytes before the end of "
                             f"{header.files[self._index].name}")
        manifest = json.loads(header.manifest_json)
        manifest_part = self.dir / f".{MANIFEST_FILE}.{os.getpid()}.part"
        self._parts.append(manifest_part)
        manifest_part.write_text(header.manifest_json.rstrip("\n") + "\n")
        targets = [self.dir / f.name for f in header.files]
        for part, target in zip(self._parts, [*targets, self.dir / MANIFEST_FILE]):
            os.replace(part, target)
        self._parts = []
        return DownloadedModel(targets[0], header.model, manifest, tuple(targets), self.dir / MANIFEST_FILE)

    def close(self) -> None:
        """Removes the part files of a download that did not finish (nothing after ``finish``)."""
        if self._out is not None:
            self._out.close()
            self._out = None
        for part in self._parts:
            part.unlink(missing_ok=True)
        self._parts = []
