"""Every dotted ``torchrod.X.Y...`` name the docs and the docstrings write resolves to something that exists.

What is read:

- the docs (``docs/**/*.md``) and ``README.md``: every ``torchrod.a.b...`` anywhere in the text (prose, backticks,
  code blocks, mkdocstrings ``:::`` lines), and each name that a ``from torchrod.x import a, b`` line imports;
- the package's docstrings (``torchrod/**/*.py``: every bare string statement, so module, class, function and
  attribute docstrings) and comments: a name written in a Sphinx role (:func:`torchrod.a.b`, :class:`~torchrod.x`,
  ``:mod:``, ``:data:``, ``:meth:``, ``:attr:``) or in plain backticks. A role's name written short
  (:func:`.search.step`, :meth:`ready`, :class:`Rod`) is looked up where it is written, as Python would: a leading
  dot from the module's package, else in the enclosing classes, the module (its imports included, those made for
  type checkers too), the package's top level, then as an absolute name (another library's).

``CHANGELOG.md`` is not read: it records what each release changed, renames and removals included, so it names on
purpose what no longer exists (an old name beside its new one is how a user finds where a thing went).

A docstring's or comment's reference to a section of the docs, ``docs/page.md, "Heading"``, must name a heading of
that page, so that moving a section cannot leave it pointing nowhere.

A name resolves when the longest prefix of it that is a module imports and the rest is found by ``getattr`` from
there; a class's dataclass fields, annotated attributes and the attributes its methods set on ``self`` count too
(they exist on instances only), and so does a property or method (``getattr`` on the class finds them).
``__main__`` modules are looked for as files, never imported (importing one runs it).
"""

from __future__ import annotations

import ast
import builtins
import dataclasses
import functools
import importlib
import inspect
import io
import re
import textwrap
import tokenize
import typing
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "torchrod"

NAME = re.compile(r"(?<![\w.])torchrod(?:\.[A-Za-z_]\w*)+")
"""A dotted name under torchrod (``torchrod`` alone is not checked: it is the package). One followed by ``/`` and a
digit is a format's tag (``"torchrod.warm_start/1"``, a checkpoint's ``format``), not a name."""

ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|exc|obj):`~?(torchrod(?:\.[A-Za-z_]\w*)+)`")
"""A Sphinx role naming a torchrod name in full (``~`` shows the last part only)."""

SHORT_ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|exc|obj):`~?(\.*[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)`")
"""A Sphinx role with any name, full or short (those in full are also matched by :data:`ROLE`)."""

BACKTICKS = re.compile(r"(?<![`:\w])`{1,2}([^`\n]+)`{1,2}")
"""Plain backticks, single (Markdown, Sphinx's default role) or double (reStructuredText's literal)."""

FROM_IMPORT = re.compile(
    r"^[ \t]*from[ \t]+(torchrod(?:\.\w+)*)[ \t]+import[ \t]+(?:\(([^)]*)\)|([\w \t,]+))", re.MULTILINE
)
"""``from torchrod.x import a, b`` in a code block: ``torchrod.x.a`` and ``torchrod.x.b`` are names too."""

SUFFIXES = (".py", ".md", ".json", ".jsonl", ".pt", ".csv", ".toml", ".yml", ".yaml")
"""File names that a dotted name may be followed by, as in ``torchrod.data``'s files: ``nitinol.json`` is not an
attribute. A name is cut before a part that is such a suffix."""


def _strip_file_suffix(name: str) -> str:
    for suffix in SUFFIXES:
        if name.endswith(suffix) and name.count(".") > 1:
            return name[: -len(suffix)]
    return name


@functools.cache
def _assigned_on_self(cls: type) -> set[str]:
    """The attributes that the methods of ``cls`` (and its bases) set on ``self`` (``self.x = ...``)."""
    found = set()
    for klass in cls.__mro__:
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):  # a builtin, or a class made at run time
            continue
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            for target in targets:
                if isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name):
                    if target.value.id == "self":
                        found.add(target.attr)
    return found


