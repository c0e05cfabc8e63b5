"""The depth network's ``'ground_plane'`` output prior: the road's log depth at every pixel,
against float64 formulas (level camera and a tilted plane), and the network's log depth =
that map + the head's residual at every output scale."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.models.depth_unet import DepthUNet, ground_log_depth, output_sizes
from tests.test_depth_unet import _P, IMAGE_SIZE, TINY, _images, random_variables


def test_level_plane_is_the_road_depth_of_each_row_capped_above_the_horizon():
    P = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.22], [0, 0, 1, 0.003]])
    out = np.asarray(ground_log_depth(jnp.asarray(P[None], jnp.float32), None, (375, 3), 1.0))
    v = np.arange(375, dtype=np.float64)
    # the ray through row v meets y = 1.65 (fy * EL + Ty) / (v - cy) metres ahead (P's Ty kept
    # as the GAC's disparity prior does)
    with np.errstate(divide="ignore"):
        z = np.where(v > 172.9, (721.5 * 1.65 + 0.22) / (v - 172.9), np.inf)
    want = np.log(np.minimum(z, 75.0))
    np.testing.assert_allclose(out[0], np.repeat(want[:, None], 3, axis=1), atol=2e-5)
    # a stride-4 map: rows 0-1 of P divided by 4, the same road
    quarter = np.asarray(ground_log_depth(jnp.asarray(P[None], jnp.float32), None, (94, 2), 4.0))
    v4 = np.arange(94, dtype=np.float64)
    with np.errstate(divide="ignore"):
        z4 = np.where(v4 > 172.9 / 4, (721.5 * 1.65 + 0.22) / 4 / (v4 - 172.9 / 4), np.inf)
    np.testing.assert_allclose(quarter[0, :, 0], np.log(np.minimum(z4, 75.0)), atol=2e-5)


def test_a_tilted_plane_gives_the_depth_where_each_pixel_ray_meets_it():
    K = np.array([[700.0, 0, 300], [0, 700, 100], [0, 0, 1]])
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    a, c = np.sin(0.03), np.sin(-0.02)  # rolled and pitched road, camera 1.5 m above it
    n = np.array([a, -np.sqrt(1 - a * a - c * c), c])
    plane = np.append(n, 1.5)
    out = np.asarray(
        ground_log_depth(
            jnp.asarray(P[None], jnp.float32),
            jnp.asarray(plane[None], jnp.float32),
            (200, 600),
            1.0,
        )
    )[0]
    u, v = np.meshgrid(np.arange(600.0), np.arange(200.0))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    down = -(rays @ n)  # n . X + d = 0  ->  z = d / (-n . r)
    with np.errstate(divide="ignore"):
        z = np.where(down > 0, 1.5 / down, np.inf)
    np.testing.assert_allclose(out, np.log(np.minimum(z, 75.0)), atol=5e-5)


def test_network_log_depth_is_the_map_plus_the_heads_residual():
    max_depth = 40.0  # (not the default 75 m: the cap is the one given)
    model = DepthUNet(
        **TINY, prior_mean=1.5, output_prior="ground_plane", prior_max_depth=max_depth
    )
    variables = random_variables(model, seed=0)
    images, P = jnp.asarray(_images(2, 1)), jnp.asarray(_P(2))
    out, state = jax.jit(
        lambda v, x, p: model.apply(
            v,
            x,
            p,
            train=False,
            capture_intermediates=lambda mdl, _: (mdl.name or "").startswith("out_scale_"),
        )  # fmt: skip
    )(variables, images, P)
    for scale, size in output_sizes(IMAGE_SIZE).items():
        head = np.asarray(state["intermediates"][f"out_{scale}"]["__call__"][0])[..., 0]
        stride = IMAGE_SIZE[0] / size[0]
        prior = np.asarray(ground_log_depth(P, None, size, stride, 1.65, max_depth))
        assert prior.max() == pytest.approx(np.log(max_depth))  # the sky rows
        assert prior.min() < np.log(max_depth) - 0.5  # the road rows
        np.testing.assert_allclose(out["log_depth"][scale], prior + head, rtol=1e-5, atol=1e-5)


def test_an_unknown_prior_is_refused():
    model = DepthUNet(**TINY, output_prior="median")
    with pytest.raises(ValueError, match="output_prior must be one of"):
        model.init(jax.random.key(0), jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), False)
