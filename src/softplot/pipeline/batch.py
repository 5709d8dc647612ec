"""Archive batches on dask.distributed: many scans, bounded memory, resume, failures recorded.

Each scan is one task: :func:`softplot.pipeline.process.process_scan` on a worker, which
writes ``<out>/<stem>.json`` atomically (temporary file, then rename) and ends it with
``"complete": true``. A rerun skips every scan whose result file is complete and redoes one
that is missing or half-written. At most ``2 * workers`` tasks are in flight at any time, so
memory stays bounded however many scans the glob names; results come back as small dicts
(the images stay on the workers).
"""

from __future__ import annotations

import csv
import glob as globmod
import json
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from softplot.errors import SoftplotError

#: columns of ``summary.csv``: scan path, status (done|failed|skipped), marks in the
#: certificate, marks measured, residual RMS against the projective film -> pixel model (px;
#: not the marks' precision, which is in each result as mark_sigma_px), correction method, its
#: leave-one-out RMS (um on the film), QC (ok or the warnings), seconds, error message
SUMMARY_FIELDS = ["scan", "status", "marks", "measured", "rms_px", "method", "loo_rms_um", "qc",
                  "seconds", "error"]


@dataclass
class BatchReport:
    """What a batch did: one row per scan (``SUMMARY_FIELDS``) and the counts."""

    rows: list[dict] = field(default_factory=list)
    skipped: int = 0
    seconds: float = 0.0
    #: scans not finished because the run was interrupted (Ctrl-C)
    interrupted: int = 0

    @property
    def failed(self) -> int:
        return sum(1 for r in self.rows if r["status"] == "failed")

    @property
    def done(self) -> int:
        return sum(1 for r in self.rows if r["status"] == "done")

    def table(self) -> str:
        """The summary table printed at the end of a batch."""
        lines = [f"{'scan':<32} {'status':<8} {'measured':>9} {'proj px':>8} {'method':<16} "
                 f"{'LOO um':>7} {'s':>6}  qc / error"]
        for r in self.rows:
            meas = f"{r.get('measured', '')}/{r.get('marks', '')}" if r.get("marks") else ""
            rms = f"{r['rms_px']:.4f}" if isinstance(r.get("rms_px"), (int, float)) else ""
            loo = f"{r['loo_rms_um']:.2f}" if isinstance(r.get("loo_rms_um"), (int, float)) else ""
            sec = f"{r['seconds']:.2f}" if isinstance(r.get("seconds"), (int, float)) else ""
            lines.append(
                f"{Path(r['scan']).name[:32]:<32} {r['status']:<8} {meas:>9} {rms:>8} "
                f"{(r.get('method') or '')[:16]:<16} {loo:>7} {sec:>6}  "
                f"{r.get('error') or r.get('qc') or ''}"
            )
        lines.append("proj px: residual RMS against one projective film -> pixel model; "
                     "LOO um: the correction's leave-one-out RMS on the film")
        lines.append(
            f"{self.done} done, {self.failed} failed, {self.skipped} skipped (already done), "
            f"{self.seconds:.1f} s"
            + (f"; interrupted: {self.interrupted} not finished (run again to resume them)"
               if self.interrupted else "")
        )
        return "\n".join(lines)


#: names a glob may match that are not scans (results, reports, flattened outputs)
_NOT_SCANS = (".json", ".csv", ".html", ".md", ".txt", ".toml", ".tmp", ".part", ".film.tif")


def expand(patterns: Iterable[str]) -> list[Path]:
    """Scan paths named by glob patterns (recursive ``**`` allowed), sorted, de-duplicated.

    Results, reports and film-flattened images (``*.film.tif``) of earlier runs are left out.
    """
    out: dict[str, Path] = {}
    for pat in patterns:
        hits = globmod.glob(pat, recursive=True) if globmod.has_magic(pat) else [pat]
        for h in hits:
            p = Path(h)
            if p.is_file() and not p.name.endswith(_NOT_SCANS):
                out[str(p.resolve())] = p
    return [out[k] for k in sorted(out)]


#: the task options that make a result what it is: a rerun resumes only results made with the
#: same values (recorded in each result as ``settings``)
SETTINGS_KEYS = ("camera", "method", "flatten", "pixel_size_um", "dpi", "polarity", "rotate",
                 "mirror", "scene", "grid_part")


def settings_of(kwargs: dict) -> dict:
    """The ``settings`` record of a task's keyword arguments (a camera by its name)."""
    out = {}
    for k in SETTINGS_KEYS:
        if k not in kwargs:
            continue
        v = kwargs[k]
        out[k] = getattr(v, "name", v) if not isinstance(v, (str, int, float, bool)) else v
        if isinstance(out[k], os.PathLike):
            out[k] = str(out[k])
    return out


