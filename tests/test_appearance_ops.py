"""The config keys of the pixel-only training augmentations (``data.cast_shadows``,
``data.random_convolution``): off by default, in the training chain only when set, never in
evaluation, and a share out of range is one line before any work."""

from __future__ import annotations

import ml_collections
import pytest

from gac_jax.builders import depth as depth_builder
from gac_jax.builders import detect3d as detect3d_builder
from gac_jax.config import REPO_CONFIGS, ConfigError, load_config
from gac_jax.data import cast_shadows, random_convolution
from gac_jax.data.cast_shadows import CastShadows
from gac_jax.data.random_convolution import RandomConvolution

KEYS = [
    ("cast_shadows", cast_shadows, CastShadows),
    ("random_convolution", random_convolution, RandomConvolution),
]


@pytest.mark.parametrize(("key", "module", "cls"), KEYS)
def test_config_key_builds_the_transform_only_when_set(key, module, cls):
    assert module.from_config(ml_collections.ConfigDict({})) is None
    assert module.from_config(ml_collections.ConfigDict({key: 0.0})) is None
    assert module.from_config(ml_collections.ConfigDict({key: 0.4})).p == 0.4
    with pytest.raises(ConfigError):
        module.from_config(ml_collections.ConfigDict({key: -0.1}))
    for builder, name in (
        (depth_builder, "depth_default.py"),
        (detect3d_builder, "detect3d_default.py"),
    ):
        config = load_config(str(REPO_CONFIGS / name))
        assert config.data[key] == 0.0
        assert not any(isinstance(op, cls) for op in builder.train_transform(config).transforms)
        config.data[key] = 0.5
        ops = builder.train_transform(config).transforms
        assert [op.p for op in ops if isinstance(op, cls)] == [0.5]
        assert not any(isinstance(op, cls) for op in builder.eval_transform(config).transforms)


def test_the_order_of_the_pixel_augmentations():
    config = load_config(str(REPO_CONFIGS / "detect3d_default.py"))
    config.data.cast_shadows = 0.5
    config.data.random_convolution = 0.5
    names = [type(op).__name__ for op in detect3d_builder.train_transform(config).transforms]
    order = ["CastShadows", "CameraEffects", "RandomConvolution", "PhotometricDistort"]
    assert [n for n in names if n in order] == order


@pytest.mark.parametrize("task", ["detect3d", "depth"])
@pytest.mark.parametrize("key", ["cast_shadows", "random_convolution"])
def test_a_share_out_of_range_is_one_line_before_any_work(task, key, tmp_path, capsys):
    import train

    workdir = tmp_path / "run"
    args = ["--task", task, "--config", f"configs/{task}_default.py:tiny"]
    code = train._run(train.parse_args([*args, "--workdir", str(workdir), f"data.{key}=1.5"]))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err == [f"error: data.{key}=1.5: the share of training images must be in [0, 1]"]
    # nothing generated, configured or trained first (the run folder's lock and log only)
    assert not (workdir / "config.json").exists() and not (workdir / "checkpoints").exists()
