"""MkDocs hooks: the pages that are generated rather than written.

- ``index.md`` is the repository's README (one text, two places), its links made relative
  to ``docs/``;
- ``commands.md`` gets the reference of every command, printed by navapp's own argparse
  parser (``navapp.cli.build_parser``), so it cannot drift from the code;
- ``api.md`` gets a mkdocstrings block for every name in ``navapp.__all__``, at the module
  that defines it (``navapp._EXPORTS``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLI_MARK = "<!-- navapp-cli-reference -->"
API_MARK = "<!-- navapp-api-reference -->"


def readme_page() -> str:
    text = (ROOT / "README.md").read_text()
    return re.sub(r"\]\(docs/", "](", text)


def cli_reference() -> str:
    os.environ["COLUMNS"] = "100"  # argparse wraps help to the terminal: fix it for a stable page
    from navapp.cli import build_parser

    parser = build_parser()
    parser.prog = "navapp"
    out = ["```text", parser.format_help().rstrip(), "```", ""]
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, command in sub.choices.items():
        command.prog = f"navapp {name}"
        out += [f"### navapp {name}", "", "```text", command.format_help().rstrip(), "```", ""]
        inner = [a for a in command._actions if a.__class__.__name__ == "_SubParsersAction"]
        for action in inner:
            for sub_name, sub_command in action.choices.items():
                sub_command.prog = f"navapp {name} {sub_name}"
                out += [f"#### navapp {name} {sub_name}", "", "```text", sub_command.format_help().rstrip(),
                        "```", ""]
    return "\n".join(out)


def api_reference() -> str:
    import navapp

    out = []
    for name in navapp.__all__:
        target = navapp._EXPORTS[name]
        module, attr = target if isinstance(target, tuple) else (target, name)
        out += [f"::: {module}.{attr}", ""]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    src = page.file.src_uri
    if src == "index.md":
        return readme_page()
    if src == "commands.md":
        assert CLI_MARK in markdown, f"{src} lost its {CLI_MARK} marker"
        return markdown.replace(CLI_MARK, cli_reference())
    if src == "api.md":
        assert API_MARK in markdown, f"{src} lost its {API_MARK} marker"
        return markdown.replace(API_MARK, api_reference())
    return markdown
