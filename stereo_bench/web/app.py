"""The local web app: compose a rig, preview it, run it, read and compare its reports.

``stereo-bench serve [--runs out/web] [--host 127.0.0.1] [--port 8765]`` starts it (FastAPI on
uvicorn); it listens on localhost unless told otherwise, and writes only into its runs folder.

API (JSON unless said; a rig is sent as the rig file's data, validated by the same schema):

* ``GET /`` the page (static/index.html, app.js, style.css; nothing from the network);
* ``GET /api/example`` the quick-start rig, resolved (every field listed), to start from;
* ``POST /api/validate {config}`` -> ``{ok, config (resolved), yaml}`` or ``{ok: false, errors}``
  (the rig file's own messages, one per field);
* ``POST /api/yaml {text}`` a rig file's text -> as /api/validate (load a YAML file);
* ``POST /api/preview {config, camera, frame}`` -> PNG: that frame rendered by the analytic
  renderer (a Blender rig is previewed analytically), with the true corners' count in a header;
* ``POST /api/trajectory {config}`` -> PNG: the board's path and the cameras in 3D;
* ``POST /api/runs {name, config}``, ``POST /api/sweeps {name, config, axes (YAML text: field
  path -> values, as a grid file's axes), trials}`` start a job;
  ``GET /api/jobs``, ``GET /api/jobs/{id}`` its state (jobs.py);
* ``GET /api/runs`` the folders of RUNS with a report, newest first;
* ``GET /runs/{name}/{file}`` a file of a run (its report.html, plots), only inside RUNS;
* ``GET /compare?a=NAME&b=NAME`` two runs' reports side by side, with their headline figures.
"""

from __future__ import annotations

import collections
import io
import json
from pathlib import Path

from fastapi import Body, FastAPI, HTTPException
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from ..config import ConfigError, load_rig, parse_rig, parse_yaml
from .jobs import Jobs

STATIC = Path(__file__).with_name("static")
EXAMPLE = Path(__file__).resolve().parents[2] / "configs" / "quickstart.yaml"
MAX_PREVIEW_RAYS = 4  # cameras whose per-pixel rays are kept between previews


def _resolved(cfg) -> dict:
    return cfg.model_dump(mode="json")


def _validated(data, source: str = "form"):
    """(config, None) or (None, [messages])."""
    try:
        return parse_rig(data, source), None
    except ConfigError as e:
        return None, str(e).splitlines()


def _example() -> dict:
    if EXAMPLE.is_file():
        return _resolved(load_rig(EXAMPLE))
    # An installed package without the repository's configs: the same rig, written here.
    return _resolved(parse_rig({"name": "quickstart", "cameras": [
        {"name": n, "width": 640, "height": 480, "fx": 600.0, "fy": 450.0, "cx": 320.0,
         "cy": 240.0, "dist": [0.5, 0.1, 0.03, 0, 0, 0, 0, 0], "position_mm": [x, 0, 0],
         "look_at_mm": [0, 0, 1000]} for n, x in (("left", -75.0), ("right", 75.0))],
        "pattern": {"kind": "checkerboard"}, "trajectory": {"frames": 40}}))


