"""What a dataset upload sends: arrays from numpy, ``.npz``/``.npy``, D4RL/Minari dicts, HDF5.

A **trajectories** dataset holds ``observations`` ``[N, obs_dim]`` and ``actions``
``[N, act_dim]`` (float32 or float64) and optionally the episode flags ``terminals``,
``timeouts`` and ``episode_starts`` ``[N]`` (bool or uint8). D4RL's keys map directly; Minari's
flat names ``terminations`` / ``truncations`` are sent as ``terminals`` / ``timeouts``. Every
other key (``rewards``, ``infos/...``, ``next_observations``) is not part of a dataset and is
left out (listed in :attr:`UploadSource.ignored`), as the CLI does.

A **samples** dataset holds one array ``samples`` ``[N, ...]`` (float32 or float64, at least
2-D), e.g. diffusion latents ``[N, C, H, W]``.

Minari *episodes* (``observations`` with one more row than ``actions``: the state after the
last action) are converted by :func:`from_minari_episodes`.

Arrays are read lazily by row ranges, so an h5py dataset or a memory-mapped ``.npy`` is never
loaded whole.
"""

from __future__ import annotations

import os
import pathlib
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from relreward._proto import datasets_pb2
from relreward._tensor import wire_dtype

TRAJECTORIES = datasets_pb2.DATASET_KIND_TRAJECTORIES
SAMPLES = datasets_pb2.DATASET_KIND_SAMPLES

# (name sent, aliases accepted), in the order they are sent.
_FLAGS = (("terminals", ("terminations",)), ("timeouts", ("truncations",)), ("episode_starts", ()))


@dataclass
class UploadSource:
    """Arrays ready to upload: ``(name, array)`` in send order, the dataset kind, and the keys
    of the input that are not sent. Arrays may be numpy arrays or anything with ``shape``,
    ``dtype`` and row slicing (an ``h5py.Dataset``)."""

    kind: datasets_pb2.DatasetKind
    arrays: list[tuple[str, Any]]
    ignored: list[str] = field(default_factory=list)

    def specs(self) -> list[datasets_pb2.ArraySpec]:
        """The header's ArraySpec of every array (little-endian on the wire)."""
        return [
            datasets_pb2.ArraySpec(name=name, dtype=wire_dtype(a.dtype), shape=[int(d) for d in a.shape])
            for name, a in self.arrays
        ]

    def total_bytes(self) -> int:
        """Payload bytes of all arrays together."""
        return sum(int(np.prod(a.shape, dtype=np.int64)) * np.dtype(a.dtype).itemsize for _, a in self.arrays)


def _is_float(a: Any) -> bool:
    return np.dtype(a.dtype).kind == "f" and np.dtype(a.dtype).itemsize in (4, 8)


def _flag_ok(a: Any) -> bool:
    d = np.dtype(a.dtype)
    return d.kind == "b" or (d.kind == "u" and d.itemsize == 1)


def trajectories(data: Mapping[str, Any]) -> UploadSource:
    """A trajectories upload from a D4RL-style mapping (a dict, ``np.load(...)`` of an
    ``.npz``, an ``h5py.File``). Checks shapes and dtypes locally (ValueError) so a bad input
    fails before anything is sent."""
    keys = list(data.keys())
    for required in ("observations", "actions"):
        if required not in data:
            raise ValueError(f"no '{required}' array (the input holds {', '.join(map(repr, keys)) or 'none'})")
    chosen: list[tuple[str, str]] = [("observations", "observations"), ("actions", "actions")]
    for name, aliases in _FLAGS:
        present = [k for k in (name, *aliases) if k in data]
        if len(present) > 1:
            raise ValueError(f"holds both '{present[0]}' and its Minari alias '{present[1]}'; keep only one")
        if present:
            chosen.append((name, present[0]))
    arrays: list[tuple[str, Any]] = []
    for name, key in chosen:
        a = data[key]
        if not hasattr(a, "shape"):
            a = np.asarray(a)
        shown = f"'{key}'" if key == name else f"'{key}' (sent as '{name}')"
        if name in ("observations", "actions"):
            if not _is_float(a):
                raise ValueError(f"{shown} has dtype {a.dtype}; it must be float32 or float64")
            if len(a.shape) != 2:
                raise ValueError(f"{shown} has shape {tuple(a.shape)}; expected 2-D [N, dim]")
        else:
            if not _flag_ok(a):
                if np.dtype(a.dtype).kind in "iuf":
                    a = np.asarray(a[()] if not isinstance(a, np.ndarray) else a).astype(bool)
                else:
                    raise ValueError(f"{shown} has dtype {a.dtype}; episode flags must be bool or uint8")
            if len(a.shape) != 1:
                raise ValueError(f"{shown} has shape {tuple(a.shape)}; episode flags must be 1-D [N]")
        arrays.append((name, a))
    rows = arrays[0][1].shape[0]
    for name, a in arrays[1:]:
        if a.shape[0] != rows:
            raise ValueError(f"'{name}' has {a.shape[0]} rows but 'observations' has {rows}")
    used = {key for _, key in chosen}
    return UploadSource(TRAJECTORIES, arrays, [k for k in keys if k not in used])


def samples(array: Any) -> UploadSource:
    """A samples upload of one float array ``[N, ...]`` (at least 2-D)."""
    if not hasattr(array, "shape"):
        array = np.asarray(array)
    if not _is_float(array):
        raise ValueError(f"samples have dtype {array.dtype}; they must be float32 or float64")
    if len(array.shape) < 2:
        raise ValueError(f"samples have shape {tuple(array.shape)}; expected [N, ...] with at least 2 dimensions")
    return UploadSource(SAMPLES, [("samples", array)])


