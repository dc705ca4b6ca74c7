"""The documentation holds together: every relative link in README.md and docs/*.md reaches an existing file
(and, for `#anchor` links into Markdown, an existing heading), every docs page is linked from the README, and
the README stays the short entry point that CI's test command is named in.

Anchors follow GitHub's rule for heading ids (lowercase; drop everything but letters, digits, `_`, `-` and
spaces; spaces become `-`; a repeated id gets `-1`, `-2`, ...), because that is where readers follow them.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

import pytest
import typer

from jitterguard.cli import app
from jitterguard.stack.supervisor import StackSpec, programs

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md"))
MARKDOWN = [ROOT / "README.md", *PAGES]

_FENCE = re.compile(r"^\s*(```|~~~)")
_CODE_SPAN = re.compile(r"`+[^`]*`+")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_HTML_ID = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"")


def _prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks (links and headings inside code are not links or headings)."""
    out, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return out


def github_slug(heading: str) -> str:
    """GitHub's id for a heading's text (before de-duplication)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading keeps only its text
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every id a link into ``path`` can target: its headings' slugs (de-duplicated as GitHub does)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for line in _prose_lines(path.read_text(encoding="utf-8")):
        out.update(_HTML_ID.findall(line))
        m = _HEADING.match(line)
        if not m:
            continue
        slug = github_slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(path: Path) -> list[str]:
    """Targets of the Markdown links and images in ``path``'s prose (code spans and blocks excluded)."""
    found: list[str] = []
    for line in _prose_lines(path.read_text(encoding="utf-8")):
        found.extend(_LINK.findall(_CODE_SPAN.sub("", line)))
    return found


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def broken_links(path: Path) -> list[str]:
    """Each relative link of ``path`` whose file or heading does not exist, with the reason."""
    bad: list[str] = []
    for target in links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ... are not checked here
            continue
        file_part, _, anchor = target.partition("#")
        dest = path if not file_part else (path.parent / file_part).resolve()
        if not dest.exists():
            bad.append(f"{target}: no such file {_shown(dest)}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {_shown(dest)}")
    return bad


def test_github_slugs_of_headings_like_ours() -> None:
    assert github_slug("`jitterguard bench pipeline`") == "jitterguard-bench-pipeline"
    assert github_slug("The detector (paper §III-A, §IV-A, Table I)") == "the-detector-paper-iii-a-iv-a-table-i"
    assert github_slug("Several hosts: Zenoh router with mutual TLS (`deploy/zenoh/`)") == (
        "several-hosts-zenoh-router-with-mutual-tls-deployzenoh")
    assert github_slug("The classifier (`ClassifierConfig`)") == "the-classifier-classifierconfig"


def test_the_checker_finds_a_broken_file_and_a_broken_anchor(tmp_path: Path) -> None:
    (tmp_path / "a.md").write_text("# A\n\n## Real heading\n\nsee [b](b.md) and [x](#real-heading)\n", encoding="utf-8")
    page = tmp_path / "b.md"
    page.write_text(
        "# B\n\n[ok](a.md#real-heading) [gone](missing.md) [no anchor](a.md#nope)\n"
        "`[in code](missing2.md)`\n```\n[in a block](missing3.md)\n```\n[web](https://example.org/x)\n",
        encoding="utf-8",
    )
    bad = [b.split(":")[0] for b in broken_links(page)]
    assert bad == ["missing.md", "a.md#nope"]
    assert broken_links(tmp_path / "a.md") == []


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(path: Path) -> None:
    assert broken_links(path) == []


def test_every_docs_page_is_linked_from_the_readme_and_has_a_title_and_intro() -> None:
    assert PAGES, "docs/*.md pages exist"
    readme_targets = {t.partition("#")[0] for t in links(ROOT / "README.md")}
    for page in PAGES:
        rel = page.relative_to(ROOT).as_posix()
        assert rel in readme_targets, f"README.md does not link {rel}"
        lines = page.read_text(encoding="utf-8").splitlines()
        assert lines[0].startswith("# "), f"{rel} starts with a title"
        assert lines[1] == "" and lines[2].strip() and not lines[2].startswith("#"), f"{rel}: an intro paragraph"


_DELIMITER_ROW = re.compile(r"^\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")


