"""A relreward reward inside online RL loops: vector-environment wrappers that replace the
environment's reward with the reward model's.

    import gymnasium as gym, relreward
    from relreward.rl import RewardVectorWrapper
    client = relreward.Client("127.0.0.1:50051")
    envs = RewardVectorWrapper(gym.make_vec("MyEnv-v0", num_envs=8), client, "maze-reward")

Module map:

- :class:`RewardWindows`: the core both wrappers share: each sub-environment's recent rows in
  the reward model's item layout, and one batched ``Score`` call per vector step.
- :class:`RewardVectorWrapper`: a ``gymnasium.vector.VectorWrapper`` for gymnasium 1.x vector
  environments (every autoreset mode).
- ``SB3RewardWrapper``: a Stable-Baselines3 ``VecEnvWrapper`` over an SB3 ``VecEnv``; SB3 2.x
  has no adapter for gymnasium vector environments. Loaded on first use, as SB3 imports torch.
- :func:`pointmaze_mapping`: gymnasium-robotics PointMaze's observations and actions in
  relreward's maze frame (the frame of ``experiments/pointmaze/generate.py``'s data).

What the reward is (docs/rl.md gives the measurements behind each choice):

- Row n of a sub-environment's episode is ``[a_n | s_n]``: the action and the observation it
  was taken from, the layout of the datasets the reward was trained on.
- The reward of step n is, for a windowed reward (``model.reward.window`` h > 0), the score
  g of the h rows ending at step n (the last per-window value of the H-row item ending there);
  for any other reward, rho of the H rows ending at step n. ``window_value=True`` takes rho of
  the H rows for a windowed reward too.
- Before an episode's first row, the item is filled with rows ``[0 | s_0]``: the agent at rest
  at its first observation, with zero action. Windows never span two episodes.

gymnasium is needed for :class:`RewardVectorWrapper` (``pip install gymnasium``), and
stable-baselines3 for ``SB3RewardWrapper``; neither is needed to import this module.
"""

from __future__ import annotations

import copy
import math
import numbers
from typing import Any, Callable, Sequence

import numpy as np

from relreward.client import Client
from relreward.errors import InvalidInput, NotFound
from relreward.results import Model

try:
    import gymnasium
    from gymnasium.vector import AutoresetMode, VectorWrapper
