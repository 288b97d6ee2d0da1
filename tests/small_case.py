"""A small forward-model fit case (40x32, lambert + torrance_sparrow) shared by CLI tests."""

from __future__ import annotations

import os

import numpy as np

import fitter
from fitter import imageio
from fitter.config import dumps_toml, load_config

SMALL = {
    "scene": {
        "width": 40, "height": 32, "supersampling": 2,
        "camera": {"type": "perspective", "origin": [0.0, 0.0, 4.0], "fov": 35.0},
        "lights": [{"type": "point", "position": [3.0, 4.0, 5.0],
                    "intensity": [30.0, 30.0, 30.0]},
                   {"type": "point", "position": [-4.0, 1.0, 4.0],
                    "intensity": [10.0, 12.0, 14.0]}],
    },
    "material": {
        "lobes": ["lambert", "torrance_sparrow"],
        "truth": {"lambert.rho_d": [0.6, 0.4, 0.2], "torrance_sparrow.m": 0.2,
                  "torrance_sparrow.eta": 1.5},
        "init": {"torrance_sparrow.m": 0.3, "torrance_sparrow.eta": 1.4},
        "fixed": {"torrance_sparrow.geometry": "smith"},
    },
    "fit": {"target": "target.exr", "validate": False},
}


def write_case(folder, data=SMALL, target_name="target.exr"):
    """A config in ``folder`` and its forward-model target; returns the config path."""
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, "small.toml")
    with open(path, "w") as fh:
        fh.write(dumps_toml(data))
    job = load_config(path)
    truth = job.material.full_params({**job.fixed, **job.truth})
    img = np.asarray(fitter.render(truth, job.scene, job.material))
    imageio.write_image(os.path.join(folder, target_name), img)
    return path
