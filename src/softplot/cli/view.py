"""``softplot view``: the plotting session in the browser (stereo viewer, floating mark)."""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.command("view")
@click.argument("session", type=click.Path(path_type=Path))
@click.option("--port", type=click.IntRange(0, 65535), default=0, show_default=True,
              help="Port on 127.0.0.1 (0: a free one).")
@click.option("--no-browser", is_flag=True, help="Do not open the page in the default browser.")
@click.option("--motors", default="virtual", show_default=True, metavar="virtual|grbl:PORT",
              help="virtual: the secondary carriage moves the left image on screen; "
                   "grbl:PORT drives an instrument on that serial port (the screen then shows "
                   "where the instrument is).")
@click.option("--cache", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder for the scans' image pyramids (default: $SOFTPLOT_CACHE or "
                   "~/.cache/softplot); a pyramid is built once per scan content.")
def command(session: Path, port: int, no_browser: bool, motors: str, cache: Path | None):
    """Open plotting SESSION in the browser: stereo view, floating mark, plotting.

    The first line printed is the page's address (with its access token). Ctrl-C stops the
    server; the session's journal is kept.
    """
    import uvicorn

    from softplot.ui.server import bind, make_app, new_token
    from softplot.ui.viewer import Viewer

    sock = bind(port)
    try:
        real_port = sock.getsockname()[1]
        viewer = Viewer(session, motors=motors, cache=cache)
    except BaseException:
        sock.close()
        raise
    try:
        token = new_token()
        url = f"http://127.0.0.1:{real_port}/?token={token}"
        click.echo(url)
        sys.stdout.flush()
        if not no_browser:
            import webbrowser

            webbrowser.open(url)
        app = make_app(viewer, token, {"port": real_port})
        config = uvicorn.Config(app, log_level="warning", lifespan="off", access_log=False,
                                ws_ping_interval=None)
        server = uvicorn.Server(config)
        click.echo("softplot view: serving; Ctrl-C to stop", err=True)
        try:
            server.run(sockets=[sock])  # Ctrl-C: uvicorn shuts down, then re-raises it
        except KeyboardInterrupt:
            pass
    finally:
        viewer.close()
        sock.close()
        click.echo(f"softplot view: stopped; journal of {session} saved", err=True)
