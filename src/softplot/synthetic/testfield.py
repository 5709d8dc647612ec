"""A 49-point spatial test field (as Preuss's, Warsaw) photographed by a terrestrial camera.

Object frame: X to the right along the room, Y the viewing direction (depth), Z up, metres.
The 7 x 7 targets stand at depths of 10-38 m in front of the camera stations (Preuss: 10 to
40 m), spread over about 40 m x 18 m so that they fill the wide-angle format. Camera
stations stand on a line across the room at ``Y = 0``; *convergent* photos look at the
centre of the field from stations up to +-12 m apart, *rolled* photos are turned by 0, 90,
180 and 270 degrees about the optical axis (the two ingredients that decorrelate the
principal point from the exterior orientation).
Default camera: a wide-angle Wild P-31 (c = 45.3 mm, 4 x 5 in plates: 120 x 96 mm format),
radial distortion k1 = -3e-7 mm^-2 (-65 um at r = 60 mm); the UMK 10/1318 (c = 99.5 mm,
166 x 120 mm) is one ``intrinsics=..., format_mm=(166, 120)`` away.

The target coordinates are known with standard error ``control_sigma_m`` (theodolite
intersection in the paper); the generated control is the truth plus that noise.
"""

from __future__ import annotations

import numpy as np

from softplot.synthetic.network import Network, look_at, observe, perturb_eo

__all__ = ["make_testfield", "TRUE_INTRINSICS"]

