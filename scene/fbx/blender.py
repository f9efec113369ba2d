"""Headless Blender as a tool: find it, run ``blender_side.py`` in it (the tests' and benchmarks' sampling of
an exported file, ``tests/blender_sampling.py``, runs it the same way).

The project has no FBX writer of its own (no open one on PyPI writes skin and blend-shape animation);
Blender's does.  Blender is found as ``$BLENDER`` or ``blender`` on the PATH; its own Python needs numpy
(Debian: ``apt-get install blender python3-numpy``).
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from base.errors import InputError

SCRIPT = Path(__file__).with_name("blender_side.py")
INSTALL_HINT = ("apt-get install blender python3-numpy (Debian, Ubuntu), or Blender 3.x/4.x from "
                "blender.org with BLENDER=/path/to/blender")


class BlenderMissing(InputError):
    """Blender is not installed where the project looks for it."""


def blender_executable(purpose: str = "export=[fbx]") -> str:
    """The Blender to run (``$BLENDER``, else ``blender`` on the PATH); BlenderMissing saying how to get one."""
    found = os.environ.get("BLENDER") or shutil.which("blender")
    if not found or not Path(found).is_file():
        raise BlenderMissing(f"{purpose} needs Blender, which is not installed: {INSTALL_HINT}")
    return found


def run_blender(*arguments: str, purpose: str = "export=[fbx]", timeout: float = 600.0) -> str:
    """Run ``blender_side.py`` with ``arguments`` in background Blender; its output, or InputError with
    the last lines Blender printed."""
    blender = blender_executable(purpose)
    # Blender's Python takes its prefix from the first ``python3.x`` on the PATH; run from a pyenv or
    # virtualenv Python, that is the caller's (without Blender's numpy): Blender's own folder goes first.
    env = {**os.environ, "PATH": os.pathsep.join([str(Path(blender).resolve().parent), os.environ.get("PATH", "")])}
    command = [blender, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "1",
               "--python", str(SCRIPT), "--", *arguments]
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env)
    if result.returncode != 0:
        lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
        raise InputError(f"{purpose}: Blender failed ({' '.join(arguments[:2])}): " + " | ".join(lines[-4:]))
    return result.stdout
