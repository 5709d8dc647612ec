"""softplot view: pyramids, the token-guarded local server and the command (issue: browser
stereo workstation, points 1, 2, 6, 9).

Pyramid levels are exact 2x2 means, tiles carry a 1-px gutter of their neighbours, 16-bit
scans go through the window; the cache is keyed by content. Every route and the WebSocket
need the token, the loopback Host and (WebSocket) the page's Origin; tiles are typed
integers and no URL reaches the file system. The command prints the URL first, stops cleanly
on Ctrl-C with the journal intact, and reports moved/changed scans and a busy port in one
line.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from softplot.errors import SoftplotError
from softplot.ui.pyramid import build_pyramid
from softplot.ui.server import run_in_thread
from softplot.ui.viewer import Viewer
from view_helpers import make_session, pattern

CLI = [sys.executable, "-c", "from softplot.cli import main; main()"]


@pytest.fixture(scope="module")
def sess(tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    return make_session(d)


@pytest.fixture(scope="module")
def served(sess, tmp_path_factory):
    v = Viewer(sess["folder"], cache=tmp_path_factory.mktemp("cache"))
    run = run_in_thread(v)
    yield v, run
    run.stop()
    v.close()


# ------------------------------------------------------------------------------ pyramid
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_pyramid_levels_are_2x2_means_and_tiles_have_gutters(tmp_path, dtype):
    import tifffile

    rng = np.random.default_rng(5)
    h, w = 1031, 777  # odd sizes: the last row/column is averaged with itself
    full = 255 if dtype == np.uint8 else 65535
    img = rng.integers(0, full + 1, (h, w)).astype(dtype)
    p = tmp_path / "s.tif"
    tifffile.imwrite(p, img)
    pyr = build_pyramid(p, tmp_path / "cache")
    assert pyr.sizes[:3] == [(777, 1031), (389, 516), (195, 258)]
    assert max(pyr.sizes[-1]) <= 256 and max(pyr.sizes[-2]) > 256
    # level 1 against the 2x2 mean (edge repeated), to rounding
    e = np.pad(img.astype(np.float64), ((0, 1), (0, 1)), mode="edge")[: 2 * 516, : 2 * 389]
    mean = e.reshape(516, 2, 389, 2).mean(axis=(1, 3))
    assert np.abs(pyr.levels[1].astype(np.float64) - mean).max() <= 0.5 + 1e-9
    lo, hi = (0, 255) if dtype == np.uint8 else (1000, 60000)
    lut = np.clip(np.rint((np.arange(full + 1) - lo) * (255.0 / (hi - lo))), 0, 255)
    lut = lut.astype(np.uint8)
    for level in (0, 1):
        a = np.asarray(pyr.levels[level])
        nx, ny = pyr.tiles(level)
        for tx, ty in {(0, 0), (1, 1), (nx - 1, ny - 1), (nx - 1, 0)}:
            t = np.frombuffer(pyr.tile(level, tx, ty, lo, hi), np.uint8).reshape(258, 258)
            rows = np.clip(np.arange(ty * 256 - 1, ty * 256 + 257), 0, a.shape[0] - 1)
            cols = np.clip(np.arange(tx * 256 - 1, tx * 256 + 257), 0, a.shape[1] - 1)
            assert np.array_equal(t, lut[a[np.ix_(rows, cols)]]), (level, tx, ty)
    for bad in ((0, pyr.tiles(0)[0], 0), (0, 0, pyr.tiles(0)[1]), (len(pyr.sizes), 0, 0),
                (-1, 0, 0), (0, -1, 0)):
        with pytest.raises(IndexError):
            pyr.tile(*bad)


def test_pyramid_cache_is_keyed_by_content(tmp_path):
    import tifffile

    a = pattern(600, 700)
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, a)
    one = build_pyramid(p, tmp_path / "c")
    stamp = (one.folder / "pyramid.json").stat().st_mtime_ns
    moved = tmp_path / "moved.tif"
    os.replace(p, moved)
    two = build_pyramid(moved, tmp_path / "c")  # moved, same content: reused, not rebuilt
    assert two.folder == one.folder
    assert (two.folder / "pyramid.json").stat().st_mtime_ns == stamp
    tifffile.imwrite(moved, a[::-1].copy())  # changed content: a new pyramid
    three = build_pyramid(moved, tmp_path / "c")
    assert three.folder != one.folder
    assert np.array_equal(np.asarray(three.levels[0]), a[::-1])


# ------------------------------------------------------------------------------ security
def _ws(url, origin):
    async def go():
        async with websockets.connect(url, origin=origin, open_timeout=5) as ws:
            await ws.send(json.dumps({"op": "state", "seq": 7}))
            return json.loads(await ws.recv())
    return asyncio.run(go())


ROUTES = ["/", "/static/main.js", "/api/info", "/api/state", "/api/features", "/tile/0/0/0/0"]


def test_every_route_needs_the_token(served):
    _, run = served
    get = lambda r, **kw: httpx.get(run.base + r, **kw).status_code  # no cookie kept
    wrong = "x" + run.token[1:] if run.token[0] != "x" else "y" + run.token[1:]
    for r in ROUTES:
        assert get(r) == 403, r
        assert get(r, params={"token": wrong}) == 403, r
        assert get(r, headers={"Cookie": f"softplot-token-{run.port}={wrong}"}) == 403, r
        assert get(r, params={"token": run.token}) == 200, r
        assert get(r, headers={"X-Softplot-Token": run.token}) == 200, r
        assert get(r, headers={"Cookie": f"softplot-token-{run.port}={run.token}"}) == 200, r
    base = f"ws://127.0.0.1:{run.port}/ws"
    with pytest.raises(websockets.InvalidStatus) as e:
        _ws(base, f"http://127.0.0.1:{run.port}")
    assert e.value.response.status_code == 403
    rep = _ws(f"{base}?token={run.token}", f"http://127.0.0.1:{run.port}")
    assert rep["seq"] == 7 and rep["type"] == "state"


def test_page_cookie_lets_its_own_modules_load(served):
    _, run = served
    with httpx.Client(base_url=run.base) as c:
        r = c.get("/", params={"token": run.token})
        assert r.status_code == 200 and "samesite=strict" in r.headers["set-cookie"].lower()
        assert "httponly" in r.headers["set-cookie"].lower()
        assert c.get("/static/gl.js").status_code == 200  # with the cookie only


def test_host_and_origin_must_be_the_loopback_page(served):
    _, run = served
    with httpx.Client(base_url=run.base, params={"token": run.token}) as c:
        for host in ("evil.example", f"evil.example:{run.port}", "127.0.0.1",
                     f"127.0.0.1:{run.port + 1}", f"localhost.evil:{run.port}"):
            assert c.get("/api/state", headers={"Host": host}).status_code == 403, host
        assert c.get("/api/state", headers={"Host": f"localhost:{run.port}"}).status_code == 200
    url = f"ws://127.0.0.1:{run.port}/ws?token={run.token}"
    for origin in ("http://evil.example", f"http://127.0.0.1:{run.port + 1}", "null"):
        with pytest.raises(websockets.InvalidStatus):
            _ws(url, origin)
    assert _ws(url, f"http://localhost:{run.port}")["type"] == "state"


def test_binds_loopback_only_and_serves_nothing_but_tiles_and_its_files(served, sess):
    v, run = served
    s = socket.create_connection(("127.0.0.1", run.port))
    assert s.getpeername()[0] == "127.0.0.1"
    s.close()
    sockets = [x.getsockname() for srv in run.server.servers for x in srv.sockets]
    assert sockets and all(a[0] == "127.0.0.1" for a in sockets)
    with httpx.Client(base_url=run.base, params={"token": run.token}) as c:
        for bad in ["/static/..%2Fviewer.py", "/static/../server.py", "/static/%2e%2e/__init__.py",
                    "/static/viewer.py", "/session.json", "/tile/2/0/0/0", "/tile/0/0/0/-1",
                    "/tile/0/x/0/0", "/tile/0/0/0/0.5", "/tile/0/99/0/0", "/tile/0/0/99/0",
                    "/tile/0/0/0/0/../../../etc/passwd", "/tile/0/0/%2e%2e/0", "/etc/passwd",
                    "/static/", "/static/index.html/.."]:
            r = c.get(bad)
            assert r.status_code in (404, 400, 405), bad
            assert b"softplot-session" not in r.content and b"import" not in r.content[:200]
        assert c.get("/tile/0/0/0/0", params={"lo": "1;rm"}).status_code == 400
        assert c.get("/tile/0/0/0/0", params={"lo": 9, "hi": 3}).status_code == 400
        t = c.get("/tile/1/0/1/2")
        assert t.status_code == 200 and len(t.content) == 258 * 258
        exp = v.pyramids["right"].tile(0, 1, 2)
        assert t.content == exp


def test_websocket_input_drives_the_plotter_and_bad_values_are_one_line(served, sess):
    _, run = served
    url = f"ws://127.0.0.1:{run.port}/ws?token={run.token}"

    async def go():
        async with websockets.connect(url, origin=f"http://127.0.0.1:{run.port}") as ws:
            out = []
            for m in ({"op": "drive", "X": 150.0, "Y": 0.0, "Z": 0.0, "seq": 1},
                      {"op": "cycle", "X": "1e9", "Y": 0, "seq": 2},
                      {"op": "cycle", "X": float("nan"), "Y": 0, "seq": 3},
                      {"op": "nonsense", "seq": 4}):
                await ws.send(json.dumps(m))
                out.append(json.loads(await ws.recv()))
            await ws.send("not json")
            out.append(json.loads(await ws.recv()))
            return out
    a, b, c, d, e = asyncio.run(go())
    assert a["type"] == "state" and np.allclose(a["state"]["object"], [150, 0, 0], atol=1e-6)
    for r in (b, c, d, e):
        assert r["type"] == "error" and "\n" not in r["message"] and r["message"]
    assert b["state"]["object"] == a["state"]["object"]  # bad input changed nothing
    with httpx.Client(base_url=run.base, params={"token": run.token}) as cl:
        st = cl.get("/api/state").json()
    for k in ("mode", "X", "Y", "DX", "DY", "px", "height", "object", "left_px", "right_px",
              "py", "zoom", "view", "frames"):
        assert k in st


# ------------------------------------------------------------------------------ the command
def _env():
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_view_prints_url_first_and_stops_cleanly_on_ctrl_c(tmp_path):
    t = make_session(tmp_path, size=301)
    p = subprocess.Popen([*CLI, "view", str(t["folder"]), "--no-browser",
                          "--cache", str(tmp_path / "c")], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=_env())
    try:
        line = p.stdout.readline().strip()
        m = re.fullmatch(r"http://127\.0\.0\.1:(\d+)/\?token=([A-Za-z0-9_-]{40,})", line)
        assert m, line
        port, token = int(m.group(1)), m.group(2)
        for _ in range(200):
            try:
                r = httpx.get(f"http://127.0.0.1:{port}/api/state", params={"token": token})
                break
            except httpx.ConnectError:
                time.sleep(0.05)
        assert r.status_code == 200 and r.json()["mode"] == "single"
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    finally:
        p.kill()
    assert p.returncode == 0, err
    assert "Traceback" not in err and "stopped" in err
    lines = (t["folder"] / "journal.jsonl").read_bytes().splitlines()
    recs = [json.loads(x) for x in lines]
    assert recs[-1]["type"] == "motors"


def test_port_in_use_moved_and_changed_scans_are_one_line(tmp_path):
    from softplot.cli import main

    t = make_session(tmp_path, size=301)
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    r = subprocess.run([*CLI, "view", str(t["folder"]), "--no-browser",
                        "--port", str(port), "--cache", str(tmp_path / "c")],
                       capture_output=True, text=True, env=_env(), timeout=60)
    busy.close()
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and f"127.0.0.1:{port}" in r.stderr and "in use" in r.stderr

    left = t["paths"]["left"]
    os.replace(left, tmp_path / "elsewhere.tif")
    with pytest.raises(SoftplotError, match=r"left scan is missing: expected at .*left\.tif"):
        Viewer(t["folder"], cache=tmp_path / "c")
    os.replace(tmp_path / "elsewhere.tif", left)
    data = bytearray(left.read_bytes())
    data[-1] ^= 0xFF
    left.write_bytes(bytes(data))
    r = subprocess.run([*CLI, "view", str(t["folder"]), "--no-browser",
                        "--cache", str(tmp_path / "c")],
                       capture_output=True, text=True, env=_env(), timeout=60)
    assert r.returncode == 2 and r.stdout == "" and r.stderr.count("\n") == 1, r.stderr
    assert "left scan has changed" in r.stderr and "left.tif" in r.stderr
    assert main is not None


def test_the_demo_session_opens_in_the_viewer(tmp_path):
    """``softplot demo`` writes OUT/session; the viewer opens it (scans, pyramids, the mark
    on the traced contours' model) and its first contour vertex is drawn at the scan pixels
    the session's model and film corrections give."""
    from softplot.pipeline.demo import DemoConfig, run_demo

    run_demo(tmp_path / "demo", DemoConfig(dpi=300, interval=20.0, vertices=12, tie_grid=4,
                                            n_check=4), progress=False, write_scans=True)
    v = Viewer(tmp_path / "demo" / "session", cache=tmp_path / "c")
    try:
        st = v.state()
        assert st["mode"] == "contour" and st["features"] >= 1
        w, h = v.pyramids["left"].width, v.pyramids["left"].height
        assert 0 <= st["left_px"][0] < w and 0 <= st["left_px"][1] < h
        f = v.feature_pixels()[0]
        XYZ = np.asarray(v.plotter.features[0].vertices, float)[:1]
        for side, photo in (("left", v.plotter.model.left), ("right", v.plotter.model.right)):
            instr = photo.photo_to_film(photo.project(XYZ))
            px = v.maps[side].frame.to_pixel(instr)[0]
            assert np.abs(np.array(f[side][0]) - px).max() < 1e-3
    finally:
        v.close()


def test_an_instrument_behind_the_viewer_shows_where_it_is(tmp_path):
    """--motors grbl:PORT: the plotter drives the GRBL controller (simulated on a pty); the
    state shows the carriage the controller reports, which after the move puts the mark on
    the driven point's image (within 0.05 px)."""
    from softplot.motors.simulator import GrblSimulator
    from view_helpers import truth_px

    t = make_session(tmp_path, size=301, left_offset=(44.0, -0.3))
    with GrblSimulator(time_scale=50) as sim:
        v = Viewer(t["folder"], motors=f"grbl:{sim.path}", cache=tmp_path / "c")
        try:
            P = t["points"][1]
            v.handle({"op": "drive", "X": P[0], "Y": P[1], "Z": P[2]})
            target = v.motors.target()
            assert v.motors.wait(10)
            st = v.state()
            assert np.allclose([st["DX"], st["DY"]], target, atol=1e-9)
            assert np.abs(np.array(st["left_px"]) - truth_px(t["model"], t["frame"], "left",
                                                             P)[0]).max() < 0.05
            assert np.abs(np.array(st["right_px"]) - truth_px(t["model"], t["frame"], "right",
                                                              P)[0]).max() < 0.05
        finally:
            v.close()
