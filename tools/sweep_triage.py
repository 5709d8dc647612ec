#!/usr/bin/env python
"""Group the failing cases of a detection sweep by class of failure.

Reads the ``--jsonl`` lines of ``tools/sweep_detect.py`` (one or more files; a seed seen twice
keeps its last line) and writes a markdown triage: for each class of failure (no result,
whole-grid row/col shift, scattered wrong ids, claims on invisible crosses, visible crosses not
measured by reason, RMS over the bound, normalised error out of range; on logs with the crosses'
signal-to-noise ratios, refusals and misses below detection apart) the seeds, the layout and
conditions they share, and one command that reruns them. The biggest classes come first.

Usage::

    .venv/bin/python tools/sweep_triage.py sweep.jsonl [more.jsonl] --out triage.md
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections import Counter, defaultdict
from pathlib import Path

#: targets (as softplot.synthetic.sweep.TARGETS; per case here, so only a hint for RMS and z)
RMS_OVER_CRB = 1.25
Z_RANGE = (0.67, 1.5)

_ID = re.compile(r"R(\d+)C(\d+) measured at R(\d+)C(\d+)")


def load(paths: list[Path]) -> dict[int, dict]:
    out: dict[int, dict] = {}
    for p in paths:
        for line in p.read_text(encoding="utf-8").splitlines():
            if line.strip():
                d = json.loads(line)
                out[int(d["seed"])] = d
    return dict(sorted(out.items()))


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _generic(text: str) -> str:
    """A message with its numbers and names replaced (for grouping)."""
    text = re.sub(r"<array>: ", "", text)
    text = re.sub(r"R\d+C\d+", "RnCn", text)
    text = re.sub(r"\d+(\.\d+)?", "N", text)
    return text[:140]


def classify(d: dict) -> list[tuple[str, str]]:
    """(class, detail) pairs of one case's failures (empty: the case meets every target)."""
    out = []
    if d.get("ambiguous_truth") and d.get("ids_ambiguous"):
        amb = True  # an ambiguous render, warned: wrong ids are not a failure
    else:
        amb = False
    if not d["result"] and d.get("below_detection"):  # nothing a detector can be asked for
        out.append(("no result where none is required (below detection)",
                    f"{d['below_detection']}; {_generic(d['error'])}"))
    elif not d["result"]:
        out.append(("no result", _generic(d["error"])))
    wrong = d.get("wrong") or []
    shifted = False
    if wrong and not amb:
        shifts = Counter()
        for w in wrong:
            m = _ID.search(w)
            if m:
                r, c, r2, c2 = map(int, m.groups())
                shifts[(r2 - r, c2 - c)] += 1
        (dr, dc), k = shifts.most_common(1)[0] if shifts else ((0, 0), 0)
        what = "silent guess on an ambiguous render" if d.get("ambiguous_truth") else ""
        if k >= max(3, 0.8 * len(wrong)):
            shifted = True
            out.append(("whole-grid row/col shift",
                        f"{len(wrong)} crosses shifted by {dr:+d} row(s), {dc:+d} col(s)"
                        + (f" ({what})" if what else "")))
        else:
            out.append(("scattered wrong row/col", f"{len(wrong)}: {'; '.join(wrong[:3])}"))
    if shifted:  # claims, crosses missed and errors follow from the shift
        return out
    if d.get("claimed"):
        out.append(("claims on invisible crosses", ", ".join(d["claimed"][:6])))
    if d["result"] and d.get("missed"):
        below = _below(d)
        reasons = Counter(m.split(": ", 1)[1] if ": " in m else m
                          for m, b in zip(d["missed"], below, strict=True) if not b)
        for r, k in reasons.items():
            out.append((f"visible not measured: {r}", f"{k} of {d['visible']}"))
        if any(below):
            out.append(("visible below detection, not measured (not required)",
                        f"{sum(below)} of {d['visible']}"))
    if d.get("claimed_below"):
        out.append(("gross measurements below detection", ", ".join(d["claimed_below"][:6])))
    rms, crb, z = _num(d.get("rms_px")), _num(d.get("crb_px")), _num(d.get("z_rms"))
    if math.isfinite(rms) and math.isfinite(crb) and crb > 0 and rms > RMS_OVER_CRB * crb:
        kind = "RMS over 1.25x the bound" + (" (with gross errors)" if d.get("gross") else "")
        out.append((kind, f"{rms:.4f} px vs {crb:.4f} px ({rms / crb:.2f}x), "
                          f"{d['measured']} crosses"))
    if math.isfinite(z) and not Z_RANGE[0] <= z <= Z_RANGE[1]:
        out.append((f"normalised error {'too large' if z > Z_RANGE[1] else 'too small'} "
                    f"(sigmas {'too small' if z > Z_RANGE[1] else 'too large'})",
                    f"z rms {z:.2f}, {d['measured']} crosses"))
    return out


