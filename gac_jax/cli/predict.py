"""Run a trained detector on any KITTI-format images: ``python -m gac_jax.cli.predict``.

    python -m gac_jax.cli.predict --workdir W IMAGE_OR_DIR [--calib FILE_OR_DIR] [--out DIR]
        [--no-images] [--step N | --checkpoint DIR --config C] [--calib-camera 2|3]
        [--score-threshold S] [--batch-size B] [--threads T]
        [--runtime jax|onnxruntime|openvino] [--precision f32|bf16|int8] [--export DIR]
        [--int8-frames N] [--int8-seed S] [--int8-keep-float REGEX ...]

``IMAGE_OR_DIR`` is one image (PNG/JPEG) or a folder of them. Each image needs
its KITTI calibration file (``P2: ...`` line; ``--calib-camera 3`` uses ``P3``):
``--calib FILE`` serves every image (any KITTI calibration format: object, tracking, raw
``calib_cam_to_cam.txt``), ``--calib DIR`` holds ``<stem>.txt`` per image; without ``--calib``
the KITTI layout is assumed (``<images>/../calib/<stem>.txt``, else ``<stem>.txt`` beside the
image, else, for the frames of a KITTI raw drive ``DATE/DATE_drive_NNNN_sync/image_0N/data``,
the day's ``DATE/calib_cam_to_cam.txt``). An image whose KITTI layout has a ground-plane file
(``<images>/../planes/<stem>.txt``) is predicted with that plane, the others with the config's
level camera (``model.gac.camera_height``). Images of any size go through the model's
test transform (crop the top rows, resize to the input height, crop/pad the
width); results are in original-image pixels.

Writes ``OUT/data/<stem>.txt`` (KITTI result lines with scores) and, unless
``--no-images``, ``OUT/pictures/<stem>.png`` (3D/2D boxes and a bird's-eye view)
plus ``OUT/pictures/grid.png``. ``OUT`` defaults to ``W/predict/<input name>``.
``--runtime onnxruntime|openvino`` runs the exported network (:mod:`gac_jax.deploy.runtimes`; the
export is written to ``W/export/<weights>`` when absent) with the same decoding and
post-processing. Errors end with ``error: <file>: <problem>`` and exit code 2.

Video files, cameras and image sequences (``--video FILE``, ``--camera INDEX``, ``--sequence
DIR``, ``--clip [N]``) instead of ``IMAGE_OR_DIR`` run as a stream: an annotated video and
per-frame results, written as frames finish (:mod:`gac_jax.cli.predict_stream`).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

if __name__ == "__main__":  # a stop signal while the command starts: one line, no traceback
    from gac_jax.streams.stop_signals import exit_during_start

    exit_during_start()

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
EXIT_INVALID_INPUT = 2


def find_images(path: str | os.PathLike) -> list[Path]:
    """The image ``path`` or the images (PNG/JPEG) directly inside folder ``path``, sorted."""
    from gac_jax.data.files import KittiFormatError

    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise KittiFormatError(path, "image or folder not found")
    images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise KittiFormatError(path, f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    stems = [p.stem for p in images]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise KittiFormatError(path, f"several images share the name {dup[0]!r} (e.g. .png/.jpg)")
    return images


def find_calibrations(
    images: Sequence[Path], calib: str | os.PathLike | None, camera: int = 2
) -> list[Path]:
    """Calibration file of every image (see the module docstring for the search order;
    ``camera``: 2 or 3, checked against a KITTI raw drive's ``image_0N``)."""
    from gac_jax.data.files import KittiFormatError
    from gac_jax.data.kitti_raw import RawDrive

    hint = (
        "pass --calib FILE (one calibration for all images) or --calib DIR "
        "(a <image stem>.txt per image)"
    )
    if calib is not None:
        calib = Path(calib)
        if calib.is_file():
            return [calib] * len(images)
        if not calib.is_dir():
            raise KittiFormatError(calib, "calibration file or folder not found")
        found = []
        for image in images:
            path = calib / f"{image.stem}.txt"
            if not path.is_file():
                raise KittiFormatError(path, f"calibration of {image} not found; {hint}")
            found.append(path)
        return found
    found = []
    for image in images:
        candidates = [
            image.parent.parent / "calib" / f"{image.stem}.txt",
            image.with_suffix(".txt"),
        ]
        raw = RawDrive.locate(image.parent, camera) if image.parent.name == "data" else None
        if raw is not None:
            if raw.camera != camera:
                raise KittiFormatError(
                    image, f"a frame of camera {raw.camera}: pass --calib-camera {raw.camera}"
                )
            candidates.append(raw.calib)
        path = next((c for c in candidates if c.is_file()), None)
        if path is None:
            looked = " and ".join(str(c) for c in candidates)
            raise KittiFormatError(image, f"no calibration found (looked for {looked}); {hint}")
        found.append(path)
    return found


class ImageSource:
    """Random-access source of unlabelled images with their calibration (``source[i]`` samples).

    Args:
      images, calibs: paths, one calibration per image.
      camera: 2 (``P2``) or 3 (``P3``) of the calibration file.
      input_geometry: ``(crop_top, height, width)`` of the model's test transform: images
        must be taller than ``crop_top``; those wider than ``width`` after the resize to
        ``height`` are cut on the right by the transform and listed in :attr:`cut_off`.
    """

    def __init__(
        self,
        images: Sequence[Path],
        calibs: Sequence[Path],
        camera: int = 2,
        input_geometry: tuple[int, int, int] | None = None,
    ):
        self.images = [Path(p) for p in images]
        self.calibs = [Path(p) for p in calibs]
        self.camera = camera
        self.input_geometry = input_geometry
        self.frame_ids = [p.stem for p in self.images]
        self.cut_off: set[str] = set()

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> dict:
        from gac_jax.data.files import KittiFormatError, read_image
        from gac_jax.data.kitti import read_calib, read_plane
        from gac_jax.data.sources import new_sample

        P = read_calib(self.calibs[i], self.camera).projection(self.camera)
        image = read_image(self.images[i])
        if self.input_geometry is not None:
            crop_top, height, width = self.input_geometry
            h, w = image.shape[:2]
            if h <= crop_top:
                raise KittiFormatError(
                    self.images[i], f"image is {h} rows tall; the model crops the top {crop_top}"
                )
            if round(w * height / (h - crop_top)) > width:
                self.cut_off.add(self.frame_ids[i])
        plane = self.images[i].parent.parent / "planes" / f"{self.images[i].stem}.txt"
        extra = {"plane": read_plane(plane)} if plane.is_file() else {}
        return new_sample(self.frame_ids[i], self.camera, image, P, **extra)


def build_parser() -> argparse.ArgumentParser:
    from gac_jax.cli.model_mode import PRECISION_CHOICES
    from gac_jax.cli.predict_stream import add_stream_arguments
    from gac_jax.deploy.int8 import add_int8_arguments

    parser = OneLineParser(
        prog="python -m gac_jax.cli.predict",
        description="Run a trained GAC detector on KITTI-format images; write KITTI result files "
        "and pictures.",
    )
    parser.add_argument(
        "input", metavar="IMAGE_OR_DIR", nargs="?", help="an image or a folder of images"
    )
    parser.add_argument("--workdir", required=True, help="training workdir (or priors + config)")
    parser.add_argument("--calib", metavar="FILE_OR_DIR", help="calibration file or folder")
    parser.add_argument("--out", metavar="DIR", help="output folder (default: W/predict/<input>)")
    parser.add_argument("--no-images", action="store_true", help="write result files only")
    parser.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    parser.add_argument("--checkpoint", metavar="DIR", help="converted weights instead")
    parser.add_argument("--config", help="config file[:arg] instead of W/config.json")
    parser.add_argument(
        "--calib-camera", type=int, choices=(2, 3), default=2, help="P2 or P3 of the calibration"
    )
    parser.add_argument(
        "--score-threshold",
        type=float,
        help="default: the run's deployed threshold (its recorded operating point where its "
        "config says eval.deploy_threshold=operating_point, else eval.score_threshold)",
    )
    parser.add_argument("--batch-size", type=int, default=1, help="images per model call")
    parser.add_argument("--threads", type=int, help="CPU threads of XLA (default: all usable)")
    parser.add_argument(
        "--runtime",
        choices=("jax", "onnxruntime", "openvino"),
        default="jax",
        help="what runs the network (default jax; the others export it to W/export/ if absent)",
    )
    parser.add_argument("--precision", choices=PRECISION_CHOICES, default="f32")
    parser.add_argument(
        "--export", metavar="DIR", help="export folder for --runtime (default: W/export/<weights>)"
    )
    add_int8_arguments(parser)
    add_stream_arguments(parser)
    return parser


def predict(args: argparse.Namespace, threads: int) -> Path:
    """Runs the command (``threads``: XLA CPU threads in effect); returns the output folder."""
    import jax.numpy as jnp

    from gac_jax.data.files import KittiFormatError
    from gac_jax.deploy.runtime_choice import use_runtime
    from gac_jax.drawing.detection_pictures import save_pictures
    from gac_jax.guard.verdict_file import precision_line
    from gac_jax.trained.detector import evaluator_for, load_detector
    from gac_jax.trained.operating_point import apply_deploy_threshold
    from gac_jax.trained.run_config import load_run_config

    workdir = Path(args.workdir)
    if not workdir.is_dir():
        raise KittiFormatError(workdir, "workdir not found")
    images = find_images(args.input)
    calibs = find_calibrations(images, args.calib, args.calib_camera)
    overrides = []
    if args.score_threshold is not None:
        overrides.append(f"eval.score_threshold={args.score_threshold}")
    config = load_run_config(workdir, args.config, overrides)
    dtype = jnp.bfloat16 if (args.runtime, args.precision) == ("jax", "bf16") else jnp.float32
    detector = load_detector(
        workdir, config, step=args.step, checkpoint=args.checkpoint, dtype=dtype
    )
    try:
        explicit = args.score_threshold is not None
        threshold_line = apply_deploy_threshold(workdir, detector, explicit)
    except ValueError as e:  # an unknown eval.deploy_threshold
        raise KittiFormatError(args.config or workdir / "config.json", str(e)) from None
    d = config.data
    source = ImageSource(images, calibs, args.calib_camera, (d.crop_top, d.height, d.width))
    evaluator = evaluator_for(detector, source, args.batch_size)
    name = Path(args.input).resolve()
    out = Path(args.out) if args.out else workdir / "predict" / (name.stem or "input")
    print(f"{detector.weights}: {len(images)} images -> {out}", flush=True)
    print(threshold_line, flush=True)
    int8 = getattr(args, "int8", None)
    if args.runtime == "jax":
        compile_s = evaluator.compile(detector.variables, (d.height, d.width))
    else:
        compile_s = use_runtime(
            evaluator,
            detector,
            workdir,
            args.runtime,
            args.precision,
            export_dir=args.export,
            threads=threads,
            int8=int8,
        )
    print(precision_line(workdir, detector, args.runtime, args.precision, int8, args.export))
    detections, timings = evaluator.predict_split(detector.variables, out / "data", resume=False)
    n = int(timings["num_frames"])
    total = timings["model_s"] + timings["postprocess_s"] + timings["io_s"]
    print(
        f"{n} images, {sum(len(d) for d in detections.values())} detections; "
        f"{n / total:.2f} images/s on {threads} CPU threads, {args.runtime} {args.precision} "
        f"(model {timings['model_s']:.2f} s, "
        f"post-processing {timings['postprocess_s']:.2f} s, I/O {timings['io_s']:.2f} s; "
        f"compile {compile_s:.1f} s)"
    )
    if source.cut_off:
        cut = sorted(source.cut_off)
        print(
            f"note: {len(cut)} images are wider than the model input ({d.width} px at height "
            f"{d.height} after cropping {d.crop_top} rows): their right part was not seen "
            f"({', '.join(cut[:5])}{' ...' if len(cut) > 5 else ''})"
        )
    if not args.no_images:
        save_pictures(source, detections, out / "pictures", None)
        print(f"pictures in {out / 'pictures'}")
    return out


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, ``error: <option>: <problem>`` (exit 2),
    as every other input error of the command, not a usage dump (``--help`` gives that)."""

    def error(self, message: str):
        print(f"error: {message}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_INVALID_INPUT)


def main(argv: Sequence[str] | None = None) -> int:
    """The command (module doc); what it prints never stops it (:mod:`gac_jax.cli.console`)."""
    from gac_jax.cli.console import safe_console

    with safe_console():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    from gac_jax.cpu_backend import apply_default_xla_flags

    apply_default_xla_flags()  # before JAX starts its backend
    parser = build_parser()
    args = parser.parse_args(argv)
    from gac_jax.cli.predict_stream import check_stream_arguments, run_stream
    from gac_jax.cli.stream_start import numeric_problems, refuse, start_stream, stream_kind

    check_stream_arguments(parser, args)
    if args.checkpoint and args.step is not None:
        parser.error("--step selects a checkpoint of the workdir; it cannot go with --checkpoint")
    if args.export and args.runtime == "jax":
        parser.error("--export only applies with --runtime onnxruntime|openvino")
    for problem in numeric_problems(args):  # before anything opens, JAX included
        refuse(problem)
    from gac_jax.cli.model_mode import limit_cpu_threads
    from gac_jax.data.files import KittiFormatError
    from gac_jax.deploy.int8 import int8_settings

    try:
        threads = limit_cpu_threads(args.threads)
        args.int8 = int8_settings(args)
    except ValueError as e:
        parser.error(str(e))
    from gac_jax.api.inputs import InputError
    from gac_jax.data.io_errors import error_line, exit_code
    from gac_jax.streams import output_lock
    from gac_jax.streams.output_lock import OutputBusyError
    from gac_jax.streams.stop_signals import restore_defaults
    from gac_jax.training import workdir_lock

    streaming = stream_kind(args) is not None
    if not streaming:
        restore_defaults()  # Ctrl-C is a KeyboardInterrupt (below)
    # W/predict by default; the runtimes export into W/export
    outputs = [args.out] if args.runtime == "jax" or args.export else [args.out, None]
    if streaming and args.out_video:
        outputs.append(args.out_video)
    start = None
    try:
        with workdir_lock.hold_if_inside(args.workdir, *outputs):
            start = start_stream(args) if streaming else None  # all its checks, before JAX
            from gac_jax.deploy.runtime_choice import resolve_runtime

            resolve_runtime(args.runtime, args.precision)
            if streaming:
                start, begun = None, start
                return run_stream(args, threads, begun)  # it closes the source
            predict(args, threads)
    except (KittiFormatError, InputError, workdir_lock.WorkdirBusyError, OutputBusyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_INVALID_INPUT
    except OSError as e:
        print(f"error: {error_line(e, args.out or args.workdir)}", file=sys.stderr)
        return exit_code(e)
    except KeyboardInterrupt:  # before a stream's frames (they handle Ctrl-C themselves)
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        if start is not None:  # opened and claimed, but the stream did not start
            start.source.close()
        if streaming:
            output_lock.release_all()
    return 0


if __name__ == "__main__":
    sys.exit(main())