def unended_tables(path: Path) -> list[str]:
    """Each table in ``path`` whose rows run on into a line that is not a row: GitHub's Markdown reads such a line
    (a cell's text wrapped onto the next line, a paragraph without the blank line before it) as one more row, so
    the table shows a broken row and the rest of that cell as a stray one."""
    bad: list[str] = []
    lines = _prose_lines(path.read_text(encoding="utf-8"))
    in_table = False
    for prev, line in zip(lines, lines[1:]):
        if _DELIMITER_ROW.match(line) and prev.lstrip().startswith("|"):
            in_table = True
        elif in_table and not line.lstrip().startswith("|"):
            if line.strip():
                bad.append(f"{_shown(path)}: a table runs on into {line.strip()[:60]!r}")
            in_table = False
    return bad


def test_the_table_checker_finds_a_row_wrapped_onto_the_next_line(tmp_path: Path) -> None:
    page = tmp_path / "t.md"
    page.write_text("# T\n\n| a | b |\n|---|---|\n| 1 | two\nlines |\n\n| c |\n|---|\n| 3 |\n\ntext\n"
                    "```\n| x |\n|---|\nnot a table\n```\n", encoding="utf-8")
    assert unended_tables(page) == [f"{page}: a table runs on into 'lines |'"]


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_table_ends_with_a_blank_line(path: Path) -> None:
    assert unended_tables(path) == []


def test_cli_page_names_every_environment_variable_a_flag_reads() -> None:
    """An option that falls back on an environment variable (``--ns``: ``JG_NS``) is a setting a deployment may make
    without any flag: docs/cli.md names each one (it had not named ``JG_NS``)."""
    page = (DOCS / "cli.md").read_text(encoding="utf-8")
    envs: set[str] = set()

    def walk(cmd) -> None:
        for sub in getattr(cmd, "commands", {}).values():
            walk(sub)
        for param in getattr(cmd, "params", []):
            env = getattr(param, "envvar", None)
            envs.update([env] if isinstance(env, str) else (env or []))

    walk(typer.main.get_command(app))
    assert {"JG_NS", "JG_STACK"} <= envs
    assert sorted(e for e in envs if f"`{e}`" not in page and f"`${e}`" not in page) == []


def test_logs_names_every_program_up_can_run() -> None:
    """`jitterguard logs SERVICE` reads any program's log; its help (and so docs/cli.md's table, and the list in
    docs/operations.md) had left out the ones `up` runs only on request (foxglove, record, ros2-in, ros2-out)."""
    specs = [StackSpec(run_dir="/r", input="points", foxglove=True, record_ros2="/r/bag"),
             StackSpec(run_dir="/r", input="tracks"),
             StackSpec(run_dir="/r", input="points", ros2_points="/sensing/lidar/top/pointcloud")]
    names = {p.name for spec in specs for p in programs(spec)} | {"supervisord"}
    assert {"router", "classifier", "replay", "monitor-watch", "foxglove", "record", "ros2-in"} <= names
    logs = typer.main.get_command(app).commands["logs"]  # type: ignore[attr-defined]
    help_text = next(p.help for p in logs.params if p.name == "service")
    assert sorted(n for n in names if not re.search(rf"(?<![\w-]){re.escape(n)}(?![\w-])", help_text)) == []
    ops = (DOCS / "operations.md").read_text(encoding="utf-8")
    listed = re.search(r"`jitterguard logs SERVICE \[-n 50\]` prints the end of one program's log \(([^)]*)\)", ops)
    assert listed, "operations.md lists the programs `logs` reads"
    assert sorted(n for n in names if f"`{n}`" not in listed.group(1)) == []


def test_readme_is_short_and_names_the_commands_ci_runs() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    assert "bash scripts/run.sh" in readme and "bash scripts/test.sh" in readme
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text(encoding="utf-8")


def test_cli_page_lists_every_command_and_flag() -> None:
    """docs/cli.md promises every command and flag: each command has its section and each option its name."""
    page = (DOCS / "cli.md").read_text(encoding="utf-8")
    missing: list[str] = []

    def walk(cmd, path: str) -> None:
        if hasattr(cmd, "commands"):
            for name, sub in cmd.commands.items():
                walk(sub, f"{path} {name}")
            return
        if f"### `{path}`" not in page:
            missing.append(path)
        for param in cmd.params:
            for opt in getattr(param, "opts", []) + getattr(param, "secondary_opts", []):
                if opt.startswith("-") and opt != "--help" and f"`{opt}`" not in page:
                    missing.append(f"{path} {opt}")

    walk(typer.main.get_command(app), "jitterguard")
    assert missing == []


