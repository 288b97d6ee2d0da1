"""The post-fit cost profile (``fitter.fit._identify.weak_profile``) on the pixel
subset (``fitter.fit._profile``) against every pixel, in one process.

Cases: 256^2 plastic (lambert + torrance_sparrow, 4x4 samples, JAX target at
the truth + noise sigma 2e-3, from the lobe defaults), the 128^2 dielectric
(``configs/dielectric.toml`` on its Mitsuba target, from the config's start)
and, by ``--cases``, the four env cases (``configs/env_*.toml``, Mitsuba
targets), three sharp highlights (``_sharp``: Beckmann m = 0.05 and 0.02
at 128^2, 0.01 at 192^2), a gold conductor at 128^2 (``_metal``) and, by
their names, the shipped point-lit configs (quickstart, lambert, ...,
extreme_*). Each case is fitted once (compiling everything), the profile's
inputs are captured at the fit's solution, then the profile runs ``--repeat``
times each way, interleaved; the line gives the minima, the verdicts and the
largest |estimated - whole-image| chi^2 rise over the points, also in the
subset's guarded standard errors (``_profile.GUARD`` applies to these), and
how many points the guard sent to every pixel. Then
whole ``fitter.fit`` calls, subset on and off interleaved (minima).

    python benchmarks/profile_subset.py [--repeat 5] [--cases "env_plastic 128²" ...] [--float64]

``--float64``: the subset's residuals in float64 (``_profile.SINGLE`` off;
float32 is the default where every lobe has ``single_precision``, and never
under environment samples).
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _plastic():
    from error_vs_time import load_job

    import fitter

    job, base = load_job("plastic", 256)
    truth = job.material.full_params({**job.fixed, **job.truth})
    clean = np.asarray(fitter.render(truth, job.scene, job.material, base_dir=base))
    target = clean + np.random.default_rng(0).normal(0.0, 2e-3, clean.shape)
    return lambda: fitter.fit(target, job.scene, job.material, fixed=job.fixed, base_dir=base)


def _sharp(m: float, res: int):
    """A sharp highlight: lambert + Beckmann (Smith) m at res^2, two point
    lights, 4x4 samples, JAX target at the truth + noise sigma 2e-3, fitted from
    the truth (the profile is what is measured, not the start)."""
    import fitter

    scene = fitter.Scene(width=res, height=res, supersampling=4, lights=(
        fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
        fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 20.0, 30.0))))
    material = fitter.Material.make(["lambert", "torrance_sparrow"],
                                    {"torrance_sparrow.geometry": "smith"})
    truth = {"lambert.rho_d": [0.5, 0.4, 0.3], "torrance_sparrow.m": m,
             "torrance_sparrow.eta": 1.5}
    clean = np.asarray(fitter.render(material.full_params(truth), scene, material))
    target = clean + np.random.default_rng(0).normal(0.0, 2e-3, clean.shape)
    return lambda: fitter.fit(target, scene, material, init=truth)


def _metal(res: int):
    """A gold conductor (``configs/metal_gold.toml``'s material and lights) at
    res^2, JAX target at the truth + noise sigma 2e-3, fitted from the truth."""
    import fitter
    from fitter import config

    job = config.load_config(os.path.join(ROOT, "configs/metal_gold.toml"))
    scene = job.scene.replace(width=res, height=res)
    truth = job.material.full_params({**job.fixed, **job.truth})
    clean = np.asarray(fitter.render(truth, scene, job.material))
    target = clean + np.random.default_rng(0).normal(0.0, 2e-3, clean.shape)
    return lambda: fitter.fit(target, scene, job.material, init=job.truth, fixed=job.fixed)


def _config(case: str):
    """A shipped config's fit (its Mitsuba target, from the config's start)."""
    import fitter
    from fitter import config, pipeline

    job = config.load_config(os.path.join(ROOT, f"configs/{case}.toml"))
    target, _ = pipeline.read_target(job.fit.target, job.scene)
    return lambda: fitter.fit(target, job.scene, job.material, init=job.init, fixed=job.fixed,
                              base_dir=job.base_dir)


def rises(args, subset: bool):
    """(chi^2 rises at the profile's points, their estimated standard errors
    (None on every pixel), the verdict, seconds)."""
    from fitter.fit import _compile, _identify, _profile

    spec, data, z, R, _, sigma = args
    # The fit's verdict used its remembered Jacobian: linearise again at z
    # (and profile from these residuals, with which it is remembered).
    J, rr, _ = _compile.jac_full(spec, z, data)
    _compile.remember_jacobian(spec, z, data, J, rr)
    args = (spec, data, z, R, rr, sigma)
    _profile.ENABLED = subset
    seen = {}
    verdict = _identify.profile_verdict

    def spy(s2, cost, profile):
        seen["rise"] = np.array([2 * (c - cost) / s2 for _, _, c in profile])
        return verdict(s2, cost, profile)

    estimate = _profile.estimated_rises

    def spy_se(*a, **k):
        out = estimate(*a, **k)
        seen["se"] = out[1]
        return out

    whole = _compile.costs_at

    def spy_whole(spec, zs, data):
        seen["whole"] = seen.get("whole", 0) + len(zs)
        return whole(spec, zs, data)

    _identify.profile_verdict = spy
    _profile.estimated_rises = spy_se
    _compile.costs_at = spy_whole
    try:
        why, _, sec = _identify.weak_profile(*args)
    finally:
        _identify.profile_verdict = verdict
        _profile.estimated_rises = estimate
        _compile.costs_at = whole
        _profile.ENABLED = True
    rises.whole = seen.get("whole", 0)
    return seen.get("rise", np.zeros(0)), seen.get("se"), why, sec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cases", nargs="*", default=["plastic 256²", "dielectric 128²"])
    ap.add_argument("--float64", action="store_true",
                    help="the subset's residuals in float64 (``_profile.SINGLE`` off)")
    args = ap.parse_args(argv)

    from fitter.fit import _drivers, _profile

    _profile.SINGLE = not args.float64

    makers = {"plastic 256²": _plastic,
              "sharp m=0.05 128²": functools.partial(_sharp, 0.05, 128),
              "sharp m=0.02 128²": functools.partial(_sharp, 0.02, 128),
              "sharp m=0.01 192²": functools.partial(_sharp, 0.01, 192),
              "metal 128²": functools.partial(_metal, 128),
              **{f"{c} 128²": functools.partial(_config, c)
                 for c in ("dielectric", "env_plastic", "env_phong", "env_oren_nayar",
                           "env_point")},
              # (by the config's name: its own size)
              **{c: functools.partial(_config, c)
                 for c in ("quickstart", "lambert", "oren_nayar", "phong", "torrance_sparrow",
                           "plastic", "plastic_vgroove", "oren_nayar_phong", "bright_phong",
                           "metal_gold", "extreme_sharp_phong", "extreme_sharp_ts",
                           "extreme_grazing", "extreme_low_eta", "extreme_sigma0")}}
    for name in args.cases:
        run = makers[name]()
        captured: list = []

        def capture(*a, captured=captured, real=_drivers.weak_profile, **k):
            captured.append(a)
            return real(*a, **k)

        real = _drivers.weak_profile
        _drivers.weak_profile = capture
        try:
            res = run()  # compiles the fit and both profiles' executables
        finally:
            _drivers.weak_profile = real
        if not captured:
            print(f"{name}: the profile did not run ({res.status})")
            continue
        a = captured[-1]
        rises(a, False)
        times = {True: [], False: []}
        for _ in range(args.repeat):
            for subset in (False, True):
                rise, se, why, sec = rises(a, subset)
                times[subset].append(sec)
                if subset:
                    est, se_sub, why_sub, redone = rise, se, why, rises.whole
                else:
                    full, why_full = rise, why
        fits = {True: [], False: []}
        for _ in range(args.repeat):
            for subset in (False, True):
                _profile.ENABLED = subset
                t0 = time.perf_counter()
                out = run()
                fits[subset].append(time.perf_counter() - t0)
                _profile.ENABLED = True
                if subset:
                    p_sub = out.params
                else:
                    p_full = out.params
        guarded = (np.max(np.abs(est - full) / np.hypot(se_sub, _profile.SE_FLOOR))
                   if se_sub is not None and len(se_sub) == len(full) else float("nan"))
        same = all(np.array_equal(np.asarray(p_sub[k]), np.asarray(p_full[k])) for k in p_sub)
        print(f"{name}: {len(full)} points; profile stage min {min(times[False]):.3f} s "
              f"(every pixel) -> {min(times[True]):.3f} s (subset), "
              f"x{min(times[False]) / min(times[True]):.1f}; verdict {why_full!r} / "
              f"{why_sub!r}; max |rise est - rise| {np.max(np.abs(est - full)):.3g} "
              f"(rises {np.min(full):.3g}..{np.max(full):.3g}; {guarded:.2f} guarded standard "
              f"errors; {redone} points on every pixel); fitter.fit min "
              f"{min(fits[False]):.3f} -> {min(fits[True]):.3f} s; fitted values equal: {same}")
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
