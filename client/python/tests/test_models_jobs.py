"""Models (list/show/delete, TorchScript upload) and jobs (submit, watch with live loss,
resume after a restart, cancel)."""

from __future__ import annotations

import dataclasses
import socket
import threading
import time
import warnings

import numpy as np
import pytest

import relreward
from conftest import start_server, tiny_trajectories


def test_models_list_show(client, tiny):
    names = {m.name for m in client.list_models()}
    assert {tiny.base, tiny.expert, tiny.reward} <= names
    assert {m.name for m in client.list_models("reward")} >= {tiny.reward}
    assert tiny.reward not in {m.name for m in client.list_models("diffusion")}
    rw = client.get_model(tiny.reward)
    assert rw.reward.input_shape == rw.item_shape == (tiny.horizon, tiny.transition_dim)
    assert rw.reward.n_timesteps == rw.n_timesteps == tiny.n_timesteps and rw.reward.window == 4
    with pytest.raises(relreward.NotFound):
        client.get_model("nope")


def test_torchscript_upload_with_a_manifest(client, tmp_path):
    torch = pytest.importorskip("torch")

    class Eps(torch.nn.Module):
        def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return 0.1 * x

    path = tmp_path / "eps.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.script(Eps()).save(str(path))
    manifest = {"parametrization": "epsilon", "n_timesteps": 10, "schedule": {"kind": "cosine"},
                "space": {"kind": "sample", "shape": [3]}, "normalizer": {"kind": "identity"}}
    seen = []
    m = client.upload_model(path, "py-ts", manifest, description="scripted", chunk_bytes=512,
                            progress=lambda s, t: seen.append(s))
    import hashlib

    assert m.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert m.format == "torchscript" and m.manifest.n_timesteps == 10 and m.item_shape == (3,)
    assert seen[-1] == path.stat().st_size
    out = client.sample("py-ts", n=2, seed=0)
    assert out.x.shape == (2, 3)
    with pytest.raises(relreward.InvalidArgument):
        client.upload_model(path, "py-ts-bad", dict(manifest, space={"kind": "sample", "shape": []}))
    client.delete_model("py-ts")
    with pytest.raises(relreward.NotFound):
        client.get_model("py-ts")


def test_submit_watch_with_live_loss_and_idempotent_ids(client, tiny):
    spec = relreward.DiffusionJob(output_model="py-diff", dataset=tiny.dataset, seed=4, horizon=8, n_timesteps=10,
                                  architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
                                  optimization=relreward.Optimization(steps=12, batch_size=8, log_every=4))
    job = client.submit_job(spec, job_id="py-diff-job")
    assert client.submit_job(spec, job_id="py-diff-job").id == job.id  # same spec: the same job
    with pytest.raises(relreward.AlreadyExists):
        client.submit_job(relreward.DiffusionJob(output_model="other", dataset=tiny.dataset), job_id="py-diff-job")
    events = list(client.watch_job(job.id))
    seqs = [e.seq for e in events]
    assert seqs == list(range(1, len(seqs) + 1))
    progress = [e for e in events if e.type == "progress"]
    assert progress and all(np.isfinite(e.loss) and e.total_steps == 12 for e in progress)
    assert events[-1].terminal and events[-1].state == "succeeded"
    # from_seq replays from there
    assert [e.seq for e in client.watch_job(job.id, from_seq=3)] == seqs[2:]
    assert client.get_job(job.id).state is relreward.JobState.SUCCEEDED
    assert job.id in {j.id for j in client.list_jobs("succeeded")}
    with pytest.raises(relreward.FailedPrecondition):
        client.cancel_job(job.id)


def test_dict_specs_reward_job_and_cancel(client, tiny):
    job = client.submit_job({"output_model": "py-long", "seed": 1,
                             "optimization": {"steps": 100000, "batch_size": 8, "log_every": 1},
                             "diffusion": {"dataset": tiny.dataset, "horizon": 8, "n_timesteps": 10,
                                           "temporal_unet": {"dim": 8, "dim_mults": [1, 2]}}})
    cancelled = None
    for event in client.watch_job(job.id):
        if event.type == "progress" and cancelled is None:
            cancelled = client.cancel_job(job.id)
            assert cancelled.id == job.id
        last = event
    assert last.state == relreward.JobState.CANCELLED
    r = client.submit_job(relreward.RewardJob(output_model="py-rw", base_model=tiny.base, expert_model=tiny.expert,
                                              datasets=[tiny.dataset], seed=2,
                                              architecture=("windowed_mlp", {"window": 4, "hidden": [8]}),
                                              optimization=relreward.Optimization(steps=4, batch_size=8)))
    done = client.wait_job(r.id)
    assert done.state is relreward.JobState.SUCCEEDED
    assert client.get_model("py-rw").reward.window == 4
    with pytest.raises(relreward.NotFound):
        client.submit_job(relreward.DiscriminatorJob(output_model="py-d", base_dataset="nope", expert_dataset="nope",
                                                     diffusion_model=tiny.base))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_watch_resumes_after_a_server_restart(tmp_path):
    """The server is killed mid-job and restarted on the same port and data: the watch goes on
    and yields every event exactly once, in order, up to the terminal state."""
    port = free_port()
    listen = f"127.0.0.1:{port}"
    data = tmp_path / "data"
    s1 = start_server(data, listen=listen)
    client = relreward.Client(listen)
    client.upload_dataset("d", tiny_trajectories())
    job = client.submit_job(relreward.DiffusionJob(
        output_model="m", dataset="d", horizon=8, n_timesteps=10, seed=1,
        architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
        optimization=relreward.Optimization(steps=300, batch_size=8, log_every=5, checkpoint_every=20)))
    events = []
    servers = [s1]
    for event in client.watch_job(job.id):
        events.append(event)
        if len(servers) == 1 and event.type == "checkpoint":
            s1.stop()  # SIGKILL mid-job
            threading.Timer(1.0, lambda: servers.append(start_server(data, listen=listen))).start()
    try:
        assert len(servers) == 2, "the server was restarted"
        seqs = [e.seq for e in events]
        assert seqs == list(range(1, len(seqs) + 1)), seqs
        assert events[-1].state == "succeeded"
    finally:
        client.close()
        for s in servers:
            s.stop()


