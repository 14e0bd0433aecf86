"""Dataset export: OccuFly layout (FORMATS.md section 3) and SSCBench-style layout (section 4).

The entry point is :func:`export_dataset`; the layouts live in :mod:`occufly.export.occufly`
and :mod:`occufly.export.sscbench`.
"""

from occufly.export.common import ExportError
from occufly.export.dataset import LAYOUTS, ExportOptions, export_dataset, export_frame_task

__all__ = ["LAYOUTS", "ExportError", "ExportOptions", "export_dataset", "export_frame_task"]
