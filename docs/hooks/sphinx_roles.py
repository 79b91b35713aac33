"""Griffe extension: the docstrings' Sphinx roles rendered on the docs site as links.

The package's docstrings name things with Sphinx roles (``:class:`~torchrod.rod.Rod```, ``:func:`simulate```,
``:meth:`.search.step```, ...): ``tests/test_doc_names.py`` checks that each resolves, and Python's ``help()`` shows
them as written. mkdocstrings renders docstrings as Markdown, where a role would show raw, so this extension
rewrites each role, in every docstring of the loaded package and before anything is rendered, into what
mkdocstrings' cross-references (mkdocs-autorefs) read:

- ``[`B`][torchrod.a.B]`` where the target is rendered on the site (a link to it); the title is the last part of
  the name when the role writes ``~``, else the name as written (a leading dot left out, as Sphinx does);
- plain inline code ```B``` where it is not (a private helper, another library's name, a builtin): autorefs would
  warn about an identifier that no page renders, and the strict build fails on warnings.

A short name is looked up where the docstring is written, as ``tests/test_doc_names.py`` does: a leading dot from
the module's package, else in the enclosing classes, the module (its imports included), the package's top level,
then as an absolute name. The link goes to the object's canonical path (``torchrod.Rod`` links to
``torchrod.rod.Rod``).

What is rendered: every ``::: identifier`` of a page under ``docs/`` and the members mkdocstrings renders with it,
chosen as its Python handler chooses them (the ``filters``, ``members``, ``show_if_no_docstring``,
``inherited_members`` and ``show_submodules`` options, from ``mkdocs.yml`` and the block's own ``options:``).

Loaded by ``mkdocs.yml``: ``plugins: mkdocstrings: handlers: python: options: extensions:``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Container, Iterator, Mapping
from pathlib import Path
from typing import Any

import griffe
import yaml

ROLE = re.compile(r":(?:py:)?(?:func|class|mod|data|meth|attr|exc|obj):`(~?)(\.*[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)`")
"""A Sphinx cross-reference role: ``~`` (show the last part only) and the name."""

FENCE = re.compile(r"^\s*(```|~~~)")
"""A fenced code block's opening or closing line: what is inside is code, left as written."""

DIRECTIVE = re.compile(r"^:::[ \t]+(\S+)[ \t]*$")
"""mkdocstrings' ``::: identifier`` line."""

DOCS = Path(__file__).resolve().parent.parent
"""The docs folder (this file is in ``docs/hooks/``)."""

HANDLER_DEFAULTS: dict[str, Any] = {
    "filters": ["!^_[^_]"],
    "members": None,
    "show_if_no_docstring": False,
    "inherited_members": False,
    "show_submodules": False,
}
"""mkdocstrings-python's defaults for the options that choose what is rendered."""


def rewrite(text: str, resolve: Callable[[str], str | None], rendered: Container[str]) -> str:
    """``text`` with each Sphinx role made a cross-reference (``resolve(name)`` is rendered) or inline code.

    ``resolve`` gives a role's name written there its canonical full name, or None when it finds nothing.
    """

    def replace(match: re.Match[str]) -> str:
        tilde, name = match.group(1), match.group(2)
        title = name.lstrip(".")
        if tilde:
            title = title.rpartition(".")[2]
        target = resolve(name)
        if target is not None and target in rendered:
            return f"[`{title}`][{target}]"
        return f"`{title}`"

    lines = text.split("\n")
    in_code = False
    for index, line in enumerate(lines):
        if FENCE.match(line):
            in_code = not in_code
        elif not in_code:
            lines[index] = ROLE.sub(replace, line)
    return "\n".join(lines)


def _canonical(obj: griffe.Object | griffe.Alias) -> str | None:
    """The path of what ``obj`` is (an alias followed to its target), or None when it leads outside what is loaded."""
    try:
        return obj.final_target.path if isinstance(obj, griffe.Alias) else obj.path
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _lookup(collection: griffe.ModulesCollection, path: str) -> str | None:
    try:
        found = collection[path]
    except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None
    return _canonical(found)


def resolver(obj: griffe.Object) -> Callable[[str], str | None]:
    """What resolves a role's name written in the docstring of ``obj`` (see the module's docstring)."""
    module = obj.module
    collection = obj.modules_collection
    scopes = []  # the enclosing classes, innermost first (a class's own docstring is written inside it)
    current: griffe.Object | None = obj
    while current is not None and not current.is_module:
        if current.is_class:
            scopes.append(current.path)
        current = current.parent

    def resolve(name: str) -> str | None:
        if name.startswith("."):
            package = module.path if module.is_init_module else module.path.rpartition(".")[0]
            level = len(name) - len(name.lstrip("."))
            parts = package.split(".")
            candidates = [".".join([*parts[: len(parts) - level + 1], name.lstrip(".")])]
        else:
            candidates = [f"{scope}.{name}" for scope in [*scopes, module.path, module.package.path]] + [name]
        for candidate in candidates:
            if (found := _lookup(collection, candidate)) is not None:
                return found
        return None

    return resolve


