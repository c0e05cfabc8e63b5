"""``python -m gac_jax.deploy.export``: a trained network -> ``DIR/model.onnx`` + ``export.json``.

    python -m gac_jax.deploy.export --task detect3d|depth (--workdir W [--step N] |
        --checkpoint C --config F) --out DIR [--opset K] [--precision int8 [--int8-frames N]
        [--int8-seed S] [--int8-keep-float REGEX ...]] [key.sub=value ...]

The graph is emitted from the Flax variables and the config (:mod:`gac_jax.deploy.export.networks`):
NCHW, BatchNorm folded, inputs ``images`` (B,H,W,3) float32, ``P2`` (B,3,4) and ``plane`` (B,4)
(the frame's ground plane) with a dynamic batch. ``--checkpoint`` (converted weights,
``python -m gac_jax.weights.convert``) is for the detector. ``--precision int8`` also writes
``DIR/model_int8.xml`` (+ ``.bin``), the network quantized by NNCF on frames of the run's
training split (:mod:`gac_jax.deploy.int8`), for ``--runtime openvino --precision int8``. An
``--out`` inside ``--workdir`` is a write into that run folder: the command holds its lock
(:mod:`gac_jax.training.workdir_lock`) and refuses a folder that another process writes to.
Errors end with ``error: <file>: <problem>`` and exit code 2 (1: a full disk).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from gac_jax.deploy.export.artifact import DEFAULT_OPSET, MODEL_FILE
from gac_jax.deploy.int8 import add_int8_arguments, ensure_int8, int8_settings

EXIT_INVALID_INPUT = 2
MIN_OPSET = 13  # Resize with align_corners and sizes, Clip/Pad/Slice with tensor inputs


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m gac_jax.deploy.export",
        description="Export a trained GAC detector or depth network to ONNX (+ export.json).",
    )
    parser.add_argument("--task", required=True, choices=("detect3d", "depth"))
    parser.add_argument("--workdir", help="training workdir (config.json, checkpoints/)")
    parser.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    parser.add_argument("--checkpoint", metavar="DIR", help="converted detector weights")
    parser.add_argument("--config", help="config file[:arg] (needed with --checkpoint)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET, help="ONNX opset")
    parser.add_argument(
        "--precision",
        choices=("f32", "int8"),
        default="f32",
        help="f32: model.onnx only (default); int8: also the NNCF-quantized model_int8.xml",
    )
    add_int8_arguments(parser)
    parser.add_argument("overrides", nargs="*", help="config overrides key.sub=value")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if bool(args.workdir) == bool(args.checkpoint):
        parser.error("give exactly one of --workdir W or --checkpoint C --config F")
    if args.checkpoint and not args.config:
        parser.error("--checkpoint (converted weights) needs --config")
    if args.checkpoint and args.step is not None:
        parser.error("--step selects a checkpoint of the workdir; it cannot go with --checkpoint")
    if args.opset < MIN_OPSET:
        parser.error(f"--opset must be >= {MIN_OPSET}")
    try:
        int8 = int8_settings(args)
    except ValueError as e:
        parser.error(str(e))
    if int8 is not None:
        from gac_jax.deploy.runtimes import RuntimeUnavailableError, check_runtime

        try:
            note = check_runtime("openvino", "int8")
        except RuntimeUnavailableError as e:
            print(f"error: {e}", file=sys.stderr)
            return EXIT_INVALID_INPUT
        if note:
            print(note)
    from gac_jax.data.files import KittiFormatError
    from gac_jax.data.io_errors import error_line, exit_code
    from gac_jax.deploy.export.networks import ExportError
    from gac_jax.deploy.export.sources import export_source, load_source
    from gac_jax.training import workdir_lock

    try:
        with workdir_lock.hold_if_inside(args.workdir, args.out):
            source = load_source(
                args.task,
                workdir=args.workdir,
                step=args.step,
                checkpoint=args.checkpoint,
                config_spec=args.config,
                overrides=args.overrides,
            )
            meta = export_source(source, args.out, args.opset)
            if int8 is not None:
                ensure_int8(args.out, source.task, source.config, int8, source.workdir)
    except ExportError as e:
        print(f"error: {args.workdir or args.checkpoint}: {e}", file=sys.stderr)
        return EXIT_INVALID_INPUT
    except (KittiFormatError, workdir_lock.WorkdirBusyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_INVALID_INPUT
    except OSError as e:
        print(f"error: {error_line(e, args.out)}", file=sys.stderr)
        return exit_code(e)
    except ValueError as e:  # an --int8-keep-float pattern that matches no layer
        print(f"error: {args.out}/{MODEL_FILE}: {e}", file=sys.stderr)
        return EXIT_INVALID_INPUT
    h, w = source.image_size
    weights = source.weights
    origin = f"step {weights['step']}" if "step" in weights else weights["checkpoint"]
    print(
        f"{args.task} {origin} (weights sha256 {weights['sha256'][:12]}) -> {args.out}/"
        f"{MODEL_FILE} ({meta['size_bytes'] / 1e6:.1f} MB, opset {args.opset}, input {h}x{w}, "
        f"sha256 {meta['sha256'][:12]})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