def settings_differ(recorded, wanted: dict) -> list[str]:
    """The names of the settings in which ``recorded`` (a result's) differs from ``wanted``."""
    if not wanted:
        return []
    if not isinstance(recorded, dict):
        return ["settings (not recorded)"]
    return [k for k in wanted if recorded.get(k) != wanted[k]]


def check_resume(scans, out_dir: Path, kwargs: dict, overwrite: bool) -> None:
    """Refuse (one line) a rerun whose finished results were made with other settings, unless
    ``overwrite`` (they are then recomputed)."""
    if overwrite:
        return
    want = settings_of(kwargs)
    for s in scans:
        rp = result_path(out_dir, Path(s))
        if not is_complete(rp):
            continue
        with open(rp, encoding="utf-8") as fh:
            rec = json.load(fh).get("settings")
        diff = settings_differ(rec, want)
        if diff:
            was = ", ".join(f"{k}={(rec or {}).get(k)!r}" for k in diff if isinstance(rec, dict))
            now = ", ".join(f"{k}={want.get(k)!r}" for k in diff if k in want)
            raise SoftplotError(
                f"{rp}: made with other settings ({was or 'not recorded'}; now {now or diff[0]});"
                " use --overwrite to recompute, or another --out"
            )


def result_path(out_dir: Path, scan: Path) -> Path:
    """Where the per-scan result of ``scan`` goes."""
    return Path(out_dir) / f"{scan.stem}.json"


def is_complete(path: Path) -> bool:
    """True when ``path`` is a fully written result (parses and says ``complete``)."""
    try:
        with open(path, encoding="utf-8") as fh:
            return bool(json.load(fh).get("complete"))
    except (OSError, ValueError, AttributeError):
        return False


