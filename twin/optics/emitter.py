"""LED angular emission profiles Psi (paper Eq. 1; reference §1.1, §2.8).

The forward model uses the LED's relative radiant intensity towards a direction at angle theta from its
emission normal, A(theta) = Psi(theta, phi) * cos(theta) (Eq. 1 writes the cosine separately as
(-wi . n_l)+). Two parametric families, chosen per rig (`Rig.led_profile`), parameters per LED
(`LEDs.profile`, 8 floats, as in the reference's lights_angular.npy):

``cosine`` (default)
    A = cos(theta)^p with p = profile[0]. p = 1 is a Lambertian emitter behind its diffuser (Psi = 1);
    p = 0 an isotropic point source (Psi = 1/cos), used for the Mitsuba point-light check.
``polynomial``
    Psi = cos^2(phi) P_u(theta) + sin^2(phi) P_v(theta), clamped at 0, with two cubics
    P(theta) = c0 + c1 theta + c2 theta^2 + c3 theta^3 (theta in radians): profile[0:4] along the board's
    column direction u, profile[4:8] along its row direction v, phi measured from u. The reference names
    "two cubic polynomials per LED" but does not release their form or values; this is our
    parametrisation of that form (an elliptical beam, as diffused SMD LEDs have).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

PROFILE_COSINE = 0
PROFILE_POLYNOMIAL = 1
PROFILE_MODES = {"cosine": PROFILE_COSINE, "polynomial": PROFILE_POLYNOMIAL}


@wp.func
def _cubic(c0: Any, c1: Any, c2: Any, c3: Any, x: Any):
    return c0 + x * (c1 + x * (c2 + x * c3))


@wp.func
def led_intensity(emit: Any, led_n: Any, led_u: Any, prof: wp.array2d(dtype=Any), l: int, mode: int):
    """A(theta) = Psi * cos(theta) of LED l towards the unit direction `emit` (from the LED outwards)."""
    c = wp.dot(emit, led_n)
    zero = type(c)(0.0)
    if c <= zero:
        return zero
    if mode == PROFILE_POLYNOMIAL:
        theta = wp.acos(wp.min(c, type(c)(1.0)))
        eu = wp.dot(emit, led_u)
        ev = wp.dot(emit, wp.cross(led_n, led_u))
        s = eu * eu + ev * ev
        cu2 = type(c)(0.5)  # on the axis phi is undefined; both cubics agree there for a smooth beam
        if s > type(c)(1.0e-12):
            cu2 = eu * eu / s
        pu = _cubic(prof[l, 0], prof[l, 1], prof[l, 2], prof[l, 3], theta)
        pv = _cubic(prof[l, 4], prof[l, 5], prof[l, 6], prof[l, 7], theta)
        return wp.max(cu2 * pu + (type(c)(1.0) - cu2) * pv, zero) * c
    p = prof[l, 0]
    if p == type(c)(1.0):
        return c  # exact Lambertian: no pow rounding, so the OpenSVBRDF convention is bit-faithful
    return wp.pow(c, p)


def led_u_axes(rig) -> np.ndarray:
    """(L, 3) unit in-plane axis of each LED along its board's columns (the u axis of the polynomial
    profile): the least-squares column step of the board's LED grid, made orthogonal to the LED normal."""
    leds = rig.leds
    out = np.zeros((rig.num_leds, 3))
    for b in range(len(rig.boards)):
        sel = np.flatnonzero(leds.board == b)
        if sel.size == 0:
            continue
        A = np.stack([np.ones(sel.size), leds.col[sel], leds.row[sel]], axis=1).astype(float)
        coef, *_ = np.linalg.lstsq(A, leds.positions[sel], rcond=None)
        u = coef[1] if np.linalg.norm(coef[1]) > 1e-9 else np.cross(leds.normals[sel[0]], [0.0, 0.0, 1.0])
        if np.linalg.norm(u) < 1e-9:
            u = np.array([1.0, 0.0, 0.0])
        out[sel] = u
    n = leds.normals
    out -= np.einsum("ij,ij->i", out, n)[:, None] * n
    return out / np.linalg.norm(out, axis=1, keepdims=True)
