"""Property-based fuzzing of every input a user gives: rig files, grid files and command-line
options, mutated at random from a small valid rig (a generator of our own, seeded, so a failing
case is reproduced by its number).

For every case: no traceback; a refusal exits 2 and names the file (or the option); nothing is
written outside the output folder; and a run that exits 0 either produced a dataset every camera
of which can see the board, or warned about each camera that cannot. ``-m slow`` runs 1,200
cases; the default run 240. The counts by outcome are printed (``pytest -s``)."""

from __future__ import annotations

import copy
import random
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from stereo_bench.cli import main
from stereo_bench.scene.rig import MIN_BOARD_SPAN_PX

BASE = {
    "name": "fz", "seed": 3,
    "cameras": [
        {"name": "a", "width": 160, "height": 120, "fx": 150.0, "fy": 112.5, "cx": 80.0,
         "cy": 60.0, "dist": [0.3, 0.05, 0.01, 0.0], "position_mm": [-40.0, 0.0, 0.0],
         "look_at_mm": [0.0, 0.0, 700.0]},
        {"name": "b", "width": 160, "height": 120, "fx": 150.0, "fy": 112.5, "cx": 80.0,
         "cy": 60.0, "position_mm": [40.0, 0.0, 0.0], "look_at_mm": [0.0, 0.0, 700.0]}],
    "pattern": {"kind": "checkerboard"},
    "trajectory": {"frames": 3, "turns": 1.0},
    "environment": {"kind": "clean", "supersampling": 1},
}

# A small studio: cameras placed by a layout, a session trajectory, calibration settings.
STUDIO = {
    "name": "fzs", "seed": 4,
    "studio": {"layout": "ring", "count": 3, "radius_mm": 1200.0, "height_mm": [1000.0],
               "look_at_mm": [0.0, 0.0, 900.0],
               "lenses": [{"width": 160, "height": 120, "fx": 150.0, "fy": 150.0, "cx": 79.5,
                           "cy": 59.5, "dist": [-0.05, 0.0, 0.0, 0.0]}]},
    "pattern": {"kind": "charuco", "squares_x": 5, "squares_y": 4, "square_mm": 60.0,
                "marker_mm": 45.0, "dictionary": "DICT_4X4_50"},
    "trajectory": {"kind": "session", "frames": 3, "turns": 1.0, "closeups": 1},
    "environment": {"kind": "clean", "supersampling": 1},
    "calibration": {"loss": "soft_l1"},
}

NASTY = [None, True, False, 0, -1, 1, 2, 1.5, 1e12, -1e12, 1e-300, 2**70, 1000, 0.0,
         float("nan"), float("inf"), float("-inf"), "", ".", "..", "../../x", "/abs/x",
         "x" * 300, "abc", "9", "a/b", [], [1], [1, 2, 3], [float("nan"), 0, 0], {}, {"a": 1}]
PLAUSIBLE = [0.5, 3, 5, 7, 9, 11, 20.0, 50.0, 300, 640, 1e4, 5e5, [5e5, 6e5], [100, 200],
             [0, 0, 0], "charuco", "noisy", "symmetric_circles", "asymmetric_circles", "left",
             "office", {"f_number": 2.0}, {"warp_mm": [3, 3]}, {"speed_mm_s": 400.0}]
# Keys a user might set that the base file leaves out (pattern overrides, optional fields).
EXTRA_KEYS = [("pattern", "square_mm"), ("pattern", "squares_x"), ("pattern", "squares_y"),
              ("pattern", "cols"), ("pattern", "rows"), ("pattern", "spacing_mm"),
              ("pattern", "diameter_mm"), ("pattern", "marker_mm"), ("pattern", "margin_mm"),
              ("pattern", "dictionary"), ("trajectory", "depth_mm"), ("trajectory", "radius_mm"),
              ("trajectory", "tilt_deg"), ("environment", "sensor"),
              ("environment", "optics"), ("environment", "motion"), ("environment", "light"),
              ("environment", "board"), ("environment", "background"),
              ("cameras", 0, "skew"), ("cameras", 1, "up"), ("cameras", 0, "k1"), ("colour",),
              ("studio", "arc_deg"), ("studio", "size_mm"), ("studio", "layout"),
              ("studio", "names"), ("trajectory", "kind"), ("trajectory", "closeups"),
              ("trajectory", "walk_radius_mm"), ("trajectory", "height_mm"),
              ("calibration", "intrinsics_views"), ("calibration", "refine_intrinsics"),
              ("calibration", "loss"), ("calibration", "loss_scale_px")]


