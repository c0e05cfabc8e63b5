"""bfloat16 training (``train.compute_dtype``) of both tasks: what runs in bfloat16, what stays
float32, and checkpoints that resume across the two.

Tiny configs on the vendored real KITTI frames (as tests/test_train_detect3d.py and
tests/test_train_depth.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from test_train_depth import tiny_config  # tests/ is on sys.path under pytest
from test_train_detect3d import tiny_overrides

from gac_jax.builders import depth as depth_builders
from gac_jax.builders import detect3d as detect_builders
from gac_jax.config import ConfigError, apply_overrides, load_config
from gac_jax.data.loader import DetectionArrays, Loader
from gac_jax.data.sources import open_object_source
from gac_jax.detection.anchor_priors import make_detection_constants
from gac_jax.detection.anchors import generate_anchors
from gac_jax.trainers import depth, detect3d
from gac_jax.training import multiprocess, parallel
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.training.compute_dtype import compute_dtype, training_model
from gac_jax.training.train_state import TrainState, make_optimizer

REPO = Path(__file__).resolve().parents[1]


def detect_config(root: Path, *overrides: str):
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(config, [*tiny_overrides(root), *overrides])
    return config


def sub_jaxprs(value):
    """The jaxprs inside an equation parameter (pjit, custom_vjp, scan, cond branches)."""
    if hasattr(value, "eqns"):
        yield value
    elif hasattr(value, "jaxpr") and hasattr(value.jaxpr, "eqns"):
        yield value.jaxpr
    elif isinstance(value, list | tuple):
        for v in value:
            yield from sub_jaxprs(v)


def equations(jaxpr):
    for eqn in jaxpr.eqns:
        yield eqn
        for value in eqn.params.values():
            for sub in sub_jaxprs(value):
                yield from equations(sub)


def conv_operand_dtypes(step, state, batch) -> list[tuple[str, str]]:
    """(lhs, rhs) dtypes of every convolution in the train step's jaxpr (forward and
    backward)."""
    closed = jax.make_jaxpr(step)(state, batch)
    return [
        (str(e.invars[0].aval.dtype), str(e.invars[1].aval.dtype))
        for e in equations(closed.jaxpr)
        if e.primitive.name == "conv_general_dilated"
    ]


def float_dtypes(tree) -> set[str]:
    return {str(x.dtype) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)}


def abstract_state(init, tx, mesh):
    """The train state's shapes and dtypes (nothing compiled or computed) and its sharding."""
    variables = jax.eval_shape(init)
    state = jax.eval_shape(
        lambda v: TrainState.create(v["params"], v["batch_stats"], tx, 0), variables
    )
    return state, jax.tree.map(lambda _: parallel.replicated(mesh), state)


def detection_step(config, tmp_path):
    layout = detect_builders.anchor_layout(config)
    priors = detect_builders.compute_priors(config, Path(config.data.root), layout, tmp_path)
    constants = make_detection_constants(
        generate_anchors(layout), priors, detect_builders.sign_axis(config)
    )
    model = detect_builders.build_model(config, layout.anchors_per_cell)
    tx = make_optimizer(lambda s: 1e-3, 1.0)
    mesh = parallel.make_mesh(jax.devices()[:1])
    state, sharding = abstract_state(
        lambda: detect_builders.init_variables(model, config, 0), tx, mesh
    )
    step = detect3d.make_train_step(
        training_model(model, config),
        tx,
        constants,
        detect_builders.loss_config(config),
        config,
        mesh,
        sharding,
    )
    source = open_object_source(config.data.root, "labeled")
    arrays = DetectionArrays(("Car",), config.data.max_objects, True)
    loader = Loader(source, detect_builders.train_transform(config), arrays, batch_size=2)
    batch = parallel.to_global(loader.load_batch(0), mesh)
    return step, state, batch


def depth_step(config):
    model = depth_builders.build_model(config, 2.5)
    tx = make_optimizer(lambda s: 1e-3, 1.0)
    mesh = parallel.make_mesh(jax.devices()[:1])
    state, sharding = abstract_state(
        lambda: depth_builders.init_variables(model, config, 0), tx, mesh
    )
    step = depth.make_train_step(
        training_model(model, config), tx, depth_builders.loss_options(config), mesh, sharding
    )
    source = depth_builders.train_source(config, depth_builders.depth_root(config.data))
    loader = depth.make_train_loader(config, source, 2, mesh)
    batch = parallel.to_global(loader.load_batch(0), mesh)
    return step, state, batch


