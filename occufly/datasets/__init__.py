"""Readers of exported datasets (OccuFly layout and SSCBench-style layout).

:func:`open_dataset` needs only numpy and Pillow; :mod:`occufly.datasets.torch` adds a
``torch.utils.data.Dataset`` (optional extra ``occufly[torch]``).
"""

from occufly.datasets.reader import (
    FrameKey,
    OccuFlyReader,
    SSCBenchReader,
    detect_layout,
    open_dataset,
)

__all__ = ["FrameKey", "OccuFlyReader", "SSCBenchReader", "detect_layout", "open_dataset"]
