"""The help texts: every command's and suite's --help renders (the documentation's CLI reference is made from
them), and every help that speaks of a rod names every preset."""

from __future__ import annotations

from torchrod.cli import COMMANDS, help_pages, main
from torchrod.presets import PRESETS


def test_every_help_that_takes_a_rod_lists_every_preset():
    pages = help_pages()
    assert {"torchrod", *(f"torchrod {name}" for name in COMMANDS)} <= set(pages)
    with_rod = [line for line, text in pages.items() if "--rod" in text or "ROD" in text]
    assert "torchrod" in with_rod and "torchrod estimate" in with_rod and "torchrod stream" in with_rod
    for line in with_rod:
        flat = " ".join(pages[line].split())
        for name in PRESETS:
            assert name in flat, f"{line} --help does not name the preset {name}"


def test_the_top_level_help_names_every_preset(capsys):
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert f"preset name ({', '.join(PRESETS)})" in out
