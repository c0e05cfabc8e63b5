"""KITTI evaluation entry point; see ``gac_jax/evaluation/cli.py`` (``python evaluate.py -h``)."""

import sys

from gac_jax.evaluation.cli import main

if __name__ == "__main__":
    sys.exit(main())
