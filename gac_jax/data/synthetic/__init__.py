"""Procedural KITTI-format driving scenes for 3D detection and depth (real KITTI not needed).

Usage::

    python -m gac_jax.data.synthetic --out DIR --num 1000 --seed 0

    from gac_jax.data.synthetic import generate_dataset
    generate_dataset("DIR", 1000, seed=0)   # idempotent; resumes interrupted runs

Driving clips (10 Hz, KITTI tracking layout, labels with track ids, planes, poses)::

    python -m gac_jax.data.synthetic --out DIR --sequences 2 --frames-per-sequence 100

    from gac_jax.data.synthetic.clips import ensure_clips
    root = ensure_clips(None, 1, 100)       # the cached default clip, generated on first use

Each frame is a straight road seen from a car (camera 1.65 +- 0.05 m above the
road, pitch within +-1 deg) with lanes, kerbs, sidewalks, buildings, trees and
poles, and 3-8 Cars plus Pedestrians and Cyclists with KITTI's size statistics
at 4-70 m. Both colour cameras (P2, P3: real KITTI intrinsics, 0.54 m
baseline) are rendered with exact per-pixel depth; labels, dense depth and
LiDAR-like sparse depth are derived from the renders.

Modules:

* ``calibration`` - camera rigs (real KITTI intrinsics), calib file contents.
* ``rigs`` - rig sets: KITTI's (default) or eight vehicles with ground planes (``--rigs multi``).
* ``shapes`` - convex solids; part models of cars, pedestrians, cyclists.
  ``vehicles`` - vans and trucks (``--large-vehicles``).
* ``scene`` / ``roadside`` - sampling a scene (road, roadside, road users, light);
  ``gardens`` - urban buildings set back behind front gardens (``--gardens``).
* ``render`` - ray-casting z-buffer rasteriser; ``materials`` - surface appearance.
* ``domain_randomization`` - random colours and patterns on the background (``--randomize``)
  and on the cars (``--randomize-cars``);
  ``photo_textures`` - detail from photographs of grass and gravel (``--photo``).
* ``labels`` - KITTI labels from a render; ``lidar`` - sparse depth sampling.
* ``frame`` - one frame in memory; ``writer`` - the layout on disk, resumable.
* ``traffic`` - road users that move through a clip; ``drive`` - a clip's world, ego motion
  and frames; ``clips`` - clips in the KITTI tracking layout, resumable, and the clip cache.
"""

from gac_jax.data.synthetic.writer import GenerationResult, generate_dataset

__all__ = ["GenerationResult", "generate_dataset"]
