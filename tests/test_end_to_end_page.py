"""docs/guides/end-to-end.md, run as a newcomer runs it: every ``sh`` block, in order, in one empty folder.

``torchrod`` is ``python -m torchrod`` of this checkout and ``python`` this interpreter (shell functions ahead of
each block). Each block must exit 0, or the status an ``<!-- test: exit N -->`` comment on the line before it
names, and the key lines of the output the page shows after it (the ``text`` block that follows, up to the next
``sh`` block) must be in the output the block gave: the rod report's EI, layout and force count, the calibrations'
reading counts and files written, each answer's id, status and force count. Timings and the digits of fitted
values are not compared. The section on raw wavelengths with a jig calibration runs too: the page's commands make
every file they read, so nothing is left to ``--help``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "guides" / "end-to-end.md"

PRELUDE = 'set -eo pipefail\ntorchrod() { "$E2E_PYTHON" -m torchrod "$@"; }\npython() { "$E2E_PYTHON" "$@"; }\n'
"""Ahead of each block: stop at the first failing command (in a pipe too), and the page's two programs."""

KEY_LINES = (
    r"^(EI|gratings|forces|length) .*$",
    r"^1 N at the tip .*$",
    r"^torchrod \w+: error: [^;]*",
    r"^torchrod calibrate( --fibre)?: \d+ (jig )?readings.*$",
    r"^wrote \S+$",
    r"^id,ux_1,uy_1,.*$",
    r'"id": "\w+", "status": "\w+", "num_forces": \d+',
    r"^\w+  (ok|misfit|unconverged|poorly_determined|timeout)  \d+ of \d+ forces$",
    r"^\w+\.png$",
)
"""Patterns of the shown output whose every match must be in the real output (whitespace runs compared as one)."""


@dataclass(frozen=True)
class Step:
    """One ``sh`` block of the page: its commands, the exit status it must give, and the output shown after it."""

    line: int
    command: str
    status: int
    shown: str


def page_steps(text: str) -> list[Step]:
    """The page's ``sh`` blocks in order, each with its expected status and the ``text`` block shown after it."""
    lines = text.splitlines()
    blocks: list[tuple[int, str, str, int]] = []  # (line, language, body, status)
    k = 0
    while k < len(lines):
        fence = re.fullmatch(r"```(\w*)\s*", lines[k])
        if fence is None:
            k += 1
            continue
        mark = re.fullmatch(r"<!--\s*test:\s*exit\s+(\d+)\s*-->", lines[k - 1].strip()) if k else None
        end = lines.index("```", k + 1)
        blocks.append((k + 1, fence.group(1), "\n".join(lines[k + 1 : end]), int(mark.group(1)) if mark else 0))
        k = end + 1
    steps = []
    for n, (line, language, body, status) in enumerate(blocks):
        if language != "sh":
            continue
        shown = ""
        for _, later_language, later_body, _ in blocks[n + 1 :]:
            if later_language == "sh":
                break
            if later_language == "text":
                shown = later_body
                break
        steps.append(Step(line, body, status, shown))
    return steps


def key_lines(shown: str) -> list[str]:
    """The parts of a shown output that the real output must hold."""
    return [m.group(0) for pattern in KEY_LINES for m in re.finditer(pattern, shown, re.MULTILINE)]


def _squeeze(text: str) -> str:
    return re.sub(r"[ \t]+", " ", text)


def test_page_names_what_it_checks():
    """The page shows the lines this test holds the commands to: without them the run below would check little."""
    keys = [key for step in page_steps(PAGE.read_text()) for key in key_lines(step.shown)]
    assert any(key.startswith("EI ") for key in keys)
    assert any(key.startswith("torchrod calibrate: 8 readings") for key in keys)
    assert any(key.startswith("torchrod calibrate --fibre: 15 jig readings") for key in keys)
    statuses = [key.split()[1] for key in keys if re.fullmatch(KEY_LINES[7][1:-1], key)]
    assert statuses.count("ok") >= 8 and statuses.count("misfit") >= 2


def test_page_runs_as_shown(tmp_path):
    env = dict(
        os.environ,
        E2E_PYTHON=sys.executable,
        PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        PYTHONUNBUFFERED="1",  # stdout and stderr interleaved as on a terminal
    )
    steps = page_steps(PAGE.read_text())
    assert len(steps) >= 10
    for step in steps:
        done = subprocess.run(
            ["bash", "-c", PRELUDE + step.command],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=300,
        )
        where = f"{PAGE.name}, the block at line {step.line}"
        assert done.returncode == step.status, f"{where} exited {done.returncode}:\n{done.stdout}"
        output = _squeeze(done.stdout)
        for key in key_lines(step.shown):
            assert _squeeze(key) in output, f"{where}: the page shows {key!r}, the run gave:\n{done.stdout}"
