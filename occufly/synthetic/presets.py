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
    full_frames / full_width / full_height: that many frames, spread evenly over the flight,
    are rendered at the full sensor size (the others at ``width`` x ``height``, the same
    sensor scaled down: same field of view); their depth maps are sampled every
    ``pixel_stride * full_width / width`` pixels so they add no denser sampling than the rest.
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
    full_frames: int = 0
    full_width: int = 0
    full_height: int = 0

    def __post_init__(self) -> None:
        if self.full_frames:
            scale = self.full_width / self.width
            if (self.full_width % self.width or self.full_height * self.width != self.height * self.full_width):
                raise ValueError(f"preset {self.name}: full size {self.full_width}x{self.full_height} must be an "
                                 f"integer multiple of {self.width}x{self.height}")
            if scale < 1:
                raise ValueError(f"preset {self.name}: full size smaller than the reduced size")

    @property
    def full_scale(self) -> int:
        """Full-size / reduced-size factor (1 when the preset has no full-size frames)."""
        return self.full_width // self.width if self.full_frames else 1

    def to_dict(self) -> dict:
        d = asdict(self)
        if not self.full_frames:  # presets without full-size frames keep their old meta.json
            for k in ("full_frames", "full_width", "full_height"):
                d.pop(k)
        return d


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
    # the OccuFly benchmark's scale: a DJI Phantom 4 Pro-like sensor (5472 x 3648 px, 8.8 mm
    # lens on a 13.2 mm wide sensor: fx = 3648 px, 73.74 deg horizontal FOV), most frames
    # rendered at 1/12 of that size (456 x 304, fx = 304 px), 20 at the full 20 MP
    "survey": Preset(
        name="survey", core=232.0, margin=50.0, width=456, height=304,
        forward_overlap=0.80, side_overlap=0.75, pixel_stride=1, fuse_voxel=0.11,
        image_ext=".jpg", sparse_points=20000, hfov_deg=73.7397952917,
        vis_depth_check=False, full_frames=20, full_width=5472, full_height=3648,
    ),
    # about half the survey's frames and points (the growth fit's middle size)
    "survey-half": Preset(
        name="survey-half", core=162.0, margin=50.0, width=456, height=304,
        forward_overlap=0.80, side_overlap=0.75, pixel_stride=1, fuse_voxel=0.11,
        image_ext=".jpg", sparse_points=10000, hfov_deg=73.7397952917,
        vis_depth_check=False, full_frames=10, full_width=5472, full_height=3648,
    ),
}


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise OccuflyError(
            f"unknown synthetic preset {name!r}; expected one of {', '.join(PRESETS)}"
        ) from None
