"""The local web app (``stereo-bench serve``): app.py the FastAPI routes, jobs.py the runs and
sweeps it starts, static/ the page (plain HTML, CSS and JavaScript, nothing from the network)."""
