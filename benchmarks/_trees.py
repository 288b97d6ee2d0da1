"""The source trees a before/after benchmark compares: this checkout and, with
``--before REF``, that commit extracted by ``git archive`` to a temporary folder."""

from __future__ import annotations

import os
import subprocess
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def trees(before: str | None, prefix: str = "fitter-before-") -> list[tuple[str, str]]:
    """[(name, folder)]: ("before (REF)", extracted) first if ``before``, then ("after", ROOT)."""
    out = [("after", ROOT)]
    if before:
        tmp = tempfile.mkdtemp(prefix=prefix)
        archive = subprocess.run(["git", "-C", ROOT, "archive", before], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        out.insert(0, (f"before ({before})", tmp))
    return out
