"""``tests.packaging.built_once``: with ``pytest -n``, a product the tests share (the
sdist, the docs site) is built by one worker while the others wait, then read by all."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from tests import packaging


class WorkerTemp:
    """What ``built_once`` asks of ``tmp_path_factory``: a worker's base folder."""

    def __init__(self, base: Path) -> None:
        self.base = base

    def getbasetemp(self) -> Path:
        return self.base


def test_workers_asking_at_once_get_one_build(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")  # the run's folder is the parent
    builds: list[str] = []

    def build(out: Path) -> None:
        builds.append(threading.current_thread().name)
        time.sleep(0.2)  # long enough for every other worker to ask meanwhile
        (out / "product").write_text("built", encoding="utf-8")

    got: dict[str, Path] = {}

    def worker(name: str) -> None:
        (tmp_path / name).mkdir()
        got[name] = packaging.built_once(WorkerTemp(tmp_path / name), "thing", build)  # type: ignore[arg-type]

    threads = [threading.Thread(target=worker, args=(f"gw{i}",), name=f"gw{i}") for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert len(builds) == 1
    assert set(got.values()) == {tmp_path / "thing"}
    assert (tmp_path / "thing" / "product").read_text(encoding="utf-8") == "built"


def test_a_build_that_failed_is_tried_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)  # pytest without -n

    def broken(out: Path) -> None:
        (out / "half").write_text("", encoding="utf-8")
        raise RuntimeError("the build failed")

    with pytest.raises(RuntimeError, match="the build failed"):
        packaging.built_once(WorkerTemp(tmp_path), "thing", broken)  # type: ignore[arg-type]
    out = packaging.built_once(WorkerTemp(tmp_path), "thing", lambda o: None)  # type: ignore[arg-type]
    assert out == tmp_path / "thing" and not (out / "half").exists()
