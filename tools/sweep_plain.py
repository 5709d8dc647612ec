#!/usr/bin/env python
"""Reseau detection on scans of a second renderer (``softplot.synthetic.plain``), written apart
from the one the detector was developed on: a check that the detector is not tuned to its own
renderer.

Each seed draws a scan (camera, dpi, true arm length and line width against the
certificate's, polarity, RGB and colour masks, 8/16 bit, JPEG, defocus, grain, scene, crop,
dark rows), detects it as ``softplot detect SCAN --camera NAME`` would (with ``--dpi`` except
on every third seed, where the dpi is estimated) and scores the result. Prints one line per
scan and the pooled figures, overall and per camera (markdown, for docs/accuracy.md).

Usage::

    .venv/bin/python tools/sweep_plain.py --n 200 --jsonl plain.jsonl
    .venv/bin/python tools/sweep_plain.py --seeds 69,87
    .venv/bin/python tools/sweep_plain.py --merge a.jsonl b.jsonl   # the table of logs
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _table(rows: list[dict]) -> str:
    from softplot.synthetic.plain import summarise

    head = ("| scans | n | must give a result | gave one | visible | measured | wrong row/col "
            "| claims on invisible | more than 1 px off | median error px | RMS px | "
            "normalised-error RMS | one-armed: n, normalised error across, along |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    out = [head]
    groups = [("all", rows)] + [(c, [r for r in rows if r["camera"] == c])
                                for c in sorted({r["camera"] for r in rows})]
    for name, rs in groups:
        s = summarise(rs)
        out.append(f"| {name} | {s['n']} | {s['expected']} | {s['results_expected']} | "
                   f"{s['visible']} | {100 * s['measured']:.2f} % | {s['wrong']} | "
                   f"{s['claimed']} | {s['gross']} | {s['median_px']:.3f} | "
                   f"{s['rms_px']:.3f} | {s['z']:.2f} | {s['lone']}, {s['z_across']:.2f}, "
                   f"{s['z_along']:.2f} |")
    refused = [r for r in rows if r["expected"] and not r["result"]]
    if refused:
        out.append("")
        out.append("Refused though the scan shows at least 3 x 3 crosses:")
        out += [f"- seed {r['seed']}: {r['error']}" for r in refused]
    return "\n".join(out)


def _line(row: dict, seconds: float) -> str:
    import numpy as np

    if not row["result"]:
        tag = "REFUSED" if row["expected"] else "refused (rightly)"
        return f"{row['seed']:4d} {tag}: {row['error']} [{row['case']}]"
    e = np.asarray(row["errors"], float)
    z = np.sqrt(np.mean(row["z2"])) if row["z2"] else float("nan")
    med = float(np.median(e)) if len(e) else float("nan")
    return (f"{row['seed']:4d} {row['measured']}/{row['visible']} measured, "
            f"{len(row['wrong'])} wrong, {len(row['claimed'])} claims, "
            f"{len(row['gross'])} gross, median {med:.3f} px, z {z:.2f}, dpi "
            f"{row['dpi_source']} ({seconds:.1f} s) [{row['case']}]")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=40, help="scans (default 40)")
    ap.add_argument("--start", type=int, default=0, help="first seed")
    ap.add_argument("--seeds", help="comma-separated seeds to run instead")
    ap.add_argument("--jsonl", type=Path, help="append one JSON line per scan here")
    ap.add_argument("--table", type=Path, help="write the markdown table here")
    ap.add_argument("--merge", type=Path, nargs="+", metavar="JSONL",
                    help="detect nothing: the table of these --jsonl logs")
    a = ap.parse_args(argv)
    if a.merge:
        rows = {}
        for p in a.merge:
            for ln in p.read_text().splitlines():
                if ln.strip():
                    r = json.loads(ln)
                    rows[r["seed"]] = r
        text = _table([rows[k] for k in sorted(rows)])
    else:
        from softplot.synthetic.plain import run_plain

        seeds = ([int(s) for s in a.seeds.split(",")] if a.seeds
                 else range(a.start, a.start + a.n))
        rows = []
        for seed in seeds:
            t = time.perf_counter()
            _, row = run_plain(seed)
            print(_line(row, time.perf_counter() - t), flush=True)
            rows.append(row)
            if a.jsonl:
                with a.jsonl.open("a") as f:
                    f.write(json.dumps(row) + "\n")
        text = _table(rows)
    print(text)
    if a.table:
        a.table.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
