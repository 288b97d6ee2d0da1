"""Mitsuba's named metals as a conductor's eta / k (issue 13).

Reference: Mitsuba itself -- ``roughconductor`` with ``material = name``,
its ``eta.value`` / ``k.value`` read through ``mi.traverse`` -- for every
material name Mitsuba ships data for. (The renderer against Mitsuba's
``roughconductor`` for given numbers is ``tests/test_conductor.py``'s.)
"""

from __future__ import annotations

import numpy as np
import pytest

import fitter
from fitter.bsdf.metals import METALS
from fitter.config import ConfigError, job_from_dict
from fitter.material import Material, MaterialError

CONDUCTOR = {"torrance_sparrow.fresnel": "conductor", "torrance_sparrow.geometry": "smith"}
METAL = Material.make(["torrance_sparrow"], CONDUCTOR)


@pytest.mark.mitsuba
def test_the_table_is_mitsubas_for_every_name_it_ships():
    from fitter.bsdf.metals import from_mitsuba, mitsuba_names
    from fitter.mitsuba.variant import load

    mi, _ = load(None)
    names = mitsuba_names(mi)
    assert {"Au", "Ag", "Al", "Cu", "Cr"} <= set(names)
    assert list(METALS) == names
    for name in names:
        eta, k = from_mitsuba(mi, name)
        assert METALS[name] == (eta, k), name  # float32 values, exactly


def test_a_name_stands_for_its_numbers_in_the_api_and_a_config():
    by_name = METAL.full_params({"torrance_sparrow.eta": "Au", "torrance_sparrow.k": "Au"})
    np.testing.assert_array_equal(by_name["torrance_sparrow.eta"], METALS["Au"][0])
    np.testing.assert_array_equal(by_name["torrance_sparrow.k"], METALS["Au"][1])
    data = {"scene": {"width": 16, "height": 16},
            "material": {"lobes": ["torrance_sparrow"],
                         "fixed": {**CONDUCTOR, "torrance_sparrow.k": "Cu"},
                         "init": {"torrance_sparrow.eta": "Cu"}, "truth": {
                             "torrance_sparrow.eta": "Cu", "torrance_sparrow.k": "Cu"}}}
    job = job_from_dict(data)
    assert job.init["torrance_sparrow.eta"] == METALS["Cu"][0]
    assert job.fixed["torrance_sparrow.k"] == METALS["Cu"][1]
    assert job.truth["torrance_sparrow.k"] == METALS["Cu"][1]
    scene = fitter.Scene(width=16, height=16, supersampling=1,
                         lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),))
    named = fitter.render({"torrance_sparrow.eta": "Au", "torrance_sparrow.k": "Au",
                           **CONDUCTOR}, scene)
    numbers = fitter.render({"torrance_sparrow.eta": METALS["Au"][0],
                             "torrance_sparrow.k": METALS["Au"][1], **CONDUCTOR}, scene)
    np.testing.assert_array_equal(np.asarray(named), np.asarray(numbers))


def test_unknown_or_unusable_names_are_refused_naming_the_key():
    with pytest.raises(MaterialError, match="torrance_sparrow.eta = 'Gold' is not a known "
                                            "name; known: Ag, Al"):
        METAL.full_params({"torrance_sparrow.eta": "Gold"})
    # a dielectric in Mitsuba's list: k = 0 is not a conductor's
    with pytest.raises(MaterialError, match=r"torrance_sparrow.k = 'CsI' \(\[0.0, 0.0, 0.0\]\) "
                                            r"is outside its valid range"):
        METAL.full_params({"torrance_sparrow.k": "CsI"})
    data = {"scene": {}, "material": {"lobes": ["torrance_sparrow"],
                                      "init": {"torrance_sparrow.eta": "Au"}}}
    with pytest.raises(ConfigError, match=r"material\.init\.torrance_sparrow\.eta = 'Au': a name "
                                          r"is allowed only with torrance_sparrow\.fresnel = "
                                          r"'conductor'"):
        job_from_dict(data)


def test_fits_take_names_in_init_and_fixed():
    """A named metal as a conductor fit's start or fixed values."""
    scene = fitter.Scene(width=32, height=32, supersampling=2,
                         lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
                                 fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0))))
    truth = {"torrance_sparrow.eta": "Au", "torrance_sparrow.k": "Au", "torrance_sparrow.m": 0.25}
    target = np.asarray(fitter.render(truth, scene, METAL))
    from fitter.fit._setup import Problem

    started = Problem.make(target[None], scene, METAL, init={"torrance_sparrow.eta": "Ag"})
    np.testing.assert_array_equal(started.init_full["torrance_sparrow.eta"], METALS["Ag"][0])
    res = fitter.fit(target, scene, METAL, init={"torrance_sparrow.m": 0.4},
                     fixed={"torrance_sparrow.eta": "Au", "torrance_sparrow.k": "Au"})
    assert res.converged, res.message
    assert abs(res.params["torrance_sparrow.m"] / 0.25 - 1) < 1e-6
    np.testing.assert_array_equal(res.params["torrance_sparrow.eta"], METALS["Au"][0])
