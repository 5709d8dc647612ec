"""Rotation matrices omega-phi-kappa (Wolf & Dewitt), their derivatives and angle units.

Convention (``docs/conventions.md``): sequential rotations omega about x, phi about
y, kappa about z; the matrix

    M = Mk(kappa) @ Mp(phi) @ Mo(omega)

rotates *object* axes into *photo* axes, i.e. ``photo_vector = M @ object_vector``, with

    Mo = [[1, 0, 0], [0, cos o, sin o], [0, -sin o, cos o]]
    Mp = [[cos p, 0, -sin p], [0, 1, 0], [sin p, 0, cos p]]
    Mk = [[cos k, sin k, 0], [-sin k, cos k, 0], [0, 0, 1]]

so that ``m31 = sin(phi)``, ``m32 = -sin(omega) cos(phi)``, ``m33 = cos(omega) cos(phi)``,
``m11 = cos(phi) cos(kappa)``, ``m21 = -cos(phi) sin(kappa)``.

Angles are radians everywhere inside softplot; :func:`to_radians` / :func:`from_radians`
convert at the edges (``"deg"``, ``"gon"`` with 400 gon per turn, ``"rad"``).
"""

from __future__ import annotations

import numpy as np

from softplot.errors import SoftplotError

__all__ = [
    "rotation_matrix",
    "rotation_derivatives",
    "angles_from_matrix",
    "deg2rad",
    "rad2deg",
    "gon2rad",
    "rad2gon",
    "to_radians",
    "from_radians",
    "ANGLE_UNITS",
]

#: angle units accepted at the edges
ANGLE_UNITS = ("rad", "deg", "gon")


def _trig(omega, phi, kappa):
    o, p, k = np.broadcast_arrays(
        np.asarray(omega, dtype=float), np.asarray(phi, dtype=float), np.asarray(kappa, dtype=float)
    )
    return np.sin(o), np.cos(o), np.sin(p), np.cos(p), np.sin(k), np.cos(k)


def _stack(rows, shape):
    out = np.empty(shape + (3, 3))
    for i in range(3):
        for j in range(3):
            out[..., i, j] = rows[i][j]
    return out


def rotation_matrix(omega, phi, kappa) -> np.ndarray:
    """Rotation matrix ``M = Mk @ Mp @ Mo`` (object axes -> photo axes).

    Parameters
    ----------
    omega, phi, kappa : float or array_like
        Angles in radians, broadcast against each other.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``M`` for every broadcast element; ``photo = M @ object``.
    """
    so, co, sp, cp, sk, ck = _trig(omega, phi, kappa)
    rows = (
        (cp * ck, so * sp * ck + co * sk, -co * sp * ck + so * sk),
        (-cp * sk, -so * sp * sk + co * ck, co * sp * sk + so * ck),
        (sp, -so * cp, co * cp),
    )
    return _stack(rows, so.shape)


def rotation_derivatives(omega, phi, kappa) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Partial derivatives ``dM/domega, dM/dphi, dM/dkappa`` of :func:`rotation_matrix`.

    Parameters
    ----------
    omega, phi, kappa : float or array_like
        Angles in radians, broadcast against each other.

    Returns
    -------
    (dMo, dMp, dMk) : tuple of ndarray, each shape (..., 3, 3)
    """
    so, co, sp, cp, sk, ck = _trig(omega, phi, kappa)
    z = np.zeros_like(so)
    d_omega = (
        (z, co * sp * ck - so * sk, so * sp * ck + co * sk),
        (z, -co * sp * sk - so * ck, -so * sp * sk + co * ck),
        (z, -co * cp, -so * cp),
    )
    d_phi = (
        (-sp * ck, so * cp * ck, -co * cp * ck),
        (sp * sk, -so * cp * sk, co * cp * sk),
        (cp, so * sp, -co * sp),
    )
    d_kappa = (
        (-cp * sk, -so * sp * sk + co * ck, co * sp * sk + so * ck),
        (-cp * ck, -so * sp * ck - co * sk, co * sp * ck - so * sk),
        (z, z, z),
    )
    shape = so.shape
    return _stack(d_omega, shape), _stack(d_phi, shape), _stack(d_kappa, shape)


def angles_from_matrix(M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles ``(omega, phi, kappa)`` in radians of a rotation matrix ``M = Mk @ Mp @ Mo``.

    ``phi`` is returned in [-pi/2, pi/2], ``omega`` and ``kappa`` in (-pi, pi]. At the gimbal
    lock ``|phi| = pi/2`` only ``omega +- kappa`` is defined; kappa is then set to 0.

    Parameters
    ----------
    M : array_like, shape (..., 3, 3)
        Rotation matrix (object -> photo axes). It is not re-orthonormalised.

    Returns
    -------
    omega, phi, kappa : ndarray, shape (...)
    """
    M = np.asarray(M, dtype=float)
    if M.shape[-2:] != (3, 3):
        raise SoftplotError(f"angles_from_matrix: expected (...,3,3), got shape {M.shape}")
    m31 = np.clip(M[..., 2, 0], -1.0, 1.0)
    phi = np.arcsin(m31)
    omega = np.arctan2(-M[..., 2, 1], M[..., 2, 2])
    kappa = np.arctan2(-M[..., 1, 0], M[..., 0, 0])
    lock = np.abs(m31) > 1.0 - 1e-12
    if np.any(lock):
        # at phi = +-pi/2 with kappa := 0: m12 = +-sin(omega), m22 = cos(omega)
        omega = np.where(lock, np.arctan2(np.sign(m31) * M[..., 0, 1], M[..., 1, 1]), omega)
        kappa = np.where(lock, 0.0, kappa)
    return omega, phi, kappa


def deg2rad(a):
    """Degrees -> radians."""
    return np.asarray(a, dtype=float) * (np.pi / 180.0)


def rad2deg(a):
    """Radians -> degrees."""
    return np.asarray(a, dtype=float) * (180.0 / np.pi)


def gon2rad(a):
    """Gon (grad, 400 per turn) -> radians."""
    return np.asarray(a, dtype=float) * (np.pi / 200.0)


def rad2gon(a):
    """Radians -> gon (grad, 400 per turn)."""
    return np.asarray(a, dtype=float) * (200.0 / np.pi)


def _check_unit(unit: str) -> str:
    u = unit.lower()
    if u in ("degree", "degrees"):
        u = "deg"
    if u in ("grad", "grads", "gons"):
        u = "gon"
    if u in ("radian", "radians"):
        u = "rad"
    if u not in ANGLE_UNITS:
        raise SoftplotError(f"unknown angle unit {unit!r}; use one of {', '.join(ANGLE_UNITS)}")
    return u


def to_radians(a, unit: str):
    """Convert angles ``a`` given in ``unit`` ("rad", "deg" or "gon") to radians."""
    u = _check_unit(unit)
    return {"rad": lambda v: np.asarray(v, dtype=float), "deg": deg2rad, "gon": gon2rad}[u](a)


def from_radians(a, unit: str):
    """Convert angles ``a`` in radians to ``unit`` ("rad", "deg" or "gon")."""
    u = _check_unit(unit)
    return {"rad": lambda v: np.asarray(v, dtype=float), "deg": rad2deg, "gon": rad2gon}[u](a)
