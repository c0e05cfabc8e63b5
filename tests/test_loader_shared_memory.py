"""Loader worker batches leave no shared memory behind (grain 0.2.x, Python 3.11).

grain's worker batches arrive in shared-memory blocks; a block still linked when the program
ends makes Python's resource_tracker print "There appear to be N leaked shared_memory objects
to clean up at shutdown". Each case runs a small program as its own process (the warning is
printed when that process's resource tracker ends) and reads its stderr: the loop run to its
end, closed early, and left open when the program exits. (A whole tiny depth training with
two loader workers and evaluation at the end is checked the same way in
tests/test_first_run.py.)
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PROGRAM = textwrap.dedent(
    """
    import sys
    import numpy as np
    from gac_jax.data.loader import Loader

    class Source:
        def __len__(self):
            return 64

        def __getitem__(self, i):
            return {"x": np.full((32, 32, 3), i, np.float32), "frame_id": f"{i:06d}"}

    def to_arrays(sample):
        return {"x": sample["x"], "frame_id": np.asarray(sample["frame_id"], dtype=str)}

    if __name__ == "__main__":
        mode = sys.argv[1]
        loader = Loader(Source(), None, to_arrays, batch_size=4, worker_count=2, shuffle=False)
        batches = loader.iterate(0, 10)
        seen = []
        for batch in batches:
            seen.extend(batch["x"][:, 0, 0, 0].astype(int).tolist())
            if mode != "to_the_end" and len(seen) == 12:
                break
        if mode == "closed_early":
            batches.close()
        want = 40 if mode == "to_the_end" else 12
        assert seen == list(range(want)), seen
        print("done", mode, flush=True)
    """
)


@pytest.mark.parametrize("mode", ["to_the_end", "closed_early", "left_open"])
def test_no_shared_memory_leaks_at_exit(mode, tmp_path):
    script = tmp_path / "loader_program.py"
    script.write_text(PROGRAM)
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])
    )
    proc = subprocess.run(
        [sys.executable, str(script), mode],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"done {mode}" in proc.stdout
    assert "resource_tracker" not in proc.stderr, proc.stderr[-3000:]
    assert "leaked shared_memory" not in proc.stderr, proc.stderr[-3000:]
