import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
EXAMPLE_BOX2 = SHARED / "data" / "example_box2"


@pytest.fixture
def example_box2() -> Path:
    """The recording made outside the project (../shared); skipped where absent."""
    if not (EXAMPLE_BOX2 / "meta.yaml").is_file():
        pytest.skip("../shared/data/example_box2 is not present (a user's clone has none)")
    return EXAMPLE_BOX2
