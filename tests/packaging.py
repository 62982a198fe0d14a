"""Build the sdist once per test run, for the sdist and interpreter smoke tests; and
``built_once``, which builds such a product once for every xdist worker of the run."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import tarfile
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: What a smoke run executes: the sans-I/O protocol tests and both timer back-ends.
SMOKE_TESTS = ("tests/protocol", "tests/bus/test_timer.py", "tests/bus/test_timer_api.py")


def build_available() -> bool:
    """True if the ``build`` front-end is installed (it is in the test extra)."""
    out = subprocess.run(
        [sys.executable, "-m", "build", "--version"], capture_output=True, timeout=60
    )
    return out.returncode == 0


def built_once(
    tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]
) -> Path:
    """The folder ``name`` that ``build(folder)`` filled, built once for the whole run.

    With ``pytest -n``, every worker has its own base temporary folder, below one shared
    by the run: the first worker to ask builds there while the others wait on a lock,
    and then they all read the same folder.  A build that raised is tried again by the
    next worker to ask (which then fails the same way).
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # pytest-N/, shared by this run's workers only
    out = root / name
    done = out / ".built"
    with (root / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            build(out)
            done.touch()
    return out


def build_sdist(out_dir: Path) -> None:
    """Build the sdist of this tree into ``out_dir``, the build's output beside it."""
    done = subprocess.run(
        [sys.executable, "-m", "build", "--sdist", "--outdir", str(out_dir), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    log = done.stdout + done.stderr
    if done.returncode != 0:
        raise RuntimeError(f"python -m build --sdist failed:\n{log[-4000:]}")
    (out_dir / "build.log").write_text(log, encoding="utf-8")


def sdist(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The sdist of this tree and the build's output; built once a run (``built_once``)."""
    out_dir = built_once(tmp_path_factory, "sdist", build_sdist)
    (archive,) = out_dir.glob("motorbus-*.tar.gz")
    return archive, (out_dir / "build.log").read_text(encoding="utf-8")


def unpack(archive: Path, into: Path) -> Path:
    """Unpack ``archive`` below ``into``; returns the project folder it holds."""
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    (top,) = into.iterdir()
    return top
