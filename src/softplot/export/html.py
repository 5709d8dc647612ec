"""Self-contained HTML reports: text, tables and matplotlib figures embedded as base64 PNG.

One file that opens in any browser, with nothing beside it. Build a :class:`Report`, add
sections, write it::

    rep = Report("softplot process")
    rep.heading("Summary")
    rep.table(["scan", "rms px"], rows)
    rep.figure(fig)            # a matplotlib Figure; closed after embedding
    rep.write(path)
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path

_STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;
max-width:1100px;color:#222;line-height:1.4}
h1{border-bottom:2px solid #444;padding-bottom:.2em}\
h2{margin-top:1.6em;border-bottom:1px solid #bbb}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}th{background:#eee}
td:first-child,th:first-child{text-align:left}
.warn{color:#a40}.ok{color:#060}.bad{color:#b00}figure{margin:1em 0}img{max-width:100%}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto}
"""


@dataclass
class Report:
    """An HTML report under construction."""

    title: str
    parts: list[str] = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> "Report":
        self.parts.append(f"<h{level}>{html.escape(text)}</h{level}>")
        return self

    def paragraph(self, text: str, cls: str | None = None) -> "Report":
        c = f' class="{cls}"' if cls else ""
        self.parts.append(f"<p{c}>{html.escape(text)}</p>")
        return self

    def preformatted(self, text: str) -> "Report":
        self.parts.append(f"<pre>{html.escape(text)}</pre>")
        return self

    def table(self, header: list[str], rows: list[list], floatfmt: str = "{:.4g}") -> "Report":
        """A table; floats are formatted with ``floatfmt``, None shows as an empty cell."""

        def cell(v) -> str:
            if v is None:
                return ""
            if isinstance(v, float):
                return floatfmt.format(v)
            return html.escape(str(v))

        head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
        self.parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        return self

    def figure(self, fig, caption: str = "", dpi: int = 100) -> "Report":
        """Embed a matplotlib figure as a PNG data URI (the figure is closed)."""
        import matplotlib.pyplot as plt

        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
        plt.close(fig)
        return self.png(buf.getvalue(), caption)

    def png(self, data: bytes, caption: str = "") -> "Report":
        """Embed PNG bytes."""
        b64 = base64.b64encode(data).decode("ascii")
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self.parts.append(f'<figure><img src="data:image/png;base64,{b64}" alt="">{cap}</figure>')
        return self

    def render(self) -> str:
        """The whole document as a string."""
        t = html.escape(self.title)
        return (
            f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{t}</title>"
            f"<style>{_STYLE}</style></head><body><h1>{t}</h1>\n"
            + "\n".join(self.parts)
            + "\n</body></html>\n"
        )

    def write(self, path: str | Path) -> Path:
        """Write the report to ``path`` (UTF-8) and return the path."""
        p = Path(path)
        p.write_text(self.render(), encoding="utf-8")
        return p
