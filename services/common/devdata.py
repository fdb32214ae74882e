"""Where the development data lives: third-party maps, laser logs and the reference harness used by benches.

``$ZAGV_SHARED`` when set, else a folder named ``shared`` next to the repository. Benches that need it say so and
leave their rows out where it is absent (a user's checkout has none).
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]


def shared_dir() -> Path:
    """The development data folder (it may not exist)."""
    return Path(os.environ.get("ZAGV_SHARED", REPO_ROOT.parent / "shared"))
