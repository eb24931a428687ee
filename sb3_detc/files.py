"""Writing files so that an interruption never leaves half of one."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["replace_atomically"]


def replace_atomically(path: Path, write: Callable[[Path], Any], scratch_name: str | None = None) -> None:
    """Write a file through a scratch file next to it, then put it in place at once.

    Readers never see half of it, and an interruption leaves the file as it was (a scratch
    file at most, which the next write replaces).

    :param path: the file
    :param write: writes the content to the path it is given
    :param scratch_name: the scratch file's name (default: the file's with the suffix ``.tmp``)
    """
    scratch = path.with_name(scratch_name) if scratch_name else path.with_suffix(".tmp")
    write(scratch)
    os.replace(scratch, path)
