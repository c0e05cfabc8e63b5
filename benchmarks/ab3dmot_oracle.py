"""3D MOT figures (sAMOTA, AMOTA, AMOTP) of a test case from AB3DMOT's own evaluation script.

    python benchmarks/ab3dmot_oracle.py --ab3dmot /path/to/AB3DMOT \
        [--out tests/data/tracking/ab3dmot_figures.json]

``--ab3dmot`` is a checkout of https://github.com/xinshuoweng/AB3DMOT (its
``scripts/KITTI/evaluate.py`` and ``AB3DMOT_libs``). That script imports numba (for ``jit``),
matplotlib (for its plots) and xinshuo_io; this script stands in for them (``jit`` does
nothing, no plot is drawn) and changes nothing else. It runs the script's ``evaluate`` on the
case of ``tests/tracking_cases.clean_3d_lines`` at 3D IoU 0.25 and 0.5, in a temporary
folder laid out as the script expects, and writes the figures it computes to the fixture
that tests/test_tracking_eval.py reads.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import types
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import tracking_cases  # noqa: E402


def _stand_ins() -> None:
    def jit(*args, **kwargs):
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda f: f

    sys.modules.setdefault("numba", types.SimpleNamespace(jit=jit, njit=jit))
    mpl = types.ModuleType("matplotlib")
    mpl.use = lambda *a, **k: None
    mpl.pyplot = types.ModuleType("matplotlib.pyplot")
    sys.modules.setdefault("matplotlib", mpl)
    sys.modules.setdefault("matplotlib.pyplot", mpl.pyplot)
    sys.modules.setdefault("xinshuo_io", types.SimpleNamespace(fileparts=None))


def run(checkout: Path, work: Path) -> dict:
    labels, results = tracking_cases.clean_3d_lines()
    kitti = work / "scripts" / "KITTI"
    (kitti / "label").mkdir(parents=True)
    data = work / "results" / "KITTI" / "case" / "data_0"
    data.mkdir(parents=True)
    seqmap = ""
    for seq, lines in labels.items():
        (kitti / "label" / f"{seq}.txt").write_text("".join(lines))
        (data / f"{seq}.txt").write_text("".join(results[seq]))
        n = 1 + max(int(line.split()[0]) for line in lines + results[seq])
        seqmap += f"{seq} empty 000000 {n - 1:06d}\n"
    (kitti / "evaluate_tracking.seqmap.val").write_text(seqmap)
    _stand_ins()
    sys.path[:0] = [str(checkout / "scripts" / "KITTI"), str(checkout)]
    import evaluate as ab3dmot  # the script itself

    figures, current = {}, {}

    def output(self):
        original_output(self)
        current[self.cls] = {"sAMOTA": self.sAMOTA, "AMOTA": self.amota, "AMOTP": self.amotp}

    ab3dmot.mail = ab3dmot.mailpy.Mail("")  # a global its __main__ block sets
    original_output = ab3dmot.stat.output
    ab3dmot.stat.output = output
    ab3dmot.stat.plot = lambda self: None
    cwd = os.getcwd()
    os.chdir(work)
    try:
        for thres in (0.25, 0.5):
            current.clear()
            with contextlib.redirect_stdout(io.StringIO()):
                ok = ab3dmot.evaluate("case", ab3dmot.mail, 1, True, False, thres)
            if not ok or "car" not in current:
                raise SystemExit(f"AB3DMOT's evaluation failed at IoU {thres}")
            figures[f"{thres:.2f}"] = {k: float(v) for k, v in current["car"].items()}
    finally:
        os.chdir(cwd)
    return figures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ab3dmot", required=True, help="path of an AB3DMOT checkout")
    parser.add_argument("--out", default=str(REPO / "tests/data/tracking/ab3dmot_figures.json"))
    args = parser.parse_args(argv)
    checkout = Path(args.ab3dmot).resolve()
    rev = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        figures = {"car": run(checkout, Path(tmp))}
    figures["_oracle"] = f"xinshuoweng/AB3DMOT@{rev or 'unknown'} scripts/KITTI/evaluate.py"
    Path(args.out).write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}: {json.dumps(figures['car'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
