"""Tie points of a block of scans, as a bundle project (``softplot match SCAN SCAN SCAN ...``).

:func:`match_block`:

1. every pair of scans is matched (:func:`softplot.matching.ties.match_pair`: SIFT, RANSAC,
   least-squares matching, relative orientation with data snooping) on dask.distributed, as
   ``softplot batch`` runs its scans (a LocalCluster of single-threaded worker processes, or
   an existing scheduler); pairs that do not overlap are recorded and skipped;
2. the ties of all pairs are linked into multi-ray points through their SIFT keypoints (a
   scan's keypoints are the same in every pair it is part of); a point whose rays disagree
   (two keypoints of one scan) is dropped;
3. each point is measured anew from one template: the integer pixel of its keypoint in its
   first scan (in the order given), least-squares matched into every other scan that sees it
   (each with its standard deviation); templates of different points never overlap;
4. the bundle project (``docs/bundle.md``): ``cameras.toml`` (the camera's certificate),
   ``photos.csv`` (one photo per scan, orientation left to ``softplot bundle``),
   ``observations.csv`` (film mm through each scan's film correction, ``sx``, ``sy``);
   with ``block.json`` (pairs, points by number of rays) and each pair's ties in
   ``pairs/<left>__<right>/`` (the ``softplot match`` outputs of a pair).

Coordinates: scan pixels (x right, y down, origin at the centre of the top-left pixel); film
mm (x right, y up).
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError
from softplot.matching.ties import MIN_TIES, MatchOptions, _separated, check_outputs

__all__ = ["match_block", "BLOCK_FILES"]

BLOCK_FILES = ("cameras.toml", "photos.csv", "observations.csv", "block.json")


def _pair_task(a: str, b: str, camera: str, det_a, det_b, opts: dict, out: str) -> dict:
    """Worker side: match one pair, write its ties, never raise (a small result dict)."""
    from softplot.cli.match import load_pair
    from softplot.matching.ties import match_pair

    try:
        from softplot.pipeline.batch import _one_thread_in_worker

        _one_thread_in_worker()
        _, scans, maps = load_pair(a, b, camera, det_a, det_b)
        res = match_pair(scans[0], scans[1], maps[0], maps[1], MatchOptions(**opts))
    except SoftplotError as exc:
        return {"status": "no overlap", "error": str(exc)}
    res.write(out, overwrite=True)
    return {"status": "done", "n": res.n, "rms_px": res.rms_px, "std_scale": res.std_scale,
            "sigma0": res.to_json()["sigma0"], "left_px": res.left_px,
            "right_px": res.right_px, "keypoints": res.keypoints}


def _run_pairs(jobs, workers: int, scheduler: str | None, progress) -> list[dict]:
    """``_pair_task(*job)`` for every job: in this process when ``workers`` is 0, else on
    dask.distributed (a LocalCluster of ``workers`` single-threaded processes, or
    ``scheduler``)."""
    if workers == 0 and not scheduler:
        out = []
        for j in jobs:
            out.append(_pair_task(*j))
            progress(len(out), len(jobs))
        return out
    try:
        from dask.distributed import as_completed
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise SoftplotError("matching a block needs dask.distributed: "
                            "pip install 'softplot[batch]'") from exc
    from softplot.pipeline.batch import _quiet_close, start_client

    client, cluster = start_client(scheduler, workers)
    try:
        futs = [client.submit(_pair_task, *j, pure=False) for j in jobs]
        index = {f.key: i for i, f in enumerate(futs)}
        out = [None] * len(jobs)
        done = 0
        for f in as_completed(futs):
            out[index[f.key]] = f.result()
            done += 1
            progress(done, len(jobs))
    finally:
        _quiet_close(client, cluster)
    return out


class _Links:
    """Union-find over (scan, keypoint) nodes."""

    def __init__(self):
        self.parent: dict = {}

    def find(self, x):
        p = self.parent.setdefault(x, x)
        while p != self.parent[p]:
            self.parent[p] = self.parent[self.parent[p]]
            p = self.parent[p]
        return p

    def union(self, a, b):
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _tracks(pairs, results) -> list[dict]:
    """Multi-ray points {scan: approximate pixel} (the first scan: its template pixel)."""
    links = _Links()
    pos = {}
    for (a, b), r in zip(pairs, results, strict=True):
        if r["status"] != "done":
            continue
        for (ka, kb), pl, pr in zip(r["keypoints"], r["left_px"], r["right_px"], strict=True):
            na, nb = (a, int(ka)), (b, int(kb))
            links.union(na, nb)
            pos[na] = pl  # a left pixel: the keypoint's integer pixel (the same in every pair)
            pos.setdefault(nb, pr)
    groups: dict = {}
    for node in pos:
        groups.setdefault(links.find(node), []).append(node)
    tracks = []
    for nodes in groups.values():
        scans = [n[0] for n in nodes]
        if len(set(scans)) != len(scans) or len(scans) < 2:
            continue  # two keypoints of one scan in one point: ambiguous, dropped
        tracks.append({s: np.asarray(pos[(s, k)], float) for s, k in sorted(nodes)})
    return tracks


def _measure(tracks, greys, opt: MatchOptions):
    """Least-squares matching of every point from its first scan into the others.

    Returns a list of {scan: (x, y, sx_px, sy_px)} (points with >= 2 rays)."""
    import cv2

    from softplot.matching.lsm import match_patches

    # templates never overlap: per first scan, the points with most rays first
    keep = []
    by_master: dict = {}
    for t, tr in enumerate(tracks):
        by_master.setdefault(min(tr), []).append(t)
    for m, ts in by_master.items():
        xy = np.rint(np.array([tracks[t][m] for t in ts]))
        score = np.array([len(tracks[t]) for t in ts], float)
        keep.extend(ts[i] for i in _separated(xy, score, 2 * opt.half + 2))
    keep = sorted(keep)
    meas = {t: {} for t in keep}
    groups: dict = {}
    for t in keep:
        m = min(tracks[t])
        for s in tracks[t]:
            if s != m:
                groups.setdefault((m, s), []).append(t)
    for (m, s), ts in groups.items():
        L = np.rint(np.array([tracks[t][m] for t in ts]))
        R0 = np.array([tracks[t][s] for t in ts])
        A = None
        if len(ts) >= 3:
            A2, _ = cv2.estimateAffine2D(L.astype(np.float32), R0.astype(np.float32),
                                         method=cv2.LMEDS)
            A = None if A2 is None else A2[:, :2]
        pm = match_patches(greys[m], greys[s], L, R0, A, half=opt.half, max_shift=2.0)
        ok = (pm.ok & (pm.corr >= opt.min_corr) & np.all(pm.std <= opt.max_std_px, axis=1))
        for i, t in enumerate(ts):
            if ok[i]:
                meas[t][s] = (*pm.xy[i], *pm.std[i])
                meas[t].setdefault(m, (*L[i], np.nan, np.nan))
    return [meas[t] for t in keep if len(meas[t]) >= 2]


def _camera_toml(camera, sigma_um: float, pixel_um: float) -> str:
    from softplot.camera import load_camera

    cam = load_camera(camera)
    p = Path(str(camera))
    cert = str(p.resolve()) if p.suffix.lower() == ".toml" and p.is_file() else str(camera)
    return "\n".join(["[[camera]]", f"name = {json.dumps(cam.name)}",
                      f"certificate = {json.dumps(cert)}",
                      f"sigma_image_um = {sigma_um:.4f}", f"pixel_size_um = {pixel_um:.4f}",
                      ""])


def match_block(scans, camera: str, out, detections=None, *, options: MatchOptions | None = None,
                workers: int = 2, scheduler: str | None = None, overwrite: bool = False,
                progress=None) -> dict:
    """Match a block of scans and write it as a bundle project in ``out`` (module docstring).

    Parameters
    ----------
    scans : list of path
        Three or more scans (two work too) of one camera; photo names are the file stems.
    camera : str
        Built-in camera name or certificate (TOML).
    detections : list of (path or None), optional
        Each scan's mark detection (softplot detect JSON); detected once when missing.
    workers : int
        Worker processes of the LocalCluster (0: match the pairs in this process).
    scheduler : str, optional
        Address of an existing dask scheduler instead.

    Returns
    -------
    dict
        What ``block.json`` holds.
    """
    from softplot.camera import load_camera
    from softplot.io import load_scan
    from softplot.pipeline.session import scan_photo_map

    opt = options or MatchOptions()
    say = progress or (lambda done, total: None)
    scans = [Path(s) for s in scans]
    if len(scans) < 2:
        raise SoftplotError(f"a block needs at least two scans, got {len(scans)}")
    names = [s.stem for s in scans]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise SoftplotError(f"scans with the same name stem {dup[0]!r}: photo names must differ")
    dets = list(detections or [None] * len(scans))
    if len(dets) != len(scans):
        raise SoftplotError(f"{len(dets)} detections for {len(scans)} scans: give one "
                            "--detection per scan, in the same order, or none")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SoftplotError(f"{out}: exists and is not a folder")
    check_outputs([out / f for f in BLOCK_FILES], overwrite)
    cam = load_camera(camera)
    # marks: detected once per scan (not once per pair)
    greys, maps = [], []
    for k, (s, d) in enumerate(zip(scans, dets, strict=True)):
        if d is None:
            from softplot.io import fingerprint
            from softplot.marks import detect

            try:
                det = detect(load_scan(s), cam).to_json()
            except SoftplotError as exc:
                raise SoftplotError(f"scan {s}: {exc} (is {cam.name} its camera?)") from None
            det["scan"] = fingerprint(s)
            d = out / "detections" / f"{s.stem}.detection.json"
            d.parent.mkdir(parents=True, exist_ok=True)
            d.write_text(json.dumps(det) + "\n", encoding="utf-8")
            dets[k] = d
        try:
            maps.append(scan_photo_map(s, cam, str(d)))
        except SoftplotError as exc:
            raise SoftplotError(f"scan {s}: {exc} (is {cam.name} its camera?)") from None
    pairs = [(i, j) for i in range(len(scans)) for j in range(i + 1, len(scans))]
    opts = asdict(opt)
    jobs = [(str(scans[i]), str(scans[j]), str(camera), str(dets[i]), str(dets[j]), opts,
             str(out / "pairs" / f"{names[i]}__{names[j]}")) for i, j in pairs]
    results = _run_pairs(jobs, workers, scheduler, say)
    linked = {s for (i, j), r in zip(pairs, results, strict=True) if r["status"] == "done"
              for s in (i, j)}
    if not linked:
        raise SoftplotError("no two scans of the block overlap (too few ties in every pair)")
    alone = [names[k] for k in range(len(scans)) if k not in linked]
    if alone:
        raise SoftplotError(f"scan {alone[0]} overlaps no other scan of the block")
    # every point measured from one template, in the scans themselves
    for s in scans:
        greys.append(np.ascontiguousarray(load_scan(s).pixels, np.float32))
    points = _measure(_tracks(pairs, results), greys, opt)
    rays = np.bincount([len(p) for p in points], minlength=3)
    per_scan = np.zeros(len(scans), int)
    for p in points:
        for s in p:
            per_scan[s] += 1
    thin = [names[k] for k in range(len(scans)) if per_scan[k] < MIN_TIES]
    if thin:
        raise SoftplotError(f"too few ties in scan {thin[0]}: {per_scan[names.index(thin[0])]}"
                            f", at least {MIN_TIES} needed")
    # observations: film mm; each ray's precision (the match's, shared by both images)
    rows = []
    sig_all = []
    # (a match's standard deviation is that of a difference of two image positions: half
    # its variance to each; the template's position takes the median of its point's; all
    # scaled by the pairs' median variance factor, as softplot match scales a pair's)
    scale = float(np.median([r["std_scale"] for r in results if r["status"] == "done"]))
    for n, p in enumerate(points):
        sd = {s: np.maximum(np.array(v[2:4]) * scale / np.sqrt(2.0), opt.sigma_floor_px)
              for s, v in p.items() if np.isfinite(v[2])}
        s_med = np.median(np.array(list(sd.values())), axis=0)
        for s, v in sorted(p.items()):
            sx, sy = sd.get(s, s_med)
            rows.append((s, f"T{n + 1:05d}", v[0], v[1], float(sx), float(sy)))
    px_mm = np.array([m.frame.pixel_mm for m in maps])
    obs = []
    for k in range(len(scans)):
        sel = [r for r in rows if r[0] == k]
        film = maps[k].correction.pixel_to(np.array([r[2:4] for r in sel], float), to="film")[0]
        for r, f in zip(sel, film, strict=True):
            obs.append((names[k], r[1], f[0], f[1], r[4] * px_mm[k], r[5] * px_mm[k]))
            sig_all.append(0.5 * (r[4] + r[5]) * px_mm[k])
    obs.sort(key=lambda o: (o[1], o[0]))
    out.mkdir(parents=True, exist_ok=True)
    summary = {
        "photos": names, "scans": [str(s) for s in scans], "camera": cam.name,
        "std_scale": scale,
        "pairs": [{"left": names[i], "right": names[j], "status": r["status"],
                   **({"ties": r["n"], "rms_px": r["rms_px"], "sigma0": r["sigma0"]}
                      if r["status"] == "done" else {"error": r["error"]})}
                  for (i, j), r in zip(pairs, results, strict=True)],
        "points": len(points), "observations": len(obs),
        "points_by_rays": {str(k): int(v) for k, v in enumerate(rays) if k >= 2 and v},
        "observations_per_photo": dict(zip(names, per_scan.tolist(), strict=True)),
    }
    (out / "cameras.toml").write_text(
        _camera_toml(camera, float(np.median(sig_all)) * 1000.0, float(np.mean(px_mm)) * 1000),
        encoding="utf-8")
    with open(out / "photos.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["photo", "camera", "scan"])
        for n, s in zip(names, scans, strict=True):
            w.writerow([n, cam.name, str(s)])
    with open(out / "observations.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["photo", "name", "x", "y", "sx", "sy"])
        for o in obs:
            w.writerow([o[0], o[1], f"{o[2]:.6f}", f"{o[3]:.6f}", f"{o[4]:.6f}",
                        f"{o[5]:.6f}"])
    (out / "block.json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    return summary
