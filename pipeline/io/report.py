"""`report.html`: one self-contained page per run (previews embedded as base64 data URIs).

It shows what came out at a glance: warnings first, then the grids, stages, components,
field-quality numbers and output files from the manifest, then the preview images.
"""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pipeline.util.atomic import atomic_path

SURFACE_PNG = "surface_mesh.png"  # the surface preview, shown first (pipeline.io.previews writes it)

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:1.5em auto;max-width:1250px;
color:#222;padding:0 1em}
h1{margin-bottom:.2em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f0f0f0}td.num{text-align:right;font-variant-numeric:tabular-nums}
.warn{background:#fff4ce;border:1px solid #e0b400;padding:.5em 1em}.ok{color:#2a7a2a}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}figcaption{color:#555}
.meta{color:#555}code{background:#f5f5f5;padding:0 .2em}
"""


def fmt(value: Any) -> str:
    """Compact text for a manifest value (floats to 6 significant digits, nested lists/dicts)."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return ", ".join(f"{k}={fmt(v)}" for k, v in value.items())
    return str(value)


def _cell(value: Any) -> str:
    cls = ' class="num"' if isinstance(value, int | float) and not isinstance(value, bool) else ""
    return f"<td{cls}>{html.escape(fmt(value))}</td>"


def table(rows: list[Mapping[str, Any]], columns: list[str] | None = None) -> str:
    """HTML table of dict rows; columns default to the union of keys in first-seen order."""
    if not rows:
        return "<p class='meta'>none</p>"
    cols = columns or list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(_cell(r.get(c, "")) for c in cols) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def grids_rows(grids: Mapping[str, Mapping[str, Any]]) -> list[dict]:
    first = ["class", "type", "active_voxels", "bbox", "min", "max"]
    rows = []
    for name, entry in grids.items():
        row: dict[str, Any] = {"grid": name}
        row.update({k: entry[k] for k in first if k in entry})
        row.update({k: v for k, v in entry.items() if k not in first})
        rows.append(row)
    return rows


def stages_rows(stages: Iterable[Mapping[str, Any]]) -> list[dict]:
    return [{"stage": s.get("name", "?"), "seconds": s.get("seconds", ""), "stats": s.get("stats", {})}
            | {k: v for k, v in s.items() if k not in ("name", "seconds", "stats")} for s in stages]


def components_html(comp: Mapping[str, Any] | None) -> str:
    if not comp:
        return "<p class='meta'>no component stage in this run</p>"
    volumes = list(comp.get("volumes", []))
    total = sum(volumes) or 1.0
    rows = [{"label": n + 1, "volume": v, "fraction": v / total} for n, v in enumerate(volumes)]
    extra = {k: v for k, v in comp.items() if k not in ("count", "volumes")}
    more = f"<p class='meta'>{html.escape(fmt(extra))}</p>" if extra else ""
    return f"<p>count: <b>{html.escape(fmt(comp.get('count', len(volumes))))}</b></p>{more}{table(rows)}"


def quality_rows(quality: Mapping[str, Any] | None) -> list[dict]:
    if not quality:
        return []
    return [{"grid": g, **(s if isinstance(s, Mapping) else {"value": s})} for g, s in quality.items()]


def warnings_html(warnings: list) -> str:
    if not warnings:
        return "<p class='ok'>no warnings</p>"
    items = "".join(f"<li>{html.escape(fmt(w))}</li>" for w in warnings)
    return f"<div class='warn'><b>{len(warnings)} warning(s)</b><ul>{items}</ul></div>"


def image_html(path: Path) -> str:
    """A figure with the PNG embedded as a base64 data URI."""
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    name = html.escape(path.name)
    return (f"<figure><img alt='{name}' src='data:image/png;base64,{data}'>"
            f"<figcaption>{name}</figcaption></figure>")


def outputs_rows(outputs: Iterable[Mapping[str, Any]]) -> list[dict]:
    return [dict(o) for o in outputs]


def render_report(manifest: Mapping[str, Any], images: Iterable[Path] = ()) -> str:
    """The HTML text of the report."""
    name = html.escape(str(manifest.get("name", "run")))
    domain = manifest.get("domain", {})
    head = (f"<p class='meta'>config <code>{html.escape(str(manifest.get('config', '')))}</code> "
            f"sha256 <code>{html.escape(str(manifest.get('config_sha256', ''))[:16])}</code> · "
            f"domain {html.escape(fmt(domain))}</p>")
    sections = [
        ("Warnings", warnings_html(list(manifest.get("warnings", [])))),
        ("Grids", table(grids_rows(manifest.get("grids", {})))),
        ("Stages", table(stages_rows(manifest.get("stages", [])))),
        ("Components", components_html(manifest.get("components"))),
        ("Field quality", table(quality_rows(manifest.get("quality")))),
        ("Outputs", table(outputs_rows(manifest.get("outputs", [])))),
        ("Previews", "".join(image_html(p) for p in images) or "<p class='meta'>no previews</p>"),
    ]
    body = "".join(f"<h2>{title}</h2>{content}" for title, content in sections)
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>frepvdb: {name}</title>"
            f"<style>{_CSS}</style></head><body><h1>frepvdb run: {name}</h1>{head}{body}</body></html>\n")


def write_report(path: str | os.PathLike, manifest: Mapping[str, Any],
                 images: Iterable[str | os.PathLike] | None = None) -> Path:
    """Write ``report.html`` atomically. ``images`` default to ``<folder>/previews/*.png`` (surface first)."""
    path = Path(path)
    if images is None:
        found = (path.parent / "previews").glob("*.png")
        images = sorted(found, key=lambda p: (p.name != SURFACE_PNG, p.name))
    text = render_report(manifest, [Path(p) for p in images])
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
