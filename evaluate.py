"""KITTI evaluation entry point; see ``gac_jax/cli/evaluate.py`` (``python evaluate.py -h``)."""

import sys

from gac_jax.cpu_backend import apply_default_xla_flags

if __name__ == "__main__":
    apply_default_xla_flags()  # before JAX starts its backend
    from gac_jax.cli.evaluate import main

    sys.exit(main())
