"""MJX, imported without the two lines it prints when its optional warp backend is absent.

``mujoco.mjx`` tries to import NVIDIA warp at import time and, when warp is not installed,
prints ``Failed to import warp: No module named 'warp'`` and the same for ``mujoco_warp``
(with ``print``, on stdout: no logger or warning to filter). Those two lines, in exactly that
case, are dropped; anything else MJX prints while importing (a warp that is installed but
broken, say) is passed on unchanged, and an error in the import itself is raised as usual.
"""

from __future__ import annotations

import contextlib
import io
import sys

__all__ = ["mjx"]

_ABSENT = (
    "Failed to import warp: No module named ",
    "Failed to import mujoco_warp: No module named ",
)

_printed = io.StringIO()
try:
    with contextlib.redirect_stdout(_printed):
        from mujoco import mjx
finally:
    for _line in _printed.getvalue().splitlines(keepends=True):
        if not _line.startswith(_ABSENT):
            sys.stdout.write(_line)
