"""int8 networks: NNCF post-training quantization of an export, calibrated on the run's data.

``--runtime openvino --precision int8`` runs ``DIR/model_int8.xml`` (+ ``.bin``), an OpenVINO
IR that NNCF (``nncf.quantize``, preset ``mixed``: symmetric int8 weights, asymmetric int8
activations; fast bias correction) made from ``DIR/model.onnx``. Calibration frames are
``frames`` images of the run's *training* split drawn with ``seed``, read and transformed by
the project's own eval transform (:func:`gac_jax.builders.detect3d.eval_transform`,
:func:`gac_jax.builders.depth.eval_transform`), i.e. exactly what the network sees at test
time, with their ``P2``.

``export.json`` gains an ``int8`` block: the sha256 of ``model.onnx`` it was made from, the
calibration (split, data root, frame ids, seed, transform), the preset, the layers kept in
float32, the sha256 of both IR files and the NNCF / OpenVINO versions. :func:`ensure_int8`
reuses a matching int8 model and (re)builds a missing, stale (other ``model.onnx`` or other
settings) or damaged one, saying why in one line; both IR files are written to a temporary
folder and renamed into place, and ``export.json`` last, so an interrupted build is only
ever seen as "missing" or "damaged" and built again.

Mixed precision: ``keep_float`` are regular expressions (NNCF ``IgnoredScope(patterns=...)``,
matched with ``re.match``, i.e. at the start, against OpenVINO node names). The exporter names
every convolution by its Flax path (detector: ``backbone/layer1_0/conv1``, ``head/cls_out``,
``head/gac/extract``; depth U-Net: ``backbone/...``, ``up0/gac/...``, ``up2/conv1``,
``out_scale_1/taps``), so ``head/`` keeps the whole detection head in float32,
``head/(cls|reg)_out`` its two output convs. A pattern that matches no node is refused (the
message lists the layer prefixes), so a scope cannot silently stop applying when the model
changes. ``benchmarks/bench_int8_sensitivity.py`` measures which blocks cost the AP.

Heading kept in float32 (``keep_heading``, ``--int8-keep-heading``): adds to the float32
scope the first convolution on the image input (the stem, ``backbone/conv1``) and the
convolutions that produce the outputs the heading is decoded from (:data:`HEADING_OUTPUTS`:
the alpha sign bit and the orientation residuals, :mod:`gac_jax.detection.box_coding`;
detector: ``head/cls_out`` and ``head/reg_out``), all found by walking the exported graph
from that input and back from those outputs to the nearest convolution, not listed by hand.
Measured with the paired guard (``python -m gac_jax.cli.guard``, default detector, step 400,
300 frames): with the output convs alone in float32 int8 lost as many headings as full int8
(moderate: 15 objects lost / 4 gained vs 12 / 5; 95th percentile of the heading change of
matched detections 6.7 vs 7.0 deg); with the stem in float32 the losses and gains balanced
(5 / 6) and that percentile fell to 1.9 deg: the quantized image and stem, not the head,
carry most of the heading's int8 error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import re
import shutil
import sys
import tempfile
import time
import types
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.deploy.export import artifact
from gac_jax.deploy.telemetry import import_nncf, import_openvino

INT8_MODEL = "model_int8.xml"  # + model_int8.bin (weights)
INT8_WEIGHTS = "model_int8.bin"
PRESET = "mixed"
# calibration time is mostly NNCF's bias correction, roughly linear in the frames: 13 frames
# took 104 s for the paper detector (R101, 288x1280) on a loaded 2-core EPYC, 2 s for the
# default one; 16 is about a minute to a minute and a half for the paper detector
DEFAULT_FRAMES = 16
DEFAULT_SEED = 0
# what a stored int8 model must agree on with the requested one (else it is rebuilt)
COMPARED = ("source_sha256", "calibration", "preset", "keep_float")
# the network outputs the heading is decoded from (sign bit; sin/cos residual channels) and
# the input whose first conv's quantization moves it most (measured, module docstring)
HEADING_OUTPUTS = ("sign_logits", "reg")
HEADING_INPUTS = ("images",)


@dataclasses.dataclass(frozen=True)
class Int8Settings:
    """How the int8 model is calibrated: ``frames`` training images drawn with ``seed``;
    ``keep_float``: node-name patterns kept in float32; ``keep_heading``: also the convs
    that produce the heading outputs (see the module docstring)."""

    frames: int = DEFAULT_FRAMES
    seed: int = DEFAULT_SEED
    keep_float: tuple[str, ...] = ()
    keep_heading: bool = False

    def __post_init__(self):
        if self.frames < 1:
            raise ValueError(f"--int8-frames must be >= 1, got {self.frames}")
        for pattern in self.keep_float:
            try:
                re.compile(pattern)
            except re.error as e:
                raise ValueError(
                    f"--int8-keep-float {pattern!r}: not a regular expression ({e})"
                ) from None


INT8_OPTIONS = ("int8_frames", "int8_seed", "int8_keep_float", "int8_keep_heading")


def add_int8_arguments(parser) -> None:
    """``--int8-frames``, ``--int8-seed`` and ``--int8-keep-float`` (argparse parser or group;
    all default to None, i.e. "not given": :func:`int8_settings` fills in the defaults)."""
    parser.add_argument(
        "--int8-frames",
        type=int,
        metavar="N",
        help=f"--precision int8: calibration images from the training split (default "
        f"{DEFAULT_FRAMES}: about a minute for the paper detector on 2 cores)",
    )
    parser.add_argument(
        "--int8-seed", type=int, help=f"which calibration images (default seed {DEFAULT_SEED})"
    )
    parser.add_argument(
        "--int8-keep-float",
        action="append",
        metavar="REGEX",
        help="--precision int8: keep the layers whose names match in float32 (repeatable; "
        "names are Flax paths, e.g. 'head/.*' or 'head/(cls|reg)_out.*')",
    )
    parser.add_argument(
        "--int8-keep-heading",
        action="store_true",
        default=None,
        help="--precision int8: keep the stem (first conv on the image) and the convs that "
        "produce the heading (alpha sign bit, orientation residuals) in float32",
    )


def int8_settings(args) -> Int8Settings | None:
    """The :class:`Int8Settings` of parsed arguments with ``--precision int8`` (defaults for
    options not given), None for another precision.

    Raises:
      ValueError: ``--int8-*`` options without ``--precision int8``, or invalid values.
    """
    given = [n for n in INT8_OPTIONS if getattr(args, n, None) is not None]
    if getattr(args, "precision", None) != "int8":
        if given:
            flags = ", ".join("--" + n.replace("_", "-") for n in given)
            verb = "apply" if len(given) > 1 else "applies"
            raise ValueError(f"{flags} only {verb} with --precision int8")
        return None
    frames, seed = getattr(args, "int8_frames", None), getattr(args, "int8_seed", None)
    return Int8Settings(
        frames=DEFAULT_FRAMES if frames is None else frames,
        seed=DEFAULT_SEED if seed is None else seed,
        keep_float=tuple(getattr(args, "int8_keep_float", None) or ()),
        keep_heading=bool(getattr(args, "int8_keep_heading", None)),
    )


def _versions() -> dict[str, str]:
    return artifact.library_versions(("nncf", "openvino"))


def _sha256_file(path: Path) -> str:
    return artifact.sha256_bytes(path.read_bytes())


# OpenVINO names the nodes it creates ``<Type>_<n>`` from a per-process counter, so the same
# quantized network serialized in another process (or after another model) differs in those
# names only; the IR's identity renumbers them in order of appearance
_AUTO_NAME = re.compile(r"\b([A-Z][A-Za-z0-9]*)_(\d+)\b")


def ir_sha256(out_dir: str | os.PathLike) -> str:
    """The identity of the int8 IR in ``out_dir``: sha256 of ``model_int8.xml`` with the
    nodes' generated names renumbered by first appearance, then of ``model_int8.bin``. Equal
    for the same quantized network wherever it was made; any other topology, attribute or
    constant (weights, quantization ranges) gives another."""
    out = Path(out_dir)
    seen: dict[str, int] = {}

    def renumber(match: re.Match) -> str:
        index = seen.setdefault(match.group(0), len(seen))
        return f"{match.group(1)}_#{index}"

    xml = _AUTO_NAME.sub(renumber, (out / INT8_MODEL).read_text())
    return artifact.sha256_bytes(xml.encode() + (out / INT8_WEIGHTS).read_bytes())


# ----------------------------------------------------------------------------- calibration


@contextlib.contextmanager
def children_without_main() -> Iterator[None]:
    """Inside, worker processes that ``multiprocessing`` starts (the embedded dataset's
    generator pool, forkserver or spawn) do not import the caller's main script.

    Those start methods run the parent's ``__main__`` file again in every child (as
    ``__mp_main__``); a user's script without an ``if __name__ == "__main__":`` guard that
    asks for an int8 model would load, export and quantize again in each worker. The
    workers' functions live in ``gac_jax`` modules, so the children need no main module: it
    is swapped for an empty one while the pool starts."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main


