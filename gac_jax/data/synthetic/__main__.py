"""Command line: ``python -m gac_jax.data.synthetic --out DIR --num N --seed S``.

Writes (or completes) a synthetic KITTI-format dataset; see
:mod:`gac_jax.data.synthetic.writer` for the layout. With ``--sequences N
--frames-per-sequence F`` instead of ``--num``, writes N driving clips at 10 Hz in the
KITTI tracking layout (:mod:`gac_jax.data.synthetic.clips`). Running the same command
again is a no-op once the output is complete, and resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import sys
import time

from gac_jax.data.files import KittiFormatError
from gac_jax.data.io_errors import error_line
from gac_jax.data.synthetic.clips import generate_clips
from gac_jax.data.synthetic.scene import CLASS_SIZES, DEFAULT_COUNTS
from gac_jax.data.synthetic.traffic import DEFAULT_MIX, SCENARIOS
from gac_jax.data.synthetic.writer import generate_dataset


def _class_arg(text: str) -> tuple[str, tuple[int, int]]:
    """``Car`` (its default range), ``Car:5`` (exactly 5) or ``Car:3-8`` (3 to 8 per frame)."""
    name, _, rng = text.partition(":")
    if name not in CLASS_SIZES:
        raise argparse.ArgumentTypeError(
            f"unknown class {name!r} (known: {', '.join(CLASS_SIZES)})"
        )
    if not rng:
        return name, DEFAULT_COUNTS[name]
    lo, _, hi = rng.partition("-")
    try:
        lo_i = int(lo)
        hi_i = int(hi) if hi else lo_i
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"bad count range {rng!r} in {text!r} (want e.g. Car:3-8)"
        ) from None
    return name, (lo_i, hi_i)


def _scenario_arg(text: str) -> tuple[str, float]:
    """``curve`` (its default share of sequences), ``curve:0.8`` or ``none``."""
    name, _, share = text.partition(":")
    if name not in (*SCENARIOS, "none"):
        raise argparse.ArgumentTypeError(
            f"unknown scenario {name!r} (known: {', '.join(SCENARIOS)}, none)"
        )
    if not share:
        return name, DEFAULT_MIX.get(name, 0.0)
    try:
        value = float(share)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"bad share {share!r} in {text!r} (want e.g. curve:0.5)"
        ) from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"share of sequences must be in [0, 1] in {text!r}")
    return name, value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return value


class _Parser(argparse.ArgumentParser):
    """Bad arguments: one line (``PROG: error: ...``) and exit status 2, no usage block."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m gac_jax.data.synthetic",
        description="Generate a synthetic KITTI-format driving dataset (3D objects + depth).",
    )
    p.add_argument("--out", required=True, help="output directory (created; must be empty or ours)")
    p.add_argument("--num", type=_positive_int, help="number of frames (independent scenes)")
    p.add_argument(
        "--sequences",
        type=_positive_int,
        help="number of driving clips (KITTI tracking layout) instead of --num frames",
    )
    p.add_argument("--frames-per-sequence", type=_positive_int, help="frames of each clip (10 Hz)")
    p.add_argument("--seed", type=_non_negative_int, default=0, help="dataset seed (default 0)")
    p.add_argument("--height", type=_positive_int, default=375, help="image height (default 375)")
    p.add_argument("--width", type=_positive_int, default=1242, help="image width (default 1242)")
    p.add_argument(
        "--val-fraction",
        type=_fraction,
        default=None,
        help="share of val frames (default 0.5; not for clips)",
    )
    p.add_argument(
        "--workers", type=_positive_int, default=None, help="processes (default: all cores)"
    )
    p.add_argument(
        "--classes",
        nargs="+",
        type=_class_arg,
        default=None,
        metavar="CLASS[:MIN-MAX]",
        help="road users per frame, e.g. Car:3-8 Pedestrian:0-4 Cyclist:0-2 (the default); "
        "classes not listed are absent",
    )
    p.add_argument(
        "--scenarios",
        nargs="+",
        type=_scenario_arg,
        default=None,
        metavar="NAME[:SHARE]",
        help="clips: what happens in them, each in a share of the sequences: "
        + " ".join(f"{k}:{v:g}" for k, v in DEFAULT_MIX.items())
        + " (the default); scenarios not listed never happen; none: straight roads, "
        "constant speeds",
    )
    p.add_argument(
        "--rigs",
        choices=("kitti", "multi"),
        default="kitti",
        help="camera rigs: kitti (KITTI's, 1.65 m, level; default) or multi (eight vehicles, "
        "1.2-2.4 m, pitch -6..+7 deg, two held out into val_heldout; writes training/planes; "
        "clips: one vehicle per sequence)",
    )
    p.add_argument(
        "--randomize",
        type=float,
        default=None,
        metavar="SHARE",
        help="frames only: share of frames (0-1) whose background (buildings, trees, street "
        "furniture) gets random colours and patterns, for detectors meant for real cameras "
        "(default 0)",
    )
    p.add_argument(
        "--photo",
        type=float,
        default=None,
        metavar="SHARE",
        help="frames only: share of frames (0-1) whose foliage, fences, boxes and verges take "
        "their detail from photographs of grass and gravel (default 0)",
    )
    p.add_argument(
        "--randomize-cars",
        type=float,
        default=None,
        metavar="SHARE",
        help="frames only: share of frames (0-1) in which most cars get a random paint and "
        "pattern, window tint and tyre shade (domain randomization of the cars; default 0)",
    )
    p.add_argument(
        "--large-vehicles",
        type=float,
        default=None,
        metavar="SHARE",
        help="frames only: share of frames (0-1) with 1-3 vans and trucks among the road users, "
        "labelled Van / Truck (default 0)",
    )
    p.add_argument(
        "--gardens",
        type=float,
        default=None,
        metavar="SHARE",
        help="frames only: probability (0-1) that an urban roadside has front gardens, its "
        "buildings 3-14 m behind lawns, hedges and trees (default 0)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace a dataset made with other arguments"
    )
    p.add_argument(
        "--shard",
        type=_shard_arg,
        default=None,
        metavar="K/N",
        help="frames only: write the K-th of N equal frame ranges (K = 0..N-1) into --out; N "
        "shards run anywhere (a job array, one machine each) into one folder give the bytes "
        "of one run, and the last to finish completes the dataset",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _shard_arg(text: str) -> tuple[int, int]:
    k, sep, n = text.partition("/")
    try:
        k_i, n_i = int(k), int(n)
    except ValueError:
        k_i = n_i = -1
    if not sep or n_i < 1 or not 0 <= k_i < n_i:
        raise argparse.ArgumentTypeError(f"{text!r}: expected K/N with 0 <= K < N, e.g. 0/4")
    return k_i, n_i


def _check_mode(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exactly one of --num and --sequences (with --frames-per-sequence); exits 2 otherwise."""
    if args.sequences is None and args.frames_per_sequence is None:
        if args.scenarios is not None:
            parser.error("--scenarios is for clips (--sequences N --frames-per-sequence F)")
        if args.num is None:
            parser.error("give --num N (frames) or --sequences N --frames-per-sequence F (clips)")
        return
    if args.shard is not None:
        parser.error("--shard is for frames (--num N), not clips")
    if args.num is not None:
        parser.error("--num (frames) and --sequences (clips) exclude each other")
    if args.sequences is None or args.frames_per_sequence is None:
        parser.error("clips need both --sequences N and --frames-per-sequence F")
    if args.val_fraction is not None:
        parser.error("--val-fraction: clips have no splits")
    if args.randomize is not None:
        parser.error("--randomize: for frames only")
    if args.photo is not None:
        parser.error("--photo: for frames only")
    if args.randomize_cars is not None:
        parser.error("--randomize-cars: for frames only")
    if args.large_vehicles is not None:
        parser.error("--large-vehicles: for frames only")
    if args.gardens is not None:
        parser.error("--gardens: for frames only")


def _generate(args: argparse.Namespace, what: str, call):
    """Runs ``call()``: (result, seconds), or (None, exit status) after one line on stderr."""
    start = time.perf_counter()
    try:
        result = call()
    except (ValueError, OSError, KittiFormatError) as e:
        message = error_line(e, args.out) if isinstance(e, OSError) else str(e)
        print(f"error: {message}", file=sys.stderr)
        return None, 1
    except KeyboardInterrupt:
        print(f"interrupted: run the same command again to finish the {what}", file=sys.stderr)
        return None, 130
    return result, time.perf_counter() - start


def _clips(args: argparse.Namespace, classes) -> int:
    result, took = _generate(
        args,
        "clips",
        lambda: generate_clips(
            args.out,
            args.sequences,
            args.frames_per_sequence,
            args.seed,
            rigs=args.rigs,
            height=args.height,
            width=args.width,
            classes=classes,
            scenarios=None
            if args.scenarios is None
            else {k: v for k, v in args.scenarios if k != "none"},
            workers=args.workers,
            overwrite=args.overwrite,
            progress=not args.quiet,
            announce=None if args.quiet else print,
        ),
    )
    if result is None:
        return took
    total = result.num_sequences * result.frames_per_sequence
    if result.generated == 0:
        print(
            f"{result.root}: complete clips ({result.num_sequences} x "
            f"{result.frames_per_sequence} frames) already there"
        )
    else:
        print(
            f"{result.root}: wrote {result.generated} of {total} clip frames "
            f"in {took:.1f} s ({result.generated / took:.2f} frames/s)"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_mode(parser, args)
    classes = dict(args.classes) if args.classes else None
    if args.sequences is not None:
        return _clips(args, classes)
    result, took = _generate(
        args,
        "dataset",
        lambda: generate_dataset(
            args.out,
            args.num,
            args.seed,
            height=args.height,
            width=args.width,
            val_fraction=0.5 if args.val_fraction is None else args.val_fraction,
            classes=classes,
            rig_set=args.rigs,
            randomize=args.randomize or 0.0,
            photo=args.photo or 0.0,
            randomize_cars=args.randomize_cars or 0.0,
            large_vehicles=args.large_vehicles or 0.0,
            gardens=args.gardens or 0.0,
            workers=args.workers,
            overwrite=args.overwrite,
            progress=not args.quiet,
            shard=args.shard,
        ),
    )
    if result is None:
        return took
    if args.shard is not None:
        k, n = args.shard
        state = "complete" if result.complete else "not complete yet (other shards to come)"
        print(
            f"{result.root}: shard {k}/{n}: wrote {result.generated} frames in {took:.1f} s; "
            f"the dataset of {result.num_frames} frames is {state}"
        )
        return 0
    if result.generated == 0:
        print(f"{result.root}: complete dataset of {result.num_frames} frames already there")
    else:
        print(
            f"{result.root}: wrote {result.generated} of {result.num_frames} frames "
            f"in {took:.1f} s ({result.generated / took:.2f} frames/s)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
