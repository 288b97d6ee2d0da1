"""The shipped synthetic cases (``data_synthetic/<name>/``) as plain data.

Each entry of ``CASES`` is a dict in the TOML config layout
(``fitter.serialize``: ``scene``, ``material`` with ``lobes``, ``truth`` and
``fixed`` -- lobe options go in ``fixed`` --, ``synth``), so
``fitter.config.job_from_dict(CASES[name], base_dir=<case folder>)`` builds
the job and a ``configs/<name>.toml`` can be written from it. Relative paths
(the envmap) are relative to the case folder. ``NOTES`` says what each case
is for. ``fitter.mitsuba.synth.generate_all(root)`` renders them all.

The ``env_*`` cases light opaque lobes by the HDR probe ``PROBE`` (sun, sky,
ground, window; ``fitter.mitsuba.synth.make_probe``), rendered by Mitsuba's
``path`` integrator (MIS, max_depth 2) at ``SPP_ENV`` samples per pixel.
"""

from __future__ import annotations

import copy

#: Default frame: 128 x 128, 4 x 4 supersampling, the quickstart camera.
_CAMERA = {"type": "perspective", "origin": [0.0, 0.0, 4.0], "target": [0.0, 0.0, 0.0],
           "up": [0.0, 1.0, 0.0], "fov": 35.0}
_TWO_LIGHTS = [
    {"type": "point", "position": [3.0, 4.0, 5.0], "intensity": [50.0, 50.0, 50.0]},
    {"type": "point", "position": [-4.0, 1.0, 3.0], "intensity": [20.0, 20.0, 30.0]},
]
_BLACK = {"type": "black"}
#: The procedural envmap ``synth.make_envmap`` writes at ``data_synthetic/envmap.exr``.
ENVMAP = "envmap.exr"
_ENVMAP = {"type": "envmap", "file": "../" + ENVMAP, "scale": 1.0}
#: The HDR probe ``synth.make_probe`` writes at ``data_synthetic/probe.exr``.
PROBE = "probe.exr"
_PROBE = {"type": "envmap", "file": "../" + PROBE, "scale": 1.0}
#: Glossy lobes under a small sun need many samples (path + MIS).
SPP_ENV = 2048

#: Samples per pixel: direct lighting converges fast (interior relative noise
#: ~6e-5 at 1024 spp); the absorbing dielectric's volume sampling is noisier.
SPP_OPAQUE = 1024
SPP_MIRROR = 1024
SPP_DIELECTRIC = 4096


def _case(lobes, truth, *, fixed=None, lights=_TWO_LIGHTS, environment=_BLACK,
          spp=SPP_OPAQUE, seed=0):
    material = {"lobes": list(lobes), "truth": truth}
    if fixed:
        material["fixed"] = fixed
    return {
        "scene": {"width": 128, "height": 128, "supersampling": 4, "camera": dict(_CAMERA),
                  "sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0},
                  "lights": copy.deepcopy(list(lights)), "environment": dict(environment)},
        "material": material,
        "synth": {"spp": spp, "seed": seed},
    }


_SMITH = {"torrance_sparrow.geometry": "smith"}
_VGROOVE = {"torrance_sparrow.geometry": "v_groove"}
_GRAZING = [{"type": "point", "position": [5.0, 0.5, 0.0], "intensity": [60.0, 60.0, 60.0]},
            {"type": "point", "position": [-4.0, 1.0, 3.0], "intensity": [20.0, 20.0, 30.0]}]

