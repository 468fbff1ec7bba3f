"""The house rule on function length: no function in tg_gpudrive/ or kernels/ is longer than 80 lines,
except Warp kernels kept whole for speed, which say so in a comment line right above their decorator."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_LINES = 80
KERNEL_NOTE = "# one kernel on purpose"


def _is_warp_kernel(node: ast.FunctionDef) -> bool:
    return any(ast.unparse(d.func if isinstance(d, ast.Call) else d) == "wp.kernel" for d in node.decorator_list)


def long_functions(root: Path = ROOT, folders: tuple[str, ...] = ("tg_gpudrive", "kernels")) -> list[str]:
    """'path:line name (n lines)' for every function over MAX_LINES that is not a noted Warp kernel."""
    found = []
    for folder in folders:
        for path in sorted((root / folder).rglob("*.py")):
            src = path.read_text()
            lines = src.splitlines()
            for node in ast.walk(ast.parse(src)):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                n = node.end_lineno - node.lineno + 1
                if n <= MAX_LINES:
                    continue
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                noted = first >= 2 and lines[first - 2].strip().startswith(KERNEL_NOTE)
                if not (_is_warp_kernel(node) and noted):
                    found.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({n} lines)")
    return found


def test_no_function_over_80_lines():
    assert long_functions() == [], "split these into helpers (or, for a Warp kernel kept whole for speed, " \
                                   f"note it with '{KERNEL_NOTE}: ...' above it)"


def test_the_check_sees_long_functions_and_unnoted_kernels(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text(
        f"def short():\n    pass\n\n\ndef long():\n{body}\n\n\n"
        f"{KERNEL_NOTE}: splitting it would add launches\n@wp.kernel\ndef noted():\n{body}\n\n\n"
        f"@wp.kernel\ndef unnoted():\n{body}\n")
    assert long_functions(tmp_path, ("pkg",)) == [f"pkg/m.py:5 long ({MAX_LINES + 1} lines)",
                                                  f"pkg/m.py:{MAX_LINES * 2 + 14} unnoted ({MAX_LINES + 1} lines)"]