def calibration_source(task: str, config, workdir: str | os.PathLike | None = None):
    """``(source, transform, root)``: the run's training split and its eval transform; the
    embedded dataset is looked for (and generated, if missing) in the cache the run recorded
    (:func:`gac_jax.builders.datasets.cache_of_run`), never re-importing the main script."""
    from gac_jax.builders.datasets import cache_of_run

    with cache_of_run(workdir), children_without_main():
        return _calibration_source(task, config)


def _calibration_source(task: str, config):
    if task == "detect3d":
        from gac_jax.builders.datasets import prepare_dataset
        from gac_jax.builders.detect3d import eval_transform
        from gac_jax.data.sources import open_object_source

        root = prepare_dataset(config.data)
        source = open_object_source(root, config.data.train_split, use_right_image=False)
        return source, eval_transform(config), root
    from gac_jax.builders import depth

    root = depth.depth_root(config.data)
    return depth.train_source(config, root), depth.eval_transform(config), root


def calibration_frames(
    task: str, config, frames: int, seed: int, workdir: str | os.PathLike | None = None
) -> tuple[list[dict], dict]:
    """``frames`` transformed training images (fewer if the split is smaller) as network
    feeds ``{'images': (1,H,W,3) float32, 'P2': (1,3,4) float32, 'plane': (1,4) float32}`` (the
    frame's ground plane, else the config's level one), and their description (``frames``:
    how many were used). ``workdir``: the run (:func:`calibration_source`)."""
    from gac_jax.data.loader import plane_array  # grain: imported when calibrating only

    source, transform, root = calibration_source(task, config, workdir)
    if len(source) == 0:
        raise KittiFormatError(root, f"no frames in the training split {config.data.train_split}")
    rng = np.random.default_rng(seed)
    picked = np.sort(rng.choice(len(source), min(frames, len(source)), replace=False))
    feeds, ids = [], []
    for i in picked:
        sample = transform(source[int(i)])
        feeds.append(
            {
                "images": np.asarray(sample["image"], np.float32)[None],
                "P2": np.asarray(sample["P2"], np.float32)[None],
                "plane": plane_array(sample, config.model.gac.camera_height)[None],
            }
        )
        ids.append(f"{sample.get('frame_id', i)}:{sample.get('camera', 2)}")
    described = {
        "split": config.data.train_split,
        "data_root": str(Path(root).resolve()),
        "frames": len(feeds),
        "frames_requested": frames,
        "seed": seed,
        "frame_ids": ids,
        "transform": f"gac_jax.builders.{'detect3d' if task == 'detect3d' else 'depth'}"
        ".eval_transform",
    }
    return feeds, described


