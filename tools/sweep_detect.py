#!/usr/bin/env python
"""Robustness sweep of reseau detection (``softplot.synthetic.sweep``): seeded renders of
scans nobody tuned the detector to, detected in this process and scored against the truth.

Prints one line per render and, at the end, the per-condition table (markdown) of
``docs/accuracy.md``; ``--failures FILE`` writes every case that misses a target (seed,
conditions, what went wrong) so that it can be rerun with ``--seeds``.

Usage::

    .venv/bin/python tools/sweep_detect.py --full --table sweep.md --failures failures.md
    .venv/bin/python tools/sweep_detect.py --n 40            # a quick sample
    .venv/bin/python tools/sweep_detect.py --seeds 17,230    # rerun given cases
    .venv/bin/python tools/sweep_detect.py --condition busy --n 10 --save cases/
                                           # 10 renders that have a condition, files kept
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

#: renders of the full run
FULL = 520


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=40, help="renders (default 40)")
    ap.add_argument("--full", action="store_true", help=f"the full sweep ({FULL} renders)")
    ap.add_argument("--start", type=int, default=0, help="first seed")
    ap.add_argument("--seeds", help="comma-separated seeds to run instead")
    ap.add_argument("--layout", help="force one layout (a built-in certificate name)")
    ap.add_argument("--condition", help="only renders that have this condition (the first "
                    "--n seeds from --start that have it)")
    ap.add_argument("--save", type=Path, help="write each render as stored (TIFF, or JPEG "
                    "as the case says) and its truth JSON into this folder")
    ap.add_argument("--table", type=Path, help="write the markdown table here")
    ap.add_argument("--failures", type=Path, help="write the failing cases here (markdown)")
    ap.add_argument("--jsonl", type=Path, help="append one JSON line per case here")
    ap.add_argument("--cache", type=Path, help="keep the renders in this folder and reuse "
                    "them (the renders cost far more than detection)")
    ap.add_argument("--render-only", action="store_true",
                    help="only fill --cache with the renders, detect nothing")
    ap.add_argument("--every", type=int, default=20,
                    help="rewrite --table and --failures every this many renders")
    ap.add_argument("--merge", type=Path, nargs="+", metavar="JSONL",
                    help="detect nothing: the table of these --jsonl logs (runs split with "
                    "--start/--n; a seed seen twice keeps its last line)")
    a = ap.parse_args(argv)
    if a.merge:
        return _merge(a)

    from softplot.synthetic.sweep import (
        aggregate,
        failure_lines,
        make_case,
        misses,
        run_case,
        table,
    )

    if a.seeds:
        seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    elif a.condition:
        from softplot.synthetic.sweep import CONDITIONS

        if a.condition not in CONDITIONS and not a.condition.startswith("layout:"):
            ap.error(f"--condition: one of {', '.join(CONDITIONS)} or layout:NAME")
        seeds, s = [], a.start
        while len(seeds) < (FULL if a.full else a.n) and s < a.start + 100_000:
            if a.condition in make_case(s, a.layout).conditions:
                seeds.append(s)
            s += 1
    else:
        seeds = list(range(a.start, a.start + (FULL if a.full else a.n)))
    results, failures = [], []
    t0 = time.perf_counter()
    if a.render_only:
        if not a.cache:
            ap.error("--render-only needs --cache")
        from softplot.synthetic.sweep import render_case

        for k, seed in enumerate(seeds):
            t1 = time.perf_counter()
            render_case(make_case(seed, a.layout), a.cache)
            print(f"[{k + 1}/{len(seeds)}] seed {seed} rendered in "
                  f"{time.perf_counter() - t1:.1f} s", flush=True)
        return 0
    for k, seed in enumerate(seeds):
        case = make_case(seed, a.layout)
        t1 = time.perf_counter()
        if a.save:
            _save(a.save, case)
        sc, det = run_case(case, cache=a.cache)
        bad = failure_lines(case, sc)
        results.append((case, sc))
        d = sc.to_dict()
        print(f"[{k + 1}/{len(seeds)}] seed {seed} {case.camera}: "
              f"{'ok' if not bad else 'FAIL'} measured {sc.measured}/{sc.visible}"
              f"{_below(sc)}, "
              f"rms {d['rms_px']:.4f} px (crb {d['crb_px']:.4f}), z {d['z_rms']:.2f}, "
              f"detect {sc.seconds:.2f} s, total {time.perf_counter() - t1:.1f} s"
              + (f" | {bad[0][:160]}" if bad else ""), flush=True)
        if bad:
            failures.append((case, bad))
        if a.jsonl:
            with a.jsonl.open("a", encoding="utf-8") as f:
                f.write(json.dumps({"seed": seed, "case": case.describe(),
                                    "conditions": list(case.conditions), **d}) + "\n")
        if (k + 1) % a.every == 0 and k + 1 < len(seeds):  # the figures so far
            _write(a, aggregate(results), failures, k + 1, seeds)
    agg = aggregate(results)
    md = table(agg)
    print()
    print(md)
    print(f"\n{len(seeds)} renders in {time.perf_counter() - t0:.0f} s; "
          f"{len(failures)} with a failure")
    print(_one_arm_line(agg))
    short = {k: misses(v) for k, v in agg.items() if misses(v)}
    for k, v in short.items():
        print(f"  {k}: misses {'; '.join(v)}")
    _write(a, agg, failures, len(seeds), seeds)
    return 0


def _one_arm_line(agg: dict) -> str:
    """The one-armed crosses across their bar against their renders' two-armed crosses
    (``softplot.synthetic.sweep.one_arm_over_render``), pooled."""
    r = agg["all"]
    return (f"one-armed across: {r['rms1_over_crb1']:.3f}x their bound, "
            f"{r['rms1_over_render']:.3f}x their renders' two-armed RMS/CRB")


def _below(sc) -> str:
    """' (k below detection)' for a score with visible crosses under their detection threshold
    (``softplot.synthetic.sweep.mark_snr``), else ''."""
    k = sum(r[0] < r[1] for r in sc.snr_measured + sc.snr_missed)
    return f" ({k} below detection)" if k else ""


def _merge(a) -> int:
    from types import SimpleNamespace

    from softplot.synthetic.sweep import Score, aggregate, misses, table

    rows = {}
    for p in a.merge:
        for line in p.read_text(encoding="utf-8").splitlines():
            if line.strip():
                d = json.loads(line)
                rows[int(d["seed"])] = d
    seeds = sorted(rows)
    results = [(SimpleNamespace(conditions=rows[s]["conditions"]),
                Score.from_dict(rows[s])) for s in seeds]
    agg = aggregate(results)
    md = table(agg)
    head = f"{len(seeds)} renders (seeds {seeds[0]}-{seeds[-1]})"
    print(head + "\n\n" + md)
    print(_one_arm_line(agg))
    for k, v in agg.items():
        if misses(v):
            print(f"  {k}: misses {'; '.join(misses(v))}")
    if a.table:
        a.table.write_text(head + "\n\n" + md + "\n", encoding="utf-8")
    return 0


def _save(folder: Path, case) -> None:
    """The render of ``case`` as stored and its truth, ``sweep-<seed>.tif|jpg`` + JSON."""
    from softplot.synthetic import render_scan
    from softplot.synthetic.files import write_image

    folder.mkdir(parents=True, exist_ok=True)
    img, truth = render_scan(case.camera, case.spec, case.seed)
    ext = "jpg" if case.jpeg else "tif"
    path = folder / f"sweep-{case.seed:04d}.{ext}"
    write_image(path, img, case.spec.dpi, ext, overwrite=True, jpeg_quality=case.jpeg or 92)
    truth["image"] = path.name
    truth["sweep_case"] = {"seed": case.seed, "rotate": case.rotate, "jpeg": case.jpeg,
                           "conditions": list(case.conditions)}
    (folder / f"sweep-{case.seed:04d}.truth.json").write_text(json.dumps(truth, indent=1),
                                                             encoding="utf-8")


def _write(a, agg, failures, done, seeds) -> None:
    from softplot.synthetic.sweep import table

    span = f"seeds {seeds[0]}-{seeds[done - 1]}" if seeds == list(
        range(seeds[0], seeds[0] + len(seeds))) else f"{done} given seeds"
    if a.table:
        a.table.write_text(f"{done} of {len(seeds)} renders ({span})\n\n" + table(agg) + "\n",
                           encoding="utf-8")
    if a.failures:
        lines = [f"# Detection sweep failures ({len(failures)} of {done} renders, {span})", "",
                 "Rerun one with `tools/sweep_detect.py --seeds SEED` "
                 "(`softplot.synthetic.sweep.make_case(SEED)` gives the render).", ""]
        for case, bad in failures:
            lines.append(f"- **seed {case.seed}** ({case.describe()})")
            lines += [f"  - {b}" for b in bad]
        a.failures.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    sys.exit(main())
