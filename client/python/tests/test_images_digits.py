"""The digits experiment (experiments/images/digits.py, `make images`) end to end in its tiny
configuration: real server, both DDPMs on the native UNet2D, Algorithm 2 from the models only,
Algorithm 1, the discriminator, `relreward eval discriminate` on image items, guided sampling
and the pictures. Tiny means nothing is expected to separate; the test checks that every stage
ran on the right data and produced well-formed results."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from conftest import REPO

pytest.importorskip("sklearn")
pytest.importorskip("matplotlib")


def test_digits_experiment_runs_end_to_end(tmp_path):
    out = tmp_path / "digits"
    p = subprocess.run([sys.executable, str(REPO / "experiments/images/digits.py"), "--tiny", "--out", str(out),
                        "--seed", "3"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, f"digits.py failed:\n{p.stdout}\n{p.stderr}"
    s = json.loads((out / "summary.json").read_text())
    assert s["subset"] == [0, 1, 2, 3, 4]
    # 1797 digits, 75/25 stratified; about half the classes in the subset.
    assert s["train_sizes"]["all"] + s["test_sizes"]["inside"] + s["test_sizes"]["outside"] == 1797
    assert 0.4 < s["train_sizes"]["subset"] / s["train_sizes"]["all"] < 0.6
    for tag in ("algorithm2", "algorithm1", "discriminator"):
        r = s["real_heldout"][tag]
        assert 0.0 <= r["balanced_accuracy"] <= 1.0 and 0.0 <= r["auc"] <= 1.0
        # eval discriminate held out 20% of each class of the held-out digits.
        assert r["n_test"][0] > 0 and r["n_test"][1] > 0
    steer = s["steering"]["fraction_in_subset"]
    assert all(0.0 <= steer[k] <= 1.0 for k in ("base_unguided", "base_guided", "expert"))
    assert 0.5 <= s["samples"]["cap"] <= 1.0
    assert s["classifier_test_accuracy"] > 0.9  # the pixel classifier is real, even here
    assert "algorithm2_t5" in s["real_heldout"]
    for png in ("hist-real-algorithm2-t0.png", "extremes-algorithm2.png", "samples-unguided-vs-guided.png",
                "hist-samples-algorithm2.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