# ----------------------------------------------------------------------------- quantization


def nearest_convs(onnx_path: Path, tensors: tuple[str, ...], backwards: bool) -> list[str]:
    """Names of the Conv nodes nearest to graph tensors (inputs or outputs) of an ONNX model:
    walking from each tensor through the other nodes (``backwards``: towards the inputs, from
    an output; else towards the outputs, from an input), the first Conv on every path."""
    import onnx

    graph = onnx.load(str(onnx_path), load_external_data=False).graph
    step: dict[str, list] = {}
    for node in graph.node:
        for t in node.output if backwards else node.input:
            step.setdefault(t, []).append(node)
    missing = [t for t in tensors if t not in step]
    if missing:
        raise ValueError(f"{onnx_path}: no tensor {', '.join(missing)} (heading scope)")
    found, seen, todo = set(), set(), list(tensors)
    while todo:
        for node in step.get(todo.pop(), []):
            if id(node) in seen:
                continue
            seen.add(id(node))
            if node.op_type == "Conv":
                found.add(node.name)
            else:
                todo.extend(node.input if backwards else node.output)
    return sorted(found)


def heading_convs(onnx_path: Path) -> list[str]:
    """The convs ``keep_heading`` keeps in float32: the first conv on the image input (the
    stem, whose quantized input and weights carry most of int8's heading and 2D error) and
    the convs that produce :data:`HEADING_OUTPUTS` (module docstring)."""
    return sorted(
        {
            *nearest_convs(onnx_path, HEADING_INPUTS, backwards=False),
            *nearest_convs(onnx_path, HEADING_OUTPUTS, backwards=True),
        }
    )


