"""Offline relabelling: a dataset file written back with its ``rewards`` replaced by a reward
model's value of every transition (docs/relabel.md).

    with relreward.Client(addr) as client:
        relreward.relabel(client, "maze-reward", "maze2d-umaze.hdf5", "maze2d-umaze-rho.hdf5")

**The reward of a transition.** Row ``i`` of a dataset is the transition ``[a_i | s_i]`` (the
reward model's row layout: action, then observation). Its reward is the value of the **last
window** of the model's item **ending at row i**: the item is the ``H`` rows ``i - H + 1 .. i``
(H the model's horizon), and rows before the episode's first row ``e`` are padding rows
``[0 (action) | s_e]``: the episode's first observation with a zero action (raw units). The
value is ``score(..., per_window=True).per_window[:, -1]``: for a windowed reward (window
``h``) that is ``g(rows i - h + 1 .. i)``, the window of the h transitions ending at row i,
equal to ``per_step[:, H - h]``; for any other reward (one window per item) it is rho of the
item. Padding therefore reaches only the first ``h - 1`` (windowed) or ``H - 1`` rows of an
episode. Only rows up to ``i`` are used, so an online agent at step ``i`` can compute the same
value. (``per_step[:, H - 1]``, the per-step value of the item's last row, would score the
window that starts at row i, which the server pads at the item's end by repeating row i
``h - 1`` times: a window the reward never saw in training, and not defined for
non-windowed rewards.)

**Episodes** are cut as the server cuts them for training (relreward.datasets): after a
``terminals`` or ``timeouts`` row, before an ``episode_starts`` row (or per
``episode_lengths``), and at every Minari episode group.

**Forms** (by the file's signature, as :func:`relreward.datasets.source_of` reads them): an
``.npz`` with D4RL keys, a D4RL-layout HDF5 file, a Minari ``main_data.hdf5``, or a Minari
dataset directory. The output has the input's form; everything but ``rewards`` is copied
unchanged (HDF5 objects with their attributes, dtypes and filters; ``.npz`` members byte for
byte once extracted; a Minari directory's other files), except a Minari directory's
``metadata.json`` (beside ``main_data.hdf5``): its ``dataset_id`` becomes the output's id as
Minari derives it (:func:`_minari_id`) and ``dataset_size`` is measured again; every other key
is kept as it was. ``rewards`` becomes float32 ``[N]``
(per Minari episode ``[T]``); the input's ``rewards`` is kept as ``rewards_original`` beside it,
unless the input already holds a ``rewards_original`` (a relabelled file relabelled again:
the first original stays, the previous relabelling is dropped). HDF5 ``rewards`` carry the
attributes ``relreward_model`` and ``relreward_t``.

**Memory**: the observations and actions as relreward.datasets reads them (an HDF5 file by row
ranges; an ``.npz`` or Minari file in memory), plus ``batch`` items ``[H, D]`` at a time and
the float32 rewards; never all ``[N, H, D]`` windows.

Everything that can be refused is refused before anything is written (InvalidInput naming
``src``, ``dst``, ``model``, ``t`` or ``batch``; a Minari ``metadata.json`` that is not a JSON
object is refused naming ``src``), and the output is written to a temporary
name beside ``dst`` and renamed into place once complete: a failure at any point, a server
error during scoring included, leaves no ``dst``.
"""

from __future__ import annotations

import json
import os
import pathlib
import secrets
import shutil
import warnings
import zipfile
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from relreward import datasets as _ds
from relreward.errors import InvalidInput, NotFound

#: The name the input's ``rewards`` is kept under in the output.
ORIGINAL = "rewards_original"
#: Upper bound on one Score request's payload when ``batch`` is not given (the server's
#: message limit is 64 MiB and it takes at most ``serving.max_request_items`` items, 4096 by
#: default).
_BATCH_BYTES = 8 << 20
_BATCH_ITEMS = 1024

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class Relabelled:
    """What :func:`relabel` wrote: ``dst``, the ``form`` ("npz", "hdf5" for the D4RL layout,
    "minari-hdf5", "minari-dir"), the float32 ``rewards`` ``[N]`` in the order relreward reads
    the rows (Minari: episodes in id order), the number of ``episodes``, and ``original``: the
    name the input's rewards are kept under (None when the input had none)."""

    dst: pathlib.Path
    form: str
    rewards: np.ndarray
    episodes: int
    original: str | None


