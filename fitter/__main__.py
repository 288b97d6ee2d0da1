"""``python -m fitter``: the same command line as the ``fitter`` console script."""

from .program import run

run()
