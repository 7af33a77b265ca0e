"""End to end, tiny: agents trained on the extracted reward (experiments/pointmaze/rl.py, issue 35
item 3). generate.py data, `relreward extract --size tiny --discriminator` through the real
server, SAC for a few hundred steps per arm in MuJoCo PointMaze, evaluation, curves, table.
Nothing is expected to learn; the checks are that every arm ran on its own reward and that the
outputs hold what the experiment reports.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import sys

import numpy as np
import pytest

from conftest import REPO

pytest.importorskip("stable_baselines3")
pytest.importorskip("gymnasium_robotics")


def load_rl(monkeypatch):
    # rl.py imports generate.py as its sibling (conftest puts experiments/pointmaze on the path).
    spec = importlib.util.spec_from_file_location("pointmaze_rl", REPO / "experiments/pointmaze/rl.py")
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, mod)  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_tiny_pointmaze_rl_runs_every_arm_and_writes_its_table(server, tmp_path, monkeypatch):
    rl = load_rl(monkeypatch)
    from PIL import Image

    goal = (3, 1)
    cfg = rl.Config(work=tmp_path / "work", goals=(goal,), seeds=1, steps=240, n_envs=2, gradient_steps=1,
                    learning_starts=100, batch_size=32, net=(16, 16), cap=40, eval_episodes=3, curve_episodes=1,
                    eval_every=120, base_transitions=1500, expert_transitions=600, extract_size="tiny",
                    workers=2, log=lambda s: None)
    result = rl.experiment(cfg, server)
    assert result["trained_now"] == 4

    runs = {r["arm"]: r for r in result["runs"]}
    assert sorted(runs) == sorted(rl.ARMS)
    for arm, r in runs.items():
        assert r["env_steps"] >= 240, arm
        eps = r["episodes"]
        assert [e["seed"] for e in eps] == [rl.EVAL_SEED + k for k in range(3)], arm
        assert all(e["steps"] == 40 and math.isfinite(e["final_distance"]) and 0 <= e["time_within"] <= 1
                   for e in eps), eps
        assert r["success"] == np.mean([e["final_distance"] <= 0.5 for e in eps])
        # The final position in relreward's frame (pointmaze_mapping) and the distance measured
        # in gymnasium-robotics' frame (cell_rowcol_to_xy) agree.
        for e in eps:
            assert np.linalg.norm(np.subtract(e["final_position"], goal)) == pytest.approx(e["final_distance"],
                                                                                            abs=2e-3), e
        assert (cfg.work / "agents" / f"3-1-{arm}-0.zip").stat().st_size > 0
        assert [p["steps"] for p in r["curve"]][:2] == [120, 240], r["curve"]
        assert r["train_rewards"]["count"] >= 240
    # Each arm trained on its own reward: zero, PointMaze's exp(-distance), and the models' scores.
    assert runs["constant"]["train_rewards"]["min"] == runs["constant"]["train_rewards"]["max"] == 0.0
    env = runs["env"]["train_rewards"]
    assert 0.0 < env["min"] < env["max"] <= 1.0
    for arm in ("rho", "discriminator"):
        tr = runs[arm]["train_rewards"]
        assert tr["std"] > 0 and np.isfinite([tr["min"], tr["max"]]).all(), (arm, tr)
    assert result["models"]["3,1"]["rho"] != result["models"]["3,1"]["discriminator"]

    work = cfg.work
    table = (work / "results.md").read_text()
    for arm in rl.ARMS:
        assert f"| 3,1 | {arm} | {runs[arm]['success']:.2f} (" in table, table
    curves = json.loads((work / "curves.json").read_text())
    assert {c["arm"] for c in curves} == set(rl.ARMS)
    assert json.loads((work / "results.json").read_text())["runs"][0]["episodes"] == result["runs"][0]["episodes"]
    with Image.open(work / "curves.png") as im:
        im.load()
        assert im.size[0] > 100

    # A rerun in the same WORK (a run split across sessions) reuses the extract and every
    # recorded agent; a changed setting retrains.
    logs: list[str] = []
    again = rl.experiment(dataclasses.replace(cfg, log=logs.append), server)
    assert any("reusing WORK/prepare.json" in line for line in logs), logs
    assert again["trained_now"] == 0 and again["models"] == result["models"] and again["runs"] == result["runs"]
    assert rl.finished_run(dataclasses.replace(cfg, steps=250), goal, "rho", 0, result["models"]["3,1"]) is None