@dataclass
class _Rows:
    """Transitions as relreward reads them: float32 observations / actions (numpy arrays or
    lazy row-range readers) and each row's episode start."""

    observations: Any
    actions: Any
    first: np.ndarray  # int64 [N]: the first row of each row's episode

    @property
    def episodes(self) -> int:
        return int(np.count_nonzero(self.first == np.arange(len(self.first))))


def _rows_of(data: Any) -> tuple[_Rows, Any]:
    """The transitions of ``data`` (a path or a D4RL-style mapping) read by
    relreward.datasets' rules, and the open file to close afterwards (or None)."""
    source, closer = _ds.source_of(data, kind="trajectories")
    arrays = dict(source.arrays)
    n = int(arrays["observations"].shape[0])
    starts = np.zeros(n, bool)
    if n:
        starts[0] = True
    ends = np.zeros(n, bool)
    for key in ("terminals", "timeouts"):
        if key in arrays:
            ends |= arrays[key]
    starts[1:] |= ends[:-1]
    if "episode_starts" in arrays:
        starts |= arrays["episode_starts"]
    first = np.maximum.accumulate(np.where(starts, np.arange(n), 0))
    return _Rows(arrays["observations"], arrays["actions"], first), closer


def _check_model(client: Any, model: str, rows: _Rows, t: Any, name: str) -> tuple[int, int]:
    """``(H, D)`` of the reward ``model`` after checking that it scores trajectories whose rows
    are this data's ``[action | observation]`` and that ``t`` is one of its steps."""
    if isinstance(t, bool) or not isinstance(t, (int, np.integer)):
        raise InvalidInput(f"t: {t!r} is not an integer; expected one diffusion step")
    m = client.get_model(model)
    horizon, width = m.trajectory_window()
    act_dim, obs_dim = int(rows.actions.shape[1]), int(rows.observations.shape[1])
    if act_dim + obs_dim != width:
        raise InvalidInput(f"{name}: rows of {act_dim} action + {obs_dim} observation values = {act_dim + obs_dim}, "
                           f"but model '{model}' takes rows of {width} (its items are [{horizon}, {width}], "
                           "rows [action | observation])")
    # The split too, where the reward's base model still says it: 1 + 3 is not 2 + 2.
    try:
        space = client.get_model(m.reward.base_model).manifest.space if m.reward.base_model else None
    except NotFound:
        space = None
    if space is not None and space.kind == "trajectory" and (space.action_dim, space.obs_dim) != (act_dim, obs_dim):
        raise InvalidInput(f"{name}: rows of {act_dim} action + {obs_dim} observation values, but model '{model}' "
                           f"was extracted from '{m.reward.base_model}', whose rows are {space.action_dim} action + "
                           f"{space.obs_dim} observation values")
    steps = m.n_timesteps
    if steps and not 0 <= int(t) < steps:
        raise InvalidInput(f"t: {int(t)} is outside [0, {steps}), the diffusion steps of model '{model}'")
    return int(horizon), int(width)