def cli_tables(page: str) -> dict[str, dict[str, tuple[str, str]]]:
    """docs/cli.md's option tables: per ``### `command` `` section, each name in a row's first cell (``--flag``,
    ``-d``, ``SOURCE``) → (default cell, meaning cell)."""
    tables: dict[str, dict[str, tuple[str, str]]] = {}
    section: dict[str, tuple[str, str]] | None = None
    for line in _prose_lines(page):
        heading = re.match(r"^### `([^`]+)`", line)
        if heading:
            section = tables.setdefault(heading.group(1), {})
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("| `") else []
        if section is not None and len(cells) >= 3:
            for name in re.findall(r"`([^`]+)`", cells[0]):
                section[name] = (cells[1], cells[2])
    return tables


def default_disagreements(root, page: str, path: str = "jitterguard") -> list[str]:
    """Each option of ``root`` (a click command tree) whose default in docs/cli.md's table is not the one the
    command has: a required option must read ``required``; a flag ``on``/``off`` or the spelling in force
    (``--no-twist``); any other default its value. A default of None is resolved at run time (from a parameter
    file, the weights, the environment) and its row says how in words, which this cannot check."""
    bad: list[str] = []
    table = cli_tables(page)

    def walk(cmd, where: str) -> None:
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, f"{where} {name}")
        rows = table.get(where, {})
        for param in getattr(cmd, "params", []):
            names = [param.name.upper()] if not param.opts[0].startswith("-") else [*param.opts, *param.secondary_opts]
            row = next((rows[n] for n in names if n in rows), None)
            if row is None or "--help" in names:
                continue
            cell, default = row[0], param.default
            if param.required:
                ok = cell == "required"
            elif callable(default) or default is None or default == "" or cell == "required":
                ok = cell != "required"
            elif getattr(param, "is_flag", False) and isinstance(default, bool):
                spelled = param.opts[0] if default or not param.secondary_opts else param.secondary_opts[0]
                ok = cell in ("on" if default else "off", f"`{spelled}`")
            else:
                ok = re.search(rf"(?<![\w.]){re.escape(str(default))}(?![\w.])", cell) is not None
            if not ok:
                bad.append(f"{where} {names[0]}: --help's default {default!r}, docs/cli.md's {cell!r}")

    walk(root, path)
    return bad


def test_the_default_checker_finds_a_default_the_page_misstates() -> None:
    demo = typer.Typer()

    @demo.command("run")
    def run(out: Annotated[str, typer.Option("--out")],
            rate: Annotated[float, typer.Option("--rate")] = 10.0,
            twist: Annotated[bool, typer.Option("--twist/--no-twist")] = True,
            flips: Annotated[bool, typer.Option("--flips/--no-flips")] = False,
            seed: Annotated[int, typer.Option("--seed")] = 0) -> None:
        """A command of a demo app."""

    @demo.command("other")
    def other() -> None:
        """Another, so that `run` is a sub-command."""

    page = ("### `demo run`\n\n| argument / option | default | meaning |\n|---|---|---|\n"
            "| `--out` |  | x |\n| `--rate` | `1.0` | x |\n| `--twist` / `--no-twist` | `--twist` | x |\n"
            "| `--flips` / `--no-flips` | on | x |\n| `--seed` | `0` | x |\n")
    assert default_disagreements(typer.main.get_command(demo), page, "demo") == [
        "demo run --out: --help's default None, docs/cli.md's ''",
        "demo run --rate: --help's default 10.0, docs/cli.md's '`1.0`'",
        "demo run --flips: --help's default False, docs/cli.md's 'on'",
    ]


def test_cli_page_states_every_default_as_help_has_it() -> None:
    page = (DOCS / "cli.md").read_text(encoding="utf-8")
    assert default_disagreements(typer.main.get_command(app), page) == []


def test_http_api_page_lists_every_route_and_no_other() -> None:
    """docs/http-api.md's endpoint table names every route the sidecar serves (``METHOD path``; HEAD, which only
    answers a GET's status, on that GET's row) and no route it does not serve."""
    from jitterguard.services.sidecar.routes import ROUTERS

    page = (DOCS / "http-api.md").read_text(encoding="utf-8")
    rows = {m.group(1): line for line in page.splitlines() if line.startswith("| `")
            for m in re.finditer(r"`((?:GET|HEAD|PUT|PATCH|POST|DELETE) /[^`?]*)", line)}
    served = {f"{method} {route.path}" for router in ROUTERS for route in router.routes
              for method in getattr(route, "methods", None) or ()}
    missing = sorted(s for s in served if s not in rows and not (
        s.startswith("HEAD ") and "`HEAD`" in rows.get(s.replace("HEAD", "GET", 1), "")))
    assert "GET /v1/state/{track_id}" in served and missing == []
    assert sorted(set(rows) - served) == []
