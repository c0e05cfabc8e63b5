"""Video files, cameras and image sequences through a trained detector, frame by frame.

:mod:`~gac_jax.streams.sources` reads frames with their calibration (and ground plane);
:mod:`~gac_jax.streams.pipeline` overlaps reading, the network, post-processing + drawing and
writing on threads; :mod:`~gac_jax.streams.outputs` writes the annotated video and the
per-frame results; :mod:`~gac_jax.streams.rates` measures frames/s and latency. The command
is ``python -m gac_jax.cli.predict --video/--camera/--sequence/--clip``.
"""
