"""Fuzzing of everything the suite reads that a user or another tool wrote: every exchange
format (through ``score``), a run folder's files and stage markers (through ``run`` and
``export``), ``calibrate-images`` inputs (image folders, board options and board files) and the
web app's API (started as a user starts it). Each case is a valid input mutated at random by a
seeded generator of our own, so a failing case is reproduced by its group and number.

For every case: no traceback, no hang over 60 s, nothing written outside the output folder (the
web app: nothing read or deleted outside its runs folder), and no exit 0 from input that cannot
determine the result: a score with a figure the clean file's score has and the mutated one's
lacks, a reused run whose numbers changed without a note, a capture calibrated from fewer than
two usable views of the board as given. ``-m slow`` runs 1,150 cases; the default run 110. The
counts by outcome are printed (``pytest -s``)."""

from __future__ import annotations

import copy
import json
import math
import random
import re
import shutil
import signal
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.io import FORMATS
from stereo_bench.io.rundir import RunPaths

from web_server import call, running_server
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]
HANG_S = 60
# Spellings of numbers no camera has, in each reader's syntax (YAML, TOML, JSON, Python).
POISON = ["nan", ".nan", "NaN", "inf", ".inf", "-.inf", "1e308", "-1e308", "1e300", "0", "-0",
          "1e-300", "abc", "", "[]", "{}", "1e6", "-5", "9" * 400, "true", "null", "~"]
DEEP = "[" * 50_000 + "]" * 50_000


class Hang(Exception):
    pass


def _alarm(*_):
    raise Hang()


def guarded(fn):
    """(exit code, None) or (None, what went wrong): a traceback or a hang."""
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(HANG_S)
    try:
        return fn(), None
    except SystemExit as e:  # argparse's refusal of an option it cannot parse
        return e.code, None
    except Hang:
        return None, f"hang over {HANG_S} s"
    except BaseException as e:  # noqa: BLE001 — exactly what this test looks for
        return None, f"traceback: {type(e).__name__}: {str(e)[:200]}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def run_checked(argv, work: Path, allowed: list[Path], capsys, case: str):
    """Run the command of one case: (exit code, what it printed, None), or (None, "", what went
    wrong) when it raised, hung or wrote outside ``allowed``; ``case`` names it in that."""
    before = _files(work)
    rc, wrong = guarded(lambda: main(argv))
    captured = capsys.readouterr()
    said = (captured.out + captured.err).replace("\n", " ")
    if wrong:
        return None, "", f"{wrong} ({case})"
    if outside := _written_outside(work, before, allowed):
        return None, "", f"write outside {allowed[0].name}: {outside[:2]}"
    return rc, said, None


def _files(root: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file() and not p.is_symlink()}


def _written_outside(root: Path, before: dict, allowed: list[Path]) -> list[Path]:
    after = _files(root)
    changed = [p for p, t in after.items() if before.get(p) != t]
    return [p for p in changed if not any(p.is_relative_to(a) for a in allowed)]


def _mutate_text(text: str, rng: random.Random) -> str:
    """One of the ways a file goes wrong: a number that is not a camera's, a line lost or
    doubled, a file cut short, garbage, a nesting bomb, a list one longer or shorter."""
    numbers = list(re.finditer(r"-?\d+(\.\d+)?([eE][-+]?\d+)?", text))
    lines = text.splitlines(keepends=True)
    kind = rng.random()
    if kind < 0.45 and numbers:
        for m in sorted(rng.sample(numbers, min(len(numbers), rng.randint(1, 3))),
                        key=lambda m: -m.start()):
            text = text[:m.start()] + rng.choice(POISON) + text[m.end():]
        return text
    if kind < 0.55 and numbers:  # a list one longer, or one shorter
        m = rng.choice(numbers)
        extra = rng.choice([", 0.0", ", 1", " 0.5", ""])
        return text[:m.end()] + extra + text[m.end():] if extra else text[:m.start()] + \
            text[m.end():].lstrip(", ")
    if kind < 0.65 and lines:
        del lines[rng.randrange(len(lines))]
        return "".join(lines)
    if kind < 0.72 and lines:
        i = rng.randrange(len(lines))
        lines.insert(i, lines[i])
        return "".join(lines)
    if kind < 0.80:
        return text[:rng.randrange(max(1, len(text)))]
    if kind < 0.86:
        return "".join(chr(rng.randrange(1, 0x2FF)) for _ in range(rng.randint(0, 400)))
    if kind < 0.90:
        return DEEP
    if kind < 0.95 and numbers:  # a small, legal-looking change: must still score
        m = rng.choice(numbers)
        value = float(m.group()) * rng.choice([0.999, 1.001, -1.0, 2.0])
        return text[:m.start()] + repr(value) + text[m.end():]
    return ""