def create_app(runs: Path) -> FastAPI:
    import yaml

    runs = Path(runs)
    runs.mkdir(parents=True, exist_ok=True)
    jobs = Jobs(runs)
    app = FastAPI(title="SynthCal", docs_url=None, redoc_url=None)
    rays_cache: collections.OrderedDict = collections.OrderedDict()

    def answer(cfg, errors):
        if errors:
            return {"ok": False, "errors": errors}
        return {"ok": True, "config": _resolved(cfg),
                "yaml": yaml.safe_dump(_resolved(cfg), sort_keys=False)}

    def need(data) -> object:
        cfg, errors = _validated(data)
        if errors:
            raise HTTPException(422, detail=errors)
        return cfg

    @app.get("/")
    def index():
        return FileResponse(STATIC / "index.html")

    @app.get("/favicon.ico")
    def favicon():
        return Response(status_code=204)  # no icon, and no 404 in the browser's console

    @app.get("/api/example")
    def example():
        return _example()

    @app.post("/api/validate")
    def validate(config: dict = Body(..., embed=True)):
        return answer(*_validated(config))

    @app.post("/api/yaml")
    def from_yaml(text: str = Body(..., embed=True)):
        try:
            data = parse_yaml(text, "the YAML file")
        except ConfigError as e:
            return {"ok": False, "errors": str(e).splitlines()}
        return answer(*_validated(data, "the YAML file"))

    @app.post("/api/preview")
    def preview(config: dict = Body(...), camera: int = Body(0), frame: int = Body(0)):
        import cv2

        from ..dataset import frame_rng, render_settings
        from ..render import AnalyticRenderer, PixelRays
        from ..rig import Rig

        cfg = need(config)
        rig = Rig.from_config(cfg)
        if not 0 <= camera < len(rig.cameras) or not 0 <= frame < len(rig.trajectory):
            raise HTTPException(422, detail=[f"camera 0..{len(rig.cameras) - 1}, frame "
                                             f"0..{len(rig.trajectory) - 1}"])
        cam = rig.cameras[camera]
        key = json.dumps(cam.to_dict(), sort_keys=True)
        if key not in rays_cache:
            rays_cache[key] = PixelRays(cam)
            while len(rays_cache) > MAX_PREVIEW_RAYS:
                rays_cache.popitem(last=False)
        rays_cache.move_to_end(key)
        renderer = AnalyticRenderer(cam, rig.pattern, render_settings(cfg, rig, cam),
                                    rays_cache[key])
        R, t = rig.cam_from_board(cam)
        image = renderer.render(R[frame], t[frame], frame_rng(cfg.seed, camera, frame))
        visible = int(rig.ground_truth().visible[camera, frame].sum())
        ok, png = cv2.imencode(".png", image)
        return Response(png.tobytes(), media_type="image/png",
                        headers={"X-Visible-Points": str(visible),
                                 "X-Camera": cam.name, "X-Frames": str(len(rig.trajectory))})

    @app.post("/api/trajectory")
    def trajectory(config: dict = Body(..., embed=True)):
        from ..plots import plot_trajectory
        from ..rig import Rig

        cfg = need(config)
        buffer = io.BytesIO()
        plot_trajectory(Rig.from_config(cfg), buffer, cfg.trajectory.kind == "session")
        return Response(buffer.getvalue(), media_type="image/png")

    @app.post("/api/runs")
    def start_run(name: str = Body(...), config: dict = Body(...)):
        cfg = need(config)
        try:
            return jobs.start_run(name, cfg).view()
        except ValueError as e:
            raise HTTPException(422, detail=[str(e)]) from None

    @app.post("/api/sweeps")
    def start_sweep(name: str = Body(...), config: dict = Body(...), axes: str = Body(...),
                    trials: int = Body(1)):
        cfg = need(config)
        if not 1 <= trials <= 20:
            raise HTTPException(422, detail=["trials: expected 1..20"])
        try:
            parsed = parse_yaml(axes, "axes")
            if not isinstance(parsed, dict) or not parsed:
                raise ValueError("axes: expected a mapping of rig-file field paths to lists of "
                                 "values, e.g. environment.sensor.noise_sigma: [0, 4]")
            return jobs.start_sweep(name, cfg, parsed, trials).view()
        except (ValueError, ConfigError) as e:
            raise HTTPException(422, detail=str(e).splitlines()) from None

    @app.get("/api/jobs")
    def list_jobs():
        return [j.view() for j in jobs.all()]

    @app.get("/api/jobs/{job_id}")
    def job(job_id: int):
        found = jobs.get(job_id)
        if found is None:
            raise HTTPException(404, detail=[f"no job {job_id}"])
        return found.view()

    @app.get("/api/runs")
    def list_runs():
        found = []
        for folder in runs.iterdir():
            for page in ("report.html", "sweep.html"):
                if (folder / page).is_file():
                    found.append({"name": folder.name, "report": f"/runs/{folder.name}/{page}",
                                  "kind": page.split(".")[0],
                                  "modified": (folder / page).stat().st_mtime})
        return sorted(found, key=lambda r: -r["modified"])

    @app.get("/runs/{name}/{path:path}")
    def run_file(name: str, path: str):
        try:
            root = jobs.folder(name).resolve()
        except ValueError as e:
            raise HTTPException(404, detail=[str(e)]) from None
        target = (root / path).resolve()
        if root not in target.parents or not target.is_file():
            raise HTTPException(404, detail=[f"no file {path!r} in run {name!r}"])
        return FileResponse(target)

    @app.get("/compare", response_class=HTMLResponse)
    def compare(a: str, b: str):
        for name in (a, b):
            try:
                folder = jobs.folder(name)
            except ValueError as e:
                raise HTTPException(404, detail=[str(e)]) from None
            if not (folder / "report.html").is_file():
                raise HTTPException(404, detail=[f"run {name!r} has no report"])
        return (STATIC / "compare.html").read_text().replace("{{A}}", a).replace("{{B}}", b)

    @app.exception_handler(HTTPException)
    def refused(_, exc: HTTPException):
        detail = exc.detail if isinstance(exc.detail, list) else [str(exc.detail)]
        return JSONResponse({"ok": False, "errors": detail}, status_code=exc.status_code)

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


def serve(runs: Path, host: str = "127.0.0.1", port: int = 8765) -> None:
    import uvicorn

    uvicorn.run(create_app(runs), host=host, port=port, log_level="warning")
