"""The board and the cameras of ``calibrate-images`` as a user gives them on the command line
(OpenCV's descriptions: ``--inner-corners 9x6``, ``--squares 7x5``...; ``NAME=FOLDER``, globs,
videos and folders of videos).
"""

from __future__ import annotations

from pathlib import Path


# The board as users describe it, per option: the kinds it applies to and the rig file's field.
_BOARD_OPTIONS = {
    "inner_corners": ("checkerboard",),
    "squares": ("checkerboard", "charuco"),
    "circles": ("symmetric_circles", "asymmetric_circles"),
    "square_mm": ("checkerboard", "charuco"),
    "marker_mm": ("charuco",),
    "dictionary": ("charuco",),
    "legacy": ("charuco",),
    "spacing_mm": ("symmetric_circles", "asymmetric_circles"),
    "diameter_mm": ("symmetric_circles", "asymmetric_circles"),
}


def _grid_size(option: str, text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--{option.replace('_', '-')}: expected COLUMNSxROWS such as 9x6, got "
                         f"{text!r}") from None
    return cols, rows


def board_from_args(args):
    """The board of ``calibrate-images`` from its options (or --board-file), validated by the
    rig file's own schema (config.PatternConfig), so both name the same fields; and whether
    the user gave a circle grid's disc diameter."""
    from pydantic import ValidationError

    from ..config.schema import PatternConfig, describe
    from ..config.yaml_reader import load_yaml

    if args.board_file:
        data = load_yaml(args.board_file, "board file")
        data = data.get("pattern", data) if isinstance(data, dict) else data
        source = args.board_file
    else:
        if not args.board:
            raise ValueError("--board: expected the board's kind (checkerboard, charuco, "
                             "symmetric_circles or asymmetric_circles) or --board-file")
        kind, data = args.board, {"kind": args.board}
        for option, kinds in _BOARD_OPTIONS.items():
            value = getattr(args, option)
            if value is None:
                continue
            if kind not in kinds:
                raise ValueError(f"--{option.replace('_', '-')}: not an option of a {kind} "
                                 f"(it applies to {', '.join(kinds)})")
            if option == "inner_corners":
                data["inner_corners"] = list(_grid_size(option, value))
            elif option == "squares":
                data["squares_x"], data["squares_y"] = _grid_size(option, value)
            elif option == "circles":
                data["cols"], data["rows"] = _grid_size(option, value)
            elif option == "spacing_mm" and kind == "asymmetric_circles":
                # OpenCV's squareSize of this grid: the row pitch, half the pitch in a row.
                data["diagonal_spacing_mm"] = value * 2 ** 0.5
            else:
                data[option] = value
        if args.inverted:
            data["inverted"] = True
        source = "the --board options"
    try:
        board = PatternConfig.model_validate(data).build()
    except ValidationError as e:  # in words, each field with what was expected
        raise ValueError(describe(e, source, "board")) from None
    except Exception as e:  # the board's own ValueError
        raise ValueError(f"{source}: {e}") from None
    return board, isinstance(data, dict) and "diameter_mm" in data


def camera_folders(specs: list[str]) -> dict[str, str]:
    """NAME=FOLDER (or glob, or video); a bare folder is named after itself, a bare video after
    its stem, and a bare folder of videos (and no images) is one camera per video."""
    from ..scene.image_folders import IMAGE_SUFFIXES, VIDEO_SUFFIXES

    pairs = []
    for spec in specs:
        name, sep, where = spec.partition("=")
        if sep:
            pairs.append((name, where))
            continue
        path = Path(spec.rstrip("/"))
        inside = sorted(path.iterdir()) if path.is_dir() else []
        videos = [p for p in inside if p.suffix.lower() in VIDEO_SUFFIXES]
        if videos and not any(p.suffix.lower() in IMAGE_SUFFIXES for p in inside):
            pairs += [(p.stem, str(p)) for p in videos]
        else:
            pairs.append((path.stem if path.suffix.lower() in VIDEO_SUFFIXES else path.name,
                          spec))
    cameras = {}
    for name, where in pairs:
        if name in cameras:
            raise ValueError(f"camera {name!r} given twice; name them: NAME=FOLDER")
        cameras[name] = where
    return cameras
