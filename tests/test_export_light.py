"""scene.xml is written without importing Mitsuba (a NumPy look_at; tags from a table)."""

import subprocess
import sys


def test_export_does_not_import_mitsuba(tmp_path):
    code = ("import sys\nfrom fitter.config import load_config\n"
            "from fitter.mitsuba.export import export_job\n"
            "job = load_config('configs/quickstart.toml')\n"
            f"export_job({str(tmp_path)!r}, job, job.init)\n"
            "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    text = (tmp_path / "scene.xml").read_text()
    assert '<sensor type="perspective"' in text and "<matrix value=" in text
