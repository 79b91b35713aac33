"""What a user gets from an installed torchrod: the shipped files inside the wheel and found through
importlib.resources, one version, the licence and citation files, and a named path that does not exist refused.

The shipped files live at the repository's top level (``data/``, ``checkpoints/``) and install inside the package
(``torchrod.data``, ``torchrod.checkpoints``: pyproject.toml's ``package-dir``)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import torchrod
from torchrod.cli import main
from torchrod.data import FILES, path
from torchrod.errors import MissingFileError
from torchrod.shipped import PACKAGES

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_file_is_found_through_importlib_resources():
    for name in FILES:
        found = path(name)
        assert found.is_file() and found.stat().st_size > 0, name
        assert found.parent.name == PACKAGES[name].rpartition(".")[2], name  # data/ or checkpoints/
    # The rod files are the presets, and the example truth answers the example stream line for line.
    assert torchrod.Rod.from_json(torchrod.presets.rod_file("nitinol290")) == torchrod.presets.nitinol290()
    assert torchrod.Rod.from_json(torchrod.presets.rod_file("ctr250")) == torchrod.presets.ctr250()
    ids = [json.loads(x)["id"] for x in path("example_stream.jsonl").read_text().splitlines()]
    truth = [json.loads(x)["id"] for x in path("example_stream_truth.jsonl").read_text().splitlines()]
    assert ids == truth and len(ids) == 500
    with pytest.raises(MissingFileError, match="nitinol290.json"):
        path("nitinol290.jsn")
    with pytest.raises(torchrod.errors.RodError, match="ctr250"):
        torchrod.presets.rod_file("nitinol")


def test_the_shipped_network_serves_the_layout_it_was_trained_for():
    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT, shipped_network

    assert Path(SHIPPED_CHECKPOINT) == path("nitinol290.pt")
    network, line = shipped_network(torchrod.presets.nitinol290())
    assert network is not None and "nitinol290.pt" in line
    network, line = shipped_network(torchrod.presets.ctr250())  # 12 gratings: another layout
    assert network is None and "no shipped warm-start network" in line


def test_python_m_torchrod_data_prints_paths(capsys):
    from torchrod.data import main as data_main

    assert data_main(["example_stream.jsonl"]) == 0
    assert Path(capsys.readouterr().out.strip()) == path("example_stream.jsonl")
    assert data_main(["nope.json"]) == 2
    assert "shipped files" in capsys.readouterr().err


def test_the_version_is_written_once():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "torchrod.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", torchrod.__version__)
    # The changelog starts with this version, and the citation cites it.
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert re.search(r"^## \[?(\d+\.\d+\.\d+)", changelog, re.M).group(1) == torchrod.__version__
    citation = (ROOT / "CITATION.cff").read_text()
    assert f'version: "{torchrod.__version__}"' in citation and "2109.12469" in citation
    licence = (ROOT / "LICENSE").read_text()
    assert "MIT License" in licence and "the torchrod developers" in licence


def test_pyproject_lists_every_package_and_ships_every_file_by_name():
    """The packages are listed (a mapped folder is not found by a search): every folder of the package with Python
    files is in the list, and the package data names the shipped files, each in its package's folder."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = setuptools["package-dir"]
    assert mapped == {"torchrod.data": "data", "torchrod.checkpoints": "checkpoints"}
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "torchrod").rglob("*.py")}
    assert set(setuptools["packages"]) == folders | set(mapped)
    shipped = {name: package for package, names in setuptools["package-data"].items() for name in names}
    assert shipped.pop("py.typed") == "torchrod"
    assert shipped == PACKAGES
    for name, package in PACKAGES.items():
        assert (ROOT / mapped[package] / name).is_file(), name


def test_a_built_wheel_holds_the_package_data(tmp_path):
    """``pip wheel`` of a copy of the source (so no build files land in the checkout): the wheel carries the rod
    files, the example data, the network, py.typed and the kernels' type stub, under the version torchrod reports,
    and not the other files that the top-level folders may hold (a set generated there, a network trained there);
    unpacked and imported, it finds its files."""
    pytest.importorskip("setuptools", minversion="70.1")  # builds wheels without the `wheel` package
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in ("torchrod", "data", "checkpoints"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    (src / "checkpoints" / "warm_start.pt").write_bytes(b"trained here")
    (src / "data" / "my_stream.jsonl").write_text("{}\n")
    out = tmp_path / "wheel"
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = out.glob("torchrod-*.whl")
    assert wheel.name.startswith(f"torchrod-{torchrod.__version__}-")
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in FILES:
        assert f"{PACKAGES[name].replace('.', '/')}/{name}" in names, name
    assert {"torchrod/py.typed", "torchrod/data/__init__.py", "torchrod/checkpoints/__init__.py"} <= names
    assert "torchrod/kernels/views.pyi" in names  # (setuptools ships a package's stubs by itself)
    assert not any(n.endswith(("warm_start.pt", "my_stream.jsonl")) for n in names)
    assert any(n.endswith(".dist-info/licenses/LICENSE") or n.endswith(".dist-info/LICENSE") for n in names)
    assert not any(n.startswith(("tests/", "docs/", "examples/", "data/", "checkpoints/")) for n in names)
    # Installed (unpacked; run away from the checkout), torchrod.data finds the files inside it.
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    for name in ("nitinol290.pt", "example_stream.jsonl"):
        done = subprocess.run(
            [sys.executable, "-m", "torchrod.data", name],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": str(site)},
        )
        assert done.returncode == 0, done.stderr
        assert Path(done.stdout.strip()) == site / PACKAGES[name].replace(".", "/") / name


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["estimate", "--rod", "nitinol290", "{tmp}/none.jsonl"], "READINGS"),
        (["estimate", "--rod", "{tmp}/rod.json", "-"], "--rod"),
        (["estimate", "--rod", "nitinol290", "--checkpoint", "{tmp}/net.pt", "-"], "--checkpoint"),
        (["stream", "--rod", "nitinol290", "--input", "{tmp}/none.jsonl"], "--input"),
        (["stream", "--rod", "nitinol290", "--checkpoint", "{tmp}/net.pt"], "--checkpoint"),
        (["simulate", "--rod", "nitinol290", "{tmp}/forces.jsonl"], "FORCES"),
        (["calibrate", "--rod", "nitinol290", "{tmp}/none.jsonl", "--out", "{tmp}/new.json"], "READINGS"),
        (["plot", "{tmp}/r.jsonl", "{tmp}/e.jsonl", "--rod", "nitinol290"], "READINGS"),
    ],
)
def test_a_named_path_that_does_not_exist_is_an_error(args, named, tmp_path, capsys):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert named in err and "no such" in err and str(tmp_path) in err
    assert "warning" not in err.lower()
    assert not (tmp_path / "new.json").exists()


def test_missing_files_raise_the_librarys_error():
    from torchrod.cli.commands.estimate import load_network
    from torchrod.io.jsonl import check_input
    from torchrod.learn.warm_start import WarmStart

    rod = torchrod.presets.nitinol290()
    for call in (
        lambda: check_input("/no/such/readings.jsonl", "READINGS"),
        lambda: torchrod.presets.load("no/such/rod.json"),
        lambda: load_network("/no/such/net.pt", rod),
        lambda: WarmStart.load("/no/such/net.pt", rod),
    ):
        with pytest.raises(MissingFileError, match="no such"):
            call()
    # A bare word that is no preset is a rod error naming every preset, not a missing file.
    with pytest.raises(torchrod.errors.RodError, match="nitinol290, ctr250"):
        torchrod.presets.load("nitinol")
