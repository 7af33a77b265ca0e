"""Models out through the API (``download_model``, ModelService.DownloadModel): a trained reward's
weights load with safetensors into the PyTorch reference net (relreward_dev.reward_nets) and give
the server's Score to 1e-5; the sync and asyncio clients write the same checked files; failures
leave nothing behind."""

from __future__ import annotations

import asyncio
import hashlib
import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import relreward
from relreward_dev.reward_nets import build


def test_downloaded_reward_loads_into_pytorch_and_matches_score(client, tiny, tmp_path):
    got = client.download_model(tiny.reward, tmp_path / "rw")
    record = client.get_model(tiny.reward)
    assert got.model == record
    assert got.path == tmp_path / "rw" / "weights.safetensors" and got.files == (got.path,)
    data = got.path.read_bytes()
    assert (hashlib.sha256(data).hexdigest(), len(data)) == (record.sha256, record.size_bytes)
    assert json.loads((tmp_path / "rw" / "manifest.json").read_text()) == got.manifest
    assert sorted(p.name for p in (tmp_path / "rw").iterdir()) == ["manifest.json", "weights.safetensors"]

    # The manifest rebuilds the net: architecture and its sizes, the item layout, T.
    man = got.manifest
    assert man["architecture"] == {"kind": "windowed_mlp", "window": 4, "hidden": [16, 16]}
    space = man["space"]
    shape = [space["horizon"], space["action_dim"] + space["obs_dim"]]
    assert shape == [tiny.horizon, tiny.transition_dim] and man["n_timesteps"] == tiny.n_timesteps
    net = build(man["architecture"], shape)
    net.load_state_dict(load_file(got.path), strict=True)
    net.eval()

    # rho takes normalized inputs: Score in normalized units is the net's forward.
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.0, 1.0, (6, *shape)).astype(np.float32)
    t = np.arange(6) % tiny.n_timesteps
    served = client.score(tiny.reward, x, t, units="normalized").rewards
    with torch.no_grad():
        ours = net(torch.from_numpy(x), torch.from_numpy(t).long()).numpy()
    np.testing.assert_allclose(ours, served, rtol=1e-5, atol=1e-5)


def test_async_download_writes_the_same_files(client, tiny, tmp_path):
    sync = client.download_model(tiny.base, tmp_path / "sync")

    async def fetch():
        async with relreward.AsyncClient(client.endpoint) as ac:
            return await ac.download_model(tiny.base, tmp_path / "async")

    got = asyncio.run(fetch())
    assert got.model == sync.model and got.manifest == sync.manifest
    assert got.path.read_bytes() == sync.path.read_bytes()
    assert got.model.kind == "diffusion"
    assert got.manifest["architecture"]["kind"] == "temporal_unet"


def test_download_refusals_leave_nothing_behind(client, tiny, tmp_path):
    with pytest.raises(relreward.NotFound, match="no-such-model"):
        client.download_model("no-such-model", tmp_path / "none")
    assert not (tmp_path / "none").exists()
    with pytest.raises(relreward.InvalidArgument) as refused:
        client.download_model("Not A Name", tmp_path / "bad")
    assert refused.value.message.startswith("name:"), refused.value.message

    out = tmp_path / "rw"
    out.mkdir()
    (out / "weights.safetensors").write_bytes(b"mine")
    with pytest.raises(FileExistsError, match="weights.safetensors"):
        client.download_model(tiny.reward, out)
    assert sorted(p.name for p in out.iterdir()) == ["weights.safetensors"]
    assert (out / "weights.safetensors").read_bytes() == b"mine"
    got = client.download_model(tiny.reward, out, overwrite=True)
    assert hashlib.sha256(got.path.read_bytes()).hexdigest() == got.model.sha256