def _fields(cls: type) -> dict[str, typing.Any]:
    """The attributes that instances of ``cls`` carry without the class carrying them: dataclass fields, annotated
    attributes and those its methods set on ``self``, with their annotations where they have one (unresolved strings
    where ``get_type_hints`` cannot resolve them, None where there is none)."""
    found: dict[str, typing.Any] = dict.fromkeys(_assigned_on_self(cls))
    for klass in reversed(cls.__mro__):
        found.update(getattr(klass, "__annotations__", {}))
    if dataclasses.is_dataclass(cls):
        found.update({f.name: f.type for f in dataclasses.fields(cls)})
    try:
        found.update(typing.get_type_hints(cls))
    except Exception:  # an annotation naming what only type checkers import: keep the strings
        pass
    return found


def _class_of(annotation: typing.Any) -> type | None:
    """The class an annotation names, when it names one class (``X`` or ``X | None``)."""
    if isinstance(annotation, type):
        return annotation
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if len(args) == 1 and isinstance(args[0], type) else None


def _import(module: str) -> object | None:
    """The module of that name, or None when there is none (an error inside a module that exists is raised)."""
    if module.rpartition(".")[2] == "__main__":  # running it is not looking it up
        path = ROOT / (module.replace(".", "/") + ".py")
        return module if path.exists() else None
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as error:
        if error.name is not None and (module == error.name or module.startswith(error.name + ".")):
            return None
        raise


