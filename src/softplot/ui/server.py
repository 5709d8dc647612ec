"""The local web server of the stereo viewer (Starlette on uvicorn).

Routes (every one needs the access token, else 403)::

    GET /?token=T                    the page (sets the token as a same-site cookie, so the
                                     page's own module scripts load with it)
    GET /static/NAME                 the page's own files: a fixed list, never a path
    GET /api/info                    the session: scans (pyramid sizes), views
    GET /api/state                   the floating mark's state (JSON)
    GET /tile/EYE/LEVEL/TX/TY?lo=&hi=  a pyramid tile: integers only (EYE 0 left, 1 right),
                                     (tile + 2)^2 bytes uint8 (see softplot.ui.pyramid)
    WS  /ws                          operator input in, state out (softplot.ui.viewer)

Security: the server binds 127.0.0.1 only; the token is compared in constant time; the Host
header must be ``127.0.0.1:PORT`` or ``localhost:PORT`` (no DNS rebinding); a WebSocket's
Origin must be the page's own (``http://127.0.0.1:PORT`` or ``http://localhost:PORT``); no
route builds a filesystem path from the URL: tiles come from the session's two pyramids by
integer indices, static files from a table built at start-up.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import secrets
import socket
from pathlib import Path
from urllib.parse import parse_qs

from starlette.applications import Starlette
from starlette.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from softplot.errors import SoftplotError

__all__ = ["make_app", "bind", "new_token", "STATIC"]

STATIC_DIR = Path(__file__).parent / "static"
_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html"}
#: the page's files, read once: name -> (bytes, media type); nothing else is served
STATIC = {
    p.name: (p.read_bytes(), _TYPES[p.suffix])
    for p in sorted(STATIC_DIR.iterdir()) if p.suffix in _TYPES
}
COOKIE = "softplot-token-{port}"
_SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "default-src 'self'; connect-src 'self' ws://127.0.0.1:* "
                               "ws://localhost:*; img-src 'self' data:; frame-ancestors 'none'",
}


def new_token() -> str:
    """A random access token (32 bytes, URL-safe)."""
    return secrets.token_urlsafe(32)


def bind(port: int | None) -> socket.socket:
    """A listening socket on 127.0.0.1 (``port`` 0 or None: a free one).

    Raises :class:`SoftplotError` (one line) when the port is in use or not allowed.
    """
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        s.bind(("127.0.0.1", int(port or 0)))
        s.listen(64)
    except OSError as exc:
        s.close()
        why = "in use" if exc.errno in (98, 48, 10048) else (exc.strerror or str(exc))
        raise SoftplotError(f"cannot listen on 127.0.0.1:{port}: port {why} "
                            "(choose another with --port, or --port 0 for a free one)") \
            from None
    return s


class Guard:
    """ASGI middleware: token, Host and (WebSocket) Origin checks before any route."""

    def __init__(self, app, token: str, port_ref: dict):
        self.app = app
        self.token = token.encode()
        self.port_ref = port_ref

    def _hosts(self) -> set[bytes]:
        p = self.port_ref["port"]
        return {f"127.0.0.1:{p}".encode(), f"localhost:{p}".encode()}

    def _authorised(self, scope) -> bool:
        headers = dict(scope.get("headers") or [])
        if headers.get(b"host") not in self._hosts():
            return False
        if scope["type"] == "websocket":
            origin = headers.get(b"origin")
            if origin not in {b"http://" + h for h in self._hosts()}:
                return False
        q = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        cands = q.get("token", [])[:1]
        if b"x-softplot-token" in headers:
            cands.append(headers[b"x-softplot-token"].decode("latin-1"))
        cookie = headers.get(b"cookie", b"").decode("latin-1")
        name = COOKIE.format(port=self.port_ref["port"])
        for part in cookie.split(";"):
            k, _, v = part.strip().partition("=")
            if k == name:
                cands.append(v)
        return any(hmac.compare_digest(c.encode(), self.token) for c in cands)

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        if self._authorised(scope):
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            await receive()  # websocket.connect
            await send({"type": "websocket.close", "code": 1008})
            return
        resp = PlainTextResponse("403 forbidden: this page needs its access token",
                                 status_code=403, headers={"Cache-Control": "no-store"})
        await resp(scope, receive, send)


def make_app(viewer, token: str, port_ref: dict):
    """The ASGI app of ``viewer`` (a :class:`softplot.ui.viewer.Viewer`) guarded by
    ``token``; ``port_ref["port"]`` is the port the page is served on (Host checks)."""

    async def page(request):
        body = STATIC["index.html"][0]
        r = HTMLResponse(body, headers=_SECURITY_HEADERS)
        q = request.query_params.get("token")
        if q:
            r.set_cookie(COOKIE.format(port=port_ref["port"]), q, httponly=True,
                         samesite="strict", path="/")
        return r

    async def static(request):
        item = STATIC.get(request.path_params["name"])
        if item is None:
            return PlainTextResponse("404 not found", status_code=404)
        return Response(item[0], media_type=item[1], headers=_SECURITY_HEADERS)

    async def info(request):
        return JSONResponse(viewer.info(), headers={"Cache-Control": "no-store"})

    async def state(request):
        with viewer.lock:
            st = viewer.state()
        return JSONResponse(st, headers={"Cache-Control": "no-store"})

    async def features(request):
        with viewer.lock:
            f = viewer.feature_pixels()
        return JSONResponse(f, headers={"Cache-Control": "no-store"})

    async def tile(request):
        pp = request.path_params
        eye = pp["eye"]
        if eye not in (0, 1):
            return PlainTextResponse("404 no such eye", status_code=404)
        pyr = viewer.pyramids["left" if eye == 0 else "right"]
        try:
            lo = int(request.query_params.get("lo", pyr.window[0]))
            hi = int(request.query_params.get("hi", pyr.window[1]))
        except ValueError:
            return PlainTextResponse("400 lo and hi must be integers", status_code=400)
        if not (0 <= lo < hi <= pyr.full):
            return PlainTextResponse("400 window out of range", status_code=400)
        try:
            data = pyr.tile(pp["level"], pp["tx"], pp["ty"], lo, hi)
        except IndexError:
            return PlainTextResponse("404 no such tile", status_code=404)
        return Response(data, media_type="application/octet-stream",
                        headers={"Cache-Control": "private, max-age=3600"})

    async def ws(websocket: WebSocket):
        await websocket.accept()
        try:
            while True:
                text = await websocket.receive_text()
                try:
                    msg = json.loads(text)
                    reply = await asyncio.to_thread(viewer.handle, msg) \
                        if viewer.motors_spec != "virtual" else viewer.handle(msg)
                except (SoftplotError, ValueError, TypeError) as exc:
                    seq = msg.get("seq") if isinstance(locals().get("msg"), dict) else None
                    with viewer.lock:
                        st = viewer.state()
                    reply = {"type": "error", "seq": seq, "message": str(exc).splitlines()[0]
                             if str(exc) else type(exc).__name__, "state": st}
                await websocket.send_text(json.dumps(reply))
        except WebSocketDisconnect:
            pass

    routes = [
        Route("/", page),
        Route("/static/{name}", static),
        Route("/api/info", info),
        Route("/api/state", state),
        Route("/api/features", features),
        Route("/tile/{eye:int}/{level:int}/{tx:int}/{ty:int}", tile),
        WebSocketRoute("/ws", ws),
    ]
    app = Starlette(routes=routes)
    return Guard(app, token, port_ref)


class Running:
    """A server started by :func:`run_in_thread`: ``url`` (with the token), ``port``,
    ``token``; :meth:`stop` shuts it down."""

    def __init__(self, server, thread, port: int, token: str):
        self.server, self.thread, self.port, self.token = server, thread, port, token
        self.base = f"http://127.0.0.1:{port}"
        self.url = f"{self.base}/?token={token}"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


def run_in_thread(viewer, port: int = 0) -> Running:
    """Serve ``viewer`` from a background thread (tests, benchmarks); returns when listening."""
    import threading
    import time

    import uvicorn

    sock = bind(port)
    real = sock.getsockname()[1]
    token = new_token()
    app = make_app(viewer, token, {"port": real})
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off",
                                           access_log=False, ws_ping_interval=None))
    th = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    th.start()
    t0 = time.monotonic()
    while not server.started and time.monotonic() - t0 < 10:
        time.sleep(0.01)
    return Running(server, th, real, token)
