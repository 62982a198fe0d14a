"""Build the sdist once per test run, for the sdist and interpreter smoke tests; and
``built_once``, which builds such a product once for every xdist worker of the run."""

from __future__ import annotations

import fcntl
import importlib.util
import os
import shutil
import subprocess
import sys
import tarfile
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: What a smoke run executes: the sans-I/O protocol tests and both timer back-ends, but
#: for the property tests (``-m "not hypothesis"``: README's test command runs them all,
#: on the default interpreter; they were more than half of each smoke run's time).
SMOKE_TESTS = (
    "tests/protocol",
    "tests/bus/test_timer.py",
    "tests/bus/test_timer_api.py",
    "-m",
    "not hypothesis",
)


def build_available() -> bool:
    """True if the ``build`` front-end is installed (it is in the test extra).  Found, not
    run: test_sdist.py asks at collection, in every worker."""
    return importlib.util.find_spec("build") is not None


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


def build_wheel(out_dir: Path, archive: Path) -> None:
    """Build the wheel of the sdist ``archive`` into ``out_dir``, as pip does when it
    installs the sdist (in an isolated build environment)."""
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out_dir), str(archive)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if done.returncode != 0:
        raise RuntimeError(f"pip wheel of the sdist failed:\n{(done.stdout + done.stderr)[-4000:]}")


def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel built from the sdist (``sdist``), once a run: pure Python, so every
    interpreter installs the same one."""
    archive, _ = sdist(tmp_path_factory)
    out_dir = built_once(tmp_path_factory, "wheel", lambda out: build_wheel(out, archive))
    (built,) = out_dir.glob("motorbus-*.whl")
    return built


def unpack(archive: Path, into: Path) -> Path:
    """Unpack ``archive`` below ``into``; returns the project folder it holds."""
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    (top,) = into.iterdir()
    return top
