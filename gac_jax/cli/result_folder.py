"""A resumable result folder: ``run.json`` records what its result files depend on.

``evaluate.py`` and the accuracy guard write one result file per frame as they go and, when run
again, keep the files already there. ``run.json`` holds the settings they were made with; a run
with other settings:

- other *weights or network* (the weights' sha256, the exported graph, the int8 model, the
  runtime's version: :data:`IDENTITY_KEYS`) starts the folder again, removing its result files
  and saying why in one line: they describe a model that no longer runs here;
- anything else (split, data, config, runtime, precision) is refused, naming what differs:
  those are different experiments, and which one the user wants is theirs to say.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.trained.fingerprint import short

IDENTITY_KEYS = ("weights_sha256", "network")


def check_resumable(path: Path, settings: dict, results: Path) -> None:
    """Records ``settings`` in ``path`` (``run.json``), or checks them against the stored ones.

    Args:
      path: the folder's ``run.json``; settings: what the results depend on (JSON-able);
        results: the folder of result files (emptied when the weights or network differ).

    Raises:
      KittiFormatError: the stored settings differ in anything but the weights' identity.
    """
    canonical = json.loads(json.dumps(settings, default=str))
    if path.exists():
        try:
            stored = json.loads(path.read_text())
        except ValueError:
            stored = {}
        if stored == canonical:
            return
        keys = sorted(k for k in set(stored) | set(canonical) if stored.get(k) != canonical.get(k))
        if not set(keys) <= set(IDENTITY_KEYS):
            raise KittiFormatError(
                path,
                f"the results here were made with other settings ({', '.join(keys)} differ); "
                f"delete {path.parent} to evaluate again",
            )
        if stored.get("weights_sha256") != canonical.get("weights_sha256"):
            why = (
                f"other weights (sha256 {short(stored.get('weights_sha256'))}, these are "
                f"{short(canonical.get('weights_sha256'))})"
            )
        else:
            why = "another exported network (graph, int8 model or runtime version)"
        print(f"starting {path.parent} again: its results were made from {why}", flush=True)
        if results.exists():
            shutil.rmtree(results)
    with atomic_write(path) as f:
        json.dump(canonical, f, indent=2)
        f.write("\n")
