import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def config():
    """A shipped training config by task name."""
    return lambda task: str(ROOT / "configs" / "train" / f"{task}.toml")


@pytest.fixture(autouse=True)
def _run_from_root(monkeypatch):
    # The configs name their world files relative to themselves; nothing depends on the cwd,
    # but torchrun children inherit it, so keep it predictable.
    monkeypatch.chdir(ROOT)
    monkeypatch.setenv("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "1"))
