"""The documentation's examples work: README.md, CONTRIBUTING.md and every page under docs/.

- Every ```python block runs, in order, one namespace per page, in a fresh temporary working
  directory. A block whose first line is ``# not run: <reason>`` is skipped (a Blender script that
  needs bpy's UI, a path to the reader's own capture); the reason is required.
- Every shell line that calls the CLI (``mlx3d ...``, ``python -m mlx3d ...``, after an optional
  ``$`` prompt, ``\\`` continuations joined) parses with the CLI's own argparse definitions, so a
  renamed or removed option fails here.
- Every ``make TARGET`` a page shows is a target of the Makefile.
"""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
from core_marks import above_kernels

pytestmark = above_kernels

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md"] + [p for p in (ROOT / "docs").rglob("*.md") if "hooks" not in p.parts])
FENCE = re.compile(r"^(?P<indent> *)```(?P<info>[^\n`]*)\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.M | re.S)
SHELL = {"sh", "bash", "shell", "console", "zsh"}


def _blocks(page: Path, languages: set) -> list:
    text = page.read_text(encoding="utf-8")
    out = []
    for m in FENCE.finditer(text):
        lang = m.group("info").strip().split(" ")[0].split("{")[0].lower()
        if lang in languages:
            indent = len(m.group("indent"))
            body = "\n".join(line[indent:] for line in m.group("body").splitlines())
            out.append((text.count("\n", 0, m.start()) + 1, body))
    return out


def _ids(pages):
    return [str(p.relative_to(ROOT)) for p in pages]


PYTHON_PAGES = [p for p in PAGES if p.exists() and _blocks(p, {"python", "py"})]
SHELL_PAGES = [p for p in PAGES if p.exists() and _blocks(p, SHELL)]


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=_ids(PYTHON_PAGES))
def test_python_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    ran = 0
    for line, body in _blocks(page, {"python", "py"}):
        first = body.lstrip().splitlines()[0] if body.strip() else ""
        if first.startswith("# not run"):
            assert re.match(r"# not run: \S", first), f"{page.name}:{line}: '# not run:' needs a reason"
            continue
        try:
            exec(compile(body, f"{page.relative_to(ROOT)}:{line}", "exec"), namespace)
        except Exception as exc:
            raise AssertionError(f"{page.relative_to(ROOT)}, the block at line {line}: {type(exc).__name__}: {exc}") from exc
        ran += 1
    assert ran or True


def _commands(body: str) -> list:
    """CLI invocations in a shell block: (argv after the program, the line as written)."""
    joined = re.sub(r"\\\n\s*", " ", body)
    out = []
    for raw in joined.splitlines():
        line = raw.strip()
        if line.startswith("$ "):
            line = line[2:]
        line = line.split(" #")[0].strip()
        for part in re.split(r"\s*(?:&&|;|\|\||&)\s*", line):
            words = shlex.split(part, comments=True) if part else []
            while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):  # VAR=value prefixes
                words = words[1:]
            if not words:
                continue
            prog = os.path.basename(words[0])
            if prog == "mlx3d":
                out.append((words[1:], raw.strip()))
            elif prog.startswith("python") and words[1:3] == ["-m", "mlx3d"]:
                out.append((words[3:], raw.strip()))
            elif "--" in words and prog in ("mlx.launch", "mpirun"):
                rest = words[words.index("--") + 1:] if prog == "mlx.launch" else words
                for i, w in enumerate(rest):
                    if os.path.basename(w).startswith("python") and rest[i + 1:i + 3] == ["-m", "mlx3d"]:
                        out.append((rest[i + 3:], raw.strip()))
    return out


@pytest.mark.parametrize("page", SHELL_PAGES, ids=_ids(SHELL_PAGES))
def test_cli_commands_parse(page, capsys):
    from mlx3d.cli import build_parser

    parser = build_parser()
    for line, body in _blocks(page, SHELL):
        for argv, written in _commands(body):
            if not argv or argv[0] in ("-h", "--help"):
                continue
            try:
                parser.parse_args(argv)
            except SystemExit as exc:
                err = capsys.readouterr().err
                raise AssertionError(f"{page.relative_to(ROOT)}:{line}: `{written}` does not parse: {err.strip()}") from exc


@pytest.mark.parametrize("page", [p for p in PAGES if p.exists()], ids=_ids([p for p in PAGES if p.exists()]))
def test_make_targets_exist(page):
    makefile = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([A-Za-z0-9_.-]+)\s*:(?!=)", makefile, re.M))
    targets |= set(re.findall(r"\b(test-[a-z0-9-]+)\b", makefile))
    for line, body in _blocks(page, SHELL):
        for m in re.finditer(r"(?:^|[;&|][ \t]*|\$ )make ((?:[a-z][\w-]*[ \t]*)+)", body, re.M):
            for target in m.group(1).split():
                if "=" in target:
                    continue
                assert target in targets, f"{page.relative_to(ROOT)}:{line}: `make {target}` is not a Makefile target"


def test_readme_is_short_and_its_cli_table_lists_every_command():
    import argparse

    from mlx3d.cli import build_parser

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300, "the README is for a first session; details go to docs/"
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    listed = re.findall(r"^\| `mlx3d (\w+)", text, re.M)
    assert sorted(listed) == sorted(sub.choices), (listed, list(sub.choices))


def test_readme_links_point_at_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" not in target:
            assert (ROOT / target).exists(), f"README.md links to {target}, which does not exist"
