"""gmsh leaves the process's signal handling as it found it (:mod:`regtrack._gmsh`).

gmsh's initialisation sets SIGPIPE to terminate the process and (Python API) SIGINT to the
default action.  A test run that had meshed in-process then died of SIGPIPE when a
process-pool worker died (``tests/test_pipeline_concurrent.py``), instead of the pool
raising ``BrokenPipeError``.  Each check runs in a fresh interpreter, since a failure
would kill the process it runs in."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("gmsh")

REPO = str(Path(__file__).resolve().parents[1])

AFTER_MESHING = """
import os, signal
from regtrack.mechanics.meshes import hemisphere_model
hemisphere_model(radius=20.0, lc=10.0)
r, w = os.pipe()
os.close(r)
try:
    os.write(w, b"x")
except BrokenPipeError:
    print("SIGPIPE ignored")
try:
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(1000):
        pass
except KeyboardInterrupt:
    print("SIGINT raised KeyboardInterrupt")
"""


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_after_meshing_sigpipe_and_sigint_behave_as_in_python():
    proc = subprocess.run([sys.executable, "-c", AFTER_MESHING], cwd=REPO, capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.split("\n")[:2] == ["SIGPIPE ignored", "SIGINT raised KeyboardInterrupt"]
