"""Splitting one scene's frames into train / val / test (``occufly export --split-by``), so
that a single-scene export trains and validates.

Rules (each frame gets one split, recorded as ``frames[<id>]["split"]`` in the manifest, and
the rule as ``split_by``):

``altitude``
    whole altitudes: the lowest altitude is ``test``, the next lowest ``val``, every higher
    one ``train`` (50 / 40 / 30 m -> train / val / test). Needs at least three altitudes.
    Splits are whole sequences (``<scene>_<altitude>``), so ``splits/*.txt`` are exact even
    for loaders that read only those.
``region``
    per altitude, the frames ordered by camera position along the axis on which the camera
    centres spread most, cut into contiguous strips of the given ratios (train first, then
    val, then test): val / test see ground the train frames see least of.
``ratio``
    per altitude, the frames in frame-id order, interleaved so that every prefix holds the
    ratios as closely as possible (0.8 / 0.1 / 0.1: 8 train, 1 val, 1 test in every ten).

``region`` and ``ratio`` put frames of one sequence into several splits; ``splits/*.txt`` list
a sequence in every split it has frames in and ``splits/<split>_frames.txt`` list
``<sequence> <frame id>`` lines; :func:`occufly.datasets.open_dataset` and the adapters in
:mod:`occufly.datasets.compat` filter by frame.
"""

from __future__ import annotations

import numpy as np

from occufly.export.common import ExportError

SPLITS = ("train", "val", "test")
RULES = ("altitude", "region", "ratio")
DEFAULT_RATIOS = (0.8, 0.1, 0.1)


def parse_ratios(text: str | None) -> tuple[float, float, float]:
    if text is None:
        return DEFAULT_RATIOS
    try:
        v = tuple(float(x) for x in str(text).split(","))
    except ValueError:
        raise ExportError(f"--split-ratios {text!r}: expected three numbers like 0.8,0.1,0.1") from None
    return check_ratios(v)


def check_ratios(v) -> tuple[float, float, float]:
    v = tuple(float(x) for x in v)
    if len(v) != 3 or min(v) <= 0 or not np.isfinite(v).all():
        raise ExportError(f"split ratios {list(v)}: expected three positive numbers "
                          "(train, val, test), e.g. 0.8,0.1,0.1")
    s = sum(v)
    return (v[0] / s, v[1] / s, v[2] / s)


def _interleave(n: int, ratios) -> list[str]:
    """n labels, every prefix as close to ``ratios`` as possible (largest remainder)."""
    counts = np.zeros(3)
    out = []
    r = np.asarray(ratios)
    for i in range(n):
        k = int(np.argmax(r * (i + 1) - counts))
        counts[k] += 1
        out.append(SPLITS[k])
    return out


def _strips(n: int, ratios) -> list[str]:
    """n labels in contiguous runs train, val, test of sizes ~ ratios (each >= 1 if n >= 3)."""
    if n < 3:
        return ["train"] * n
    nv = max(1, int(round(ratios[1] * n)))
    nt = max(1, int(round(ratios[2] * n)))
    ntr = max(1, n - nv - nt)
    nv = n - ntr - nt
    return ["train"] * ntr + ["val"] * nv + ["test"] * nt


def assign_splits(frames: dict[str, dict], rule: str, ratios=DEFAULT_RATIOS) -> dict[str, str]:
    """{frame id: split} for the manifest's ``frames`` records (``altitude``, ``pose``)."""
    if rule not in RULES:
        raise ExportError(f"--split-by {rule!r}: expected one of {', '.join(RULES)}")
    ratios = check_ratios(ratios)
    by_alt: dict[int, list[str]] = {}
    for fid in sorted(frames):
        by_alt.setdefault(int(frames[fid]["altitude"]), []).append(fid)
    out: dict[str, str] = {}
    if rule == "altitude":
        alts = sorted(by_alt)
        if len(alts) < 3:
            raise ExportError(
                f"--split-by altitude needs at least three altitudes (the lowest becomes test, the "
                f"next val, the rest train); this scene has {alts}. Use --split-by region or ratio")
        for a in alts:
            s = "test" if a == alts[0] else "val" if a == alts[1] else "train"
            for fid in by_alt[a]:
                out[fid] = s
        return out
    for _alt, fids in sorted(by_alt.items()):
        if rule == "ratio":
            labels = _interleave(len(fids), ratios) if len(fids) >= 3 else ["train"] * len(fids)
            if len(fids) >= 3:  # few frames: the last ones become the missing val / test
                for pos, s in ((-1, "test"), (-2, "val")):
                    if s not in labels:
                        labels[pos] = s
            out.update(zip(fids, labels, strict=True))
            continue
        centres = np.array([np.asarray(frames[f].get("pose", np.eye(4)), np.float64).reshape(4, 4)[:3, 3]
                            for f in fids])
        spread = centres[:, :2].max(0) - centres[:, :2].min(0) if len(fids) else np.zeros(2)
        axis = int(np.argmax(spread))
        order = np.lexsort((np.arange(len(fids)), centres[:, axis]))
        labels = _strips(len(fids), ratios)
        for rank, i in enumerate(order):
            out[fids[i]] = labels[rank]
    missing = [s for s in SPLITS if s not in out.values()]
    if missing:
        raise ExportError(
            f"--split-by {rule}: {len(frames)} frames give no {' / '.join(missing)} frame (each "
            "altitude needs at least three frames); export more frames or use --split")
    return out
