"""Autoencoders (issue 37, item 3: a latent space): a TorchScript module exporting ``encode`` and
``decode``, uploaded with an AutoencoderUploadManifest (``Client.upload_autoencoder``, ``relreward
model upload --autoencoder``), and the RewardService's Encode and Decode (``Client.encode`` /
``decode``, ``relreward encode`` / ``decode``).

- a scripted conv autoencoder: Encode and Decode equal the module run in-process with diffusers'
  scaling ((encode(x) - shift) * scale, decode(z / scale + shift)) to 1e-5, in one request or in
  many small batches, from the sync and the asyncio client and the CLI; the model lists, gets,
  downloads (its module.pt as uploaded) and deletes like any other;
- a tiny randomly initialised diffusers ``AutoencoderKL``, traced as the documented recipe
  (encode: ``latent_dist.mean``; decode: ``.sample``) with its own ``scaling_factor``: the
  service's latents and images equal diffusers' own calls to 1e-5;
- hostile uploads (a method missing, a wrong output shape, NaN output, manifest shapes that do not
  fit the module, a bad manifest, TorchScript disabled) are refused naming the problem, nothing
  stored;
- bad Encode/Decode requests, through the client and through the raw stub (the server's own
  answers): unknown model NOT_FOUND, another kind FAILED_PRECONDITION, wrong shape, missing or
  non-finite tensors INVALID_ARGUMENT naming the field, an answer over the size limit
  RESOURCE_EXHAUSTED.
"""

from __future__ import annotations

import asyncio
import warnings

import grpc
import numpy as np
import pytest
import torch
from torch import nn

import relreward
from relreward.v1 import autoencoder_pb2, reward_pb2_grpc, tensor_pb2
from conftest import start_server

SCALE, SHIFT = 0.5, 0.125
IMAGE, LATENT = (1, 8, 8), (2, 4, 4)


class ConvAutoencoder(nn.Module):
    """[1, 8, 8] images <-> [2, 4, 4] latents: a strided convolution with tanh, and a transposed
    convolution back."""

    def __init__(self) -> None:
        super().__init__()
        self.enc = nn.Conv2d(1, 2, 3, stride=2, padding=1)
        self.dec = nn.ConvTranspose2d(2, 1, 4, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))

    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.enc(x))

    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.dec(z)


class Identity(nn.Module):
    """A diffusion model's denoiser (forward(x, t)), to ask Encode of the wrong kind of model."""

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x


class EncodeOnly(nn.Module):
    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.avg_pool2d(x, 2).repeat(1, 2, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x


class WrongLatent(ConvAutoencoder):
    """encode returns [B, 2, 2, 2], not the [B, 2, 4, 4] its manifest declares."""

    @torch.jit.export
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.avg_pool2d(torch.tanh(self.enc(x)), 2)


class NanDecode(ConvAutoencoder):
    @torch.jit.export
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.dec(z) * float("nan")


def script(module: nn.Module, path) -> str:
    torch.manual_seed(0)
    torch.jit.script(module.eval()).save(str(path))
    return str(path)


def manifest(**changes):
    m = {"image_shape": list(IMAGE), "latent_shape": list(LATENT), "scaling_factor": SCALE, "shift_factor": SHIFT}
    m.update(changes)
    return m


@pytest.fixture(scope="module")
def conv(client, tmp_path_factory):
    """The conv autoencoder, scripted and uploaded as ``ae-conv``: (model, module, file)."""
    path = script(ConvAutoencoder(), tmp_path_factory.mktemp("ae") / "conv.pt")
    model = client.upload_autoencoder(path, "ae-conv", manifest(), description="conv")
    return model, torch.jit.load(path), path


def images(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, *IMAGE))


