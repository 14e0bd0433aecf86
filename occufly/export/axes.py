"""The frame grid's axis convention as the manifest records it (``axes``): which grid axis is
image left-right, top-bottom and the optical axis, so that a training codebase's
augmentation can mirror the grid together with the image -- or refuse to.

The frame grid is camera-centric (x right, y down, z forward; :mod:`occufly.sampling`), so a
left-right image flip (pixel u -> W - 1 - u) mirrors grid axis 0 (voxel i -> X - 1 - i, the
grid is centred on the optical axis) and needs cx -> W - 1 - cx in the integer-pixel-centre
K of calib.txt; flipping axis 1 instead (KITTI's y is left, ours is down) turns the scene
upside down.
"""

from __future__ import annotations

FRAME_AXES = {
    "image_left_right": 0,
    "image_top_bottom": 1,
    "optical_axis": 2,
    "x": "right", "y": "down", "z": "forward",
    "flip_lr": "mirror grid axis 0 (i -> X-1-i) and set cx' = W-1-cx in calib.txt's K "
               "(integer pixel centres); image, depth and every label scale flip together",
}


def frame_axes() -> dict:
    return dict(FRAME_AXES)
