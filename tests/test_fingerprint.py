"""The weights' identity (gac_jax.trained.fingerprint): equal contents, equal hash; any
changed value, name, shape or dtype, another; independent of dict order and array placement."""

from __future__ import annotations

import hashlib

import jax.numpy as jnp
import numpy as np

from gac_jax.trained.fingerprint import short, weights_sha256


def tree(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "params": {"conv": {"kernel": rng.standard_normal((3, 3, 2, 4)).astype(np.float32)}},
        "batch_stats": {"bn": {"mean": np.arange(4, dtype=np.float32)}},
    }


def test_hash_is_the_contents_not_the_container():
    a = tree()
    reordered = {"batch_stats": a["batch_stats"], "params": a["params"]}
    on_device = {"params": {"conv": {"kernel": jnp.asarray(a["params"]["conv"]["kernel"])}}}
    on_device["batch_stats"] = a["batch_stats"]
    fortran = {"params": {"conv": {"kernel": np.asfortranarray(a["params"]["conv"]["kernel"])}}}
    fortran["batch_stats"] = a["batch_stats"]
    assert weights_sha256(a) == weights_sha256(reordered) == weights_sha256(on_device)
    assert weights_sha256(a) == weights_sha256(fortran)
    # an independent computation of the documented definition
    digest = hashlib.sha256()
    for name, arr in (
        ("batch_stats/bn/mean", a["batch_stats"]["bn"]["mean"]),
        ("params/conv/kernel", a["params"]["conv"]["kernel"]),
    ):
        digest.update(f"{name}\0<f4\0{arr.shape}\0".encode() + arr.tobytes())
    assert weights_sha256(a) == digest.hexdigest()
    assert short(weights_sha256(a)) == digest.hexdigest()[:12] and short(None) == "none"


def test_any_change_gives_another_hash():
    base = weights_sha256(tree())
    one_value = tree()
    one_value["params"]["conv"]["kernel"][0, 0, 0, 0] += 1e-6
    renamed = tree()
    renamed["params"]["conv2"] = renamed["params"].pop("conv")
    reshaped = tree()
    reshaped["batch_stats"]["bn"]["mean"] = reshaped["batch_stats"]["bn"]["mean"].reshape(2, 2)
    recast = tree()
    recast["batch_stats"]["bn"]["mean"] = recast["batch_stats"]["bn"]["mean"].astype(np.float64)
    others = [weights_sha256(t) for t in (one_value, renamed, reshaped, recast, tree(seed=1))]
    assert len({base, *others}) == 6
