"""The configuration reference, generated from the comments of ``conf/**/*.yaml`` at every ``mkdocs build``.

mkdocs loads this file as a hook (``hooks:`` in ``mkdocs.yml``): :func:`on_files` adds the page
``reference/configuration.md``, rendered by :func:`render` from the YAML files themselves, so the page can never
drift from the config tree. ``python docs/hooks/config_reference.py`` prints the page.

Each file's leading comment lines are its description; each ``key: value  # comment`` line is a row (dotted key,
default, comment), with the comment lines indented under it appended. A group's options are listed in one table
when they are many one-entry files (the degradation catalogue), else one section each.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
PAGE = "reference/configuration.md"
#: the apps' configs first, then the groups in the order of train.yaml's defaults list
APPS = ("train", "evaluate", "report")
#: groups whose options are listed in one table (one line each) rather than a section each
COMPACT = {"degradation"}

_KEY = re.compile(r"^(?P<indent>\s*)(?P<key>[A-Za-z_$@][\w.@/${}-]*)\s*:(?:\s+(?P<rest>.*))?$")
_ITEM = re.compile(r"^(?P<indent>\s*)-\s+(?P<rest>.*)$")


def _split_comment(text: str) -> tuple[str, str]:
    """(value, comment) of the text after ``key:``; a ``#`` inside quotes or brackets is part of the value."""
    quote, depth = None, 0
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "#" and depth <= 0 and (i == 0 or text[i - 1].isspace()):
            return text[:i].strip(), text[i + 1:].strip()
    return text.strip(), ""


def _md(text: str) -> str:
    """Comment text made safe for a Markdown table cell: ``[seed=1]`` stays literal text, not a reference link."""
    text = text.replace("\\", "\\\\").replace("|", "\\|").replace("*", "\\*")
    text = text.replace("[", "\\[").replace("]", "\\]")
    return text.replace("<", "&lt;").replace(">", "&gt;")


def parse(path: Path) -> tuple[list[str], list[tuple[str, str, str]], list[tuple[str, str]]]:
    """(header lines, rows of (dotted key, default, comment), defaults list as (entry, comment)) of one YAML file."""
    header: list[str] = []
    rows: list[list[str]] = []
    defaults: list[list[str]] = []
    stack: list[tuple[int, str]] = []  # (indent, key) of the open mappings
    last: list[str] | None = None  # the row (or defaults entry) continuation comments extend
    last_indent = -1
    in_header = True
    in_defaults = False
    for raw in path.read_text().splitlines():
        line = raw.rstrip()
        stripped = line.strip()
        if not stripped:
            in_header = False
            continue
        if stripped.startswith("#"):
            text = stripped.lstrip("#").strip()
            if in_header:
                if not text.startswith("@package"):
                    header.append(text)
                continue
            indent = len(line) - len(line.lstrip())
            if last is not None and indent > last_indent and text:
                last[-1] = f"{last[-1]} {text}".strip()
            continue
        in_header = False
        item = _ITEM.match(line)
        if item and in_defaults:
            value, comment = _split_comment(item.group("rest"))
            defaults.append([value, comment])
            last, last_indent = defaults[-1], len(item.group("indent"))
            continue
        m = _KEY.match(line)
        if not m:  # a list item or a continued value: comments below it still extend the last row
            continue
        indent = len(m.group("indent"))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        key = m.group("key")
        value, comment = _split_comment(m.group("rest") or "")
        in_defaults = indent == 0 and key == "defaults"
        if in_defaults:
            last = None
            continue
        dotted = ".".join([k for _, k in stack] + [key])
        if value == "":
            stack.append((indent, key))
        if value != "" or comment:
            rows.append([dotted, value, comment])
            last, last_indent = rows[-1], indent
        else:
            last = None
    return header, [tuple(r) for r in rows], [tuple(d) for d in defaults]


def _table(rows: list[tuple[str, str, str]]) -> list[str]:
    out = ["| key | default | what it is |", "|---|---|---|"]
    for key, value, comment in rows:
        shown = f"`{value}`" if value else ""
        out.append(f"| `{key}` | {shown.replace('|', '&#124;')} | {_md(comment)} |")
    return out


def _section(path: Path, title: str, level: str) -> list[str]:
    header, rows, defaults = parse(path)
    out = [f"{level} {title}", ""]
    if header:
        out += ["  \n".join(_md(h) for h in header), ""]
    if defaults:
        out += ["| defaults list entry | options |", "|---|---|"]
        out += [f"| `{_md(entry)}` | {_md(comment)} |" for entry, comment in defaults]
        out.append("")
    if rows:
        out += _table(rows) + [""]
    out += [f"Source: `{path.relative_to(ROOT)}`.", ""]
    return out


def _groups() -> list[Path]:
    order = []
    _, _, defaults = parse(CONF / "train.yaml")
    for entry, _ in defaults:
        name = entry.split(":", 1)[0].replace("override ", "").strip()
        if "/" not in name and (CONF / name).is_dir() and CONF / name not in order:  # hydra/* comes with hydra/
            order.append(CONF / name)
    order += sorted(p for p in CONF.iterdir() if p.is_dir() and p not in order)
    return order


def _group(group: Path) -> list[str]:
    rel = group.relative_to(CONF)
    files = sorted(group.rglob("*.yaml"))
    out = [f"## `{rel}` group", ""]
    base = group / "base.yaml"
    if base.exists():
        out += _section(base, f"`{rel}/base` (shared by the options)", "###")
    options = [f for f in files if f != base]
    names = [f"{f.relative_to(CONF).parent}={f.stem}" for f in options]  # hydra/launcher=slurm: nested groups
    out += ["Options: " + ", ".join(f"`{n}`" for n in names) + ".", ""]
    if rel.name in COMPACT:
        single = [f for f in options if "." in f.stem]
        out += ["| option | what it is |", "|---|---|"]
        for f in single:
            header, _, _ = parse(f)
            out.append(f"| `{f.stem}` | {_md(header[0] if header else '')} |")
        out.append("")
        for f in options:
            if f not in single:
                out += _section(f, f"`{rel}={f.stem}`", "###")
        return out
    for f, name in zip(options, names):
        out += _section(f, f"`{name}`", "###")
    return out


def render() -> str:
    """The configuration reference page (Markdown)."""
    out = [
        "# Configuration reference",
        "",
        "Every entry point is a Hydra app composed from `conf/`: `python -m torcsrl.train` from `conf/train.yaml`,",
        "`python -m torcsrl.evaluate` from `conf/evaluate.yaml`, `python -m torcsrl.report` from `conf/report.yaml`.",
        "A group is chosen with `group=option` (`algo=sac`), a key set with `key=value` (`algo.gamma=0.98`), a key",
        "added with `+key=value`. Unknown keys, wrong types, unknown names and severities outside 1..5 fail in one",
        "line before any work starts.",
        "",
        "This page is generated from the comments of the YAML files at every build of the site",
        "(`docs/hooks/config_reference.py`): the files are the source, units in `[brackets]`.",
        "",
    ]
    for app in APPS:
        out += _section(CONF / f"{app}.yaml", f"`conf/{app}.yaml`", "##")
    for group in _groups():
        out += _group(group)
    return "\n".join(out).rstrip() + "\n"


def on_files(files, config):  # noqa: ANN001, ANN201  (the mkdocs hook signature)
    """mkdocs hook: add the generated page to the site's files."""
    from mkdocs.structure.files import File  # deferred: only mkdocs builds need it

    files.append(File.generated(config, PAGE, content=render()))
    return files


if __name__ == "__main__":
    print(render(), end="")
