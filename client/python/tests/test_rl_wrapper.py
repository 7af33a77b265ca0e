"""relreward.rl: the online reward wrappers against the tiny reward (`rw`: windowed MLP, h = 4,
items [8, 2 + 2], T = 10) on a tiny gymnasium point environment.

Every reward the wrappers return is checked against ``client.score`` of a window this file
builds on its own from the recorded episodes (rows [a_n | s_n], the item filled with [0 | s_0]
before the first row, no window across two episodes), for vector sizes 1 and 4 whose episodes
end at different steps, in gymnasium's NEXT_STEP and SAME_STEP autoreset modes and in SB3's
VecEnv."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import relreward
from relreward.rl import RewardVectorWrapper, RewardWindows, pointmaze_mapping

from conftest import start_server, tiny_trajectories


class PointEnv(gym.Env):
    """A point in the plane: observation its position (2-d), action a velocity command (2-d).
    Episode k lasts ``lengths[k % len(lengths)]`` steps and ends terminated (even k) or
    truncated (odd k); the environment's own reward is minus the distance to the origin."""

    observation_space = gym.spaces.Box(-5.0, 5.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, lengths: list[int]) -> None:
        self.lengths = lengths
        self.episode = -1

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode += 1
        self.n = 0
        self.pos = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        return self.pos.copy(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.1 * np.asarray(action, np.float32), -5, 5).astype(np.float32)
        self.n += 1
        done = self.n >= self.lengths[self.episode % len(self.lengths)]
        return self.pos.copy(), -float(np.linalg.norm(self.pos)), done and self.episode % 2 == 0, \
            done and self.episode % 2 == 1, {}


def lengths(i: int) -> list[int]:
    # Sub-environments end at different steps; episodes shorter than h (4) and than H (8), and
    # longer than H (full windows that shift), in each.
    return [3 + i, 11, 2 + i, 9 + 2 * i]


def vector(n: int, mode: AutoresetMode = AutoresetMode.NEXT_STEP, copy: bool = True) -> SyncVectorEnv:
    return SyncVectorEnv([lambda i=i: PointEnv(lengths(i)) for i in range(n)], autoreset_mode=mode, copy=copy)


def reference(client, model: str, first_obs, steps, same_step: bool, window_value: bool) -> np.ndarray:
    """The rewards, built here without relreward.rl: per sub-environment, the episode's rows
    [a_n | s_n]; the window ending at each step is the last H rows of H rows [0 | s_0] followed by
    the episode's rows; all windows scored in one ``client.score`` call. ``steps``: (actions,
    new observations, ended) per vector step. NaN where a step moved nothing (NEXT_STEP reset)."""
    record = client.get_model(model)
    H, D = record.item_shape
    A = D - first_obs.shape[1]
    n = len(first_obs)
    obs = [first_obs[i] for i in range(n)]
    rows: list[list[np.ndarray]] = [[] for _ in range(n)]
    resetting = [False] * n
    windows, where = [], []
    for k, (actions, new_obs, ended) in enumerate(steps):
        for i in range(n):
            if resetting[i]:  # NEXT_STEP: this step only reset the sub-environment
                resetting[i] = False
                rows[i] = []
            else:
                rows[i].append(np.concatenate([actions[i], obs[i]]))
                rest = np.concatenate([np.zeros(A), rows[i][0][A:]])
                windows.append(np.stack([rest] * H + rows[i])[-H:])
                where.append((k, i))
                if ended[i]:
                    if same_step:
                        rows[i] = []
                    else:
                        resetting[i] = True
            obs[i] = new_obs[i]
    got = client.score(model, np.stack(windows).astype(np.float32), 0, per_window=True)
    values = got.rewards if window_value else got.per_window[:, -1]
    out = np.full((len(steps), n), np.nan, np.float32)
    for (k, i), v in zip(where, values):
        out[k, i] = v
    return out


