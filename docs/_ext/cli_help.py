"""Sphinx directive ``.. hybridoc-cli-help::``: the ``--help`` text of every subcommand.

It builds the installed command's parser (:func:`hybridoc.cli.build_parser`, which includes
every plug-in that is installed) and renders ``hybridoc --help`` and ``hybridoc COMMAND
--help`` as literal blocks, so the page always matches the version it was built from.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from docutils import nodes
from docutils.parsers.rst import Directive

_WIDTH = "88"  # argparse wraps to $COLUMNS; fixed so that the build is reproducible


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse has no public accessor for subparsers
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


class CliHelp(Directive):
    has_content = False

    def run(self) -> list[Any]:
        from hybridoc.cli import build_parser

        old = os.environ.get("COLUMNS")
        os.environ["COLUMNS"] = _WIDTH
        try:
            parser = build_parser()
            blocks = [("hybridoc", parser.format_help())]
            for name, sub in _subcommands(parser).items():
                blocks.append((f"hybridoc {name}", sub.format_help()))
        finally:
            if old is None:
                del os.environ["COLUMNS"]
            else:
                os.environ["COLUMNS"] = old
        out: list[Any] = []
        for title, text in blocks:
            out.append(nodes.rubric(text=title))
            block = nodes.literal_block(text, text)
            block["language"] = "text"
            out.append(block)
        return out


def setup(app: Any) -> dict[str, Any]:
    app.add_directive("hybridoc-cli-help", CliHelp)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
