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
  ``GET /api/jobs``, ``GET /api/jobs/{id}`` its state, ``POST /api/jobs/{id}/cancel`` stops it
  (jobs.py); a rig, a sweep or a preview over the web app's budget is refused (budget.py);
* ``GET /api/runs`` the folders of RUNS with a report, newest first; ``DELETE /api/runs/{name}``
  removes one (not while a job writes into it);
* ``GET /runs/{name}/{file}`` a file of a run (its report.html, plots), only inside RUNS;
* ``GET /compare?a=NAME&b=NAME`` two runs' reports side by side, with their headline figures.

Requests are checked before any route sees them: a Host header other than this machine's
names (or ``--host``'s) is refused, so a web page cannot reach the app through DNS rebinding; a
body over MAX_BODY_BYTES is refused unread.
"""

from __future__ import annotations

import io
from pathlib import Path

from fastapi import Body, FastAPI, HTTPException
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware

from ..config.bounds import ConfigError
from ..config.schema import load_rig, parse_rig
from ..config.yaml_reader import parse_yaml
from ..run.grid import parse_grid
from . import budget
from .jobs import Jobs, grid_data
from .preview import PreviewTimeout, PreviewWorker

STATIC = Path(__file__).with_name("static")
EXAMPLE = Path(__file__).resolve().parents[2] / "configs" / "quickstart.yaml"
MAX_BODY_BYTES = 2 << 20  # a rig file is at most 1 MiB of YAML; its JSON form is about as long
LOCAL_HOSTS = ["127.0.0.1", "localhost", "::1", "[::1]"]


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


def allowed_hosts(host: str) -> list[str]:
    """The Host headers the app answers: this machine's names, and ``host`` when it listens on
    a named interface; any, when it listens on every interface (the user chose to expose it)."""
    if host in ("0.0.0.0", "::", ""):
        return ["*"]
    return LOCAL_HOSTS + ([host] if host not in LOCAL_HOSTS else [])


def create_app(runs: Path, host: str = "127.0.0.1") -> FastAPI:
    import yaml

    runs = Path(runs)
    runs.mkdir(parents=True, exist_ok=True)
    root = runs.resolve()
    jobs = Jobs(runs)
    previews = PreviewWorker()
    app = FastAPI(title="SynthCal", docs_url=None, redoc_url=None,
                  on_shutdown=[previews.close])
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts(host))

    @app.middleware("http")
    async def bounded_body(request, call_next):
        length = request.headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > MAX_BODY_BYTES):
            return JSONResponse({"ok": False, "errors": [
                f"request body: expected at most {MAX_BODY_BYTES:,} bytes"]}, status_code=413)
        if length is None and "transfer-encoding" in request.headers:  # a body of unknown size
            return JSONResponse({"ok": False, "errors": [
                "request body: expected a Content-Length"]}, status_code=411)
        return await call_next(request)

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
        cfg = need(config)
        cameras = len(cfg.cameras_true())
        frames = cfg.trajectory.frames_for(cameras)
        if not 0 <= camera < cameras or not 0 <= frame < frames:
            raise HTTPException(422, detail=[f"camera 0..{cameras - 1}, frame 0..{frames - 1}"])
        try:
            budget.refuse_preview(cfg, camera)
            png, headers = previews.render(cfg.model_dump(mode="json"), camera, frame)
        except ValueError as e:
            raise HTTPException(422, detail=str(e).splitlines()) from None
        except PreviewTimeout as e:
            raise HTTPException(503, detail=[str(e)]) from None
        return Response(png, media_type="image/png", headers=headers)

    @app.post("/api/trajectory")
    def trajectory(config: dict = Body(..., embed=True)):
        from ..report.plots import plot_trajectory
        from ..scene.rig import Rig

        cfg = need(config)
        buffer = io.BytesIO()
        plot_trajectory(Rig.from_config(cfg), buffer, cfg.trajectory.kind == "session")
        return Response(buffer.getvalue(), media_type="image/png")

    @app.post("/api/runs")
    def start_run(name: str = Body(...), config: dict = Body(...)):
        cfg = need(config)
        try:
            budget.refuse_job(budget.rig_samples(cfg), "run")
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
            # The whole grid is validated here, as `stereo-bench sweep` validates it before
            # anything runs, so that a bad axis is refused in the answer, not in the job.
            resolved = cfg.model_dump(mode="json")
            sweep = parse_grid(grid_data(name, parsed, trials), jobs.folder(name) / "grid.yaml",
                               lambda _: (resolved, resolved))
            budget.refuse_job(sweep.trials * sum(budget.rig_samples(c.config)
                                                 for c in sweep.configurations), "sweep")
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

    @app.post("/api/jobs/{job_id}/cancel")
    def cancel(job_id: int):
        found = jobs.cancel(job_id)
        if found is None:
            raise HTTPException(404, detail=[f"no job {job_id}"])
        return found.view()

    @app.delete("/api/runs/{name}")
    def delete_run(name: str):
        try:
            removed = jobs.delete(name)
        except ValueError as e:
            raise HTTPException(409 if "job" in str(e) else 404, detail=[str(e)]) from None
        if not removed:
            raise HTTPException(404, detail=[f"no run {name!r}"])
        return {"ok": True, "deleted": name}

    @app.get("/api/runs")
    def list_runs():
        found = []
        for folder in runs.iterdir():
            if folder.is_symlink():
                continue  # served from nowhere (run_file), so not listed
            for page in ("report.html", "sweep.html"):
                if (folder / page).is_file():
                    found.append({"name": folder.name, "report": f"/runs/{folder.name}/{page}",
                                  "kind": page.split(".")[0],
                                  "modified": (folder / page).stat().st_mtime})
        return sorted(found, key=lambda r: -r["modified"])

    @app.get("/runs/{name}/{path:path}")
    def run_file(name: str, path: str):
        # Contained in the runs folder itself, whatever a run folder or a file in it links to
        # (a symlinked run folder would otherwise be its own root).
        try:
            target = (jobs.folder(name) / path).resolve()
            inside = target.is_relative_to(root) and target.is_file()
        except (ValueError, OSError):  # a NUL byte, a loop of links: no such file
            inside = False
        if not inside:
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

    # Starlette's own refusals too (a body that is not JSON, an unknown path), in one shape.
    @app.exception_handler(StarletteHTTPException)
    def refused(_, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, list) else [str(exc.detail)]
        return JSONResponse({"ok": False, "errors": detail}, status_code=exc.status_code)

    @app.exception_handler(Exception)
    def failed(_, exc: Exception):  # a bug, said in one line (the server's log has the rest)
        return JSONResponse({"ok": False, "errors": [
            f"internal error: {type(exc).__name__}: {exc}"]}, status_code=500)

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


def serve(runs: Path, host: str = "127.0.0.1", port: int = 8765) -> None:
    import uvicorn

    uvicorn.run(create_app(runs, host), host=host, port=port, log_level="warning")
