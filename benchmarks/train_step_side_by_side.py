"""Side-by-side train-step timing for ``bench_train_step.py --compare`` (see its docstring).

Implementations, timed round-robin in one process so that machine load hits all alike:

* ``jax-plain``: the trainer's step traced under :func:`gac_jax.models.resnet.plain_formulation`
  (Flax's ``nn.max_pool`` etc.: what the code did before the CPU backward-pass work);
* ``jax``: the trainer's step as shipped;
* ``torch``: the PyTorch twin ``GroundAwareYolo3D`` of ``tests/torch_reference_models.py``
  (same layers and parameter count), train mode, with a loss of comparable cost (sigmoid
  focal loss over all anchors + smooth-L1 on the positives' 12 regression targets), AdamW
  and gradient clipping. The depth U-Net has no PyTorch twin (its DCNv2 decoder and
  ground-aware conv would need one); it is timed for the two JAX variants only.

Phases: ``forward`` (train-mode forward, batch statistics), ``fwd+bwd`` (value and gradient of
the loss w.r.t. the parameters), ``step`` (the full optimizer step); ``backward`` is
``fwd+bwd - forward``. Each figure is the median over rounds of wall seconds and of process
CPU seconds (all threads; steadier on a shared machine).
"""

from __future__ import annotations

import contextlib
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

REPO = Path(__file__).resolve().parents[1]
PHASES = ("forward", "fwd+bwd", "step")


def _jax_detector(case: dict, plain: bool) -> dict:
    from gac_jax.builders import detect3d as builders
    from gac_jax.detection.anchor_filter import ground_mask_from_constants
    from gac_jax.detection.detection_loss import detection_loss
    from gac_jax.models.resnet import plain_formulation
    from gac_jax.trainers import detect3d

    c, model, constants, batch = case["config"], case["model"], case["constants"], case["batch"]
    loss_cfg, fopts = builders.loss_config(c), detect3d.filter_options(c)
    key = jax.random.key(0)

    def forward(params, batch_stats, batch):  # the batch is an argument: no constant folding
        return model.apply(
            {"params": params, "batch_stats": batch_stats},
            batch["image"],
            batch["P2"],
            train=True,
            rngs={"dropout": key},
            mutable=["batch_stats"],
        )

    def loss_fn(params, batch_stats, batch):
        outputs, _ = forward(params, batch_stats, batch)
        mask = ground_mask_from_constants(constants, batch["P2"], **fopts)
        mask = mask if c.anchors.filter else None
        return detection_loss(outputs, batch, constants, mask, loss_cfg)[0]

    step = detect3d.make_train_step(
        model, case["tx"], constants, loss_cfg, c, case["mesh"], case["state_sharding"]
    )
    state = jax.tree.map(lambda x: x.copy(), case["state"])
    p, bs = state.params, state.batch_stats
    with plain_formulation() if plain else contextlib.nullcontext():
        fwd = jax.jit(forward).lower(p, bs, batch).compile()
        grad = jax.jit(jax.value_and_grad(loss_fn)).lower(p, bs, batch).compile()
        step = step.lower(state, batch).compile()
    return _timed_calls(fwd, grad, step, state, p, bs, batch)


