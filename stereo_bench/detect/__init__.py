"""Pattern detection: find a board's feature points in an image, in ``object_points()`` order.

This is the measuring instrument of the benchmark, so it works as a careful user would: OpenCV's
detectors find the board, the board's own appearance (never the ground truth) fixes the order, and
the points are then measured as precisely as the image allows.

* Checkerboard, ``"classic"`` (default): findChessboardCorners, then every corner re-measured by
  the saddle fit below.  ``"sb"``: findChessboardCornersSB with CALIB_CB_ACCURACY and its own
  subpixel result (OpenCV 5.0 returns it in reverse order).  On clean renders of the paper's
  wide-angle camera classic is about 4x more accurate (see benchmarks/detection_accuracy.py); SB
  is kept to measure what the choice costs.
* Circle grids, ``"grid"``: findCirclesGrid (retried with CALIB_CB_CLUSTERING, which copes with
  stronger perspective) with a blob detector sized from the image and the board; the returned
  grid must be locally affine (a mis-ordered grid is rejected), and every centre is re-measured at
  full resolution as the darkness centroid of its disc, with windows sized by the discs' diameter
  as measured in the image (the pattern's ``diameter_mm`` is only the first guess;
  ``measure_disc_diameter`` measures it over a set of images).  A disc cut by the image border,
  or without paper around it inside the board's outline, whose centroid would be biased, becomes
  a NaN row.  That is the centroid of the imaged ellipse, which is not the image of the circle's
  centre under perspective: the bias is what circle boards really cost, and it is kept, not
  corrected.
* ChArUco, ``"charuco"``: cv2.aruco.CharucoDetector, then each corner re-measured by the saddle
  fit restricted to the square edges, which keeps the markers out of it.  Partial boards are
  allowed (unseen corners are NaN rows); fewer than ``MIN_CHARUCO_CORNERS`` corners count as not
  found.

Saddle fit (``refine_saddles``, both corner boards).  Real boards have no white quiet zone: they
are printed or cut to (or into) their outer squares and lie on a dark frame or in a hand.  A
corner is measured only from image content known to be the board's: a Förstner fit over a
window laid out on the grid (through the local board -> image map of its neighbours), short of
the next grid line and, beside the outer squares, of where the image shows the print to end.
On OpenCV's sample stereo images (benchmarks/real_detection.py) the opencv method's RPE is
0.173 / 0.172 px on these corners, against 0.655 / 0.811 with cornerSubPix and a window of half a
square, and 0.408 / 0.458 with OpenCV's own pipeline (whose 11 x 11 window is pulled on 12-13
corners per camera too); tests/detect/test_detect_margin.py renders the failure for all four boards.

Orientation.  The 9 x 12 checkerboard is not 180-degree symmetric in colour (the square diagonally
beyond corner 0 is black, the one beyond the last corner white), so its order is read from the
image whatever the roll.  ChArUco ids and the asymmetric grid (odd row count) are unambiguous.  A
symmetric circle grid has no cue at all: its orientation is defined only up to its symmetry (180
degrees, and 90 degrees when square) and is fixed by convention: the row direction (point 0 ->
point 1) is the one closest to the image's +x axis, i.e. point 0 is the grid corner nearest the
image's top-left.  The order is right for views rolled less than 90 degrees from upright (45 for
the square 10 x 10 grid) and turned beyond; ``detection_errors`` counts such flips against the
truth.

Search and measurement.  The search runs on a copy whose longest side is at most
``SEARCH_MAX_SIDE`` px (findChessboardCornersSB takes > 20 s on 4096 x 3072; ChArUco's markers of a
small image are searched on a copy enlarged to ``CHARUCO_MIN_SEARCH_SIDE``), and every point is
then measured on the full image: the saddle fit for checkerboard corners (SB's included when the
copy was shrunk); for ChArUco the markers found on the copy, scaled back, go to CharucoDetector, which
interpolates the corners on the full image before the saddle fit; circle centres are always
re-measured at full resolution (a centroid needs only a window, which the scaled-back estimate
places to well under a pixel).  A shrunk checkerboard or circle grid copy is blurred by 1 px
first: sensor noise would otherwise fill the search with specks and double its time.  A ChArUco
board not found as described costs one more marker search, for any marker of the board's ids
in either polarity, printed or mirrored; only when that finds one are the other polarity and
the mirror image searched (a studio camera sees no board in most frames).  Where the camera's
previous frame had no board, that search goes first: when it finds no marker, neither would
the first search, so such a frame costs one marker search.  A board whose markers are read (two
or more of its ids) but with too few corners between them is seen as it is, and not searched
again inverted or mirrored.  Markers are read against the first markers of the dictionary, up
to the board's largest id (OpenCV takes the first marker within the correction distance, so
the board's ids read as with the whole dictionary).  The per-pixel work of
both measurements (each saddle-fit step, each disc window) is compiled with numba: a single pass
over each window's pixels.

"""
