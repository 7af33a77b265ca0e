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
last action) are converted by :func:`from_minari_episodes`; Minari's on-disk layout
(``main_data.hdf5`` with one ``episode_<id>`` group per episode, or the dataset directory
holding ``data/main_data.hdf5``) by :func:`from_minari_hdf5`, which :func:`source_of` picks
for such files.

The rules shared with the Rust toolkit (``relreward_toolkit::episodes``, docs/data-formats.md):

- ``episode_starts``: a bool array is per-row flags; an integer array of N values all 0 or 1
  is per-row flags; any other integer array is a list of start row indices (strictly
  increasing, in ``[0, N)``). Both readings can only fit ``[0]`` or ``[0, 1]``, where they give
  the same episodes. Float arrays are refused.
- ``episode_lengths``: positive integers summing to N. With ``episode_starts`` they must agree.
  Either is sent as per-row ``episode_starts`` flags; ``terminals`` / ``timeouts`` are sent
  too (the server cuts at any of them).
- Dict observations (Minari) are flattened like gymnasium's ``spaces.flatten`` for a Dict
  built from a plain dict: keys sorted, nested dicts recursively, each entry's trailing
  dimensions row-major.
- Maze walls: :func:`walls_of` takes the first of ``walls``, ``wall_map``, ``maze_map``
  (nonzero = wall); several present must agree.

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
_FLAGS = (("terminals", ("terminations",)), ("timeouts", ("truncations",)))
WALL_KEYS = ("walls", "wall_map", "maze_map")


def episode_starts_flags(rows: int, starts: Any = None, lengths: Any = None) -> np.ndarray | None:
    """Per-row start flags from ``episode_starts`` (flags or indices) and/or
    ``episode_lengths`` by the module's rules; None when neither is given. ValueError names
    the key."""
    flags = None
    if starts is not None:
        a = np.asarray(starts[()] if not isinstance(starts, np.ndarray) else starts)
        if a.ndim != 1:
            raise ValueError(f"'episode_starts' has shape {a.shape}; expected 1-D (flags [N] or start indices [K])")
        if a.dtype.kind == "b":
            if len(a) != rows:
                raise ValueError(f"'episode_starts' holds {len(a)} flags but 'observations' has {rows} rows")
            flags = a.astype(bool)
        elif a.dtype.kind in "iu":
            if len(a) == rows and np.isin(a, (0, 1)).all():
                flags = a.astype(bool)
            else:
                if ((a < 0) | (a >= rows)).any():
                    bad = int(np.flatnonzero((a < 0) | (a >= rows))[0])
                    raise ValueError(
                        f"'episode_starts' read as start indices: entry {bad} is {a[bad]}, outside [0, {rows})"
                    )
                if (np.diff(a) <= 0).any():
                    bad = int(np.flatnonzero(np.diff(a) <= 0)[0]) + 1
                    raise ValueError(f"'episode_starts' read as start indices: entry {bad} does not increase")
                flags = np.zeros(rows, bool)
                flags[a] = True
        else:
            raise ValueError("'episode_starts' is a float array; it must be bool flags [N] or integer start indices [K]")
    if lengths is not None:
        ln = np.asarray(lengths[()] if not isinstance(lengths, np.ndarray) else lengths)
        if ln.ndim != 1 or ln.dtype.kind not in "iu":
            raise ValueError(f"'episode_lengths' must be a 1-D integer array; it has shape {ln.shape}, dtype {ln.dtype}")
        if (ln < 1).any():
            raise ValueError("'episode_lengths': lengths must be positive integers")
        if int(ln.sum()) != rows:
            raise ValueError(f"'episode_lengths' sum to {int(ln.sum())} rows but 'observations' has {rows}")
        from_lengths = np.zeros(rows, bool)
        from_lengths[np.concatenate([[0], np.cumsum(ln)[:-1]]).astype(np.int64)] = True
        if flags is not None:
            f = flags.copy()
            if rows:
                f[0] = True
            if not np.array_equal(f, from_lengths):
                raise ValueError("'episode_starts' and 'episode_lengths' disagree; keep only one")
        flags = from_lengths
    return flags


