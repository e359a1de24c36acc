"""The image's vanishing points from every cue: the Manhattan triplet and the focal length.

:func:`manhattan_vps` takes image lines from any number of *cues* — explicit LSD segments
(:func:`rescu.scene.vp.lsd.lsd_segments`) and the implicit lines of RP rows
(:func:`rescu.scene.vp.lines.pattern_lines`: the tracks of corresponding features along a
row) — and estimates up to three mutually orthogonal 3D directions (a *Manhattan frame*)
whose vanishing points (VPs) the lines point to, with the focal length they imply when it
is not given (principal point at the image centre, square pixels, no skew).

1. **Hypotheses** (after Lu et al., WACV 2017, "2-line exhaustive search"): for a focal
   length ``f``, two lines give the first VP (their intersection) and so a direction
   ``d1``; a third line's interpretation plane gives ``d2`` (orthogonal to ``d1``, inside
   that plane) and ``d3 = d1 x d2``. Lines are drawn with probability proportional to
   their weight, ``hypotheses`` triplets per focal; with the focal unknown, every focal of
   a log-spaced grid over ``focal_range`` (times the larger image side) is tried with the
   same draws.
2. **Scoring**: every line of every cue votes for the VP it points to best, with the
   truncated quadratic ``w (1 - (e / tau)^2)`` where ``e`` is the sine of the angle
   between the line and the direction from its midpoint to the VP and ``tau`` the sine of
   ``inlier_angle_deg``; ``w`` is the line's weight: its length in pixels, times the
   cue's weight (``rp_weight`` for implicit lines, whose length is the span of their
   points).
3. **Refinement**: the best hypothesis is refined on its inliers (lines within
   ``refine_angle_deg`` of their VP) by weighted least squares of the sines over the
   rotation (and the log focal length, with a weak prior at the hypothesis' focal so
   that an unobservable focal, e.g. two VPs at infinity, stays put), re-assigning the
   inliers three times.
4. **Refit**: with ``refit_free`` each VP is refitted on its own inliers (weighted least
   squares of the sines, :func:`rescu.scene.vp.geometry._fit_vp`), no longer bound to
   be orthogonal to the others. A *point hypothesis* (a VP estimated elsewhere, e.g.
   the RP-based VPs of the scene step) then replaces it when its lines cannot tell the
   two apart (:func:`_point_hypothesis`, level ``point_alpha``).
5. **Result**: the three VPs ordered by support (inlier weight); a VP with fewer than
   ``min_lines`` inlier lines is left out of the list. The first is the *dominant* VP.

All estimation runs in normalised coordinates (principal point at 0, (W + H) / 2 pixels
to 1). Directions are in the camera frame (x right, y down, z forward), sign fixed so
that the VP's homogeneous ``w >= 0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ...params import config_section, params_from_dict
from ...types import VanishingPoint
from .geometry import _canonical, _chi2_ppf, _fit_vp, inside_image
from .lines import Lines


@dataclass(frozen=True)
@config_section("scene", "image_vp")
class ImageVPParams:
    """Parameters of the image's joint VP estimator (config section ``scene.image_vp``;
    defaults from the shipped configuration, :func:`rescu.params.config_section`).

    Attributes
    ----------
    hypotheses : int
        Line triplets drawn per focal length tried.
    inlier_angle_deg : float
        Scale ``tau`` of the truncated-quadratic vote, degrees.
    refine_angle_deg : float
        Inlier threshold of the refinement and of the reported support, degrees.
    min_lines : int
        Fewest inlier lines for a VP to be reported.
    focal_px : float or None
        The focal length in original pixels when known; None: estimated.
    focal_range : (float, float)
        Focal lengths tried when it is estimated, as multiples of the larger image side.
    focal_steps : int
        Number of focal lengths tried (log-spaced over ``focal_range``).
    line_weight : float
        Weight of an LSD segment per pixel of length (0: explicit lines are not used).
    rp_weight : float
        Weight of an RP implicit line per pixel of its span (0: RP rows are not used).
    refit_free : bool
        Refit each VP on its own inliers after the frame's refinement (the Manhattan
        frame then only assigns the lines; real scenes are not exactly orthogonal:
        York Urban's ground-truth directions deviate by 1.4 degrees, median); False:
        report the strictly orthogonal frame.
    noise_px : float
        Noise floor of a line point (pixels): a segment's direction has the angular
        standard deviation ``noise_px * sqrt(2) / length``, an RP implicit line that of
        its fit (:func:`angular_sigma`); the test of ``point_alpha`` weighs lines by the
        inverse variance. (The fits weigh them by their votes: inverse-variance weights
        fitted York Urban's VPs less well, median 0.78 against 0.55 degrees;
        ``benchmarks/studies/image_vp_sweep.py``.)
    point_alpha : float
        A VP given as a point hypothesis (the RP-based VPs of the scene step, whose
        maximum-likelihood and spacing refinements locate a VP along its lines better
        than a line fit does where the lines are nearly parallel) replaces a fitted VP
        when that VP's lines cannot tell the two apart: likelihood-ratio test of this
        level (:func:`_point_hypothesis`); 0: never.
    seed : int
        Seed of the random draws.
    """

    hypotheses: int
    inlier_angle_deg: float
    refine_angle_deg: float
    min_lines: int
    focal_px: float | None
    focal_range: tuple[float, float]
    focal_steps: int
    line_weight: float
    rp_weight: float
    refit_free: bool
    noise_px: float
    point_alpha: float
    seed: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "focal_range", tuple(float(v) for v in self.focal_range))
        lo, hi = self.focal_range
        if lo > hi:
            raise ValueError(f"ImageVPParams.focal_range must be [low, high] with low <= high, "
                             f"got {list(self.focal_range)}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "ImageVPParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


@dataclass
class ManhattanVP:
    """One VP of the image's Manhattan frame.

    Attributes
    ----------
    vanishing_point : VanishingPoint
        Homogeneous pixel point (original pixels), ``support`` = inlier lines.
    direction : (3,) float
        Unit 3D direction, camera frame (x right, y down, z forward).
    weight : float
        Inlier weight (sum of the inlier lines' weights).
    cues : dict of str -> int
        Inlier lines per cue (e.g. ``{"lines": 120, "rp_rows": 4}``).
    """

    vanishing_point: VanishingPoint
    direction: np.ndarray
    weight: float
    cues: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d = self.vanishing_point.to_json()
        d["direction"] = [round(float(v), 9) for v in self.direction]
        d["weight"] = round(float(self.weight), 6)
        d["cues"] = {k: int(v) for k, v in self.cues.items()}
        return d


@dataclass
class ManhattanResult:
    """The image's VPs: ``vps`` ordered by support (the first is the dominant VP), and
    the focal length (original pixels) they were estimated with."""

    vps: list[ManhattanVP]
    focal_px: float
    focal_estimated: bool

    @property
    def dominant(self) -> VanishingPoint | None:
        return self.vps[0].vanishing_point if self.vps else None


# --------------------------------------------------------------------------- geometry
def _rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``r`` (3,), radians."""
    th = float(np.linalg.norm(r))
    if th < 1e-15:
        return np.eye(3)
    k = r / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


def _vps_of(dirs: np.ndarray, f: float) -> np.ndarray:
    """Homogeneous normalised VPs ``(..., 3)`` of unit directions ``(..., 3)``, focal ``f``."""
    return dirs * np.array([f, f, 1.0])


def _sines(vps: np.ndarray, mids: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Sine of the angle between each line and the direction from its midpoint to each VP.

    ``vps`` (..., 3) homogeneous, ``mids`` / ``dirs`` (N, 2) (unit directions); returns
    (..., N).
    """
    t = vps[..., None, :2] - mids * vps[..., None, 2:3]
    cross = dirs[:, 0] * t[..., 1] - dirs[:, 1] * t[..., 0]
    return np.abs(cross) / np.maximum(np.hypot(t[..., 0], t[..., 1]), 1e-12)


def _homogeneous_lines(mids: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Homogeneous lines (N, 3) through ``mids`` (N, 2) along ``dirs`` (N, 2)."""
    return np.cross(np.c_[mids - dirs, np.ones(len(mids))],
                    np.c_[mids + dirs, np.ones(len(mids))])


def _hypotheses(lines: np.ndarray, draws: np.ndarray, f: float) -> np.ndarray:
    """Manhattan frames ``(H', 3, 3)`` (rows = unit directions) from triplets ``draws``
    (H, 3) of the homogeneous ``lines`` (N, 3) at focal ``f`` (normalised); degenerate
    draws are dropped."""
    v1 = np.cross(lines[draws[:, 0]], lines[draws[:, 1]])
    d1 = v1 / np.array([f, f, 1.0])
    n3 = lines[draws[:, 2]] * np.array([f, f, 1.0])
    d1n = np.linalg.norm(d1, axis=1)
    ok = d1n > 1e-12
    d1 = d1[ok] / d1n[ok, None]
    d2 = np.cross(d1, n3[ok])
    d2n = np.linalg.norm(d2, axis=1)
    ok2 = d2n > 1e-12
    d1, d2 = d1[ok2], d2[ok2] / d2n[ok2, None]
    return np.stack([d1, d2, np.cross(d1, d2)], axis=1)


def _scores(frames: np.ndarray, f: float, mids: np.ndarray, dirs: np.ndarray,
            w: np.ndarray, tau: float, chunk: int = 256) -> np.ndarray:
    """Truncated-quadratic score (H,) of each frame (H, 3, 3)."""
    out = np.empty(len(frames))
    for s in range(0, len(frames), chunk):
        e = _sines(_vps_of(frames[s:s + chunk], f), mids, dirs).min(axis=1)   # (h, N)
        out[s:s + chunk] = (np.maximum(0.0, 1.0 - (e / tau) ** 2) * w).sum(axis=1)
    return out


def _refine(frame: np.ndarray, f: float, estimate_f: bool, mids: np.ndarray,
            dirs: np.ndarray, w: np.ndarray, thr: float,
            rounds: int = 3) -> tuple[np.ndarray, float]:
    """Least-squares refinement of the frame (3, 3) and (optionally) the focal."""
    from scipy.optimize import least_squares

    f0 = f
    prior = 0.01 * np.sqrt(max(float(w.sum()), 1e-12))
    for _ in range(rounds):
        e = _sines(_vps_of(frame, f), mids, dirs)                      # (3, N)
        k = e.argmin(axis=0)
        inl = e[k, np.arange(len(k))] < thr
        if inl.sum() < 3:
            break
        m, d, sw, kk = mids[inl], dirs[inl], np.sqrt(w[inl]), k[inl]
        base = frame.copy()

        def resid(x: np.ndarray) -> np.ndarray:
            fr = base @ _rodrigues(x[:3]).T
            ff = f * np.exp(x[3]) if estimate_f else f
            v = _vps_of(fr, ff)[kk]                                    # (n, 3)
            t = v[:, :2] - m * v[:, 2:3]
            cr = d[:, 0] * t[:, 1] - d[:, 1] * t[:, 0]
            r = sw * cr / np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-12)
            if estimate_f:
                r = np.r_[r, prior * (np.log(ff) - np.log(f0))]
            return r

        x0 = np.zeros(4 if estimate_f else 3)
        sol = least_squares(resid, x0, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=200)
        frame = base @ _rodrigues(sol.x[:3]).T
        if estimate_f:
            f = f * float(np.exp(sol.x[3]))
    return frame, f


def angular_sigma(lines: Lines, noise_px: float) -> np.ndarray:
    """Standard deviation (radians) of each line's direction, (L,).

    A line fitted to points (``Lines.points``: RP implicit lines) has
    ``max(r, noise_px) / sqrt(sum (t_i - mean t)^2)``, with ``r`` the RMS distance of its
    points from it and ``t_i`` their positions along it; a segment without points (LSD)
    is its two end points: ``noise_px * sqrt(2) / length`` (``Lines.weights`` = length).
    """
    out = noise_px * np.sqrt(2.0) / np.maximum(np.asarray(lines.weights, float), 1e-9)
    if lines.points is None:
        return out
    for i, q in enumerate(lines.points):
        if len(q) < 2:
            continue
        c = q - q.mean(axis=0)
        t = c @ lines.directions[i]
        r = c @ np.array([-lines.directions[i][1], lines.directions[i][0]])
        rms = float(np.sqrt(np.mean(r ** 2)))
        out[i] = max(rms, noise_px) / max(float(np.sqrt(np.sum(t ** 2))), 1e-9)
    return out


def _point_hypothesis(v: np.ndarray, cands: Sequence[np.ndarray], mids: np.ndarray,
                      dirs: np.ndarray, prec: np.ndarray, alpha: float) -> np.ndarray:
    """The fitted VP ``v`` (normalised), or the candidate of ``cands`` its lines cannot
    tell from it: the likelihood-ratio statistic ``sum p_i (e_ic^2 - e_iv^2) / s^2``
    (``p_i`` the inverse angular variances, ``e`` the sines, ``s^2`` the residual variance
    factor of ``v``, at least 1) below the ``1 - alpha`` quantile of chi^2(2); the
    smallest statistic wins."""
    if alpha <= 0 or not cands or len(mids) < 3:
        return v
    c_v = prec * _sines(v, mids, dirs) ** 2
    s2 = max(float(c_v.sum()) / (len(mids) - 2), 1.0)
    crit = _chi2_ppf(1.0 - alpha, 2)
    best, best_t = v, crit
    for c in cands:
        t = float((prec * _sines(c, mids, dirs) ** 2 - c_v).sum()) / s2
        if t < best_t:
            best, best_t = c / np.linalg.norm(c), t
    return best


# --------------------------------------------------------------------------- estimator
def manhattan_vps(cues: Sequence[tuple[str, Lines, float]], image_size: tuple[int, int],
                  params: ImageVPParams = ImageVPParams(),
                  focal_px: float | None = None,
                  principal_point: tuple[float, float] | None = None,
                  point_hypotheses: Sequence[np.ndarray] = ()) -> ManhattanResult | None:
    """The image's Manhattan VPs from lines of several cues (module docstring).

    Parameters
    ----------
    cues : list of (name, Lines, weight)
        Each cue's lines in pixels of the image (``Lines.weights`` = length or span in
        pixels) and its weight per pixel (e.g. ``("lines", lsd, 1.0)``,
        ``("rp_rows", implicit, 1.0)``); a cue of weight 0 is left out.
    image_size : (int, int)
        ``(width, height)`` of the image the lines are in, pixels.
    params : ImageVPParams
    focal_px : float or None
        Focal length in the same pixels; None: ``params.focal_px`` if set (the caller
        scales it), else estimated.

    Returns
    -------
    ManhattanResult or None
        None when fewer than 3 lines are given. VPs are in the pixels of ``image_size``.
    """
    w_img, h_img = image_size
    if w_img <= 0 or h_img <= 0:
        raise ValueError(f"image_size must be positive, got {image_size}")
    names, mids, dirs, wts, sigs = [], [], [], [], []
    for name, lines, cw in cues:
        if cw <= 0 or len(lines) == 0:
            continue
        d = np.asarray(lines.directions, float)
        n = np.linalg.norm(d, axis=1)
        ok = (n > 0) & (np.asarray(lines.weights, float) > 0)
        mids.append(np.asarray(lines.midpoints, float)[ok])
        dirs.append(d[ok] / n[ok, None])
        wts.append(np.asarray(lines.weights, float)[ok] * cw)
        sigs.append(angular_sigma(lines, params.noise_px)[ok])
        names += [name] * int(ok.sum())
    if not mids or sum(len(m) for m in mids) < 3:
        return None
    s = 2.0 / (w_img + h_img)
    pp = (np.array([w_img / 2.0, h_img / 2.0]) if principal_point is None
          else np.asarray(principal_point, float))
    mids_n = (np.concatenate(mids) - pp) * s
    dirs_n = np.concatenate(dirs)
    w = np.concatenate(wts) * s
    var_inv = 1.0 / np.concatenate(sigs) ** 2         # inverse angular variances

    cue = np.array(names)
    tau = np.sin(np.radians(params.inlier_angle_deg))
    thr = np.sin(np.radians(params.refine_angle_deg))

    estimate_f = focal_px is None
    if estimate_f:
        lo, hi = params.focal_range
        side = max(w_img, h_img) * s
        focals = list(np.geomspace(lo * side, hi * side, params.focal_steps))
    else:
        focals = [float(focal_px) * s]
    rng = np.random.default_rng(params.seed)
    p = w / w.sum()
    draws = rng.choice(len(w), size=(params.hypotheses, 3), p=p)
    draws = draws[(draws[:, 0] != draws[:, 1]) & (draws[:, 2] != draws[:, 0])
                  & (draws[:, 2] != draws[:, 1])]
    best: tuple[float, np.ndarray, float] | None = None
    lines = _homogeneous_lines(mids_n, dirs_n)        # the same for every focal tried
    for f in focals:
        frames = _hypotheses(lines, draws, f)
        if not len(frames):
            continue
        sc = _scores(frames, f, mids_n, dirs_n, w, tau)
        i = int(np.argmax(sc))
        if best is None or sc[i] > best[0]:
            best = (float(sc[i]), frames[i], f)
    if best is None:
        return None
    frame, f = _refine(best[1], best[2], estimate_f, mids_n, dirs_n, w, thr)

    e = _sines(_vps_of(frame, f), mids_n, dirs_n)
    k = e.argmin(axis=0)
    inl = e[k, np.arange(len(k))] < thr
    t_n = np.array([[s, 0, -s * pp[0]], [0, s, -s * pp[1]], [0, 0, 1.0]])
    cands = [t_n @ np.asarray(v, float) for v in point_hypotheses]
    t_inv = np.array([[1 / s, 0, pp[0]], [0, 1 / s, pp[1]], [0, 0, 1.0]])
    vps = []
    for j in range(3):
        sel = inl & (k == j)
        if sel.sum() < params.min_lines:
            continue
        d = frame[j] / np.linalg.norm(frame[j])
        if params.refit_free:
            vn = _fit_vp(mids_n[sel], dirs_n[sel], w[sel], _vps_of(d, f))
            vn = _point_hypothesis(vn, cands, mids_n[sel], dirs_n[sel], var_inv[sel],
                                   params.point_alpha)
            d = vn / np.array([f, f, 1.0])
            d = d / np.linalg.norm(d)
        v = _canonical(t_inv @ _vps_of(d, f))
        if float(d @ (np.linalg.solve(t_inv, v) / np.array([f, f, 1.0]))) < 0:
            d = -d              # the direction's sign follows the canonical point's
        cues_j = {c: int(np.sum(sel & (cue == c))) for c in dict.fromkeys(names)}
        vps.append(ManhattanVP(VanishingPoint(v, inside_image(v, image_size), int(sel.sum())),
                               d + 0.0, float(w[sel].sum() / s), cues_j))
    vps.sort(key=lambda m: -m.weight)
    return ManhattanResult(vps, float(f / s), estimate_f)
