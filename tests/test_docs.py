"""The documentation: the mkdocs site builds in strict mode, and every Python block runs.

``mkdocs build --strict`` fails on a broken link, a page left out of the navigation,
a docstring that names a parameter the signature does not have, or an API reference
(``::: motorbus.x``) that does not resolve.  The Python blocks of README.md and of
every page in docs/ are run as pasted, each in a fresh interpreter, against the
built-in simulators; a block may opt out only with a reason in the comment
``<!-- not run: REASON -->`` on the line before it.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests import packaging
from tests.helpers import LOADED_HOST_MARGIN_MS

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
HAS_MKDOCS = all(
    importlib.util.find_spec(name) is not None for name in ("mkdocs", "mkdocstrings_handlers")
)
needs_mkdocs = pytest.mark.skipif(not HAS_MKDOCS, reason="pip install -e '.[docs]'")
NOT_RUN = re.compile(r"<!-- not run: (.+?) -->\s*$")


def mkdocs(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def build_site(out: Path) -> None:
    r = mkdocs("build", "--strict", "--site-dir", str(out))
    assert r.returncode == 0, r.stderr[-4000:]


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site, built once for the tests that read it, whichever worker runs them (a
    strict build must pass)."""
    return packaging.built_once(tmp_path_factory, "site", build_site)


def api_page(site: Path, name: str) -> str:
    return (site / "api" / name / "index.html").read_text(encoding="utf-8")


@needs_mkdocs
@pytest.mark.timeout(300)
def test_the_site_builds_in_strict_mode_with_the_api_reference(site: Path) -> None:
    page = api_page(site, "devices")
    assert "motorbus.devices.la.InspireLA.move_to" in page  # rendered from the docstrings
    assert "ArrivalTimeoutError" in page


