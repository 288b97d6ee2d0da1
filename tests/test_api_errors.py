"""The Python API checks its input like the config does: every bad argument is a
``FitterError`` (the named subclass) whose message names the argument or key,
never an internal error from NumPy, JAX, lineax or optimistix, and never a
silent or misleading result (issue 15, items 4 and 5)."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitter
from fitter.camera import SceneError
from fitter.errors import FitterError
from fitter.fit import FitError
from fitter.limits import MAX_STARTS, ResourceError
from fitter.material import MaterialError

LIGHTS = (fitter.PointLight((3.0, 4.0, 5.0), (50.0, 50.0, 50.0)),)
SCENE = fitter.Scene(width=16, height=16, supersampling=1, lights=LIGHTS)
TARGET = np.full((16, 16, 3), 0.2)
DARK = (fitter.PointLight((3.0, 4.0, 5.0), (-1.0, 1.0, 1.0)),)


def fit(**kwargs):
    args = {"target": TARGET, "scene": SCENE, "material": "lambert", **kwargs}
    return fitter.fit(args.pop("target"), args.pop("scene"), args.pop("material"), **args)


def render(params, scene=SCENE):
    return fitter.render(params, scene)


#: id -> (call, error class, pattern the message must contain: the argument or key).
CASES = {
    # Internal errors before (lineax, jacfwd, LinAlgError, broadcasting, ...).
    "dtype float16": (lambda: fit(dtype=jnp.float16), FitError, r"^dtype: 'float16'.*float64"),
    "dtype int32": (lambda: fit(dtype=jnp.int32), FitError, r"^dtype: 'int32'"),
    "dtype None": (lambda: fit(dtype=None), FitError, r"^dtype: None"),
    "NaN weights": (lambda: fit(weights=np.full((16, 16), np.nan)), FitError,
                    r"^weights: contains NaN"),
    "negative weights": (lambda: fit(weights=-np.ones((16, 16))), FitError,
                         r"^weights: .*>= 0"),
    "wrong-shape weights": (lambda: fit(weights=np.ones((8, 8))), FitError,
                            r"^weights has shape \(8, 8\), expected \(16, 16\)"),
    "RGB of 2 in init": (lambda: fit(init={"lambert.rho_d": [0.5, 0.5]}), MaterialError,
                         r"^lambert\.rho_d: expected 3 value\(s\), got 2"),
    "RGB of 2 in fixed": (lambda: fit(material="lambert+phong",
                                      fixed={"phong.rho_s": [0.5, 0.5]}),
                          MaterialError, r"^phong\.rho_s: expected 3"),
    "RGB of 2 in render": (lambda: render({"lambert.rho_d": [0.5, 0.5]}), MaterialError,
                           r"^lambert\.rho_d: expected 3"),
    "text value in init": (lambda: fit(init={"lambert.rho_d": "half"}), MaterialError,
                           r"^lambert\.rho_d: expected a number"),
    "Scene(width=0) fit": (lambda: fit(scene=fitter.Scene(width=0)), SceneError,
                           r"^scene\.width: expected an integer >= 1, got 0"),
    "Scene(width=0) render": (lambda: render({"lambert.rho_d": 0.5}, fitter.Scene(width=0)),
                              SceneError, r"^scene\.width"),
    "list of lists, ragged": (lambda: fit(target=[[0.1, 0.2], [0.3]]), FitError, r"^target: "),
    "file name as target": (lambda: fit(target="target.exr"), FitError,
                            r"^target: got the file name 'target\.exr'"),
    "n_starts=2.5": (lambda: fit(n_starts=2.5), FitError,
                     r"^n_starts: expected an integer, got 2\.5"),
    "n_starts=0": (lambda: fit(n_starts=0), FitError, r"^n_starts: expected an integer >= 1"),
    "scene=None": (lambda: fit(scene=None), SceneError, r"^scene: expected a fitter\.Scene"),
    "material=5": (lambda: fit(material=5), MaterialError, r"^material: expected a Material"),
    "init not a dict": (lambda: fit(init=[0.5]), FitError, r"^init: expected a dict"),
    "noise_sigma text": (lambda: fit(noise_sigma="0.1"), FitError,
                         r"^noise_sigma: expected a number"),
    "fit_batch scene=None": (lambda: fitter.fit_batch(TARGET[None], None, "lambert"), SceneError,
                             r"^scene: "),
    "fit_batch n_starts": (lambda: fitter.fit_batch(TARGET[None], SCENE, "lambert", n_starts=3),
                           FitError, r"fit_batch takes no n_starts"),
    "fit_batch one image": (lambda: fitter.fit_batch(TARGET, SCENE, "lambert"), FitError,
                            r"^targets have shape \(16, 16, 3\), expected \(B, H, W, 3\)"),
    "render params not a dict": (lambda: fitter.render([0.5], SCENE), MaterialError,
                                 r"^params: expected a dict"),
    "render scene=None": (lambda: render({"lambert.rho_d": 0.5}, None), SceneError,
                          r"^scene: expected a fitter\.Scene"),
    "render material=5": (lambda: fitter.render({}, SCENE, 5), MaterialError, r"^material: "),
    "complex target": (lambda: fit(target=TARGET.astype(complex)), FitError,
                       r"^target: expected an array of numbers.*complex128"),
    "mask of wrong shape": (lambda: fit(mask=np.ones((4, 4), bool)), FitError,
                            r"^mask has shape \(4, 4\)"),
    "exclude of wrong shape": (lambda: fit(exclude=np.ones((4, 4), bool)), FitError,
                               r"^exclude has shape \(4, 4\)"),
    "n_starts text": (lambda: fit(n_starts="2"), FitError, r"^n_starts: expected an integer"),
    "rtol True": (lambda: fit(rtol=True), FitError, r"^rtol: expected a number, got True"),
    "identifiability text": (lambda: fit(identifiability="yes"), FitError,
                             r"^identifiability: expected true or false"),
    "bounds NaN": (lambda: fit(bounds={"lambert.rho_d": (float("nan"), 0.5)}), FitError,
                   r"^bounds for lambert\.rho_d: expected a finite number"),
    "supersampling over the cap": (lambda: fit(scene=SCENE.replace(supersampling=40)),
                                   ResourceError, r"scene\.supersampling = 40 is over the limit"),
    # Silent or misleading results before.
    "render NaN": (lambda: render({"lambert.rho_d": float("nan")}), MaterialError,
                   r"^lambert\.rho_d = nan is not finite"),
    "render m = 0": (lambda: render({"torrance_sparrow.m": 0.0}), MaterialError,
                     r"^torrance_sparrow\.m = 0\.0 is outside its valid range \[0\.001, 1\]"),
    "render m < 0": (lambda: render({"torrance_sparrow.m": -0.1}), MaterialError,
                     r"^torrance_sparrow\.m = -0\.1 is outside its valid range"),
    "render rho = 2": (lambda: render({"lambert.rho_d": 2.0}), MaterialError,
                       r"^lambert\.rho_d = 2\.0 is outside its valid range \[0, 1\]"),
    "render rho = -1": (lambda: render({"lambert.rho_d": [0.5, -1.0, 0.5]}), MaterialError,
                        r"^lambert\.rho_d = \[0\.5, -1\.0, 0\.5\] is outside its valid range"),
    "render eta = 0": (lambda: render({"torrance_sparrow.eta": 0.0}), MaterialError,
                       r"^torrance_sparrow\.eta = 0\.0 is outside its valid range \[1, 4\]"),
    "render negative light": (lambda: render({"lambert.rho_d": 0.5}, SCENE.replace(lights=DARK)),
                              SceneError, r"^scene\.lights\[0\]\.intensity: -1\.0 is outside"),
    "fit negative light": (lambda: fit(scene=SCENE.replace(lights=DARK)), SceneError,
                           r"^scene\.lights\[0\]\.intensity"),
    "max_steps=0": (lambda: fit(max_steps=0), FitError,
                    r"^max_steps: expected an integer >= 1, got 0"),
    "max_steps=-1": (lambda: fit(max_steps=-1), FitError, r"^max_steps: .* got -1"),
    "all-zero weights": (lambda: fit(weights=np.zeros((16, 16))), FitError,
                         r"^no pixels to fit: weights are 0"),
    "unknown bounds key": (lambda: fit(bounds={"lambert.rho": (0.1, 0.9)}), FitError,
                           r"^bounds: unknown parameter 'lambert\.rho'.*known: lambert\.rho_d"),
    "bounds on a fixed key": (lambda: fit(material="lambert+phong", fixed={"phong.e": 10.0},
                                          bounds={"phong.e": (2.0, 50.0)}),
                              FitError, r"^bounds: phong\.e is fixed"),
    "bounds not a pair": (lambda: fit(bounds={"lambert.rho_d": 0.5}), FitError,
                          r"^bounds for lambert\.rho_d: expected \(lower, upper\)"),
    "rtol=-1": (lambda: fit(rtol=-1), FitError, r"^rtol: -1 is outside the allowed range"),
    "atol=0": (lambda: fit(atol=0.0), FitError, r"^atol: 0\.0 is outside the allowed range"),
    "n_starts over the cap": (lambda: fit(n_starts=MAX_STARTS + 1), ResourceError,
                              r"fit\.n_starts = 1025 is over the limit"),
    # Item 5: messages name the key (or argument) to change.
    "every parameter fixed": (lambda: fit(fixed={"lambert.rho_d": 0.5}), FitError,
                              r"every parameter is fixed.*remove lambert\.rho_d from fixed "
                              r"\(material\.fixed"),
    "radius 1e-300": (lambda: fit(scene=SCENE.replace(sphere=fitter.Sphere(radius=1e-300))),
                      FitError, r"^no pixels to fit: the sphere covers no pixel.*"
                                r"scene\.sphere\.radius"),
    "sphere off screen": (lambda: fit(scene=SCENE.replace(
        sphere=fitter.Sphere(center=(50.0, 0.0, 0.0)))), FitError,
        r"^no pixels to fit: the sphere covers no pixel.*scene\.sphere\.center = \[50\.0"),
    "(32, 32) target": (lambda: fit(target=np.zeros((32, 32))), FitError,
                        r"^target has shape \(32, 32\), expected \(16, 16, 3\)"),
    "all target pixels NaN": (lambda: fit(target=np.full((16, 16, 3), np.nan)), FitError,
                              r"^no pixels to fit: every selected pixel of the target is "
                              r"NaN/Inf"),
}


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_a_named_fitter_error(case):
    call, cls, pattern = CASES[case]
    try:
        call()
    except Exception as exc:  # noqa: BLE001 (the point: which class it is)
        assert isinstance(exc, FitterError), f"{type(exc).__module__}.{type(exc).__name__}: {exc}"
        assert type(exc) is cls or isinstance(exc, cls), type(exc)
        assert re.search(pattern, str(exc)), str(exc)
        assert "\n" not in str(exc)  # one sentence, no traceback text
    else:
        pytest.fail("no error raised")


def test_the_table_covers_the_cases_of_issue_15():
    # 16 internal errors and 14 silent/misleading results, plus the messages of item 5.
    assert len(CASES) >= 30


def test_render_checks_concrete_values_but_still_differentiates():
    """Values JAX traces (grad, jacfwd, jit) are not known when the renderer is
    called: only their shape is checked, so derivatives still work."""
    scene = SCENE

    def total(rho):
        return jnp.sum(fitter.render({"lambert.rho_d": rho, "phong.e": 10.0}, scene))

    g = jax.grad(total)(0.5)
    assert np.isfinite(g) and g > 0
    J = jax.jacfwd(total)(jnp.array([0.5, 0.4, 0.3]))
    assert J.shape == (3,) and np.all(np.isfinite(J))
    assert np.isfinite(jax.jit(total)(0.5))
    with pytest.raises(MaterialError, match=r"^lambert\.rho_d: expected 3 value\(s\), got 2"):
        jax.grad(total)(jnp.array([0.5, 0.4]))


def test_a_valid_call_with_numpy_scalars_and_lists_still_fits():
    """The checks accept what the config accepts: NumPy integers and floats,
    nested lists as the target, a (H, W, 3) weight array."""
    truth = {"lambert.rho_d": [0.6, 0.4, 0.2]}
    target = np.asarray(fitter.render(truth, SCENE))
    r = fitter.fit(target.tolist(), SCENE, "lambert", n_starts=np.int64(1),
                   max_steps=np.int32(50), rtol=np.float64(1e-6),
                   weights=np.ones((16, 16, 3)), dtype="float64")
    assert r.status == "converged", r.message
    np.testing.assert_allclose(r.params["lambert.rho_d"], truth["lambert.rho_d"], rtol=1e-6)
