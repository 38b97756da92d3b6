"""Several cameras at once: the rig's bundle adjustment (``bundle``: one adjuster for stereo
pairs and studios, with the scoring of a rig against the truth), triangulation, the numbering of
a symmetric board's views across cameras (``orientation``), and the independent references the
rig is checked against: pycolmap's bundle adjuster (``colmap_ref``) and OpenCV's
calibrateMultiview (``opencv_ref``).
"""