def _leaves(d, prefix=()):
    if isinstance(d, dict):
        for k, v in d.items():
            yield from _leaves(v, prefix + (k,))
    elif isinstance(d, list) and d and isinstance(d[0], dict):
        for i, v in enumerate(d):
            yield from _leaves(v, prefix + (i,))
    yield prefix


def _set(d, path, value):
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value


def _delete(d, path):
    for k in path[:-1]:
        d = d[k]
    del d[path[-1]]


def _legal_looking(d, rng: random.Random) -> None:
    """Scale one number of the base by a factor that keeps it valid-looking: the values that
    make unusable datasets without breaking any rule (a lens of fx 1.5, a board 500 m away)."""
    path = rng.choice([p for p in _leaves(d) if p and isinstance(_get(d, p), (int, float))
                       and not isinstance(_get(d, p), bool) and p[-1] not in ("seed",)]
                      + [("trajectory", "depth_mm")]
                      + ([("cameras", 1, "look_at_mm")] if "cameras" in d else []))
    if path == ("trajectory", "depth_mm"):
        near = rng.choice([50.0, 300.0, 2e3, 2e4, 5e5])
        value = [near, near * rng.choice([1.0, 2.0])]
    elif path[-1] == "look_at_mm":
        value = [rng.choice([0.0, -1e5, 1e5]), rng.choice([0.0, 1e5]), rng.choice([700.0, -700.0])]
    else:
        value = _get(d, path) * rng.choice([0.01, 0.1, 0.5, 0.9, 2, 10, 100, 1000])
        value = int(value) if isinstance(_get(d, path), int) else float(value)
    _set(d, path, value)


def _get(d, path):
    for k in path:
        d = d[k]
    return d


def mutated_rig(rng: random.Random) -> bytes:
    """A rig file: the base (a pair, or a studio) with 1-3 mutations, sometimes broken at the
    text level."""
    d = copy.deepcopy(STUDIO if rng.random() < 0.3 else BASE)
    if rng.random() < 0.4:
        for _ in range(rng.randint(1, 2)):
            _legal_looking(d, rng)
        return yaml.safe_dump(d, sort_keys=False).encode()
    for _ in range(rng.randint(1, 3)):
        kind = rng.random()
        leaves = [p for p in _leaves(d) if p]
        try:
            # Copies: a later mutation writes inside a dict or list set here, and the shared
            # value would carry that write into later cases (even into itself: a cycle).
            if kind < 0.45:
                _set(d, rng.choice(leaves), copy.deepcopy(rng.choice(NASTY + PLAUSIBLE)))
            elif kind < 0.75:
                _set(d, rng.choice(EXTRA_KEYS), copy.deepcopy(rng.choice(NASTY + PLAUSIBLE)))
            elif kind < 0.85:
                _delete(d, rng.choice(leaves))
            elif kind < 0.92:
                d["cameras"].append(copy.deepcopy(d["cameras"][0]))  # a duplicate name
            else:
                d["cameras"][0]["name"] = rng.choice(["../../x", "/abs/x", "", ".", "..", "a b"])
        except (KeyError, IndexError, TypeError):
            pass  # the path no longer exists after an earlier mutation: keep what we have
    text = yaml.safe_dump(d, sort_keys=False, allow_unicode=True)
    r = rng.random()
    if r < 0.03:
        return text.encode("utf-16")
    if r < 0.05:
        return bytes(rng.randrange(256) for _ in range(200))
    if r < 0.07:
        return text.encode()[: rng.randrange(len(text))]
    if r < 0.09:
        return (text + "cameras: []\n").encode()  # a duplicate top-level key
    if r < 0.10:
        return ("a: " + "[" * 5000 + "]" * 5000 + "\n").encode()
    return text.encode()


def mutated_grid(rng: random.Random, rig: Path) -> bytes:
    d = {"name": "g", "rigs": [str(rig)], "patterns": ["checkerboard"],
         "environments": ["clean"], "methods": ["opencv"], "frames": 6}
    key = rng.choice(["name", "rigs", "patterns", "environments", "methods", "trials", "frames",
                      "extra"])
    d[key] = rng.choice(NASTY + [[str(rig), str(rig)], ["nosuch"], ["charuco", "charuco"],
                                 "../../g", [str(rig.parent / "missing.yaml")]])
    return yaml.safe_dump(d).encode()


