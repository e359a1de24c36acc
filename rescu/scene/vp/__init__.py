"""Vanishing-point detection (VPD) from recurring patterns, a line baseline, and VP errors.

RP-based VPD (no explicit lines)
--------------------------------
When the instances of an RP recur along a line in 3D, the corresponding features of
one visual word across the instances lie on an *implicit line* in the image, and the
implicit lines of all visual words (and of all parallel rows of the RP) meet at the
vanishing point (VP) of the recurrence direction.

1. :func:`rescu.layout.group_rows` orders the instances into collinear *rows* (greedy
   multi-line search on the instance centres; the longest rows first, and later rows may
   not cross earlier ones, so that a grid yields its rows *or* its columns, never a mix,
   and no diagonals).
2. :func:`~rescu.scene.vp.lines.pattern_lines` fits one implicit line (total least
   squares) per visual word and row; a row with no usable feature gives the line through
   its instance centres.
3. :func:`~rescu.scene.vp.ransac.ransac_vp` hypothesises a VP from every pair of lines
   (all pairs when there are at most ``ransac_iterations`` of them, else that many random
   pairs drawn from ``seed``) and, so that a frontal view is represented, the point at
   infinity along every line. The *angular constraint* (AC) refuses pairs of lines closer
   to parallel than ``ac_threshold_deg``: their intersection is ill-conditioned. A line
   is an inlier of a VP when the angle between the line and the direction from its
   midpoint to the VP is below ``inlier_angle_deg``. The hypothesis with the largest
   (weighted) support is refined by iteratively reweighted least squares of the sines of
   those angles, and replaced by the point at infinity when an F-test (level
   ``infinity_alpha``) cannot tell the finite fit from the best fit at infinity.
4. Where the lines carry their feature points (implicit lines always do),
   :func:`~rescu.scene.vp.refine.ml_refine_vp` finishes with the maximum-likelihood VP:
   every feature track gets its own line through the VP and the squared orthogonal
   distances of all the points are minimised (``ml_refine``). Rows that pass the
   translation-symmetry test also constrain the VP by their spacing
   (:func:`~rescu.scene.vp.refine.spacing_refine_vp`: equally spaced 3D instances, so the
   image spacing shrinks towards the VP; accepted by a likelihood-ratio test of level
   ``spacing_alpha``). The infinity decision is then a point-level F-test
   (:func:`~rescu.scene.vp.refine.ml_infinity_test`, noise floor ``infinity_noise_px``)
   instead of the line-level one, which has only (lines - 2) degrees of freedom.
5. :func:`~rescu.scene.vp.estimator.joint_vanishing_point` re-estimates a VP on the
   tracks of several patterns that share it (likelihood-ratio test of level
   ``joint_alpha``); the scene step uses it for the image's dominant VP.

All estimation runs in normalised coordinates (image centre at 0, (W + H) / 2 pixels to
1); a VP is returned as a unit-norm homogeneous point in original pixels, ``w = 0`` for a
point at infinity.

Line baseline
-------------
:func:`~rescu.scene.vp.lsd.line_vanishing_point`: LSD line segments
(``cv2.createLineSegmentDetector``) longer than ``lsd_min_length`` x the image diagonal,
then the same RANSAC with the segment lengths as weights (a stand-in for Zhou, Farhat
and Wang 2017). The dominant VP (largest inlier length) is returned.

Errors
------
:func:`~rescu.scene.vp.errors.point_error`, :func:`~rescu.scene.vp.errors.vector_error`
(the paper's two VP errors), :func:`~rescu.scene.vp.errors.closest_gt_error` (with
several ground-truth VPs, the error to the closest one) and
:func:`~rescu.scene.vp.errors.success_rate`.

Modules, in the order the data flows: ``params`` (:class:`VPParams`), ``geometry``
(normalisation, angles, least-squares VPs, quantiles), ``lines``, ``refine``,
``ransac``, ``estimator``, ``lsd``, ``errors``. Nothing is imported here.
"""
