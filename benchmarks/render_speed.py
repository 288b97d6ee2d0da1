"""Render speed of the forward model: prints figures, asserts nothing.

256 x 256 image, 2 point lights, supersampling 4 (16 samples a pixel), for
``lambert+torrance_sparrow`` and ``dielectric`` (constant environment), in
float64 and float32. For each: scene preparation (geometry, once per scene),
first call (trace + XLA compile + run), and the warm time of a render and of
a reverse-mode gradient of a scalar of the image (median of ``--repeat``
runs, ``block_until_ready``).

    .venv/bin/python benchmarks/render_speed.py [--size 256] [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import fitter

CASES = {
    "lambert+torrance_sparrow": {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.15,
                                 "torrance_sparrow.eta": 1.5},
    "dielectric": {"dielectric.eta": 1.5, "dielectric.attenuation": [0.8, 0.9, 0.95]},
}


def scene(size: int) -> fitter.Scene:
    return fitter.Scene(
        width=size, height=size, supersampling=4,
        lights=(fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),
                fitter.PointLight((-4.0, 1.0, 3.0), (20.0, 25.0, 30.0))),
        environment=fitter.Environment(type="constant", radiance=(0.5, 0.6, 0.7)))


def timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench(name, params, sc, dtype, repeat):
    material = fitter.Material.from_params(params)
    t0 = time.perf_counter()
    renderer = fitter.Renderer(sc, material, dtype=dtype)
    prep = time.perf_counter() - t0
    p = {k: jnp.asarray(v, dtype=dtype) for k, v in params.items()}

    t0 = time.perf_counter()
    jax.block_until_ready(renderer.active(p))
    first = time.perf_counter() - t0
    warm = timed(lambda: renderer.active(p), repeat)

    grad = jax.jit(jax.grad(lambda q: jnp.sum(renderer.active(q))))
    t0 = time.perf_counter()
    jax.block_until_ready(grad(p))
    grad_first = time.perf_counter() - t0
    grad_warm = timed(lambda: grad(p), repeat)
    print(f"{name:26s} {jnp.dtype(dtype).name:8s} {renderer.n_active:7d} {prep:8.3f} "
          f"{first:9.3f} {1e3 * warm:9.1f} {grad_first:10.3f} {1e3 * grad_warm:10.1f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    sc = scene(args.size)
    print(f"{args.size}x{args.size}, supersampling 4, 2 point lights; jax {jax.__version__} "
          f"on {jax.devices()[0].platform}")
    print(f"{'material':26s} {'dtype':8s} {'active':>7s} {'prep s':>8s} {'compile s':>9s} "
          f"{'warm ms':>9s} {'grad cmp s':>10s} {'grad ms':>10s}")
    for name, params in CASES.items():
        for dtype in (jnp.float64, jnp.float32):
            bench(name, params, sc, dtype, args.repeat)


if __name__ == "__main__":
    main()
