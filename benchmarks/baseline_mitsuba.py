"""Baseline B: Mitsuba 3's own differentiable rendering + ``mi.ad.Adam``.

The way Mitsuba's inverse-rendering tutorials fit BSDF parameters: render
with an AD integrator (``prb``, ``max_depth = 2``: direct light only, all the
scene has), an L2 image loss over the whole image, ``dr.backward``, Adam
(lr 0.02-0.05) on the raw parameters, clamped to their valid box after each
step. Monte Carlo gradients at ``spp`` samples per pixel, a new seed each
iteration.

Mitsuba 3.9 has no additive BSDF whose children are differentiable (its
``blendbsdf`` is a convex mix, the project's ``fitter_sum`` plugin does not
expose its children), so ``lambert + torrance_sparrow`` is rendered as two
scenes -- ``diffuse`` and ``roughconductor`` (Beckmann, k = 0) -- whose images
are added: exact by linearity of light transport, at the cost of two renders
per iteration.
"""

from __future__ import annotations

import time

import numpy as np


def fit(target, scene, x0, *, spp=16, lr=0.02, iters=200, record=None, variant=None):
    """Fit (rho_r, rho_g, rho_b, m, eta); returns (x, seconds excluding iteration 0, first s).

    ``record(x, t)`` is called after every iteration with the seconds since
    the end of iteration 0 (the first iteration compiles the kernels and is
    reported separately), excluding the recording.
    """
    import drjit as dr

    from fitter.material import Material
    from fitter.mitsuba import scene_dict
    from fitter.mitsuba.variant import load

    mi, _ = load(variant)
    x0 = np.asarray(x0, dtype=float)
    lambert = Material.make(["lambert"])
    ts = Material.make(["torrance_sparrow"], {"torrance_sparrow.geometry": "smith"})
    d1 = scene_dict(scene, lambert, {"lambert.rho_d": x0[:3]}, spp=spp, seed=0, variant=variant)
    d2 = scene_dict(scene, ts, {"torrance_sparrow.m": x0[3], "torrance_sparrow.eta": x0[4]},
                    spp=spp, seed=0, variant=variant)
    for d in (d1, d2):
        d["integrator"] = {"type": "prb", "max_depth": 2}
    s1, s2 = mi.load_dict(d1), mi.load_dict(d2)
    p1, p2 = mi.traverse(s1), mi.traverse(s2)
    k_rho, k_m, k_eta = "sphere.bsdf.reflectance.value", "sphere.bsdf.alpha.value", \
        "sphere.bsdf.eta.value"
    opt = mi.ad.Adam(lr=lr)
    opt["rho"] = mi.Color3f(*(float(v) for v in x0[:3]))
    opt["m"] = mi.Float(float(x0[3]))
    opt["eta"] = mi.Float(float(x0[4]))

    def apply():
        opt["rho"] = dr.clip(opt["rho"], 0.0, 1.0)
        opt["m"] = dr.clip(opt["m"], 1e-3, 1.0)
        opt["eta"] = dr.clip(opt["eta"], 1.0, 4.0)
        p1[k_rho] = opt["rho"]
        p2[k_m] = opt["m"]
        p2[k_eta] = opt["eta"]
        p1.update()
        p2.update()

    apply()
    ref = mi.TensorXf(np.asarray(target, dtype=np.float32))
    paused, t0, first = 0.0, None, 0.0
    for it in range(iters):
        ta = time.perf_counter()
        img = mi.render(s1, p1, spp=spp, seed=2 * it) + mi.render(s2, p2, spp=spp, seed=2 * it + 1)
        loss = dr.mean(dr.square(img - ref), axis=None)
        dr.backward(loss)
        opt.step()
        apply()
        x = np.concatenate([np.array(opt["rho"], dtype=float).reshape(-1),
                            np.array(opt["m"], dtype=float).reshape(-1),
                            np.array(opt["eta"], dtype=float).reshape(-1)])
        if it == 0:
            first = time.perf_counter() - ta
            t0 = time.perf_counter()
            continue
        if record is not None:
            tb = time.perf_counter()
            record(x, tb - t0 - paused)
            paused += time.perf_counter() - tb
    return x, time.perf_counter() - t0 - paused, first