except ImportError:  # gymnasium is optional: the package imports without it
    gymnasium = None

    class VectorWrapper:  # type: ignore[no-redef]
        """Stands in for ``gymnasium.vector.VectorWrapper`` when gymnasium is not installed."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            raise ImportError("relreward.rl.RewardVectorWrapper needs gymnasium >= 1.0: pip install gymnasium")

#: ``mapping(observations, actions) -> (action_rows [N, action_dim], observation_rows [N,
#: obs_dim])``: a batch of the environment's observations (an array or a dict of arrays, as the
#: vector environment returns them) and the actions taken from them, in the dataset's layout.
RowMapping = Callable[[Any, Any], "tuple[np.ndarray, np.ndarray]"]


class RewardWindows:
    """Each sub-environment's last H rows ``[action | observation]`` in the reward model's item
    layout, and their rewards, scored for all sub-environments in one ``client.score`` call per
    vector step. The wrappers drive it; use it directly for a loop of your own:

        windows = RewardWindows(client, "maze-reward", num_envs)
        windows.begin(obs)                        # after reset: every episode starts
        ...
        rewards = windows.rewards(actions, moved) # before the new observations are known
        windows.begin(new_obs, starts)            # the observations the next actions are taken from

    ``model``: a reward or discriminator model (name or :class:`relreward.Model`) over
    trajectories ``[H, action_dim + obs_dim]``. ``t``: the diffusion step the rewards are read
    at (default 0, the clean data). ``mapping``: see :data:`RowMapping` (default: observations
    and actions as they come, flattened per sub-environment). ``window_value``: rho of the whole
    H-row item also for a windowed reward. ``action_dim``: the rows' action width (default:
    the space of the reward's base model, ``client.get_model(model.reward.base_model)``).
    Scores are in raw units (the server normalizes). Every failed call raises its
    :class:`relreward.RelrewardError`; nothing is ever replaced by a default value.
    """

    def __init__(self, client: Client, model: str | Model, num_envs: int, *, t: int = 0,
                 mapping: RowMapping | None = None, window_value: bool = False, action_dim: int | None = None) -> None:
        record = model if isinstance(model, Model) else client.get_model(model)
        horizon, width = record.trajectory_window()
        if action_dim is None:
            action_dim = _action_dim_of_base(client, record)
        if (isinstance(action_dim, bool) or not isinstance(action_dim, (int, np.integer))
                or not 0 <= action_dim <= width):
            raise InvalidInput(f"action_dim: {action_dim!r} is not an integer in [0, {width}] (the rows' width)")
        T = int(record.n_timesteps or 0)
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= t < T:
            raise InvalidInput(f"t: {t!r} is not an integer in [0, {T}) (the model's diffusion steps)")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise InvalidInput(f"num_envs: {num_envs!r} is not a positive integer")
        self.client = client
        self.model = record
        self.t = int(t)
        self.mapping = mapping
        self.action_dim = int(action_dim)
        self.obs_dim = width - self.action_dim
        # h > 0: the reward is the item's last per-window value (the windows tile the item, so
        # the last is the h rows ending at the current step); 0: rho of the whole item.
        self.window = 0 if window_value else int(record.reward.window)
        self._items = np.zeros((num_envs, horizon, width), np.float32)
        self._started = np.zeros(num_envs, bool)  # whether the episode has a row yet
        self._obs: Any = None  # the observations the next actions are taken from

    @property
    def num_envs(self) -> int:
        """The number of sub-environments."""
        return len(self._items)

    @property
    def items(self) -> np.ndarray:
        """``[num_envs, H, D]``: each sub-environment's item as last scored (read-only view)."""
        view = self._items.view()
        view.flags.writeable = False
        return view

    def begin(self, observations: Any, starts: np.ndarray | None = None) -> None:
        """Records the observations the next actions are taken from (the whole batch);
        sub-environments where ``starts`` is true (all when None) begin a new episode, so their
        next row starts a fresh window."""
        # A copy: vector environments may hand out one buffer that their next step overwrites
        # (gymnasium's ``copy=False``), and the rows need these observations after that step.
        self._obs = copy.deepcopy(observations)
        if starts is None:
            self._started[:] = False
        else:
            self._started[np.asarray(starts, bool)] = False

    def rows(self, observations: Any, actions: Any) -> tuple[np.ndarray, np.ndarray]:
        """The action and observation parts of the rows for a batch, float32 ``[N, action_dim]``
        and ``[N, obs_dim]``, through ``mapping`` when there is one; InvalidInput naming what
        does not fit the model."""
        n = self.num_envs
        what = "mapping" if self.mapping is not None else "observations"
        if self.mapping is not None:
            acts, obs = self.mapping(observations, actions)
        elif isinstance(observations, dict):
            raise InvalidInput("observations: the environment's observations are a dict; pass mapping= to say which "
                               "of them make the rows (e.g. relreward.rl.pointmaze_mapping)")
        else:
            acts, obs = actions, observations
        acts, obs = np.asarray(acts, np.float32), np.asarray(obs, np.float32)
        for part, values in (("action", acts), ("observation", obs)):
            if values.ndim == 0 or len(values) != n:
                raise InvalidInput(f"{what}: {part}s for {len(values) if values.ndim else 0} sub-environments, "
                                   f"the environment has {n}")
        acts, obs = acts.reshape(n, -1), obs.reshape(n, -1)
        if obs.shape[1] != self.obs_dim:
            raise InvalidInput(f"{what}: {obs.shape[1]} observation values per sub-environment, but the rows of "
                               f"{self.model.name!r} take obs_dim = {self.obs_dim}")
        if acts.shape[1] != self.action_dim:
            raise InvalidInput(f"{'mapping' if self.mapping is not None else 'actions'}: {acts.shape[1]} action values "
                               f"per sub-environment, but the rows of {self.model.name!r} take action_dim = "
                               f"{self.action_dim}")
        return acts, obs

    def rewards(self, actions: Any, moved: np.ndarray | None = None) -> np.ndarray:
        """Appends row ``[action | observation]`` (the observation from :meth:`begin`) to the
        window of every sub-environment where ``moved`` is true (all when None), scores those
        windows in one call and returns float32 ``[num_envs]``: their rewards, 0 where nothing
        moved (a step that only reset the sub-environment). Raises the call's error."""
        if self._obs is None:
            raise RuntimeError("RewardWindows.rewards before begin(): reset the environment first")
        acts, obs = self.rows(self._obs, actions)
        idx = np.arange(self.num_envs) if moved is None else np.flatnonzero(np.asarray(moved, bool))
        out = np.zeros(self.num_envs, np.float32)
        if idx.size == 0:
            return out
        a, x = self.action_dim, self._items
        # A new episode's item is filled with the agent at rest at its first observation
        # ([0 | s_0]): measured closest to the reward a real history gives (docs/rl.md).
        fresh = idx[~self._started[idx]]
        x[fresh, :, :a] = 0.0
        x[fresh, :, a:] = obs[fresh, None, :]
        x[idx, :-1] = x[idx, 1:]
        x[idx, -1, :a] = acts[idx]
        x[idx, -1, a:] = obs[idx]
        self._started[idx] = True
        got = self.client.score(self.model.name, x[idx], self.t, units="raw", per_window=self.window > 0)
        out[idx] = got.per_window[:, -1] if self.window > 0 else got.rewards
        return out


