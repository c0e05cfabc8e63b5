"""Every convolution of the default detector, alone: XLA:CPU (as the model runs it) vs PyTorch.

Where is the rest of the train-step gap to PyTorch eager (``bench_train_step.py --compare``)?
This times each distinct convolution of the default detector (batch 8, 160x720, half-width
ResNet-18 to stride 16, GAC head with 128 features) on its own, forward and backward:

* JAX: ``jax.jit`` of the convolution as the model calls it (NHWC/HWIO; the stem via
  :mod:`gac_jax.models.stride2_conv`, the others ``lax.conv_general_dilated``), and of its
  VJP (input and weight gradients; the weight gradient alone for the stem, whose input
  needs none);
* PyTorch (the optional ``.[torch]`` extra, NCHW as its twin in
  ``tests/torch_reference_models.py`` runs): ``F.conv2d`` under ``no_grad``, and
  ``torch.autograd.grad`` of a retained graph (backward only, like the JAX VJP).

Calls alternate between the two, medians of wall milliseconds; "step share" multiplies by
how often the op occurs in the network. Isolated convolutions run on warm inputs; the last
line therefore also times a chain as the network runs it: four layer1 convolutions, each
followed by a ReLU, forward and forward + backward (gradients of a sum of squares wrt the
input and the four kernels). Prints the CPU and library versions.

    python benchmarks/bench_conv_ops.py [--repeats 9] [--no-torch] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

import jax  # noqa: E402
from jax import lax  # noqa: E402
from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.models import stride2_conv  # noqa: E402

BATCH = 8
# name, input (H, W, C), output channels, kernel, stride, occurrences in the default
# detector, whether the input needs a gradient
OPS = [
    ("stem 7x7/2", (160, 720, 3), 32, 7, 2, 1, False),
    ("layer1 3x3", (40, 180, 32), 32, 3, 1, 4, True),
    ("layer2 3x3/2", (40, 180, 32), 64, 3, 2, 1, True),
    ("layer2 1x1/2 shortcut", (40, 180, 32), 64, 1, 2, 1, True),
    ("layer2 3x3", (20, 90, 64), 64, 3, 1, 3, True),
    ("layer3 3x3/2", (20, 90, 64), 128, 3, 2, 1, True),
    ("layer3 1x1/2 shortcut", (20, 90, 64), 128, 1, 2, 1, True),
    ("layer3 + head 3x3 128", (10, 45, 128), 128, 3, 1, 7, True),
    ("head cls out 3x3", (10, 45, 128), 64, 3, 1, 1, True),
    ("head reg out 3x3", (10, 45, 128), 384, 3, 1, 1, True),
    ("GAC extract 1x1", (10, 45, 129), 128, 1, 1, 1, True),
]


def _jax_case(hwc, out, k, stride, needs_gx):
    pad = ((k // 2, k // 2), (k // 2, k // 2))

    # as resnet.py: the space-to-depth form for the stem only
    conv_fn = stride2_conv.conv_general_dilated if k == 7 else lax.conv_general_dilated

    def conv(x, w):
        return conv_fn(x, w, (stride, stride), pad, dimension_numbers=("NHWC", "HWIO", "NHWC"))

    x = jax.random.normal(jax.random.key(0), (BATCH, *hwc))
    w = 0.1 * jax.random.normal(jax.random.key(1), (k, k, hwc[2], out))
    dy = jax.random.normal(jax.random.key(2), jax.eval_shape(conv, x, w).shape)
    fwd = jax.jit(conv)
    if needs_gx:
        bwd = jax.jit(lambda x, w, dy: jax.vjp(conv, x, w)[1](dy))
    else:
        bwd = jax.jit(lambda x, w, dy: jax.vjp(lambda w: conv(x, w), w)[1](dy))
    return {
        "forward": lambda: jax.block_until_ready(fwd(x, w)),
        "backward": lambda: jax.block_until_ready(bwd(x, w, dy)),
    }


def _torch_case(torch, hwc, out, k, stride, needs_gx):
    F = torch.nn.functional
    h, w_, c = hwc
    x = torch.randn(BATCH, c, h, w_, requires_grad=needs_gx)
    w = (0.1 * torch.randn(out, c, k, k)).requires_grad_(True)
    y = F.conv2d(x, w, None, stride, k // 2)
    dy = torch.randn_like(y)
    inputs = (x, w) if needs_gx else (w,)

    def forward():
        with torch.no_grad():
            return F.conv2d(x, w, None, stride, k // 2)

    return {
        "forward": forward,
        "backward": lambda: torch.autograd.grad(y, inputs, dy, retain_graph=True),
    }


def _jax_chain(n=4, hwc=(40, 180, 32)):
    def net(kernels, x):
        for k in kernels:
            x = jax.nn.relu(
                lax.conv_general_dilated(
                    x, k, (1, 1), ((1, 1), (1, 1)), dimension_numbers=("NHWC", "HWIO", "NHWC")
                )
            )
        return (x * x).sum()

    x = jax.random.normal(jax.random.key(0), (BATCH, *hwc))
    ks = [0.08 * jax.random.normal(jax.random.key(i + 1), (3, 3, hwc[2], hwc[2])) for i in range(n)]
    fwd, grad = jax.jit(net), jax.jit(jax.grad(net, argnums=(0, 1)))
    return {
        "forward": lambda: jax.block_until_ready(fwd(ks, x)),
        "fwd+bwd": lambda: jax.block_until_ready(grad(ks, x)),
    }


def _torch_chain(torch, n=4, hwc=(40, 180, 32)):
    F = torch.nn.functional
    h, w, c = hwc
    x = torch.randn(BATCH, c, h, w, requires_grad=True)
    ks = [(0.08 * torch.randn(c, c, 3, 3)).requires_grad_(True) for _ in range(n)]

    def net():
        y = x
        for k in ks:
            y = F.relu(F.conv2d(y, k, None, 1, 1))
        return (y * y).sum()

    def forward():
        with torch.no_grad():
            return net()

    return {"forward": forward, "fwd+bwd": lambda: torch.autograd.grad(net(), [x, *ks])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--no-torch", action="store_true", help="JAX only")
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()
    torch = None
    if not args.no_torch:
        try:
            import torch  # its default thread count: one per core, as XLA:CPU uses
        except ImportError:
            print("torch is not installed (pip install -e '.[torch]'): JAX only")
    impls = ["jax"] + (["torch"] if torch is not None else [])
    cases = {}
    for name, hwc, out, k, stride, _, needs_gx in OPS:
        cases[name, "jax"] = _jax_case(hwc, out, k, stride, needs_gx)
        if torch is not None:
            cases[name, "torch"] = _torch_case(torch, hwc, out, k, stride, needs_gx)
    cases["chain", "jax"] = _jax_chain()
    if torch is not None:
        cases["chain", "torch"] = _torch_chain(torch)
    for fns in cases.values():  # compile / warm up
        for fn in fns.values():
            fn(), fn()
    times = {(key, phase): [] for key, fns in cases.items() for phase in fns}
    for _ in range(args.repeats):
        for key, fns in cases.items():
            for phase, fn in fns.items():
                t0 = time.perf_counter()
                fn()
                times[key, phase].append(1000 * (time.perf_counter() - t0))
    libs = ("numpy", "jax") + (("torch",) if torch is not None else ())
    machine = describe_machine(*libs)
    if torch is not None:
        machine["torch_threads"] = torch.get_num_threads()
    print(f"machine: {one_line(machine)}")
    print(f"batch {BATCH}, medians of {args.repeats} alternating calls, wall ms")
    head = f"{'convolution':24s} {'x':>2s}" + "".join(
        f" {impl + ' ' + phase:>15s}" for phase in ("forward", "backward") for impl in impls
    )
    print(head)
    rows, totals = [], {(i, p): 0.0 for i in impls for p in ("forward", "backward")}
    for name, _, _, _, _, count, _ in OPS:
        med = {
            (i, p): statistics.median(times[(name, i), p])
            for i in impls
            for p in ("forward", "backward")
        }
        for key, value in med.items():
            totals[key] += count * value
        rows.append({"op": name, "count": count, **{f"{i}_{p}_ms": round(v, 2)
                                                     for (i, p), v in med.items()}})  # fmt: skip
        cells = "".join(f" {med[i, p]:15.1f}" for p in ("forward", "backward") for i in impls)
        print(f"{name:24s} {count:2d}{cells}")
    cells = "".join(f" {totals[i, p]:15.0f}" for p in ("forward", "backward") for i in impls)
    print(f"{'step share (sum x count)':27s}{cells}")
    if torch is not None:
        for p in ("forward", "backward"):
            print(f"{p}: jax / torch = {totals['jax', p] / totals['torch', p]:.2f}")
    chain = {(i, p): statistics.median(times[("chain", i), p]) for i in impls
             for p in ("forward", "fwd+bwd")}  # fmt: skip
    print(
        "chain of 4 layer1 3x3 convolutions + ReLU: "
        + ", ".join(
            f"{i} forward {chain[i, 'forward']:.1f} fwd+bwd {chain[i, 'fwd+bwd']:.1f}"
            for i in impls
        )
    )
    result = {"machine": machine, "batch": BATCH, "rows": rows,
              "chain_ms": {f"{i}_{p}": round(v, 1) for (i, p), v in chain.items()},
              "totals_ms": {f"{i}_{p}": round(v, 1) for (i, p), v in totals.items()}}  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
