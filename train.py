"""Train a GAC model.

    python train.py --task detect3d      # default: generated dataset, 26-45 min on 2 CPU cores
    python train.py --task detect3d --config configs/detect3d_kitti.py --workdir runs/gac
    python train.py --task depth
    python train.py --task detect3d train.num_steps=200 data.batch_size=4   # overrides

Multi-host: add ``--coordinator HOST:PORT --num-processes N --process-id I`` on every host
(or set GAC_COORDINATOR, GAC_NUM_PROCESSES, GAC_PROCESS_ID; ``--coordinator auto`` detects
SLURM / Open MPI). See docs/multihost.md.

SIGTERM or Ctrl-C (SIGINT): the run finishes its current step, saves a checkpoint, prints
"stopped at step N, checkpoint saved; run the same command to resume" and exits with 75;
a second Ctrl-C stops at once (130, no checkpoint). One run per workdir: a second train.py (or
evaluate.py) on a workdir in use stops at once, naming the process that holds it (exit 2). A
full disk ends the run with one line naming the file, the free space and the checkpoint kept
(exit 1; library details in WORKDIR/details.log); run again, with space, to resume. Out of
device memory: one line with what the step needs, naming data.batch_size (exit 1). Exit
codes: 0 done, 1 crash or disk failure, 2 bad config or data or workdir in use, 3 another
process died or hung, 75 stopped after a checkpoint (run again to resume).
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback

if __name__ == "__mp_main__":  # a worker (or fork server) of this trainer: never outlive it
    from gac_jax.data.worker_lifetime import guard_spawned_child

    guard_spawned_child()

DEFAULT_CONFIGS = {"detect3d": "configs/detect3d_default.py", "depth": "configs/depth_default.py"}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--task", required=True, choices=sorted(DEFAULT_CONFIGS))
    parser.add_argument("--config", help="config file[:arg] (default: the task's default config)")
    parser.add_argument(
        "--workdir",
        help="output folder; a run there is resumed (default: workdirs/<task>_<config>)",
    )
    parser.add_argument("--coordinator", help="multi-process: HOST:PORT of process 0")
    parser.add_argument(
        "--num-processes", type=int, help="multi-process: total number of processes"
    )
    parser.add_argument("--process-id", type=int, help="multi-process: index of this process")
    parser.add_argument(
        "--heartbeat-timeout",
        type=int,
        help="multi-process: seconds without heartbeats before a process counts as dead (100)",
    )
    parser.add_argument(
        "--step-timeout",
        type=float,
        help="multi-process: seconds without a completed training step (compilation and "
        "checkpoint saves included) before a process stops, assuming a peer hung (900)",
    )
    parser.add_argument(
        "--wait-timeout",
        type=float,
        help="multi-process: seconds the other processes wait for process 0's evaluation, "
        "dataset generation, anchor priors or depth prior mean (7200)",
    )
    parser.add_argument("overrides", nargs="*", help="config overrides, key.sub=value")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    from gac_jax.data.worker_lifetime import mark_owner

    mark_owner()  # helper processes (loader, generator workers) exit when this process dies
    from gac_jax.cpu_backend import apply_default_xla_flags

    apply_default_xla_flags()  # before JAX starts its backend
    from gac_jax.data.io_errors import EXIT_DISK_FAILURE, DiskWriteError
    from gac_jax.training import multiprocess, stopping, workdir_lock

    try:
        multi = multiprocess.initialize_distributed(
            args.coordinator,
            args.num_processes,
            args.process_id,
            heartbeat_timeout=args.heartbeat_timeout,
            step_timeout=args.step_timeout,
            wait_timeout=args.wait_timeout,
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stopping.install_stop_handlers()
    leave_at_once = multi  # on failure (see below)
    try:
        code = _run(args)
    except DiskWriteError as e:  # one line; the library noise went to the details file
        print(f"error: {e}", file=sys.stderr)
        code = EXIT_DISK_FAILURE
        leave_at_once = True  # a normal exit has the failed save's tasks log at shutdown
    except multiprocess.PeerLostError as e:
        if multi:  # one line, even if a watcher thread reports the same loss meanwhile
            multiprocess.exit_once(f"error: {e}", multiprocess.EXIT_PEER_LOST)
        print(f"error: {e}", file=sys.stderr)
        code = multiprocess.EXIT_PEER_LOST
    except multiprocess.PreemptedError as e:
        print(e, flush=True)
        code = multiprocess.EXIT_PREEMPTED
    except BaseException:
        if not multi:
            raise
        traceback.print_exc()
        code = 1
    if leave_at_once and code not in (0, multiprocess.EXIT_PREEMPTED):
        # Failed: leave at once. A normal exit would wait in JAX's shutdown barrier
        # for peers that may be dead or stuck in a collective with this process.
        sys.stdout.flush()
        sys.stderr.flush()
        workdir_lock.release_all()
        os._exit(code)
    return code


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from gac_jax.config import ConfigError, apply_overrides, load_config, resolve_config_path
    from gac_jax.data.files import KittiFormatError
    from gac_jax.data.io_errors import error_line
    from gac_jax.training.step_memory import DeviceMemoryError
    from gac_jax.training.workdir_lock import LockUnsupportedError, WorkdirBusyError

    spec = args.config or DEFAULT_CONFIGS[args.task]
    try:
        config = load_config(spec)
        apply_overrides(config, args.overrides)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    workdir = args.workdir or str(
        Path("workdirs") / f"{args.task}_{resolve_config_path(spec)[0].stem}"
    )
    _print_devices()
    try:
        if args.task == "detect3d":
            from gac_jax.trainers import detect3d

            detect3d.train_and_evaluate(config, workdir)
        else:
            from gac_jax.trainers import depth

            depth.train_and_evaluate(config, workdir)
    except (ConfigError, KittiFormatError, WorkdirBusyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except DeviceMemoryError as e:  # one line; XLA's text is in WORKDIR/details.log
        print(f"error: {e}", file=sys.stderr)
        return 1
    except (FileNotFoundError, PermissionError, LockUnsupportedError) as e:
        print(f"error: {error_line(e, workdir)}", file=sys.stderr)
        return 2
    return 0


def _print_devices() -> None:
    """One start-up line naming JAX's backend and devices (e.g. ``gpu: 1 x NVIDIA H200``)."""
    import jax

    devices = jax.devices()
    if jax.process_index() == 0:
        kinds = sorted({d.device_kind for d in devices})
        print(
            f"JAX {jax.__version__}, backend {jax.default_backend()}: {len(devices)} device(s) "
            f"({', '.join(kinds)}) in {jax.process_count()} process(es)",
            flush=True,
        )


if __name__ == "__main__":
    sys.exit(main())
