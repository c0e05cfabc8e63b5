"""Train-step time, jit compile time and peak memory of the detection trainer.

    python benchmarks/bench_train_step.py                      # paper + default configs
    python benchmarks/bench_train_step.py --configs default --batch-sizes 8 --steps 10

Each (config, batch size) runs in its own subprocess so that peak resident
memory (``ru_maxrss``) belongs to that case alone. Inputs are random images
with real-looking calibration and random ground truth; the step is the
trainer's own jitted step (``gac_jax.trainers.detect3d.make_train_step``).
Reports the median step time over ``--steps`` steps after the compile step, and the line the
trainer prints after compiling: what XLA's compiled step needs per device (arguments,
outputs, temporaries) next to what the device has. ``--compute-dtype bfloat16`` measures the
``train.compute_dtype=bfloat16`` step; ``--steps 0`` compiles only (the memory line)::

    python benchmarks/bench_train_step.py --configs paper --batch-sizes 8 --steps 0 \
        --compute-dtype bfloat16      # on a GPU: the need on that GPU, before a real run
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from detector_case import CONFIGS, build_detector_case  # benchmarks/ is on sys.path
from machine_info import describe_machine

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

# Measure what train.py / evaluate.py run with (GAC_JAX_DEFAULT_XLA_FLAGS=0: JAX's own).
apply_default_xla_flags()


def run_case(config_spec: str, batch_size: int, steps: int, compute_dtype: str) -> dict:
    import resource
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from gac_jax.training.step_memory import StepMemory, memory_line

    case = build_detector_case(config_spec, batch_size, compute_dtype)
    c, state, batch, step = case["config"], case["state"], case["batch"], case["step"]
    h, w, init_s = c.data.height, c.data.width, case["init_s"]
    t0 = time.perf_counter()
    compiled = step.lower(state, batch).compile()
    compile_s = time.perf_counter() - t0
    memory = StepMemory.of(compiled)
    print(memory_line(memory), file=sys.stderr, flush=True)
    times = []
    for _ in range(steps + 1 if steps else 0):
        t0 = time.perf_counter()
        state, metrics = compiled(state, batch)
        jax.block_until_ready(metrics["loss"])
        times.append(time.perf_counter() - t0)
    times = times[1:] or [float("nan")]  # the first call also transfers/allocates
    n_params = sum(x.size for x in jax.tree.leaves(state.params))
    return {
        "config": config_spec,
        "input": f"{h}x{w}",
        "backbone": f"ResNet-{c.model.backbone_depth}",
        "params": int(n_params),
        "batch_size": batch_size,
        "compute_dtype": compute_dtype,
        "init_s": round(init_s, 2),
        "compile_s": round(compile_s, 2),
        "step_s_median": round(float(np.median(times)), 4),
        "step_s_all": [round(t, 4) for t in times],
        "images_per_s": round(batch_size / float(np.median(times)), 2),
        "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "loss_finite": bool(jnp.isfinite(metrics["loss"])) if steps else None,
        "memory_per_device": memory.as_record() if memory else None,
        "memory_line": memory_line(memory),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--configs", default="paper,default")
    parser.add_argument(
        "--batch-sizes", default="", help="comma list (default: 8 and the config's)"
    )
    parser.add_argument("--steps", type=int, default=3, help="timed steps (0: compile only)")
    parser.add_argument("--compute-dtype", default="float32", choices=("float32", "bfloat16"))
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # internal: run one case
    args = parser.parse_args()
    if args.case:
        spec, bs = args.case.rsplit("@", 1)
        print(json.dumps(run_case(spec, int(bs), args.steps, args.compute_dtype)))
        return
    from gac_jax.config import load_config

    results = []
    for name in args.configs.split(","):
        spec = CONFIGS.get(name, name)
        sizes = [int(b) for b in args.batch_sizes.split(",") if b] or sorted(
            {8, load_config(spec).data.batch_size}
        )
        for bs in sizes:
            cmd = [sys.executable, __file__, "--case", f"{spec}@{bs}", "--steps", str(args.steps)]
            cmd += ["--compute-dtype", args.compute_dtype]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
                result = {"config": spec, "batch_size": bs, "error": tail[0]}
            else:
                result = json.loads(proc.stdout.strip().splitlines()[-1])
            results.append(result)
            print(json.dumps(result), flush=True)
    report = {"machine": describe_machine("numpy", "jax"), "results": results}
    print(json.dumps(report["machine"]))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
