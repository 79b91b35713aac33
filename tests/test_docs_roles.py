"""The docs site renders the docstrings' Sphinx roles as links, or as code where no page renders their target.

``docs/hooks/sphinx_roles.py`` (a Griffe extension that ``mkdocs.yml`` loads) rewrites each role before
mkdocstrings renders it. Here: the rewrite on sample docstrings written in the package's own modules, what it takes
to be rendered, and (where mkdocs is installed) the built API page itself.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

griffe = pytest.importorskip("griffe")  # the docs extra's; the rest of the suite does without it

ROOT = Path(__file__).resolve().parent.parent
HOOK = ROOT / "docs" / "hooks" / "sphinx_roles.py"
ROLE_TEXT = re.compile(r":(?:class|func|meth|data|mod|attr|exc|obj):`")


def _hook() -> ModuleType:
    spec = importlib.util.spec_from_file_location("sphinx_roles_under_test", HOOK)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


roles = _hook()


@pytest.fixture(scope="module")
def package() -> Any:
    """torchrod as Griffe reads it (statically, no extension): the objects the roles are resolved against."""
    loader = griffe.GriffeLoader(docstring_parser=griffe.Parser("google"), search_paths=[str(ROOT)])
    return loader.load("torchrod")


@pytest.fixture(scope="module")
def rendered(package: Any) -> set[str]:
    return roles.rendered_identifiers(package.modules_collection, list(roles.directives()), roles.handler_options())


def _rewrite(package: Any, rendered: set[str], where: str, text: str) -> str:
    return roles.rewrite(text, roles.resolver(package.modules_collection[where]), rendered)


def test_a_role_with_a_tilde_links_under_its_last_part(package: Any, rendered: set[str]) -> None:
    text = "the sensor (:class:`~torchrod.sensors.Fibre`), or :class:`torchrod.sensors.Fibre` in full"
    assert _rewrite(package, rendered, "torchrod.rod.Rod", text) == (
        "the sensor ([`Fibre`][torchrod.sensors.Fibre]), or [`torchrod.sensors.Fibre`][torchrod.sensors.Fibre] in full"
    )


def test_a_short_name_is_resolved_where_it_is_written(package: Any, rendered: set[str]) -> None:
    # imported by the module: the link goes where the class is defined
    assert _rewrite(package, rendered, "torchrod.estimate.estimator.Estimator", ":class:`EstimatorOptions`") == (
        "[`EstimatorOptions`][torchrod.estimate.options.EstimatorOptions]"
    )
    # a method of the enclosing class, from another method's docstring
    where = "torchrod.estimate.estimator.Estimator.__init__"
    assert _rewrite(package, rendered, where, ":meth:`estimate`") == (
        "[`estimate`][torchrod.estimate.estimator.Estimator.estimate]"
    )
    # the package's top level (a lazy name, bound for type checkers) and a module of the same package (leading dot)
    assert _rewrite(package, rendered, "torchrod.estimate.estimator", ":class:`torchrod.Rod`") == (
        "[`torchrod.Rod`][torchrod.rod.Rod]"
    )
    assert _rewrite(package, rendered, "torchrod.estimate.estimator", ":class:`~.options.LMPolicy`") == (
        "[`LMPolicy`][torchrod.estimate.options.LMPolicy]"
    )


def test_a_target_no_page_renders_is_code(package: Any, rendered: set[str]) -> None:
    where = "torchrod.estimate.estimator"
    assert "torchrod.kernels.fit" not in rendered
    assert _rewrite(package, rendered, where, "see :mod:`torchrod.kernels.fit`") == "see `torchrod.kernels.fit`"
    assert _rewrite(package, rendered, where, ":func:`~torchrod.cli.main`") == "`main`"  # exists, not rendered
    assert _rewrite(package, rendered, where, ":class:`torch.Tensor`, :class:`int`") == "`torch.Tensor`, `int`"
    assert _rewrite(package, rendered, where, ":func:`no_such_name`") == "`no_such_name`"


def test_code_blocks_are_left_as_written(package: Any, rendered: set[str]) -> None:
    text = ":class:`Rod`\n\n```python\n# :class:`Rod`\n```\n:class:`Rod`"
    assert _rewrite(package, rendered, "torchrod.rod", text) == (
        "[`Rod`][torchrod.rod.Rod]\n\n```python\n# :class:`Rod`\n```\n[`Rod`][torchrod.rod.Rod]"
    )


def test_what_is_rendered_follows_the_blocks_options(rendered: set[str]) -> None:
    assert "torchrod.estimate.estimator.Estimator.estimate" in rendered  # `members: [estimate]`
    assert "torchrod.estimate.estimator.Estimator.plan" not in rendered  # left out by that list
    assert "torchrod.estimate.implicit" in rendered
    assert not any(name.startswith("torchrod.estimate.implicit.") for name in rendered)  # `members: false`
    assert "torchrod.rod.Rod.from_json" in rendered  # a member under the default options
    assert not any(name.rpartition(".")[2].startswith("_") for name in rendered)  # filters: ["!^_"]


def test_the_filters_option_reads_as_mkdocstrings_reads_it() -> None:
    assert roles._keep("step", ["!^_"]) and not roles._keep("_step", ["!^_"])
    assert roles._keep("step", ["^s"]) and not roles._keep("other", ["^s"])  # only includes: no match is out
    assert roles._keep("other", ["!^_", "^s"])  # includes and excludes: no match is in


def test_the_extension_rewrites_every_docstring_when_griffe_loads_the_package() -> None:
    extensions = griffe.load_extensions(f"{HOOK}:SphinxRoles")
    loader = griffe.GriffeLoader(extensions=extensions, search_paths=[str(ROOT)])
    package = loader.load("torchrod")
    estimator = package.modules_collection["torchrod.estimate.estimator.Estimator"]
    assert "[`EstimatorOptions`][torchrod.estimate.options.EstimatorOptions]" in estimator.docstring.value
    left = [obj.path for obj in roles._objects(package) if obj.docstring and ROLE_TEXT.search(obj.docstring.value)]
    assert left == []


def test_each_attribute_entry_of_a_rendered_class_names_one_attribute(package: Any, rendered: set[str]) -> None:
    """A Google "Attributes:" entry listing several names renders as one row named "a," typed "b"."""
    bad = []
    for path in sorted(rendered):
        obj = package.modules_collection[path]
        if obj.is_class and obj.docstring is not None:
            for section in obj.docstring.parse(griffe.Parser("google")):
                if section.kind.value == "attributes":
                    bad += [f"{path}: {item.name!r}" for item in section.value if not item.name.isidentifier()]
    assert not bad, "\n".join(bad)


@pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None,
    reason="the docs extra (mkdocs, mkdocstrings) is not installed",
)
def test_the_built_api_page_shows_no_role_and_links_the_estimator(tmp_path: Path) -> None:
    """The whole site, built as CI builds it (strict: an unknown cross-reference fails the build)."""
    site = tmp_path / "site"
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    page = (site / "reference" / "api" / "index.html").read_text(encoding="utf-8")
    assert not ROLE_TEXT.search(page), ROLE_TEXT.search(page)
    for role in (":class:", ":func:", ":meth:", ":data:", ":mod:", ":attr:"):
        assert role not in page
    assert 'href="#torchrod.estimate.estimator.Estimator"' in page
    assert 'href="#torchrod.estimate.options.EstimatorOptions"' in page
