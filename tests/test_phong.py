"""Phong's rho_s is bounded by what physics bounds, its albedo (issue 13, item 2).

The lecture's lobe rho_s cos^e(alpha) reflects rho_s 2 pi / (e + 2) at normal
incidence, so energy conservation bounds rho_s by (e + 2) / (2 pi), not by 1:
rho_s = 4 at e = 300 has an albedo of 0.083. The lecture form's box reaches
``phong.RHO_MAX``; normalised, rho_s is the albedo and stays in [0, 1].
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from fitter import pipeline
from fitter.bsdf import phong
from fitter.config import load_config
from fitter.material import Material, MaterialError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_box_is_the_albedo_bound():
    lecture = Material.make(["phong"]).param_specs()["phong.rho_s"]
    assert lecture.upper >= (1e4 + 2.0) / (2.0 * math.pi)  # albedo 1 at the largest e
    Material.make(["phong"]).full_params({"phong.rho_s": 4.0, "phong.e": 300.0})
    normalized = Material.make(["phong"], {"phong.normalized": True})
    assert normalized.param_specs()["phong.rho_s"].upper == 1.0
    with pytest.raises(MaterialError, match="phong.rho_s"):
        normalized.full_params({"phong.rho_s": 4.0})


@pytest.mark.mitsuba
def test_bright_phong_case_recovered_within_3_percent():
    """The shipped ``bright_phong`` case (Mitsuba fitter_phong, 96^2) from the defaults."""
    job = load_config(os.path.join(ROOT, "configs", "bright_phong.toml"))
    job = job.replace(fit=job.fit.replace(validate=False))
    target, saturated = pipeline.read_target(job.fit.target, job.scene)
    res = pipeline.run_job(job, target, saturated).fit
    assert res.converged, res.message
    np.testing.assert_allclose(res.params["phong.rho_s"], 4.0, rtol=0.03)
    assert res.params["phong.e"] == pytest.approx(300.0, rel=0.03)
    assert not res.unidentifiable
    assert res.params["phong.rho_s"][0] * 2 * math.pi / (res.params["phong.e"] + 2) < 1.0
    assert phong.RHO_MAX >= 4.0
