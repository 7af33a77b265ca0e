"""End to end, tiny: the locomotion steering experiment (experiments/locomotion, paper section 5.2).

From the committed Hopper ARS policy: a few short rollouts as data, two tiny planners, upload
to a real relreward-server (TorchScript uploads on), the reward (Algorithm 1) and the
discriminator trained for a few steps, every arm run in the external-planner mode (GradientStream)
and the unsteered/reward arms in the server-side mode (Sample), a sweep, and the report. Checks
that returns are finite and recorded per arm and mode, the table names every arm and the PNG
decodes. Sizes are tiny, so nothing here measures steering; the numbers are in docs/results.md.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import relreward

# experiments/locomotion's modules (common, data, planner, steer, diagnose) are on sys.path
# through conftest.py.


def test_tiny_steering_experiment_runs_both_planner_modes(tmp_path):
    import common
    import data
    import planner as planner_mod
    import steer
    from PIL import Image

    d = tmp_path / "data"
    d.mkdir()
    for name, set_ in (("expert", data.make_expert("hopper", 2, 0.02, 0, max_steps=40)),
                       ("medium-replay", data.make_medium_replay("hopper", 4, 0.05, 1, 1 / 3, max_steps=40))):
        assert len(set_["rewards"]) > 0 and np.isfinite(set_["observations"]).all()
        np.savez(d / f"hopper-{name}.npz", **set_)
    base = np.load(d / "hopper-medium-replay.npz")
    expert = np.load(d / "hopper-expert.npz")
    rows = np.concatenate([np.concatenate([z["actions"], z["observations"]], 1) for z in (base, expert)])
    lo, hi = rows.min(0), rows.max(0)
    hi = np.where(hi - lo < 1e-6, lo + 1e-6, hi)
    planners = tmp_path / "planners"
    for name, z in (("medium-replay", base), ("expert", expert)):
        pl = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=5, hidden=32, depth=2)
        losses = pl.train(pl.windows(dict(z)), steps=20, batch=16, log=lambda s: None)
        assert all(math.isfinite(v) for v in losses)
        pl.save(planners / f"hopper-{name}", dict(set=name))
    cfg = steer.Config(env="hopper", data=d, planners=planners, work=tmp_path / "work", episodes=2, sweep_episodes=1,
                       max_steps=6, n_plans=3, widths=(32,), reward_steps=10, disc_steps=10, batch_size=8,
                       omegas=(0.1,), t_stopgrads=(1,), server_mode_episodes=1, guide_at="sweep",
                       reward_action_weight=10.0, reward_condition_weight=0.0, inpaint_condition=True,
                       log=lambda s: None)
    result = steer.experiment(cfg)

    eps = result["episodes"]
    for arm in steer.ARMS:
        got = [e for e in eps if e["arm"] == arm and e["mode"] == "external"]
        assert [e["seed"] for e in got] == [0, 1], arm
        assert all(math.isfinite(e["ret"]) and 1 <= e["length"] <= 6 for e in got), got
    for arm in ("unsteered", "reward"):
        got = [e for e in eps if e["arm"] == arm and e["mode"] == "server"]
        assert len(got) == 1 and math.isfinite(got[0]["ret"]), arm
    # Guided arms waited for the service; the unsteered arm never asked it anything.
    assert all(e["wait_seconds"] > 0 for e in eps if e["arm"] != "unsteered")
    assert all(e["wait_seconds"] == 0 for e in eps if e["arm"] == "unsteered" and e["mode"] == "external")
    assert set(result["sweeps"]) == {"reward", "discriminator"}
    # guide_at="sweep": each guided arm tried both rules and its episodes used the one it chose.
    for arm, key in (("reward", "guide_at"), ("discriminator", "disc_guide_at")):
        assert {r["guide_at"] for r in result["sweeps"][arm]} == set(planner_mod.GUIDE_AT)
        assert result[key] in planner_mod.GUIDE_AT
        assert {e["guide_at"] for e in eps if e["arm"] == arm and e["mode"] == "external"} == {result[key]}
    saved = json.loads((cfg.work / "hopper-results.json").read_text())
    assert len(saved["episodes"]) == len(eps)
    assert saved["summary"]["arms"]["reward"]["welch"]["p"] <= 1.0
    # Both networks were trained on x_t with the current state clean, and their manifests (as
    # the API hands them out) say so.
    server = steer.start_server(cfg.work / "server-data")
    try:
        with relreward.Client(server.addr) as client:
            for name in ("hopper-reward", "hopper-discriminator"):
                got = client.download_model(name, tmp_path / "downloads" / name)
                assert got.manifest["inpaint_condition"] is True, name
                assert json.loads(got.manifest_path.read_text()) == got.manifest
    finally:
        server.stop(grace=30)
    table = (cfg.work / "hopper-table.md").read_text()
    assert all(f"| {arm} |" in table for arm in steer.ARMS)
    with Image.open(cfg.work / "hopper-steer.png") as img:
        img.load()
        assert img.size == (640, 360)
    assert common.normalized_score("hopper", 3234.3) == pytest.approx(100.0)


def test_welch_and_paired_match_known_values():
    import common

    # Student t two-sided p-values (t = 2, df = 10: 0.07339; t = 1, df = 3: 0.39100).
    assert common.t_two_sided_p(2.0, 10) == pytest.approx(0.073388, abs=1e-5)
    assert common.t_two_sided_p(1.0, 3) == pytest.approx(0.391002, abs=1e-5)
    a, b = [1.0, 2.0, 3.0, 4.0], [2.0, 4.0, 6.0, 8.0, 10.0]
    w = common.welch(a, b)
    # By hand: va = 1.6667/4, vb = 10/5, t = -3.5 / sqrt(2.41667), df = 5.1057 (Welch-Satterthwaite).
    assert w["t"] == pytest.approx(-3.5 / math.sqrt(2.416667), rel=1e-5)
    assert w["df"] == pytest.approx(2.416667**2 / ((1.666667 / 4) ** 2 / 3 + 2.0**2 / 4), rel=1e-5)
    pr = common.paired([3.0, 5.0, 4.0], [1.0, 2.0, 3.0])
    assert pr["mean"] == pytest.approx(2.0) and pr["wins"] == 3


def test_external_sampler_and_server_sample_draw_the_same_plans(tmp_path):
    """The external planner's loop (planner.sample) and the server's Sample run the same
    uploaded module with the same schedule, normaliser and inpainting: over many plans from one
    state, their per-coordinate means agree within sampling error (a wrong schedule, posterior
    or normaliser on either side moves them apart by far more)."""
    import planner as planner_mod
    import relreward
    import steer

    rng = np.random.default_rng(0)
    lo, hi = -rng.uniform(1, 3, 14), rng.uniform(1, 3, 14)
    pl = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=6, hidden=32, depth=2)
    # Windows with structure (actions follow the state) so the denoiser learns something.
    s = rng.uniform(-1, 1, (2048, 4, 11))
    a = np.tanh(s[..., :3] * 2)
    win = np.concatenate([a, s], -1).astype(np.float32)
    pl.train(win, steps=150, batch=64, log=lambda m: None)
    pl.save(tmp_path / "pl", {})
    pl = planner_mod.Planner.load(tmp_path / "pl")
    obs = pl.unnormalize(np.concatenate([np.zeros(3), rng.uniform(-0.5, 0.5, 11)]))[3:]
    state = 2 * (obs - lo[3:]) / (hi[3:] - lo[3:]) - 1
    n = 400
    ext = pl.unnormalize(planner_mod.sample(pl, state[None, :], n, seed=1))
    data = tmp_path / "server-data"
    data.mkdir()
    server = steer.start_server(data)
    try:
        client = relreward.Client(server.addr)
        client.upload_model(tmp_path / "pl" / "denoiser.torchscript.pt", "pl",
                            json.loads((tmp_path / "pl" / "manifest.json").read_text()))
        srv = client.sample("pl", n=n, seed=2, conditions={0: obs.astype(np.float32)}).x
    finally:
        server.stop(grace=30)
    assert np.allclose(srv[:, 0, 3:], obs, atol=1e-4) and np.allclose(ext[:, 0, 3:], obs, atol=1e-6)
    free = np.ones((4, 14), bool)
    free[0, 3:] = False  # the inpainted state: equal on both sides, no spread to compare with

    def z(x):
        se = np.sqrt(x.var(0) / n + srv.var(0) / n)
        return (np.abs(x.mean(0) - srv.mean(0)) / se)[free]

    assert z(ext).max() < 5.0, z(ext).max()
    # The check has teeth: the same loop with a wrong posterior coefficient is told apart.
    pl.sched.coef1 = pl.sched.coef1[::-1].copy()
    moved = pl.unnormalize(planner_mod.sample(pl, state[None, :], n, seed=1))
    assert z(moved).max() > 5.0, z(moved).max()


def test_lockstep_plans_equal_one_episode_at_a_time():
    """Episodes planned in lockstep (act_many: one batch, one gradient call per denoising step)
    choose the actions each would choose alone (act with its own seed), with guidance and plan
    selection on; and a row's plans do not depend on the other rows (a shuffled batch gives the
    same rows)."""
    import planner as planner_mod
    import torch

    rng = np.random.default_rng(3)
    lo, hi = -rng.uniform(1, 3, 14), rng.uniform(1, 3, 14)
    torch.manual_seed(0)
    pl = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=6, hidden=32, depth=2)
    w = torch.randn(4, 14, dtype=torch.float64)

    def grad_fn(x, t):  # grad of rho(x) = sum(w * tanh(x)), scaled by t
        return (w.numpy()[None] * (1 - np.tanh(x) ** 2)) * (1 + 0.1 * t)

    def select_fn(x):
        return (w.numpy()[None] * np.tanh(x)).sum(axis=(1, 2))

    obs = pl.unnormalize(rng.uniform(-0.8, 0.8, (5, 14)))[:, 3:]
    seeds = [7, 11, 100_003, 5, 42]
    calls = []

    def counted(x, t):
        calls.append(len(x))
        return grad_fn(x, t)

    together = planner_mod.act_many(pl, obs, 4, seeds, counted, 0.3, 1, select_fn)
    alone = np.stack([planner_mod.act(pl, o, 4, s, grad_fn, 0.3, 1, select_fn) for o, s in zip(obs, seeds)])
    np.testing.assert_allclose(together, alone, rtol=1e-5, atol=1e-5)
    # One gradient request per guided denoising step (t = 5..1) for all 5 x 4 plans.
    assert calls == [20] * 5
    perm = [3, 0, 4, 1, 2]
    shuffled = planner_mod.act_many(pl, obs[perm], 4, [seeds[i] for i in perm], grad_fn, 0.3, 1, select_fn)
    np.testing.assert_allclose(shuffled, together[perm], rtol=1e-5, atol=1e-5)
    # A different seed for one episode changes that episode's action only.
    other = planner_mod.act_many(pl, obs, 4, seeds[:4] + [43], grad_fn, 0.3, 1, select_fn)
    np.testing.assert_allclose(other[:4], together[:4], rtol=1e-5, atol=1e-5)
    assert not np.allclose(other[4], together[4])


def test_mean_guidance_by_the_true_difference_samples_the_expert():
    """guide_at="mean" adds omega * grad to the base's posterior mean: with the exact
    mu_expert - mu_base as the gradient and omega 1 every step is the expert's step, so with the
    same noise the guided base planner returns the expert planner's plans (to float error).
    Diffuser's "x_t" rule with the same gradient does not (the denoiser sees a shifted input),
    nor does stopping the guidance early (t_stopgrad 2: the last steps are the base's)."""
    import planner as planner_mod
    import torch

    rng = np.random.default_rng(5)
    lo, hi = -rng.uniform(1, 3, 14), rng.uniform(1, 3, 14)
    torch.manual_seed(1)
    base = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=6, hidden=32, depth=2)
    expert = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=6, hidden=32, depth=2)
    s = base.sched

    def diff(x, t):
        mu = [s.coef1[t] * np.clip(planner_mod._denoise(p, x, t), -1, 1) for p in (expert, base)]
        return mu[0] - mu[1]

    state = rng.uniform(-0.8, 0.8, (3, 11))
    want = planner_mod.sample(expert, state, 5, [1, 2, 3])
    got = planner_mod.sample(base, state, 5, [1, 2, 3], diff, 1.0, 0, guide_at="mean")
    np.testing.assert_allclose(got, want, atol=1e-5)
    plain = planner_mod.sample(base, state, 5, [1, 2, 3])
    assert np.abs(plain - want).max() > 0.05
    for other in (planner_mod.sample(base, state, 5, [1, 2, 3], diff, 1.0, 0, guide_at="x_t"),
                  planner_mod.sample(base, state, 5, [1, 2, 3], diff, 1.0, 2, guide_at="mean")):
        assert np.abs(other - want).max() > 0.01
    with pytest.raises(ValueError, match="guide_at"):
        planner_mod.sample(base, state, 5, [1, 2, 3], diff, 1.0, 0, guide_at="x0")


