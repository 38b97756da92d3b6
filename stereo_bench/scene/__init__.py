"""The world a calibration looks at, synthetic or real, behind one read interface.

* ``rig``: the true cameras (pairs and studio layouts), the board and its trajectory
  (conical spring, studio session, explicit poses);
* ``dataset``: a rendered dataset on disk (images + exact ground truth), rendered on demand;
* ``image_folders``: a user's images or videos per camera, paired by frame, with the same
  interface and no ground truth.
"""
