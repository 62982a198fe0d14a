"""The oldest and newest supported Pythons (3.11, 3.13), and the one running the tests,
install the sdist and pass its own smoke tests.

README's test command runs the whole suite once, on the default ``python3``; this test
runs the sdist's sans-I/O protocol tests (but for the property tests, which the whole
suite runs) and both timer back-ends (tests/bus/test_timer_api.py forces the
``os.timerfd_*`` and the ctypes branch), from the unpacked sdist, under each supported
interpreter found on the machine (and under this one when it is the only one: it runs
the whole suite, installed by README's test line), each in a fresh venv with the
sdist's wheel installed the way a user would (pip builds the wheel from the sdist once
a run: it is pure Python, the same for every interpreter).  That the sdist's own tests
pass from the installed wheel is tests/test_sdist.py's promise, kept here.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests import packaging

#: The oldest and the newest Python that pyproject.toml's classifiers promise.
SUPPORTED = ((3, 11), (3, 13))
#: This interpreter's version.
THIS = (sys.version_info[0], sys.version_info[1])
#: Those and this interpreter's version, each once.
VERSIONS = sorted({*SUPPORTED, THIS})
#: What the smoke run needs besides motorbus (pytest-timeout: pyproject sets a timeout).
TEST_DEPS = ("pytest", "pytest-asyncio", "hypothesis", "pytest-timeout")


def _version_of(python: str) -> tuple[int, int] | None:
    try:
        out = subprocess.run(
            [python, "-c", "import sys; print(*sys.version_info[:2])"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except OSError:
        return None
    if out.returncode != 0:
        return None
    major, minor = out.stdout.split()
    return int(major), int(minor)


def find_python(version: tuple[int, int]) -> str | None:
    """An interpreter of ``version``: this one, ``python3.X`` on PATH, or a pyenv build."""
    major, minor = version
    candidates = []
    if sys.version_info[:2] == version:
        candidates.append(sys.executable)
    candidates.append(shutil.which(f"python{major}.{minor}"))
    pyenv = os.environ.get("PYENV_ROOT", os.path.expanduser("~/.pyenv"))
    candidates += sorted(glob.glob(f"{pyenv}/versions/{major}.{minor}.*/bin/python3"))
    candidates.append(f"/usr/bin/python{major}.{minor}")
    for python in candidates:
        if python and os.access(python, os.X_OK) and _version_of(python) == version:
            return python
    return None


def run(cmd: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.timeout(400)
@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: f"py{v[0]}.{v[1]}")
def test_smoke_run_on_each_supported_python(
    version: tuple[int, int], tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    python = find_python(version)
    if python is None:
        pytest.skip(f"Python {version[0]}.{version[1]} is not installed on this machine")
    if version == THIS and any(v != THIS and find_python(v) for v in VERSIONS):
        # This interpreter runs the whole suite, after README's test line installed the
        # project on it; the installed wheel's smoke run goes on the others (15 s here).
        pytest.skip(
            f"Python {THIS[0]}.{THIS[1]} runs the whole suite; the wheel's smoke runs elsewhere"
        )
    if not packaging.build_available():
        pytest.skip("the 'build' front-end is not installed (pip install .[test])")
    archive, _ = packaging.sdist(tmp_path_factory)
    project = packaging.unpack(archive, tmp_path / "src")
    venv = tmp_path / "venv"
    # The venv without a pip of its own: this pip installs into it, run by the venv's
    # interpreter (``pip --python``), as the venv's own pip would (ensurepip, which
    # unpacks and compiles a pip for every venv, was a third of this test's time).
    made = run([python, "-m", "venv", "--without-pip", str(venv)], tmp_path, 120)
    assert made.returncode == 0, made.stdout + made.stderr
    vpython = str(venv / "bin" / "python")
    pip = [sys.executable, "-m", "pip", "--python", vpython]
    # --no-compile, as README's test line: the smoke run compiles what it imports (a
    # fraction of pytest's and hypothesis's modules), pip would compile them all.
    wheel = str(packaging.wheel(tmp_path_factory))
    installed = run([*pip, "install", "-q", "--no-compile", wheel, *TEST_DEPS], tmp_path, 300)
    assert installed.returncode == 0, installed.stdout[-3000:] + installed.stderr[-3000:]
    where = run([vpython, "-c", "import motorbus; print(motorbus.__file__)"], project, 60)
    assert Path(where.stdout.strip()).is_relative_to(venv), where.stdout + where.stderr
    smoke = run(
        [vpython, "-m", "pytest", "-q", "-p", "no:cacheprovider", *packaging.SMOKE_TESTS],
        project,
        240,
    )
    assert smoke.returncode == 0, smoke.stdout[-4000:] + smoke.stderr[-2000:]
    assert " passed" in smoke.stdout and " failed" not in smoke.stdout
    # both timerfd branches ran for real, none skipped
    assert "skipped" not in smoke.stdout.splitlines()[-1], smoke.stdout[-2000:]
