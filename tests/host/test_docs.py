"""The user-facing documents name only what exists (issue 60 item 7).

Each document is parsed: its code (inline spans and fenced blocks) and its relative links.
- a path under one of the repository's folders (``host/oibar/nav/pose/``, ``mk/rig.mk``) must
  exist; a file name with a known extension given alone or as a partial path (``sitl.py``,
  ``rig/mechanism.py``) must be the end of some file's path in the repository;
- ``make TARGET`` must be a target of the Makefile or mk/*.mk;
- ``oibar SUB... --flag`` must be a subcommand of the real parser (oibar.cli.build_parser) and
  every flag an option of that subcommand;
- any other ``--flag`` must be an option of some ``oibar`` subcommand or appear in the source of
  the tools (Python, C, shell, make files), unless it belongs to an outside tool's command (pip,
  git, apt-get...);
- a relative link must point at an existing file.
A finding names the document and line, so a stale name is easy to fix.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ["README.md", "docs/architecture.md", "docs/setup.md", "docs/hil.md", "docs/navigation.md"]
# first components of paths that must exist (build/, runs/, data/ are outputs: not checked)
REPO_DIRS = {
    "proto", "firmware", "host", "models", "hil", "bench", "tests", "docs", "scripts",
    "requirements", "mk", "deploy",
}  # fmt: skip
ROOT_FILES = {"Makefile", "platformio.ini", "pyproject.toml", "pytest.ini", "README.md"}
OUTPUT_DIRS = {"build", "runs", "data", ".venv", ".cache", "$OUT", "~"}
EXTENSIONS = (
    ".py", ".c", ".h", ".md", ".proto", ".options", ".toml", ".yaml", ".mk", ".sh", ".service",
    ".ini", ".lock", ".conf", ".onnx", ".txt",
)  # fmt: skip
# A name given alone is checked only for the kinds of file the repository owns (a bare
# `camera.yaml` or `model.onnx` in an example is the user's own file).
BARE_EXTENSIONS = (".py", ".c", ".h", ".md", ".mk", ".sh", ".proto", ".options", ".service")
# Commands of outside tools: their flags are theirs, not ours.
OUTSIDE_TOOLS = {
    "pip", "pip3", "apt-get", "apt", "apt-cache", "git", "pytest", "torchrun", "ruff", "mypy",
    "cmake", "systemctl", "systemd-analyze", "sudo", "curl", "docker", "uv", "nvidia-smi", "ls",
    "du", "cp", "install", "useradd", "journalctl", "python3", "python", "openocd", "st-flash",
    "dfu-util", "gdb", "arm-none-eabi-gdb", "qemu-system-arm", "tar", "rm", "cd", "export", "source",
    "dpkg", "lscpu", "free", "df", "wget", "chmod", "mkdir", "ln", "cat", "echo", "env", "time",
}  # fmt: skip
SKIP_DIRS = {".git", ".venv", ".cache", "build", "runs", "data", "node_modules", "__pycache__"}


@cache
def repo_files() -> tuple[str, ...]:
    out = []
    for dirpath, dirnames, filenames in os.walk(ROOT):
        dirnames[:] = [d for d in dirnames if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        rel = Path(dirpath).relative_to(ROOT)
        out.extend(str(rel / f) for f in filenames)
    return tuple(out)


@cache
def make_targets() -> frozenset[str]:
    targets = set()
    rule = re.compile(r"^([A-Za-z0-9_. %-]+?)\s*:(?!=)(.*)$")
    for mk in [ROOT / "Makefile", *sorted((ROOT / "mk").glob("*.mk"))]:
        for line in mk.read_text().splitlines():
            m = rule.match(line)
            # a target-specific variable (`demo: SETUP_PROFILE = demo`) defines no rule
            if not m or re.match(r"\s*[A-Za-z_]+\s*[:?+]?=", m.group(2)):
                continue
            targets.update(t for t in m.group(1).split() if "%" not in t)
    return frozenset(targets)


@cache
def oibar_parser() -> argparse.ArgumentParser:
    from oibar.cli import build_parser

    return build_parser()


def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


@cache
def oibar_flags() -> frozenset[str]:
    flags: set[str] = set()

    def walk(p: argparse.ArgumentParser) -> None:
        for a in p._actions:
            flags.update(a.option_strings)
        for child in _subparsers(p).values():
            walk(child)

    walk(oibar_parser())
    return frozenset(flags)


@cache
def source_text() -> str:
    """The tools' source (Python, C, shell, make, CMake), docs and tests excluded."""
    parts = []
    for rel in repo_files():
        if rel.startswith(("docs/", "tests/")) or not (
            rel.endswith((".py", ".c", ".h", ".sh", ".mk", ".cmake"))
            or Path(rel).name in ("Makefile", "CMakeLists.txt", "third_party.lock")
        ):
            continue
        try:
            parts.append((ROOT / rel).read_text(errors="replace"))
        except OSError:
            continue
    return "\n".join(parts)


