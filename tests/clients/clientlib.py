"""Helpers for the real-program tests: find and run the programs, judge their screenshots.

A module with its own name (not conftest) so that test modules import it unambiguously.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent

TIMEOUT = 300  # seconds per program run


def require(program: str) -> str:
    """Absolute path of ``program``; fails (not skips) when absent: `make test-clients` installs it."""
    path = shutil.which(program)
    if path is None:
        pytest.fail(f"{program} is not installed; run `make test-clients` (it installs paraview, blender, "
                    f"chromium and xvfb with apt-get)")
    return path


# what a client prints when the virtual X server it was given is not (yet) accepting connections
X_NOT_READY = ("bad X server connection", "cannot open display", "Can't open display")


def run(cmd: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a client program; on a non-zero exit show its output in the failure.

    Under ``xvfb-run`` a program that could not connect to the X server is run once more: a
    clean-clone CI run once saw ParaView abort with "bad X server connection" on the display
    xvfb-run had just started, and pass three times in a row after it. Nothing the program
    checks is retried: only a start that never reached the program's own work."""
    def once() -> subprocess.CompletedProcess:
        return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT,
                              env={**os.environ, **(env or {})})

    proc = once()
    if proc.returncode != 0 and Path(cmd[0]).name == "xvfb-run" and any(m in proc.stderr for m in X_NOT_READY):
        print(f"{cmd[0]}: no X connection ({proc.returncode}); running it once more")
        proc = once()
    if proc.returncode != 0:
        pytest.fail(f"{cmd[0]} exited {proc.returncode}\nstdout:\n{proc.stdout[-4000:]}\n"
                    f"stderr:\n{proc.stderr[-4000:]}")
    return proc


def with_display(cmd: list[str]) -> list[str]:
    """Prefix ``xvfb-run`` when there is no X display (Debian's ParaView renders through X only)."""
    if os.environ.get("DISPLAY"):
        return cmd
    return [require("xvfb-run"), "-a", "-s", "-screen 0 1280x1024x24", *cmd]


def foreground_fraction(png: Path) -> float:
    """Fraction of pixels that differ clearly from the image's corner (background) colour."""
    import matplotlib.image as mpimg

    img = mpimg.imread(png)[..., :3].astype(np.float64)
    background = img[0, 0]
    return float((np.abs(img - background).max(axis=2) > 0.08).mean())