def _nulls(obj, path="") -> set[str]:
    """Paths of the figures of a report that are missing (None or not finite)."""
    if isinstance(obj, dict):
        return set().union(*[_nulls(v, f"{path}/{k}") for k, v in obj.items()]) if obj else set()
    if isinstance(obj, list):
        return set().union(*[_nulls(v, f"{path}[]") for v in obj]) if obj else set()
    if obj is None or (isinstance(obj, float) and not math.isfinite(obj)):
        return {path}
    return set()


# --------------------------------------------------------------------------------------------
# The shared material: one small stereo run, its exports and scores, a capture's image folders.


@pytest.fixture(scope="module")
def material(tmp_path_factory):
    base = tmp_path_factory.mktemp("fuzz_readers")
    d = quickstart(8)
    rig = base / "rig.yaml"
    rig.write_text(yaml.safe_dump(d, sort_keys=False))
    out = base / "run"
    cfg = parse_rig(d)
    assert main(["run", str(rig), "--out", str(out), "--methods", "opencv-radtan"]) == 0
    dataset = RunPaths(out).trial(cfg.seed).dataset.root
    exports, clean = {}, {}
    for fmt in FORMATS:
        exports[fmt] = base / "export" / fmt
        assert main(["export", str(out), "--format", fmt, "--method", "opencv-radtan",
                     "--out", str(exports[fmt])]) == 0
        scored = base / "scored" / fmt
        assert main(["score", str(dataset), str(exports[fmt]), "--format", fmt,
                     "--out", str(scored)]) == 0
        clean[fmt] = _nulls(json.loads((scored / "results.json").read_text()))
    # The detections of the dataset, shared by every score (reused by fingerprint).
    detections = base / "scored" / "opencv" / "detections"
    folders = base / "images"
    for cam in ("left", "right"):
        shutil.copytree(dataset / "images" / cam, folders / cam)
    return {"base": base, "rig": rig, "run": out, "dataset": dataset, "exports": exports,
            "clean": clean, "detections": detections, "folders": folders,
            "results": json.loads(RunPaths(out).results.read_text())}


# --------------------------------------------------------------------------------------------
# Exchange formats, through `score`.


def exchange_case(i: int, m: dict, work: Path, capsys) -> str:
    rng = random.Random(("exchange", i).__repr__())
    fmt = rng.choice(sorted(FORMATS))
    calib = work / "calib"
    shutil.copytree(m["exports"][fmt], calib)
    files = sorted(p for p in calib.rglob("*") if p.is_file())
    target = rng.choice(files)
    if rng.random() < 0.05 and len(files) > 1:
        target.unlink()
    else:
        target.write_text(_mutate_text(target.read_text(), rng), errors="surrogateescape")
    out = work / "scored"
    shutil.copytree(m["detections"], out / "detections")
    given = rng.choice([fmt, None])
    argv = ["score", str(m["dataset"]), str(calib), "--out", str(out)] + \
        (["--format", given] if given else [])
    rc, err, problem = run_checked(argv, work, [out], capsys, f"{fmt} {target.name}")
    if problem:
        return problem
    if rc == 2:
        return "refused (exit 2)" if str(calib) in err else f"refusal not naming the file: {err}"
    if rc == 0:
        lost = _nulls(json.loads((out / "results.json").read_text())) - m["clean"][fmt]
        if lost:
            return f"exit 0 with figures lost: {sorted(lost)[:3]} ({fmt} {target.name})"
        return "scored (exit 0)"
    return f"exit {rc}"


