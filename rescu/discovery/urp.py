"""Unit recurring patterns (URPs): the 2 x 2 building blocks of an RP matrix Omega.

A URP takes visual words ``m1, m2`` in instances ``n1, n2`` with features
``(f11, f12, f21, f22)`` (``f_{word,instance}``). Its affinity (RESCU, eq. for u)::

    u = exp(-Delta_s^2 / (2 sigma_s) - Delta_theta^2 / (2 sigma_theta))
    r = d(f11, f21) / d(f12, f22)                      # instance size ratio
    D_s(fi, fj) = (s_i - r s_j) / (s_i + r s_j)
    Delta_s = max(|D_s(f11, f12)|, |D_s(f21, f22)|)

``Delta_theta`` has three forms (``orientation_mode``):

* ``"paper"``: ``D_theta(fi, fj) = (theta_i - r theta_j) / (theta_i + r theta_j)`` with
  angles in degrees, ``Delta_theta = max(|D_theta(f11, f12)|, |D_theta(f21, f22)|)``
  (as printed; scaling an angle by a size ratio is dimensionally odd and jumps at the
  0/360 wrap).
* ``"wrapped"`` (default): ``Delta_theta = max(|wrap(theta_11 - theta_12)|,
  |wrap(theta_21 - theta_22)|) / 180`` in ``[0, 1]``: each word has the same orientation
  in both instances. Chosen as the default because the recurring patterns RESCU targets
  (windows, chess pieces, cars in a car park) are translated copies in an upright photo;
  an absolute difference also rejects accidental URPs between rotated look-alikes.
* ``"relative"``: ``Delta_theta = |wrap((theta_12 - theta_11) - (theta_22 - theta_21))|
  / 180``: the rotation between the two instances is the same for both words, so
  rotated copies (e.g. cars parked at an angle) score 1. Use it for rotated RPs.

``wrap`` maps degrees to ``(-180, 180]``.

Candidate correspondences (which features can be the same visual word in two instances)
come from descriptor similarity: RootSIFT descriptors, for each feature its ``k``
nearest descriptor neighbours with Euclidean distance below ``max_dist`` that lie
farther than ``min_sep`` keypoint radii away (a feature is not its own copy). Visual
words are therefore formed implicitly, per RP row, as sets of mutually similar
features, rather than by a global vocabulary.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..params import config_defaults, config_section, schema_enum

ORIENTATION_MODES: tuple[str, ...] = schema_enum("stage1", "orientation_mode")

_D = config_defaults("stage1")


@dataclass(frozen=True)
@config_section("stage1")
class AffinityParams:
    """The URP affinity's parameters, shared by stage I, GRASP and the search context.

    Defaults: the ``stage1`` section of the shipped configuration (``sigma_s``,
    ``sigma_theta``, ``orientation_mode``).

    Attributes
    ----------
    sigma_s, sigma_theta : float
        Bandwidths of Delta_s and Delta_theta (the paper's 0.2).
    orientation_mode : {"wrapped", "relative", "paper"}
        The form of Delta_theta (module docstring).
    """

    sigma_s: float
    sigma_theta: float
    orientation_mode: str


@dataclass(frozen=True)
class MatchParams:
    """Candidate correspondences (:func:`match_candidates`), shared by stage I and GRASP.

    Defaults: ``match_k``, ``match_max_dist``, ``match_min_sep`` of the shipped
    configuration's ``stage1`` section.

    Attributes
    ----------
    k : int
        Descriptor neighbours per feature.
    max_dist : float
        Largest RootSIFT Euclidean distance of a candidate (in [0, sqrt 2]).
    min_sep : float
        Least separation of a copy, keypoint radii.
    """

    k: int = _D["match_k"]
    max_dist: float = _D["match_max_dist"]
    min_sep: float = _D["match_min_sep"]


class AffinityMatchGroups:
    """Mixin of a parameter dataclass with the flat fields ``sigma_s``, ``sigma_theta``,
    ``orientation_mode`` and ``match_k``, ``match_max_dist``, ``match_min_sep`` (as the
    configuration spells them; the dataclass declares them): the two groups as
    :class:`AffinityParams` and :class:`MatchParams`."""

    @property
    def affinity(self) -> AffinityParams:
        """``sigma_s``, ``sigma_theta``, ``orientation_mode`` as an AffinityParams."""
        return AffinityParams(self.sigma_s, self.sigma_theta, self.orientation_mode)

    @property
    def match(self) -> MatchParams:
        """``match_k``, ``match_max_dist``, ``match_min_sep`` as a MatchParams."""
        return MatchParams(self.match_k, self.match_max_dist, self.match_min_sep)


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Wrap angles (degrees) into ``(-180, 180]``."""
    a = np.asarray(a, np.float64)
    return 180.0 - np.mod(180.0 - a, 360.0)


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise, square root.

    Parameters
    ----------
    descriptors : (K, D) float
        Raw SIFT descriptors.

    Returns
    -------
    (K, D) float32
        Unit-L2 descriptors; Euclidean distance between them lies in ``[0, sqrt(2)]``.
    """
    d = np.asarray(descriptors, np.float32)
    if d.ndim != 2:
        raise ValueError(f"root_sift: descriptors must have shape (K, D), got {d.shape}")
    d = np.maximum(d, 0.0)
    s = d.sum(axis=1, keepdims=True)
    return np.sqrt(d / np.where(s > 0, s, 1.0)).astype(np.float32)


def urp_terms(xy: np.ndarray, scale: np.ndarray, angle: np.ndarray,
              f11: np.ndarray, f12: np.ndarray, f21: np.ndarray, f22: np.ndarray,
              orientation_mode: str) -> dict[str, np.ndarray]:
    """The quantities of a batch of URPs (broadcast over the index arrays).

    Parameters
    ----------
    xy : (K, 2) float, pixels; scale : (K,) float, pixels; angle : (K,) float, degrees.
    f11, f12, f21, f22 : int arrays of one broadcastable shape S
        Feature indices (word 1 / word 2 in instance 1 / instance 2).
    orientation_mode : {"wrapped", "relative", "paper"}

    Returns
    -------
    dict of arrays of shape S
        ``d1`` = d(f11, f21) and ``d2`` = d(f12, f22) (pixels, within-instance
        distances), ``r`` (instance size ratio), ``delta_s``, ``delta_theta`` (unitless),
        ``size_diff`` = 1 - min(r, 1/r) and ``rot`` = max |wrap(theta_1x - theta_2x)|
        (degrees, the orientation difference between the instances).
    """
    if orientation_mode not in ORIENTATION_MODES:
        raise ValueError(f"orientation_mode must be one of {ORIENTATION_MODES}, "
                         f"got {orientation_mode!r}")
    p11, p12, p21, p22 = xy[f11], xy[f12], xy[f21], xy[f22]
    d1 = np.hypot(p11[..., 0] - p21[..., 0], p11[..., 1] - p21[..., 1])
    d2 = np.hypot(p12[..., 0] - p22[..., 0], p12[..., 1] - p22[..., 1])
    r = d1 / np.maximum(d2, 1e-9)                     # r in the paper
    s11, s12, s21, s22 = scale[f11], scale[f12], scale[f21], scale[f22]

    def d_s(si: np.ndarray, sj: np.ndarray) -> np.ndarray:  # D_s in the paper
        return (si - r * sj) / np.maximum(si + r * sj, 1e-12)

    delta_s = np.maximum(np.abs(d_s(s11, s12)), np.abs(d_s(s21, s22)))  # Delta_s
    t11, t12, t21, t22 = angle[f11], angle[f12], angle[f21], angle[f22]
    rot1 = np.abs(wrap_deg(t11 - t12))
    rot2 = np.abs(wrap_deg(t21 - t22))
    if orientation_mode == "wrapped":
        delta_t = np.maximum(rot1, rot2) / 180.0
    elif orientation_mode == "relative":
        delta_t = np.abs(wrap_deg((t12 - t11) - (t22 - t21))) / 180.0
    else:  # "paper": D_theta(fi, fj) = (theta_i - r theta_j) / (theta_i + r theta_j)
        def d_t(ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
            den = ti + r * tj
            return np.where(den > 1e-9, (ti - r * tj) / np.where(den > 1e-9, den, 1.0), 0.0)
        delta_t = np.maximum(np.abs(d_t(t11, t12)), np.abs(d_t(t21, t22)))
    return {"d1": d1, "d2": np.asarray(d2, np.float64), "r": r, "delta_s": delta_s,
            "delta_theta": delta_t, "size_diff": 1.0 - np.minimum(r, 1.0 / np.maximum(r, 1e-12)),
            "rot": np.maximum(rot1, rot2)}


@dataclass(frozen=True)
class Gates:
    """The adaptive parameters as hard limits on a URP (absolute units).

    Attributes
    ----------
    max_dist : float
        P_d * image diagonal, pixels: both within-instance distances must not exceed it.
    max_size_diff : float
        P_s: ``1 - min(r, 1/r)`` must not exceed it (instance sizes differ by at most a
        factor ``1 / (1 - P_s)``).
    max_rot : float
        P_theta, degrees: the orientation difference of each word between the two
        instances must not exceed it.
    """

    max_dist: float
    max_size_diff: float
    max_rot: float


def urp_affinity(xy: np.ndarray, scale: np.ndarray, angle: np.ndarray,
                 f11: np.ndarray, f12: np.ndarray, f21: np.ndarray, f22: np.ndarray,
                 affinity: AffinityParams = AffinityParams(), gates: Gates | None = None,
                 return_parts: bool = False) -> np.ndarray:
    """URP affinity u of a batch of URPs (see module docstring).

    Parameters
    ----------
    xy : (K, 2) float, pixels
    scale : (K,) float, pixels
    angle : (K,) float, degrees
    f11, f12, f21, f22 : int arrays, one broadcastable shape S
        Feature indices; -1 marks a missing entry (affinity 0).
    affinity : AffinityParams
        sigma_s, sigma_theta and the Delta_theta form.
    gates : Gates, optional
        When given, URPs violating P_d / P_s / P_theta get affinity 0.
    return_parts : bool
        Return the :class:`AffinityParts` (ungated u and gate quantities) instead.

    Returns
    -------
    (S) float64 in [0, 1]
        1 for a perfect translated copy; 0 for a degenerate URP (a repeated feature or
        zero within-instance distance).
    """
    sigma_s, sigma_theta = affinity.sigma_s, affinity.sigma_theta
    orientation_mode = affinity.orientation_mode
    if orientation_mode not in ORIENTATION_MODES:
        raise ValueError(f"orientation_mode must be one of {ORIENTATION_MODES}, "
                         f"got {orientation_mode!r}")
    f11, f12, f21, f22 = (np.asarray(f, np.int64) for f in (f11, f12, f21, f22))
    valid = (f11 >= 0) & (f12 >= 0) & (f21 >= 0) & (f22 >= 0)
    valid &= (f11 != f21) & (f12 != f22) & (f11 != f12) & (f21 != f22)
    # Fast path, same arithmetic as urp_terms: the index arrays are only broadcast by
    # the arithmetic (no materialised copies), and -1 entries index the last feature
    # harmlessly (they are invalid, so masked below).
    xy = np.asarray(xy, np.float64)
    scale = np.asarray(scale, np.float64)
    angle = np.asarray(angle, np.float64)
    x, y = xy[:, 0], xy[:, 1]
    d1 = np.hypot(x[f11] - x[f21], y[f11] - y[f21])
    d2 = np.hypot(x[f12] - x[f22], y[f12] - y[f22])
    r = d1 / np.maximum(d2, 1e-9)                     # r in the paper
    s11, s12, s21, s22 = scale[f11], scale[f12], scale[f21], scale[f22]
    rs12, rs22 = r * s12, r * s22
    # Delta_s = max(|D_s(f11, f12)|, |D_s(f21, f22)|)
    delta_s = np.maximum(np.abs((s11 - rs12) / np.maximum(s11 + rs12, 1e-12)),
                         np.abs((s21 - rs22) / np.maximum(s21 + rs22, 1e-12)))
    t11, t12, t21, t22 = angle[f11], angle[f12], angle[f21], angle[f22]
    rot1 = np.abs(wrap_deg(t11 - t12))
    rot2 = np.abs(wrap_deg(t21 - t22))
    rot = np.maximum(rot1, rot2)
    if orientation_mode == "wrapped":
        delta_t = rot / 180.0
    elif orientation_mode == "relative":
        delta_t = np.abs(wrap_deg((t12 - t11) - (t22 - t21))) / 180.0
    else:  # "paper"
        def d_t(ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
            den = ti + r * tj
            return np.where(den > 1e-9, (ti - r * tj) / np.where(den > 1e-9, den, 1.0), 0.0)
        delta_t = np.maximum(np.abs(d_t(t11, t12)), np.abs(d_t(t21, t22)))
    valid = valid & (d1 > 1e-6) & (d2 > 1e-6)
    u = np.exp(-delta_s ** 2 / (2.0 * sigma_s) - delta_t ** 2 / (2.0 * sigma_theta))
    parts = AffinityParts(np.where(valid, u, 0.0), valid, d1, d2,
                          1.0 - np.minimum(r, 1.0 / np.maximum(r, 1e-12)), rot)
    if return_parts:
        return parts
    return parts.gated(gates)


@dataclass(frozen=True)
class AffinityParts:
    """A batch of URPs with the quantities the gates test, so that one batch can be
    gated by many parameter sets (the adaptive grid) without recomputing it.

    ``u`` is the ungated affinity (0 for degenerate URPs) and ``valid`` its support;
    ``d1``, ``d2`` (pixels), ``size_diff`` and ``rot`` (degrees) as in
    :func:`urp_terms`. The arrays broadcast to one shape S.
    """

    u: np.ndarray
    valid: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    size_diff: np.ndarray
    rot: np.ndarray

    def gated(self, gates: "Gates | None") -> np.ndarray:
        """(S) float64: u with the URPs violating ``gates`` set to 0 (the same values
        as :func:`urp_affinity` with those gates)."""
        if gates is None:
            return self.u
        ok = self.valid & (self.d1 <= gates.max_dist) & (self.d2 <= gates.max_dist)
        ok &= self.size_diff <= gates.max_size_diff
        ok &= self.rot <= gates.max_rot
        return np.where(ok, self.u, 0.0)


@lru_cache(maxsize=512)
def pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)``: all index pairs ``i < j`` of ``n`` items, cached
    (read-only arrays)."""
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = False
    j.flags.writeable = False
    return i, j


def objective_omega(omega: np.ndarray, caller: str) -> np.ndarray | None:
    """An RP matrix ``omega`` (M, N) as int64 for an objective U(Omega), or None when it
    has fewer than 2 rows or columns (U is 0 then); raises ValueError naming ``caller``
    when ``omega`` is not 2-D."""
    omega = np.asarray(omega, np.int64)
    if omega.ndim != 2:
        raise ValueError(f"{caller}: omega must have shape (M, N), got {omega.shape}")
    m, n = omega.shape
    return None if m < 2 or n < 2 else omega


def objective(xy: np.ndarray, scale: np.ndarray, angle: np.ndarray, omega: np.ndarray,
              affinity: AffinityParams = AffinityParams(),
              gates: Gates | None = None) -> float:
    """U(Omega) = 1/(M N) * sum over m1 < m2, n1 < n2 of u(m1, m2, n1, n2 | Omega).

    Parameters
    ----------
    omega : (M, N) int
        Feature indices, -1 for missing entries.

    Returns
    -------
    float
        0 for a matrix with fewer than 2 rows or columns.
    """
    omega = objective_omega(omega, "objective")
    if omega is None:
        return 0.0
    m, n = omega.shape
    i1, i2 = pairs(m)
    j1, j2 = pairs(n)
    a = omega[i1][:, j1]   # f11: word m1, instance n1
    b = omega[i1][:, j2]   # f12
    c = omega[i2][:, j1]   # f21
    d = omega[i2][:, j2]   # f22
    u = urp_affinity(xy, scale, angle, a, b, c, d, affinity, gates)
    return float(u.sum() / (m * n))


def match_candidates(descriptors: np.ndarray, xy: np.ndarray, scale: np.ndarray,
                     match: MatchParams = MatchParams(),
                     block: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Candidate correspondences: k nearest RootSIFT neighbours under a distance limit.

    Parameters
    ----------
    descriptors : (K, 128) float
        Raw SIFT descriptors (RootSIFT is applied here).
    xy : (K, 2) float, pixels; scale : (K,) float, pixels (keypoint diameter).
    match : MatchParams
        ``k`` neighbours per feature; ``max_dist``, the largest RootSIFT Euclidean
        distance of a candidate (in [0, sqrt 2]); a candidate must lie farther than
        ``min_sep * max(size_i, size_j) / 2`` pixels (keypoints overlapping their own
        copy are the same structure).
    block : int
        Rows per block of the brute-force distance computation (memory bound).

    Returns
    -------
    nbr : (K, k) int64
        Neighbour indices sorted by distance, -1 padded.
    dist : (K, k) float32
        Their RootSIFT distances, inf where padded.
    """
    k, max_dist, min_sep = match.k, match.max_dist, match.min_sep
    kk = len(descriptors)
    if np.shape(xy) != (kk, 2):
        raise ValueError(f"match_candidates: xy must have shape ({kk}, 2), got {np.shape(xy)}")
    nbr = np.full((kk, k), -1, np.int64)
    dist = np.full((kk, k), np.inf, np.float32)
    if kk < 2 or k < 1:
        return nbr, dist
    rs = root_sift(descriptors)
    xy = np.asarray(xy, np.float32)
    rad = np.asarray(scale, np.float32) / 2.0
    md2 = max_dist * max_dist
    for s in range(0, kk, block):
        e = min(kk, s + block)
        d2 = 2.0 - 2.0 * (rs[s:e] @ rs.T)
        np.maximum(d2, 0.0, out=d2)
        # only the pairs under the descriptor limit (a small fraction) are examined
        r, c = np.nonzero(d2 <= md2)
        dr = d2[r, c]
        gi = r + s
        dx = xy[gi, 0] - xy[c, 0]
        dy = xy[gi, 1] - xy[c, 1]
        sep = min_sep * np.maximum(rad[gi], rad[c])
        ok = (dx * dx + dy * dy) > sep * sep        # also removes the feature itself
        r, c, dr = r[ok], c[ok], dr[ok]
        # per feature: nearest first, ties by index; keep the first k
        o = np.lexsort((c, dr, r))
        r, c, dr = r[o], c[o], dr[o]
        rank = np.arange(len(r)) - np.searchsorted(r, r, side="left")
        ok = rank < k
        nbr[r[ok] + s, rank[ok]] = c[ok]
        dist[r[ok] + s, rank[ok]] = np.sqrt(dr[ok])
    return nbr, dist
