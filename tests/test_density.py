"""occufly.density: the one place cloud density is estimated."""

from __future__ import annotations

import numpy as np
import pytest

from occufly import density


def _grid_plane(step: float, n: int = 300) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(n) * step, np.arange(n) * step), -1).reshape(-1, 2)
    return np.c_[g, np.zeros(len(g))].astype(np.float32)


def _random_plane(per_m2: float, side: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = int(per_m2 * side * side)
    return np.c_[rng.random((n, 2)) * side, np.zeros(n)].astype(np.float32)


@pytest.mark.parametrize("per_m2, side", [(25.0, 60.0), (100.0, 60.0)])  # 90 k / 360 k points
def test_spacing_and_density_of_a_random_plane(per_m2, side):
    plane = _random_plane(per_m2, side)
    # a planar Poisson process: median nearest-neighbour distance sqrt(ln 2 / (pi rho));
    # the 360 k cloud is measured on a 200 k subsample and rescaled
    assert density.point_spacing(plane) == pytest.approx(np.sqrt(np.log(2) / (np.pi * per_m2)), rel=0.05)
    assert density.surface_density(plane) == pytest.approx(per_m2, rel=0.1)


def test_knn_radius_of_a_lattice():
    plane = _grid_plane(0.2)
    # 4 neighbours at one step, 4 at sqrt(2) steps: the 8th is at 0.2 sqrt(2)
    assert density.knn_radius(plane, 8, quantile=0.5) == pytest.approx(0.2 * np.sqrt(2), rel=0.02)
    # 4 more at 2 steps: the 12th
    assert density.knn_radius(plane, 12, quantile=0.5) == pytest.approx(0.4, rel=0.02)


def test_degenerate_clouds():
    assert density.point_spacing(np.zeros((1, 3))) == 1.0
    assert density.surface_density(np.zeros((5, 3))) == 0.0
    few = np.array([[0, 0, 0], [2.0, 0, 0], [0, 1.0, 0]])
    assert density.knn_radius(few, 10) == pytest.approx(2.0)


def test_the_pipeline_uses_this_module_only():
    from occufly import render
    from occufly.densify import pipeline
    from occufly.lifting import knn

    assert render.estimate_point_spacing is density.point_spacing
    assert pipeline.surface_density is density.surface_density
    assert knn.typical_knn_radius is density.knn_radius