# --------------------------------------------------------------------------------------------
# A run folder's files and stage markers, through `run` (stages reused or redone) and `export`.


def _run_files(run_dir: Path) -> list[Path]:
    return sorted(p for p in run_dir.rglob("*")
                  if p.is_file() and p.suffix in (".json", ".yaml", ".npz", ".npy", ".png"))


def _mutate_file(path: Path, rng: random.Random) -> None:
    data = path.read_bytes()
    if path.suffix in (".json", ".yaml") and rng.random() < 0.7:
        path.write_text(_mutate_text(data.decode(), rng))
        return
    kind = rng.random()
    if kind < 0.3:
        path.write_bytes(data[:rng.randrange(max(1, len(data)))])
    elif kind < 0.6:
        flipped = bytearray(data)
        for _ in range(rng.randint(1, 20)):
            if flipped:
                flipped[rng.randrange(len(flipped))] = rng.randrange(256)
        path.write_bytes(bytes(flipped))
    elif kind < 0.8:
        path.unlink()
    else:
        path.write_bytes(b"")


def _figures(results):
    """The run's numbers a reuse must keep: every figure but the wall times (keys ending in _s,
    which a redone stage renews, and which a lost timing file leaves unknown)."""
    if isinstance(results, dict):
        return {k: _figures(v) for k, v in results.items()
                if not k.endswith("_s") and k not in ("timing", "notes")}
    if isinstance(results, list):
        return [_figures(v) for v in results]
    return results


def rundir_case(i: int, m: dict, work: Path, capsys) -> str:
    rng = random.Random(("rundir", i).__repr__())
    copy_dir = work / "run"
    shutil.copytree(m["run"], copy_dir)
    target = rng.choice(_run_files(copy_dir))
    _mutate_file(target, rng)
    command = rng.choice(["run", "run", "export"])
    if command == "run":
        argv = ["run", str(m["rig"]), "--out", str(copy_dir), "--methods", "opencv-radtan"]
    else:
        argv = ["export", str(copy_dir), "--format", rng.choice(sorted(FORMATS)),
                "--method", "opencv-radtan", "--out", str(work / "exported")]
    where = target.relative_to(copy_dir)
    rc, said, problem = run_checked(argv, work, [copy_dir, work / "exported"], capsys,
                                    f"{command} after {where}")
    if problem:
        return problem
    if rc == 2:
        return "refused (exit 2)"
    if rc == 0 and command == "run":
        again = json.loads(RunPaths(copy_dir).results.read_text())
        if _figures(again) != _figures(m["results"]) and "redone" not in said:
            return f"run's numbers changed without a note ({where})"
        return "run, reused or redone (exit 0)"
    if rc == 0:
        fmt = argv[3]
        if _tree(work / "exported") != _tree(m["exports"][fmt]):
            return f"exported cameras the run did not estimate ({where}, {fmt})"
        return "exported the run's own estimates (exit 0)"
    return f"{command}: exit {rc}"


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in folder.rglob("*") if p.is_file()}


# --------------------------------------------------------------------------------------------
# calibrate-images: image folders as they come, the board's options and board files.

# The quickstart's board: 9 x 12 squares of 15 mm, 8 x 11 inner corners.
BOARD_OPTIONS = [["--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15"]]
# Boards other than the one shown (a transposed count is the same board turned, so not here).
WRONG_BOARDS = [["--board", "checkerboard", "--inner-corners", c, "--square-mm", "15"]
                for c in ("7x11", "8x10", "6x9", "5x4", "3x3", "20x20")]
NASTY_OPTIONS = [["--board", "checkerboard", "--inner-corners", c, "--square-mm", s]
                 for c, s in (("0x0", "15"), ("8x", "15"), ("-8x11", "15"), ("8x11", "0"),
                              ("8x11", "nan"), ("8x11", "-3"), ("99999x99999", "15"),
                              ("8x11", "inf"))] + [["--board", "charuco"], []]


