"""The documentation stays true: every Python snippet of README.md and docs/ runs, and every documented command line
of the three apps composes and passes its config check.

Conventions for writers of README.md and docs/**/*.md (the site's "Getting started" repeats them):

* A ```` ```python ```` block is self-contained (its own imports) and runs here in a fresh namespace, in the order of
  its file, with small budgets (a few env steps, a tiny grid): the whole file stays well under a minute.
* What cannot run here (a 30-minute training, a held-out benchmark, a folder only a run creates) is written as a
  ```` ```bash ```` block of command lines. Every ``python -m torcsrl.train|evaluate|report ...`` line of such a block is
  composed with Hydra exactly as the app would compose it (sweeps reduced to their first value, ``<placeholder>`` values
  and Hydra launcher / sweeper settings left out) and checked by the app's own config check — training commands
  with ``debug=smoke`` added, the way a smoke run of them would start. The main command itself trains, on the toy
  env.
* A Python block whose first line is ``# doc: not run (<why>)`` is skipped (there is none today; prefer bash).

Uses ``mktestdocs`` (the ``dev`` extra) to find the blocks.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest
from mktestdocs import grab_code_blocks

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
SKIP = "# doc: not run"
APPS = ("train", "evaluate", "report")
#: overrides of where a run writes or resumes: a placeholder there says nothing about the config
_PLACEHOLDER = re.compile(r"<[^>]*>")


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def python_blocks(path: Path) -> list[str]:
    return [b for b in grab_code_blocks(path.read_text(), lang="python") if not b.lstrip().startswith(SKIP)]


def bash_blocks(path: Path) -> list[str]:
    return grab_code_blocks(path.read_text(), lang="bash")


def app_commands(path: Path) -> list[tuple[str, list[str]]]:
    """(app, argv) of every ``python -m torcsrl.<app> ...`` line of the file's bash blocks (continuations joined)."""
    out = []
    for block in bash_blocks(path):
        for line in block.replace("\\\n", " ").splitlines():
            for part in re.split(r"\s(?:&&|;)\s", line):
                part = part.strip()
                if not part.startswith("python -m torcsrl."):
                    continue
                words = shlex.split(_PLACEHOLDER.sub("<x>", part), comments=True)  # a placeholder may hold spaces
                if len(words) >= 3:
                    app = words[2].split(".", 1)[1]
                    if app in APPS:
                        out.append((app, [w for w in words[3:] if w != "&"]))
    return out


def _first_value(value: str, group: str) -> str | None:
    """A sweep's first value (``a,b`` → ``a``; ``glob(x.*)`` → the first option of the group that matches)."""
    if value.startswith("glob(") and value.endswith(")"):
        names = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
        pattern = re.compile(value[5:-1].replace(".", r"\.").replace("*", ".*") + "$")
        hits = [n for n in names if pattern.match(n)]
        return hits[0] if hits else None
    depth, cut = 0, None
    for i, ch in enumerate(value):
        depth += ch in "[{("
        depth -= ch in "]})"
        if ch == "," and depth == 0:
            cut = i
            break
    return value if cut is None else value[:cut]


def job_overrides(app: str, argv: list[str]) -> list[str] | None:
    """The overrides one job of the documented command composes with (None: it cannot be composed here)."""
    if app == "train":
        words = argv
    else:  # evaluate and report: their flags are aliases of key=value overrides
        from torcsrl.utils.hydra_app import flags_to_overrides

        module = __import__(f"torcsrl.{app}.app", fromlist=["FLAGS"])
        words = flags_to_overrides(argv, module.FLAGS)
    out = []
    for w in words:
        if w in ("-m", "--multirun"):
            continue
        if _PLACEHOLDER.fullmatch(w):
            continue  # "<the run's overrides>": stands for overrides shown elsewhere
        key, sep, value = w.partition("=")
        if not sep:
            return None  # a positional argument: not an app config command
        name = key.lstrip("+~")
        if name.startswith("init.") and _PLACEHOLDER.search(value):
            out.append(f"{key}=runs/placeholder/checkpoints/ckpt.pt")  # a run's checkpoint: validation checks that one is set
            continue
        if name.startswith("hydra") or name == "hparams_search" or _PLACEHOLDER.search(value):
            continue  # launcher / sweeper settings (optional plugins), or a folder only a run creates
        value = _first_value(value, name)
        if value is None:
            return None
        out.append(f"{key}={value}")
    return out