def test_diagnose_auc_and_gap_closed_against_direct_counts():
    """diagnose.py's AUC equals the share of (expert, medium-replay) pairs ordered right, ties
    half; its gap-closed measure is 1 for mean guidance by the exact difference at omega 1 and 0
    without guidance (omega 0)."""
    import diagnose
    import planner as planner_mod
    import torch

    rng = np.random.default_rng(7)
    pos, neg = rng.integers(0, 5, 40).astype(float), rng.integers(0, 4, 30).astype(float)
    direct = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert abs(diagnose.auc(pos, neg) - direct) < 1e-12

    lo, hi = -rng.uniform(1, 3, 14), rng.uniform(1, 3, 14)
    torch.manual_seed(2)
    base = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=5, hidden=32, depth=2)
    expert = planner_mod.Planner("hopper", 4, 3, 11, lo, hi, n_timesteps=5, hidden=32, depth=2)
    win = rng.uniform(-0.8, 0.8, (6, 4, 14))

    class Exact(torch.nn.Module):  # stands in for rho only through grad_rho, patched below
        pass

    orig = diagnose.grad_rho
    diagnose.grad_rho = lambda rho, x, t: diagnose.mean_diff(base, expert, x, t)
    try:
        rows = diagnose.shift(base, expert, Exact(), win, (0.0, 1.0), 0, 3, "mean")
    finally:
        diagnose.grad_rho = orig
    assert abs(rows[0]["grad_rho_gap_closed"]) < 1e-9
    assert abs(rows[1]["grad_rho_gap_closed"] - 1.0) < 1e-4 and abs(rows[1]["true_difference_gap_closed"] - 1.0) < 1e-4