def _jax_depth(plain: bool, batch_size: int = 8) -> dict:
    from bench_depth import inputs  # benchmarks/ is on sys.path

    from gac_jax.builders import depth as depth_builders
    from gac_jax.config import load_config
    from gac_jax.depth.depth_loss import depth_loss
    from gac_jax.models.resnet import plain_formulation
    from gac_jax.trainers import depth
    from gac_jax.trainers.common import create_train_state
    from gac_jax.training import parallel
    from gac_jax.training.train_state import learning_rate_schedule, make_optimizer

    config = load_config(str(REPO / "configs" / "depth_default.py"))
    model = depth_builders.build_model(config, prior_mean=2.6)
    variables = depth_builders.init_variables(model, config, 0)
    mesh = parallel.make_mesh(jax.devices()[:1])
    tx = make_optimizer(
        learning_rate_schedule(1e-4, 1e-5, 1000, 100),
        config.train.clip_norm,
        config.train.weight_decay,
    )
    state, sharding = create_train_state(jax.tree.map(np.asarray, variables), tx, 0, mesh)
    opts = depth_builders.loss_options(config)
    step = depth.make_train_step(model, tx, opts, mesh, sharding)
    images, P, gt = inputs(config, batch_size, config.data.width, seed=batch_size)
    batch = parallel.to_global({"image": images, "P2": P, "depth": gt}, mesh)

    def forward(params, batch_stats, batch):
        return model.apply(
            {"params": params, "batch_stats": batch_stats},
            batch["image"],
            batch["P2"],
            train=True,
            mutable=["batch_stats"],
        )

    def loss_fn(params, batch_stats, batch):
        outputs, _ = forward(params, batch_stats, batch)
        return depth_loss(outputs["log_depth"], batch["depth"], batch["image"], **opts)[0]

    p, bs = state.params, state.batch_stats
    with plain_formulation() if plain else contextlib.nullcontext():
        fwd = jax.jit(forward).lower(p, bs, batch).compile()
        grad = jax.jit(jax.value_and_grad(loss_fn)).lower(p, bs, batch).compile()
        step = step.lower(state, batch).compile()
    return {
        **_timed_calls(fwd, grad, step, state, p, bs, batch),
        "input": f"{batch_size}x{config.data.height}x{config.data.width}",
    }


def _torch_detector(case: dict) -> dict:
    import torch
    from torch.nn import functional as F  # noqa: N812

    sys.path.insert(0, str(REPO / "tests"))
    from torch_reference_models import GroundAwareYolo3D

    c, batch = case["config"], case["batch"]
    num_classes = len(c.data.classes)
    num_anchors = case["num_anchors"]
    torch.manual_seed(0)
    net = GroundAwareYolo3D(
        depth=c.model.backbone_depth,
        width=c.model.backbone_width,
        num_classes=num_classes,
        num_anchors=num_anchors,
        cls=c.model.cls_features,
        reg=c.model.reg_features,
    ).train()
    images = torch.from_numpy(np.array(batch["image"])).permute(0, 3, 1, 2).contiguous()
    P2 = torch.from_numpy(np.array(batch["P2"]))
    with torch.no_grad():
        cls, reg = net(images, P2)
    gen = torch.Generator().manual_seed(0)
    positive = torch.rand(cls.shape[:2], generator=gen) < 0.002
    cls_target = torch.zeros(cls.shape[:2] + (num_classes,))
    cls_target[positive] = 1.0
    reg_target = torch.randn(reg.shape, generator=gen)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=0.01)

    def loss_fn():
        cls, reg = net(images, P2)
        logits = cls[..., :num_classes]
        p = torch.sigmoid(logits)
        ce = F.binary_cross_entropy_with_logits(logits, cls_target, reduction="none")
        pt = torch.where(cls_target > 0, p, 1 - p)
        focal = (ce * (1 - pt) ** 2).sum() / positive.sum().clamp(min=1)
        box = F.smooth_l1_loss(reg[positive], reg_target[positive])
        return focal + box

    def fwd_bwd():
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        return loss

    def step():
        loss = fwd_bwd()
        torch.nn.utils.clip_grad_norm_(net.parameters(), c.train.clip_norm)
        opt.step()
        return loss

    return {
        "forward": lambda: net(images, P2),
        "fwd+bwd": fwd_bwd,
        "step": step,
        "params": int(sum(t.numel() for t in net.parameters())),
        "threads": torch.get_num_threads(),
        "version": torch.__version__,
    }


