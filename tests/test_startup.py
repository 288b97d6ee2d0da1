"""Start-up: help, usage and config errors answer without importing JAX or Mitsuba.

Time is not asserted (benchmarks measure it); what is asserted is the cause of
a slow start: which heavy modules a command loaded before answering.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

HEAVY = ("jax", "mitsuba", "drjit", "OpenImageIO", "optimistix", "matplotlib")

BAD_CONFIG = """
[scene]
width = 0
height = 32
[material]
lobes = ["lambert", "torrance_sparrow"]
"""


def _modules_after(argv, tmp_path):
    code = ("import sys\nfrom fitter.cli import main\n"
            f"rc = main({argv!r})\n"
            "print(rc)\nprint(' '.join(sorted(sys.modules)))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    rc, modules = proc.stdout.splitlines()[-2:]
    return int(rc), set(modules.split()), proc.stderr


@pytest.mark.parametrize("argv,rc", [
    (["--help"], 0),
    (["--version"], 0),
    (["fit"], 2),
    (["fit", "absent.toml"], 2),
    (["fit", "bad.toml"], 2),
])
def test_help_usage_and_config_errors_do_not_import_heavy_modules(tmp_path, argv, rc):
    (tmp_path / "bad.toml").write_text(BAD_CONFIG)
    code, modules, err = _modules_after(argv, tmp_path)
    assert code == rc, err
    loaded = [m for m in HEAVY if m in modules]
    assert not loaded, (argv, loaded)
    if argv[-1] == "bad.toml":
        assert "scene.width" in err


def test_documented_submodules_are_attributes_of_the_package_on_first_use(tmp_path):
    """``fitter.mitsuba.render``, ``fitter.metrics.compare``, ``fitter.batch.run_batch``
    (as the README writes them) after a bare ``import fitter``: AttributeError before;
    ``import fitter`` alone still loads none of the heavy modules."""
    code = ("import sys, fitter\n"
            "heavy = [m for m in %r if m in sys.modules]\n"
            "print(fitter.mitsuba.render.__module__, fitter.metrics.compare.__name__,\n"
            "      fitter.batch.run_batch.__name__, fitter.config.load_config.__name__,\n"
            "      fitter.imageio.read_image.__name__, heavy)\n"
            "try:\n    fitter.no_such_module\nexcept AttributeError as e:\n    print(e)\n"
            % (HEAVY,))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.splitlines()
    assert first == "fitter.mitsuba compare run_batch load_config read_image []", first
    assert second == "module 'fitter' has no attribute 'no_such_module'"