def _board_file(rng: random.Random, folder: Path) -> Path:
    d = {"kind": "checkerboard", "squares_x": 9, "squares_y": 12, "square_mm": 15.0}
    for _ in range(rng.randint(1, 2)):
        key = rng.choice(list(d) + ["squares_x", "marker_mm", "dictionary", "warp_mm", "extra"])
        d[key] = rng.choice([None, 0, -1, 1e12, float("nan"), "", "../x", [], {}, 5, 7, 2.5,
                             "charuco", "DICT_4X4_50", "9x6"])
    path = folder / "board.yaml"
    text = yaml.safe_dump(d)
    r = rng.random()
    if r < 0.1:
        text = "a: &a [1,2]\n" + "".join(f"b{k}: &b{k} [{', '.join([f'*b{k-1}' if k else '*a'] * 9)}]\n"
                                          for k in range(9))
    elif r < 0.15:
        text = DEEP
    path.write_text(text)
    return path


def _spoil_image(path: Path, rng: random.Random, outside: Path) -> str:
    """Spoil one image; what it became."""
    kind = rng.random()
    if kind < 0.15:
        path.write_bytes(b"")
        return "empty"
    if kind < 0.3:
        data = path.read_bytes()
        path.write_bytes(data[:rng.randrange(1, max(2, len(data)))])
        return "truncated"
    if kind < 0.4:
        path.write_bytes(bytes(rng.randrange(256) for _ in range(500)))
        return "garbage"
    if kind < 0.5:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2)))
        return "another size"
    if kind < 0.6:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), np.zeros_like(image))
        return "black"
    if kind < 0.7:
        path.unlink()
        path.symlink_to(outside)
        return "a link to a file elsewhere"
    if kind < 0.8:
        path.unlink()
        path.mkdir()
        return "a folder"
    if kind < 0.9:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), (image.astype(np.uint16) * 257))
        return "16-bit"
    path.unlink()
    return "removed"


def capture_case(i: int, m: dict, work: Path, capsys) -> str:
    rng = random.Random(("capture", i).__repr__())
    folders = work / "images"
    shutil.copytree(m["folders"], folders)
    outside = work / "elsewhere.png"
    outside.write_bytes(b"not an image")
    usable = {}
    for cam in ("left", "right"):
        images = sorted((folders / cam).glob("*.png"))
        spoil = rng.sample(images, rng.choice([0, 1, 2, len(images) - 2, len(images) - 1,
                                               len(images)]))
        # A 16-bit image is still an image of the board (OpenCV reads it as 8-bit grey).
        usable[cam] = len(images) - sum(_spoil_image(path, rng, outside) != "16-bit"
                                        for path in spoil)
    cameras = [f"{c}={folders / c}" for c in ("left", "right")]
    r = rng.random()
    if r < 0.08:
        cameras = [f"left={folders / 'nosuch'}"] + cameras[1:]
        usable["left"] = 0
    elif r < 0.14:
        cameras = [cameras[0], cameras[0]]
    elif r < 0.2:
        cameras = [f"../x={folders / 'left'}"]
    elif r < 0.25:
        cameras = [f"left={folders / 'left' / '*.jpg'}"]
        usable["left"] = 0
    board = rng.choice(BOARD_OPTIONS * 3 + WRONG_BOARDS + NASTY_OPTIONS + [["board file"]])
    wrong_board = board in WRONG_BOARDS
    if board == ["board file"]:
        board = ["--board-file", str(_board_file(rng, work))]
    out = work / "out"
    argv = ["calibrate-images", *cameras, *board, "--methods", "opencv", "--folds", "2",
            "--out", str(out)]
    rc, _, problem = run_checked(argv, work, [out], capsys, f"argv {argv[1:]}")
    if problem:
        return problem
    if rc in (0, 1) and (out / "results.json").is_file():
        results = json.loads((out / "results.json").read_text())
        done = {cam for cams in results["calibration"].values() for cam, e in cams.items()
                if "error" not in e}
        short = [c for c in done if usable.get(c, 0) < 2]
        if short:
            return f"calibrated from fewer than 2 usable views: {short} (argv {argv[1:]})"
        if wrong_board and done:
            # A sub-grid of the board is a board of the same squares: right intrinsics, and a
            # right rig when every camera numbers the same sub-grid. Wrong only if the rig is.
            rig = results.get("rig", {}).get("opencv", {})
            baseline = rig.get("baseline_mm", {}).get("right")
            if baseline is not None and abs(baseline / 120.0 - 1) > 0.01:
                return f"a rig from a board that is not the one shown (argv {board})"
            return "calibrated from a part of the board, the rig right (exit 0)"
        if rc == 0:
            return "calibrated (exit 0)"
    if rc in (1, 2):
        return f"refused (exit {rc})"
    return f"exit {rc}"