def _timed(fn) -> tuple[float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0, time.process_time() - c0


def compare(networks: list[str], rounds: int, with_torch: bool) -> dict:
    """Times every (network, implementation, phase) round-robin; prints and returns the table."""
    from detector_case import CONFIGS, build_detector_case
    from machine_info import describe_machine, one_line

    impls: dict[tuple[str, str], dict] = {}
    notes = []
    if "detector" in networks:
        case = build_detector_case(CONFIGS["default"], 8)
        impls["detector", "jax-plain"] = _jax_detector(case, plain=True)
        impls["detector", "jax"] = _jax_detector(case, plain=False)
        if with_torch:
            try:
                impls["detector", "torch"] = _torch_detector(case)
            except ImportError as exc:
                notes.append(f"PyTorch side skipped: torch is not installed ({exc}); "
                             "install the optional extra: pip install '.[torch]'")  # fmt: skip
    if "depth" in networks:
        impls["depth", "jax-plain"] = _jax_depth(plain=True)
        impls["depth", "jax"] = _jax_depth(plain=False)
    for fns in impls.values():  # warm-up: first calls allocate
        for phase in PHASES:
            _timed(fns[phase])
    times = {(k, phase): [] for k in impls for phase in PHASES}
    for _ in range(rounds):
        for k, fns in impls.items():
            for phase in PHASES:
                times[k, phase].append(_timed(fns[phase]))
    machine = describe_machine("numpy", "jax")
    rows = []
    for (net, impl), fns in impls.items():
        wall = {ph: statistics.median(t[0] for t in times[(net, impl), ph]) for ph in PHASES}
        cpu = {ph: statistics.median(t[1] for t in times[(net, impl), ph]) for ph in PHASES}
        rows.append(
            {
                "network": net,
                "impl": impl + (f" {fns['version']}/{fns['threads']}t" if "version" in fns else ""),
                "params": fns["params"],
                **{f"{ph}_ms": round(1000 * wall[ph], 1) for ph in PHASES},
                "backward_ms": round(1000 * (wall["fwd+bwd"] - wall["forward"]), 1),
                **{f"{ph}_cpu_ms": round(1000 * cpu[ph], 1) for ph in PHASES},
                "images_per_s": round(8 / wall["step"], 2),
            }
        )  # fmt: skip
    print(f"machine: {one_line(machine)}")
    print(f"rounds: {rounds}, batch 8, medians; wall ms (process CPU ms)")
    header = "network   impl                      params     forward    backward    step"
    print(header)
    for r in rows:
        cells = [
            f"{r['forward_ms']:7.0f} ({r['forward_cpu_ms']:5.0f})",
            f"{r['backward_ms']:7.0f}",
            f"{r['step_ms']:7.0f} ({r['step_cpu_ms']:5.0f})",
        ]
        print(f"{r['network']:9s} {r['impl'][:25]:25s} {r['params']:9d}  " + "  ".join(cells))
    by = {(r["network"], r["impl"].split()[0]): r for r in rows}
    for net in ("detector", "depth"):
        if (net, "jax") in by and (net, "jax-plain") in by:
            ratio = by[net, "jax"]["step_ms"] / by[net, "jax-plain"]["step_ms"]
            print(f"{net}: step jax / jax-plain = {ratio:.3f}")
    if ("detector", "torch") in by:
        for ph in PHASES:
            ratio = by["detector", "jax"][f"{ph}_ms"] / by["detector", "torch"][f"{ph}_ms"]
            print(f"detector: {ph} jax / torch eager = {ratio:.3f}")
    for note in notes:
        print(note)
    return {"machine": machine, "rounds": rounds, "rows": rows, "notes": notes}


def _timed_calls(fwd, grad, step, state, p, bs, batch) -> dict:
    """The three timed calls of one JAX network (the step donates its state: a copy is kept)."""
    holder = {"state": jax.tree.map(lambda x: x.copy(), state)}

    def run_step():
        holder["state"], metrics = step(holder["state"], batch)
        return metrics["loss"]

    return {
        "forward": lambda: fwd(p, bs, batch),
        "fwd+bwd": lambda: grad(p, bs, batch),
        "step": run_step,
        "params": int(sum(x.size for x in jax.tree.leaves(p))),
    }
