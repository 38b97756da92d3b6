"""The quick-start rig as a rig-file dict, shortened to the frames a test needs."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def quickstart(frames: int) -> dict:
    """configs/quickstart.yaml with ``frames`` frames (edit the dict further, then parse_rig)."""
    d = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    d["trajectory"]["frames"] = frames
    return d
