"""MkDocs hook: the Python API reference, generated from each module's runtime ``__all__``.

A page containing ``<!-- mlx3d-api MODULE -->`` gets, in its place, one mkdocstrings
entry per public name of MODULE (its ``__all__``, which the lazily importing packages
build at run time), each rendered from the module that defines it, so every public name
is documented from its own docstring and none is listed by hand.
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

PATTERN = re.compile(r"^<!-- mlx3d-api (?P<module>[\w.]+) -->$", re.M)
ROOT = Path(__file__).resolve().parents[2]


def _defining_path(module, name: str) -> str:
    obj = getattr(module, name)
    if inspect.ismodule(obj):
        return obj.__name__
    if getattr(obj, "__module__", None) and getattr(obj, "__qualname__", None) and (inspect.isclass(obj) or callable(obj)):
        return f"{obj.__module__}.{obj.__qualname__}"
    # a constant: the module of the package whose source assigns it
    package = module.__name__.split(".")[0]
    for path in sorted((ROOT / package).rglob("*.py")):
        if re.search(rf"^{re.escape(name)}\s*(:[^=\n]*)?=", path.read_text(encoding="utf-8"), re.M):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            return ".".join(parts) + f".{name}"
    raise LookupError(f"cannot find where {module.__name__}.{name} is defined")


def api_markdown(module_name: str) -> str:
    module = importlib.import_module(module_name)
    names = list(getattr(module, "__all__", []))
    if not names:
        raise LookupError(f"{module_name} has no __all__")
    out = []
    for name in names:
        target = _defining_path(module, name)
        out += [f"::: {target}", "    options:", "      show_root_full_path: false", "      heading_level: 2", ""]
        if target != f"{module_name}.{name}":
            out += [f"*`{module_name}.{name}` is defined in `{target.rsplit('.', 1)[0]}`.*", ""]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    return PATTERN.sub(lambda m: api_markdown(m.group("module")), markdown)
