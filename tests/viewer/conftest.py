"""Fixtures for the viewer tests (the tiny scene lives in viewer_fixtures.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from viewer_fixtures import ORIGIN, Tiny, build_tiny

from occufly.grid import SceneGrid


@pytest.fixture
def tiny(tmp_path: Path) -> Tiny:
    return build_tiny(tmp_path / "tiny")


@pytest.fixture
def tiny_grid(tiny: Tiny) -> SceneGrid:
    labels = np.zeros((5, 5, 5), np.uint8)
    labels[1:4, 1:4, 1:4] = 16  # a solid 3x3x3 building block: 26 surface voxels
    labels[0, 0, 0] = 11
    grid = SceneGrid(labels, ORIGIN + np.array([10.0, 20.0, 0.0]), 1.0)
    grid.save(tiny.ws / "grid" / "scene_grid.npz")
    return grid