@pytest.mark.parametrize("n", [1, 4])
@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
@pytest.mark.parametrize("window_value", [False, True])
@pytest.mark.parametrize("copy", [True, False])  # False: the env overwrites one observation buffer
def test_gymnasium_rewards_are_the_scores_of_each_episodes_windows(client, tiny, n, mode, window_value, copy):
    envs = RewardVectorWrapper(vector(n, mode, copy), client, tiny.reward, window_value=window_value)
    obs, _ = envs.reset(seed=7)
    first = obs.copy()
    rng = np.random.default_rng(0)
    steps, got, env_rewards, resets = [], [], [], 0
    for _ in range(30):
        actions = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
        obs, reward, term, trunc, info = envs.step(actions)
        steps.append((actions, obs.copy(), term | trunc))
        got.append(reward)
        np.testing.assert_array_equal(reward, info["rho"])  # env_weight 0: rho alone
        env_rewards.append(info["env_reward"])
        resets += int(np.any(~info["_rho"]))
    want = reference(client, tiny.reward, first, steps, mode == AutoresetMode.SAME_STEP, window_value)
    got = np.array(got)
    moved = ~np.isnan(want)
    np.testing.assert_allclose(got[moved], want[moved], rtol=1e-5, atol=1e-6)
    assert np.all(got[~moved] == 0)  # a NEXT_STEP reset step applies no action: no row, reward 0
    assert np.all(np.array(env_rewards)[~moved] == 0)
    if mode == AutoresetMode.NEXT_STEP:
        assert resets >= 4 and (~moved).sum() >= 4  # several resets, mid-batch when n = 4
        if n == 4:
            assert any(0 < (~moved[k]).sum() < n for k in range(len(steps)))
    else:
        assert moved.all()


def test_an_episode_starts_at_rest_and_never_joins_the_last(client, tiny):
    envs = RewardVectorWrapper(vector(1), client, tiny.reward)
    obs, _ = envs.reset(seed=1)
    a0 = np.array([[0.5, -0.25]], np.float32)
    envs.step(a0)
    item = envs.windows.items[0]
    np.testing.assert_array_equal(item[:-1], np.tile(np.concatenate([[0, 0], obs[0]]), (tiny.horizon - 1, 1)))
    np.testing.assert_array_equal(item[-1], np.concatenate([a0[0], obs[0]]))
    # Episode 0 lasts 3 steps; step 4 is NEXT_STEP's reset; step 5 is the new episode's first row.
    for _ in range(3):
        obs, *_ = envs.step(a0)
    a1 = np.array([[-1.0, 1.0]], np.float32)
    envs.step(a1)
    item = envs.windows.items[0]
    np.testing.assert_array_equal(item[:-1, :2], 0)
    np.testing.assert_array_equal(item[:, 2:], np.tile(obs[0], (tiny.horizon, 1)))
    np.testing.assert_array_equal(item[-1, :2], a1[0])


def test_info_keeps_the_environment_reward_and_mixes_it_by_weight(client, tiny):
    envs = RewardVectorWrapper(vector(4), client, tiny.reward, env_weight=0.5)
    envs.reset(seed=3)
    for _ in range(12):
        obs, reward, _, _, info = envs.step(np.full((4, 2), 0.3, np.float32))
        moved = info["_rho"]
        np.testing.assert_allclose(info["env_reward"][moved], -np.linalg.norm(obs[moved], axis=1), rtol=1e-6)
        np.testing.assert_allclose(reward, info["rho"].astype(np.float64) + 0.5 * info["env_reward"], rtol=1e-12)


def test_gymnasium_normalize_reward_composes_outside(client, tiny):
    envs = gym.wrappers.vector.NormalizeReward(RewardVectorWrapper(vector(4), client, tiny.reward), gamma=0.9)
    envs.reset(seed=0)
    for _ in range(10):
        _, reward, _, _, info = envs.step(np.full((4, 2), -0.5, np.float32))
    moved = info["_rho"]
    scale = reward[moved] / info["rho"][moved]  # one running scale for every sub-environment
    np.testing.assert_allclose(scale, scale[0], rtol=1e-5)
    assert scale[0] > 0 and not np.isclose(scale[0], 1.0)


def test_disabled_autoreset_starts_the_masked_windows(client, tiny):
    envs = RewardVectorWrapper(vector(2, AutoresetMode.DISABLED), client, tiny.reward)
    obs, _ = envs.reset(seed=5)
    first, steps = obs.copy(), []
    for _ in range(14):
        actions = np.full((2, 2), 0.7, np.float32)
        obs, reward, term, trunc, _ = envs.step(actions)
        ended = term | trunc
        if ended.any():
            obs, _ = envs.reset(options={"reset_mask": ended})
        steps.append((actions, obs.copy(), ended))
        steps[-1] += (reward,)
    want = reference(client, tiny.reward, first, [s[:3] for s in steps], True, False)
    np.testing.assert_allclose(np.array([s[3] for s in steps]), want, rtol=1e-5, atol=1e-6)


