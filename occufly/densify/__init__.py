"""Class-aware densification and scene voxelisation (instances, ground, other; issue 4).

Public API:

- :func:`densify` / :func:`voxelize_workspace` -- labelled cloud -> :class:`occufly.grid.SceneGrid`
- :class:`DensifyOptions` (ablation switches ``carve`` / ``poisson``, tolerances)
- :func:`dbscan` -- memory-bounded DBSCAN on occupied cells (exact with ``cell=0``)
- :func:`carve_instance` -- visual hull from α-shape silhouettes of 24 virtual cameras
- :func:`voxelize_ground` -- Poisson surface, scan conversion, majority ground class
- :func:`evaluate_grids` -- completion IoU, per-class IoU, mIoU vs a truth grid
- :func:`save_preview` -- top-down + oblique PNG
"""

from occufly.densify.carve import CarveParams, carve_instance, fibonacci_sphere
from occufly.densify.dbscan import dbscan, partition_agreement
from occufly.densify.evaluate import evaluate_grids
from occufly.densify.ground import PoissonParams, voxelize_ground
from occufly.densify.pipeline import DensifyOptions, DensifyResult, densify, voxelize_workspace
from occufly.densify.preview import render_preview, save_preview

__all__ = [
    "CarveParams",
    "DensifyOptions",
    "DensifyResult",
    "PoissonParams",
    "carve_instance",
    "dbscan",
    "densify",
    "evaluate_grids",
    "fibonacci_sphere",
    "partition_agreement",
    "render_preview",
    "save_preview",
    "voxelize_ground",
    "voxelize_workspace",
]
