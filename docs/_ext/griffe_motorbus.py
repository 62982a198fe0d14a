"""A griffe extension for the API reference (mkdocs.yml loads it for mkdocstrings).

It changes what the reference shows, never the code: the docstrings and the object
tree it edits are the copies griffe loaded for the site.

* reST roles (``:class:`Streamer```, ``:meth:`~Bus.close```, ``:func:``, ``:attr:``,
  ``:mod:``, ``:data:``, ``:exc:``, ``:obj:``, ``:const:``, also with ``py:``) become
  cross-references, resolved the way Python resolves the name where the docstring is:
  the object itself, then the class, module and packages around it, imports included.
  A target the site renders becomes a link; one it does not render (a private helper,
  an object without a docstring, another library) stays plain code.  A name that
  resolves nowhere is a warning, which fails the strict build.
* ``#:`` comments (above an assignment, or after it on its line: the convention the
  code uses for constants and fields) become the docstring of what they describe.
* Each object is documented once, on one page: where it is defined when a page renders
  that module, else the one module with a page that re-exports it (``motorbus.sim``
  re-exports ``SimProcess``; ``motorbus.sim.process``, which defines it, has the entry).
* Left out: ``__repr__`` and the other special methods, and the objects listed in
  ``internal``: methods public by name that only the package itself calls
  (``Stream.end``, ``Stream.poll_done``, ...).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import griffe

_log = griffe.get_logger("griffe_motorbus")

#: ``:role:`target```, ``:role:`~target```, ``:role:`title <target>```.
ROLE = re.compile(
    r":(?:py:)?(?P<role>class|func|meth|attr|mod|data|exc|obj|const):"
    r"`(?P<text>[^`]+)`"
)
#: The ``::: identifier`` lines of the pages: the modules the site renders.
DIRECTIVE = re.compile(r"^:::\s+(?P<id>[\w.]+)\s*$", re.MULTILINE)


class MotorbusReference(griffe.Extension):
    """Roles to cross-references, each public name once, internals left out."""

    def __init__(
        self, pages: str = "docs", internal: list[str] | None = None, package: str = "motorbus"
    ) -> None:
        super().__init__()
        self.package = package
        self.pages = Path(pages)
        self.internal = list(internal or [])

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **_: Any) -> None:
        if pkg.name != self.package:
            return
        everything = _walk(pkg)
        for obj in everything:
            if not obj.is_alias and obj.is_attribute and obj.docstring is None:
                _doc_comment(obj)
        for obj in everything:
            if isinstance(obj, griffe.Object) and obj.docstring is not None:
                obj.docstring.value = _rewrite_roles(pkg, obj, obj.docstring.value)
        for obj in everything:
            if not obj.is_alias and obj.is_function and _is_dunder(obj.name):
                _leave_out(obj)  # ``__repr__`` and co. (``__init__`` is merged into the class)
        _one_home_each(pkg, everything, self._rendered_ids())
        for path in self.internal:
            internal = _lookup(pkg, path)
            if internal is None or internal.is_alias:
                _log.warning("griffe_motorbus: internal %s names no object defined there", path)
            else:
                _leave_out(internal)

    def _rendered_ids(self) -> set[str]:
        """What the pages render (``::: motorbus.x`` lines): modules, a few single objects."""
        found: set[str] = set()
        for page in sorted(self.pages.rglob("*.md")):
            found.update(m["id"] for m in DIRECTIVE.finditer(page.read_text(encoding="utf-8")))
        return found


def _is_dunder(name: str) -> bool:
    return name.startswith("__") and name.endswith("__")


def _one_home_each(pkg: griffe.Module, everything: list[Any], rendered: set[str]) -> None:
    """Make each object public on exactly one page, its home.

    The home is where the object is defined, when a page renders that module (or the
    object itself).  Otherwise it is a rendered module that imports the object and
    exports it: the one the package itself imports it from (``motorbus.PERIOD_MAX_S``
    comes from ``motorbus.streams``), else the first by name.  Every other re-export
    in a rendered module is left out.  Names the package exports (its imports,
    ``from motorbus.x import Name as Name``: griffe cannot read the ``__all__`` it
    computes) are public at their home even when their module's ``__all__`` omits them.
    """
    exported: dict[str, str] = {}  # target path -> the module the package imports it from
    for member in pkg.members.values():
        if isinstance(member, griffe.Alias):
            try:
                exported[member.final_target.path] = member.target_path.rsplit(".", 1)[0]
            except griffe.AliasResolutionError:
                continue  # another library (``__future__``, ``importlib``)
    holders: dict[str, list[Any]] = {}
    for obj in everything:
        parent = obj.parent
        if obj.is_alias and parent is not None and parent.is_module and parent.path in rendered:
            try:
                holders.setdefault(obj.final_target.path, []).append(obj)
            except griffe.AliasResolutionError:
                continue
    for path in exported:
        target = _lookup(pkg, path)
        if target is not None and _defined_on_a_page(target, rendered):
            target.public = True
        elif path not in holders:
            _log.warning("griffe_motorbus: motorbus exports %s, which no page renders", path)
    for path, aliases in holders.items():
        target = _lookup(pkg, path)
        keep = None
        if target is not None and not _defined_on_a_page(target, rendered):
            ordered = sorted(aliases, key=lambda a: a.parent.path)
            keep = next((a for a in ordered if a.parent.path == exported.get(path)), None)
            if keep is None:
                keep = next((a for a in ordered if a.is_public), None)
        for alias in aliases:
            alias.public = alias is keep


def _defined_on_a_page(target: Any, rendered: set[str]) -> bool:
    home = target.parent
    return bool(target.path in rendered or (home is not None and home.path in rendered))


def _doc_comment(attr: Any) -> None:
    """Give an attribute documented by ``#:`` comments (above it, or after it on its
    line: the Sphinx convention) that text as its docstring."""
    try:
        lines = attr.lines_collection[attr.filepath] if attr.lineno else None
    except KeyError:
        return
    if not lines:
        return
    at = attr.lineno - 1
    text: list[str] = []
    if "#: " in lines[at]:
        text.append(lines[at].split("#: ", 1)[1].strip())
    else:
        above = at - 1
        while above >= 0 and lines[above].strip().startswith("#:"):
            text.insert(0, lines[above].strip()[2:].strip())
            above -= 1
    if text:
        # Written as plain text: ``[x][k]`` is an index there, not a Markdown reference.
        value = "\n".join(text).replace("[", "\\[")
        attr.docstring = griffe.Docstring(value, lineno=attr.lineno, parent=attr)


def _leave_out(obj: griffe.Object | griffe.Alias) -> None:
    """Take ``obj`` out of the tree the site is rendered from (also from every alias of
    its class: ``public = False`` would hide it only where it is defined)."""
    if obj.parent is not None and obj.name != "__init__":
        del obj.parent.members[obj.name]


def _walk(obj: griffe.Object | griffe.Alias) -> list[griffe.Object | griffe.Alias]:
    """``obj`` and everything it defines (aliases are yielded, not entered)."""
    out = [obj]
    if obj.is_alias:
        return out
    for member in obj.members.values():
        out.extend(_walk(member))
    return out


def _lookup(pkg: griffe.Module, path: str) -> griffe.Object | griffe.Alias | None:
    if path == pkg.path:
        return pkg
    if not path.startswith(pkg.path + "."):
        return None
    try:
        found: griffe.Object | griffe.Alias = pkg[path[len(pkg.path) + 1 :]]
        return found
    except (KeyError, griffe.AliasResolutionError):
        return None


def _path(obj: Any) -> str:
    """Where ``obj`` is defined; for another library's object, the path it was imported as."""
    try:
        return str(obj.final_target.path if obj.is_alias else obj.path)
    except griffe.AliasResolutionError:
        return str(obj.target_path)