def float_scope(onnx_path: Path, settings: Int8Settings) -> tuple[str, ...]:
    """The patterns kept in float32: ``keep_float`` plus, with ``keep_heading``, one exact
    pattern per conv of :func:`heading_convs`."""
    scope = list(settings.keep_float)
    if settings.keep_heading:
        scope += [re.escape(n) + r"\b" for n in heading_convs(onnx_path)]
    return tuple(scope)


def check_keep_float(model, keep_float: tuple[str, ...]) -> None:
    """Refuses a ``keep_float`` pattern that matches no node of the OpenVINO ``model``.

    Raises:
      ValueError: naming the pattern and the convolutions' top-level layer names.
    """
    ops = list(model.get_ordered_ops())
    names = [op.get_friendly_name() for op in ops]
    for pattern in keep_float:
        if not any(re.match(pattern, n) for n in names):  # as NNCF matches them
            convs = [
                n for n, op in zip(names, ops, strict=True) if op.get_type_name() == "Convolution"
            ]
            layers = sorted({n.split("/")[0] for n in convs if "/" in n})
            raise ValueError(
                f"--int8-keep-float {pattern!r} matches no layer of the network (names are Flax "
                f"paths under {', '.join(layers)}, e.g. '{layers[-1] if layers else 'head'}/.*')"
            )


def quantize_model(onnx_path: Path, feeds: list[dict], keep_float: tuple[str, ...] = ()):
    """The NNCF-quantized OpenVINO model of ``onnx_path`` (calibrated on ``feeds``)."""
    import logging

    nncf = import_nncf()
    ov = import_openvino()

    nncf.set_log_level(logging.WARNING)  # not one INFO line per layer kept in float32
    model = ov.Core().read_model(str(onnx_path))
    check_keep_float(model, keep_float)
    scope = nncf.IgnoredScope(patterns=list(keep_float), validate=False) if keep_float else None
    return nncf.quantize(
        model,
        nncf.Dataset(feeds),
        preset=nncf.QuantizationPreset.MIXED,
        subset_size=len(feeds),
        ignored_scope=scope,
    )


def _save_atomic(model, out: Path) -> dict[str, str]:
    """Saves ``model`` as ``out/model_int8.{xml,bin}`` via a temporary folder (weights first,
    the xml that references them last); returns the sha256 of both files."""
    ov = import_openvino()

    tmp = Path(tempfile.mkdtemp(prefix=".int8.", dir=out))
    try:
        ov.save_model(model, str(tmp / INT8_MODEL), compress_to_fp16=False)
        sums = {name: _sha256_file(tmp / name) for name in (INT8_MODEL, INT8_WEIGHTS)}
        os.replace(tmp / INT8_WEIGHTS, out / INT8_WEIGHTS)
        os.replace(tmp / INT8_MODEL, out / INT8_MODEL)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return sums