CASES: dict[str, dict] = {
    "lambert": _case(["lambert"], {"lambert.rho_d": [0.6, 0.4, 0.2]}),
    "oren_nayar": _case(["oren_nayar"], {"oren_nayar.rho_d": [0.5, 0.45, 0.4],
                                         "oren_nayar.sigma": 0.4}),
    "phong": _case(["phong"], {"phong.rho_s": [0.3, 0.3, 0.3], "phong.e": 50.0}),
    "torrance_sparrow": _case(["torrance_sparrow"], {"torrance_sparrow.m": 0.2,
                                                     "torrance_sparrow.eta": 1.6}, fixed=_SMITH),
    "mirror": _case(["mirror"], {"mirror.rho_m": [0.9, 0.85, 0.8]}, lights=[],
                    environment=_ENVMAP, spp=SPP_MIRROR),
    "plastic": _case(["lambert", "torrance_sparrow"],
                     {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
                      "torrance_sparrow.eta": 1.5}, fixed=_SMITH),
    "plastic_vgroove": _case(["lambert", "torrance_sparrow"],
                             {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
                              "torrance_sparrow.eta": 1.5}, fixed=_VGROOVE),
    "oren_nayar_phong": _case(["oren_nayar", "phong"],
                              {"oren_nayar.rho_d": [0.3, 0.5, 0.6], "oren_nayar.sigma": 0.3,
                               "phong.rho_s": [0.2, 0.2, 0.2], "phong.e": 100.0},
                              fixed={"phong.normalized": True}),
    "dielectric": _case(["dielectric"], {"dielectric.eta": 1.5,
                                         "dielectric.attenuation": [0.9, 0.7, 0.5]},
                        lights=[], environment=_ENVMAP, spp=SPP_DIELECTRIC),
    "extreme_sharp_ts": _case(["lambert", "torrance_sparrow"],
                              {"lambert.rho_d": [0.5, 0.5, 0.5], "torrance_sparrow.m": 0.02,
                               "torrance_sparrow.eta": 1.5}, fixed=_SMITH),
    "extreme_sharp_phong": _case(["lambert", "phong"],
                                 {"lambert.rho_d": [0.4, 0.4, 0.5], "phong.rho_s": [0.5, 0.5, 0.5],
                                  "phong.e": 2000.0}),
    "extreme_low_eta": _case(["lambert", "torrance_sparrow"],
                             {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
                              "torrance_sparrow.eta": 1.02}, fixed=_SMITH),
    "extreme_sigma0": _case(["oren_nayar"], {"oren_nayar.rho_d": [0.5, 0.45, 0.4],
                                             "oren_nayar.sigma": 0.0}),
    "extreme_grazing": _case(["lambert", "torrance_sparrow"],
                             {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.3,
                              "torrance_sparrow.eta": 1.5}, fixed=_VGROOVE, lights=_GRAZING),
    "env_plastic": _case(["lambert", "torrance_sparrow"],
                         {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.1,
                          "torrance_sparrow.eta": 1.5}, fixed=_SMITH, lights=[],
                         environment=_PROBE, spp=SPP_ENV),
    "env_oren_nayar": _case(["oren_nayar"], {"oren_nayar.rho_d": [0.5, 0.45, 0.4],
                                             "oren_nayar.sigma": 0.35},
                            lights=[], environment=_PROBE, spp=SPP_ENV),
    "env_phong": _case(["lambert", "phong"],
                       {"lambert.rho_d": [0.3, 0.4, 0.5], "phong.rho_s": [0.4, 0.4, 0.4],
                        "phong.e": 300.0}, fixed={"phong.normalized": True}, lights=[],
                       environment=_PROBE, spp=SPP_ENV),
    "env_point": _case(["lambert", "torrance_sparrow"],
                       {"lambert.rho_d": [0.2, 0.5, 0.3], "torrance_sparrow.m": 0.25,
                        "torrance_sparrow.eta": 1.6}, fixed=_SMITH,
                       lights=[{"type": "point", "position": [-4.0, 1.0, 3.0],
                                "intensity": [20.0, 20.0, 30.0]}],
                       environment=_PROBE, spp=SPP_ENV),
}

#: Mitsuba 3.9's ``roughconductor`` ``material = "Au"`` in the rgb variants.
_GOLD = {"torrance_sparrow.eta": [0.143, 0.3753, 1.442],
         "torrance_sparrow.k": [3.983, 2.3856, 1.6034]}


def _sized(case: dict, size: int) -> dict:
    case["scene"]["width"] = case["scene"]["height"] = size
    return case


CASES.update({
    "metal_gold": _sized(_case(["torrance_sparrow"], {**_GOLD, "torrance_sparrow.m": 0.25},
                               fixed={**_SMITH, "torrance_sparrow.fresnel": "conductor"}), 64),
    "bright_phong": _sized(_case(["phong"], {"phong.rho_s": [4.0, 4.0, 4.0],
                                             "phong.e": 300.0}), 96),
})

NOTES: dict[str, str] = {
    "metal_gold": "Gold roughconductor (Mitsuba's Au eta, k; Smith G, m = 0.25), 64^2: "
                  "F0 per channel is what the image pins, eta and k trade along its curve.",
    "bright_phong": "Lecture Phong with rho_s = 4, e = 300 (albedo 0.083: rho_s is the "
                    "peak, not a reflectance), 96^2.",
    "lambert": "Lambert alone, two point lights (Mitsuba diffuse).",
    "oren_nayar": "Oren-Nayar alone, sigma = 0.4 (Python plugin fitter_oren_nayar).",
    "phong": "Un-normalised Phong alone, e = 50 (Python plugin fitter_phong).",
    "torrance_sparrow": "Torrance-Sparrow alone, Smith G (Mitsuba roughconductor, k = 0).",
    "mirror": "Perfect mirror in the procedural envmap (conductor, material none; path).",
    "plastic": "The quickstart case: lambert + torrance_sparrow (Smith G), two point lights.",
    "plastic_vgroove": "The quickstart material with the lecture's V-groove G (Python plugin).",
    "oren_nayar_phong": "Oren-Nayar + normalised Phong, summed by fitter_sum.",
    "dielectric": "Smooth dielectric sphere with Beer-Lambert attenuation in the envmap "
                  "(dielectric + homogeneous medium; volpathmis).",
    "extreme_sharp_ts": "Very sharp highlight, m = 0.02 (about a pixel wide).",
    "extreme_sharp_phong": "Very sharp Phong highlight, e = 2000.",
    "extreme_low_eta": "eta = 1.02: the specular lobe is ~1e-4 of the diffuse; m, eta barely "
                       "identifiable.",
    "extreme_sigma0": "Oren-Nayar at sigma = 0, the edge of its box (equals Lambert).",
    "extreme_grazing": "Light at 90 degrees to the view: half-lit sphere, highlight near "
                       "the limb (V-groove G at grazing angles).",
    "env_plastic": "Lambert + Torrance-Sparrow (m = 0.1) lit only by the HDR probe "
                   "(sun, sky, ground, window); Mitsuba path, max_depth 2.",
    "env_oren_nayar": "Oren-Nayar (sigma = 0.35) lit only by the HDR probe.",
    "env_phong": "Lambert + normalised Phong (e = 300) lit only by the HDR probe.",
    "env_point": "Lambert + Torrance-Sparrow (m = 0.25) under the HDR probe plus one point "
                 "light.",
}
