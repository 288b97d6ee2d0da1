"""Before the solve: a coarse search for the start, for lobes whose cost has
narrow basins (``Lobe.start_search``; the dielectric's eta near 1), and the
cheapest lobe options whose truncation stays below the noise
(``Lobe.cheapest_options``; the dielectric's bounce count).

The search sees every ``stride``-th fitted pixel (about ``SEARCH_PIXELS``)
through one sub-pixel sample each, the one of largest quadrature weight
(measured: from the search's point the shipped case took 6 solver steps, 10
with all 16 samples of 1/16 as many pixels), and the plain weighted squared
residual: a cheap, rough cost whose minimum lies near the fit's. The start
itself is the first candidate, so the solver never starts from a point the
search found worse (and a tie keeps the start).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._math import to_device
from ..bsdf.base import SurfaceHit
from ..environment import lookup
from ..material import Material, lobe_params
from ._compile import FAST_XLA_OPTIONS

#: About this many pixels enter the search.
SEARCH_PIXELS = 2048
#: What a lobe's options may leave out of any pixel, as a fraction of the noise
#: level (the given noise_sigma, else the level estimated from the target; that
#: estimate also counts fine image structure, so it is an upper bound).
TRUNCATION_NOISE_FRACTION = 0.1
#: A parameter along which the search's cost changed by more than this
#: (relative) is one the pixels depend on; where every free one did, the start
#: check (``_drivers``: a Jacobian at the start, 0.9 s of a dielectric's first
#: run to trace and compile) is not made. Conservative: that check calls a
#: column dead only below 1e-9 of the largest (``_identify.ZERO_COLUMN``).
SEEN_CHANGE = 1e-6


@functools.lru_cache(maxsize=8)
def _searcher(lobe, opts_items, env_type):
    opts = dict(opts_items)

    def run(p, position, normal, ray_dir, center, radius, sample_weight, env, target, weights):
        hit = SurfaceHit(position, normal, ray_dir, center, radius)

        def cost(model):  # (P, K, 3) -> (3,)
            pixels = jnp.einsum("pkc,pk->pc", model, sample_weight)
            return jnp.sum(jnp.square((pixels - target) * weights), axis=0)

        return lobe.start_search.best(p, opts, hit, functools.partial(lookup, env_type, env),
                                      cost)

    return jax.jit(run, compiler_options=FAST_XLA_OPTIONS)


def searched(problem):
    """``problem`` with its start (``init_full``) moved to the search's best
    point, and the parameters the search saw change the cost added to its
    ``alive``; unchanged if its material is not one lobe with a search."""
    material = problem.material
    lobe = material.lobe_objects[0]
    if len(material.lobes) != 1 or lobe.start_search is None:
        return problem
    free = {b.key.split(".", 1)[1]: (b.lower, b.upper) for b in problem.blocks}
    if not free:
        return problem
    geo = problem.geometry
    n = np.asarray(geo.hit).shape[0]
    rows = np.arange(0, n, max(1, n // SEARCH_PIXELS))
    k = int(np.argmax(np.asarray(geo.sample_weight)))
    # In float64 whatever the fit's dtype: the search only ranks candidates.
    # (to_device: jnp.asarray compiled a copy kernel per argument's shape, 9 per first run)
    f64 = lambda a: to_device(a, np.float64)  # noqa: E731
    pick = lambda a: f64(np.asarray(a)[rows, k:k + 1])  # noqa: E731
    sample_weight = np.asarray(geo.hit)[rows, k:k + 1].astype(np.float64)
    p = lobe_params(problem.init_full, lobe.name)
    run = _searcher(lobe, tuple(sorted(material.options_of(lobe.name).items())),
                    problem.renderer.env_type)
    sphere = problem.renderer.sphere
    args = (pick(geo.position), pick(geo.normal), pick(geo.ray_dir), f64(sphere[0]),
            f64(sphere[1]), f64(sample_weight), jax.tree_util.tree_map(f64, problem.renderer.env),
            f64(problem.targets[0][rows] - np.asarray(geo.background)[rows]),
            f64(problem.weights[0][rows]))
    best, seen = p, {name: 0.0 for name in free}
    for grid in lobe.start_search.rounds(p, tuple(free), free):
        found, spread = run({k_: f64(v) for k_, v in grid(best).items()}, *args)
        best = {k_: np.asarray(v, dtype=np.float64) for k_, v in found.items()}
        seen = {name: np.maximum(seen[name], np.asarray(spread[name])) for name in free}
    init = dict(problem.init_full)
    for name in free:
        init[f"{lobe.name}.{name}"] = best[name]
    alive = frozenset(f"{lobe.name}.{name}" for name in free
                      if np.all(seen[name] > SEEN_CHANGE))
    return dataclasses.replace(problem, init_full=init, alive=problem.alive | alive)


def cheapened(problem):
    """``problem`` with each lobe's work options (``Lobe.cheapest_options``) as
    low as keeps what they leave out of every fitted pixel below
    ``TRUNCATION_NOISE_FRACTION`` of the noise, at the start point."""
    material = problem.material
    lobes = [lb for lb in material.lobe_objects if lb.cheapest_options is not None]
    sigma = (np.full(3, problem.noise_sigma) if problem.noise_sigma is not None
             else np.asarray(problem.noise[0], dtype=np.float64))
    if not lobes or not np.all(np.isfinite(sigma) & (sigma > 0)):
        return problem
    geo, renderer = problem.geometry, problem.renderer
    hit = SurfaceHit(np.asarray(geo.position), np.asarray(geo.normal), np.asarray(geo.ray_dir),
                     np.asarray(renderer.sphere[0]), float(renderer.sphere[1]))
    weight = np.asarray(geo.sample_weight)[None] * np.asarray(geo.hit)
    env = renderer.env
    env_max = (np.max(np.asarray(env.image), axis=(0, 1)) if renderer.env_type == "envmap"
               else np.asarray(env.constant))
    options = dict(material.options)
    for lobe in lobes:
        found = lobe.cheapest_options(lobe_params(problem.init_full, lobe.name),
                                      material.options_of(lobe.name), hit, weight, env_max,
                                      TRUNCATION_NOISE_FRACTION * sigma)
        options.update({f"{lobe.name}.{k}": v for k, v in found.items()})
    if options == dict(material.options):
        return problem
    return dataclasses.replace(problem, material=Material.make(material.lobes, options,
                                                               exposure=material.exposure))