def _wanted(meta: dict, calibration: dict, scope: tuple[str, ...]) -> dict:
    return {
        "source_sha256": meta["sha256"],
        "calibration": calibration,
        "preset": PRESET,
        "keep_float": list(scope),
    }


def _why_rebuild(out: Path, stored: dict | None, wanted: dict) -> str | None:
    """Why the stored int8 model cannot be used (None: it can)."""
    if stored is None:
        return "no int8 model yet"
    diffs = [k for k in COMPARED if stored.get(k) != wanted[k]]
    if diffs:
        return f"int8 model made with other {', '.join(diffs).replace('_', ' ')}"
    for name, expected in stored.get("sha256", {}).items():
        path = out / name
        if not path.is_file():
            return f"{name} missing"
        if _sha256_file(path) != expected:
            return f"{name} damaged or replaced (sha256 differs from {artifact.EXPORT_FILE})"
    return None


def ensure_int8(
    out_dir: str | os.PathLike,
    task: str,
    config,
    settings: Int8Settings,
    workdir: str | os.PathLike | None = None,
) -> Path:
    """``out_dir/model_int8.xml`` for these settings, built (printing why) when it is
    missing, stale or damaged; ``out_dir`` must hold a checked float export
    (:func:`gac_jax.deploy.export.sources.ensure_export`); ``workdir``: the run, whose
    recorded dataset cache the calibration reads (:func:`calibration_source`).

    Raises:
      KittiFormatError: the calibration data cannot be read, or quantization fails (naming
        the file); ValueError: a ``keep_float`` pattern matches no layer.
    """
    out = Path(out_dir)
    meta = artifact.read_export(out)
    calibration = _calibration_key(task, config, settings, workdir)
    scope = float_scope(out / artifact.MODEL_FILE, settings)
    wanted = _wanted(meta, calibration, scope)
    why = _why_rebuild(out, meta.get("int8"), wanted)
    if why is None:
        return out / INT8_MODEL
    if scope:  # refuse a bad pattern before announcing the build
        ov = import_openvino()

        check_keep_float(ov.Core().read_model(str(out / artifact.MODEL_FILE)), scope)
    t0 = time.perf_counter()
    feeds, described = calibration_frames(task, config, settings.frames, settings.seed, workdir)
    used = f"{len(feeds)} calibration frames"
    if len(feeds) < settings.frames:
        used += f" (of {settings.frames} asked: the training split has {len(feeds)})"
    print(f"{out / INT8_MODEL}: {why}; quantizing (NNCF, {used})", flush=True)
    try:
        model = quantize_model(out / artifact.MODEL_FILE, feeds, scope)
    except ValueError:  # a keep_float pattern that matches nothing: the caller's message
        raise
    except Exception as e:  # NNCF / OpenVINO raise their own types
        text = str(e).strip().splitlines()
        raise KittiFormatError(
            out / artifact.MODEL_FILE, f"int8 quantization failed: {text[0] if text else e}"
        ) from None
    sums = _save_atomic(model, out)
    seconds = time.perf_counter() - t0
    meta["int8"] = {
        **wanted,
        "calibration_frames": described,
        "sha256": sums,
        "ir_sha256": ir_sha256(out),
        "libraries": _versions(),
        "seconds": round(seconds, 1),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    with atomic_write(out / artifact.EXPORT_FILE) as f:
        json.dump(meta, f, indent=2)
        f.write("\n")
    print(f"int8 model written to {out / INT8_MODEL} ({seconds:.0f} s)", flush=True)
    return out / INT8_MODEL


def _calibration_key(task: str, config, settings: Int8Settings, workdir=None) -> dict:
    """What selects the calibration frames (compared on use): split, data root, count, seed."""
    _, _, root = calibration_source(task, config, workdir)
    return {
        "split": config.data.train_split,
        "data_root": str(Path(root).resolve()),
        "frames": settings.frames,
        "seed": settings.seed,
    }
