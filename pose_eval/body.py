"""SMPL-format body models through smplx: the shipped open stand-in, or a real SMPL the user has.

The stand-in (assets/body_model/open_body_neutral.npz, built by scripts/build_body_model.py)
is a humanoid on SMPL's 24-joint tree in the layout of an SMPL model file; it is not SMPL,
whose files are licence-gated (Loper et al., SIGGRAPH Asia 2015).

How a model reaches smplx (0.1.28): `smplx.SMPL.__init__` reads files only as pickles from
`model_path`, but it also takes the same arrays as `data_struct` (a `smplx.utils.Struct` whose
attributes are the model file's keys) and then builds every buffer from them exactly as for a
pickle: shapedirs cut to num_betas, posedirs reshaped to (207, 3V), parents from kintree_table,
lbs_weights. So `load_body_model` reads the file itself (np.load for .npz; for .pkl the same
`pickle.load(..., encoding="latin1")` smplx uses), checks the keys, and passes it as
`data_struct`: smplx's constructor and its forward pass (`smplx.lbs.lbs`) run unchanged, for
the stand-in and for real SMPL alike. smplx appends extra keypoints picked from vertices
(nose, eyes, ears, toes, heels, fingertips); the stand-in ships its own landmark vertices
for them, a real SMPL uses smplx's.

Units: smplx works in metres in SMPL's body frame (y up). SynthCal's geometry is in
millimetres: `to_mm` is the one conversion, applied where a body enters a rig's world.
"""

from __future__ import annotations

import contextlib
import io
import pickle
from pathlib import Path

import numpy as np
import smplx
import torch
from smplx.utils import Struct

from .motion import STANDIN_MODEL_PATH, Skeleton

MODEL_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
NUM_JOINTS = 24
MM_PER_M = 1000.0
CHUNK = 128  # poses per lbs call: smplx materializes a (N, V, 4, 4) transform per vertex


def _resolve(model_path, gender: str) -> Path:
    """The model file: the path itself, or SMPL_<GENDER>.pkl/.npz in a folder (or its smpl/)."""
    path = Path(model_path)
    if path.is_dir():
        names = [f"SMPL_{gender.upper()}.{ext}" for ext in ("pkl", "npz")]
        candidates = [folder / name for folder in (path, path / "smpl") for name in names]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise FileNotFoundError(f"no SMPL model in folder {path}: looked for "
                                    f"{', '.join(str(c.relative_to(path)) for c in candidates)}")
        return found
    if not path.is_file():
        raise FileNotFoundError(f"body model {path} does not exist; expected an SMPL model file "
                                "(.pkl or .npz) or a folder holding SMPL_<GENDER>.pkl")
    return path


def _read(path: Path) -> dict:
    if path.suffix == ".npz":
        with np.load(path) as data:
            arrays = dict(data)
    elif path.suffix == ".pkl":
        try:
            with open(path, "rb") as f:
                arrays = pickle.load(f, encoding="latin1")
        except ModuleNotFoundError as err:  # SMPL 1.0 pickles hold chumpy arrays
            raise ValueError(f"{path} needs the module {err.name!r} to unpickle; convert it to plain numpy "
                             "arrays first (smplx's tools/clean_ch.py does this for chumpy)") from err
    else:
        raise ValueError(f"body model {path}: expected an SMPL model file ending in .pkl or .npz")
    missing = [k for k in MODEL_KEYS if k not in arrays] if isinstance(arrays, dict) else list(MODEL_KEYS)
    if missing:
        raise ValueError(f"body model {path} lacks {missing}; an SMPL-format model has {', '.join(MODEL_KEYS)}")
    if np.shape(arrays["J_regressor"])[0] != NUM_JOINTS:
        raise ValueError(f"body model {path}: J_regressor has {np.shape(arrays['J_regressor'])[0]} rows; "
                         f"expected SMPL's {NUM_JOINTS} joints (SMPL-H/SMPL-X files are not SMPL)")
    return arrays


