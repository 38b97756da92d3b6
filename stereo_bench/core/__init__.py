"""What every layer stands on: the camera model and its conventions, the boards, and the files.

* ``camera``: ``Camera`` (pinhole + OpenCV distortion), projection with its Jacobians, the
  single source of truth for projection; ``distortion``: OpenCV's distortion model, its
  Jacobians and its exact inverse; ``poses``: rotations and rigid transforms (Rodrigues,
  composition, look-at, poses relative to a reference camera).
* ``patterns``: the calibration boards (checkerboard, ChArUco, circle grids), their points and
  textures; ``board_shape``: the board as made (warp, misprint).
* ``files``: bounded readers and atomic writers, strict JSON, safe names: every file the suite
  reads or writes goes through them.

Nothing here imports from another package of the suite.
"""
