"""One self-contained HTML file per report: opens offline, from disk, with nothing to fetch.

Every command that writes a Markdown report (a run, a sweep, a real capture, a pose evaluation)
also writes ``report.html`` (``sweep.html``) beside it with :func:`write_html`: the same tables
(the Markdown converted by Python-Markdown), every figure embedded as a PNG data URI, the
configuration that produced it and its provenance (package, OpenCV, NumPy and Python versions,
seeds, fingerprints). Two interactions, in a few lines of inline script: a figure opens full
size and zooms with the mouse wheel about the pointer (drag to pan) to read a residual map, and
pointing at a method's name in any table highlights that method's row or column in every table.
No script, style or font comes from the network.
"""

from __future__ import annotations

import base64
import html
import platform
from pathlib import Path

import markdown as md

from ..core.files import write_text

_STYLE = """
body { font: 15px/1.45 system-ui, sans-serif; margin: 2em auto; max-width: 1200px;
       padding: 0 1em; color: #1d1d1f; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; margin-top: 1.8em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 13px;
        font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f2f2f4; }
tr:hover td { background: #f7f7ff; }
.hl { background: #fff2b3 !important; }
figure { display: inline-block; margin: 0.6em 1em 0.6em 0; vertical-align: top; }
figure img { max-width: 560px; width: 100%; cursor: zoom-in; border: 1px solid #eee; }
figcaption { font-size: 12px; color: #555; max-width: 560px; }
pre { background: #f6f6f8; padding: 0.8em; overflow-x: auto; font-size: 12px; }
#zoom { position: fixed; inset: 0; background: rgba(0, 0, 0, 0.85); display: none;
        overflow: hidden; cursor: grab; z-index: 10; }
#zoom img { position: absolute; left: 0; top: 0; transform-origin: 0 0; max-width: none; }
#zoom .hint { position: fixed; right: 1em; top: 0.6em; color: #eee; font-size: 12px; }
"""

# Zoom about the pointer (wheel), pan by dragging, close with a click that did not drag or Esc;
# highlight every table cell that names the method under the pointer.
_SCRIPT = """
(function () {
  const box = document.getElementById('zoom'), big = box.querySelector('img');
  let s = 1, x = 0, y = 0, drag = null, moved = false;
  const show = () => { big.style.transform = `translate(${x}px,${y}px) scale(${s})`; };
  document.querySelectorAll('figure img').forEach(img => img.addEventListener('click', () => {
    big.src = img.src; box.style.display = 'block';
    s = Math.min(innerWidth / img.naturalWidth, innerHeight / img.naturalHeight, 1);
    x = (innerWidth - s * img.naturalWidth) / 2; y = (innerHeight - s * img.naturalHeight) / 2;
    show();
  }));
  box.addEventListener('wheel', e => {
    e.preventDefault();
    const k = Math.exp(-e.deltaY / 300);
    x = e.clientX - k * (e.clientX - x); y = e.clientY - k * (e.clientY - y); s *= k; show();
  }, { passive: false });
  box.addEventListener('mousedown', e => { drag = [e.clientX - x, e.clientY - y]; moved = false; });
  box.addEventListener('mousemove', e => {
    if (drag) { x = e.clientX - drag[0]; y = e.clientY - drag[1]; moved = true; show(); }
  });
  box.addEventListener('mouseup', () => { if (!moved) box.style.display = 'none'; drag = null; });
  addEventListener('keydown', e => { if (e.key === 'Escape') box.style.display = 'none'; });
  const methods = new Set(JSON.parse(document.getElementById('methods').textContent));
  const cells = [...document.querySelectorAll('th, td')];
  const named = t => methods.has(t.textContent.trim()) ? t.textContent.trim() : null;
  document.querySelectorAll('table').forEach(table => {
    const head = [...table.querySelectorAll('thead th')].map(named);
    table.querySelectorAll('tbody tr').forEach(tr => {
      const row = [...tr.cells].map(named).find(Boolean);  // 'camera | method | ...' too
      [...tr.cells].forEach((td, i) => { td.dataset.method = row || head[i] || ''; });
    });
    table.querySelectorAll('thead th').forEach((th, i) => { th.dataset.method = head[i] || ''; });
  });
  cells.forEach(c => c.addEventListener('mouseenter', () => {
    const m = c.dataset.method;
    cells.forEach(o => o.classList.toggle('hl', !!m && o.dataset.method === m));
  }));
})();
"""


def provenance(seeds=(), fingerprints=()) -> dict:
    """The versions a report's numbers depend on, and the seeds and fingerprints given."""
    import cv2
    import numpy as np

    from .. import __version__

    facts = {"synthcal-bench": __version__, "OpenCV": cv2.__version__, "NumPy": np.__version__,
             "Python": platform.python_version()}
    if seeds:
        facts["seeds"] = ", ".join(str(s) for s in seeds)
    if fingerprints:
        facts["fingerprints"] = ", ".join(str(f) for f in fingerprints)
    return facts


def render_html(title: str, markdown_text: str, figures: list[Path], facts: dict,
                config_text: str | None = None, methods=()) -> str:
    """The report page (see the module notes). ``figures``: PNG files, captioned by name."""
    body = md.markdown(markdown_text, extensions=["tables", "fenced_code"])
    parts = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
             f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
             f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
             "<div id='zoom'><img alt='zoomed figure'><div class='hint'>wheel: zoom, drag: pan, "
             "click or Esc: close</div></div>", body]
    if figures:
        parts.append("<h2>Figures</h2>")
        for path in figures:
            data = base64.b64encode(Path(path).read_bytes()).decode()
            name = html.escape(Path(path).stem.replace("_", " "))
            parts.append(f"<figure><img src='data:image/png;base64,{data}' alt='{name}'>"
                         f"<figcaption>{name}</figcaption></figure>")
    parts.append("<h2>Provenance</h2><table><tbody>" + "".join(
        f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(v))}</td></tr>"
        for k, v in facts.items()) + "</tbody></table>")
    if config_text:
        parts.append("<details><summary>The configuration that produced it</summary>"
                     f"<pre>{html.escape(config_text)}</pre></details>")
    names = "[" + ",".join(f'"{html.escape(m)}"' for m in methods) + "]"
    parts.append(f"<script type='application/json' id='methods'>{names}</script>"
                 f"<script>{_SCRIPT}</script></body></html>")
    return "\n".join(parts)


def write_html(path: Path, title: str, markdown_text: str, figures: list[Path], facts: dict,
               config_text: str | None = None, methods=()) -> Path:
    """Write :func:`render_html` to ``path`` (atomically, as every file of a run)."""
    return write_text(path, render_html(title, markdown_text, sorted(figures), facts,
                                        config_text, methods))


def write_run_html(out: Path, title: str, trials: list[dict], agg: dict, plots: list[Path],
                   cfg) -> Path:
    """RUN/report.html of a run (one configuration): report.md's tables, the plots, the
    resolved rig file and each trial's seed and dataset fingerprint."""
    import yaml

    from ..io.rundir import RunPaths

    run = RunPaths(out)
    facts = provenance([t["seed"] for t in trials], [t["fingerprint"] for t in trials])
    return write_html(run.html, title, run.report.read_text(), plots, facts,
                      yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False),
                      methods=list(agg["calibration"]))
