"""A coarse search for the solver's start, for lobes whose cost has narrow
basins (``Lobe.start_search``; the dielectric's eta near 1).

The search sees every ``stride``-th fitted pixel (about ``SEARCH_PIXELS``)
through one sub-pixel sample each (the one of largest quadrature weight),
and the plain weighted squared residual: a cheap, rough cost whose minimum is
near the fit's. The solver then starts there if it beats the given start on
that cost (the given point is one of the candidates).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..bsdf.base import SurfaceHit
from ..environment import lookup
from ..material import lobe_params

#: About this many pixels enter the search.
SEARCH_PIXELS = 2048


@functools.lru_cache(maxsize=8)
def _searcher(lobe, opts_items, env_type, free, box_items):
    opts, box = dict(opts_items), dict(box_items)

    def run(p, position, normal, ray_dir, center, radius, env, target, weights):
        hit = SurfaceHit(position, normal, ray_dir, center, radius)

        def cost(model):  # (..., P, 3) -> (..., 3)
            return jnp.sum(jnp.square((model - target) * weights), axis=-2)

        return lobe.start_search(p, opts, hit, functools.partial(lookup, env_type, env), cost,
                                 free, box)

    return jax.jit(run)


def searched(problem):
    """``problem`` with its start (``init_full``) moved to the search's best
    point, or unchanged (no lobe searches, or the material has more lobes)."""
    material = problem.material
    if len(material.lobes) != 1 or material.lobe_objects[0].start_search is None:
        return problem
    lobe = material.lobe_objects[0]
    blocks = {b.key.split(".", 1)[1]: b for b in problem.blocks}
    if not blocks:
        return problem
    geo = problem.geometry
    n = int(np.asarray(geo.hit).shape[0])
    rows = np.arange(0, n, max(1, n // SEARCH_PIXELS))
    k = int(np.argmax(np.asarray(geo.sample_weight)))
    pick = lambda a: jnp.asarray(np.asarray(a)[rows, k])  # noqa: E731
    hit = np.asarray(geo.hit)[rows, k]
    weights = np.where(hit[:, None], problem.weights[0][rows], 0.0)
    p0 = {k_: jnp.asarray(v) for k_, v in lobe_params(problem.init_full, lobe.name).items()}
    run = _searcher(lobe, tuple(sorted(material.options_of(lobe.name).items())),
                    problem.renderer.env_type, tuple(sorted(blocks)),
                    tuple(sorted((k_, (b.lower, b.upper)) for k_, b in blocks.items())))
    sphere = problem.renderer.sphere
    best = run(p0, pick(geo.position), pick(geo.normal), pick(geo.ray_dir), sphere[0],
               sphere[1], problem.renderer.env, jnp.asarray(problem.targets[0][rows]),
               jnp.asarray(weights))
    init = dict(problem.init_full)
    for name in blocks:
        init[f"{lobe.name}.{name}"] = np.asarray(best[name], dtype=np.float64)
    return dataclasses.replace(problem, init_full=init)