def walls_of(data: Mapping[str, Any]) -> np.ndarray | None:
    """The maze walls (bool ``[rows, cols]``) from ``walls`` / ``wall_map`` / ``maze_map``, by
    the module's rule; None when there are none."""
    chosen: tuple[str, np.ndarray] | None = None
    for key in WALL_KEYS:
        if key not in data:
            continue
        w = np.asarray(data[key][()] if not isinstance(data[key], np.ndarray) else data[key])
        if w.ndim != 2:
            raise ValueError(f"'{key}' has shape {w.shape}; maze walls must be 2-D [rows, cols]")
        w = w != 0
        if chosen is None:
            chosen = (key, w)
        elif not np.array_equal(chosen[1], w):
            raise ValueError(f"'{chosen[0]}' and '{key}' both give maze walls and they differ; keep only one")
    return None if chosen is None else chosen[1]


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
    starts = episode_starts_flags(int(rows), data.get("episode_starts"), data.get("episode_lengths"))
    if starts is not None:
        arrays.append(("episode_starts", starts))
        used |= {k for k in ("episode_starts", "episode_lengths") if k in data}
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


def _flatten_dict(value: Any, where: str) -> np.ndarray:
    """A dataset, or a dict/group flattened by gymnasium's rule (sorted keys, recursively)."""
    if isinstance(value, Mapping) or (hasattr(value, "keys") and not hasattr(value, "shape")):
        keys = sorted(value.keys())
        if not keys:
            raise ValueError(f"{where} is an empty group")
        parts = [_flatten_dict(value[k], f"{where}/{k}") for k in keys]
        n = parts[0].shape[0]
        for k, p in zip(keys, parts):
            if p.shape[0] != n:
                raise ValueError(f"{where}/{k} has {p.shape[0]} rows but {where}/{keys[0]} has {n}")
        return np.concatenate(parts, axis=1)
    a = np.asarray(value[()] if not isinstance(value, np.ndarray) else value)
    return a.reshape(a.shape[0], -1)


def from_minari_hdf5(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A Minari dataset on disk (``main_data.hdf5``, or its dataset directory) as a D4RL-style
    dict for :func:`trajectories`: episodes in id order (``episode_2`` before ``episode_10``),
    dict observations flattened by the module's rule, then :func:`from_minari_episodes`."""
    import h5py

    p = pathlib.Path(path)
    if p.is_dir():
        for cand in (p / "data" / "main_data.hdf5", p / "main_data.hdf5"):
            if cand.is_file():
                p = cand
                break
        else:
            raise ValueError(f"{path}: a directory without data/main_data.hdf5 (not a Minari dataset)")
    with h5py.File(p, "r") as f:
        ids = sorted(int(k[len("episode_"):]) for k in f.keys() if k.startswith("episode_") and k[8:].isdigit())
        if not ids:
            raise ValueError(f"{p}: no 'episode_<id>' groups (not a Minari main_data.hdf5)")
        episodes = []
        for i in ids:
            g = f[f"episode_{i}"]
            if "actions" not in g or not hasattr(g["actions"], "shape"):
                raise ValueError(f"{p}: 'episode_{i}/actions' is missing or a group (dict actions are not supported)")
            for key in ("observations", "terminations", "truncations"):
                if key not in g:
                    raise ValueError(f"{p}: no 'episode_{i}/{key}'")
            episodes.append(
                {
                    "observations": _flatten_dict(g["observations"], f"episode_{i}/observations"),
                    "actions": np.asarray(g["actions"][()]),
                    "terminations": np.asarray(g["terminations"][()]),
                    "truncations": np.asarray(g["truncations"][()]),
                }
            )
    return from_minari_episodes(episodes)


def _is_minari(path: pathlib.Path) -> bool:
    if path.is_dir():
        return (path / "data" / "main_data.hdf5").is_file() or (path / "main_data.hdf5").is_file()
    import h5py

    with h5py.File(path, "r") as f:
        return "observations" not in f and any(k.startswith("episode_") for k in f.keys())


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
        if path.is_dir() or (suffix in (".h5", ".hdf5") and _is_minari(path)):
            if kind == "samples" or key is not None:
                raise ValueError("a Minari dataset uploads as trajectories")
            return trajectories(from_minari_hdf5(path)), None
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


__all__: Sequence[str] = (
    "UploadSource",
    "trajectories",
    "samples",
    "from_minari_episodes",
    "from_minari_hdf5",
    "episode_starts_flags",
    "walls_of",
    "source_of",
    "row_chunks",
)
