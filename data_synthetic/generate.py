"""Regenerate the synthetic Mitsuba targets: ``python data_synthetic/generate.py [case ...]``.

The cases are defined in ``fitter/cases.py``; see README.md here.
"""

import os
import sys

from fitter.mitsuba.synth import generate_all

if __name__ == "__main__":
    root = os.path.dirname(os.path.abspath(__file__))
    times = generate_all(root, sys.argv[1:] or None)
    print(f"{len(times)} cases, {sum(times.values()):.1f} s of rendering")