def write_json_atomic(path: Path, obj: dict) -> None:
    """Write JSON to ``path`` via a temporary file and an atomic rename (fsync'd)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=1, allow_nan=False, default=_json_default)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _row_from_result(scan: Path, res: dict) -> dict:
    return {
        "scan": str(scan),
        "status": res.get("status", "done"),
        "marks": res.get("marks_total"),
        "measured": res.get("marks_measured"),
        "rms_px": res.get("rms_px"),
        "method": res.get("method"),
        "loo_rms_um": res.get("loo_rms_um"),
        "qc": _qc_text(res.get("qc")),
        "seconds": res.get("seconds"),
        "error": res.get("error"),
    }


def _qc_text(qc) -> str | None:
    if not isinstance(qc, dict):
        return None
    return "ok" if qc.get("ok") else "; ".join(qc.get("warnings", []))


def check_stems(scans: list[Path]) -> None:
    """Raise :class:`SoftplotError` if two scans share a file stem (their results would)."""
    seen: dict[str, Path] = {}
    for s in scans:
        if s.stem in seen:
            raise SoftplotError(
                f"{s} and {seen[s.stem]} have the same name stem {s.stem!r}: their results "
                "would collide in one output folder"
            )
        seen[s.stem] = s


def _one_thread_in_worker() -> None:
    """In a dask worker process (one per core already) detection runs on one thread."""
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return
    from softplot.runtime import set_threads, threads

    if threads() != 1:
        set_threads(1)


def run_one(task: Callable[..., dict], scan: str, out_dir: str, kwargs: dict) -> dict:
    """Worker side: process one scan, never raise; the outcome is a small summary dict."""
    t0 = time.perf_counter()
    scan_p = Path(scan)
    _one_thread_in_worker()
    try:
        res = task(scan_p, Path(out_dir), **kwargs)
        res.setdefault("status", "done")
    except SoftplotError as exc:
        res = {"status": "failed", "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - a batch records every failure and goes on
        res = {"status": "failed", "error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    res["seconds"] = time.perf_counter() - t0
    if res["status"] == "failed":
        # a failure is recorded in its own file so the rerun retries it (it is not complete)
        write_json_atomic(
            Path(out_dir) / f"{scan_p.stem}.error.json",
            {"scan": str(scan_p), "error": res["error"], "complete": False},
        )
    return _row_from_result(scan_p, res)


def run_batch(
    scans: list[Path],
    out_dir: Path,
    task: Callable[..., dict],
    task_kwargs: dict | None = None,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = True,
    memory_limit: str = "auto",
    overwrite: bool = False,
) -> BatchReport:
    """Process ``scans`` with ``task(scan, out_dir, **task_kwargs)`` on dask.distributed.

    ``scheduler`` is the address of an existing cluster; without it a LocalCluster of
    ``workers`` single-threaded worker processes is started and closed again. Scans whose
    result is already complete and made with the same settings (:func:`settings_of`) are
    skipped; one made with other settings is refused unless ``overwrite`` (which recomputes
    every scan). The summary CSV ``summary.csv`` in ``out_dir``
    lists every scan of this run and of earlier runs found complete.
    """
    try:
        from dask.distributed import as_completed
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise SoftplotError(
            "softplot batch needs dask.distributed: pip install 'softplot[batch]'"
        ) from exc
    from tqdm import tqdm

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    kwargs = dict(task_kwargs or {})
    check_resume(scans, out_dir, kwargs, overwrite)
    report = BatchReport()
    t0 = time.perf_counter()
    todo = []
    for s in scans:
        rp = result_path(out_dir, s)
        if not overwrite and is_complete(rp):
            report.skipped += 1
            with open(rp, encoding="utf-8") as fh:
                report.rows.append({**_row_from_result(s, json.load(fh)), "status": "skipped"})
        else:
            todo.append(s)
    if todo:
        client, cluster = start_client(scheduler, workers, memory_limit)
        finished = set()
        try:
            window = 2 * max(1, len(client.scheduler_info().get("workers", {})) or workers)
            pending = iter(todo)
            ac = as_completed()
            scan_of = {}

            def submit(scan):
                f = client.submit(run_one, task, str(scan), str(out_dir), kwargs, pure=False)
                scan_of[f.key] = scan
                ac.add(f)

            for s in [next(pending) for _ in range(min(window, len(todo)))]:
                submit(s)
            bar = tqdm(total=len(todo), unit="scan", disable=not progress, desc="batch")
            try:
                _collect(ac, scan_of, report, out_dir, bar, pending, submit, finished)
            except KeyboardInterrupt:
                report.interrupted = len(todo) - len(finished)
            bar.close()
        finally:
            _quiet_close(client, cluster)
        if report.interrupted:
            # results the workers wrote (atomically) before they were stopped still count
            for s in todo:
                if s not in finished and is_complete(result_path(out_dir, s)):
                    with open(result_path(out_dir, s), encoding="utf-8") as fh:
                        report.rows.append(_row_from_result(s, json.load(fh)))
                    report.interrupted -= 1
    report.rows.sort(key=lambda r: r["scan"])
    report.seconds = time.perf_counter() - t0
    write_summary(out_dir / "summary.csv", report.rows)
    return report


def _collect(ac, scan_of, report, out_dir, bar, pending, submit, finished) -> None:
    """Gather results as they come, submitting the next scan for each one finished."""
    for fut in ac:
        scan = scan_of.pop(fut.key)
        try:
            report.rows.append(fut.result())
        except Exception as exc:  # noqa: BLE001 - a worker died (memory, signal)
            rp = result_path(out_dir, scan)
            if is_complete(rp):  # finished; only its summary died with the worker
                with open(rp, encoding="utf-8") as fh:
                    report.rows.append(_row_from_result(scan, json.load(fh)))
            else:
                msg = f"worker lost: {type(exc).__name__}: {exc}".splitlines()[0]
                report.rows.append({**_row_from_result(scan, {}), "status": "failed",
                                    "error": msg})
                write_json_atomic(out_dir / f"{scan.stem}.error.json",
                                  {"scan": str(scan), "error": msg, "complete": False})
        finished.add(scan)
        fut.release()
        bar.update(1)
        nxt = next(pending, None)
        if nxt is not None:
            submit(nxt)


def start_client(scheduler, workers: int, memory_limit="auto"):
    """``(client, cluster)``: a client of ``scheduler`` (cluster None), or of a new local
    cluster of ``workers`` single-threaded worker processes.

    The worker processes ignore Ctrl-C (they inherit SIGINT ignored): the terminal sends it to
    the whole process group, and only this process handles it. Close both with
    :func:`_quiet_close`.
    """
    from dask.distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler), None
    old = _ignore_sigint()
    try:
        cluster = LocalCluster(
            n_workers=max(1, workers),
            threads_per_worker=1,
            processes=True,
            # a random port: None does not disable the dashboard (dask/distributed#8136)
            dashboard_address=":0",
            memory_limit=memory_limit,
        )
        return Client(cluster), cluster
    finally:
        _restore_sigint(old)


def _ignore_sigint():
    """Ignore SIGINT (returns the old handler; None when not in the main thread)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGINT, signal.SIG_IGN)


def _restore_sigint(old) -> None:
    import signal

    if old is not None:
        signal.signal(signal.SIGINT, old)


def _quiet_close(client, cluster) -> None:
    """Close the client and the local cluster without tracebacks (also after Ctrl-C)."""
    import contextlib
    import logging

    old = _ignore_sigint()  # a second Ctrl-C does not tear the shutdown
    try:
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        with contextlib.suppress(Exception):
            client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
    finally:
        _restore_sigint(old)


def write_summary(path: Path, rows: list[dict]) -> None:
    """Write the summary CSV (``SUMMARY_FIELDS``) atomically."""
    tmp = Path(path).with_name(f".{Path(path).name}.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow(r)
    os.replace(tmp, path)
