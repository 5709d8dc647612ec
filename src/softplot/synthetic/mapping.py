"""The exact geometry of a synthetic scan: film deformation and scanner placement.

A synthetic scan is made in three steps, and its truth mapping is their composition::

    undeformed film mm (u) --deformation--> deformed film mm (d) --scanner--> pixel (p)

* **Deformation** (film mm -> film mm, both x right, y up): a uniform shrinkage plus a smooth
  displacement field, a sum of ``K`` plane sinusoids with vector amplitudes::

      d = (1 - shrink_ppm * 1e-6) * u + sum_k a_k * sin(2 pi f_k . u + phi_k)

  ``a_k`` (mm, 2-vector), ``f_k`` (cycles per mm, 2-vector), ``phi_k`` (rad). Wavelengths are
  of the order of the film format, so the field is smooth over a reseau mesh but not affine.
* **Scanner** (film mm -> pixel): an affine ``p = A d + t`` with
  ``A = diag(sx, sy) @ [[1, 0], [0, -1]] @ R(theta)``, ``sx, sy = dpi / 25.4 * (1 +- a / 2)``
  (a = anisotropy in ppm * 1e-6), ``R(theta)`` a counter-clockwise rotation of the film frame
  by ``rotation_deg`` (the photo appears turned counter-clockwise on screen), and ``t`` the
  pixel position of the film origin (offset and crop included). Pixel: x right (column),
  y down (row), (0, 0) the centre of the top-left pixel.

The inverse of the deformation is found by Newton's method, vectorised over points; it
converges to 1e-13 mm in a few steps because the field's gradient is of the order of 1e-3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from softplot.errors import SoftplotError

#: identifies the formulas above in truth files
MODEL = "softplot-synth-1: d = (1 - shrink) u + sum a_k sin(2 pi f_k.u + phi_k); p = A d + t"


def _as_points(xy: Any, what: str) -> tuple[np.ndarray, tuple[int, ...]]:
    a = np.asarray(xy, dtype=float)
    if a.shape[-1:] != (2,):
        raise SoftplotError(f"{what} must have shape (..., 2), got {a.shape}")
    return a.reshape(-1, 2), a.shape


@dataclass(frozen=True)
class Deformation:
    """Uniform shrinkage plus a sum of plane sinusoids (film mm -> deformed film mm).

    Attributes
    ----------
    shrink_ppm : float
        Uniform shrinkage in parts per million (positive: the film got smaller).
    amp : ndarray, shape (K, 2)
        Vector amplitude of each sinusoid, film mm.
    freq : ndarray, shape (K, 2)
        Spatial frequency vector of each sinusoid, cycles per film mm.
    phase : ndarray, shape (K,)
        Phase of each sinusoid, radians.
    """

    shrink_ppm: float = 0.0
    amp: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    freq: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    phase: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def scale(self) -> float:
        """The uniform scale factor ``1 - shrink_ppm * 1e-6``."""
        return 1.0 - self.shrink_ppm * 1e-6

    @classmethod
    def random(
        cls,
        format_mm: tuple[float, float],
        amplitude_um: float,
        shrink_ppm: float,
        rng: np.random.Generator,
        components: int = 4,
    ) -> "Deformation":
        """A seeded random smooth field whose largest displacement over the format is exact.

        Parameters
        ----------
        format_mm : (float, float)
            Film format (width, height) in mm; the field is normalised over this rectangle
            centred on the film origin.
        amplitude_um : float
            The largest displacement length (micrometres) of the sinusoidal field over the
            format (uniform shrinkage not included), evaluated on a 129 x 129 grid.
        shrink_ppm : float
            Uniform shrinkage, parts per million.
        rng : numpy.random.Generator
            Source of the field's parameters.
        components : int
            Number of sinusoids.
        """
        size = float(max(format_mm))
        k = int(components)
        wavelength = size * rng.uniform(0.9, 2.5, k)
        angle = rng.uniform(0.0, 2 * math.pi, k)
        freq = np.column_stack([np.cos(angle), np.sin(angle)]) / wavelength[:, None]
        direction = rng.uniform(0.0, 2 * math.pi, k)
        weight = rng.uniform(0.5, 1.0, k)
        amp = weight[:, None] * np.column_stack([np.cos(direction), np.sin(direction)])
        phase = rng.uniform(0.0, 2 * math.pi, k)
        unit = cls(shrink_ppm=float(shrink_ppm), amp=amp, freq=freq, phase=phase)
        if amplitude_um <= 0 or k == 0:
            return cls(shrink_ppm=float(shrink_ppm))
        peak = unit.max_displacement(format_mm)
        return cls(
            shrink_ppm=float(shrink_ppm),
            amp=amp * (amplitude_um * 1e-3 / peak),
            freq=freq,
            phase=phase,
        )

    def displacement(self, u: np.ndarray) -> np.ndarray:
        """Smooth displacement field (mm) at undeformed film points ``u`` (N, 2) mm."""
        u = np.asarray(u, float)
        if len(self.phase) == 0:
            return np.zeros_like(u)
        arg = 2 * math.pi * (u @ self.freq.T) + self.phase  # (N, K)
        return np.sin(arg) @ self.amp

    def forward(self, u: np.ndarray) -> np.ndarray:
        """Deformed film mm (N, 2) of undeformed film points ``u`` (N, 2) mm."""
        u = np.asarray(u, float)
        return self.scale * u + self.displacement(u)

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """d(deformed film)/d(undeformed film) at ``u`` (N, 2) mm, shape (N, 2, 2)."""
        u = np.asarray(u, float)
        jac = np.zeros((len(u), 2, 2))
        jac[:, 0, 0] = jac[:, 1, 1] = self.scale
        if len(self.phase):
            arg = 2 * math.pi * (u @ self.freq.T) + self.phase
            c = np.cos(arg) * (2 * math.pi)  # (N, K)
            # J[i, a, b] = sum_k amp[k, a] * c[i, k] * freq[k, b]
            jac += np.einsum("ik,ka,kb->iab", c, self.amp, self.freq)
        return jac

    def inverse(self, d: np.ndarray, tol: float = 1e-13, max_iter: int = 30) -> np.ndarray:
        """Undeformed film mm (N, 2) of deformed film points ``d`` (N, 2) mm (Newton)."""
        d = np.asarray(d, float)
        u = d / self.scale
        if len(self.phase) == 0:
            return u
        active = np.arange(len(d))
        for _ in range(max_iter):
            ua = u[active]
            r = self.forward(ua) - d[active]
            jac = self.jacobian(ua)
            det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
            dx = (jac[:, 1, 1] * r[:, 0] - jac[:, 0, 1] * r[:, 1]) / det
            dy = (-jac[:, 1, 0] * r[:, 0] + jac[:, 0, 0] * r[:, 1]) / det
            u[active, 0] -= dx
            u[active, 1] -= dy
            step = np.maximum(np.abs(dx), np.abs(dy))
            active = active[step > tol]
            if active.size == 0:
                break
        return u

    def max_displacement(self, format_mm: tuple[float, float], n: int = 129) -> float:
        """Largest displacement length (mm) of the field on an n x n grid over the format."""
        w, h = format_mm
        gx, gy = np.meshgrid(np.linspace(-w / 2, w / 2, n), np.linspace(-h / 2, h / 2, n))
        disp = self.displacement(np.column_stack([gx.ravel(), gy.ravel()]))
        return float(np.max(np.hypot(disp[:, 0], disp[:, 1]))) if len(disp) else 0.0

    def to_dict(self) -> dict:
        """JSON-ready parameters (full double precision)."""
        return {
            "shrink_ppm": float(self.shrink_ppm),
            "components": [
                {
                    "amp_mm": [float(a[0]), float(a[1])],
                    "freq_per_mm": [float(f[0]), float(f[1])],
                    "phase_rad": float(p),
                }
                for a, f, p in zip(self.amp, self.freq, self.phase, strict=False)
            ],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Deformation":
        """Inverse of :meth:`to_dict`."""
        comps = d.get("components", [])
        return cls(
            shrink_ppm=float(d.get("shrink_ppm", 0.0)),
            amp=np.array([c["amp_mm"] for c in comps], float).reshape(-1, 2),
            freq=np.array([c["freq_per_mm"] for c in comps], float).reshape(-1, 2),
            phase=np.array([c["phase_rad"] for c in comps], float).reshape(-1),
        )


@dataclass(frozen=True)
class Scanner:
    """The scanner's affine placement of the deformed film: ``p = A d + t``.

    Attributes
    ----------
    dpi : float
        Nominal resolution (dots per inch).
    rotation_deg : float
        Counter-clockwise rotation of the film frame as seen on screen, degrees.
    anisotropy_ppm : float
        x/y scale difference: ``sx = s (1 + a/2)``, ``sy = s (1 - a/2)``, ``s = dpi / 25.4``.
    tx, ty : float
        Pixel position of the deformed film origin.
    """

    dpi: float
    rotation_deg: float = 0.0
    anisotropy_ppm: float = 0.0
    tx: float = 0.0
    ty: float = 0.0

    @property
    def matrix(self) -> np.ndarray:
        """The 2 x 2 matrix ``A`` (pixel per deformed film mm)."""
        s = self.dpi / 25.4
        a = self.anisotropy_ppm * 1e-6
        th = math.radians(self.rotation_deg)
        c, sn = math.cos(th), math.sin(th)
        rot = np.array([[c, -sn], [sn, c]])
        return np.diag([s * (1 + a / 2), -s * (1 - a / 2)]) @ rot

    def forward(self, d: np.ndarray) -> np.ndarray:
        """Pixel (N, 2) of deformed film points ``d`` (N, 2) mm."""
        return np.asarray(d, float) @ self.matrix.T + np.array([self.tx, self.ty])

    def inverse(self, p: np.ndarray) -> np.ndarray:
        """Deformed film mm (N, 2) of pixel points ``p`` (N, 2)."""
        inv = np.linalg.inv(self.matrix)
        return (np.asarray(p, float) - np.array([self.tx, self.ty])) @ inv.T

    def to_dict(self) -> dict:
        """JSON-ready parameters, with the matrix for convenience."""
        return {
            "dpi": float(self.dpi),
            "rotation_deg": float(self.rotation_deg),
            "anisotropy_ppm": float(self.anisotropy_ppm),
            "tx_px": float(self.tx),
            "ty_px": float(self.ty),
            "matrix_px_per_mm": self.matrix.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Scanner":
        """Inverse of :meth:`to_dict`."""
        return cls(
            dpi=float(d["dpi"]),
            rotation_deg=float(d.get("rotation_deg", 0.0)),
            anisotropy_ppm=float(d.get("anisotropy_ppm", 0.0)),
            tx=float(d["tx_px"]),
            ty=float(d["ty_px"]),
        )


@dataclass(frozen=True)
class TruthMapping:
    """The complete, exact mapping of a synthetic scan: undeformed film mm <-> pixel.

    ``film_to_pixel`` applies the deformation and then the scanner; ``pixel_to_film`` inverts
    both (the deformation by Newton's method). Both are vectorised over points and accept
    any array of shape (..., 2); the result has the same shape.
    """

    deformation: Deformation
    scanner: Scanner

    def film_to_pixel(self, xy_mm: Any) -> np.ndarray:
        """Pixel coordinates (..., 2) of undeformed film points ``xy_mm`` (..., 2) mm."""
        u, shape = _as_points(xy_mm, "xy_mm")
        return self.scanner.forward(self.deformation.forward(u)).reshape(shape)

    def pixel_to_film(self, xy_px: Any) -> np.ndarray:
        """Undeformed film mm (..., 2) of pixel points ``xy_px`` (..., 2)."""
        p, shape = _as_points(xy_px, "xy_px")
        return self.deformation.inverse(self.scanner.inverse(p)).reshape(shape)

    def film_to_deformed(self, xy_mm: Any) -> np.ndarray:
        """Deformed film mm (..., 2) of undeformed film points (..., 2) mm."""
        u, shape = _as_points(xy_mm, "xy_mm")
        return self.deformation.forward(u).reshape(shape)

    def jacobian(self, xy_mm: Any) -> np.ndarray:
        """d(pixel)/d(film mm) at undeformed film points (N, 2): shape (N, 2, 2)."""
        u, _ = _as_points(xy_mm, "xy_mm")
        return np.einsum("ab,nbc->nac", self.scanner.matrix, self.deformation.jacobian(u))

    def to_dict(self) -> dict:
        """The ``mapping`` block of a truth file."""
        return {
            "model": MODEL,
            "deformation": self.deformation.to_dict(),
            "scanner": self.scanner.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "TruthMapping":
        """A mapping from the ``mapping`` block of a truth file."""
        try:
            return cls(
                deformation=Deformation.from_dict(d.get("deformation", {})),
                scanner=Scanner.from_dict(d["scanner"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SoftplotError(f"malformed truth mapping: {exc!r}") from None

    @classmethod
    def from_truth(cls, truth: dict | str | Any) -> "TruthMapping":
        """A mapping from a truth dict (as returned by ``render_scan``) or a truth JSON path."""
        if not isinstance(truth, dict):
            import json
            from pathlib import Path

            p = Path(truth)
            try:
                truth = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise SoftplotError(f"{p}: cannot read truth file: {exc}") from None
        if "mapping" not in truth:
            raise SoftplotError("truth has no 'mapping' block")
        return cls.from_dict(truth["mapping"])