def directives(docs: Path = DOCS) -> Iterator[tuple[str, dict[str, Any]]]:
    """(identifier, the block's own options) of each ``:::`` line of the pages under ``docs`` (its hooks left out)."""
    for page in sorted(docs.rglob("*.md")):
        lines = page.read_text(encoding="utf-8").splitlines()
        for index, line in enumerate(lines):
            match = DIRECTIVE.match(line)
            if not match:
                continue
            block = []
            for following in lines[index + 1 :]:
                if not following.strip() or not following[0].isspace():
                    break
                block.append(following)
            config = yaml.safe_load("\n".join(block)) if block else None
            options = config.get("options") if isinstance(config, dict) else None
            yield match.group(1), dict(options or {})


class _IgnoreTags(yaml.SafeLoader):
    """A YAML loader that reads MkDocs' custom tags (``!ENV``, ``!relative``, ``!!python/name``) as None."""


_IgnoreTags.add_multi_constructor("", lambda loader, suffix, node: None)


def handler_options(config_file: Path = DOCS.parent / "mkdocs.yml") -> dict[str, Any]:
    """The python handler's options in ``mkdocs.yml`` that choose what is rendered, over the handler's defaults."""
    options = dict(HANDLER_DEFAULTS)
    try:
        config = yaml.load(config_file.read_text(encoding="utf-8"), Loader=_IgnoreTags)
    except OSError:
        return options
    for plugin in config.get("plugins") or []:
        if isinstance(plugin, dict) and "mkdocstrings" in plugin:
            python = ((plugin["mkdocstrings"] or {}).get("handlers") or {}).get("python") or {}
            options.update({k: v for k, v in (python.get("options") or {}).items() if k in HANDLER_DEFAULTS})
    return options


def _keep(name: str, filters: list[str] | str) -> bool:
    """Whether the ``filters`` option (mkdocstrings-python's rule: the last matching pattern decides) keeps ``name``."""
    keep = None
    for pattern in filters:
        exclude = pattern.startswith("!")
        if re.search(pattern[1:] if exclude else pattern, name):
            keep = not exclude
    if keep is None:  # no pattern matched: rejected only where every pattern is one to include
        return not all(not pattern.startswith("!") for pattern in filters)
    return keep


def _rendered_members(obj: griffe.Object | griffe.Alias, options: Mapping[str, Any], root: bool) -> Iterator[Any]:
    """The members mkdocstrings' python handler renders under ``obj`` (its ``children`` template)."""
    members_list = options["members"] if root else None
    inherited = options["inherited_members"]
    kinds = ["attributes", "type_aliases", "classes", "functions"] + (["modules"] if options["show_submodules"] else [])
    for kind in kinds:
        members = getattr(obj, kind, {})
        for member in members.values():
            if inherited is False and member.inherited:
                continue
            if isinstance(inherited, list) and member.inherited and member.name not in inherited:
                continue
            if members_list is True:
                pass
            elif members_list is False or members_list == []:
                if not member.inherited:
                    continue
            elif members_list is not None:
                if member.name not in members_list:
                    continue
            else:
                filters = options["filters"]
                if filters == "public" and not member.is_public:
                    continue
                if filters != "public" and filters and not _keep(member.name, filters):
                    continue
                if not options["show_if_no_docstring"] and not member.has_docstrings:
                    continue
                if filters != "public" and member.is_imported and not member.is_public:
                    continue  # what a module imports is rendered only where the module exports it
            if kind == "functions" and obj.is_class and member.name == "__init__":
                continue  # merged into the class, or not rendered at all under the filters
            yield member


def rendered_identifiers(
    collection: griffe.ModulesCollection, blocks: list[tuple[str, dict[str, Any]]], options: Mapping[str, Any]
) -> set[str]:
    """The canonical paths of what the ``:::`` blocks render: each block's object and its rendered members."""
    found: set[str] = set()

    def walk(obj: Any, opts: Mapping[str, Any], root: bool) -> None:
        try:
            path = _canonical(obj)
            if path is None or (not root and path in found):
                return
            found.add(path)
            found.add(obj.path)
            if obj.is_class or obj.is_module:
                for member in _rendered_members(obj, opts, root):
                    walk(member, opts, root=False)
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return

    for identifier, own in blocks:
        try:
            obj = collection[identifier]
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        walk(obj, {**options, **{k: v for k, v in own.items() if k in HANDLER_DEFAULTS}}, root=True)
    return found


def _objects(obj: griffe.Object) -> Iterator[griffe.Object]:
    """``obj`` and every object defined under it (aliases left out: their docstrings are their targets')."""
    yield obj
    for member in obj.members.values():
        if not isinstance(member, griffe.Alias):
            yield from _objects(member)


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx roles of every docstring of a loaded package into cross-references or code."""

    def __init__(self, docs: str | None = None, config_file: str | None = None) -> None:
        super().__init__()
        self.docs = Path(docs) if docs else DOCS
        self.config_file = Path(config_file) if config_file else self.docs.parent / "mkdocs.yml"

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:  # noqa: ARG002 - Griffe's hook signature
        blocks = [(i, o) for i, o in directives(self.docs) if i.split(".")[0] == pkg.name]
        rendered = rendered_identifiers(pkg.modules_collection, blocks, handler_options(self.config_file))
        for obj in _objects(pkg):
            docstring = obj.docstring
            if docstring is None or ":" not in docstring.value:
                continue
            docstring.value = rewrite(docstring.value, resolver(obj), rendered)
            docstring.__dict__.pop("parsed", None)  # parsed before the rewrite (by another extension): parse again
