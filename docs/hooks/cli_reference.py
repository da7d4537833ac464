"""MkDocs hook: the command-line reference, generated from ``mlx3d.cli.build_parser()`` at build time.

A page containing the line ``<!-- mlx3d-cli -->`` gets, in its place, one section per
subcommand: its description, usage line and a table of its arguments (help text and
default), so the reference cannot drift from the argparse definitions.
"""

from __future__ import annotations

import argparse

MARKER = "<!-- mlx3d-cli -->"


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _argument_rows(parser: argparse.ArgumentParser) -> list:
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue
        if action.option_strings:
            name = ", ".join(f"`{s}`" for s in action.option_strings)
            if action.nargs != 0:
                metavar = action.metavar or (f"{{{','.join(map(str, action.choices))}}}" if action.choices else action.dest.upper())
                name += f" `{metavar if isinstance(metavar, str) else ' '.join(metavar)}`"
        else:
            name = f"`{action.metavar or action.dest}`"
        default = "" if action.default in (None, argparse.SUPPRESS, False) or not action.option_strings else f"`{action.default}`"
        choices = f" (one of {', '.join(f'`{c}`' for c in action.choices)})" if action.choices and action.option_strings else ""
        rows.append(f"| {name} | {_cell(action.help or '')}{choices} | {default} |")
    return rows


def cli_markdown() -> str:
    from mlx3d.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {choice.dest: choice.help for choice in sub._choices_actions}
    out = []
    for name, command in sub.choices.items():
        out += [f"## `mlx3d {name}`", "", _cell(helps.get(name) or command.description or ""), "",
                "```text", command.format_usage().strip().replace("usage: ", ""), "```", ""]
        rows = _argument_rows(command)
        if rows:
            out += ["| argument | what it does | default |", "|---|---|---|", *rows, ""]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_markdown())
    return markdown
