"""Automatic stereo: tie points, normalised (epipolar) images, dense surfaces and contours.

* :mod:`softplot.matching.lsm` - least-squares matching of image patches (affine geometry,
  linear radiometry), vectorised over all points, with the precision of every match;
* :mod:`softplot.matching.ties` - tie points between two scans: SIFT in film-corrected
  images, ratio test and mutual check, five-point RANSAC, least-squares matching in the
  scans, relative orientation with data snooping (``softplot match``);
* :mod:`softplot.matching.epipolar` - normalised images of an oriented pair
  (``softplot epipolar``);
* :mod:`softplot.matching.dsm` - semi-global matching of the normalised pair, intersection,
  gridding to a GeoTIFF with a precision band, automatic contours (``softplot dsm``).

Coordinate systems: pixel (x right, y down, origin at the centre of the top-left pixel of a
scan); film and photo mm (``docs/conventions.md``); model and object m.
"""
