"""``occufly synth OUT --preset tiny|small|bench --seed N [--format F]``: the synthetic aerial
scene (``--format``: written as COLMAP, OpenDroneMap, Metashape or Pix4D export it, through a
lens-distorted camera and in UTM 32N; :mod:`occufly.synthetic.formats`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from occufly.cli import command
from occufly.errors import InputFormatError
from occufly.progress import tqdm_progress
from occufly.synthetic import generate
from occufly.synthetic.formats import FORMATS
from occufly.synthetic.presets import PRESETS


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "synth", _synth,
                help="generate the synthetic aerial scene (COLMAP dense workspace + exact truth)")
    p.add_argument("out", type=Path, help="output folder (must not exist or be empty, unless --force)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="small",
                   help="scene size: tiny (tests, seconds), small (demo), bench (~5 M points), survey-half, "
                        "survey (the benchmark's scale: 2,100 frames, 20 at 20 MP, > 20 M points)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the world (default 0)")
    p.add_argument("--format", dest="formats", type=_formats,
                   help="write the scene as a photogrammetry tool exports it: colmap, odm, "
                        "metashape or pix4d (lens distortion, EPSG:32632); several comma-"
                        "separated or 'all' give OUT/<format>/ each; default: the plain "
                        "COLMAP workspace (pinhole camera)")
    p.add_argument("--force", action="store_true", help="replace a non-empty OUT")
    p.add_argument("--workers", type=int, default=1,
                   help="render frames in this many processes (same output; default 1)")


def _formats(text: str) -> list[str]:
    names = list(FORMATS) if text.strip() == "all" else [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in FORMATS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"{', '.join(bad) or text!r}: expected {'|'.join(FORMATS)} (comma-separated) or all")
    return names


def _synth(args: argparse.Namespace) -> dict:
    if not 1 <= args.workers <= 64:
        raise InputFormatError(f"--workers: expected 1..64 processes, got {args.workers}")
    # SIGTERM unwinds like Ctrl-C (occufly.cli.main): the temporary output folder is removed
    # and OUT is left as it was
    with tqdm_progress("synth") as bar:
        if args.formats:
            from occufly.synthetic.formats import generate_formats

            summary = generate_formats(args.out, args.formats, preset=args.preset,
                                       seed=args.seed, progress=bar, overwrite=args.force)
        else:
            summary = generate(args.out, preset=args.preset, seed=args.seed, progress=bar,
                               overwrite=args.force, workers=args.workers)
    if not args.json:  # readable: class names instead of four id lists
        from occufly.taxonomy import default_taxonomy

        tax = default_taxonomy()
        present = summary.pop("classes_present")
        summary["classes_present"] = ", ".join(tax[i].name for i in present["world"])
        summary["classes_missing_in_points"] = ", ".join(
            tax[i].name for i in present["world"] if i not in present["points"]) or "none"
    return summary
