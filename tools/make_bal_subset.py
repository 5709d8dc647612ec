"""Write the small BAL problem shipped in tests/data/bal/ from the full Ladybug problem.

    .venv/bin/python tools/make_bal_subset.py PROBLEM-49-7776-pre.txt tests/data/bal/ladybug-8.txt

The sub-problem is what cameras 0-7 see (points re-numbered, every value as in the source).
"""

from __future__ import annotations

import argparse

import numpy as np

from softplot.adjust.bal import read_bal


def write_bal(p, path) -> None:
    """BAL text: header, observations, 9 numbers per camera, 3 per point (full precision)."""
    with open(path, "w") as fh:
        fh.write(f"{p.n_cameras} {p.n_points} {p.n_observations}\n")
        for c, i, (x, y) in zip(p.cam_index, p.point_index, p.xy, strict=True):
            fh.write(f"{int(c)} {int(i)} {float(x)!r} {float(y)!r}\n")
        for v in np.concatenate([p.cameras.ravel(), p.points.ravel()]):
            fh.write(f"{float(v)!r}\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", help="the full BAL problem")
    ap.add_argument("out", help="the sub-problem to write")
    ap.add_argument("--cameras", type=int, default=8, help="first N cameras (default 8)")
    a = ap.parse_args()
    write_bal(read_bal(a.source).subset(range(a.cameras)), a.out)


if __name__ == "__main__":
    main()
