"""MkDocs hook: the command-line reference rendered from the commands' own argument parsers.

A page holding the marker ``<!-- cli-reference -->`` gets, in its place, one section per command and benchmark
suite with what its ``--help`` prints (:func:`torchrod.cli.help_pages`), so the reference never drifts from the
code and nothing is copied by hand.
"""

from __future__ import annotations

MARKER = "<!-- cli-reference -->"


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 - MkDocs' hook signature
    if MARKER not in markdown:
        return markdown
    from torchrod.cli import help_pages

    sections = []
    for command, text in help_pages(width=100).items():
        level = "##" if command.count(" ") <= 1 else "###"
        sections.append(f"{level} `{command}`\n\n```text\n{text.rstrip()}\n```\n")
    return markdown.replace(MARKER, "\n".join(sections))
