"""Tokens: Unauthenticated without one, PermissionDenied beyond its scope, accepted with it."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

import relreward
from conftest import SERVER_BIN, start_server


def make_token(scopes: str) -> tuple[str, str]:
    """(token, the `tokens = [...]` config line) from `relreward-server token create`."""
    out = subprocess.run([str(SERVER_BIN), "token", "create", "--scopes", scopes], capture_output=True, text=True,
                         check=True).stdout
    token = next(line.split(" ", 1)[1].strip() for line in out.splitlines() if line.startswith("token: "))
    line = next(line for line in out.splitlines() if line.startswith("tokens = "))
    return token, line


def test_tokens_and_scopes(tmp_path):
    token, line = make_token("read")
    config = tmp_path / "config.toml"
    config.write_text(f"[security]\n{line}\n")
    server = start_server(tmp_path / "data", args=["--config", str(config)])
    try:
        with relreward.Client(server.addr) as anonymous:
            with pytest.raises(relreward.Unauthenticated) as e:
                anonymous.list_datasets()
            assert "token" in e.value.message
        with relreward.Client(server.addr, token=token) as reader:
            assert reader.list_datasets() == []
            with pytest.raises(relreward.PermissionDenied):
                reader.upload_dataset("d", np.zeros((4, 2), np.float32))
        with relreward.Client(server.addr, token="rrt_not-a-real-token") as wrong:
            with pytest.raises(relreward.Unauthenticated):
                wrong.list_models()
    finally:
        server.stop()


def test_tls_settings_need_an_https_endpoint():
    with pytest.raises(ValueError, match="https://"):
        relreward.Client("http://127.0.0.1:1", tls=relreward.TLS(ca_cert=b"x"))
