"""The source trees a before/after benchmark compares: this checkout and, with
``--before REF``, that commit extracted by ``git archive`` to a temporary folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def trees(before: str | None, prefix: str = "fitter-before-") -> list[tuple[str, str]]:
    """[(name, folder)]: ("before (REF)", extracted) first if ``before``, then ("after", ROOT),
    each package's bytecode written (``compileall``: with ``PYTHONDONTWRITEBYTECODE`` set,
    as on the benchmark machine, an extracted tree compiled its ~15 k lines in every run
    and a checkout its edited modules)."""
    out = [("after", ROOT)]
    if before:
        tmp = tempfile.mkdtemp(prefix=prefix)
        archive = subprocess.run(["git", "-C", ROOT, "archive", before], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        out.insert(0, (f"before ({before})", tmp))
    for _, folder in out:  # bytecode written once: no tree compiles its sources in a timed run
        subprocess.run([sys.executable, "-m", "compileall", "-q", os.path.join(folder, "fitter")],
                       check=True, capture_output=True)
    return out


def interleaved(trees, cases, repeat: int, run) -> dict:
    """{(tree name, case): [record]}: ``run(folder, case, round)`` for every round,
    case and tree in turn (so both trees see the same load), each record printed
    to stderr as it comes (without its "params" and "stderr")."""
    records: dict = {}
    for rnd in range(repeat):
        for case in cases:
            for name, tree in trees:
                r = run(tree, case, rnd)
                records.setdefault((name, case), []).append(r)
                brief = {k: v for k, v in r.items() if k not in ("params", "stderr")}
                print(f"# {name:>20} {case:>24}: {json.dumps(brief)}", file=sys.stderr,
                      flush=True)
    return records


def succeeded(records: dict, name: str, case: str) -> list:
    """The records of (tree ``name``, ``case``) that did not fail; when none did
    not, the table row saying so is printed."""
    rs = [r for r in records[(name, case)] if "failed" not in r]
    if not rs:
        print(f"| {case} | {name} | failed: {records[(name, case)][0]} |")
    return rs