#: true interior orientation of the synthetic camera: c, x0, y0 (mm), k1 (mm^-2) ... b2
TRUE_INTRINSICS = np.array([45.312, 0.0125, -0.0207, -3.0e-7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
#: certificate values given to the adjustment as the start
GIVEN_INTRINSICS = np.array([45.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def field_points(seed: int = 0) -> np.ndarray:
    """The 49 target coordinates (m), row-major 7 x 7 from the top-left as seen from Y=0."""
    rng = np.random.default_rng(1000 + seed)
    X, Z = np.meshgrid(np.linspace(-20.0, 20.0, 7), np.linspace(12.0, -6.0, 7))
    Y = 10.0 + 28.0 * rng.random(X.shape)
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    P[:, :2] += rng.normal(0, 0.3, (49, 2))
    return P


def make_testfield(
    n_photos: int = 24,
    convergent: bool = True,
    rolled: bool = True,
    noise_um: float = 2.0,
    control_sigma_m: float = 0.00005,
    intrinsics=None,
    given=None,
    format_mm=(120.0, 96.0),
    seed: int = 0,
    approx_sigma=(0.3, 0.02),
    depth_scale: float = 1.0,
    field_seed: int | None = None,
) -> Network:
    """Photos of the 49-point test field with exact truth.

    Parameters
    ----------
    n_photos : int
        Number of photos (stations cycle over 4 positions and, when ``rolled``, 4 rolls).
    convergent : bool
        Stations up to +-6 m apart all looking at the field centre; else parallel axes
        along +Y from stations +-3 m apart.
    rolled : bool
        Rolls 0/90/180/270 degrees; else all upright.
    noise_um : float
        Image noise, um (film).
    control_sigma_m : float
        Standard error of the known target coordinates (m); 0 gives exact, fixed control.
    intrinsics, given : array (10,), optional
        True interior orientation / start values (default :data:`TRUE_INTRINSICS` /
        ``GIVEN_INTRINSICS``).
    format_mm : (w, h)
    seed : int
    approx_sigma : (metres, radians)
        Perturbation of the approximate exterior orientations.
    depth_scale : float
        Scales the depth spread of the field (< 1 flattens it: a weak geometry for c).
    field_seed : int, optional
        Seed of the target layout (default ``seed``).

    Returns
    -------
    Network
    """
    rng = np.random.default_rng(seed)
    intr = np.asarray(TRUE_INTRINSICS if intrinsics is None else intrinsics, float)
    giv = np.asarray(GIVEN_INTRINSICS if given is None else given, float)
    P = field_points(seed if field_seed is None else field_seed)
    if depth_scale != 1.0:
        P[:, 1] = 25.0 + (P[:, 1] - 25.0) * depth_scale
    centre = np.array([0.0, 25.0, 2.0])
    xs = [-12.0, 12.0, -4.0, 4.0] if convergent else [-3.0, 3.0, -1.0, 1.0]
    rolls = np.deg2rad([0.0, 90.0, 180.0, 270.0]) if rolled else np.zeros(4)
    X0, M = [], []
    for i in range(n_photos):
        C = np.array([xs[i % 4], 0.0, 1.2 + 0.6 * ((i // 4) % 3)])
        C += rng.normal(0, 0.05, 3)
        target = centre if convergent else C + np.array([0.0, 25.0, 0.8])
        roll = rolls[(i + i // 4) % 4]
        X0.append(C)
        M.append(look_at(C, target, roll=roll))
    X0, M = np.array(X0), np.array(M)
    fm = [tuple(format_mm)]
    op, oq, xy_true = observe(intr[None], np.zeros(n_photos, int), X0, M, P, fm, 0, rng)
    noise = noise_um / 1000.0
    xy = xy_true + rng.normal(0, noise, xy_true.shape)
    Xa, ang = perturb_eo(X0, M, rng, *approx_sigma)
    ctl_sig = np.full((49, 3), float(control_sigma_m))
    control = P + rng.normal(0, control_sigma_m, P.shape) if control_sigma_m > 0 else P.copy()
    return Network(
        camera_names=["P31-wide"],
        intr_true=intr[None].copy(),
        intr_given=giv[None].copy(),
        format_mm=fm,
        photo_names=[f"T{i + 1:02d}" for i in range(n_photos)],
        photo_camera=np.zeros(n_photos, int),
        X0_true=X0,
        M_true=M,
        X0_approx=Xa,
        angles_approx=ang,
        point_names=[f"{i + 1:02d}" for i in range(49)],
        XYZ_true=P,
        XYZ_approx=control.copy(),
        control=control,
        control_sigma=ctl_sig,
        check=np.zeros(49, bool),
        obs_photo=op,
        obs_point=oq,
        xy=xy,
        xy_true=xy_true,
        sigma_xy=noise if noise > 0 else 0.001,
        info={"kind": "testfield", "convergent": convergent, "rolled": rolled, "seed": seed},
    )


def make_series(
    n_series: int = 3,
    photos_per_series: int = 12,
    spread_um=(8.0, 10.0, 7.0),
    seed: int = 0,
    **kwargs,
) -> Network:
    """Several series of photos of the test field, each with its own interior orientation.

    As Preuss's repeatability experiment: every series (one plate loading / one day) shifts
    ``x0, y0, c`` by normal deviates of ``spread_um`` (um). All photos refer to one camera;
    ``info["series"]`` labels every photo and ``info["series_truth"]`` (n_series, 10) holds the
    true interior orientation of each series.
    """
    rng = np.random.default_rng(5000 + seed)
    base = np.asarray(kwargs.pop("intrinsics", TRUE_INTRINSICS), float)
    parts, truths = [], []
    for s in range(n_series):
        t = base.copy()
        t[[1, 2, 0]] += rng.normal(0, 1, 3) * np.asarray(spread_um)[[0, 1, 2]] / 1000.0
        truths.append(t)
        parts.append(
            make_testfield(
                n_photos=photos_per_series,
                intrinsics=t,
                seed=seed * 100 + s,
                field_seed=seed,
                **kwargs,
            )
        )
    first = parts[0]
    F = sum(len(p.photo_names) for p in parts)
    off = np.cumsum([0] + [len(p.photo_names) for p in parts])
    names = [f"S{s + 1}-{n}" for s, p in enumerate(parts) for n in p.photo_names]
    labels = [f"S{s + 1}" for s, p in enumerate(parts) for _ in p.photo_names]
    return Network(
        camera_names=first.camera_names,
        intr_true=first.intr_true,
        intr_given=first.intr_given,
        format_mm=first.format_mm,
        photo_names=names,
        photo_camera=np.zeros(F, int),
        X0_true=np.vstack([p.X0_true for p in parts]),
        M_true=np.vstack([p.M_true for p in parts]),
        X0_approx=np.vstack([p.X0_approx for p in parts]),
        angles_approx=np.vstack([p.angles_approx for p in parts]),
        point_names=first.point_names,
        XYZ_true=first.XYZ_true,
        XYZ_approx=first.XYZ_approx,
        control=first.control,
        control_sigma=first.control_sigma,
        check=first.check,
        obs_photo=np.concatenate([p.obs_photo + off[s] for s, p in enumerate(parts)]),
        obs_point=np.concatenate([p.obs_point for p in parts]),
        xy=np.vstack([p.xy for p in parts]),
        xy_true=np.vstack([p.xy_true for p in parts]),
        sigma_xy=first.sigma_xy,
        info={"kind": "testfield-series", "series": labels, "series_truth": np.array(truths)},
    )
