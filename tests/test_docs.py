"""Examples are tests: the commands and links shown in README.md and docs/*.md.

* Every command line in a ```bash block, and every ``regtrack ...`` code span in the text,
  is checked: a ``regtrack ...`` (or ``python -m regtrack.cli ...``) line must parse with regtrack's own argparse parser (nothing is
  executed); ``make TARGET`` must name a Makefile target; ``python pipelines/X.py`` must
  name a script that exists; any other program must be in :data:`OTHER_PROGRAMS`.
  Output shown in the docs goes in ```text blocks, which are not checked.
* Every relative link and image resolves to a file of the repository.
* README.md stays a user's page: at most 200 lines.
* ``docs/cli.md`` is what ``pipelines/make_cli_docs.py`` writes from the parsers.
* The cheap commands run for real: ``regtrack --help``, every command's ``--help``, and
  ``regtrack validate`` on the bundled sample case, as the README shows them.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
from pathlib import Path

import pytest

from regtrack.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

#: programs other than regtrack that the docs may show in ```bash blocks
OTHER_PROGRAMS = {"make", "cd", "cp", "mkdir", "ls", "git", "pip", "python", "paraview",
                  "Slicer", "cat", "export", "unzip", "pytest"}

FENCE = re.compile(r"^```(\w*)\s*$")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _bash_commands(path: Path) -> list[tuple[int, str]]:
    """(line number, command) of every command in the file's ```bash blocks; a trailing
    backslash continues a command on the next line."""
    out, lang, pending, start = [], None, "", 0
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        m = FENCE.match(line.strip())
        if m:
            lang = None if lang is not None else m.group(1)
            continue
        if lang not in ("bash", "sh", "shell"):
            continue
        text = line.strip()
        if text.startswith("$ "):
            text = text[2:]
        if not pending:
            start = n
        if text.endswith("\\"):
            pending += text[:-1] + " "
            continue
        text, pending = pending + text, ""
        if text and not text.startswith("#"):
            out.append((start, text))
    return out


INLINE = re.compile(r"`((?:regtrack|python -m regtrack\.cli) [^`]*)`")


def _inline_commands(path: Path) -> list[tuple[int, str]]:
    """(line number, command) of the ``regtrack ...`` code spans in the text (tables,
    prose) outside code blocks; ``COMMAND`` stands for any command and is skipped."""
    out, in_code = [], False
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if FENCE.match(line.strip()):
            in_code = not in_code
            continue
        if not in_code:
            out += [(n, m.group(1)) for m in INLINE.finditer(line) if "COMMAND" not in m.group(1)]
    return out


def _all_commands() -> list[tuple[str, str]]:
    cases = []
    for doc in DOCS:
        for n, cmd in _bash_commands(doc):
            cases.append((f"{doc.relative_to(REPO)}:{n}", cmd))
    return cases


def _all_mentions() -> list[tuple[str, str]]:
    return [(f"{doc.relative_to(REPO)}:{n}", cmd) for doc in DOCS for n, cmd in _inline_commands(doc)]


COMMANDS = _all_commands()


def _regtrack_argv(words: list[str]) -> list[str] | None:
    """The arguments after ``regtrack`` / ``python -m regtrack.cli``, or None."""
    if words[:1] == ["regtrack"]:
        return words[1:]
    for i in range(len(words) - 2):
        if words[i].endswith("python") and words[i + 1:i + 3] == ["-m", "regtrack.cli"]:
            return words[i + 3:]
    return None


def _makefile_targets() -> set[str]:
    text = (REPO / "Makefile").read_text(encoding="utf-8")
    return {m.group(1) for m in re.finditer(r"^([A-Za-z][\w-]*):", text, re.MULTILINE)}


def test_the_docs_show_commands():
    """The checks below see the README's commands (a parser that found no block would
    pass every command test)."""
    shown = [c for where, c in COMMANDS if where.startswith("README.md")]
    assert "make demo" in " ".join(shown) and any(c.startswith("regtrack run") for c in shown)


@pytest.mark.parametrize("where, command", COMMANDS, ids=[w for w, _ in COMMANDS])
def test_command_in_docs_is_valid(where, command):
    # a pipe, `&&` or `;` joins several commands: check each
    for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", command):
        words = shlex.split(part, comments=True)
        if not words:
            continue
        if words[0].endswith("=") or re.match(r"^[A-Z_]+=", words[0]):
            words = words[1:]  # an environment assignment before the command
        argv = _regtrack_argv(words)
        if argv is not None:
            try:
                build_parser().parse_args(argv)
            except SystemExit as exc:  # argparse exits: 0 after --help, 2 on a bad line
                if exc.code == 0 and ("--help" in argv or "-h" in argv):
                    continue
                pytest.fail(f"{where}: `{part}` is not a valid regtrack command line "
                            f"(argparse exit {exc.code})")
            continue
        prog = Path(words[0]).name
        assert prog in OTHER_PROGRAMS, f"{where}: unexpected program {prog!r} in `{part}`"
        if prog == "make":
            targets = [w for w in words[1:] if not w.startswith("-") and "=" not in w]
            missing = set(targets) - _makefile_targets()
            assert not missing, f"{where}: `{part}`: no Makefile target {sorted(missing)}"
        if prog == "python" and words[1:2] and words[1].endswith(".py"):
            assert (REPO / words[1]).is_file(), f"{where}: `{part}`: {words[1]} not found"


MENTIONS = _all_mentions()


def _subparsers():
    root = build_parser()
    return root, root._subparsers._group_actions[0].choices


@pytest.mark.parametrize("where, mention", MENTIONS, ids=[w for w, _ in MENTIONS])
def test_command_mentioned_in_text_exists(where, mention):
    """A ``regtrack VERB --option ...`` code span in the text names a real command and only
    options it has (a mention need not be a complete command line)."""
    words = shlex.split(mention)
    words = words[1:] if words[0] == "regtrack" else words[3:]
    root, verbs = _subparsers()
    global_opts = {o for a in root._actions for o in a.option_strings}
    rest = [w for w in words if w not in global_opts]
    if not rest:
        return
    verb = rest[0]
    assert verb in verbs, f"{where}: `{mention}`: no command {verb!r}"
    parser, args = verbs[verb], rest[1:]
    actions = parser._subparsers._group_actions[0].choices if parser._subparsers else {}
    if args and args[0] in actions:  # a verb with actions: `regtrack surrogate build ...`
        parser, verb, args = actions[args[0]], f"{verb} {args[0]}", args[1:]
    options = {o for a in parser._actions for o in a.option_strings}
    for w in args:
        if w.startswith("-"):
            opt = w.split("=", 1)[0]
            assert opt in options, f"{where}: `{mention}`: regtrack {verb} has no option {opt}"


def _links() -> list[tuple[str, str, Path]]:
    out = []
    for doc in DOCS:
        in_code = False
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            if FENCE.match(line.strip()):
                in_code = not in_code
                continue
            if in_code:
                continue
            for m in LINK.finditer(line):
                target = m.group(1)
                if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                    continue  # http(s), mailto, ... and links inside the page
                out.append((f"{doc.relative_to(REPO)}:{n}", target, doc.parent))
    return out


LINKS = _links()


@pytest.mark.parametrize("where, target, base", LINKS, ids=[f"{w}->{t}" for w, t, _ in LINKS])
def test_relative_link_resolves(where, target, base):
    path = (base / target.split("#", 1)[0]).resolve()
    assert path.exists(), f"{where}: link target {target} does not exist"
    assert REPO in path.parents or path == REPO, f"{where}: link {target} leaves the repository"


def test_readme_is_short():
    n = len((REPO / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= 200, f"README.md has {n} lines; keep it under 200 and move the rest to docs/"


def test_cli_reference_is_up_to_date():
    spec = importlib.util.spec_from_file_location("make_cli_docs",
                                                  REPO / "pipelines" / "make_cli_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    committed = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    assert committed == mod.format_cli_reference(), (
        "docs/cli.md is stale: run python pipelines/make_cli_docs.py")


@pytest.mark.parametrize("verb", [None, *sorted(build_parser()._subparsers._group_actions[0].choices)])
def test_help_runs(verb, capsys):
    argv = ["--help"] if verb is None else [verb, "--help"]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    assert "usage: regtrack" in capsys.readouterr().out


def test_validate_sample_case_as_shown(capsys, monkeypatch):
    """`regtrack validate sample_cases/phantom01`, as README.md shows it, exits 0."""
    shown = [c for _, c in COMMANDS if c.startswith("regtrack validate sample_cases/phantom01")]
    assert shown, "README.md no longer shows `regtrack validate sample_cases/phantom01`"
    monkeypatch.chdir(REPO)
    rc = main(shlex.split(shown[0], comments=True)[1:])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "phantom01" in out and "OK" in out
