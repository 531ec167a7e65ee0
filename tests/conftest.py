import builtins
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


@pytest.fixture
def opened_files(monkeypatch) -> list:
    """Every path passed to ``open`` or ``cv2.imread`` from now on in the test, in order."""
    import cv2

    opened = []
    real_open, real_imread = builtins.open, cv2.imread

    def spy(file, *a, **k):
        opened.append(str(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr(builtins, "open", spy)
    monkeypatch.setattr(cv2, "imread", lambda f, *a: (opened.append(str(f)), real_imread(f, *a))[1])
    return opened