def _member(scope: Any, dotted: str) -> str | None:
    """The path of ``scope.a.b`` (inherited members included), or None."""
    obj = scope
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        try:
            if obj.is_alias:
                obj = obj.final_target
            members = obj.all_members if obj.is_class else obj.members
        except griffe.AliasResolutionError:
            # Another library's object imported here (``asyncio``): the rest is its own.
            return ".".join([str(obj.target_path), *parts[i:]])
        if part not in members:
            return None
        obj = members[part]
    return _path(obj)


def _resolve(pkg: griffe.Module, owner: griffe.Object, name: str) -> str | None:
    """The path of what ``name`` means in ``owner``'s docstring, or None: an absolute
    path in the package, else the first scope out from ``owner`` that has the name."""
    absolute = _lookup(pkg, name)
    if absolute is not None:
        return _path(absolute)
    scope: Any = owner
    while scope is not None:
        found = _member(scope, name)
        if found is not None:
            return found
        scope = scope.parent
    return None


def _rewrite_roles(pkg: griffe.Module, owner: griffe.Object, text: str) -> str:
    return ROLE.sub(lambda m: _reference(pkg, owner, m), text)


def _reference(pkg: griffe.Module, owner: griffe.Object, match: re.Match[str]) -> str:
    text = match["text"].strip()
    titled = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", text)
    if titled:
        title, target = titled["title"], titled["target"]
    else:
        target = text.lstrip("!")
        title = target.lstrip("~.").rsplit(".", 1)[-1] if "~" in target else target
    target = target.lstrip("~!.")
    code = f"<code>{title}</code>"
    path = _resolve(pkg, owner, target)
    if path is None:
        where = f"{owner.relative_filepath}:{owner.lineno}"
        _log.warning("%s: %s in the docstring of %s names nothing", where, match[0], owner.path)
        return code
    if not path.startswith(pkg.path + ".") and path != pkg.path:
        return code  # another library: the site has no page for it
    # ``optional``: linked when the site renders the target, plain code when it does not.
    return f'<autoref identifier="{path}" optional>{code}</autoref>'