def test_scripted_autoencoder_encodes_and_decodes_as_in_process(client, server, conv, tmp_path):
    model, module, path = conv
    assert (model.kind, model.format, model.description) == ("autoencoder", "torchscript", "conv")
    assert model.autoencoder == relreward.AutoencoderInfo(IMAGE, LATENT, SCALE, SHIFT)
    assert model.manifest is None and model.reward is None and model.item_shape is None
    assert model.parameter_count == sum(p.numel() for p in ConvAutoencoder().parameters())

    x = images(7)  # float64, sent as float32
    with torch.no_grad():
        x32 = torch.from_numpy(x.astype(np.float32))
        want_z = ((module.encode(x32) - SHIFT) * SCALE).numpy()
    z = client.encode("ae-conv", x)
    assert z.dtype == np.float32 and z.shape == (7, *LATENT)
    np.testing.assert_allclose(z, want_z, atol=1e-5, rtol=0)
    with torch.no_grad():
        want_x = module.decode(torch.from_numpy(z) / SCALE + SHIFT).numpy()
    back = client.decode("ae-conv", z)
    assert back.shape == (7, *IMAGE)
    np.testing.assert_allclose(back, want_x, atol=1e-5, rtol=0)

    # Small batches (two images or latents per request) answer the same, to the last bits that
    # a convolution's blocking by batch size changes.
    np.testing.assert_allclose(client.encode("ae-conv", x, max_batch_bytes=2 * 4 * 32), z, atol=1e-6, rtol=0)
    np.testing.assert_allclose(client.decode("ae-conv", z, max_batch_bytes=2 * 4 * 64), back, atol=1e-6, rtol=0)
    # The asyncio client runs the same plan.

    async def run_async():
        async with relreward.AsyncClient(server.addr) as ac:
            return await ac.encode("ae-conv", x), await ac.decode("ae-conv", z)

    az, ax = asyncio.run(run_async())
    np.testing.assert_array_equal(az, z)
    np.testing.assert_array_equal(ax, back)
    assert client.encode("ae-conv", np.zeros((0, *IMAGE))).shape == (0, *LATENT)

    # The CLI: an .npz of images (with labels) to latents and back; labels copied.
    labels = np.arange(7)
    np.savez(tmp_path / "images.npz", x=x.astype(np.float32), y=labels)
    out = server.cli_json("encode", "--model", "ae-conv", "--input", str(tmp_path / "images.npz"),
                          "--out", str(tmp_path / "latents.npz"), "--batch", "3")
    assert out["items"] == 7 and out["requests"] == 3 and out["copied"] == ["y"], out
    with np.load(tmp_path / "latents.npz") as f:
        np.testing.assert_allclose(f["x"], z, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(f["y"], labels)
    server.cli("decode", "--model", "ae-conv", "--input", str(tmp_path / "latents.npz"),
               "--out", str(tmp_path / "decoded.npz"), "--out-key", "images")
    with np.load(tmp_path / "decoded.npz") as f:
        np.testing.assert_allclose(f["images"], back, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(f["y"], labels)


def test_an_autoencoder_lists_gets_downloads_and_deletes_like_any_model(client, server, conv, tmp_path):
    model, _, path = conv
    assert "ae-conv" in [m.name for m in client.list_models("autoencoder")]
    assert "ae-conv" not in [m.name for m in client.list_models("diffusion")]
    assert client.get_model("ae-conv") == model
    shown = server.cli_json("model", "show", "ae-conv")
    assert shown["kind"] == "autoencoder" and shown["autoencoder"] == model.as_dict()["autoencoder"], shown
    assert model.as_dict() == {**shown, "created_at": model.as_dict()["created_at"]}
    got = client.download_model("ae-conv", tmp_path / "dl")
    assert got.path.name == "module.pt" and got.path.read_bytes() == open(path, "rb").read()
    assert got.manifest == {"image_shape": list(IMAGE), "latent_shape": list(LATENT), "scaling_factor": SCALE,
                            "shift_factor": SHIFT}
    with pytest.raises(relreward.FailedPrecondition, match="is an autoencoder"):
        client.export_model("ae-conv", tmp_path / "export")
    # A second copy, deleted: gone from the listing, and Encode then says NOT_FOUND.
    client.upload_autoencoder(path, "ae-conv-2", manifest())
    assert "ae-conv-2" in [m.name for m in client.list_models("autoencoder")]
    client.delete_model("ae-conv-2")
    assert "ae-conv-2" not in [m.name for m in client.list_models()]
    with pytest.raises(relreward.NotFound):
        client.encode("ae-conv-2", images(1))


def test_a_diffusers_autoencoder_kl_through_the_service_equals_diffusers(client, tmp_path):
    """The documented recipe for diffusers' AutoencoderKL: encode -> latent_dist.mean (the mean,
    not a sample, so Encode is deterministic), decode -> .sample, traced with both methods;
    the manifest carries the VAE's config.scaling_factor. A tiny random VAE (16x16 RGB, block
    widths 8 and 16, 4 latent channels: latents [4, 8, 8])."""
    from diffusers import AutoencoderKL

    torch.manual_seed(0)
    vae = AutoencoderKL(in_channels=3, out_channels=3, down_block_types=("DownEncoderBlock2D",) * 2,
                        up_block_types=("UpDecoderBlock2D",) * 2, block_out_channels=(8, 16), layers_per_block=1,
                        latent_channels=4, norm_num_groups=4, sample_size=16).eval()

    class Wrapped(nn.Module):
        def __init__(self, vae: AutoencoderKL) -> None:
            super().__init__()
            self.vae = vae

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.decode(self.encode(x))

        def encode(self, x: torch.Tensor) -> torch.Tensor:
            return self.vae.encode(x).latent_dist.mean

        def decode(self, z: torch.Tensor) -> torch.Tensor:
            return self.vae.decode(z).sample

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about diffusers' shape asserts
        traced = torch.jit.trace_module(Wrapped(vae).eval(), {"encode": (torch.randn(2, 3, 16, 16),),
                                                               "decode": (torch.randn(2, 4, 8, 8),)})
    path = tmp_path / "vae.pt"
    traced.save(str(path))
    scale = vae.config.scaling_factor
    model = client.upload_autoencoder(path, "ae-kl", {"image_shape": [3, 16, 16], "latent_shape": [4, 8, 8],
                                                      "scaling_factor": scale})
    assert model.autoencoder.scaling_factor == scale == 0.18215 and model.autoencoder.shift_factor == 0

    x = np.random.default_rng(1).uniform(-1, 1, (5, 3, 16, 16)).astype(np.float32)
    with torch.no_grad():
        want_z = vae.encode(torch.from_numpy(x)).latent_dist.mean * scale
    z = client.encode("ae-kl", x)
    np.testing.assert_allclose(z, want_z.numpy(), atol=1e-5, rtol=0)
    with torch.no_grad():
        want_x = vae.decode(torch.from_numpy(z) / scale).sample
    np.testing.assert_allclose(client.decode("ae-kl", z), want_x.numpy(), atol=1e-5, rtol=0)


def _stored(client) -> set[str]:
    return {m.name for m in client.list_models()}


def test_hostile_autoencoder_uploads_are_refused_by_name_and_leave_nothing(client, server, tmp_path):
    before = _stored(client)
    cases = [
        (script(EncodeOnly(), tmp_path / "encode_only.pt"), manifest(), "has no method `decode`"),
        (script(WrongLatent(), tmp_path / "wrong.pt"), manifest(),
         "encode(x) returned shape [2, 2, 2, 2] for input shape [2, 1, 8, 8]; header.autoencoder.latent_shape "
         "declares [2, 4, 4]"),
        (script(NanDecode(), tmp_path / "nan.pt"), manifest(), "decode(z) on zeros [2, 2, 4, 4] returned NaN"),
        # Manifest shapes the module does not fit: its encode raises on [2, 3, 8, 8].
        (script(ConvAutoencoder(), tmp_path / "conv.pt"), manifest(image_shape=[3, 8, 8]),
         "module: encode(x) on zeros [2, 3, 8, 8] raised"),
        (str(tmp_path / "conv.pt"), manifest(latent_shape=[2, 4, 5]), "header.autoencoder.latent_shape declares"),
        (str(tmp_path / "conv.pt"), manifest(scaling_factor=0.0), "header.autoencoder.scaling_factor: 0"),
        (str(tmp_path / "conv.pt"), manifest(shift_factor=float("inf")), "header.autoencoder.shift_factor"),
    ]
    for i, (path, m, says) in enumerate(cases):
        with pytest.raises(relreward.InvalidArgument) as e:
            client.upload_autoencoder(path, f"ae-bad-{i}", m)
        assert says in e.value.message, (i, e.value.message)
    # Refused by the client before anything is sent.
    with pytest.raises(relreward.InvalidInput, match="autoencoder manifest.latent_shape"):
        client.upload_autoencoder(tmp_path / "conv.pt", "ae-bad-x", manifest(latent_shape=[]))
    with pytest.raises(relreward.InvalidInput, match=r"unknown field\(s\) \['scale'\]"):
        client.upload_autoencoder(tmp_path / "conv.pt", "ae-bad-x", {**manifest(), "scale": 2})
    # The CLI refuses a bad manifest file before connecting, naming the field.
    (tmp_path / "bad.toml").write_text("image_shape = [1, 8, 8]\nlatent_shape = [2, 0, 4]\n")
    p = server.cli("model", "upload", str(tmp_path / "conv.pt"), "--name", "ae-bad-cli", "--autoencoder",
                   "--manifest", str(tmp_path / "bad.toml"), check=False)
    assert p.returncode != 0 and "latent_shape: [2, 0, 4] has a zero dimension" in p.stderr, p.stderr
    assert _stored(client) == before


def test_autoencoder_uploads_need_torchscript_enabled(tmp_path):
    path = script(ConvAutoencoder(), tmp_path / "conv.pt")
    s = start_server(tmp_path / "data")
    try:
        with relreward.Client(s.addr) as c:
            with pytest.raises(relreward.FailedPrecondition, match="allow_torchscript_upload"):
                c.upload_autoencoder(path, "ae", manifest())
            assert c.list_models() == []
    finally:
        s.stop()


def test_bad_encode_and_decode_requests_are_refused_naming_the_field(client, server, conv, tmp_path):
    denoiser = {"parametrization": "epsilon", "n_timesteps": 10, "schedule": {"kind": "cosine"},
                "space": {"kind": "sample", "shape": list(LATENT)}, "normalizer": {"kind": "identity"}}
    client.upload_model(script(Identity(), tmp_path / "identity.pt"), "ae-not", denoiser)
    # Through the client: what it checks itself, and what the server answers.
    with pytest.raises(relreward.NotFound, match="'ae-absent'"):
        client.encode("ae-absent", images(1))
    with pytest.raises(relreward.FailedPrecondition, match="not an autoencoder"):
        client.encode("ae-not", images(1))
    with pytest.raises(relreward.InvalidInput, match=r"images: shape \[2, 8, 8\] but autoencoder 'ae-conv' takes "
                                                     r"images of shape \[B, 1, 8, 8\]"):
        client.encode("ae-conv", np.zeros((2, 8, 8)))
    bad = images(3)
    bad[1, 0, 2, 2] = np.nan
    with pytest.raises(relreward.InvalidInput, match="images: value at flat index 82 is not a finite float32"):
        client.encode("ae-conv", bad)
    with pytest.raises(relreward.InvalidInput, match=r"latents: shape \[1, 1, 8, 8\]"):
        client.decode("ae-conv", images(1))

    # The server's own answers, through the raw stub (nothing checked on the client side).
    stub = reward_pb2_grpc.RewardServiceStub(grpc.insecure_channel(server.addr))

    def refused(call, request):
        with pytest.raises(grpc.RpcError) as e:
            call(request, timeout=30)
        return e.value.code(), e.value.details()

    def tensor(a) -> tensor_pb2.Tensor:
        return relreward._tensor.encode(a)

    Enc, Dec = autoencoder_pb2.EncodeRequest, autoencoder_pb2.DecodeRequest
    code, msg = refused(stub.Encode, Enc(model="ae-absent", images=tensor(images(1))))
    assert code == grpc.StatusCode.NOT_FOUND and "'ae-absent'" in msg, msg
    code, msg = refused(stub.Decode, Dec(model="ae-not", latents=tensor(np.zeros((1, *LATENT)))))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "is a diffusion model, not an autoencoder" in msg, msg
    code, msg = refused(stub.Encode, Enc(model="Bad Name", images=tensor(images(1))))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and msg.startswith("model:"), msg
    code, msg = refused(stub.Encode, Enc(model="ae-conv"))
    assert (code, msg) == (grpc.StatusCode.INVALID_ARGUMENT, "images: missing")
    code, msg = refused(stub.Encode, Enc(model="ae-conv", images=tensor(np.zeros((2, 1, 8, 9)))))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and msg == (
        "images: shape [2, 1, 8, 9] but autoencoder 'ae-conv' takes images of shape [B, 1, 8, 8] with B >= 1"), msg
    code, msg = refused(stub.Encode, Enc(model="ae-conv", images=tensor(np.zeros((0, 1, 8, 8)))))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "B >= 1" in msg, msg
    code, msg = refused(stub.Decode, Dec(model="ae-conv", latents=tensor(np.zeros((2, 1, 8, 8)))))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and msg.startswith("latents: shape [2, 1, 8, 8]"), msg
    z = np.zeros((2, *LATENT))
    z[1, 1, 3, 3] = np.inf
    code, msg = refused(stub.Decode, Dec(model="ae-conv", latents=tensor(z)))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and msg == "latents: value at flat index 63 is not finite (inf)", msg
    big = tensor_pb2.Tensor(shape=[1, *IMAGE], dtype=tensor_pb2.DTYPE_FLOAT64, data=np.full(64, 1e300).tobytes())
    code, msg = refused(stub.Encode, Enc(model="ae-conv", images=big))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "outside float32's range" in msg, msg
    ints = tensor_pb2.Tensor(shape=[1, *IMAGE], dtype=tensor_pb2.DTYPE_INT32, data=bytes(4 * 64))
    code, msg = refused(stub.Encode, Enc(model="ae-conv", images=ints))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "images: dtype is int32" in msg, msg


def test_an_answer_over_the_response_limit_is_refused_naming_the_limit(tmp_path):
    """A server whose responses are at most 64 KiB: decoding 100 latents into 100 images of
    [1, 8, 8] (25.6 KB) fits, 1000 (256 KB) does not, and the message says how many would."""
    path = script(ConvAutoencoder(), tmp_path / "conv.pt")
    s = start_server(tmp_path / "data", env={"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true",
                                             "RELREWARD__SERVER__MAX_RESPONSE_BYTES": str(64 << 10)})
    try:
        with relreward.Client(s.addr) as c:
            c.upload_autoencoder(path, "ae", manifest())
            assert c.decode("ae", np.zeros((100, *LATENT))).shape == (100, *IMAGE)
            stub = reward_pb2_grpc.RewardServiceStub(grpc.insecure_channel(s.addr))
            with pytest.raises(grpc.RpcError) as e:
                stub.Decode(autoencoder_pb2.DecodeRequest(
                    model="ae", latents=relreward._tensor.encode(np.zeros((1000, *LATENT)))), timeout=30)
            assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "server.max_response_bytes (65536); send at most 255 per call" in e.value.details(), \
                e.value.details()
            # The client splits to its own bound: small enough batches pass.
            assert c.decode("ae", np.zeros((1000, *LATENT)), max_batch_bytes=32 << 10).shape == (1000, *IMAGE)
    finally:
        s.stop()