def _action_dim_of_base(client: Client, record: Model) -> int:
    """The action width of a reward's rows: its base model's trajectory space (the reward's
    record gives only the item's width)."""
    name = record.reward.base_model
    try:
        base = client.get_model(name) if name else None
    except NotFound as e:
        raise InvalidInput(f"action_dim: the base model {name!r} of {record.name!r} is gone, so the rows' action "
                           "width is unknown; pass action_dim=") from e
    space = base.manifest.space if base is not None and base.manifest is not None else None
    if space is None or space.kind != "trajectory":
        raise InvalidInput(f"action_dim: {record.name!r} names no base model with a trajectory space; pass action_dim=")
    return int(space.action_dim)


def _mix(rho: np.ndarray, env_reward: np.ndarray, env_weight: float) -> np.ndarray:
    """The reward handed to the learner: rho plus ``env_weight`` times the environment's own."""
    env_reward = np.asarray(env_reward, np.float64)
    return rho.astype(np.float64) + env_weight * env_reward if env_weight else rho.astype(np.float64)


def _weight(env_weight: float) -> float:
    """``env_weight`` as a float: any real number (a Python or numpy integer or float, e.g.
    ``np.float32(0.5)``) that is finite; bools are refused (a flag passed in the wrong place)."""
    if (isinstance(env_weight, (bool, np.bool_)) or not isinstance(env_weight, numbers.Real)
            or not math.isfinite(float(env_weight))):
        raise InvalidInput(f"env_weight: {env_weight!r} is not a finite number")
    return float(env_weight)


