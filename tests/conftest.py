"""Shared test fixtures: paths to the repository and to ../shared data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SPLATS = SHARED / "data" / "splats"

# keep every cache inside the workspace (Taichi, torch extensions, HF)
os.environ.setdefault("PHYSGS_CACHE_DIR", str(REPO / ".cache"))
os.environ.setdefault("XDG_CACHE_HOME", str(REPO / ".cache" / "xdg"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def splats_dir() -> Path:
    if not SPLATS.exists():
        pytest.skip(f"shared splat data not found at {SPLATS}")
    return SPLATS
