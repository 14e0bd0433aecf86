"""OccuFly Studio pipeline library: semantic voxel ground truth from camera-only drone surveys."""

__version__ = "0.1.0"
