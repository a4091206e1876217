"""The size rules of the project's packages (docs/architecture.md, "How the code is kept"):
no module over MAX_MODULE_LINES lines and no function over MAX_FUNCTION_LINES lines.

    python tools/house_rules.py        # lists every breach; exit 1 if there is one

CI runs it (``.ci/run``).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("planner", "mavlink_wire", "sim_gateway", "mavlink_bridge", "mission_view", "swarmplan")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80


def breaches(path: Path) -> list[str]:
    """The size rules ``path`` breaks, one line each."""
    text = path.read_text()
    name = path.relative_to(ROOT)
    found = []
    lines = len(text.splitlines())
    if lines > MAX_MODULE_LINES:
        found.append(f"{name}: {lines} lines (at most {MAX_MODULE_LINES})")
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            length = node.end_lineno - node.lineno + 1
            if length > MAX_FUNCTION_LINES:
                found.append(
                    f"{name}:{node.lineno}: {node.name} is {length} lines "
                    f"(at most {MAX_FUNCTION_LINES})"
                )
    return found


def main() -> int:
    found = [
        line
        for package in PACKAGES
        if (ROOT / package).is_dir()
        for path in sorted((ROOT / package).rglob("*.py"))
        for line in breaches(path)
    ]
    print("\n".join(found) if found else "house rules kept: modules and functions within size")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