def _below(d: dict) -> list[bool]:
    """Per missed cross: is it below detection (its matched-filter SNR under its threshold,
    ``snr_missed`` of logs that carry it; all False otherwise)?"""
    rows = d.get("snr_missed")
    if not rows or len(rows) != len(d["missed"]):
        return [False] * len(d["missed"])
    return [r[0] < r[1] for r in rows]


def _layout(d: dict) -> str:
    return next((c[7:] for c in d["conditions"] if c.startswith("layout:")), "?")


def triage(cases: dict[int, dict], title: str = "") -> str:
    classes: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for seed, d in cases.items():
        for cls, detail in classify(d):
            classes[cls].append((seed, detail))
    n = len(cases)
    base = Counter(c for d in cases.values() for c in d["conditions"])
    failing = {s for v in classes.values() for s, _ in v}
    lines = [f"# Detection sweep triage{': ' + title if title else ''}", "",
             f"{n} renders (seeds {min(cases)}-{max(cases)}), {len(failing)} with a failure; "
             f"{len(classes)} classes, the biggest first. A case may be in several classes. "
             "Per-case RMS and normalised error are hints (the targets are pooled per "
             "condition).", "",
             "Rerun: `PYTHONPATH=src .venv/bin/python tools/sweep_detect.py --seeds S1,S2`.", "",
             "| class | seeds |", "|---|---|"]
    order = sorted(classes, key=lambda c: (-len({s for s, _ in classes[c]}), c))
    for cls in order:
        lines.append(f"| {cls} | {len({s for s, _ in classes[cls]})} |")
    lines.append("")
    for cls in order:
        items = classes[cls]
        seeds = sorted({s for s, _ in items})
        lay = Counter(_layout(cases[s]) for s in seeds)
        cond = Counter(c for s in seeds for c in cases[s]["conditions"]
                       if not c.startswith("layout:"))
        shared = []
        for c, k in cond.most_common():
            share, lift = k / len(seeds), (k / len(seeds)) / (base[c] / n)
            if share >= 0.4 and lift >= 1.3:
                shared.append(f"{c} {k}/{len(seeds)} ({lift:.1f}x its share)")
        lines += [f"## {cls} ({len(seeds)} renders)", "",
                  "Layouts: " + ", ".join(f"{k} {v}" for k, v in lay.most_common()) + ".",
                  "Conditions over-represented: " + ("; ".join(shared) or "none") + ".", "",
                  f"`tools/sweep_detect.py --seeds {','.join(map(str, seeds))}`", ""]
        for s, detail in items[:40]:
            d = cases[s]
            lines.append(f"- seed {s} ({_layout(d)}): {detail} | "
                         f"{d['case'].split('; conditions')[0].split(', ', 2)[-1]}; "
                         f"{', '.join(c for c in d['conditions'] if not c.startswith('layout'))}")
        if len(items) > 40:
            lines.append(f"- ... {len(items) - 40} more")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("jsonl", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, help="write the markdown here (default: stdout)")
    ap.add_argument("--title", default="")
    a = ap.parse_args(argv)
    md = triage(load(a.jsonl), a.title)
    if a.out:
        a.out.write_text(md, encoding="utf-8")
    else:
        sys.stdout.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