#: A reST role as the site would show it raw: ``:class:`X``` in the HTML (the backticks
#: turned into <code> by Markdown, or left as they are).
RAW_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|mod|data|exc|obj|const):(?:`|<code>)")


@needs_mkdocs
@pytest.mark.timeout(300)
def test_no_raw_rest_role_in_the_built_site(site: Path) -> None:
    # The docstrings do use roles (docs/_ext/griffe_motorbus.py turns them into links).
    sources = [p.read_text(encoding="utf-8") for p in (ROOT / "src").rglob("*.py")]
    assert sum(len(re.findall(r":(?:class|func|meth):`", s)) for s in sources) > 100
    raw = {
        str(page.relative_to(site)): len(RAW_ROLE.findall(page.read_text(encoding="utf-8")))
        for page in site.rglob("*.html")
    }
    assert not {page: n for page, n in raw.items() if n}, "raw reST roles in the site"
    assert "<autoref" not in "".join(p.read_text(encoding="utf-8") for p in site.rglob("*.html"))
    # ":class:`Streamer`" in motorbus.streams' docstring is a link to where it is documented.
    link = re.search(
        r'<a class="autorefs[^"]*"[^>]*href="([^"]*)"><code>Streamer</code></a>',
        api_page(site, "streams"),
    )
    assert link is not None and link[1] == "#motorbus.streams.Streamer"


def documented(site: Path) -> list[str]:
    """The identifiers of every object the API pages render, with repeats."""
    return [
        m[1]
        for page in sorted((site / "api").rglob("*.html"))
        for m in re.finditer(
            r'<h\d id="(motorbus[^"]*)" class="doc doc-heading', page.read_text(encoding="utf-8")
        )
    ]


@needs_mkdocs
@pytest.mark.timeout(300)
def test_each_public_name_is_documented_once(site: Path) -> None:
    import griffe

    import motorbus

    pkg = griffe.load(
        "motorbus", search_paths=[str(ROOT / "src")], resolve_aliases=True, resolve_external=False
    )

    def canonical(path: str) -> str:
        obj = pkg[path.removeprefix("motorbus.")] if path != "motorbus" else pkg
        return str(obj.final_target.path if obj.is_alias else obj.path)

    where: dict[str, list[str]] = {}
    for ident in documented(site):
        where.setdefault(canonical(ident), []).append(ident)
    twice = {path: ids for path, ids in where.items() if len(ids) > 1}
    assert not twice, f"documented more than once: {twice}"
    # motorbus.sim re-exports SimProcess: it is documented where it is defined.
    assert where["motorbus.sim.process.SimProcess"] == ["motorbus.sim.process.SimProcess"]
    exported = [name for name in motorbus.__all__ if name != "__version__"]
    missing = [name for name in exported if canonical(f"motorbus.{name}") not in where]
    assert not missing, f"motorbus exports these, no API page documents them: {missing}"


@needs_mkdocs
@pytest.mark.timeout(300)
def test_internals_are_left_out_of_the_api_pages(site: Path) -> None:
    ids = set(documented(site))
    for public in ("Stream.stop", "Stream.wait", "Stream.set_targets", "Streamer.follow"):
        assert f"motorbus.streams.{public}" in ids
    internal = [
        "Stream.end",
        "Stream.next_targets",
        "Stream.apply_safe_action",
        "Stream.poll_id",
        "Stream.poll_done",
        "Streamer.let_go",
        "Streamer.discard",
    ]
    shown = [name for name in internal if any(i.endswith(f".{name}") for i in ids)]
    assert not shown, f"internals in the API pages: {shown}"
    assert not [i for i in ids if re.search(r"\.__\w+__$", i)]  # no __repr__ and co.


def field_descriptions(page: str, cls: str) -> dict[str, str]:
    """The rendered description of each documented field of ``cls``, as text."""
    out = {}
    for m in re.finditer(rf'id="{re.escape(cls)}\.(\w+)" class="doc doc-heading', page):
        body = page[m.end() : m.end() + 4000]
        text = re.search(r'<div class="doc doc-contents[^"]*">(.*?)</div>', body, re.S)
        out[m[1]] = re.sub(r"<[^>]+>", "", text[1]) if text else ""
    return out


@needs_mkdocs
@pytest.mark.timeout(300)
def test_stream_stats_fields_are_described_with_units_and_the_late_threshold(
    site: Path,
) -> None:
    import dataclasses

    from motorbus.streaming.model import LATE_AFTER_S
    from motorbus.streams import StreamStats

    described = field_descriptions(api_page(site, "streams"), "motorbus.streams.StreamStats")
    for f in dataclasses.fields(StreamStats):
        assert described.get(f.name, "").strip(), f"StreamStats.{f.name} has no description"
    threshold = f"{LATE_AFTER_S * 1e3:g} ms"  # the threshold the code uses, as the doc says it
    assert threshold in described["late"] and "LATE_AFTER_S" in described["late"]
    assert "seconds" in described["jitter"] and "microseconds" in described["jitter"]


@needs_mkdocs
@pytest.mark.timeout(300)
def test_a_broken_api_reference_fails_the_strict_build(tmp_path: Path) -> None:
    # A package of one module stands in for motorbus: what is tested is that a strict
    # build fails on a reference that does not resolve (loading all of motorbus took 9 s).
    docs, src = tmp_path / "docs", tmp_path / "src" / "tinypkg"
    docs.mkdir()
    src.mkdir(parents=True)
    (src / "__init__.py").write_text('"""A package."""\n\n\ndef there() -> None:\n    """Yes."""\n')
    (docs / "index.md").write_text("# x\n\n::: tinypkg.there\n\n::: tinypkg.NoSuchThing\n")
    (tmp_path / "mkdocs.yml").write_text(
        "site_name: x\nplugins:\n  - mkdocstrings:\n      handlers:\n        python:\n"
        f"          paths: [{src.parent}]\n"
    )
    r = mkdocs("build", "--strict", "--site-dir", str(tmp_path / "site"), cwd=tmp_path)
    assert r.returncode != 0
    assert "NoSuchThing" in r.stderr


def python_blocks() -> list[tuple[str, str]]:
    """``(where, code)`` of every Python block in README.md and docs/, opt-outs left out."""
    found = []
    for path in DOC_FILES:
        lines = path.read_text(encoding="utf-8").splitlines()
        i = 0
        while i < len(lines):
            if lines[i].strip() == "```python":
                start = i
                i += 1
                body = []
                while lines[i].strip() != "```":
                    body.append(lines[i])
                    i += 1
                reason = NOT_RUN.search(lines[start - 1]) if start else None
                if reason is None:
                    where = f"{path.relative_to(ROOT)}:{start + 1}"
                    found.append((where, "\n".join(body) + "\n"))
            i += 1
    return found


BLOCKS = python_blocks()


def test_there_are_blocks_to_run_and_opt_outs_give_a_reason() -> None:
    assert len(BLOCKS) >= 10
    for path in DOC_FILES:
        text = path.read_text(encoding="utf-8")
        for comment in re.findall(r"<!-- not run:(.*?)-->", text):
            assert len(comment.strip()) > 10, f"{path.name}: say why a block is not run"


@pytest.mark.parametrize(("where", "code"), BLOCKS, ids=[w for w, _ in BLOCKS])
@pytest.mark.timeout(180)
def test_every_python_block_runs_as_pasted(where: str, code: str, tmp_path: Path) -> None:
    # Tests assert behaviour, not speed: a loaded CI machine gets the tests' loaded-machine
    # host margin (a quad run's reply timed out at 50 ms with eight workers).
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": str(LOADED_HOST_MARGIN_MS)}
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert r.returncode == 0, f"{where}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"


def test_architecture_says_why_each_dependency() -> None:
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    names = [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        names += [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in extra]
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    deps = text[text.index("## Dependencies, and why these") :]
    missing = sorted({n for n in names if f"`{n}`" not in deps})
    assert not missing, f"docs/architecture.md does not say why {missing}"


def test_every_benchmark_script_says_what_published_figure_it_feeds() -> None:
    # Issue 40: each script in benchmarks/ feeds a published figure, named in the table
    # of benchmarks/README.md; a module that serves them is named below it.
    text = (ROOT / "benchmarks" / "README.md").read_text(encoding="utf-8")
    table = text[: text.index("Modules, not benchmarks:")]
    modules = text[text.index("Modules, not benchmarks:") :].split("\n\n", 1)[0]
    rows = set(re.findall(r"^\| `([a-z0-9_]+\.py)`", table, re.MULTILINE))
    named = set(re.findall(r"`([a-z0-9_]+\.py)`", modules))
    scripts = {p.name for p in (ROOT / "benchmarks").glob("*.py")}
    assert not scripts - rows - named, f"not in benchmarks/README.md: {scripts - rows - named}"
    assert not rows - scripts, f"rows for scripts that are gone: {rows - scripts}"
    for row in re.findall(r"^\| `[a-z0-9_]+\.py`.*$", table, re.MULTILINE):
        where = row.rstrip(" |").rsplit("|", 1)[1].strip()
        assert where and "nowhere" not in where, row


#: A unit, in a field's description: what the number counts or measures.
UNIT = re.compile(r"\b(ms|seconds?|units(/s)?|mA|grams|Hz|degrees|percent|no unit)\b")


RIG_VALUES = [
    "analysis.Sample",
    "analysis.StepFigures",
    "analysis.FrequencyPoint",
    "analysis.TrackFigures",
    "analysis.RepeatFigures",
    "runner.DeviceResult",
    "runner.RigResult",
]


@needs_mkdocs
@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", RIG_VALUES)
def test_rig_values_are_described_field_by_field_with_their_unit(site: Path, name: str) -> None:
    import dataclasses
    import importlib

    module, cls = name.split(".")
    value_type = getattr(importlib.import_module(f"motorbus.rig.{module}"), cls)
    described = field_descriptions(api_page(site, "rig"), f"motorbus.rig.{name}")
    for f in dataclasses.fields(value_type):
        text = described.get(f.name, "")
        assert text.strip(), f"{name}.{f.name} has no description"
        if f.type == "float":
            assert UNIT.search(text), f"{name}.{f.name}: no unit in {text.strip()!r}"


@needs_mkdocs
@pytest.mark.timeout(300)
def test_bus_stats_fields_are_described_with_units_and_the_late_threshold(site: Path) -> None:
    import dataclasses

    from motorbus.bus.matching import LATE_WINDOW_S
    from motorbus.bus.stats import BusStats, DeviceStats, LatencyHistogram

    page = api_page(site, "bus")
    for cls in (BusStats, DeviceStats, LatencyHistogram):
        described = field_descriptions(page, f"motorbus.bus.stats.{cls.__name__}")
        for f in dataclasses.fields(cls):
            text = described.get(f.name, "")
            assert text.strip(), f"{cls.__name__}.{f.name} has no description"
            if f.type == "float":
                assert UNIT.search(text), f"{cls.__name__}.{f.name}: no unit in {text!r}"
    late = field_descriptions(page, "motorbus.bus.stats.BusStats")["late_replies"]
    assert f"{LATE_WINDOW_S:g} s" in late and "LATE_WINDOW_S" in late


TOY_MODULE = '''\
"""A toy package: :class:`Thing` and :func:`~toypkg.make`; see :mod:`asyncio`."""

import asyncio

__all__ = ["Thing", "make"]


class Thing:
    """A thing; :meth:`go` starts it, :meth:`Hidden.x <toypkg.make>` is titled."""

    def go(self) -> None:
        """Go; the loop is an :class:`asyncio.AbstractEventLoop`.  ROLE_HERE"""


def make() -> Thing:
    """Make a :class:`Thing` (:meth:`Thing.go` it next)."""
    return Thing()


def _helper() -> None:
    """Private."""
'''


def build_toy(tmp_path: Path, extra_role: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    pkg = tmp_path / "src" / "toypkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(TOY_MODULE.replace("ROLE_HERE", extra_role))
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "index.md").write_text("# Toy\n\n::: toypkg\n")
    ext = ROOT / "docs" / "_ext" / "griffe_motorbus.py"
    (tmp_path / "mkdocs.yml").write_text(
        "site_name: toy\nplugins:\n  - mkdocstrings:\n      handlers:\n        python:\n"
        f"          paths: [src]\n          options:\n            filters: public\n"
        "            show_source: false\n"
        f"            extensions:\n              - {ext}:\n                  package: toypkg\n"
        f"                  pages: {tmp_path / 'docs'}\n"
    )
    site = tmp_path / "site"
    return mkdocs("build", "--strict", "--site-dir", str(site), cwd=tmp_path), site


@needs_mkdocs
@pytest.mark.timeout(300)
def test_roles_become_links_where_python_would_resolve_the_name(tmp_path: Path) -> None:
    r, site = build_toy(tmp_path, "")
    assert r.returncode == 0, r.stderr[-4000:]
    page = (site / "index.html").read_text(encoding="utf-8")
    assert not RAW_ROLE.search(page)

    def link(title: str) -> list[str]:
        pattern = rf'<a class="autorefs[^"]*"[^>]*href="([^"]*)"><code>{re.escape(title)}</code>'
        return re.findall(pattern, page)

    assert link("Thing") == ["#toypkg.Thing", "#toypkg.Thing"]  # from the module, a function
    assert link("make") == ["#toypkg.make"]  # ``~toypkg.make``: the last part shown
    assert link("go") == ["#toypkg.Thing.go"]  # a method named from its class
    assert link("Thing.go") == ["#toypkg.Thing.go"]
    assert link("Hidden.x") == ["#toypkg.make"]  # ``title <target>``
    # Another library's names stay plain code: the site has no page for them.
    assert "<code>asyncio</code>" in page and "<code>asyncio.AbstractEventLoop</code>" in page


@needs_mkdocs
@pytest.mark.timeout(300)
def test_a_role_that_names_nothing_fails_the_strict_build(tmp_path: Path) -> None:
    r, _ = build_toy(tmp_path, ":func:`nowhere`")
    assert r.returncode != 0
    assert "names nothing" in r.stderr and ":func:`nowhere`" in r.stderr


@needs_mkdocs
@pytest.mark.timeout(300)
def test_a_role_to_a_name_the_site_does_not_render_is_plain_code(tmp_path: Path) -> None:
    r, site = build_toy(tmp_path, ":func:`_helper`")  # real, but private: not rendered
    assert r.returncode == 0, r.stderr[-4000:]
    page = (site / "index.html").read_text(encoding="utf-8")
    assert "<code>_helper</code>" in page and 'href="#toypkg._helper"' not in page
