"""The ``occufly`` command line.

Each command group registers its sub-commands from its own module of this package
(``occufly/cli/<group>.py`` with a ``register(subparsers)`` function listed in
:data:`COMMAND_MODULES`). Packages built on the library add their own groups through the
``occufly.commands`` entry point (the web app's ``serve``, ``db``, ``users``, ``demo``,
``backup`` parse in ``app/cli.py``): the library never imports them by name. A command handler takes
the parsed ``argparse.Namespace`` and returns either an exit code or a dict; a dict is printed
as JSON with ``--json`` and as a readable summary otherwise.

Errors a user can cause (:class:`occufly.errors.OccuflyError`) print one line and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
import threading
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

import numpy as np

from occufly.errors import OccuflyError

COMMAND_MODULES: list[str] = [
    "occufly.cli.core",
    "occufly.cli.voxelize",
    "occufly.cli.lift",
    "occufly.cli.export",
    "occufly.cli.synth",
    "occufly.cli.masks",
]
#: entry-point group through which other packages (the web app) add command groups
ENTRY_POINT_GROUP = "occufly.commands"


def add_json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def command(
    sub: argparse._SubParsersAction, name: str, handler: Callable[[argparse.Namespace], Any], **kw
) -> argparse.ArgumentParser:
    """Add a sub-command whose result is printed by :func:`emit`; it gets ``--json``."""
    p = sub.add_parser(name, **kw)
    add_json_flag(p)
    p.set_defaults(handler=handler)
    return p


def _human(obj: Any, indent: int = 0) -> str:
    pad = "  " * indent
    if isinstance(obj, dict):
        lines = []
        for k, v in obj.items():
            if isinstance(v, (dict, list)) and v and not _is_flat_list(v):
                lines.append(f"{pad}{k}:")
                lines.append(_human(v, indent + 1))
            else:
                lines.append(f"{pad}{k}: {_scalar(v)}")
        return "\n".join(lines)
    if isinstance(obj, list):
        return "\n".join(f"{pad}- {_scalar(v) if not isinstance(v, dict) else ''}" + (
            "\n" + _human(v, indent + 1) if isinstance(v, dict) else "") for v in obj)
    return pad + _scalar(obj)


def _is_flat_list(v: Any) -> bool:
    return isinstance(v, list) and len(v) <= 8 and all(not isinstance(x, (dict, list)) for x in v)


def _scalar(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_scalar(x) for x in v) + "]"
    return str(v)


def emit(result: Any, as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, default=_json_default))
    elif isinstance(result, str):
        print(result)
    else:
        print(_human(result))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="occufly",
        description="OccuFly Studio: semantic voxel ground truth from camera-only drone surveys.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log more detail")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(sub)
    for ep in _plugin_entry_points():
        ep.load().register(sub)
    return parser


def _plugin_entry_points() -> list:
    return sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: ep.name)


def _interrupt(_signum, _frame) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    # SIGTERM (a job runner, `kill`, a container stopping) unwinds like Ctrl-C, so every
    # command's temporary output is removed and its target left as it was
    main_thread = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        result = args.handler(args)
    except OccuflyError as e:
        print(f"occufly {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"occufly {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, old_term)
    if isinstance(result, int):
        return result
    if result is not None:
        emit(result, getattr(args, "json", False))
    return 0