# --------------------------------------------------------------------------------------------
# The web app's API, served as a user serves it.

SECRET = "the secret outside the runs folder"


def _mutated_config(example: dict, rng: random.Random):
    d = copy.deepcopy(example)
    leaves = []

    def walk(x, path):
        if isinstance(x, dict):
            for k, v in x.items():
                walk(v, path + [k])
        elif isinstance(x, list):
            for j, v in enumerate(x):
                walk(v, path + [j])
        leaves.append(path)
    walk(d, [])
    for _ in range(rng.randint(1, 3)):
        path = rng.choice([p for p in leaves if p])
        node = d
        try:
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = rng.choice([None, -1, 0, 1e12, 2**70, "", "x" * 1000, [], {},
                                         [1, 2], 8000, 1e-9, "../../etc", True])
        except (KeyError, IndexError, TypeError):
            pass
    return d


def web_request(i: int, url: str, example: dict, rng: random.Random):
    kind = rng.random()
    if kind < 0.25:
        return "validate", call(url + "/api/validate", {"config": _mutated_config(example, rng)},
                                timeout=HANG_S)
    if kind < 0.4:
        text = rng.choice([yaml.safe_dump(_mutated_config(example, rng)), DEEP, "a: &a [*a]",
                           "\x00", "cameras: " + "[" * 500, ""])
        return "yaml", call(url + "/api/yaml", {"text": text}, timeout=HANG_S)
    if kind < 0.5:
        return "preview", call(url + "/api/preview", {"config": _mutated_config(example, rng),
                                                      "camera": rng.choice([0, 1, -1, 99]),
                                                      "frame": rng.choice([0, 5, -3, 10**9])},
                               timeout=HANG_S)
    if kind < 0.58:
        name = rng.choice(["ok", "", "..", "../x", "a/b", "x" * 300, ".hidden", "a b"])
        return "sweep", call(url + "/api/sweeps", {"name": name, "config": example,
                                                   "axes": rng.choice(["", "a: [1]", DEEP[:2000],
                                                                       "trajectory.frames: [0]",
                                                                       "{}", "x: &a [*a]"]),
                                                   "trials": rng.choice([1, 0, 99, -1])},
                             timeout=HANG_S)
    if kind < 0.78:
        name = rng.choice(["linked", "real", "..", "%2e%2e", "real%00", "nosuch"])
        path = rng.choice(["secret.txt", "report.md", "../secret.txt", "..%2Fsecret.txt",
                           "%2e%2e/%2e%2e/secret.txt", "a%00b", "link_out.txt", ""])
        return "file", call(f"{url}/runs/{name}/{path}", timeout=HANG_S)
    if kind < 0.88:
        name = rng.choice(["linked", "..", "%2e%2e", "nosuch", "real%2F..", "real%00"])
        return "delete", call(f"{url}/api/runs/{name}", method="DELETE", timeout=HANG_S)
    if kind < 0.94:
        raw = rng.choice([b"", b"{", b"\xff\xfe", b"[]", b"null", b'{"config": 1}',
                          b'{"config": "x"}'])
        return "raw", call(url + rng.choice(["/api/validate", "/api/yaml", "/api/preview",
                                             "/api/runs"]), raw=raw, timeout=HANG_S)
    job = rng.choice(["0", "-1", "99999999999999999999", "x", "1e3"])
    return "job", call(f"{url}/api/jobs/{job}" + rng.choice(["", "/cancel"]),
                       method=rng.choice(["GET", "POST"]), timeout=HANG_S)


