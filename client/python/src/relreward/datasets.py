"""What a dataset upload sends: arrays from numpy, ``.npz``/``.npy``, D4RL/Minari dicts, HDF5.

A **trajectories** dataset holds ``observations`` ``[N, obs_dim]`` and ``actions``
``[N, act_dim]`` and optionally the episode flags ``terminals``, ``timeouts`` and
``episode_starts`` ``[N]``. Observations and actions of any integer or float dtype (float16
included, either byte order) are read as float32 and sent as float32, as the Rust readers do;
``[N]`` is read as ``[N, 1]`` and ``[N, a, b, ...]`` flattened row-major to ``[N, a*b*...]``;
a value that is not finite as float32 (NaN, an infinity, or beyond float32's range) is refused
naming the key, its value, row and coordinate in the Rust reader's words (``'observations':
value NaN at row 13, coordinate 1 is not finite``). A float of another size than 2, 4 or 8
bytes (``np.longdouble``) is refused as the Rust readers refuse it, and so is a dataset of no
rows (N = 0). Flags are sent as bool: a bool array, or integers/floats that are all 0 or 1 (any
other value is refused naming the key and its row). D4RL's keys map directly; Minari's flat
names ``terminations`` / ``truncations`` are sent as ``terminals`` / ``timeouts``. Every other
key (``rewards``, ``infos/...``, ``next_observations``) is not part of a dataset and is left out
(listed in :attr:`UploadSource.ignored`), as the CLI does.

A **samples** dataset holds one array ``samples`` ``[N, ...]`` (float32 or float64, at least
2-D, sent in its own dtype), e.g. diffusion latents ``[N, C, H, W]``.

A path is read by its signature (first bytes), not its suffix: HDF5 (``\\x89HDF``), a zip
archive (``.npz``), an ``.npy`` array (``\\x93NUMPY``), or a Minari dataset directory. An
``.npz`` archive's arrays are loaded only when taken (an array left out is never read); one
that cannot be read (a truncated or corrupt archive) or holds pickled Python objects (an
object array) under a key that is taken is refused naming the file and the key, with the
Rust reader's words. An HDF5 file is always trajectories (D4RL keys or Minari), as for the CLI:
one without a top-level ``observations`` is refused, never uploaded as samples; soft links are
followed (a link named ``observations`` is the dataset it points to).

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
  dimensions row-major. A Tuple space's parts, which Minari stores as ``_index_0``,
  ``_index_1``, ..., go by their number (``_index_10`` after ``_index_9``) before any other
  key (:func:`_space_order`). Values that are not finite are named in the part they are in
  (``'episode_0/observations/achieved_goal'``).
- Minari JPEG frames: when ``metadata.json`` beside ``main_data.hdf5`` says
  ``"jpeg_encoding": true`` (minari 0.5's DataCollector default for uint8 images), an
  observations dataset (or part of an observations group) of uint8 that is variable-length or
  whose data begins with JPEG's signature ``FF D8 FF`` is refused naming the place and the
  setting; other observations under that metadata are read as usual.
- Minari episodes without actions are skipped (in a file, without reading their
  observations, as the Rust reader skips them); the last observation of each episode is
  dropped before anything is checked, so a non-finite value there does not matter.
- A D4RL-layout HDF5 file needs ``observations`` and ``actions`` as top-level datasets: a group
  there (dict observations) is refused as the Rust reader refuses it.
- Maze walls: :func:`walls_of` takes the first of ``walls``, ``wall_map``, ``maze_map``
  (nonzero = wall); several present must agree.

Arrays are read lazily by row ranges, so an h5py dataset or a memory-mapped ``.npy`` is never
loaded whole.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import stat
import zipfile
import zlib
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from relreward.v1 import datasets_pb2
from relreward import _tensor
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


_F32 = np.dtype("<f4")
# Rows per block when checking values, so a check never allocates more than about 1M flags.
_CHECK_ELEMENTS = 1 << 20


def _is_group(value: Any) -> bool:
    return isinstance(value, Mapping) or (hasattr(value, "keys") and not hasattr(value, "shape"))


def _array_like(a: Any) -> Any:
    """``a`` itself when it has a numpy ``shape`` and ``dtype`` (an ndarray, an h5py dataset),
    else ``np.asarray(a)`` (a list; a torch tensor detached and on the CPU, ``_tensor.host``)."""
    if hasattr(a, "shape") and hasattr(a, "dtype"):
        try:
            np.dtype(a.dtype)
            return a
        except TypeError:
            pass
    return np.asarray(_tensor.host(a))


def _is_h5py(a: Any) -> bool:
    return type(a).__module__.startswith("h5py")


def _check_float_size(a: Any, shown: str) -> None:
    """Refuses a float of another size than 2, 4 or 8 bytes (``np.longdouble``, ``'<f16'``) as the
    Rust reader of its form does: an HDF5 dataset in the HDF5 reader's words, anything else (an
    ``.npz`` member, an array) in the ``.npy`` reader's, naming the file's key."""
    d = np.dtype(a.dtype)
    if d.kind != "f" or d.itemsize in (2, 4, 8):
        return
    if _is_h5py(a):
        raise ValueError(f"{shown} holds a {d.itemsize}-byte float; expected integers, floats or bool")
    key = shown.partition(" (sent as ")[0]
    raise ValueError(f"array {key}: dtype '{d.str}' is a {d.itemsize}-byte float, which is not supported; "
                     "expected integers or floats of 1, 2, 4 or 8 bytes")


def _value_dims(a: Any, shown: str) -> tuple[int, int]:
    """``(N, dim)`` of a values array (observations/actions) by the module's rule: any integer
    or float dtype; ``[N]`` is ``[N, 1]``, ``[N, a, b, ...]`` is ``[N, a*b*...]``."""
    d = np.dtype(a.dtype)
    if d.kind == "b":
        raise ValueError(f"{shown} is bool; expected numbers (any integer or float type, read as float32)")
    if d.kind not in "iuf":
        raise ValueError(f"{shown} has dtype {d}; expected numbers (any integer or float type, read as float32)")
    _check_float_size(a, shown)
    shape = tuple(int(s) for s in a.shape)
    if not shape:
        raise ValueError(f"{shown} is a scalar; expected [N, dim]")
    return shape[0], int(np.prod(shape[1:], dtype=np.int64))


# The Rust readers' words for a finite value that float32 cannot hold (relreward_proto::tensor).
_OUTSIDE_F32 = "outside float32's range (about 3.4e38), the precision models compute in"


def _place(row: int, col: int, trailing: tuple[int, ...]) -> str:
    """Where a value is, as the Rust readers say it (``values::position``): ``row R, coordinate
    C`` for ``[N]`` and ``[N, d]``; beyond 2-D the flattened (row-major) coordinate within the
    row: ``row R, flattened coordinate C of [a, b]``."""
    if len(trailing) <= 1:
        return f"row {row}, coordinate {col}"
    return f"row {row}, flattened coordinate {col} of [{', '.join(str(int(t)) for t in trailing)}]"


def _not_f32(shown: str, value: float, place: str) -> ValueError:
    """The refusal of a value that is not finite as float32, in the Rust readers' words
    (``values::to_f32``): the value as Rust prints an f64 (``NaN``, ``inf``, ``-inf``; one beyond
    float32's range in shortest exponent form, ``1e300``)."""
    if math.isfinite(value):
        mantissa, _, exponent = np.format_float_scientific(value, unique=True, trim="-").partition("e")
        return ValueError(f"{shown}: value {mantissa}e{int(exponent)} at {place} is {_OUTSIDE_F32}")
    text = "NaN" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return ValueError(f"{shown}: value {text} at {place} is not finite")


def _check_finite(out: np.ndarray, raw: np.ndarray, shown: str, first_row: int, trailing: tuple[int, ...]) -> None:
    """ValueError naming ``shown``, the value, its row (``first_row`` + its row in ``out``) and
    coordinate (within a row of ``trailing`` dimensions), for the first value of ``out`` (float32
    ``[n, d]``) that is not finite; ``raw`` is what it was converted from (``[n, d]``, its dtype)."""
    step = max(1, _CHECK_ELEMENTS // max(1, out.shape[1] if out.ndim == 2 else 1))
    for start in range(0, out.shape[0], step):
        bad = ~np.isfinite(out[start:start + step])
        if bad.any():
            r, c = divmod(int(np.flatnonzero(bad.reshape(-1))[0]), bad.shape[1])
            raise _not_f32(shown, float(raw[start + r, c]), _place(first_row + start + r, c, trailing))


def _to_f32(part: Any, rows: int, dim: int, shown: str, first_row: int = 0) -> np.ndarray:
    """``part`` (rows as stored, ``[rows, ...]``) as C-contiguous little-endian float32 ``[rows,
    dim]``, checked finite (no copy when it already is one)."""
    stored = np.asarray(part)
    raw = stored.reshape(rows, dim)
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below, naming the row
        out = np.ascontiguousarray(raw, dtype=_F32)
    if np.dtype(raw.dtype).kind == "f":
        _check_finite(out, raw, shown, first_row, tuple(stored.shape[1:]))
    return out


class _Float32Rows:
    """A lazy float32 ``[N, dim]`` view of an array-like read by row ranges (an h5py dataset,
    a memory-mapped ``.npy``): each read is converted and checked finite, so nothing is loaded
    whole."""

    dtype = _F32

    def __init__(self, source: Any, rows: int, dim: int, shown: str) -> None:
        self.source, self.shape, self.shown = source, (rows, dim), shown

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index: Any) -> np.ndarray:
        n = self.shape[0]
        if isinstance(index, (int, np.integer)):
            i = int(index) + (n if index < 0 else 0)
            if not 0 <= i < n:
                raise IndexError(f"row {index} of {n}")
            return self[i:i + 1][0]
        if not isinstance(index, slice):
            raise TypeError("rows are read by an integer or a slice")
        start, stop, step = index.indices(n)
        part = np.asarray(self.source[start:stop:step] if step != 1 else self.source[start:stop])
        rows = part.shape[0] if part.ndim else 0
        return _to_f32(part, rows, self.shape[1], self.shown, start)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        a = self[:]
        return a if dtype is None else a.astype(dtype)


def _values(a: Any, shown: str) -> Any:
    """Observations/actions read by the module's rule: float32 ``[N, dim]``. An in-memory array
    is converted (and checked finite) now; an h5py dataset or memory-mapped array lazily, by
    row ranges."""
    a = _array_like(a)
    rows, dim = _value_dims(a, shown)
    if isinstance(a, np.ndarray) and not isinstance(a, np.memmap):
        return _to_f32(a, rows, dim, shown)
    return _Float32Rows(a, rows, dim, shown)


def _flags(a: Any, shown: str) -> np.ndarray:
    """Episode flags ``[N]`` as bool: a bool array, or integers/floats that are all 0 or 1
    (ValueError naming ``shown`` and the first other value's row)."""
    a = _array_like(a)
    d = np.dtype(a.dtype)
    if d.kind not in "biuf":
        raise ValueError(f"{shown} has dtype {d}; episode flags must be bool, or integers or floats that are 0 or 1")
    _check_float_size(a, shown)
    if len(a.shape) != 1:
        raise ValueError(f"{shown} has shape {tuple(a.shape)}; episode flags must be 1-D [N]")
    v = np.asarray(a if isinstance(a, np.ndarray) else a[()])
    if d.kind == "b":
        return v.astype(bool, copy=False)
    bad = (v != 0) & (v != 1)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{shown} holds {v[r].item()!r} at row {r}; episode flags must be bool, or 0 or 1")
    return v != 0


def trajectories(data: Mapping[str, Any]) -> UploadSource:
    """A trajectories upload from a D4RL-style mapping (a dict, ``np.load(...)`` of an
    ``.npz``, an ``h5py.File``). Checks shapes, dtypes, flags, N > 0 and (for in-memory arrays)
    finiteness locally (ValueError naming the key) so a bad input fails before anything is
    sent; ``observations`` / ``actions`` are sent as float32 ``[N, dim]``, flags as bool."""
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
        shown = f"'{key}'" if key == name else f"'{key}' (sent as '{name}')"
        if _is_group(a):
            raise ValueError(f"{shown} is a dict (a group of arrays); expected one array (dict observations are "
                             "flattened for Minari datasets: from_minari_hdf5 / from_minari_episodes)")
        arrays.append((name, _values(a, shown) if name in ("observations", "actions") else _flags(a, shown)))
    rows = arrays[0][1].shape[0]
    for name, a in arrays[1:]:
        if a.shape[0] != rows:
            raise ValueError(f"'{name}' has {a.shape[0]} rows but 'observations' has {rows}")
    if rows == 0:  # the Rust readers' words; the server would refuse it only after the upload
        raise ValueError("'observations' has no rows (N = 0); a dataset needs at least one")
    used = {key for _, key in chosen}
    starts = episode_starts_flags(int(rows), data.get("episode_starts"), data.get("episode_lengths"))
    if starts is not None:
        arrays.append(("episode_starts", starts))
        used |= {k for k in ("episode_starts", "episode_lengths") if k in data}
    return UploadSource(TRAJECTORIES, arrays, [k for k in keys if k not in used])


def samples(array: Any, labels: Any = None) -> UploadSource:
    """A samples upload of one float array ``[N, ...]`` (at least 2-D), sent in its own dtype
    (float32 or float64: a samples dataset keeps its precision), and optionally each sample's
    class label ``labels`` ``[N]`` (integers >= 0, sent as int64 unless int32 or uint8), what
    class-conditional training (``DiffusionJob(conditional=True)``) conditions on."""
    if not hasattr(array, "shape"):
        array = np.asarray(array)
    if not _is_float(array):
        raise ValueError(f"samples have dtype {array.dtype}; they must be float32 or float64")
    if len(array.shape) < 2:
        raise ValueError(f"samples have shape {tuple(array.shape)}; expected [N, ...] with at least 2 dimensions")
    arrays = [("samples", array)]
    if labels is not None:
        labels = np.asarray(labels)
        if labels.dtype.kind not in "iu" and labels.dtype != np.bool_:
            raise ValueError(f"labels have dtype {labels.dtype}; class labels must be integers")
        if labels.shape != (array.shape[0],):
            raise ValueError(f"labels have shape {labels.shape}; expected [{array.shape[0]}] (one per sample)")
        if labels.size and int(labels.min()) < 0:
            raise ValueError(f"labels hold {int(labels.min())}; class labels must be >= 0")
        if labels.dtype not in (np.dtype(np.int32), np.dtype(np.int64), np.dtype(np.uint8)):
            labels = labels.astype(np.int64)
        arrays.append(("labels", labels))
    return UploadSource(SAMPLES, arrays)


def _minari_flat(episodes: Iterable[tuple[str, Any]]) -> dict[str, np.ndarray]:
    """:func:`from_minari_episodes` on ``(label, episode)`` pairs; errors name
    ``'<label>/<key>'``."""

    def get(ep: Any, label: str, key: str) -> Any:
        try:
            v = ep[key] if isinstance(ep, Mapping) else getattr(ep, key)
        except (KeyError, AttributeError):
            raise ValueError(f"no '{label}/{key}'") from None
        if _is_group(v):
            if key == "actions":
                raise ValueError(f"'{label}/actions' is a dict (dict actions are not supported)")
            raise ValueError(f"'{label}/{key}' is a dict; flatten it to an array first")
        return _array_like(v)  # an h5py dataset stays one: a refusal then speaks as the HDF5 reader

    obs, act, term, trunc, starts = [], [], [], [], []
    dims: tuple[int, int, str] | None = None
    seen = 0
    for label, ep in episodes:
        seen += 1
        o, a = get(ep, label, "observations"), get(ep, label, "actions")
        t, act_dim = _value_dims(a, f"'{label}/actions'")
        n_obs, obs_dim = _value_dims(o, f"'{label}/observations'")
        if n_obs != t + 1:
            raise ValueError(f"'{label}/observations' has {n_obs} rows for {t} actions; Minari stores one more")
        if t == 0:
            continue  # an empty episode (no actions) has no rows
        if dims is None:
            dims = (obs_dim, act_dim, label)
        elif dims[:2] != (obs_dim, act_dim):
            raise ValueError(f"'{label}' has observations of {obs_dim} and actions of {act_dim} values per row; "
                             f"'{dims[2]}' has {dims[0]} and {dims[1]}")
        # The last observation (after the last action) is dropped: only the kept rows are read and checked.
        obs.append(_to_f32(np.asarray(o[:t]), t, obs_dim, f"'{label}/observations'"))
        act.append(_to_f32(np.asarray(a[:t]), t, act_dim, f"'{label}/actions'"))
        for key, out in (("terminations", term), ("truncations", trunc)):
            f = _flags(get(ep, label, key), f"'{label}/{key}'")
            if len(f) != t:
                raise ValueError(f"'{label}/{key}' has {len(f)} rows; expected {t} (one per action)")
            out.append(f)
        s = np.zeros(t, dtype=bool)
        s[0] = True
        starts.append(s)
    if not seen:
        raise ValueError("no episodes")
    if not obs:
        raise ValueError("every episode is empty (no actions)")
    return {
        "observations": np.concatenate(obs),
        "actions": np.concatenate(act),
        "terminals": np.concatenate(term),
        "timeouts": np.concatenate(trunc),
        "episode_starts": np.concatenate(starts),
    }


def from_minari_episodes(episodes: Iterable[Any]) -> dict[str, np.ndarray]:
    """Flattens Minari episodes into a D4RL-style dict for :func:`trajectories`.

    Each episode (a mapping or an object with attributes, like ``minari.EpisodeData``) has
    ``observations`` ``[T + 1, ...]`` (the state after every action, plus the first),
    ``actions`` ``[T, ...]`` and ``terminations`` / ``truncations`` ``[T]``. The last
    observation of each episode (the state after its final action, with no action of its own)
    is dropped (and never checked), so row k pairs the state an action was taken in with that
    action, as D4RL's rows do. Values of any integer or float dtype are read as float32
    (``[T]`` as ``[T, 1]``, more dimensions flattened per row); flags may be bool or 0/1
    numbers. Episodes without actions are skipped. ``terminals`` / ``timeouts`` are the
    episode's flags, and ``episode_starts`` marks each episode's first row so episodes stay
    apart even when one neither terminated nor was truncated. Dict observations
    (goal-conditioned envs) must be flattened by the caller. Errors name
    ``'episode[i]/key'``.
    """
    return _minari_flat((f"episode[{i}]", ep) for i, ep in enumerate(episodes))


def _space_order(keys: Iterable[str]) -> list[str]:
    """The members of an observations group in gymnasium's ``spaces.flatten`` order (the Rust
    reader's ``flatten_order``): a Tuple's parts, which Minari stores as ``_index_<n>`` (n in
    decimal digits), by their number (``_index_10`` after ``_index_9``) and before any other
    key; a Dict's keys as strings."""

    def rank(key: str) -> tuple[int, int, str]:
        n = key[len("_index_"):] if key.startswith("_index_") else ""
        if n and n.isascii() and n.isdigit() and int(n) < 1 << 64:
            return (0, int(n), key)
        return (1, 0, key)

    return sorted(keys, key=rank)


def _flatten_dict(value: Any, where: str, keep: int | None = None) -> np.ndarray:
    """A dataset as float32 ``[N, d]``, or a dict/group flattened by gymnasium's rule (keys in
    :func:`_space_order`, recursively). Values must be finite as float32 in the first ``keep``
    rows (all when None), each refusal naming the dataset it is in, as the Rust reader's."""
    if _is_group(value):
        keys = _space_order(value.keys())
        if not keys:
            raise ValueError(f"'{where}' is an empty group")
        parts = [_flatten_dict(value[k], f"{where}/{k}", keep) for k in keys]
        n = parts[0].shape[0]
        for k, p in zip(keys, parts):
            if p.shape[0] != n:
                raise ValueError(f"'{where}/{k}' has {p.shape[0]} rows but '{where}/{keys[0]}' has {n}")
        return np.concatenate(parts, axis=1)
    rows, dim = _value_dims(value, f"'{where}'")
    a = np.asarray(value[()] if not isinstance(value, np.ndarray) else value)
    kept = rows if keep is None else min(keep, rows)
    with np.errstate(over="ignore", invalid="ignore"):  # the rows after ``keep`` are dropped unchecked
        rest = np.asarray(a[kept:], dtype=_F32).reshape(rows - kept, dim)
    return np.concatenate([_to_f32(a[:kept], kept, dim, f"'{where}'"), rest])


_JPEG_SIGNATURE = b"\xff\xd8\xff"
# What the refusal of JPEG frames says after its place (the Rust reader's JPEG_ENCODED).
_JPEG_ENCODED = ("JPEG-encoded by Minari's DataCollector (data/metadata.json: jpeg_encoding = true); relreward "
                 "reads raw arrays: record with DataCollector(..., jpeg_encoding=False), or decode the frames "
                 "into an .npz")


def _jpeg_encoding(main_data: pathlib.Path) -> bool:
    """Whether ``metadata.json`` beside ``main_data.hdf5`` says ``"jpeg_encoding": true`` (minari
    0.5's DataCollector JPEG-encodes uint8 image observations of at least 32 x 32 by default).
    Absent, unreadable or other metadata says no: the data is read as it is."""
    try:
        meta = json.loads((main_data.parent / "metadata.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("jpeg_encoding") is True


def _refuse_jpeg(value: Any, where: str) -> None:
    """Refuses JPEG frames in an observations dataset or group (every part, in
    :func:`_space_order`): uint8 of variable length, or uint8 whose data begins with JPEG's
    signature ``FF D8 FF``. Only asked when the metadata says ``jpeg_encoding`` (module docs)."""
    if _is_group(value):
        for k in _space_order(value.keys()):
            _refuse_jpeg(value[k], f"{where}/{k}")
        return
    import h5py

    d = np.dtype(value.dtype)
    base = h5py.check_vlen_dtype(d)
    if base is not None:
        frames = np.dtype(base) == np.uint8
    else:
        first = np.asarray(value[:3]) if len(value.shape) else np.zeros(0, np.uint8)  # 3 rows hold 3 bytes
        frames = d == np.uint8 and first.reshape(-1)[:3].tobytes() == _JPEG_SIGNATURE
    if frames:
        raise ValueError(f"'{where}' is {_JPEG_ENCODED}")


def _minari_file(path: pathlib.Path) -> pathlib.Path | None:
    """``dir/data/main_data.hdf5`` or ``dir/main_data.hdf5``, the first that exists; None when
    neither does. One that exists but is no readable file (a directory, a dangling link, a
    symlink loop) raises ValueError naming it."""
    for cand in (path / "data" / "main_data.hdf5", path / "main_data.hdf5"):
        try:
            st = cand.stat()
        except FileNotFoundError:
            if cand.is_symlink():
                raise ValueError(f"{cand}: cannot be opened (a dangling link)") from None
            continue
        except OSError as e:
            raise ValueError(f"{cand}: cannot be opened: {e.strerror} (a dangling link or a symlink loop)") from None
        if stat.S_ISDIR(st.st_mode):
            raise ValueError(f"{cand}: is a directory, not Minari's main_data.hdf5 file")
        return cand
    return None


def _episode_groups(root: Any) -> list[tuple[int, str]]:
    """The root's episode groups ``episode_<id>`` as ``(id, name)`` in id order. Minari's root
    holds nothing else, so any other member (``episode_abc``, a second spelling of an id such
    as ``episode_01`` beside ``episode_1``, a dataset) is refused, naming it, rather than left
    out of the upload without a word (the Rust reader's rule; docs/data-formats.md)."""
    episodes, others = [], []
    for name in root.keys():
        digits = name[len("episode_"):] if name.startswith("episode_") else ""
        if digits and digits.isascii() and digits.isdigit() and _is_group(root[name]):
            episodes.append((int(digits), name))
        else:
            others.append(f"{'group' if _is_group(root[name]) else 'dataset'} '{name}'")
    if not episodes:
        raise ValueError("no 'episode_<id>' groups (not a Minari main_data.hdf5)")
    if others:
        one = len(others) == 1
        raise ValueError(f"the root holds {', '.join(others)} that {'is' if one else 'are'} not an episode group "
                         f"'episode_<id>' (id in decimal digits); a Minari main_data.hdf5 holds only episode groups, "
                         f"so the file is refused rather than uploaded without {'it' if one else 'them'}")
    episodes.sort()
    for (a, na), (b, nb) in zip(episodes, episodes[1:]):
        if a == b:
            raise ValueError(f"groups '{na}' and '{nb}' are both episode {a}")
    return episodes


def from_minari_hdf5(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A Minari dataset on disk (``main_data.hdf5``, or its dataset directory) as a D4RL-style
    dict for :func:`trajectories`: episodes in id order (``episode_2`` before ``episode_10``),
    dict and tuple observations flattened by the module's rule, then :func:`from_minari_episodes`'s
    rule (empty episodes skipped, the last observation of each dropped). Each episode is read
    in the Rust reader's order: its actions (every row checked), then, unless it has none, its
    observations (JPEG frames refused when ``metadata.json`` says ``jpeg_encoding``; the rows
    kept checked), so both readers refuse a file for the same first fault."""
    import h5py

    p = pathlib.Path(path)
    if p.is_dir():
        found = _minari_file(p)
        if found is None:
            raise ValueError(f"{path}: a directory without data/main_data.hdf5 (not a Minari dataset)")
        p = found
    jpeg = _jpeg_encoding(p)
    with h5py.File(p, "r") as f:
        try:
            names = _episode_groups(f)
        except ValueError as e:
            raise ValueError(f"{p}: {e}") from None
        episodes = []
        try:
            for i, name in names:
                g = f[name]
                if "actions" not in g or not hasattr(g["actions"], "shape"):
                    raise ValueError(f"'{name}/actions' is missing or a group (dict actions are not supported)")
                for key in ("observations", "terminations", "truncations"):
                    if key not in g:
                        raise ValueError(f"no '{name}/{key}'")
                steps, act_dim = _value_dims(g["actions"], f"'{name}/actions'")
                actions = _to_f32(g["actions"][()], steps, act_dim, f"'{name}/actions'")
                if steps == 0:
                    continue  # no action, so no row: its observations (the first state only) are not read
                if jpeg:
                    _refuse_jpeg(g["observations"], f"{name}/observations")
                episodes.append((name, {
                    "observations": _flatten_dict(g["observations"], f"{name}/observations", steps),
                    "actions": actions,
                    "terminations": g["terminations"],
                    "truncations": g["truncations"],
                }))
            if not episodes:
                raise ValueError("every episode is empty (no actions)")
            return _minari_flat(episodes)
        except ValueError as e:
            raise ValueError(f"{p}: {e}") from None


_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # an archive with entries; an empty one
FORMS = ("an HDF5 file (D4RL keys, or Minari's main_data.hdf5), an .npz archive, an .npy array, or a Minari "
         "dataset directory")


def _form_of(path: pathlib.Path) -> str:
    """``"minari-dir"``, ``"hdf5"``, ``"npz"`` or ``"npy"``, by the file's signature (its first
    bytes), never its suffix; ValueError naming the path and the forms accepted otherwise."""
    if path.is_dir():
        if _minari_file(path) is None:
            raise ValueError(f"{path}: a directory without data/main_data.hdf5 (not a Minari dataset); "
                             f"expected {FORMS}")
        return "minari-dir"
    with open(path, "rb") as f:
        head = f.read(8)
    if head == _HDF5_MAGIC:
        return "hdf5"
    if head[:4] in _ZIP_MAGICS:
        return "npz"
    if head[:6] == _NPY_MAGIC:
        return "npy"
    raise ValueError(f"{path}: not a form relreward reads (by its first bytes it is not HDF5, .npz or .npy); "
                     f"expected {FORMS}")


def _hdf5_arrays(f: Any) -> dict[str, Any]:
    """The datasets of an HDF5 file by path (top-level ones by name, those of groups such as
    ``infos/`` by their path). Soft links are followed, as the Rust reader follows them: a link
    is the dataset (or group) it points to, under the link's name; a dangling one is no member.
    External links are not followed, and each group is visited once (links may form cycles)."""
    import h5py

    out: dict[str, Any] = {}
    seen: set[Any] = set()

    def walk(group: Any, prefix: str) -> None:
        for name in group.keys():
            if isinstance(group.get(name, getlink=True), h5py.ExternalLink):
                continue
            obj = group.get(name)  # follows a soft link; None when it dangles
            if isinstance(obj, h5py.Dataset):
                out[prefix + name] = obj
            elif isinstance(obj, h5py.Group) and obj.id not in seen:
                seen.add(obj.id)
                walk(obj, f"{prefix}{name}/")

    seen.add(f.id)
    walk(f, "")
    return out


# The CLI's refusal of ``--kind samples`` / ``--key`` for these forms, in this package's words.
_TRAJECTORIES_ONLY = "kind 'samples' / key: an HDF5 file or Minari dataset uploads as trajectories"


def _open_hdf5(path: pathlib.Path, kind: str | None, key: str | None) -> tuple[str, Any]:
    """``("minari", None)`` for a Minari ``main_data.hdf5`` (by the rule of the Rust reader: no
    top-level ``observations`` dataset and some ``episode_*`` group), else ``("arrays", file)``
    with the file open. An HDF5 file is trajectories, whatever it holds (the CLI's rule): ``kind``
    ``"samples"`` or a ``key`` is refused, and a D4RL-layout file needs ``observations`` and
    ``actions`` as top-level datasets, as D4RL stores them: a file without them (one holding only
    ``obs``, or ``samples``) is refused naming what it holds, never uploaded as samples, and a
    group there (dict observations) is refused as the Rust reader refuses it."""
    try:
        import h5py
    except ImportError:
        raise ImportError("reading HDF5 needs h5py: pip install 'relreward[hdf5]'") from None
    if kind == "samples" or key is not None:
        raise ValueError(_TRAJECTORIES_ONLY)
    f = h5py.File(path, "r")
    try:
        members = {k: f.get(k) for k in f.keys()}
        datasets = sorted(k for k, v in members.items() if isinstance(v, h5py.Dataset))
        groups = sorted(k for k, v in members.items() if isinstance(v, h5py.Group))
        if "observations" not in datasets and any(g.startswith("episode_") for g in groups):
            f.close()
            return "minari", None
        for required in ("observations", "actions"):
            if required not in datasets:
                held = [f"'{d}'" for d in datasets] + [f"group '{g}'" for g in groups]
                raise ValueError(f"{path}: no '{required}' dataset at the top level (it holds "
                                 f"{', '.join(held) or 'nothing'})")
        return "arrays", f
    except BaseException:
        f.close()
        raise


def _npy_dtype(fp: Any) -> np.dtype | None:
    """The dtype an ``.npy`` header declares (``fp`` at its first byte), or None when it is no
    header numpy reads (numpy's own load then says what is wrong)."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        return np.dtype(read(fp)[2])
    except (ValueError, OSError, EOFError, SyntaxError, TypeError):
        return None


def _refuse_object_array(dtype: np.dtype | None, key: str) -> None:
    """An object array (pickled Python objects) refused naming its key in the Rust reader's
    words, where numpy would say only that ``allow_pickle`` is off."""
    if dtype is not None and dtype.hasobject and dtype.names is None:
        raise ValueError(f"array '{key}': dtype '{dtype.str}' is an object array (pickled Python objects), which is "
                         "not supported; expected integers, floats or bool")


class _NpzArrays(Mapping):
    """The arrays of an open ``np.load`` archive by key, each loaded when it is asked for, so an
    array the upload does not take (``rewards``, ``infos``) is never read, as the Rust reader
    reads only the arrays it takes. An object array, and a member that cannot be read (a corrupt
    archive: bad CRC, a truncated member), are refused naming the key (ValueError, numpy's or
    zipfile's error kept as its cause)."""

    def __init__(self, npz: Any) -> None:
        self.npz = npz

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self.npz.files:
            raise KeyError(key)
        member = f"{key}.npy" if f"{key}.npy" in self.npz.zip.namelist() else key
        try:
            with self.npz.zip.open(member) as fp:
                _refuse_object_array(_npy_dtype(fp), key)
            return self.npz[key]
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise ValueError(f"array '{key}': cannot be read: {e}") from e

    def __contains__(self, key: object) -> bool:
        return key in self.npz.files

    def __iter__(self) -> Any:
        return iter(self.npz.files)

    def __len__(self) -> int:
        return len(self.npz.files)


def source_of(data: Any, kind: str | None = None, key: str | None = None) -> tuple[UploadSource, Any]:
    """An UploadSource for ``data``, and an object to close afterwards (an open file) or None.

    ``data``: a numpy array (samples), a mapping (D4RL/Minari keys: trajectories; ``samples``
    or ``key``: samples), or a path: an ``.npz`` archive, an ``.npy`` array, an HDF5 file
    (D4RL keys or a Minari ``main_data.hdf5``; needs h5py, ``pip install relreward[hdf5]``) or
    a Minari dataset directory. A file's form is told by its signature (first bytes), not its
    suffix. ``kind`` ("trajectories" or "samples") overrides the detection: a mapping holding
    ``observations`` is trajectories, anything else samples; an HDF5 file or a Minari dataset
    is always trajectories (``kind="samples"`` or ``key`` is refused, as by the CLI).
    A refusal reading a file is a ValueError naming the file (any error it came from kept as
    its ``__cause__``).
    """
    closer: Any = None
    path: pathlib.Path | None = None
    if isinstance(data, (str, os.PathLike)):
        path = pathlib.Path(data)
        form = _form_of(path)
        if form == "hdf5":
            form, closer = _open_hdf5(path, kind, key)
        if form in ("minari", "minari-dir"):
            if kind == "samples" or key is not None:
                raise ValueError(_TRAJECTORIES_ONLY)
            return trajectories(from_minari_hdf5(path)), None
        if form == "arrays":
            data = _hdf5_arrays(closer)
        elif form == "npy":
            with open(path, "rb") as fp:
                try:
                    _refuse_object_array(_npy_dtype(fp), path.stem)
                except ValueError as e:
                    raise ValueError(f"{path}: {e}") from None
            data = np.load(path, mmap_mode="r")
        else:
            try:
                closer = np.load(path)
            except (zipfile.BadZipFile, EOFError) as e:
                raise ValueError(f"{path}: not a readable .npz archive: {e}") from e
            data = closer
    try:
        src = _source_of_loaded(data, kind, key)
        for _, a in src.arrays:  # values read (and checked) later, by row ranges: their refusal names the file too
            if path is not None and isinstance(a, _Float32Rows):
                a.shown = f"{path}: {a.shown}"
        return src, closer
    except BaseException as e:
        if closer is not None:
            closer.close()
        if path is not None and type(e) is ValueError:
            raise ValueError(f"{path}: {e}") from e.__cause__
        raise


def _source_of_loaded(data: Any, kind: str | None, key: str | None) -> UploadSource:
    if isinstance(data, np.lib.npyio.NpzFile):  # an archive: arrays loaded only when taken, and checked
        data = _NpzArrays(data)
    if isinstance(data, Mapping) or hasattr(data, "files"):
        mapping: Mapping[str, Any] = data if isinstance(data, Mapping) else {k: data[k] for k in data.files}
        detected = "trajectories" if "observations" in mapping and key is None else "samples"
        kind = kind or detected
        if kind == "trajectories":
            if key is not None:
                raise ValueError("key selects the array of a samples upload; trajectories always use their keys")
            return trajectories(mapping)
        if kind != "samples":
            raise ValueError(f"kind {kind!r}: expected 'trajectories' or 'samples'")
        names = list(mapping.keys())
        # Labels travel beside the samples, so they do not count as a second candidate.
        candidates = [k for k in names if k != "labels"]
        pick = key or ("samples" if "samples" in mapping else (candidates[0] if len(candidates) == 1 else None))
        if pick is None or pick not in mapping:
            raise ValueError(f"which array? pass key= (the input holds {', '.join(map(repr, names))})")
        # A "labels" array beside the samples travels with them (class-conditional training).
        labels = mapping["labels"] if "labels" in mapping and pick != "labels" else None
        src = samples(mapping[pick], labels)
        src.ignored = [k for k in names if k not in (pick, "labels" if labels is not None else None)]
        return src
    if kind == "trajectories":
        raise ValueError("a trajectories upload needs a mapping with 'observations' and 'actions'")
    return samples(data)


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