@functools.cache
def resolve(name: str) -> str | None:
    """None when ``name`` resolves; else why not (the part that was not found, and where it was looked for)."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        module = ".".join(parts[:cut])
        found = _import(module)
        if found is not None:
            break
    else:
        return f"no module {parts[0]}"
    if isinstance(found, str):  # a __main__ module: nothing under it to look up
        return None if cut == len(parts) else f"{module} is a program, not a namespace"
    where = module
    for index in range(cut, len(parts)):
        part = parts[index]
        if hasattr(found, part):
            found = getattr(found, part)
        elif isinstance(found, type) and part in _fields(found):
            annotation = _fields(found)[part]
            cls = _class_of(annotation)
            if cls is None:  # an instance attribute of no single class: nothing further can be looked up
                rest = parts[index + 1 :]
                return None if not rest else f"{where}.{part} is {annotation!r}: cannot look up {'.'.join(rest)}"
            found = cls
        else:
            return f"{where} has no {part}"
        where = f"{where}.{part}"
    return None


def _names(text: str) -> set[str]:
    """The dotted torchrod names in ``text`` (a format's tag left out)."""
    return {_strip_file_suffix(m.group(0)) for m in NAME.finditer(text) if not re.match(r"/\d", text[m.end() :])}


def _names_in_text(text: str) -> set[str]:
    names = _names(text)
    for m in FROM_IMPORT.finditer(text):
        for alias in (m.group(2) or m.group(3)).replace("\n", " ").split(","):
            alias = alias.split(" as ")[0].strip()
            if alias.isidentifier():
                names.add(f"{m.group(1)}.{alias}")
    return {n for n in names if n.count(".") >= 1}


def _names_in_docstring(text: str) -> set[str]:
    names = {m.group(1) for m in ROLE.finditer(text)}
    for m in BACKTICKS.finditer(text):
        names.update(_names(m.group(1)))
    return names


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@functools.cache
def _docstrings_and_comments(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, text, enclosing class's qualified name or None) of each bare string statement and each comment in a
    module (a comment's class is not looked for: None)."""
    source = path.read_text(encoding="utf-8")
    found: list[tuple[int, str, str | None]] = []

    def visit(node: ast.AST, cls: str | None) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Expr) and isinstance(child.value, ast.Constant):
                if isinstance(child.value.value, str):
                    found.append((child.lineno, child.value.value, cls))
            if isinstance(child, ast.ClassDef):
                visit(child, f"{cls}.{child.name}" if cls else child.name)
            else:
                visit(child, cls)

    visit(ast.parse(source), None)
    found += [
        (token.start[0], token.string, None)
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT
    ]
    return found


@functools.cache
def _imported(path: Path) -> dict[str, str]:
    """{name bound in the module: the full name it stands for} for every import anywhere in it (functions and
    ``TYPE_CHECKING`` blocks included), relative ones made absolute."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    bound: dict[str, str] = {}
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            bound.update({a.asname or a.name: f"{source}.{a.name}" for a in node.names})
        elif isinstance(node, ast.Import):
            bound.update({a.asname: a.name for a in node.names if a.asname})
            bound.update({a.name.split(".")[0]: a.name.split(".")[0] for a in node.names if not a.asname})
    return bound


def resolve_short(name: str, path: Path, cls: str | None) -> str | None:
    """None when a role's ``name``, written in ``path`` (within class ``cls``), resolves there; else why not."""
    module = _module_name(path)
    if name.startswith("."):
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        level = len(name) - len(name.lstrip("."))
        base = package.split(".")[: len(package.split(".")) - level + 1]
        return resolve(".".join([*base, name.lstrip(".")]))
    first, _, rest = name.partition(".")
    if not rest and hasattr(builtins, first):
        return None
    scopes = [f"{module}.{'.'.join(cls.split('.')[:n])}" for n in range(cls.count(".") + 1, 0, -1)] if cls else []
    candidates = [f"{scope}.{name}" for scope in [*scopes, module]]
    imported = _imported(path)
    if first in imported:
        candidates.append(imported[first] + (f".{rest}" if rest else ""))
    candidates += [f"torchrod.{name}", name]
    if any(resolve(candidate) is None for candidate in candidates):
        return None
    return f"not found in {', '.join(candidates)}"


def doc_names() -> dict[str, list[str]]:
    """{name: [where it is written, ...]} over the docs and the package's docstrings and comments."""
    where: dict[str, list[str]] = {}
    docs = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]
    for path in docs:
        text = path.read_text(encoding="utf-8")
        for name in _names_in_text(text):
            numbered = list(enumerate(text.splitlines(), 1))
            lines = [n for n, line in numbered if name in line] or [  # else an imported name: its own line
                n for n, line in numbered if name.rpartition(".")[2] in line
            ]
            where.setdefault(name, []).extend(f"{path.relative_to(ROOT)}:{n}" for n in lines[:1] or [0])
    for path in sorted(PACKAGE.rglob("*.py")):
        for number, text, _ in _docstrings_and_comments(path):
            for name in _names_in_docstring(text):
                where.setdefault(name, []).append(f"{path.relative_to(ROOT)}:{number}")
    return where


def test_the_docs_name_some_torchrod_names() -> None:
    """The scan finds what it is for (a regex that matched nothing would pass the test below vacuously)."""
    names = doc_names()
    assert len(names) > 100
    assert any(place.startswith("docs/") for place in names["torchrod.Rod.from_json"])  # the docs' text
    assert any(place.startswith("torchrod/io/") for place in names["torchrod.io.stream.stream"])  # docstrings' roles


def test_every_name_in_the_docs_and_docstrings_resolves() -> None:
    broken = {name: (why, places) for name, places in doc_names().items() if (why := resolve(name)) is not None}
    assert not broken, "names that do not resolve:\n" + "\n".join(
        f"  {name}: {why} (at {', '.join(sorted(set(places))[:4])})" for name, (why, places) in sorted(broken.items())
    )


SECTION = re.compile(r"(docs/[\w/.-]+\.md),\s+\"([^\"]+)\"")
"""A reference to a section of a page of the docs: ``docs/physics.md, "Precurved rods"``."""


def _headings(page: Path) -> set[str]:
    return {line.lstrip("#").strip() for line in page.read_text(encoding="utf-8").splitlines() if line.startswith("#")}


def section_problems(text: str) -> list[str]:
    """What in ``text`` refers to a page of the docs or a heading of it that does not exist."""
    problems = []
    for match in SECTION.finditer(" ".join(text.split())):  # a reference may be wrapped over lines
        page, heading = ROOT / match.group(1), match.group(2)
        if not page.is_file():
            problems.append(f"no page {match.group(1)}")
        elif heading not in _headings(page):
            problems.append(f"{match.group(1)} has no heading {heading!r}")
    return problems


def test_every_section_the_docstrings_refer_to_exists() -> None:
    broken = [
        f"  {path.relative_to(ROOT)}:{number}: {problem}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for number, text, _ in _docstrings_and_comments(path)
        for problem in section_problems(text)
    ]
    assert not broken, "section references that lead nowhere:\n" + "\n".join(broken)


def test_a_section_reference_that_leads_nowhere_is_found() -> None:
    assert section_problems('(docs/physics.md, "Precurved rods")') == []
    assert section_problems('(docs/physics.md,\n    "Precurved rods")') == []
    missing = section_problems('(docs/physics.md, "No such heading")')
    assert missing == ["docs/physics.md has no heading 'No such heading'"]
    assert section_problems('(docs/nowhere.md, "Anything")') == ["no page docs/nowhere.md"]


def test_every_short_role_in_the_docstrings_resolves_where_it_is_written() -> None:
    broken = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for number, text, cls in _docstrings_and_comments(path):
            for match in SHORT_ROLE.finditer(text):
                name = match.group(1)
                if not name.startswith("torchrod.") and (why := resolve_short(name, path, cls)) is not None:
                    broken.append(f"  {path.relative_to(ROOT)}:{number}: {match.group(0)}: {why}")
    assert not broken, "roles that do not resolve where they are written:\n" + "\n".join(broken)


@pytest.mark.parametrize(
    "name",
    [
        "torchrod.Rod",  # a lazy name of the package
        "torchrod.Rod.from_json",  # a class method
        "torchrod.rod.Rod",  # a module, then its class
        "torchrod.kernels.targets.MODULES",  # a module's constant
        "torchrod.estimate.estimator.EstimateResult.status",  # a dataclass field with no class attribute
        "torchrod.data",  # a package
        "torchrod.__main__",  # a program: looked for, not run
    ],
)
def test_resolve_finds_what_exists(name: str) -> None:
    assert resolve(name) is None


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ("torchrod.no_such_thing", "torchrod has no no_such_thing"),
        ("torchrod.kernels.layout.NoSuchRows", "torchrod.kernels.layout has no NoSuchRows"),
        ("torchrod.Estimator.from_nowhere", "torchrod.Estimator has no from_nowhere"),
        ("torchrod.no_module.Thing", "torchrod has no no_module"),
    ],
)
def test_resolve_reports_what_does_not(name: str, why: str) -> None:
    """The resolver can fail: a made-up name is reported, with the part that was not found."""
    assert resolve(name) == why


