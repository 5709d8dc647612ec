"""Synthetic textured Rollei 6006 stereo pairs with exact truth, shared by the matching tests.

:func:`make_scene` renders (once per process, cached by its arguments) the two scans of the
``softplot demo`` pair over a fractal-textured hill (optionally with a building and a blank
area), writes them as TIFFs with their mark detections, and returns the truth: each scan's
:class:`TruthMapping`, the interior orientation and the :class:`TexturedTerrain` of each
photo, so that a left pixel's true right pixel is known exactly.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from softplot.camera import load_camera
from softplot.orientation.interior import InteriorOrientation
from softplot.synthetic import ScanSpec, TruthMapping, render_scan
from softplot.synthetic.files import write_image
from softplot.synthetic.stereo import TexturedTerrain, rollei_pair

CAMERA = "rollei-6006"


@lru_cache(maxsize=4)
def make_scene(folder: str, dpi: float = 600.0, box=None, blank=None, seed: int = 6006):
    from softplot.io import Scan, fingerprint
    from softplot.marks import detect

    cam = load_camera(CAMERA)
    io = InteriorOrientation(cam)
    pair = rollei_pair(seed)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    terr, tms, paths, dets = [], [], [], []
    for k in range(2):
        t = TexturedTerrain(pair, k, io, seed=seed, box=box, blank=blank)
        spec = ScanSpec(dpi=dpi, scene=t, deform_um=12.0, shrink_ppm=150.0 + 100 * k,
                        rotation_deg=(0.35, -0.5)[k], offset_px=((3.2, -2.1), (-4.4, 1.7))[k],
                        noise_sigma=0.01, blur_sigma_px=0.8)
        side = ("left", "right")[k]
        p, dp, tp = (out / f"{side}{e}" for e in (".tif", ".detection.json", ".truth.json"))
        if not (p.exists() and dp.exists() and tp.exists()):  # a folder of this scene only
            image, truth = render_scan(cam, spec, seed=seed + k)
            write_image(p, image, dpi, "tif", overwrite=True)
            det = detect(Scan.from_array(image, dpi=dpi), cam).to_json()
            det["scan"] = fingerprint(p)
            dp.write_text(json.dumps(det) + "\n", encoding="utf-8")
            tp.write_text(json.dumps(truth) + "\n", encoding="utf-8")
        truth = json.loads(tp.read_text(encoding="utf-8"))
        terr.append(t)
        tms.append(TruthMapping.from_truth(truth))
        paths.append(p)
        dets.append(dp)
    return SimpleNamespace(camera=cam, io=io, pair=pair, terrain=terr, mapping=tms,
                           scans=paths, detections=dets, dpi=dpi, folder=out)


@lru_cache(maxsize=2)
def make_strip(folder: str, dpi: float = 600.0, n: int = 3, seed: int = 6006,
               pair_folder: str | None = None):
    """A strip of ``n`` Rollei scans (60 % forward overlap) over the textured hill: the
    scans, their detections and the truth (``pair``: a SyntheticPair of ``n`` stations).
    Photos 1 and 2 are :func:`make_scene`'s pair (taken from ``pair_folder`` when given)."""
    import dataclasses

    from softplot.io import Scan, fingerprint
    from softplot.marks import detect

    cam = load_camera(CAMERA)
    io = InteriorOrientation(cam)
    p2 = rollei_pair(seed)
    rng = np.random.default_rng(seed + 7)
    b = p2.X0[1] - p2.X0[0]
    X0 = np.vstack([p2.X0[0] + k * b for k in range(n)])
    X0[2:] += rng.uniform(-2, 2, (n - 2, 3))
    angles = np.vstack([p2.angles, np.deg2rad(rng.uniform(-1.5, 1.5, (n - 2, 3)))])
    pair = dataclasses.replace(p2, X0=X0, angles=angles, c=np.full(n, p2.c[0]),
                               x0=np.zeros(n), y0=np.zeros(n),
                               deform=np.repeat(p2.deform[:1], n, axis=0))
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    paths, dets = [], []
    for k in range(n):
        t = TexturedTerrain(pair, k, io, seed=seed)
        spec = ScanSpec(dpi=dpi, scene=t, deform_um=12.0, shrink_ppm=150.0 + 100 * (k % 2),
                        rotation_deg=(0.35, -0.5, 0.2, -0.3)[k % 4],
                        offset_px=((3.2, -2.1), (-4.4, 1.7))[k % 2],
                        noise_sigma=0.01, blur_sigma_px=0.8)
        p, dp = out / f"photo{k + 1}.tif", out / f"photo{k + 1}.detection.json"
        if k < 2 and not (p.exists() and dp.exists()) and pair_folder is not None:
            # photos 1 and 2 are the scans of make_scene (the same stations and settings)
            sc = make_scene(str(pair_folder), dpi, seed=seed)
            p.write_bytes(sc.scans[k].read_bytes())
            dp.write_bytes(sc.detections[k].read_bytes())
        if not (p.exists() and dp.exists()):
            image, _ = render_scan(cam, spec, seed=seed + k)
            write_image(p, image, dpi, "tif", overwrite=True)
            det = detect(Scan.from_array(image, dpi=dpi), cam).to_json()
            det["scan"] = fingerprint(p)
            dp.write_text(json.dumps(det) + "\n", encoding="utf-8")
        paths.append(p)
        dets.append(dp)
    return SimpleNamespace(camera=cam, pair=pair, scans=paths, detections=dets, dpi=dpi)


def true_right(scene, left_px) -> tuple[np.ndarray, np.ndarray]:
    """Exact right pixels of left pixels (N, 2), and whether the point is seen by both."""
    film = scene.mapping[0].pixel_to_film(np.asarray(left_px, float).reshape(-1, 2))
    photo = scene.io.film_to_photo(film)
    P = scene.terrain[0].intersect(photo)
    ph2 = scene.pair.photo(1, P)
    px = scene.mapping[1].film_to_pixel(scene.io.photo_to_film(ph2))
    return px, scene.terrain[1].visible(P)


def true_session(scene, folder) -> Path:
    """A plotting session of the scene's scans with the TRUE exterior orientation."""
    from softplot.pipeline.session import Session, scan_photo_map
    from softplot.stereo.model import OrientedPhoto, StereoModel

    folder = Path(folder)
    if (folder / "session.json").exists():
        return folder
    photos = []
    for k, side in enumerate(("left", "right")):
        m = scan_photo_map(scene.scans[k], scene.camera, str(scene.detections[k]))
        photos.append(OrientedPhoto(scene.pair.X0[k], scene.pair.angles[k], scene.pair.c[k],
                                    0.0, 0.0, to_photo=m, to_film=m.inverse, name=side))
    Session.create(folder, StereoModel(*photos)).close()
    return folder


def run_cli(args):
    """``softplot ARGS`` in-process: ``(exit code, output)``; a SoftplotError becomes
    ``(2, "softplot: error: ...")`` as the console entry point prints it, anything else raises."""
    from click.testing import CliRunner

    from softplot.cli import cli
    from softplot.errors import SoftplotError

    r = CliRunner().invoke(cli, args, standalone_mode=False, catch_exceptions=True)
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        if isinstance(r.exception, SoftplotError):
            return 2, f"softplot: error: {r.exception}"
        raise r.exception
    return r.exit_code or 0, r.output