def test_refusals_name_the_argument(client, tiny):
    with pytest.raises(relreward.InvalidInput, match="^INVALID_ARGUMENT: t: "):
        RewardVectorWrapper(vector(1), client, tiny.reward, t=tiny.n_timesteps)
    with pytest.raises(relreward.InvalidInput, match="model: 'base' is a diffusion model"):
        RewardVectorWrapper(vector(1), client, tiny.base)
    with pytest.raises(relreward.NotFound):
        RewardVectorWrapper(vector(1), client, "no-such-reward")
    with pytest.raises(relreward.InvalidInput, match="env_weight: "):
        RewardVectorWrapper(vector(1), client, tiny.reward, env_weight=float("nan"))
    with pytest.raises(relreward.InvalidInput, match="action_dim: "):
        RewardWindows(client, tiny.reward, 1, action_dim=5)
    wide = SyncVectorEnv([lambda: gym.wrappers.TransformObservation(
        PointEnv([5]), lambda o: np.concatenate([o, o]), gym.spaces.Box(-5, 5, (4,), np.float32))])
    with pytest.raises(relreward.InvalidInput, match=r"env: observations of shape \[4\].*obs_dim = 2; pass mapping="):
        RewardVectorWrapper(wide, client, tiny.reward)
    envs = RewardVectorWrapper(wide, client, tiny.reward, mapping=lambda o, a: (a, o))
    envs.reset(seed=0)
    with pytest.raises(relreward.InvalidInput, match="mapping: 4 observation values per sub-environment"):
        envs.step(np.zeros((1, 2), np.float32))
    envs = RewardVectorWrapper(wide, client, tiny.reward, mapping=lambda o, a: (a, o[:0, :2]))
    envs.reset(seed=0)
    with pytest.raises(relreward.InvalidInput, match="mapping: observations for 0 sub-environments, the environment "):
        envs.step(np.zeros((1, 2), np.float32))


def test_a_server_error_surfaces_with_its_field(client, tiny):
    envs = RewardVectorWrapper(vector(2), client, tiny.reward)
    envs.reset(seed=0)
    # A non-finite action makes a non-finite row; the server refuses x, naming it.
    with pytest.raises(relreward.InvalidArgument, match=r"\bx\b") as e:
        envs.step(np.array([[0.0, np.nan], [0.0, 0.0]], np.float32))
    assert not isinstance(e.value, relreward.InvalidInput)  # the server's answer, not a local check


def test_a_server_that_goes_away_fails_the_step(tmp_path):
    server = start_server(tmp_path / "data")
    try:
        with relreward.Client(server.addr, retry_budget=0.5) as c:
            c.upload_dataset("d", tiny_trajectories())
            opt = relreward.Optimization(steps=4, batch_size=8)
            for name, seed in (("b", 1), ("e", 2)):
                c.wait_job(c.submit_job(relreward.DiffusionJob(
                    output_model=name, dataset="d", horizon=8, n_timesteps=10, seed=seed, optimization=opt,
                    architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}))).id)
            job = c.wait_job(c.submit_job(relreward.RewardJob(
                output_model="r", base_model="b", expert_model="e", datasets=["d"], seed=3, optimization=opt,
                architecture=("windowed_mlp", {"window": 4, "hidden": [16]}))).id)
            assert job.state == "succeeded", job.error
            # The rows' action width comes from the base model; once it is deleted, it must be given.
            c.delete_model("b")
            with pytest.raises(relreward.InvalidInput, match="action_dim: the base model 'b' of 'r' is gone"):
                RewardVectorWrapper(vector(2), c, "r")
            envs = RewardVectorWrapper(vector(2), c, "r", action_dim=2)
            envs.reset(seed=0)
            _, reward, *_ = envs.step(np.zeros((2, 2), np.float32))
            assert np.all(np.isfinite(reward))
            server.stop()
            with pytest.raises(relreward.Unavailable):
                envs.step(np.zeros((2, 2), np.float32))
    finally:
        server.stop()


