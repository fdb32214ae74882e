"""The tree's shape, checked: service wiring imports what it runs by name, with no importlib and no import guards."""

from __future__ import annotations

import re
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the optional imports: the C extensions built at install when a compiler is present, each with a fallback that
#: computes the same result (A*'s pure-Python loop; scipy.ndimage for the grid distance transform and labelling;
#: NumPy for the DWA rollout, the obstacle layer's ray clearing and the refinement's scan likelihood)
OPTIONAL_IMPORTS = {"services/nav/astar.py", "services/common/gridops.py", "services/nav/dwa.py",
                    "services/nav/costmap.py", "services/localization/refine.py"}


def python_files(*folders: str) -> list[tuple[str, str]]:
    return [(p.relative_to(REPO_ROOT).as_posix(), p.read_text(encoding="utf-8"))
            for folder in folders for p in sorted((REPO_ROOT / folder).rglob("*.py"))]


def test_no_importlib_in_service_wiring() -> None:
    """Entry points, commands and benches are imported explicitly (a typo fails at import, not silently)."""
    found = [f"{rel}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)}"
             for rel, text in python_files("services", "proto", "tools")
             for m in re.finditer(r"\bimportlib\b(?!\.resources| import resources)|\b__import__\(|find_spec\(", text)]
    assert not found, "import what you run explicitly:\n" + "\n".join(found)


def test_no_optional_import_guards() -> None:
    found = [f"{rel}:{text.count(chr(10), 0, m.start()) + 1}"
             for rel, text in python_files("services", "proto", "tools") if rel not in OPTIONAL_IMPORTS
             for m in re.finditer(r"except (ImportError|ModuleNotFoundError)", text)]
    assert not found, "a missing module must fail loudly, not turn a feature off:\n" + "\n".join(found)
