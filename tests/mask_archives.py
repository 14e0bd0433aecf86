"""Mask archives written by the formats' own writers (Datumaro's CVAT writer), for the import
tests of the library, the API and the admin page (issue 26)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np


def datumaro_cvat_archive(dest: Path, labels: list[str], image_names: list[str],
                          size: tuple[int, int]) -> Path:
    """A CVAT for images 1.1 zip written by Datumaro's own CVAT writer, as CVAT exports a
    task: per image a polygon of ``labels[0]`` (the top-left quarter and a bit, z 0) and an
    RLE mask of ``labels[1]`` on top of it (z 1). ``size`` = (height, width)."""
    import datumaro as dm
    from datumaro.components.annotation import AnnotationType, LabelCategories, Mask, Polygon
    from datumaro.components.media import Image

    h, w = size
    items = []
    for name in image_names:
        m = np.zeros((h, w), bool)
        m[h // 8: h * 3 // 8, w * 5 // 12: w * 10 // 12] = True
        items.append(dm.DatasetItem(
            id=Path(name).stem, subset="default", media=Image.from_file(path=name, size=(h, w)),
            annotations=[Polygon([0, 0, w // 2, 0, w // 2, h // 2, 0, h // 2], label=0,
                                 z_order=0),
                         Mask(image=m, label=1, z_order=1)]))
    ds = dm.Dataset.from_iterable(items, categories={
        AnnotationType.label: LabelCategories.from_iterable(labels)})
    out = dest.with_suffix("")
    ds.export(str(out), "cvat", save_media=False)
    with zipfile.ZipFile(dest, "w") as zf:
        for p in out.rglob("*"):
            if p.is_file():
                zf.write(p, p.relative_to(out).as_posix())
    return dest
