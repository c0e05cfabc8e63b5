"""The guard decides on the detections its result files hold, whether it predicted them now
or resumed them (gac_jax.cli.guard._predict): a later look on the same frames reads the files,
so a fresh run must decide on the same detections, not on unrounded ones (bounding boxes are
written to 0.01 px; a detection at a size or overlap boundary moved a handful of count rows
between the first run and a rerun)."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np

from gac_jax.cli import guard
from gac_jax.data.sources import open_object_source
from gac_jax.trained.run_config import load_run_config


def test_a_fresh_run_and_its_resumption_give_the_same_detections(
    tiny_detect3d_workdir, kitti_object_root, tmp_path
):
    wd = tmp_path / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "export"))
    config = load_run_config(wd, None, None, None)
    source = open_object_source(kitti_object_root, config.data.val_split, use_right_image=False)
    out = tmp_path / "jax_f32"

    def run():
        found, *_ = guard._predict(wd, config, None, source, "jax", "f32", None, out, None, 1)
        return found

    fresh = run()
    assert len(fresh) and sum(map(len, fresh.values())), "the tiny detector found nothing"
    resumed = run()  # every result file exists now: read back, nothing predicted
    assert list(resumed) == list(fresh)
    for fid, objects in fresh.items():
        for field in dataclasses.fields(objects):
            a, b = getattr(objects, field.name), getattr(resumed[fid], field.name)
            np.testing.assert_array_equal(a, b, err_msg=f"frame {fid}: {field.name}")
