"""Progress reporting shared by the CLI (tqdm bars on stderr) and web jobs (callbacks).

Long pipeline functions take ``progress: ProgressFn | None``; they call it with a fraction in
[0, 1] and a short message. :func:`tqdm_progress` adapts that to a terminal bar.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

ProgressFn = Callable[[float, str], None]
T = TypeVar("T")


def noop(_fraction: float, _message: str = "") -> None:
    return None


def track(
    items: Iterable[T], total: int, progress: ProgressFn | None, message: str,
    start: float = 0.0, end: float = 1.0,
) -> Iterator[T]:
    """Yield ``items`` while reporting progress from ``start`` to ``end`` of the whole job."""
    report = progress or noop
    every = max(1, total // 100)
    for i, item in enumerate(items):
        if i % every == 0:
            report(start + (end - start) * i / max(total, 1), message)
        yield item
    report(end, message)


class tqdm_progress:
    """A ProgressFn that draws one tqdm bar on stderr (only on a terminal unless forced)."""

    def __init__(self, desc: str = "", *, enable: bool | None = None) -> None:
        self.enable = sys.stderr.isatty() if enable is None else enable
        self.bar = tqdm(total=1000, desc=desc, disable=not self.enable, leave=False,
                        bar_format="{desc} {bar} {percentage:3.0f}% {elapsed}")
        self.last = 0

    def __call__(self, fraction: float, message: str = "") -> None:
        n = int(max(0.0, min(1.0, fraction)) * 1000)
        if message:
            self.bar.set_description_str(message, refresh=False)
        if n > self.last:
            self.bar.update(n - self.last)
            self.last = n

    def close(self) -> None:
        self.bar.close()

    def __enter__(self) -> tqdm_progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