@cache
def source_flags() -> frozenset[str]:
    """Every --flag written in the tools' source."""
    return frozenset(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", source_text()))


def code_snippets(text: str) -> list[tuple[int, str]]:
    """(line, code) for each fenced block line and each inline code span (joined if wrapped)."""
    out: list[tuple[int, str]] = []
    prose: list[str] = []
    in_block = False
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            in_block = not in_block
            prose.append("")
            continue
        if in_block:
            out.append((n, line))
            prose.append("")
        else:
            prose.append(line)
    joined = "\n".join(prose)
    for m in re.finditer(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", joined, re.S):
        line = joined.count("\n", 0, m.start()) + 1
        out.append((line, m.group(2).replace("\n", " ")))
    return out


def links(text: str) -> list[tuple[int, str]]:
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        for m in re.finditer(r"\]\(([^)\s]+)\)", line):
            out.append((n, m.group(1)))
    return out


def _segments(code: str) -> list[list[str]]:
    """Shell-ish segments of a snippet, each as tokens (comments and redirections dropped)."""
    code = re.sub(r"(^|\s)#.*$", "", code)
    out = []
    for seg in re.split(r"&&|\|\||[;|]", code):
        seg = re.split(r"\s[0-9]?>>?|\s<", seg)[0]
        try:
            tokens = shlex.split(seg)
        except ValueError:
            tokens = seg.split()
        if tokens:
            out.append(tokens)
    return out


def _placeholder(token: str) -> bool:
    return bool(re.search(r"[<>{}$*\[\]…]|\.\.\.", token)) or token.isupper()


def check_oibar(tokens: list[str]) -> list[str]:
    """``oibar ...`` against the real parser: subcommands and their options."""
    problems = []
    parser = oibar_parser()
    path = ["oibar"]
    skip = False
    for tok in tokens[1:]:
        if skip:
            skip = False
            continue
        if tok.startswith("-") and tok != "-":
            name = tok.split("=", 1)[0]
            if _placeholder(name):
                continue
            action = parser._option_string_actions.get(name)
            if action is None:
                problems.append(f"`{' '.join(path)}` has no option {name}")
                continue
            skip = "=" not in tok and action.nargs != 0 and action.nargs not in ("*", "+", "?")
            continue
        subs = _subparsers(parser)
        if subs and len(path) >= 1 and not _placeholder(tok):
            if tok in subs:
                parser = subs[tok]
                path.append(tok)
                continue
            if parser is oibar_parser() or any(
                isinstance(a, argparse._SubParsersAction) and a.required for a in parser._actions
            ):
                problems.append(f"`{' '.join(path)}` has no subcommand {tok!r}")
                break
    return problems


def check_path(token: str) -> str | None:
    token = token.strip(".,;:()'\"").removeprefix("./")
    token = re.sub(r"(\.\w+):[\w.-]+$", r"\1", token)  # file:line, scenes.json:scene
    if not token or _placeholder(token) or "://" in token or token.startswith(("-", "/")):
        return None
    first = token.split("/", 1)[0]
    if first in OUTPUT_DIRS:
        return None
    if "/" in token and first in REPO_DIRS:
        return None if (ROOT / token).exists() else f"no such path: {token}"
    if token in ROOT_FILES:
        return None if (ROOT / token).exists() else f"no such file: {token}"
    name = token.rstrip("/")
    if re.fullmatch(r"[\w./-]+", name) and name.endswith(BARE_EXTENSIONS) and not name.startswith("."):
        if any(f == name or f.endswith("/" + name) for f in repo_files()):
            return None
        # a file some tool writes or reads (cycles.jsonl, report.html, the nanopb generator)
        if re.search(r"(?<![\w.-])" + re.escape(name.split("/")[-1]) + r"(?![\w-])", source_text()):
            return None
        return f"no file named {name} in the repository or its tools' source"
    return None


PACKAGES = {"oibar": "host", "oibar_hil": "hil", "oibar_models": "models", "oibar_bench": "bench"}


def check_module(token: str) -> str | None:
    """``oibar.nav.pose`` or ``oibar.nav.daemon.NavDaemon``: the module exists, and a name after
    it (a class, a function, a constant) is defined or imported in that module."""
    token = token.strip(".,;:()'\"").removesuffix("()")
    parts = token.split(".")
    if parts[0] not in PACKAGES or not all(p.isidentifier() for p in parts):
        return None
    base = ROOT / PACKAGES[parts[0]]
    module_file = None
    i = len(parts)
    while i > 0:
        stem = base.joinpath(*parts[:i])
        for candidate in (stem.with_suffix(".py"), stem / "__init__.py", stem.with_suffix(".proto")):
            if candidate.is_file():
                module_file = candidate
                break
        if module_file is not None:
            break
        i -= 1
    if module_file is None:
        return f"no module {token}"
    rest = parts[i:]
    if not rest:
        return None
    if i == 1:
        return None  # `oibar.train_range_m`: a key of the model's metadata, not a module
    text = module_file.read_text(errors="replace")
    if not re.search(r"(?<![\w.])" + re.escape(rest[0]) + r"\b", text):
        if module_file.name == "__init__.py":
            return f"no module {'.'.join(parts[: i + 1])}"
        return f"{'.'.join(parts[:i])} defines no {rest[0]} ({token})"
    return None


def check_doc(rel: str) -> list[str]:
    return check_text((ROOT / rel).read_text(), rel, (ROOT / rel).parent)


def check_text(text: str, rel: str, base: Path) -> list[str]:
    """Every finding in one document's ``text`` (``base``: its folder, for relative links)."""
    problems: list[str] = []
    for n, code in code_snippets(text):
        for tokens in _segments(code):
            # leading VAR=value assignments (env or make variables) are skipped
            while tokens and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", tokens[0]):
                tokens = tokens[1:]
            if not tokens:
                continue
            head = Path(tokens[0]).name
            found: list[str] = []
            if head == "oibar":
                found += check_oibar(tokens)
            elif head == "make":
                for tok in tokens[1:]:
                    if tok.startswith("-") or "=" in tok or _placeholder(tok):
                        continue
                    if not re.fullmatch(r"[a-z0-9][a-z0-9_.-]*", tok):
                        break  # prose after the command
                    if tok not in make_targets():
                        found.append(f"no make target {tok!r}")
            if head != "oibar" and head not in OUTSIDE_TOOLS or head in ("python", "python3"):
                ours = head not in OUTSIDE_TOOLS or (
                    len(tokens) > 2 and tokens[1] == "-m" and tokens[2].startswith("oibar")
                )
                for tok in tokens:
                    for flag in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", tok):
                        if ours and flag not in oibar_flags() and flag not in source_flags():
                            found.append(f"option {flag} exists in no oibar command and no tool's source")
            for tok in tokens:
                why = None
                if "/" in tok or tok.endswith(EXTENSIONS) or tok in ROOT_FILES:
                    why = check_path(tok)
                elif tok.startswith(tuple(PACKAGES)):
                    why = check_module(tok)
                if why:
                    found.append(why)
            problems += [f"{rel}:{n}: {p}" for p in found]
    for n, target in links(text):
        if target.startswith(("http://", "https://", "mailto:", "#")):
            continue
        path = (base / target.split("#", 1)[0]).resolve()
        if not path.exists():
            problems.append(f"{rel}:{n}: broken link {target}")
    return sorted(set(problems))


# -- the checker checks itself: each rule catches what it should --------------------------------


def test_the_checker_finds_stale_names() -> None:
    assert check_oibar(shlex.split("oibar nav --camera 0 --port none --rate-hz 5")) == []
    assert check_oibar(["oibar", "nav", "--no-such-flag"]) == ["`oibar nav` has no option --no-such-flag"]
    assert check_oibar(["oibar", "navigate"]) == ["`oibar` has no subcommand 'navigate'"]
    assert check_oibar(["oibar", "calib", "estimate", "--pattern", "p.json"]) == []
    assert "sim-mcu" in make_targets() and "test" in make_targets()
    assert check_path("host/oibar/nav/pose/") is None
    assert check_path("host/oibar/nav/frames_gone.py") is not None
    assert check_path("rig/mechanism.py") is None
    assert check_path("no_such_module.py") is not None
    assert check_path("build/anything/at/all.txt") is None
    assert "--lockstep-fd" in source_flags()
    assert check_module("oibar.nav.daemon.NavDaemon") is None and check_module("oibar_hil.rig") is None
    assert check_module("oibar.nav.gone") == "no module oibar.nav.gone"
    assert check_module("oibar.nav.daemon.NoSuchThing") is not None
    text = (
        "run `make demo no-such-target` then\n`oibar link --port loop://\n--bogus`, see\n"
        "[x](no/such.md) and `hil/oibar_hil/gone.py`; `python -m oibar_hil.rig --no-such-option`\n"
    )
    assert check_text(text, "x.md", ROOT / "docs") == [
        "x.md:1: no make target 'no-such-target'",
        "x.md:2: `oibar link` has no option --bogus",
        "x.md:4: broken link no/such.md",
        "x.md:4: no such path: hil/oibar_hil/gone.py",
        "x.md:4: option --no-such-option exists in no oibar command and no tool's source",
    ]
    assert code_snippets("a `x\ny` b\n```\nmake demo\n```\n") == [(4, "make demo"), (1, "x y")]


# Findings in a document another change owns, reported to its author; listed without line
# numbers so edits elsewhere in it do not move them. Each must still be found (fixing one
# fails the test until it is removed here), and nothing else may be.
KNOWN_STALE: dict[str, set[str]] = {}


@pytest.mark.parametrize("rel", DOCS)
def test_doc_names_only_what_exists(rel: str) -> None:
    problems = check_doc(rel)
    known = KNOWN_STALE.get(rel, set())
    new = [p for p in problems if p.split(": ", 1)[1] not in known]
    assert not new, "stale names:\n" + "\n".join(new)
    fixed = known - {p.split(": ", 1)[1] for p in problems}
    assert not fixed, f"fixed in {rel}, remove from KNOWN_STALE: {sorted(fixed)}"