def test_sb3_rewards_are_the_scores_of_each_episodes_windows(client, tiny):
    from stable_baselines3.common.vec_env import DummyVecEnv

    from relreward.rl import SB3RewardWrapper

    for n in (1, 4):
        venv = SB3RewardWrapper(DummyVecEnv([lambda i=i: PointEnv(lengths(i)) for i in range(n)]), client, tiny.reward)
        venv.seed(11)
        obs = venv.reset()
        first, steps, got = obs.copy(), [], []
        rng = np.random.default_rng(1)
        for _ in range(25):
            actions = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
            obs, reward, dones, infos = venv.step(actions)
            steps.append((actions, obs.copy(), dones))
            got.append(reward)
            assert [i["rho"] for i in infos] == pytest.approx(reward.tolist())
            # SB3 resets within the step: the finished episode's last observation is in the info.
            for i in np.flatnonzero(dones):
                assert "terminal_observation" in infos[i]
        want = reference(client, tiny.reward, first, steps, True, False)
        assert sum(s[2].sum() for s in steps) >= 4
        np.testing.assert_allclose(np.array(got), want, rtol=1e-5, atol=1e-6)


def test_sb3_ppo_trains_a_few_hundred_steps_through_the_wrapper(client, tiny):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from relreward.rl import SB3RewardWrapper

    inner = SB3RewardWrapper(DummyVecEnv([lambda i=i: PointEnv(lengths(i)) for i in range(4)]), client, tiny.reward,
                             env_weight=0.1)
    venv = VecNormalize(inner, norm_obs=False, norm_reward=True)
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256
    assert venv.ret_rms.count > 1  # VecNormalize saw the wrapper's rewards


def test_pointmaze_mapping_puts_cells_at_their_row_and_column(client, tiny):
    pytest.importorskip("gymnasium_robotics")
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make("PointMaze_UMaze-v3", continuing_task=True)
    maze = env.unwrapped.maze
    mapping = pointmaze_mapping(maze.maze_map, maze.maze_size_scaling)
    cells = [(r, c) for r in range(len(maze.maze_map)) for c in range(len(maze.maze_map[0]))]
    xy = np.array([maze.cell_rowcol_to_xy(np.array(rc)) for rc in cells])
    acts, obs = mapping({"observation": np.concatenate([xy, np.zeros_like(xy)], 1)}, np.zeros((len(cells), 2)))
    np.testing.assert_allclose(obs[:, :2], np.array(cells, float), atol=1e-9)
    # Pushing +x in gymnasium's frame moves along +col in relreward's; the action reads (0, 1).
    o, _ = env.reset(seed=0, options={"reset_cell": np.array([1, 1])})
    start = mapping({"observation": o["observation"][None]}, np.zeros((1, 2)))[1][0]
    for _ in range(10):
        o, *_ = env.step(np.array([1.0, 0.0], np.float32))
    acts, obs = mapping({"observation": o["observation"][None]}, np.array([[1.0, 0.0]]))
    np.testing.assert_allclose(acts, [[0.0, 1.0]])
    assert obs[0, 3] > 0.5 and abs(obs[0, 2]) < 1e-6  # moving along +col only
    assert obs[0, 1] - start[1] > 0.05 and abs(obs[0, 0] - start[0]) < 1e-6
    env.close()
    # In a vector environment, through the wrapper: the mapping's 4 observation values do not fit
    # the tiny reward's rows (2), named; positions alone do.
    envs = gym.make_vec("PointMaze_UMaze-v3", num_envs=2, vectorization_mode="sync", continuing_task=True)
    with pytest.raises(relreward.InvalidInput, match="mapping: 4 observation values"):
        w = RewardVectorWrapper(envs, client, tiny.reward, mapping=mapping)
        w.reset(seed=0)
        w.step(np.zeros((2, 2), np.float32))
    w = RewardVectorWrapper(envs, client, tiny.reward, mapping=lambda o, a: (mapping(o, a)[0], mapping(o, a)[1][:, :2]))
    w.reset(seed=0)
    _, reward, *_ = w.step(np.ones((2, 2), np.float32))
    assert reward.shape == (2,) and np.all(np.isfinite(reward))
    w.close()


def test_the_package_imports_without_gymnasium_or_sb3():
    import subprocess
    import sys

    # None in sys.modules makes an import fail as if the package were not installed.
    code = """
import sys
sys.modules["gymnasium"] = sys.modules["stable_baselines3"] = None
import relreward, relreward.rl
assert "torch" not in sys.modules
for make in (lambda: relreward.RewardVectorWrapper(None, None, "rw"), lambda: relreward.rl.SB3RewardWrapper):
    try:
        make()
    except ImportError as e:
        print(e)
    else:
        raise AssertionError("no ImportError")
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines() == [
        "relreward.rl.RewardVectorWrapper needs gymnasium >= 1.0: pip install gymnasium",
        "relreward.rl.SB3RewardWrapper needs stable-baselines3 >= 2.0: pip install stable-baselines3"]
