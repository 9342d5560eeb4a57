"""Procedural inputs for the demo and notebooks (no files needed)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxsh


def procedural_sky(height: int, width: int, sun_dir=(0.5, 0.3, 0.81), sun_size: float = 0.08, rotation=None):
    """An HDR sky: blue-ish gradient above the horizon, a dim ground, a bright sun lobe.

    Lat-long `(height, width, 3)` in the library frame (+z up). The sun is an
    exponential lobe of angular radius ~`sun_size` (radians) carrying most of
    the energy, so the map is far from band-limited — a fair test of projection.
    With `rotation` R (3, 3), returns the rotated sky, omega -> f(R^T omega).
    """
    d = np.asarray(jaxsh.latlong_directions(height, width, dtype=np.float64))
    if rotation is not None:
        d = d @ np.asarray(rotation, dtype=np.float64)  # rows: R^T omega
    z = d[..., 2:3]
    sky = np.where(z > 0, np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * z), np.array([0.25, 0.2, 0.15]) * (1 + z))
    s = np.asarray(sun_dir, dtype=np.float64)
    s = s / np.linalg.norm(s)
    cosang = np.clip(d @ s, -1, 1)[..., None]
    sun = np.array([60.0, 55.0, 45.0]) * np.exp((cosang - 1.0) / (sun_size**2))
    return jnp.asarray(sky + sun)
