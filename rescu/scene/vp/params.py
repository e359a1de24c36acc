"""Parameters of vanishing-point detection: :class:`VPParams` (config section ``scene.vp``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ...params import config_section, params_from_dict


@dataclass(frozen=True)
@config_section("scene", "vp")
class VPParams:
    """Parameters of vanishing-point detection (RP-based and line baseline).

    Attributes
    ----------
    ransac_iterations : int
        Line pairs hypothesised (all pairs when there are fewer).
    inlier_angle_deg : float
        A line supports a VP when its angle to the direction towards the VP is below this.
    ac_threshold_deg : float
        Angular constraint: pairs of lines closer to parallel than this hypothesise no VP.
    min_lines : int
        Fewest lines (and fewest inliers) for a VP.
    infinity_alpha : float
        Level of the F-test that snaps a VP to infinity when the data cannot tell it
        from a point at infinity; 0 disables snapping.
    infinity_noise_deg : float
        Floor of the per-line angular noise in that F-test (degrees): the noise of the
        lines of one instance is correlated (instance deformation, localisation), so
        the residual of the finite fit underestimates it.
    infinity_noise_px : float
        Floor of the feature noise (pixels) in the point-level infinity test on feature
        tracks (:func:`rescu.scene.vp.refine.ml_infinity_test`), which replaces the
        line-level test when the lines carry their points.
    row_tolerance : float
        An instance centre belongs to a row when it lies within this fraction of the
        instance's smaller box side from the row line.
    min_row_instances : int
        Fewest instances in a row (a pattern of exactly 2 instances is one row).
    max_line_residual : float
        An implicit line whose RMS residual exceeds this fraction of the median instance
        size is dropped (feature mismatch).
    precision_floor_px : float
        Implicit lines are weighted in the refinement by their inverse angular variance
        (spread^2 / max(residual, this)^2); 0 weighs all lines equally.
    lsd_min_length : float
        Baseline: shortest LSD segment kept, as a fraction of the image diagonal.
    lsd_max_segments : int
        Baseline: the longest this many segments are kept.
    ml_refine : bool
        Finish the fit with the maximum-likelihood VP
        (:func:`rescu.scene.vp.refine.ml_refine_vp`) on the feature tracks of the inlier
        lines, where the lines carry their points.
    register_centres : bool
        Locate instances by their features (:func:`rescu.layout.registered_centres`) instead of
        their box centres for rows and the centre fallbacks, and leave duplicate
        instances (registered centres closer than half an instance) out of the rows.
    joint_alpha : float
        Level of the likelihood-ratio test that merges another pattern's feature tracks into
        the image VP of the dominant pattern
        (:func:`rescu.scene.vp.estimator.joint_vanishing_point`: the patterns share the VP
        unless the joint fit is significantly worse); 0: the image VP is the dominant
        pattern's own.
    union_rows : bool
        Seek the image VP first among the rows of all patterns together
        (:func:`rescu.scene.vp.estimator.union_vanishing_point`, checked against each
        pattern's own VP at level ``joint_alpha``); False: only the groups of patterns
        that share a VP (:func:`rescu.scene.vp.estimator.joint_vanishing_point`).
    hidden_rows : bool
        The RP-only image VP also reads the rows of the stage-I RPs that the confidence
        hid (``candidate_patterns`` dropped for ``"low confidence"``, not the dense
        source's; :func:`rescu.scene.analyse.hidden_patterns`), also on an image
        with no reported RP: keypoint rows too small or thin for the map to vouch for
        them as objects still lie along lines towards a VP, and the paper's stage III
        reads every RP stage I found. They are not reported, counted or drawn, and the
        joint image VP takes the RP-only VP only as a point hypothesis; False: the
        reported RPs alone. Not with ``joint_alpha = 0``.
    spacing_alpha : float
        Level of the likelihood-ratio test that accepts the *spacing model* on rows that
        pass the translation-symmetry test (:func:`rescu.scene.vp.refine.spacing_refine_vp`:
        equally spaced 3D points, so the image spacing along the row also locates the VP);
        0: off.
    seed : int
        Seed of the random pair sampling.
    """

    ransac_iterations: int
    inlier_angle_deg: float
    ac_threshold_deg: float
    min_lines: int
    infinity_alpha: float
    infinity_noise_deg: float
    infinity_noise_px: float
    row_tolerance: float
    min_row_instances: int
    max_line_residual: float
    precision_floor_px: float
    lsd_min_length: float
    lsd_max_segments: int
    ml_refine: bool
    register_centres: bool
    joint_alpha: float
    union_rows: bool
    hidden_rows: bool
    spacing_alpha: float
    seed: int

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "VPParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)