def _unusable_cameras(out: Path) -> set[str]:
    """Cameras of a written dataset that never see the board at least MIN_BOARD_SPAN_PX wide,
    computed from the ground-truth arrays alone (independently of the code that warns)."""
    gt = out / "ground_truth"
    pts, vis = np.load(gt / "image_points.npy"), np.load(gt / "visible.npy")
    names = yaml.safe_load((out / "config.yaml").read_text())["cameras"]
    bad = set()
    for c, cam in enumerate(names):
        spans = [np.linalg.norm(np.ptp(pts[c, f][vis[c, f]], axis=0))
                 for f in range(vis.shape[1]) if vis[c, f].any()]
        if not spans or max(spans) < MIN_BOARD_SPAN_PX:
            bad.add(cam["name"])
    return bad


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def run_case(i: int, tmp_path: Path, capsys, monkeypatch) -> str:
    rng = random.Random(i)
    work = tmp_path / f"case{i}" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    rig = work / "rig.yaml"
    rig.write_bytes(mutated_rig(rng))
    out = work / "given_out"
    named = str(rig)
    kind = rng.random()
    if kind < 0.55:
        argv = ["render", str(rig)] + (["--out", str(out)] if rng.random() < 0.7 else [])
    elif kind < 0.7:
        argv = [str(rig), "--out", str(out), "--methods", "opencv"]
    elif kind < 0.85:
        option = rng.choice(["--trials", "--workers", "--methods"])
        value = str(rng.choice(NASTY + ["0", "-3", "zhang,magic", "1e9", "2000"]))
        argv = ["calibrate", str(work / "missing_dataset") if rng.random() < 0.3 else str(work),
                "--out", str(out), option, value]
        rig.write_bytes(yaml.safe_dump(BASE).encode())
        named = None  # argparse or the option check names the problem
    else:
        grid = work / "grid.yaml"
        rig.write_bytes(yaml.safe_dump(BASE).encode())
        grid.write_bytes(mutated_grid(rng, rig))
        argv = ["sweep", str(grid), "--out", str(out), "--workers", "1"]
        named = str(grid)
    before = _files(tmp_path / f"case{i}")
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's refusal of an option it cannot parse
        rc = e.code
    except BaseException as e:  # noqa: BLE001 — exactly what this test looks for
        return f"traceback: {type(e).__name__}: {e} (argv {argv})"
    err = capsys.readouterr().err.replace("\n", "")
    new = _files(tmp_path / f"case{i}") - before
    allowed = (out, work / "out")
    outside = [p for p in new if not any(p.is_relative_to(a) for a in allowed)]
    if outside:
        return f"write outside --out: {outside[:3]} (argv {argv})"
    if rc == 2:
        if named and named not in err:
            return f"refusal not naming {named}: {err[:300]}"
        return "refused (exit 2)"
    if rc == 0 and argv[0] == "render":
        dataset = out if "--out" in argv else next((work / "out").iterdir())
        bad = _unusable_cameras(dataset)
        missing = [c for c in bad if f"camera {c!r}" not in err]
        if missing:
            return f"unusable dataset without a warning: cameras {missing} (argv {argv})"
        return "exit 0, with a warning" if bad or "warning" in err else "exit 0"
    return f"exit {rc}"


def fuzz(n: int, tmp_path, capsys, monkeypatch) -> Counter:
    outcomes = Counter(run_case(i, tmp_path, capsys, monkeypatch) for i in range(n))
    print("\nfuzz outcomes over", n, "cases:")
    for outcome, count in outcomes.most_common():
        print(f"  {count:5d}  {outcome}")
    bad = [o for o in outcomes if not o.startswith(("refused", "exit 0", "exit 1"))]
    assert not bad, bad
    return outcomes


def test_fuzz_inputs(tmp_path, capsys, monkeypatch):
    outcomes = fuzz(240, tmp_path, capsys, monkeypatch)
    assert outcomes["refused (exit 2)"] > 50 and outcomes["exit 0"] > 10


@pytest.mark.slow
def test_fuzz_inputs_thoroughly(tmp_path, capsys, monkeypatch):
    fuzz(1200, tmp_path, capsys, monkeypatch)