def load_body_model(model_path=None, gender: str = "neutral", num_betas: int | None = None,
                    dtype: torch.dtype = torch.float64) -> smplx.SMPL:
    """An `smplx.SMPL` module from a real SMPL model, or the shipped stand-in when model_path is None.

    model_path: an SMPL .pkl (chumpy-free) or .npz, or a folder with SMPL_<GENDER>.pkl/.npz.
    gender: picks the file in a folder; the stand-in is neutral only.
    num_betas: shape coefficients to use; by default 10 as in smplx, or fewer if the model has fewer.
    dtype: of the module's buffers and outputs; smplx first rounds the model arrays to float32.
    """
    if model_path is None:
        if gender != "neutral":
            raise ValueError(f"the shipped stand-in body is gender-neutral; got gender={gender!r} "
                             "(pass model_path to use a gendered SMPL model)")
        path = STANDIN_MODEL_PATH
        if not path.is_file():
            raise FileNotFoundError(f"stand-in body model {path} is missing; build it with "
                                    "python scripts/build_body_model.py")
    else:
        path = _resolve(model_path, gender)
    arrays = _read(path)
    available = np.shape(arrays["shapedirs"])[-1]
    num_betas = min(10, available) if num_betas is None else num_betas
    if not 0 < num_betas <= available:
        raise ValueError(f"num_betas={num_betas}: body model {path} has {available} shape directions")
    vertex_ids = None  # smplx's own, for SMPL's topology
    if "landmark_names" in arrays:
        vertex_ids = dict(zip(arrays["landmark_names"].tolist(), arrays["landmark_vertex_ids"].tolist()))
    # smplx prints a warning for any model with fewer than 300 shape directions (SMPL has 10).
    with contextlib.redirect_stdout(io.StringIO()):
        return smplx.SMPL(str(path), data_struct=Struct(**arrays), num_betas=num_betas, gender=gender,
                          vertex_ids=vertex_ids, dtype=dtype)


def _rows(x, frames: int, width: int, name: str, dtype) -> torch.Tensor:
    """x as a (frames, width) tensor: None gives zeros, a single row is repeated."""
    if x is None:
        return torch.zeros(frames, width, dtype=dtype)
    x = torch.as_tensor(np.asarray(x), dtype=dtype)
    if x.shape not in ((width,), (1, width), (frames, width)):
        raise ValueError(f"{name} has shape {tuple(x.shape)}; expected ({width},) or ({frames}, {width})")
    return x.reshape(-1, width).expand(frames, width)


def _betas(model: smplx.SMPL, betas, frames: int) -> torch.Tensor:
    """(frames, model.num_betas); fewer coefficients are padded with zeros."""
    dtype = model.v_template.dtype
    if betas is not None:
        betas = torch.as_tensor(np.asarray(betas), dtype=dtype)
        if betas.shape[-1] > model.num_betas:
            raise ValueError(f"betas has {betas.shape[-1]} coefficients; the body model has {model.num_betas}")
        betas = torch.nn.functional.pad(betas, (0, model.num_betas - betas.shape[-1]))
    return _rows(betas, frames, model.num_betas, "betas", dtype)


def forward(model: smplx.SMPL, body_pose, global_orient, transl=None, betas=None):
    """Posed joints (T, 24, 3) and vertices (T, V, 3), float64 metres, from smplx's forward pass.

    body_pose (T, 69) or (T, 23, 3) axis-angle; global_orient (T, 3); transl (T, 3) m or None;
    betas (B,) or (T, B) with B <= model.num_betas (the rest are zero), or None.
    Only SMPL's 24 joints are returned; smplx's extra keypoints follow them in `model(...).joints`.
    """
    dtype = model.v_template.dtype
    body_pose = torch.as_tensor(np.asarray(body_pose), dtype=dtype)
    if tuple(body_pose.shape[1:]) not in ((69,), (23, 3)):
        raise ValueError(f"body_pose has shape {tuple(body_pose.shape)}; expected (T, 69) or (T, 23, 3)")
    frames = len(body_pose)
    body_pose = body_pose.reshape(frames, 69)
    global_orient = _rows(global_orient, frames, 3, "global_orient", dtype)
    transl = _rows(transl, frames, 3, "transl", dtype)
    betas = _betas(model, betas, frames)
    joints, vertices = [], []
    with torch.no_grad():
        for s in range(0, frames, CHUNK):
            out = model(betas=betas[s:s + CHUNK], body_pose=body_pose[s:s + CHUNK],
                        global_orient=global_orient[s:s + CHUNK], transl=transl[s:s + CHUNK])
            joints.append(out.joints[:, :NUM_JOINTS].double().numpy())
            vertices.append(out.vertices.double().numpy())
    return np.concatenate(joints), np.concatenate(vertices)


def rest_skeleton(model: smplx.SMPL, betas=None) -> Skeleton:
    """Rest joints and floor (lowest vertex) of a shape: what procedural motions are grounded on."""
    with torch.no_grad():
        v_shaped = model.forward_shape(betas=_betas(model, betas, 1)).vertices[0]
        joints = model.J_regressor @ v_shaped
    return Skeleton(joints.double().numpy(), float(v_shaped[:, 1].min()), tuple(model.parents.tolist()))


def rest_pose_mm(model: smplx.SMPL, betas=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(joints (24, 3), vertices (V, 3), stature) of a shape at rest, in mm: the stature is its
    lowest to its highest vertex."""
    joints, vertices = forward(model, np.zeros((1, 69)), np.zeros((1, 3)), betas=betas)
    joints, vertices = to_mm(joints[0]), to_mm(vertices[0])
    return joints, vertices, float(np.ptp(vertices[:, 1]))


def to_mm(metres) -> np.ndarray:
    """Body coordinates (m, smplx) to SynthCal's millimetres."""
    return np.asarray(metres, dtype=np.float64) * MM_PER_M
