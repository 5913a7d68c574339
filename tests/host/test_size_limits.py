"""Size limits of the host package (issue 61 item 6): no file in host/oibar over 600 lines and no
function over 80, so that each stays something one reader holds. Generated code
(host/oibar/_generated) is not ours to size.

A function's length runs from its ``def`` line to its last line, decorators excluded; a nested
function counts on its own and inside the function that holds it. A failure names every file and
function over its limit, so one run says all that needs splitting.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "host" / "oibar"
EXCLUDED = ("_generated",)  # folders under PACKAGE not checked
MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80


def package_files(package: Path = PACKAGE) -> list[Path]:
    return sorted(
        p for p in package.rglob("*.py") if not any(part in EXCLUDED for part in p.relative_to(package).parts)
    )


def oversize(path: Path, root: Path = ROOT) -> list[str]:
    """One line per limit ``path`` breaks: the file's length, then each long function's."""
    text = path.read_text(encoding="utf-8")
    rel = path.relative_to(root)
    found = []
    n_lines = len(text.splitlines())
    if n_lines > MAX_FILE_LINES:
        found.append(f"{rel}: {n_lines} lines (limit {MAX_FILE_LINES})")
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            assert node.end_lineno is not None
            length = node.end_lineno - node.lineno + 1
            if length > MAX_FUNCTION_LINES:
                found.append(
                    f"{rel}:{node.lineno}: function {node.name} is {length} lines (limit {MAX_FUNCTION_LINES})"
                )
    return found


def test_host_package_within_size_limits() -> None:
    files = package_files()
    assert len(files) > 50  # the walk did find the package
    problems = [line for path in files for line in oversize(path)]
    assert not problems, "over the size limits (split by responsibility):\n  " + "\n  ".join(problems)


def test_the_check_finds_long_files_and_functions(tmp_path: Path) -> None:
    """The checker itself: a long file and a long function (decorators not counted) are named,
    a function at the limit is not, and generated code is skipped."""
    pkg = tmp_path / "oibar"
    (pkg / "_generated").mkdir(parents=True)
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES - 2))
    at_limit = f"@staticmethod\n@staticmethod\ndef fits():\n{body}\n    return 0\n"
    over = f"def too_long():\n{body}\n    x = 1\n    return x\n"
    (pkg / "short.py").write_text(at_limit)
    (pkg / "long.py").write_text(over + "\n" * MAX_FILE_LINES)
    (pkg / "_generated" / "pb2.py").write_text("\n" * (2 * MAX_FILE_LINES))
    files = package_files(pkg)
    assert [p.name for p in files] == ["long.py", "short.py"]
    assert oversize(pkg / "short.py", tmp_path) == []
    assert oversize(pkg / "long.py", tmp_path) == [
        f"oibar/long.py: {MAX_FILE_LINES + MAX_FUNCTION_LINES + 1} lines (limit {MAX_FILE_LINES})",
        f"oibar/long.py:1: function too_long is {MAX_FUNCTION_LINES + 1} lines (limit {MAX_FUNCTION_LINES})",
    ]
