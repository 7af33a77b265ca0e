"""The safe latent diffusion experiment (experiments/images/safe_latent.py, `make images-safe`,
issue 37) end to end in its tiny configuration: the autoencoder, the class-conditional latent
DDPM, Algorithm 2 from two recipes of it, every report and picture. Nothing is expected to
separate at this size; the test checks that every stage ran and reported."""

from __future__ import annotations

import json
import subprocess
import sys

from conftest import REPO


def test_the_tiny_safe_latent_experiment_runs_every_stage(tmp_path):
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, str(REPO / "experiments/images/safe_latent.py"), "--tiny", "--out", str(out),
                        "--unsafe", "1,7"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, f"safe_latent.py failed:\n{p.stdout}\n{p.stderr}"
    s = json.loads((out / "summary.json").read_text())
    assert s["unsafe"] == [1, 7] and set(s["unsafe"]) <= set(s["prompt_set"]) and len(s["prompt_set"]) >= 3
    assert set(s["unsafe_fraction"]) == {"base", "expert", "base_guided"}
    for key in ("samples", "real_heldout"):
        assert 0.0 <= s[key]["balanced_accuracy"] <= 1.0 and 0.0 <= s[key]["auc"] <= 1.0
    assert 0.0 <= s["samples"]["cap"] <= 1.0
    assert s["pictures"]["batches"] >= 1
    assert set(s["job_seconds"]) == {"ddpm", "algorithm2"}
    for png in ("extremes.png", "hist-samples.png", "hist-real.png"):
        assert (out / png).stat().st_size > 0
