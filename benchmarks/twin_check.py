"""The twin checked where the truth is known: a capture rendered under an imaging preset, twinned
as a real one would be, the twin's measured imaging and predicted errors against the truth.

For each preset: the quick-start pair (configs/quickstart.yaml, 25 frames) is rendered under the
preset, run through calibrate-images (--fit-board-warp, methods opencv and zhang-brown) as if
its images were a user's, and twinned from zhang-brown (the method that fits the warp). Printed:
the preset's true figures beside what the twin measured (edge width, grey levels per electron,
read noise, corner illumination, board warp), whether the twin matches the capture, and each
method's true projection difference (mean px over the image) in the capture beside the twin's
prediction with its 95 % interval, and the wall time of the twin.

    python benchmarks/twin_check.py [--presets studio handheld_low_light] [--seeds 10]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from stereo_bench.cli import main
from stereo_bench.config.schema import parse_rig
from stereo_bench.core.camera import Camera
from stereo_bench.evaluate.metrics import projection_difference

ROOT = Path(__file__).resolve().parent.parent


def check(preset: str, seeds: int, work: Path) -> None:
    rig = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    rig.update(name=f"capture_{preset}", environment={"kind": preset})
    rig["trajectory"]["frames"] = 25
    env = parse_rig(rig).environment
    (work / "rig.yaml").write_text(yaml.safe_dump(rig))
    data, capture, twin = work / "data", work / "capture", work / "twin"
    quiet = ["--out"]
    assert main(["render", str(work / "rig.yaml"), *quiet, str(data)]) == 0
    main(["calibrate-images", f"left={data}/images/left", f"right={data}/images/right",
          "--board", "checkerboard", "--inner-corners", "8x11", "--square-mm", "15",
          "--methods", "opencv,zhang-brown", "--fit-board-warp", "--out", str(capture)])
    t0 = time.perf_counter()
    main(["twin", str(capture), "--method", "zhang-brown", "--seeds", str(seeds),
          "--out", str(twin)])
    seconds = time.perf_counter() - t0
    results = json.loads((twin / "results.json").read_text())
    measured = results["imaging"]["measured_on_real"]["left"]
    s = env.sensor
    true_gain = env.white_level / (s.exposure * s.full_well_e) if s.full_well_e else None
    twin_env = results["rig"]["environment"]
    print(f"\n== {preset}: twin of 2 cameras x 25 frames at {seeds} seeds in {seconds:.0f} s")
    print(f"   edge width px: measured {measured['edge_sigma_px']:.3f} (preset: lens blur "
          f"{env.optics.blur_px}, f/{env.optics.f_number}, motion {env.motion.exposure_ms} ms); "
          f"twin's lens blur {twin_env['optics']['blur_px']:.3f}")
    print(f"   grey levels per electron: true {true_gain}, measured "
          f"{measured['gain_dn_per_e']}; read noise true {s.read_noise_e} e-, twin "
          f"{twin_env['sensor'].get('read_noise_e')} e-; JPEG true {s.jpeg_quality}, "
          f"measured {measured['jpeg_quality']} (PNG files carry no table)")
    print(f"   corner illumination: true {env.optics.corner_illumination}, measured "
          f"{measured['corner_illumination']:.3f}")
    print(f"   board warp mm: true {env.board.warp_mm}, twin "
          f"{twin_env.get('board', {}).get('warp_mm')}")
    print(f"   matches: {results['matches']} {results['mismatch']}")
    truth = {c["name"]: Camera.from_dict(c)
             for c in json.loads((data / "ground_truth" / "cameras.json").read_text())}
    for method, entry in results["true_errors"].items():
        for name, cam in truth.items():
            path = capture / "calibrations" / method / f"{name}.json"
            if not path.exists() or name not in entry["cameras"]:
                continue
            actual = projection_difference(Camera.load_json(path), cam.with_params(
                rvec=np.zeros(3), tvec=np.zeros(3)))["mean_px"]
            p = entry["cameras"][name]["projection_mean_px"]
            print(f"   {method:12s} {name:5s}: true projection difference {actual:.3f} px, twin "
                  f"predicts {p['mean']:.3f} ± {p['ci95']:.3f} px")


def main_() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["studio", "handheld_low_light"])
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    for preset in args.presets:
        with tempfile.TemporaryDirectory() as tmp:
            check(preset, args.seeds, Path(tmp))


if __name__ == "__main__":
    main_()
