"""Size presets of the synthetic scene."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from occufly.errors import OccuflyError


@dataclass(frozen=True)
class Preset:
    """Parameters of one synthetic scene size.

    core: side (m) of the square area that holds the objects and is flown over.
    margin: width (m) of plain terrain around the core (what oblique/edge views see).
    forward_overlap / side_overlap: image overlap of the flight grid at the 50 m reference
    altitude; the same line and station spacing is flown at every altitude.
    pixel_stride: every ``pixel_stride``-th pixel of every depth map is back-projected.
    fuse_voxel: edge (m) of the voxel hash that fuses back-projected samples to one point.
    vis_depth_check: add images whose depth map agrees with a fused point to its visibility
    (besides the images that contributed to it).
    min_views: a fused point needs samples from at least this many distinct images.
    """

    name: str
    core: float
    margin: float
    width: int
    height: int
    forward_overlap: float
    side_overlap: float
    pixel_stride: int
    fuse_voxel: float
    image_ext: str
    sparse_points: int
    terrain_cell: float = 1.0
    hfov_deg: float = 73.0
    altitudes: tuple[int, ...] = (50, 40, 30)
    depth_noise: float = 0.004
    grid_voxel: float = 0.5
    vis_depth_check: bool = True
    vis_tolerance: float = 0.01
    min_views: int = 3

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        name="tiny", core=40.0, margin=35.0, width=240, height=160,
        forward_overlap=0.55, side_overlap=0.45, pixel_stride=2, fuse_voxel=0.7,
        image_ext=".png", sparse_points=400,
    ),
    "small": Preset(
        name="small", core=80.0, margin=40.0, width=480, height=320,
        forward_overlap=0.75, side_overlap=0.70, pixel_stride=2, fuse_voxel=0.3,
        image_ext=".jpg", sparse_points=2000,
    ),
    "bench": Preset(
        name="bench", core=115.0, margin=50.0, width=600, height=400,
        forward_overlap=0.80, side_overlap=0.75, pixel_stride=2, fuse_voxel=0.14,
        image_ext=".jpg", sparse_points=5000, vis_depth_check=False,
    ),
}


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise OccuflyError(
            f"unknown synthetic preset {name!r}; expected one of {', '.join(PRESETS)}"
        ) from None
