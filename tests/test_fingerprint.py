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


def test_int8_ir_identity_ignores_only_openvino_s_generated_names(tmp_path):
    """OpenVINO numbers the nodes it creates from a per-process counter: the same quantized
    network saved in two processes differs in those names only (seen: ``Constant_231582``
    vs ``Constant_719``), and must keep its identity; a changed attribute or weight must not."""
    from gac_jax.deploy.int8 import INT8_MODEL, INT8_WEIGHTS, ir_sha256

    def ir(folder, first: int, second: int, stride: str = "1,1", weights: bytes = b"\0\1"):
        folder.mkdir()
        (folder / INT8_MODEL).write_text(
            f'<layer id="3" name="Constant_{first}" type="Const"/>\n'
            f'<layer id="4" name="head/cls_out" type="Convolution" strides="{stride}"/>\n'
            f'<layer id="5" name="ShapeOf_{second}" type="ShapeOf"/>\n'
            f'<edge from-layer="Constant_{first}" to-layer="head/cls_out"/>\n'
        )
        (folder / INT8_WEIGHTS).write_bytes(weights)
        return ir_sha256(folder)

    a = ir(tmp_path / "a", 231582, 231595)
    assert a == ir(tmp_path / "b", 719, 732)
    assert a != ir(tmp_path / "d", 719, 732, stride="2,2")
    assert a != ir(tmp_path / "e", 719, 732, weights=b"\0\2")