@pytest.mark.parametrize("task", ["detect3d", "depth"])
def test_bfloat16_step_convolves_in_bfloat16_and_keeps_float32_state(task, kitti_samples, tmp_path):
    """Every convolution of the train step (forward and backward) takes bfloat16 operands;
    parameters, optimizer state, BatchNorm statistics and the loss stay float32. The same
    step in float32 convolves in float32 (so the check can fail)."""
    for name, expected in (("bfloat16", "bfloat16"), ("float32", "float32")):
        overrides = (f"train.compute_dtype={name}",)
        if task == "detect3d":
            config = detect_config(kitti_samples / "object", *overrides)
            step, state, batch = detection_step(config, tmp_path)
        else:
            config = tiny_config(kitti_samples / "depth", *overrides)
            step, state, batch = depth_step(config)
        convs = conv_operand_dtypes(step, state, batch)
        assert len(convs) > 20, convs  # ResNet forward + both backward convolutions
        assert set(convs) == {(expected, expected)}, (name, sorted(set(convs)))
        new_state, metrics = jax.eval_shape(step, state, batch)
        assert float_dtypes(new_state.params) == {"float32"}
        assert float_dtypes(new_state.opt_state) == {"float32"}
        assert float_dtypes(new_state.batch_stats) == {"float32"}
        assert new_state.batch_stats, "the models have BatchNorm statistics"
        assert metrics["loss"].dtype == jnp.float32


def test_compute_dtype_names_the_key_when_wrong(kitti_samples):
    config = detect_config(kitti_samples / "object", "train.compute_dtype=float16")
    with pytest.raises(ConfigError, match="train.compute_dtype: 'float16' is not one of"):
        compute_dtype(config)
    assert compute_dtype(detect_config(kitti_samples / "object")) == jnp.float32


def stop_at(module, monkeypatch, step: int | None) -> None:
    """The run stops after ``step`` as after SIGTERM (checkpoint, PreemptedError)."""
    monkeypatch.setattr(module.stopping, "preemption_requested", lambda s: s == step)


def train_losses(workdir: Path) -> dict[int, float]:
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in records if r["kind"] == "train"}


def restored_dtypes(workdir: Path, step: int) -> set[str]:
    with Checkpoints(workdir) as ckpts:
        raw = ckpts._manager.restore(step)  # noqa: SLF001 - raw restore without a template
    state = dict(raw["state"])
    return float_dtypes({k: state[k] for k in ("params", "opt_state", "batch_stats")})


@pytest.mark.parametrize("task", ["detect3d", "depth"])
def test_bfloat16_run_trains_and_resumes_in_float32_and_back(
    task, kitti_samples, tmp_path, monkeypatch, capsys
):
    """bfloat16 steps 1-2 (checkpoint), float32 step 3 resumed from it (checkpoint), bfloat16
    to the end resumed from that: one history, float32 checkpoints, the loss falls."""
    if task == "detect3d":  # one batch of all 4 frames, unaugmented: the same input each step
        module, last = detect3d, 6
        make = lambda *o: detect_config(  # noqa: E731
            kitti_samples / "object",
            *("data.batch_size=4", "data.flip_prob=0.0", "data.photometric=False"),
            *(f"train.num_steps={last}", "train.eval_at_end=False"),
            *o,
        )
    else:  # one batch (both views of the frame) per step
        module, last = depth, 4
        make = lambda *o: tiny_config(kitti_samples / "depth", "train.eval_at_end=False", *o)  # noqa: E731
    workdir = tmp_path / "run"
    for dtype, stop in (("bfloat16", 2), ("float32", 3), ("bfloat16", None)):
        stop_at(module, monkeypatch, stop)
        config = make(f"train.compute_dtype={dtype}")
        if stop is None:
            module.train_and_evaluate(config, workdir)
        else:
            with pytest.raises(multiprocess.PreemptedError):
                module.train_and_evaluate(config, workdir)
        with Checkpoints(workdir) as ckpts:
            assert ckpts.latest_step() == (stop or last)
        assert restored_dtypes(workdir, stop or last) == {"float32"}
    out = capsys.readouterr().out
    assert "resumed from" in out and "at step 2" in out and "at step 3" in out
    assert out.count("compiling the train step ...") == 3
    assert out.count("train step memory per device: ") == 3
    losses = train_losses(workdir)
    assert sorted(losses) == list(range(1, last + 1))  # one history across the dtypes
    # It learns: the detector's loss on its one batch falls at every step, in either dtype
    # (slowly: lr 4e-4, gradients clipped to norm 1); the depth net's falls faster.
    if task == "detect3d":
        assert all(losses[s + 1] < losses[s] for s in range(1, last)), losses
        assert losses[last] < 0.99 * losses[1], losses
    else:
        assert losses[last] < 0.9 * losses[1], losses
