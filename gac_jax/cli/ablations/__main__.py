"""``python -m gac_jax.cli.ablations``: the ablation runner (see :mod:`.runner`)."""

import sys

from gac_jax.cli.ablations.runner import main

if __name__ == "__main__":
    sys.exit(main())
