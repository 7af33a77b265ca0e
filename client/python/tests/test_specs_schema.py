"""The Python specs follow the Rust schema (issue 33: one schema per concept).

``proto/schema.json`` is generated from the Rust types of ``relreward_proto::schema`` (a Rust test
keeps it current). Here the Python package's typed specs are checked against it: the same field
names for every job kind and for the optimisation settings, the same architecture kinds with the
same field names, and the same spellings of the enumerations, so a field added or renamed on the
Rust side fails this test until ``relreward/specs.py`` follows.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
from google.protobuf import json_format

from conftest import REPO
from relreward import specs

SCHEMA = json.loads((REPO / "proto" / "schema.json").read_text())
COMMON = {"output_model", "seed", "optimization"}


def names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_optimization_fields_are_the_schemas():
    assert names(specs.Optimization) == set(SCHEMA["optimization"]["fields"])


def test_diffusion_job_fields_are_the_schemas():
    assert names(specs.DiffusionJob) - COMMON == set(SCHEMA["diffusion"]["fields"])


def test_reward_job_fields_are_the_schemas():
    # Python spells the algorithm as its two inputs: datasets (Algorithm 1) or num_chains (2).
    python = names(specs.RewardJob) - COMMON - {"datasets", "num_chains"} | {"algorithm"}
    assert python == set(SCHEMA["reward"]["fields"])


def test_discriminator_job_fields_are_the_schemas():
    assert names(specs.DiscriminatorJob) - COMMON == set(SCHEMA["discriminator"]["fields"])


@pytest.mark.parametrize("kind", sorted(SCHEMA["reward_architectures"]))
def test_reward_architectures_have_the_schemas_names(kind):
    """Each kind with the schema's default fields builds the message carrying exactly them."""
    fields = dict(SCHEMA["reward_architectures"][kind])
    assert fields.pop("kind") == kind
    message = specs._reward_arch((kind, fields))
    assert json_format.MessageToDict(message, preserving_proto_field_name=True) == {kind: fields}


@pytest.mark.parametrize("kind", sorted(SCHEMA["denoiser_architectures"]))
def test_denoiser_architectures_have_the_schemas_names(kind):
    fields = dict(SCHEMA["denoiser_architectures"][kind])
    assert fields.pop("kind") == kind
    message = specs._denoiser_architecture(kind, fields)
    assert json_format.MessageToDict(message, preserving_proto_field_name=True) == fields


def test_a_manifest_with_the_schemas_fields_converts_whole():
    defaults = SCHEMA["diffusion"]["defaults"]
    m = {
        "parametrization": defaults["parametrization"],
        "n_timesteps": defaults["n_timesteps"],
        "clip_denoised": defaults["clip_denoised"],
        "schedule": defaults["schedule"],
        "space": {"kind": "trajectory", "horizon": defaults["horizon"], "action_dim": 2, "obs_dim": 4},
        "normalizer": {"kind": "identity"},
        "architecture": defaults["architecture"],
        "conditioning": {"kind": "labels", "num_classes": 11, "null_class": 10},
    }
    assert set(m) == set(SCHEMA["manifest"]["fields"])
    message = specs.manifest(m)
    for field in ("schedule", "normalizer"):
        assert message.HasField(field)
    assert message.WhichOneof("space") == "trajectory" and message.WhichOneof("architecture") == "temporal_unet"
    assert message.temporal_unet.dim == defaults["architecture"]["dim"]
    assert message.schedule.diffuser_cosine.s == pytest.approx(defaults["schedule"]["s"])


def test_enumeration_spellings_are_the_schemas():
    reward = SCHEMA["reward"]["defaults"]
    spec = specs.RewardJob("r", "b", "e", datasets=["d"], target=reward["target"], eval_point=reward["eval_point"])
    message = spec.to_proto().reward
    assert (message.target, message.eval_point) == (1, 1), "mean and x_t, the first value of each enumeration"
    for target in ("mean", "score"):
        specs.RewardJob("r", "b", "e", datasets=["d"], target=target).to_proto()
    diffusion = specs.DiffusionJob("m", "d", parametrization=SCHEMA["diffusion"]["defaults"]["parametrization"])
    assert diffusion.to_proto().diffusion.parametrization == 2
    for schedule in SCHEMA["schedules"]:
        arg = {"kind": "betas", "betas": [0.1]} if schedule == "betas" else schedule
        assert specs._schedule(arg).WhichOneof("kind") == schedule
