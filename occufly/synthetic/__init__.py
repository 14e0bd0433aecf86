"""Procedural aerial scene with exact ground truth (``occufly synth``).

:func:`generate` renders a deterministic synthetic survey (double grid at 50/40/30 m, nadir
and oblique views) and writes it as a COLMAP dense workspace plus ``truth/`` (class masks,
per-point labels, the scene voxel grid). See :mod:`occufly.synthetic.generate` for the layout.
"""

from occufly.synthetic.generate import generate
from occufly.synthetic.presets import PRESETS, Preset, get_preset

__all__ = ["PRESETS", "Preset", "generate", "get_preset"]