class RewardVectorWrapper(VectorWrapper):
    """A gymnasium vector environment whose reward is a relreward reward model's.

    ``env``: a ``gymnasium.vector.VectorEnv`` (``gym.make_vec``, ``SyncVectorEnv``,
    ``AsyncVectorEnv``) in any autoreset mode: with NEXT_STEP (gymnasium's default) the step
    that resets a finished sub-environment applies no action, so it adds no row and its reward
    is 0, and the new episode starts a fresh window; with SAME_STEP the finished episode's last
    row is scored and the returned first observation starts the next; with DISABLED,
    ``reset(options={"reset_mask": ...})`` starts the masked sub-environments' windows.

    ``client``, ``model``, ``t``, ``mapping``, ``window_value``, ``action_dim``: as
    :class:`RewardWindows`. ``env_weight``: the returned reward is ``rho + env_weight *
    env_reward`` (default 0: rho alone). ``info["env_reward"]`` keeps the environment's own
    reward and ``info["rho"]`` the reward model's (each with gymnasium's ``_``-prefixed mask).

    Normalise with gymnasium's own wrapper outside this one, e.g.
    ``gymnasium.wrappers.vector.NormalizeReward(RewardVectorWrapper(...))``; observation
    wrappers that change what the reward model should see (``NormalizeObservation``) also go
    outside, so the rows stay in the dataset's units.
    """

    def __init__(self, env: Any, client: Client, model: str | Model, *, t: int = 0, mapping: RowMapping | None = None,
                 env_weight: float = 0.0, window_value: bool = False, action_dim: int | None = None) -> None:
        super().__init__(env)
        self.env_weight = _weight(env_weight)
        self.windows = RewardWindows(client, model, env.num_envs, t=t, mapping=mapping, window_value=window_value,
                                     action_dim=action_dim)
        space = env.single_observation_space
        if (mapping is None and isinstance(space, gymnasium.spaces.Box)
                and int(np.prod(space.shape)) != self.windows.obs_dim):
            raise InvalidInput(f"env: observations of shape {list(space.shape)}, but the rows of "
                               f"{self.windows.model.name!r} take obs_dim = {self.windows.obs_dim}; pass mapping=")
        self.autoreset_mode = AutoresetMode(env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP))
        self._ended = np.zeros(env.num_envs, bool)  # finished on the last step (NEXT_STEP resets them now)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
              ) -> tuple[Any, dict[str, Any]]:
        """Resets the environment (all sub-environments, or ``options["reset_mask"]``'s) and
        starts their windows."""
        # Read the mask before the environment pops it from the options.
        mask = None if options is None or "reset_mask" not in options else np.asarray(options["reset_mask"], bool)
        obs, info = self.env.reset(seed=seed, options=options)
        starts = np.ones(self.num_envs, bool) if mask is None else mask
        self.windows.begin(obs, starts)
        self._ended[starts] = False
        return obs, info

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Steps the environment and returns its step with the reward model's reward."""
        obs, env_reward, terminated, truncated, info = self.env.step(actions)
        ended = np.asarray(terminated, bool) | np.asarray(truncated, bool)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            moved, starts = ~self._ended, self._ended
        elif self.autoreset_mode == AutoresetMode.SAME_STEP:
            moved, starts = np.ones(self.num_envs, bool), ended
        else:
            moved, starts = np.ones(self.num_envs, bool), np.zeros(self.num_envs, bool)
        rho = self.windows.rewards(actions, moved)
        self.windows.begin(obs, starts)
        self._ended = ended
        info = dict(info)
        info["env_reward"], info["_env_reward"] = np.asarray(env_reward), np.ones(self.num_envs, bool)
        info["rho"], info["_rho"] = rho, moved.copy()
        return obs, _mix(rho, env_reward, self.env_weight), terminated, truncated, info


