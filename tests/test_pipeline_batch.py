"""softplot batch on dask.distributed: failures recorded, resume skips finished scans and
redoes half-written ones (LocalCluster of worker processes, and an existing scheduler)."""

from __future__ import annotations

import csv
import json

import pytest

from softplot.cli import main
from softplot.pipeline.batch import BatchReport, check_stems, expand, is_complete
from softplot.synthetic import ScanSpec, write_scan


def run_cli(*args) -> int:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    return e.value.code


def summary(out):
    with open(out / "summary.csv", encoding="utf-8") as fh:
        return {r["scan"].rsplit("/", 1)[-1]: r for r in csv.DictReader(fh)}


def test_batch_failures_and_resume(tmp_path, capsys):
    from dask.distributed import LocalCluster

    src = tmp_path / "archive"
    for i in range(3):
        write_scan(src, "rollei-6006",
                   ScanSpec(dpi=600, scene="texture", deform_um=10 + 5 * i,
                            rotation_deg=0.2 * i), seed=10 + i, stem=f"scan{i}")
    (src / "corrupt.tif").write_bytes(b"II*\x00 this is not a TIFF at all")
    out = tmp_path / "out"

    # first run: local cluster of 2 worker processes
    code = run_cli("batch", str(src / "*.tif"), "--camera", "rollei-6006", "--out", out,
                   "--workers", "2", "--quiet")
    assert code == 1  # documented: 1 when some scan failed
    text = capsys.readouterr().out
    assert "3 done, 1 failed, 0 skipped" in text
    s = summary(out)
    assert {k: v["status"] for k, v in s.items()} == {
        "scan0.tif": "done", "scan1.tif": "done", "scan2.tif": "done", "corrupt.tif": "failed"}
    assert s["corrupt.tif"]["error"]
    for i in range(3):
        r = json.loads((out / f"scan{i}.json").read_text())
        assert r["complete"] is True and r["marks_measured"] >= 115
        assert float(s[f"scan{i}.tif"]["rms_px"]) == pytest.approx(r["rms_px"])
    assert (out / "report.html").is_file()

    # damage two results: one torn mid-write, one without the complete flag
    kept = (out / "scan0.json").stat().st_mtime_ns
    raw = (out / "scan1.json").read_bytes()
    (out / "scan1.json").write_bytes(raw[: len(raw) // 2])
    r2 = json.loads((out / "scan2.json").read_text())
    r2["complete"] = False
    (out / "scan2.json").write_text(json.dumps(r2))
    assert not is_complete(out / "scan1.json") and not is_complete(out / "scan2.json")

    # resume on an existing cluster given by its scheduler address
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        code = run_cli("batch", str(src / "*.tif"), "--camera", "rollei-6006", "--out", out,
                       "--scheduler", cluster.scheduler_address, "--quiet")
    assert code == 1
    text = capsys.readouterr().out
    assert "2 done, 1 failed, 1 skipped" in text
    assert (out / "scan0.json").stat().st_mtime_ns == kept  # finished scan not redone
    s = summary(out)
    assert s["scan0.tif"]["status"] == "skipped"
    assert s["scan1.tif"]["status"] == "done" and s["scan2.tif"]["status"] == "done"
    assert all(is_complete(out / f"scan{i}.json") for i in range(3))


def test_batch_bad_input(tmp_path):
    assert run_cli("batch", str(tmp_path / "*.tif"), "--camera", "rollei-6006",
                   "--out", tmp_path / "o") == 2  # nothing matches
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for d in ("a", "b"):
        (tmp_path / d / "x.tif").write_bytes(b"")
    (tmp_path / "a" / "x.film.tif").write_bytes(b"")  # an output of process --flatten
    (tmp_path / "a" / "x.json").write_text("{}")
    scans = expand([str(tmp_path / "**" / "*.tif"), str(tmp_path / "a" / "*")])
    assert sorted(p.parent.name for p in scans) == ["a", "b"]
    from softplot.errors import SoftplotError

    with pytest.raises(SoftplotError, match="same name stem"):
        check_stems(scans)
    assert run_cli("batch", str(tmp_path / "**" / "*.tif"), "--camera", "rollei-6006",
                   "--out", tmp_path / "o") == 2


def test_report_table_counts():
    rep = BatchReport(rows=[
        {"scan": "a.tif", "status": "done", "marks": 121, "measured": 120, "rms_px": 0.05,
         "method": "poly3", "loo_rms_um": 0.8, "qc": "ok", "seconds": 1.0, "error": None},
        {"scan": "b.tif", "status": "failed", "error": "b.tif: truncated"},
    ], skipped=0, seconds=2.0)
    t = rep.table()
    assert rep.done == 1 and rep.failed == 1
    assert "120/121" in t and "b.tif: truncated" in t and "1 done, 1 failed" in t


def _crash_on_b(scan, out_dir, crash=True):
    """Batch task for the test below: the worker process dies on scan b, as killed by the OS."""
    import os

    if crash and scan.stem == "b":
        os._exit(9)
    from softplot.pipeline.batch import write_json_atomic

    write_json_atomic(out_dir / f"{scan.stem}.json", {"complete": True, "status": "done"})
    return {"status": "done"}


def test_batch_survives_a_dying_worker(tmp_path):
    import dask
    from dask.distributed import LocalCluster

    from softplot.pipeline.batch import run_batch

    scans = []
    for n in ("a", "b", "c"):
        p = tmp_path / f"{n}.tif"
        p.write_bytes(b"")
        scans.append(p)
    out = tmp_path / "out"
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                          dashboard_address=":0") as cluster:
            rep = run_batch(scans, out, _crash_on_b, workers=1,
                            scheduler=cluster.scheduler_address, progress=False)
            status = {r["scan"].rsplit("/", 1)[-1]: r for r in rep.rows}
            assert len(rep.rows) == 3
            # a finished before the crash (its complete JSON counts even if its summary died
            # with the worker); b killed the worker; c was in flight on it or ran after
            assert status["a.tif"]["status"] == "done"
            assert status["b.tif"]["status"] == "failed"
            assert "worker lost" in status["b.tif"]["error"]
            if status["c.tif"]["status"] == "failed":
                assert "worker lost" in status["c.tif"]["error"]
            assert not is_complete(out / "b.json")
            assert "worker lost" in json.loads((out / "b.error.json").read_text())["error"]
            # the rerun (the cause of the crash removed) skips what is done and finishes the
            # scans lost with the worker
            rep = run_batch(scans, out, _crash_on_b, {"crash": False}, workers=1,
                            scheduler=cluster.scheduler_address, progress=False)
    assert all(is_complete(out / f"{n}.json") for n in "abc")
    assert rep.skipped >= 1 and rep.failed == 0 and rep.skipped + rep.done == 3