def test_reads_are_retried_until_the_server_comes_writes_are_not(tmp_path):
    port = free_port()
    listen = f"127.0.0.1:{port}"
    with relreward.Client(listen) as client:
        started = time.monotonic()
        with pytest.raises(relreward.Unavailable):
            client.delete_dataset("x")  # a write: one attempt
        assert time.monotonic() - started < 1.0
        box = []
        threading.Timer(0.6, lambda: box.append(start_server(tmp_path / "data", listen=listen))).start()
        try:
            started = time.monotonic()
            assert client.list_datasets() == []  # a read: retried while the server starts
            assert 0.5 < time.monotonic() - started < 5.5
        finally:
            time.sleep(0.1)
            for s in box:
                s.stop()


def test_async_upload_submit_and_watch(server, tiny):
    import asyncio

    async def main():
        async with relreward.AsyncClient(server.addr) as ac:
            ds = await ac.upload_dataset("py-async", tiny_trajectories(seed=9), chunk_bytes=200)
            job = await ac.submit_job(relreward.DiffusionJob(
                output_model="py-async-m", dataset=ds.name, horizon=8, n_timesteps=10, seed=1,
                architecture=("temporal_unet", {"dim": 8, "dim_mults": [1, 2]}),
                optimization=relreward.Optimization(steps=8, batch_size=8, log_every=4)))
            events = [e async for e in ac.watch_job(job.id)]
            return ds, events, await ac.list_jobs()

    ds, events, jobs = asyncio.run(main())
    assert ds.num_rows == 112 and ds.episodes.count == 5
    assert [e.seq for e in events] == list(range(1, len(events) + 1)) and events[-1].state == "succeeded"
    assert any(e.type == "progress" and e.loss > 0 for e in events)


def test_progress_true_uses_tqdm_when_installed(client):
    ds = client.upload_dataset("py-progress", np.zeros((8, 3), np.float32), progress=True)
    assert ds.num_rows == 8


def test_discriminator_job(client, tiny):
    client.upload_dataset("py-disc-expert", tiny_trajectories(seed=11))
    job = client.submit_job(relreward.DiscriminatorJob(
        output_model="py-disc", base_dataset=tiny.dataset, expert_dataset="py-disc-expert", diffusion_model=tiny.base,
        architecture=("windowed_mlp", {"window": 4, "hidden": [8]}), seed=1,
        optimization=relreward.Optimization(steps=4, batch_size=8)))
    assert client.wait_job(job.id).state == "succeeded"
    assert client.get_model("py-disc").kind == "discriminator"
    x = np.zeros((2, tiny.horizon, tiny.transition_dim), np.float32)
    assert client.score("py-disc", x).rewards.shape == (2,)


def test_native_weights_upload_round_trips_a_trained_model(client, tiny, tmp_path):
    """A trained native model's own weights file (downloaded), uploaded as native weights with
    the manifest GetModel returns (which names the architecture), is the same model: same
    digest, same samples for the same seed. Needs no models.allow_torchscript_upload (weights
    are data)."""
    import hashlib

    base = client.get_model(tiny.base)
    assert base.format == "native"
    assert base.manifest.architecture is not None, "a native model's manifest names its architecture"
    got = client.download_model(tiny.base, tmp_path / "base")
    files = [got.path]
    assert hashlib.sha256(got.path.read_bytes()).hexdigest() == base.sha256
    m = client.upload_model(files[0], "py-native", base.manifest, description="re-uploaded")
    assert m.format == "native" and m.sha256 == base.sha256
    assert m.parameter_count == base.parameter_count
    a, b = client.sample(tiny.base, n=3, seed=5), client.sample("py-native", n=3, seed=5)
    np.testing.assert_array_equal(a.x, b.x)
    # Weights that do not fit the architecture are refused, naming the field; nothing is kept.
    arch = dict(base.manifest.architecture)
    if arch["kind"] == "temporal_unet":
        arch["dim"] = arch["dim"] * 2 if arch["dim"] else 64
    else:
        arch["hidden"] = [arch["hidden"][0] + 8, *arch["hidden"][1:]]
    wrong = dataclasses.replace(base.manifest, architecture=arch)
    with pytest.raises(relreward.InvalidArgument, match="header.manifest.architecture"):
        client.upload_model(files[0], "py-native-bad", wrong)
    assert "py-native-bad" not in {x.name for x in client.list_models()}
    client.delete_model("py-native")
