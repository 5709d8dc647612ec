"""The browser stereo workstation: ``softplot view SESSION``.

:mod:`softplot.ui.pyramid` (image pyramids of the scans, cached by content),
:mod:`softplot.ui.viewer` (the session, its plotter and motors behind the page),
:mod:`softplot.ui.server` (the local, token-guarded web server) and ``static/`` (the page:
plain ES modules and WebGL2). See docs/viewer.md.
"""
