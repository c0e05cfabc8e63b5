"""ONNX export of the GAC networks (``python -m gac_jax.deploy.export``).

``graph`` (ONNX graph builder, BatchNorm folding), ``networks`` (the detector and depth U-Net
re-stated in ONNX ops from Flax variables), ``sources`` (what is exported, from a workdir or a
loaded model), ``artifact`` (the ``model.onnx`` + ``export.json`` folder and its checks).
The runtimes that run the files are in :mod:`gac_jax.deploy.runtimes`.
"""