def _batch_of(batch: Any, horizon: int, width: int) -> int:
    if batch is None:
        return max(1, min(_BATCH_ITEMS, _BATCH_BYTES // (horizon * width * 4)))
    if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
        raise InvalidInput(f"batch: {batch!r}; expected a positive number of items per Score request")
    return int(batch)


def _progress_of(progress: Progress | bool | None, total: int) -> tuple[Progress | None, Any]:
    """(callback(done_rows, total_rows), bar to close): ``True`` shows a tqdm bar when tqdm is
    installed, as uploads do, and warns when it is not."""
    if progress is True:
        try:
            from tqdm.auto import tqdm
        except ImportError:
            warnings.warn("progress=True shows a tqdm bar, but tqdm is not installed: no progress is shown "
                          "(pip install 'relreward[progress]', or pass a callback(done_rows, total_rows))",
                          RuntimeWarning, stacklevel=4)
            return None, None
        bar = tqdm(total=total, unit="row", unit_scale=True, desc="relabel")
        return (lambda done, _total: bar.update(done - bar.n)), bar
    if callable(progress):
        return progress, None
    if progress is None or progress is False:
        return None, None
    raise InvalidInput(f"progress: {progress!r}; expected True, False, None or a callback(done_rows, total_rows)")


def _windows(rows: _Rows, start: int, stop: int, horizon: int) -> np.ndarray:
    """The items ``[stop - start, H, D]`` (float32, rows ``[action | observation]``) ending at
    rows ``start .. stop - 1``, padded before each episode's first row by the module's rule."""
    lo = max(0, start - (horizon - 1))
    obs = np.asarray(rows.observations[lo:stop], dtype=np.float32)
    act = np.asarray(rows.actions[lo:stop], dtype=np.float32)
    first = rows.first[start:stop, None]
    index = np.arange(start, stop)[:, None] - (horizon - 1) + np.arange(horizon)  # [n, H] rows
    pad = index < first
    take = np.maximum(index, first) - lo  # a padding row takes the episode's first row ...
    x = np.concatenate([act[take], obs[take]], axis=-1)
    x[pad, :act.shape[1]] = 0  # ... with a zero action
    return x


def _score(client: Any, model: str, rows: _Rows, horizon: int, t: int, batch: int,
           tick: Progress | None, name: str) -> np.ndarray:
    n = len(rows.first)
    out = np.empty(n, np.float32)
    for start in range(0, n, batch):
        stop = min(n, start + batch)
        try:
            x = _windows(rows, start, stop, horizon)
        except ValueError as e:  # a lazy reader (HDF5) meets a bad value only now
            raise InvalidInput(f"{name}: {e}") from None
        result = client.score(model, x, t, per_window=True)
        out[start:stop] = result.per_window[:, -1]
        if tick is not None:
            tick(stop, n)
    return out


def transition_rewards(client: Any, model: str, data: Any, *, t: int = 0, batch: int | None = None,
                       progress: Progress | bool | None = None) -> np.ndarray:
    """The reward of every transition of ``data`` by the module's rule, float32 ``[N]``, rows
    in the order relreward reads them. ``data``: a D4RL-style mapping or a path in any form
    :func:`relreward.datasets.source_of` reads as trajectories. ``t``: the diffusion step
    (default 0, clean data); ``batch``: items per Score request (default: up to 1024, at most
    8 MiB); ``progress``: ``True`` for a tqdm bar or ``callback(done_rows, total_rows)``."""
    rows, closer = _read(data, "data")
    try:
        return _rewards(client, model, rows, t, batch, progress, "data")
    finally:
        if closer is not None:
            closer.close()


def _read(data: Any, name: str) -> tuple[_Rows, Any]:
    try:
        return _rows_of(data)
    except ValueError as e:  # the readers' words, naming the key (and the path)
        raise InvalidInput(f"{name}: {e}") from None


def _rewards(client: Any, model: str, rows: _Rows, t: Any, batch: Any, progress: Any, name: str) -> np.ndarray:
    horizon, width = _check_model(client, model, rows, t, name)
    size = _batch_of(batch, horizon, width)
    tick, bar = _progress_of(progress, len(rows.first))
    try:
        return _score(client, model, rows, horizon, int(t), size, tick, name)
    finally:
        if bar is not None:
            bar.close()


# ---------------------------------------------------------------------------------------------
# Forms and writers


def _form(path: pathlib.Path) -> str:
    """"npz", "hdf5" (D4RL layout), "minari-hdf5" or "minari-dir" (refusing an ``.npy``)."""
    form = _ds._form_of(path)
    if form == "npy":
        raise ValueError(f"{path}: an .npy file holds one array (samples); relabelling needs transitions "
                         "(observations and actions)")
    if form == "hdf5":
        kind, f = _ds._open_hdf5(path, "trajectories", None)
        if f is not None:
            f.close()
        return "minari-hdf5" if kind == "minari" else "hdf5"
    return form


#: Minari's metadata file, beside ``main_data.hdf5`` in the dataset's ``data`` folder.
METADATA = "metadata.json"


@dataclass(frozen=True)
class _MinariMetadata:
    """A Minari directory's ``metadata.json``: its path inside the directory and its keys."""

    inner: pathlib.Path
    keys: dict


def _minari_metadata(src: pathlib.Path) -> _MinariMetadata | None:
    """The ``metadata.json`` beside the Minari directory ``src``'s ``main_data.hdf5`` (None when
    there is none); ValueError when it is not a JSON object (Minari could not read it either)."""
    main = _ds._minari_file(src)
    assert main is not None  # _form found it
    path = main.parent / METADATA
    if not path.is_file():
        return None
    try:
        keys = json.loads(path.read_bytes())
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not JSON ({e}); Minari's metadata is a JSON object") from None
    if not isinstance(keys, dict):
        raise ValueError(f"{path}: a JSON {type(keys).__name__}; Minari's metadata is a JSON object")
    return _MinariMetadata(path.relative_to(src), keys)


def _minari_root() -> pathlib.Path:
    """Minari's datasets root, as ``minari.storage.get_dataset_path`` finds it:
    ``$MINARI_DATASETS_PATH``, else ``~/.minari/datasets``."""
    root = os.environ.get("MINARI_DATASETS_PATH")
    return pathlib.Path(root) if root is not None else pathlib.Path.home() / ".minari" / "datasets"


def _dataset_folder(directory: pathlib.Path, inner: pathlib.Path) -> pathlib.Path:
    """The folder Minari names a dataset by: the one holding the ``data`` folder. ``inner`` is
    ``metadata.json``'s path inside ``directory``: ``data/metadata.json`` (Minari's layout:
    ``directory`` itself), or ``metadata.json`` when ``directory`` is the data folder (its
    parent when it is named ``data``)."""
    if len(inner.parts) == 1 and directory.name == "data":
        return directory.parent
    return directory


def _minari_id(dst: pathlib.Path, src: pathlib.Path, src_id: Any) -> str:
    """The id Minari gives the dataset folder ``dst``: its path relative to the datasets root
    that holds it, ``/``-separated (``namespace/name-v0``; ``name-v0`` directly in the root),
    as ``minari.list_local_datasets`` derives ids and checks them against ``dataset_id``.

    The root is Minari's (:func:`_minari_root`) when ``dst`` lies under it, else the root the
    source sits in when its path ends with its own ``dataset_id`` (``src_id``: ``ns/a-v0`` at
    ``R/ns/a-v0`` gives ``R``) and ``dst`` lies under that; otherwise (no root holds ``dst``)
    the id is ``dst``'s folder name, what Minari reads when the folder is moved into a root."""
    d = dst.resolve()
    roots = [_minari_root()]
    if isinstance(src_id, str) and src_id.strip("/"):
        parts = tuple(pathlib.PurePosixPath(src_id.strip("/")).parts)
        s = src.resolve().parts
        if len(s) > len(parts) and s[-len(parts):] == parts:
            roots.append(pathlib.Path(*s[:-len(parts)]))
    for root in roots:
        try:
            rel = d.relative_to(root.resolve())
        except ValueError:
            continue
        if rel.parts:
            return "/".join(rel.parts)
    return d.name


def _data_size_mb(folder: pathlib.Path) -> float:
    """``dataset_size`` as Minari measures it (``MinariStorage.get_size``): the bytes of
    everything under the data folder, in MB (10^6 bytes), rounded to one decimal."""
    return round(sum(p.stat().st_size for p in folder.glob("**/*")) / 1e6, 1)


def _write_metadata(tmp: pathlib.Path, dst: pathlib.Path, src: pathlib.Path, meta: _MinariMetadata) -> None:
    """Rewrites the copied ``metadata.json`` in ``tmp`` (the output, to be renamed ``dst``):
    ``dataset_id`` becomes ``dst``'s id, ``dataset_size`` (when present) the output's size;
    every other key as it was, in its order. Written as Minari writes it (``json.dump``)."""
    keys = dict(meta.keys)
    keys["dataset_id"] = _minari_id(_dataset_folder(dst, meta.inner), _dataset_folder(src, meta.inner),
                                    meta.keys.get("dataset_id"))
    path = tmp / meta.inner
    if "dataset_size" in keys:
        keys["dataset_size"] = _data_size_mb(path.parent)
    path.unlink()  # a copied link would otherwise be written through
    path.write_text(json.dumps(keys))


def _check_paths(src: pathlib.Path, dst: pathlib.Path, form: str, overwrite: bool) -> None:
    s = src.resolve()
    d = dst.resolve()
    if d == s or (dst.exists() and os.path.samefile(src, dst)):
        raise InvalidInput(f"dst: {dst} is src; write the relabelled dataset to another path")
    if form == "minari-dir" and s in d.parents:
        raise InvalidInput(f"dst: {dst} lies inside src {src}")
    if d in s.parents:
        raise InvalidInput(f"dst: {dst} holds src {src}")
    if not d.parent.is_dir():
        raise InvalidInput(f"dst: the folder {dst.parent} does not exist")
    if os.path.lexists(dst):
        if not overwrite:
            raise InvalidInput(f"dst: {dst} exists; pass overwrite=True to replace it")
        want_dir = form == "minari-dir"
        if dst.is_dir() != want_dir:
            raise InvalidInput(f"dst: {dst} is {'a directory' if dst.is_dir() else 'not a directory'}; "
                               f"the relabelled dataset is {'a Minari directory' if want_dir else 'a file'}")


def _copy_attrs(src: Any, dst: Any) -> None:
    for key in src.attrs:
        dst.attrs.create(key, src.attrs[key], dtype=src.attrs.get_id(key).dtype)


def _write_group(fin: Any, gin: Any, gout: Any, values: np.ndarray, model: str, t: int) -> bool:
    """Copies ``gin``'s members and attributes into ``gout`` with ``rewards`` replaced by
    ``values`` and the original kept; True when an original was kept."""
    _copy_attrs(gin, gout)
    kept = ORIGINAL in gin
    for name in gin:
        if name != "rewards":
            fin.copy(gin[name], gout, name)
        elif not kept:
            fin.copy(gin[name], gout, ORIGINAL)
            kept = True
    d = gout.create_dataset("rewards", data=values.astype(np.float32))
    d.attrs["relreward_model"] = model
    d.attrs["relreward_t"] = np.int64(t)
    return kept


def _write_hdf5(src: pathlib.Path, tmp: pathlib.Path, minari: bool, rewards: np.ndarray, model: str,
                t: int) -> bool:
    import h5py

    kept = False
    with h5py.File(src, "r") as fin, h5py.File(tmp, "w") as fout:
        if not minari:
            return _write_group(fin, fin, fout, rewards, model, t)
        _copy_attrs(fin, fout)
        offset = 0
        for _, name in _ds._episode_groups(fin):  # the readers' order: episodes by id
            g = fin[name]
            length = int(g["actions"].shape[0])
            kept |= _write_group(fin, g, fout.create_group(name), rewards[offset:offset + length], model, t)
            offset += length
        if offset != len(rewards):  # the reader and this walk disagree: never write such a file
            raise RuntimeError(f"{src}: episodes hold {offset} rows but {len(rewards)} were read")
    return kept


def _npy_key(name: str) -> str:
    return name[:-4] if name.endswith(".npy") else name


def _write_npz(src: pathlib.Path, tmp: pathlib.Path, rewards: np.ndarray) -> bool:
    """Copies every member of the archive (re-compressed as it was), with ``rewards.npy``
    replaced and the original kept as ``rewards_original.npy``; True when one was kept."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(tmp, "w", allowZip64=True) as zout:
        infos = zin.infolist()
        kept = any(_npy_key(i.filename) == ORIGINAL for i in infos)
        old = [i for i in infos if _npy_key(i.filename) == "rewards"]
        compress = (old or infos or [zipfile.ZipInfo()])[0].compress_type

        def copy(info: zipfile.ZipInfo, name: str) -> None:
            out = zipfile.ZipInfo(name, date_time=info.date_time)
            out.compress_type, out.external_attr = info.compress_type, info.external_attr
            with zin.open(info) as r, zout.open(out, "w", force_zip64=True) as w:
                shutil.copyfileobj(r, w, 1 << 20)

        def write_rewards() -> None:
            info = zipfile.ZipInfo("rewards.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = compress
            with zout.open(info, "w", force_zip64=True) as w:
                np.lib.format.write_array(w, rewards.astype(np.float32), allow_pickle=False)

        written = False
        for info in infos:
            if _npy_key(info.filename) != "rewards":
                copy(info, info.filename)
                continue
            if not written:
                write_rewards()
                written = True
            if not kept:
                copy(info, ORIGINAL + (".npy" if info.filename.endswith(".npy") else ""))
                kept = True
        if not written:
            write_rewards()
    return kept


def relabel(client: Any, model: str, src: str | os.PathLike, dst: str | os.PathLike, *, t: int = 0,
            batch: int | None = None, overwrite: bool = False,
            progress: Progress | bool | None = None) -> Relabelled:
    """Writes ``src`` (an ``.npz`` with D4RL keys, a D4RL HDF5 file, a Minari ``main_data.hdf5``
    or a Minari dataset directory) to ``dst`` in the same form with ``rewards`` replaced by
    reward ``model``'s value of every transition at diffusion step ``t`` (the module's rule:
    the last window of the ``H`` rows ending at the transition, padded before the episode's
    first row with its first observation and a zero action), the input's ``rewards`` kept as
    ``rewards_original`` and everything else copied unchanged (but a Minari directory's
    ``metadata.json``, whose ``dataset_id`` becomes ``dst``'s id and ``dataset_size`` its size).

    ``client``: a :class:`relreward.Client`; ``batch``: items per Score request (default: up to
    1024, at most 8 MiB); ``overwrite``: replace an existing ``dst``; ``progress``: ``True`` for
    a tqdm bar (a RuntimeWarning when tqdm is missing) or ``callback(done_rows, total_rows)``.

    Refused before anything is written, with InvalidInput naming the argument: ``dst`` that is
    ``src`` or exists (without ``overwrite``), a form relreward does not read, data without
    ``actions`` (or otherwise refused by relreward.datasets' rules), rows whose width (or
    action/observation split) is not the model's, a model that is not a trajectory reward, a
    ``t`` outside ``[0, T)``. The output is renamed into place only once complete.
    """
    src_p, dst_p = pathlib.Path(src), pathlib.Path(dst)
    if not os.path.lexists(src_p):
        raise InvalidInput(f"src: {src} does not exist")
    try:
        form = _form(src_p)
    except ValueError as e:
        raise InvalidInput(f"src: {e}") from None
    _check_paths(src_p, dst_p, form, overwrite)
    try:
        meta = _minari_metadata(src_p) if form == "minari-dir" else None
    except ValueError as e:
        raise InvalidInput(f"src: {e}") from None
    rows, closer = _read(src_p, "src")
    try:
        rewards = _rewards(client, model, rows, t, batch, progress, "src")
    finally:
        if closer is not None:
            closer.close()
    episodes = rows.episodes
    del rows
    kept = _publish(src_p, dst_p, form, rewards, model, int(t), meta)
    return Relabelled(dst_p, form, rewards, episodes, ORIGINAL if kept else None)


def _temporary(dst: pathlib.Path, directory: bool) -> pathlib.Path:
    """A new empty file or directory beside ``dst``, created with the default permissions
    (the umask's, as ``dst`` itself would get; tempfile's are owner-only)."""
    for _ in range(100):
        tmp = dst.parent / f".{dst.name}.{secrets.token_hex(4)}.partial"
        try:
            if directory:
                tmp.mkdir()
            else:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{dst.parent}: no free temporary name for {dst.name}")


def _publish(src: pathlib.Path, dst: pathlib.Path, form: str, rewards: np.ndarray, model: str, t: int,
             meta: _MinariMetadata | None = None) -> bool:
    """Writes the output under a temporary name beside ``dst`` and renames it into place (an
    existing ``dst`` is replaced only then); ``meta``: a Minari directory's metadata, rewritten
    for ``dst``."""
    tmp = _temporary(dst, form == "minari-dir")
    try:
        if form == "minari-dir":
            main = _ds._minari_file(src)
            assert main is not None  # _form found it
            inner = main.relative_to(src)
            shutil.copytree(src, tmp, symlinks=True, dirs_exist_ok=True,
                            ignore=lambda d, names: [main.name] if pathlib.Path(d) == main.parent else [])
            kept = _write_hdf5(main, tmp / inner, True, rewards, model, t)
            if meta is not None:
                _write_metadata(tmp, dst, src, meta)
        elif form == "npz":
            kept = _write_npz(src, tmp, rewards)
        else:
            kept = _write_hdf5(src, tmp, form == "minari-hdf5", rewards, model, t)
        if form == "minari-dir" and os.path.lexists(dst):
            # os.replace cannot replace a non-empty directory: move the old one aside first.
            old = _temporary(dst, True)
            os.replace(dst, old / dst.name)
            try:
                os.replace(tmp, dst)
            except BaseException:
                os.replace(old / dst.name, dst)
                raise
            finally:
                if not os.path.lexists(old / dst.name) or os.path.lexists(dst):
                    shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, dst)
        return kept
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise


__all__ = ["relabel", "transition_rewards", "Relabelled", "ORIGINAL"]
