"""Procedure reports: headings, text, tables and figures, written as one self-contained HTML file
(PNG figures embedded as data URIs) or as Markdown with the PNG figures in a folder beside it.

The format follows the file name: ``.html`` / ``.htm`` gives HTML, ``.md`` gives Markdown plus a
``<stem>_files/`` folder. Figures are rendered to PNG when they are added (matplotlib's Agg
backend through :func:`new_figure`, no pyplot state, safe in any thread), so a report holds bytes
and text only.

```python
rep = Report("Sensor calibration")
rep.section("Result")
rep.text("sensor2flange from 18 sweeps.")
rep.table(["parameter", "value", "1 sigma"], [["x (mm)", "60.012", "0.004"]])
fig, ax = new_figure()
ax.hist(residuals_um, bins=50)
rep.figure(fig, "Residuals of the joint refinement")
rep.write("report.html")
```

matplotlib is an optional dependency (the ``plot`` extra): :func:`have_matplotlib` says whether
figures can be drawn; callers skip them (and say so in the report) when it cannot.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from wristscan.daemon.io.atomic import write_atomic

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["Report", "axis_equal_3d", "blank_figure", "have_matplotlib", "new_figure"]

log = logging.getLogger(__name__)

_DPI = 110


def have_matplotlib() -> bool:
    """True when matplotlib can be imported (figures can be drawn)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def new_figure(
    nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float] = (7.0, 4.0), **kw: Any
) -> tuple[Figure, Any]:
    """A figure on an Agg canvas and its axes (as ``plt.subplots`` returns them), without pyplot.

    Extra keywords go to ``Figure.subplots`` (``subplot_kw={"projection": "3d"}``, ``sharey``...).
    Raises ``ImportError`` naming the ``plot`` extra when matplotlib is missing."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("figures need matplotlib: pip install 'wristscan[plot]'") from exc
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, **kw) if nrows and ncols else None
    return fig, axes


def blank_figure(figsize: tuple[float, float] = (7.0, 4.0)) -> Figure:
    """A figure on an Agg canvas without axes (add them with ``fig.add_subplot``)."""
    fig, _ = new_figure(0, 0, figsize=figsize)
    return fig


@dataclass(frozen=True)
class _Heading:
    title: str
    level: int


@dataclass(frozen=True)
class _Text:
    text: str
    preformatted: bool


@dataclass(frozen=True)
class _Table:
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    caption: str


@dataclass(frozen=True)
class _Image:
    name: str
    png: bytes
    caption: str


_Item = _Heading | _Text | _Table | _Image


def _cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _slug(text: str) -> str:
    s = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return s[:40] or "figure"


class Report:
    """An ordered list of report items, written as HTML or Markdown (see the module doc)."""

    def __init__(self, title: str, subtitle: str = "") -> None:
        self.title = title
        self.subtitle = subtitle
        self.created_utc = datetime.now(UTC)
        self._items: list[_Item] = []
        self._names: set[str] = set()

    # ------------------------------------------------------------------ building
    def section(self, title: str, text: str = "", level: int = 2) -> None:
        """A heading (``level`` 2 = section, 3 = subsection), optionally followed by text."""
        if level not in (2, 3, 4):
            raise ValueError(f"heading level must be 2, 3 or 4, got {level}")
        self._items.append(_Heading(title, level))
        if text:
            self.text(text)

    def text(self, text: str, preformatted: bool = False) -> None:
        """A paragraph of plain text (blank lines separate paragraphs), or a preformatted block
        (fixed-width, kept as is)."""
        self._items.append(_Text(text, preformatted))

    def table(
        self, header: Sequence[str], rows: Sequence[Sequence[object]], caption: str = ""
    ) -> None:
        """A table: every row has as many cells as ``header``; floats print with 6 digits (format
        them yourself for units-aware rounding)."""
        h = tuple(str(c) for c in header)
        body = tuple(tuple(_cell(c) for c in r) for r in rows)
        for i, r in enumerate(body):
            if len(r) != len(h):
                raise ValueError(f"table row {i} has {len(r)} cells, the header {len(h)}")
        self._items.append(_Table(h, body, caption))

    def figure(self, fig: Figure, caption: str = "", name: str | None = None) -> None:
        """Render ``fig`` to PNG now and add it (the figure can be discarded afterwards)."""
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=_DPI)
        base = _slug(name or caption or f"figure-{len(self._items)}")
        unique, k = base, 2
        while unique in self._names:
            unique, k = f"{base}-{k}", k + 1
        self._names.add(unique)
        self._items.append(_Image(unique, buf.getvalue(), caption))

    @property
    def n_figures(self) -> int:
        return sum(isinstance(i, _Image) for i in self._items)

    # ------------------------------------------------------------------ rendering
    def to_html(self) -> str:
        """One self-contained HTML document (figures embedded as PNG data URIs)."""
        e = html.escape
        out = [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{e(self.title)}</title>",
            "<style>body{font-family:sans-serif;max-width:980px;margin:2em auto;padding:0 1em;"
            "line-height:1.4}table{border-collapse:collapse;margin:.5em 0}"
            "td,th{border:1px solid #bbb;padding:.2em .6em;text-align:right}"
            "th{background:#eee}td:first-child,th:first-child{text-align:left}"
            "figure{margin:1em 0}img{max-width:100%}figcaption,caption{color:#444;"
            "font-size:.9em}pre{background:#f6f6f6;padding:.6em;overflow-x:auto}</style>",
            "</head><body>",
            f"<h1>{e(self.title)}</h1>",
        ]
        if self.subtitle:
            out.append(f"<p>{e(self.subtitle)}</p>")
        out.append(f"<p><small>created {self._stamp()}</small></p>")
        for item in self._items:
            if isinstance(item, _Heading):
                out.append(f"<h{item.level}>{e(item.title)}</h{item.level}>")
            elif isinstance(item, _Text):
                if item.preformatted:
                    out.append(f"<pre>{e(item.text)}</pre>")
                else:
                    out.extend(f"<p>{e(p.strip())}</p>" for p in item.text.split("\n\n"))
            elif isinstance(item, _Table):
                out.append("<table>")
                if item.caption:
                    out.append(f"<caption>{e(item.caption)}</caption>")
                out.append("<tr>" + "".join(f"<th>{e(c)}</th>" for c in item.header) + "</tr>")
                for r in item.rows:
                    out.append("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>")
                out.append("</table>")
            else:
                data = base64.b64encode(item.png).decode("ascii")
                out.append(
                    f'<figure><img alt="{e(item.caption or item.name)}" '
                    f'src="data:image/png;base64,{data}">'
                    + (f"<figcaption>{e(item.caption)}</figcaption>" if item.caption else "")
                    + "</figure>"
                )
        out.append("</body></html>")
        return "\n".join(out) + "\n"

    def to_markdown(self, image_dir: str) -> tuple[str, dict[str, bytes]]:
        """The Markdown text and the PNG files it links to (``image_dir/<name>.png``)."""
        out = [f"# {self.title}", ""]
        if self.subtitle:
            out += [self.subtitle, ""]
        out += [f"_created {self._stamp()}_", ""]
        files: dict[str, bytes] = {}
        for item in self._items:
            if isinstance(item, _Heading):
                out += ["#" * item.level + " " + item.title, ""]
            elif isinstance(item, _Text):
                out += (["```", item.text, "```"] if item.preformatted else [item.text]) + [""]
            elif isinstance(item, _Table):
                if item.caption:
                    out += [f"_{item.caption}_", ""]
                esc = [[c.replace("|", "\\|") for c in r] for r in (item.header, *item.rows)]
                out.append("| " + " | ".join(esc[0]) + " |")
                out.append("|" + "|".join(["---"] + ["---:"] * (len(item.header) - 1)) + "|")
                out += ["| " + " | ".join(r) + " |" for r in esc[1:]]
                out.append("")
            else:
                fname = f"{item.name}.png"
                files[fname] = item.png
                out += [f"![{item.caption or item.name}]({image_dir}/{fname})", ""]
                if item.caption:
                    out += [f"_{item.caption}_", ""]
        return "\n".join(out), files

    def write(self, path: str | os.PathLike[str]) -> Path:
        """Write the report; the suffix chooses the format (``.html``/``.htm`` or ``.md``).

        Files are written to a temporary name and renamed, so a report appears whole or not at
        all. Markdown figures go to ``<stem>_files/`` beside the file."""
        target = Path(path)
        suffix = target.suffix.lower()
        if suffix in (".html", ".htm"):
            write_atomic(target, self.to_html().encode("utf-8"))
        elif suffix == ".md":
            image_dir = f"{target.stem}_files"
            text, files = self.to_markdown(image_dir)
            if files:
                folder = target.parent / image_dir
                folder.mkdir(parents=True, exist_ok=True)
                for name, data in files.items():
                    write_atomic(folder / name, data)
            write_atomic(target, text.encode("utf-8"))
        else:
            raise ValueError(f"report {target}: the name must end in .html, .htm or .md")
        log.info("wrote report %s", target)
        return target

    def _stamp(self) -> str:
        return self.created_utc.strftime("%Y-%m-%d %H:%M:%S UTC")


def axis_equal_3d(ax: Axes, points: Any) -> None:
    """Equal scales on a 3-D axes around ``points`` (N, 3), so spheres look round."""
    import numpy as np

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = (p.max(axis=0) + p.min(axis=0)) / 2
    half = float(np.max(p.max(axis=0) - p.min(axis=0))) / 2 or 1.0
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)  # type: ignore[attr-defined]
