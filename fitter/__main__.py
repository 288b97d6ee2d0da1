"""``python -m fitter``: the same command line as the ``fitter`` console script."""

from .cli import run

run()
