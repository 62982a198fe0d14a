"""Build the sdist once per test session, for the sdist and interpreter smoke tests."""

from __future__ import annotations

import atexit
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What a smoke run executes: the sans-I/O protocol tests and both timer back-ends.
SMOKE_TESTS = ("tests/protocol", "tests/bus/test_timer.py", "tests/bus/test_timer_api.py")

_built: tuple[Path, str] | None = None


def build_available() -> bool:
    """True if the ``build`` front-end is installed (it is in the test extra)."""
    out = subprocess.run(
        [sys.executable, "-m", "build", "--version"], capture_output=True, timeout=60
    )
    return out.returncode == 0


def sdist() -> tuple[Path, str]:
    """The sdist of this tree and the build's output; built on first use, removed at exit."""
    global _built
    if _built is None:
        out_dir = Path(tempfile.mkdtemp(prefix="motorbus-sdist-"))
        atexit.register(shutil.rmtree, out_dir, True)
        done = subprocess.run(
            [sys.executable, "-m", "build", "--sdist", "--outdir", str(out_dir), str(ROOT)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        log = done.stdout + done.stderr
        if done.returncode != 0:
            raise RuntimeError(f"python -m build --sdist failed:\n{log[-4000:]}")
        (archive,) = out_dir.glob("motorbus-*.tar.gz")
        _built = (archive, log)
    return _built


def unpack(archive: Path, into: Path) -> Path:
    """Unpack ``archive`` below ``into``; returns the project folder it holds."""
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    (top,) = into.iterdir()
    return top