def from_minari_episodes(episodes: Iterable[Any]) -> dict[str, np.ndarray]:
    """Flattens Minari episodes into a D4RL-style dict for :func:`trajectories`.

    Each episode (a mapping or an object with attributes, like ``minari.EpisodeData``) has
    ``observations`` ``[T + 1, obs_dim]`` (the state after every action, plus the first),
    ``actions`` ``[T, act_dim]`` and ``terminations`` / ``truncations`` ``[T]``. The last
    observation of each episode (the state after its final action, with no action of its own)
    is dropped, so row k pairs the state an action was taken in with that action, as D4RL's
    rows do. ``terminals`` / ``timeouts`` are the episode's flags, and ``episode_starts`` marks
    each episode's first row so episodes stay apart even when one neither terminated nor was
    truncated. Dict observations (goal-conditioned envs) must be flattened by the caller.
    """

    def get(ep: Any, key: str) -> np.ndarray:
        v = ep[key] if isinstance(ep, Mapping) else getattr(ep, key)
        if isinstance(v, Mapping):
            raise ValueError(f"episode '{key}' is a dict; flatten it to an array first")
        return np.asarray(v)

    obs, act, term, trunc, starts = [], [], [], [], []
    for i, ep in enumerate(episodes):
        o, a = get(ep, "observations"), get(ep, "actions")
        t = len(a)
        if len(o) != t + 1:
            raise ValueError(f"episode {i}: {len(o)} observations for {t} actions; Minari has one more")
        obs.append(o[:-1].reshape(t, -1))
        act.append(a.reshape(t, -1))
        term.append(get(ep, "terminations").astype(bool).reshape(t))
        trunc.append(get(ep, "truncations").astype(bool).reshape(t))
        s = np.zeros(t, dtype=bool)
        s[:1] = True
        starts.append(s)
    if not obs:
        raise ValueError("no episodes")
    return {
        "observations": np.concatenate(obs),
        "actions": np.concatenate(act),
        "terminals": np.concatenate(term),
        "timeouts": np.concatenate(trunc),
        "episode_starts": np.concatenate(starts),
    }


def _hdf5_arrays(f: Any) -> dict[str, Any]:
    """The top-level datasets of an HDF5 file (groups such as ``infos/`` listed by path)."""
    out: dict[str, Any] = {}

    def visit(name: str, obj: Any) -> None:
        if hasattr(obj, "shape") and hasattr(obj, "dtype"):
            out[name] = obj

    f.visititems(visit)
    return out


def source_of(data: Any, kind: str | None = None, key: str | None = None) -> tuple[UploadSource, Any]:
    """An UploadSource for ``data``, and an object to close afterwards (an open file) or None.

    ``data``: a numpy array (samples), a mapping (D4RL/Minari keys: trajectories; ``samples``
    or ``key``: samples), or a path to ``.npz``, ``.npy`` or ``.h5``/``.hdf5`` (needs h5py,
    ``pip install relreward[hdf5]``). ``kind`` ("trajectories" or "samples") overrides the
    detection: a mapping holding ``observations`` is trajectories, anything else samples.
    """
    closer: Any = None
    if isinstance(data, (str, os.PathLike)):
        path = pathlib.Path(data)
        suffix = path.suffix.lower()
        if suffix in (".h5", ".hdf5"):
            try:
                import h5py
            except ImportError:
                raise ImportError("reading HDF5 needs h5py: pip install 'relreward[hdf5]'") from None
            closer = h5py.File(path, "r")
            data = _hdf5_arrays(closer)
        elif suffix == ".npy":
            data = np.load(path, mmap_mode="r")
        else:
            closer = np.load(path)
            data = closer
    if isinstance(data, Mapping) or hasattr(data, "files"):
        mapping: Mapping[str, Any] = data if isinstance(data, Mapping) else {k: data[k] for k in data.files}
        detected = "trajectories" if "observations" in mapping and key is None else "samples"
        kind = kind or detected
        if kind == "trajectories":
            if key is not None:
                raise ValueError("key selects the array of a samples upload; trajectories always use their keys")
            return trajectories(mapping), closer
        if kind != "samples":
            raise ValueError(f"kind {kind!r}: expected 'trajectories' or 'samples'")
        names = list(mapping.keys())
        pick = key or ("samples" if "samples" in mapping else (names[0] if len(names) == 1 else None))
        if pick is None or pick not in mapping:
            raise ValueError(f"which array? pass key= (the input holds {', '.join(map(repr, names))})")
        src = samples(mapping[pick])
        src.ignored = [k for k in names if k != pick]
        return src, closer
    if kind == "trajectories":
        raise ValueError("a trajectories upload needs a mapping with 'observations' and 'actions'")
    return samples(data), closer


def row_chunks(array: Any, chunk_bytes: int) -> Iterable[np.ndarray]:
    """C-contiguous little-endian slices of ``array`` of about ``chunk_bytes`` each (at least
    one row)."""
    n = int(array.shape[0])
    row = int(np.prod(array.shape[1:], dtype=np.int64)) * np.dtype(array.dtype).itemsize
    step = max(1, chunk_bytes // max(row, 1))
    d = np.dtype(array.dtype)
    target = d.newbyteorder("<") if d.byteorder == ">" else d
    for start in range(0, n, step):
        yield np.ascontiguousarray(array[start:min(n, start + step)], dtype=target)


__all__: Sequence[str] = ("UploadSource", "trajectories", "samples", "from_minari_episodes", "source_of", "row_chunks")
