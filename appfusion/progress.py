"""Progress bars for long work (tqdm on a terminal, quiet lines in logs)."""

from __future__ import annotations

import sys
from typing import Iterable, TypeVar

T = TypeVar("T")


def progress(it: Iterable[T], total: int | None = None, desc: str = "", enable: bool = True) -> Iterable[T]:
    """Wrap an iterable in a progress bar written to stderr.

    On a terminal the bar redraws in place; in a log (no TTY) it prints a line every ~10%.
    """
    if not enable:
        return it
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    return tqdm(it, total=total, desc=desc, file=sys.stderr, dynamic_ncols=True, leave=tty,
                mininterval=0.2 if tty else 10.0, disable=None if tty else False)
