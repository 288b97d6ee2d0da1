"""Shared test set-up: float64 JAX with strict dtype promotion, a reproducible hypothesis profile, quadrature.

The hemisphere / sphere quadrature here is the one every energy test uses:
Gauss-Legendre in the polar angle theta (measured from an axis) and the
periodic midpoint rule in phi, with weights sin(theta) dtheta dphi
(the lecture's d omega = sin theta d theta d phi). It is validated against the
lecture's closed forms in ``test_closed_forms.py``.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)
# As optimistix's own suite: no silent dtype promotion (a float32 fit stays float32).
jax.config.update("jax_numpy_dtype_promotion", "strict")

settings.register_profile(
    "ci", derandomize=True, deadline=None, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("ci")


def orthonormal_frame(axis):
    """(t, b, a): two unit tangents and the unit axis, each (3,), right-handed."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = np.cross(helper, a)
    t /= np.linalg.norm(t)
    return t, np.cross(a, t), a


def spherical_quadrature(axis, n_theta, n_phi, theta_max=np.pi / 2):
    """Nodes and weights for integrals over directions within ``theta_max`` of ``axis``.

    Returns:
        dirs (n_theta * n_phi, 3) unit vectors and weights (n_theta * n_phi,)
        in steradians; ``sum(weights * f(dirs))`` approximates the integral of
        f d omega over the cap theta <= theta_max (the hemisphere by default).
    """
    x, w = np.polynomial.legendre.leggauss(n_theta)
    theta = 0.5 * theta_max * (x + 1.0)
    w_theta = 0.5 * theta_max * w * np.sin(theta)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    t, b, a = orthonormal_frame(axis)
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    cp, sp = np.cos(phi)[None, :, None], np.sin(phi)[None, :, None]
    dirs = st * (cp * t + sp * b) + ct * a
    weights = np.broadcast_to(w_theta[:, None] * (2.0 * np.pi / n_phi), (n_theta, n_phi))
    return dirs.reshape(-1, 3), weights.reshape(-1)


def fresnel_reference(cos_i, eta):
    """The lecture's unpolarised F_r, written independently of ``fitter`` (NumPy,
    no total-internal-reflection branch): cos_t = sqrt(1 - (1 - cos_i^2)/eta^2)."""
    cos_t = np.sqrt(1.0 - (1.0 - cos_i**2) / eta**2)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return 0.5 * (rp**2 + rs**2)


@pytest.fixture(scope="session")
def quadrature():
    return spherical_quadrature


@pytest.fixture
def finer_builds(monkeypatch):
    """[(supersampling, thread name)] of each geometry the stated discretisation
    error (``fitter.fit._discretisation``) builds while the test runs."""
    import threading

    from fitter.fit import _discretisation

    made_on = []
    build = _discretisation.build_geometry

    def recorded(scene, *args, **kwargs):
        made_on.append((scene.supersampling, threading.current_thread().name))
        return build(scene, *args, **kwargs)

    monkeypatch.setattr(_discretisation, "build_geometry", recorded)
    return made_on
