"""Benchmark: the viewer's tile serving and its input-to-frame latency.

1. Tiles: a synthetic session with two ``--size`` px 16-bit scans (window/level LUT applied
   per tile); ``--tiles`` random level-0..2 tiles fetched over HTTP (keep-alive, one client)
   from ``softplot view``'s server running in this process; median and 95th percentile
   milliseconds per tile, and the same cut in-process (``Pyramid.tile``).
2. Latency, measured inside the page (Debian chromium, headless, software WebGL2 here): the
   carriage is moved ``--moves`` times (``softplot.setCarriage``, one message per frame); per
   move, the time from the message leaving to the end of the frame that shows the answer (with
   ``gl.finish``, so the GPU work counts), in ms and in 60 Hz frames.

    OPENBLAS_NUM_THREADS=1 python tools/bench_view.py [--size 4096] [--tiles 400] [--moves 120]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def pct(v, q):
    return float(np.percentile(np.asarray(v), q))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--tiles", type=int, default=400)
    ap.add_argument("--moves", type=int, default=120)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=800)
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import httpx

    from softplot.ui.server import run_in_thread
    from softplot.ui.viewer import Viewer
    from view_helpers import make_session

    tmp = Path(tempfile.mkdtemp(prefix="bench-view-"))
    try:
        t = make_session(tmp, size=a.size, pixel_mm=0.2 * 1025 / a.size, dtype=np.uint16)
        v = Viewer(t["folder"], cache=tmp / "cache")
        run = run_in_thread(v)
        pyr = v.pyramids["left"]
        rng = np.random.default_rng(1)
        reqs = []
        for _ in range(a.tiles):
            L = int(rng.integers(0, min(3, len(pyr.sizes))))
            nx, ny = pyr.tiles(L)
            reqs.append((int(rng.integers(0, 2)), L, int(rng.integers(0, nx)),
                         int(rng.integers(0, ny))))
        lo, hi = pyr.window
        http = []
        with httpx.Client(base_url=run.base, headers={"X-Softplot-Token": run.token}) as c:
            c.get(f"/tile/0/0/0/0?lo={lo}&hi={hi}")  # connection up
            for eye, L, tx, ty in reqs:
                t0 = time.perf_counter()
                r = c.get(f"/tile/{eye}/{L}/{tx}/{ty}?lo={lo}&hi={hi + 1}")
                http.append((time.perf_counter() - t0) * 1e3)
                assert r.status_code == 200 and len(r.content) == (pyr.tile_size + 2) ** 2
        cut = []
        for eye, L, tx, ty in reqs:
            t0 = time.perf_counter()
            v.pyramids["left" if eye == 0 else "right"].tile(L, tx, ty, lo, hi + 2)
            cut.append((time.perf_counter() - t0) * 1e3)
        print(f"scans {a.size} x {a.size} uint16, tile {pyr.tile_size} (+2 gutter), "
              f"{a.tiles} random tiles of levels 0-2")
        print(f"tile over HTTP: median {statistics.median(http):.2f} ms, "
              f"p95 {pct(http, 95):.2f} ms")
        print(f"tile cut in-process: median {statistics.median(cut):.3f} ms, "
              f"p95 {pct(cut, 95):.3f} ms")

        import asyncio
        import json

        import websockets

        async def ws_round_trips():
            url = f"ws://127.0.0.1:{run.port}/ws?token={run.token}"
            out = []
            async with websockets.connect(url, origin=run.base) as ws:
                st = v.state()
                for i in range(200):
                    t0 = time.perf_counter()
                    await ws.send(json.dumps({"op": "cycle", "X": st["X"] + 0.001 * i,
                                              "Y": st["Y"], "seq": i}))
                    await ws.recv()
                    out.append((time.perf_counter() - t0) * 1e3)
            return out
        rt = asyncio.run(ws_round_trips())
        print(f"carriage message -> plotter cycle -> state back (WebSocket, no page): median "
              f"{statistics.median(rt):.2f} ms, p95 {pct(rt, 95):.2f} ms")

        from playwright.sync_api import sync_playwright

        exe = shutil.which("chromium") or shutil.which("chromium-browser")
        if exe is None:
            print("latency: no chromium installed; skipped")
            return
        args = ["--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
                "--disable-background-networking", "--disable-component-update"]
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path=exe, headless=True, args=args)
            page = b.new_page(viewport={"width": a.width, "height": a.height})
            page.goto(run.url)
            page.evaluate("window.softplot.ready")
            page.evaluate("softplot.setZoom(1).then(() => softplot.setView('anaglyph-dubois'))")
            page.evaluate("softplot.setLatencySync(true); softplot.clearLatencies()")
            res = page.evaluate(f"""(async () => {{
              const s = softplot.state();
              const frames = [];
              let last = performance.now();
              for (let i = 0; i < {a.moves}; i++) {{
                await softplot.setCarriage(s.X + 0.02 * Math.sin(i / 7), s.Y + 0.01 * i % 3);
                const now = performance.now(); frames.push(now - last); last = now;
              }}
              const draw = [];
              for (let i = 0; i < 30; i++) {{
                const t0 = performance.now(); await softplot.setSwap(false);
                draw.push(performance.now() - t0);
              }}
              return {{lat: softplot.latencies(), frames, draw}};
            }})()""")
            renderer = page.evaluate("""(() => { const g = document.createElement('canvas')
              .getContext('webgl2'); const d = g.getExtension('WEBGL_debug_renderer_info');
              return d ? g.getParameter(d.UNMASKED_RENDERER_WEBGL) : g.getParameter(g.RENDERER);
            })()""")
            b.close()
        lat = res["lat"]
        print(f"input-to-frame latency in the page ({renderer}, {a.width} x {a.height}, "
              f"anaglyph, zoom 1): median {statistics.median(lat):.1f} ms "
              f"= {statistics.median(lat) / (1000 / 60):.2f} frames at 60 Hz, "
              f"p95 {pct(lat, 95):.1f} ms, over {len(lat)} moves")
        print(f"a frame alone (both eyes + composite, from the request to gl.finish): median "
              f"{statistics.median(res['draw']):.1f} ms")
        run.stop()
        v.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