def _sb3_wrapper() -> type:
    """Defines ``SB3RewardWrapper`` (on first use: stable-baselines3 imports torch)."""
    try:
        from stable_baselines3.common.vec_env import VecEnvWrapper
    except ImportError as e:
        raise ImportError("relreward.rl.SB3RewardWrapper needs stable-baselines3 >= 2.0: "
                          "pip install stable-baselines3") from e

    class SB3RewardWrapper(VecEnvWrapper):
        """A Stable-Baselines3 ``VecEnv`` whose reward is a relreward reward model's.

        ``venv``: an SB3 ``VecEnv`` (``make_vec_env``, ``DummyVecEnv``, ``SubprocVecEnv``).
        SB3 resets a finished sub-environment within the same step: the finished episode's
        last row is scored, and the returned first observation starts the next window.
        ``infos[i]["env_reward"]`` keeps the environment's reward, ``infos[i]["rho"]`` the
        model's. Other arguments as :class:`relreward.rl.RewardVectorWrapper`. Normalise with
        ``VecNormalize(SB3RewardWrapper(...), norm_reward=True)``: VecNormalize outside, so
        the reward model sees raw observations.
        """

        def __init__(self, venv: Any, client: Client, model: str | Model, *, t: int = 0,
                     mapping: RowMapping | None = None, env_weight: float = 0.0, window_value: bool = False,
                     action_dim: int | None = None) -> None:
            super().__init__(venv)
            self.env_weight = _weight(env_weight)
            self.windows = RewardWindows(client, model, venv.num_envs, t=t, mapping=mapping,
                                         window_value=window_value, action_dim=action_dim)
            self._actions: Any = None

        def reset(self) -> Any:
            """Resets every sub-environment and starts their windows."""
            obs = self.venv.reset()
            self.windows.begin(obs)
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            """Sends the actions (kept: they make this step's rows)."""
            self._actions = actions
            self.venv.step_async(actions)

        def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict[str, Any]]]:
            """The step's results with the reward model's reward."""
            obs, env_reward, dones, infos = self.venv.step_wait()
            rho = self.windows.rewards(self._actions)
            self.windows.begin(obs, dones)
            for i, info in enumerate(infos):
                info["env_reward"], info["rho"] = float(env_reward[i]), float(rho[i])
            return obs, _mix(rho, env_reward, self.env_weight).astype(np.float32), dones, infos

    SB3RewardWrapper.__module__, SB3RewardWrapper.__qualname__ = __name__, "SB3RewardWrapper"
    return SB3RewardWrapper


_LAZY: dict[str, Callable[[], type]] = {"SB3RewardWrapper": _sb3_wrapper}


def __getattr__(name: str) -> Any:
    # PEP 562: ``relreward.rl.SB3RewardWrapper`` is defined when first asked for.
    if name in _LAZY:
        value = globals()[name] = _LAZY[name]()
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def pointmaze_mapping(maze_map: Sequence[Sequence[Any]], maze_size_scaling: float = 1.0) -> RowMapping:
    """A :data:`RowMapping` from gymnasium-robotics PointMaze (v3) to relreward's maze frame, for
    a reward trained on ``experiments/pointmaze/generate.py`` data.

    PointMaze's observation is a dict whose ``observation`` is ``[x, y, vx, vy]`` with the origin
    at the maze's centre and y up; relreward's maze frame puts cell (row, col) at position (row,
    col): ``row = (y_center - y) / s - 0.5``, ``col = (x + x_center) / s - 0.5`` (s the maze
    scaling, ``x_center = cols * s / 2``, ``y_center = rows * s / 2``), velocities
    ``(-vy, vx) / s``, and actions ``(a_row, a_col) = (-a_y, a_x)``. ``maze_map``: the maze's
    rows of cells (``env.unwrapped.maze.maze_map``); only its size is used.
    """
    rows, cols = len(maze_map), len(maze_map[0])
    s = float(maze_size_scaling)
    x_center, y_center = cols * s / 2, rows * s / 2

    def mapping(observations: Any, actions: Any) -> tuple[np.ndarray, np.ndarray]:
        o = np.asarray(observations["observation"], np.float64)
        a = np.asarray(actions, np.float64).reshape(len(o), 2)
        obs = np.stack([(y_center - o[:, 1]) / s - 0.5, (o[:, 0] + x_center) / s - 0.5, -o[:, 3] / s, o[:, 2] / s], 1)
        return np.stack([-a[:, 1], a[:, 0]], 1), obs

    return mapping