@pytest.mark.parametrize(
    ("module", "name", "resolves"),
    [
        ("kernels/search.py", "step", True),  # a name of the module (imported from .fit)
        ("kernels/search.py", ".fit.step", True),  # a module of the same package, then its function
        ("kernels/search.py", "..rod.Rod", True),  # two levels up
        ("kernels/host.py", "np.ndarray", True),  # through a name bound by ``import numpy as np``
        ("kernels/search.py", "Rod", True),  # the package's top level
        ("kernels/search.py", "numpy.ndarray", True),  # another library
        ("kernels/search.py", "int", True),  # a builtin
        ("kernels/search.py", "no_such_step", False),
        ("kernels/search.py", ".no_such_module", False),
        ("kernels/search.py", "np.ndarray", False),  # search.py binds no ``np``
    ],
)
def test_resolve_short_looks_where_the_role_is_written(module: str, name: str, resolves: bool) -> None:
    assert (resolve_short(name, PACKAGE / module, None) is None) is resolves


def test_resolve_short_looks_in_the_enclosing_class() -> None:
    path = PACKAGE / "kernels" / "targets.py"
    assert resolve_short("ready", path, "Compiled") is None
    assert resolve_short("ready", path, None) is not None  # a method, not the module's


def test_the_scan_reads_roles_backticks_and_imports() -> None:
    """Each way of writing a name is picked up (so a broken name written that way fails the test above)."""
    assert _names_in_docstring(
        ":func:`torchrod.a.b` and :class:`~torchrod.c` and ``torchrod.d.e`` or `torchrod.f`"
    ) == {
        "torchrod.a.b",
        "torchrod.c",
        "torchrod.d.e",
        "torchrod.f",
    }
    assert _names_in_docstring("torchrod.bare in prose is not a reference") == set()
    assert _names_in_text("from torchrod.io import readings, stream as s\n`torchrod.x.y`, torchrod.data/rods.json") == {
        "torchrod.io",
        "torchrod.io.readings",
        "torchrod.io.stream",
        "torchrod.x.y",
        "torchrod.data",
    }
    assert _names_in_text("from torchrod.learn import (\n    WarmStart,\n    train,\n)\nx = 1") == {
        "torchrod.learn",
        "torchrod.learn.WarmStart",
        "torchrod.learn.train",
    }
    assert _names_in_text('format "torchrod.warm_start/1"') == set()  # a format's tag
