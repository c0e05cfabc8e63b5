"""Per-op timings of the ResNet stem's CPU formulations against the plain Flax/lax ops.

Shapes of the default detector (batch 8, 160x720, trunk width 32): the stem conv 7x7/2
(3 -> 32 channels) forward + weight gradient, and the 3x3/2 max-pool over its 80x360x32
output forward + input gradient, and the stem's train-mode BatchNorm + ReLU over the conv
output (Flax's ``nn.BatchNorm`` + ``nn.relu`` with autodiff vs
:mod:`gac_jax.models.batch_norm`) forward + gradients wrt input, scale and bias. Plain and
shipped formulations are called alternately;
medians of wall and process-CPU milliseconds (CPU time is the steadier figure on a shared
machine). Also checks that both give the same values/gradients (for BN + ReLU the printed
maximum is dominated by the few of the 7.4M pre-activations within float32 rounding of 0,
where the ReLU mask of either formulation may flip; tests/test_batch_norm.py checks both
against float64).

    python benchmarks/bench_stem_ops.py [--repeats 7] [--batch 8]
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
import jax.numpy as jnp  # noqa: E402
from flax import linen as nn  # noqa: E402
from jax import lax  # noqa: E402
from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.models import stride2_conv  # noqa: E402
from gac_jax.models.batch_norm import batch_norm_train  # noqa: E402
from gac_jax.models.max_pool import max_pool  # noqa: E402

DN = ("NHWC", "HWIO", "NHWC")
PAD3, PAD1 = ((3, 3), (3, 3)), ((1, 1), (1, 1))


def _vjp_fn(f, wrt: int):
    def run(*args):
        y, vjp = jax.vjp(lambda a: f(*args[:wrt], a, *args[wrt + 1 :]), args[wrt])
        return vjp(jnp.cos(y))[0]

    return jax.jit(run)


def _bn_relu_flax(x, scale, bias):
    """Flax's train-mode BatchNorm (one-pass fast variance) + ReLU, autodiff backward."""
    bn = nn.BatchNorm(use_running_average=False, momentum=0.9, epsilon=1e-5)
    y, _ = bn.apply({"params": {"scale": scale, "bias": bias},
                     "batch_stats": {"mean": jnp.zeros_like(scale), "var": jnp.ones_like(scale)}},
                    x, mutable=["batch_stats"])  # fmt: skip
    return nn.relu(y)


def _bn_grads_fn(f):
    """jit of: BN(+ReLU) forward and the gradients wrt input, scale and bias."""

    def run(x, scale, bias):
        y, vjp = jax.vjp(f, x, scale, bias)
        return vjp(jnp.cos(y))

    return jax.jit(run)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args()
    b = args.batch
    images = jax.random.normal(jax.random.key(0), (b, 160, 720, 3))
    kernel = 0.1 * jax.random.normal(jax.random.key(1), (7, 7, 3, 32))
    feats = jax.nn.relu(jax.random.normal(jax.random.key(2), (b, 80, 360, 32)))
    conv_out = 0.5 + 2.0 * jax.random.normal(jax.random.key(3), (b, 80, 360, 32))

    def conv_plain(x, k):
        return lax.conv_general_dilated(x, k, (2, 2), PAD3, dimension_numbers=DN)

    def conv_s2d(x, k):
        return stride2_conv.conv_general_dilated(x, k, (2, 2), PAD3, dimension_numbers=DN)

    cases = {
        "stem conv fwd": (jax.jit(conv_plain), jax.jit(conv_s2d), (images, kernel)),
        "stem conv fwd+weight grad": (
            _vjp_fn(conv_plain, 1), _vjp_fn(conv_s2d, 1), (images, kernel)),
        "max-pool fwd+input grad": (
            _vjp_fn(lambda x: nn.max_pool(x, (3, 3), (2, 2), PAD1), 0),
            _vjp_fn(lambda x: max_pool(x, (3, 3), (2, 2), PAD1), 0),
            (feats,),
        ),
        "BN+ReLU fwd+grads (x,s,b)": (
            _bn_grads_fn(_bn_relu_flax),
            _bn_grads_fn(lambda x, s, b: batch_norm_train(x, s, b, 1e-5, relu=True)[0]),
            (conv_out, 1.0 + 0.1 * jnp.arange(32.0), 0.01 * jnp.arange(32.0)),
        ),
    }  # fmt: skip
    times = {(name, impl): [] for name in cases for impl in ("plain", "shipped")}
    for name, (plain, shipped, a) in cases.items():
        y0, y1 = plain(*a), shipped(*a)  # compile + check
        err = max(
            float(jnp.max(jnp.abs(u - v)) / (jnp.max(jnp.abs(u)) + 1e-30))
            for u, v in zip(jax.tree.leaves(y0), jax.tree.leaves(y1), strict=True)
        )
        print(f"{name}: max |plain - shipped| / max |plain| = {err:.2e}")
    for _ in range(args.repeats):
        for name, (plain, shipped, a) in cases.items():
            for impl, f in (("plain", plain), ("shipped", shipped)):
                t0, c0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(f(*a))
                times[name, impl].append((time.perf_counter() - t0, time.process_time() - c0))
    machine = describe_machine("numpy", "jax")
    print(f"machine: {one_line(machine)}")
    print(f"batch {b}, medians of {args.repeats}: wall ms (process CPU ms)")
    rows = []
    for name in cases:
        med = {
            impl: [1000 * statistics.median(t[i] for t in times[name, impl]) for i in (0, 1)]
            for impl in ("plain", "shipped")
        }
        rows.append({"op": name, **{f"{k}_ms": [round(v, 1) for v in med[k]] for k in med}})
        p, s = med["plain"], med["shipped"]
        print(f"  {name:30s} plain {p[0]:7.1f} ({p[1]:6.1f})   shipped {s[0]:7.1f} ({s[1]:6.1f})")
    print(json.dumps({"machine": machine, "rows": rows}))


if __name__ == "__main__":
    main()