def web_cases(n: int, tmp_path: Path) -> Counter:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "secret.txt").write_text(SECRET)
    runs = tmp_path / "runs"
    (runs / "real").mkdir(parents=True)
    (runs / "real" / "report.md").write_text("a report")
    (runs / "real" / "link_out.txt").symlink_to(elsewhere / "secret.txt")
    (runs / "linked").symlink_to(elsewhere)
    (tmp_path / "secret.txt").write_text(SECRET)
    outcomes = Counter()
    with running_server(runs) as (url, _):
        example = call(url + "/api/example")[1]
        example = example.get("config", example)
        for i in range(n):
            rng = random.Random(("web", i).__repr__())
            before = _files(tmp_path)
            start = time.perf_counter()
            try:
                what, (status, answer) = web_request(i, url, example, rng)
            except (OSError, TimeoutError) as e:
                outcomes[f"no answer: {type(e).__name__}: {e}"] += 1
                continue
            took = time.perf_counter() - start
            text = answer.decode(errors="replace") if isinstance(answer, bytes) \
                else json.dumps(answer)
            if SECRET in text:
                outcomes[f"read outside the runs folder ({what})"] += 1
            elif not (elsewhere / "secret.txt").exists():
                outcomes[f"deleted outside the runs folder ({what})"] += 1
            elif status >= 500 and status != 503:
                outcomes[f"HTTP {status} ({what}): {text[:200]}"] += 1
            elif took > HANG_S:
                outcomes[f"hang ({what})"] += 1
            elif outside := [p for p in _written_outside(tmp_path, before, [runs])]:
                outcomes[f"write outside the runs folder: {outside[:2]}"] += 1
            else:
                outcomes[f"answered {status // 100}xx"] += 1
        # The jobs a case started are cancelled, so the server stops at once.
        for job in call(url + "/api/jobs")[1]:
            call(f"{url}/api/jobs/{job['id']}/cancel", method="POST")
    return outcomes


# --------------------------------------------------------------------------------------------

GROUPS = {"exchange": exchange_case, "rundir": rundir_case, "capture": capture_case}
OK = ("refused", "scored", "run, reused", "calibrated", "answered", "exported")


def fuzz(counts: dict[str, int], material, tmp_path, capsys, monkeypatch) -> Counter:
    outcomes = Counter()
    for group, fn in GROUPS.items():
        for i in range(counts[group]):
            work = tmp_path / f"{group}{i}"
            work.mkdir()
            monkeypatch.chdir(work)
            outcomes[f"{group}: {fn(i, material, work, capsys)}"] += 1
            shutil.rmtree(work, ignore_errors=True)
    web = tmp_path / "web"
    web.mkdir()
    outcomes.update({f"web: {k}": v for k, v in web_cases(counts["web"], web).items()})
    print(f"\nfuzz outcomes over {sum(outcomes.values())} cases:")
    for outcome, count in sorted(outcomes.items()):
        print(f"  {count:5d}  {outcome}")
    bad = [o for o in outcomes if not o.split(": ", 1)[1].startswith(OK)]
    assert not bad, bad
    return outcomes


def test_fuzz_readers(material, tmp_path, capsys, monkeypatch):
    fuzz({"exchange": 40, "rundir": 20, "capture": 10, "web": 40}, material, tmp_path, capsys,
         monkeypatch)


@pytest.mark.slow
def test_fuzz_readers_thoroughly(material, tmp_path, capsys, monkeypatch):
    fuzz({"exchange": 500, "rundir": 200, "capture": 150, "web": 300}, material, tmp_path,
         capsys, monkeypatch)