COMMANDS = [(f"{_rel(p)}:{app}:{i}", app, argv) for p in DOC_FILES for i, (app, argv) in enumerate(app_commands(p))]


def test_the_docs_are_collected():
    """The collection is not silently empty: the README and the site's pages hold snippets and commands."""
    assert (ROOT / "mkdocs.yml").exists()
    assert len([p for p in DOC_FILES if python_blocks(p)]) >= 8
    assert {app for _, app, _ in COMMANDS} == set(APPS)


@pytest.mark.parametrize("path", [p for p in DOC_FILES if python_blocks(p)], ids=_rel)
def test_python_snippets_run(path: Path):
    for i, block in enumerate(python_blocks(path)):
        code = compile(block, f"{_rel(path)} (python block {i + 1})", "exec")
        exec(code, {"__name__": "__main__"})


def test_documented_commands_compose_and_validate():
    """Every documented app command composes; train commands with debug=smoke pass ``problems``, evaluate and report
    commands their app's ``check_config``. One Hydra context per app, each distinct command once (a composition costs
    ~0.5 s)."""
    from hydra import compose, initialize_config_dir

    from torcsrl.evaluate.app import check_config as check_evaluate
    from torcsrl.report.app import check_config as check_report
    from torcsrl.training import problems

    failures, jobs = [], {}
    for where, app, argv in COMMANDS:
        overrides = job_overrides(app, argv)
        if overrides is None:
            failures.append(f"{where}: cannot read {' '.join(argv)!r} as overrides")
        else:
            jobs.setdefault((app, tuple(overrides)), where)
    for app in APPS:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3", job_name=app):
            for (job_app, overrides), where in jobs.items():
                if job_app != app:
                    continue
                try:
                    if app == "train":
                        found = problems(compose("train", overrides=[*overrides, "debug=smoke"]))
                        if found:
                            failures.append(f"{where}: {' '.join(overrides)}: {found}")
                    else:
                        (check_evaluate if app == "evaluate" else check_report)(compose(app, overrides=list(overrides)))
                except Exception as err:  # noqa: BLE001  (every failure is listed, not only the first)
                    failures.append(f"{where}: {' '.join(overrides)}: {type(err).__name__}: {err}")
    assert not failures, "\n".join(failures)


def test_main_command_smoke(tmp_path: Path):
    """README's main command shrunk as the README says (``env=toy debug=smoke``) trains and checkpoints; in-process,
    as the training tests call it (the command line itself is tests/test_train.py's)."""
    from hydra import compose, initialize_config_dir

    from torcsrl.training import train

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3", job_name="train"):
        cfg = compose("train", overrides=["env=toy", "debug=smoke", f"run_dir={tmp_path / 'run'}"])
    result = train(cfg)
    assert result["frames"] >= cfg.total_frames and result["episodes"] > 0
    assert list((tmp_path / "run" / "checkpoints").glob("ckpt_*.pt"))


def test_configuration_reference_renders():
    """The site's configuration page (generated from conf/ at every build) lists every config file of the tree."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        import config_reference
    finally:
        sys.path.remove(str(ROOT / "docs" / "hooks"))
    page = config_reference.render()
    for path in CONF.rglob("*.yaml"):
        rel = path.relative_to(CONF)
        if rel.parts[0] == "degradation" and "." in path.stem:
            assert f"`{path.stem}`" in page, rel
        elif path.name == "base.yaml":
            assert f"`{rel.parent}/base`" in page, rel
        elif len(rel.parts) == 1:
            assert f"`conf/{rel}`" in page, rel
        else:
            assert f"`{rel.parent}={path.stem}`" in page, rel


def test_configuration_reference_keeps_brackets_literal():
    """A comment such as ``[algo=td3] [seed=1]`` renders as text: unescaped, Markdown reads ``[a] [b]`` as a
    reference link and the strict site build (mkdocs-autorefs) fails on the missing target."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        import config_reference
    finally:
        sys.path.remove(str(ROOT / "docs" / "hooks"))
    page = config_reference.render()
    reference = re.compile(r"(?<!\\)\[[^\]\n]*(?<!\\)\] ?(?<!\\)\[")
    assert not reference.search(page), reference.search(page).group(0)
    assert r"\[seed=1\]" in page
