"""Vanishing-point detection over a dataset: errors, success rates, paired tests.

The prediction is the image-level ``vanishing_point``; it is compared with the *closest*
ground-truth VP, separately for each error (:func:`rescu.scene.vp.errors.closest_gt_error`):
the point error is the pixel distance between the dehomogenised points
(:func:`rescu.scene.vp.errors.point_error`; infinite when exactly one lies at infinity),
the angle error the angle between the back-projected 3D directions
(:func:`rescu.scene.vp.errors.vector_error`; sign-free), with the true focal length and
principal point where the dataset gives them, else ``f = (w + h) / 4`` and the image
centre. A missing prediction has infinite errors (a failure at every threshold). Every
angle error is also given with the *nominal* focal (``f = (w + h) / 4`` and the image centre,
``angle_error_nominal_deg``), so that a dataset with a true focal reads both ways.

Beside the dominant VP, :func:`vp_triplet_frame` scores every VP a method lists (the
``vanishing_points`` of the joint estimator and of peers; a method with one VP lists that):
each ground-truth VP to its *closest* listed VP. :func:`vp_aa_table` gives the literature's
angular accuracy AA@t (the area under the curve of the share of errors below x, for x
from 0 to t degrees, divided by t) for both.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from ..io import load_vanishing_points
from ..scene.vp.errors import closest_gt_error, vector_error
from ..types import ImageResult
from .core import EvaluationParams, _check_pred_dirs, _paired, load_predictions, paired_wilcoxon


def vp_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
             images: Iterable[str] | None = None,
             truth: str | Path | None = None) -> pd.DataFrame:
    """VP errors per image x method against ``vanishing_points.json`` (``truth``: another
    file in its format, e.g. the derived truth of rectified photos).

    Returns
    -------
    DataFrame
        ``dataset, image, method, vp_missing, point_error_px, angle_error_deg,
        focal_px, focal_source`` ("true" or "assumed": f = (w + h) / 4 and the image
        centre), ``n_gt_vps`` (GT VPs of the image); errors to the closest GT VP (module
        docstring), inf when missing.
        Images without a GT VP are left out.
    """
    rows = []
    for method, f, g, res in _predictions(dataset_dir, pred_dirs, images, truth):
        size, focal, pp, true_f = _camera(g)
        vp = res.vanishing_point if res is not None else None
        if vp is None:
            pe = ae = an = float("inf")
        else:
            pe = closest_gt_error(vp.homogeneous, g["vanishing_points"], "point",
                                  size, focal, pp)
            ae = closest_gt_error(vp.homogeneous, g["vanishing_points"], "vector",
                                  size, focal, pp)
            an = closest_gt_error(vp.homogeneous, g["vanishing_points"], "vector", size)
        rows.append({"dataset": Path(dataset_dir).name, "image": f, "method": method,
                     "vp_missing": vp is None, "point_error_px": pe,
                     "angle_error_deg": ae, "angle_error_nominal_deg": an,
                     "focal_px": focal, "focal_source": "true" if true_f else "assumed",
                     "n_gt_vps": len(g["vanishing_points"])})
    return pd.DataFrame(rows)


def _predictions(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                 images: Iterable[str] | None, truth: str | Path | None
                 ) -> Iterator[tuple[str, str, dict, ImageResult | None]]:
    """``(method, image, its GT, its prediction or None)`` for every method and every
    image (of ``images``; None: all) with a GT VP in ``truth`` (default ``dataset_dir /
    "vanishing_points.json"``); images without one (e.g. a frontal synthetic image) are
    left out."""
    _check_pred_dirs(pred_dirs)
    gt = load_vanishing_points(truth if truth is not None
                               else Path(dataset_dir) / "vanishing_points.json")
    if images is not None:
        keep = set(images)
        gt = {f: v for f, v in gt.items() if f in keep}
    for method, d in pred_dirs.items():
        preds = load_predictions(d, gt.keys())
        for f, g in gt.items():
            if g["vanishing_points"]:
                yield method, f, g, preds[f]


def _camera(g: Mapping) -> tuple[tuple[int, int], float, tuple[float, float], bool]:
    """``(size, focal, principal point, whether the focal is true)`` of one GT image: the
    dataset's calibration where given, else ``f = (w + h) / 4`` and the image centre."""
    w, hgt = int(g["width"]), int(g["height"])
    true_f = g.get("focal_px") is not None
    focal = float(g["focal_px"]) if true_f else (w + hgt) / 4.0
    pp = (tuple(g["principal_point"]) if g.get("principal_point") is not None
          else (w / 2.0, hgt / 2.0))
    return (w, hgt), focal, pp, true_f


def listed_vps(res: ImageResult | None) -> list[np.ndarray]:
    """Every VP a prediction lists: its ``vanishing_points`` (joint estimator, peers),
    else its one image-level ``vanishing_point``; [] without any."""
    if res is None:
        return []
    lst = res.extra.get("vanishing_points")
    if lst:
        return [np.asarray(v["homogeneous"], float) for v in lst]
    return [] if res.vanishing_point is None else [np.asarray(res.vanishing_point.homogeneous,
                                                              float)]


def vp_triplet_frame(dataset_dir: str | Path, pred_dirs: Mapping[str, str | Path],
                     images: Iterable[str] | None = None,
                     truth: str | Path | None = None) -> pd.DataFrame:
    """Each ground-truth VP's angle error to the closest VP a method lists
    (:func:`listed_vps`).

    Returns
    -------
    DataFrame
        ``dataset, image, method, gt_index, n_listed, angle_error_deg`` (true focal and
        principal point where given, else nominal), ``angle_error_nominal_deg``
        (``f = (w + h) / 4``, image centre); inf when the method lists no VP.
    """
    rows = []
    for method, f, g, res in _predictions(dataset_dir, pred_dirs, images, truth):
        size, focal, pp, _ = _camera(g)
        listed = listed_vps(res)
        for j, q in enumerate(g["vanishing_points"]):
            ae = min((vector_error(v, q, size, focal, pp) for v in listed),
                     default=float("inf"))
            an = min((vector_error(v, q, size) for v in listed), default=float("inf"))
            rows.append({"dataset": Path(dataset_dir).name, "image": f, "method": method,
                         "gt_index": j, "n_listed": len(listed),
                         "angle_error_deg": ae, "angle_error_nominal_deg": an})
    return pd.DataFrame(rows, columns=["dataset", "image", "method", "gt_index", "n_listed",
                                       "angle_error_deg", "angle_error_nominal_deg"])


def angular_accuracy(errors: Sequence[float], threshold: float) -> float:
    """AA@t: the area under the share of errors <= x for x in [0, t], divided by t.

    Equals the mean of ``max(0, 1 - e / t)`` (a missing VP, ``inf``, counts 0); NaN for
    no errors.

    >>> angular_accuracy([0.0, 5.0, float("inf")], 10.0)
    0.5
    """
    e = np.asarray(errors, float).reshape(-1)
    if threshold <= 0:
        raise ValueError(f"threshold must be > 0, got {threshold}")
    if not len(e):
        return float("nan")
    return float(np.mean(np.clip(1.0 - e / threshold, 0.0, None)))


def vp_aa_table(errors: pd.DataFrame, triplet: pd.DataFrame,
                thresholds: Sequence[float] = EvaluationParams.vp_aa_thresholds
                ) -> pd.DataFrame:
    """AA@t per dataset, method, target (``dominant``: :func:`vp_frame`; ``triplet``:
    :func:`vp_triplet_frame`) and focal (``true``: the dataset's where given; ``nominal``).

    Returns
    -------
    DataFrame
        ``dataset, method, target, focal, n, AA@<t>...``.
    """
    rows = []
    for target, fr in (("dominant", errors), ("triplet", triplet)):
        if fr is None or not len(fr):
            continue
        for (dsn, method), g in fr.groupby(["dataset", "method"], sort=False):
            for focal, col in (("true", "angle_error_deg"),
                               ("nominal", "angle_error_nominal_deg")):
                r = {"dataset": dsn, "method": method, "target": target, "focal": focal,
                     "n": int(len(g))}
                for t in thresholds:
                    r[f"AA@{t:g}"] = angular_accuracy(g[col].to_numpy(float), float(t))
                rows.append(r)
    return pd.DataFrame(rows)


def vp_aa_markdown(aa: pd.DataFrame, decimals: int = 2) -> str:
    """Markdown of :func:`vp_aa_table`: per dataset, one row per method, target and focal."""
    if not len(aa):
        return ""
    cols = [c for c in aa.columns if c.startswith("AA@")]
    lines = ["## Angular accuracy (AA@t, degrees)", "",
             "AA@t: area under the share of angle errors below x, for x from 0 to t degrees, "
             "divided by t (a missing VP counts 0). *dominant*: the image VP to the closest "
             "GT VP; *triplet*: every GT VP to the closest VP the method lists. *true*: the "
             "dataset's focal length and principal point (where it gives none: the nominal); "
             "*nominal*: f = (w + h) / 4 and the image centre.", ""]
    for dsn, g in aa.groupby("dataset", sort=False):
        lines += [f"### {dsn}", "",
                  "| method | target | focal | n | " + " | ".join(cols) + " |",
                  "|---|---|---|---:|" + "---:|" * len(cols)]
        for _, r in g.iterrows():
            lines.append(f"| {r['method']} | {r['target']} | {r['focal']} | {r['n']} | "
                         + " | ".join(f"{r[c]:.{decimals}f}" for c in cols) + " |")
        lines.append("")
    return "\n".join(lines)


def vp_success_table(frame: pd.DataFrame,
                     px_thresholds: Sequence[float] = EvaluationParams.vp_px_thresholds,
                     deg_thresholds: Sequence[float] = EvaluationParams.vp_deg_thresholds
                     ) -> pd.DataFrame:
    """Success rate (share of images with error <= threshold) per method.

    Returns
    -------
    DataFrame
        Long format ``dataset, method, kind ("point_px" | "angle_deg"), threshold,
        success_rate, n_images``.
    """
    rows = []
    for (dsn, method), g in frame.groupby(["dataset", "method"], sort=False):
        for kind, col, ths in (("point_px", "point_error_px", px_thresholds),
                               ("angle_deg", "angle_error_deg", deg_thresholds)):
            e = g[col].to_numpy(float)
            for t in ths:
                rows.append({"dataset": dsn, "method": method, "kind": kind,
                             "threshold": float(t),
                             "success_rate": float(np.mean(e <= t)) if len(e) else float("nan"),
                             "n_images": int(len(e))})
    return pd.DataFrame(rows)


def vp_significance(frame: pd.DataFrame) -> pd.DataFrame:
    """Paired Wilcoxon p-values (:func:`paired_test`: a missing VP counts as an
    error above every finite one) of the point and angle errors between method pairs."""
    rows = []
    for dsn, g in frame.groupby("dataset", sort=False):
        methods = list(dict.fromkeys(g["method"]))
        for col in ("point_error_px", "angle_error_deg"):
            for i, ma in enumerate(methods):
                for mb in methods[i + 1:]:
                    a, b = _paired(g, col, ma, mb)
                    rows.append({"dataset": dsn, "error": col, "method_a": ma,
                                 "method_b": mb, "n_pairs": int(len(a)),
                                 "median_a": float(np.median(a)) if len(a) else float("nan"),
                                 "median_b": float(np.median(b)) if len(b) else float("nan"),
                                 "p_value": paired_test(a, b) if len(a) else float("nan")})
    return pd.DataFrame(rows, columns=["dataset", "error", "method_a", "method_b",
                                       "n_pairs", "median_a", "median_b", "p_value"])


def vp_markdown(success: pd.DataFrame, decimals: int = 2,
                errors: pd.DataFrame | None = None) -> str:
    """Markdown: per dataset and error kind, methods x thresholds of success rate.

    With ``errors`` (:func:`vp_frame`), each dataset's first section opens with what its
    errors mean: how many images, how many GT VPs each (errors are to the closest one),
    which focal length the angle error used, and per method the median angle error and
    the number of images without a VP; a dataset whose point errors are all infinite
    (its GT VPs lie at infinity, e.g. rectified photos) gets a sentence saying so instead
    of a point-error table of zeros.
    """
    lines = []
    noted: set[str] = set()
    for (dsn, kind), g in success.groupby(["dataset", "kind"], sort=False):
        unit = "px" if kind == "point_px" else "°"
        p = g.pivot(index="method", columns="threshold", values="success_rate")
        p = p.reindex(list(dict.fromkeys(g["method"])))
        lines += [f"## {dsn} — {'point error' if kind == 'point_px' else 'angle error'}", ""]
        if errors is not None and dsn not in noted and len(errors):
            e = errors[errors["dataset"] == dsn]
            if len(e):
                noted.add(dsn)
                lines += [_vp_note(e), ""]
            if kind == "point_px" and len(e) and np.isinf(e["point_error_px"]).all():
                lines += ["Point errors are undefined here: the ground-truth VPs lie at "
                          "infinity (every point error is infinite). Angle errors below.", ""]
                continue
        head = ["method"] + [f"≤ {t:g} {unit}" for t in p.columns]
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "|".join(["---"] + ["---:"] * len(p.columns)) + "|")
        for m, r in p.iterrows():
            lines.append("| " + " | ".join([str(m)] + [f"{v:.{decimals}f}" for v in r]) + " |")
        lines.append("")
    return "\n".join(lines)


def _vp_note(e: pd.DataFrame) -> str:
    """One dataset's sentence for :func:`vp_markdown` (``e``: its rows of :func:`vp_frame`)."""
    per_image = e.drop_duplicates("image")
    n_img = len(per_image)
    k = per_image["n_gt_vps"]
    if k.min() == k.max():
        gts = f"{int(k.min())} GT VP{'s' if k.min() > 1 else ''} per image"
    else:
        gts = f"{int(k.min())}-{int(k.max())} GT VPs per image"
    closest = "; errors are to the closest GT VP" if k.max() > 1 else ""
    src = set(per_image["focal_source"])
    focal = ("the true focal length and principal point" if src == {"true"} else
             "f = (w + h) / 4 and the image centre (no focal length given)"
             if src == {"assumed"} else "the true focal length where given, else "
             "f = (w + h) / 4 and the image centre")
    per_m = []
    for m, gm in e.groupby("method", sort=False):
        med = float(np.median(gm["angle_error_deg"]))
        per_m.append(f"{m} {med:.2f}° ({int(gm['vp_missing'].sum())} without a VP)")
    return (f"{n_img} images, {gts}{closest}. Angle errors with {focal}; a missing VP "
            f"fails every threshold. Median angle error: {', '.join(per_m)}.")


def paired_test(errors_a: Sequence[float], errors_b: Sequence[float]) -> float:
    """Two-sided Wilcoxon signed-rank p-value between two methods' per-image VP errors.

    Pairs where either error is NaN are left out; infinite errors (a missing VP) are
    replaced by a value above every finite error (the test uses ranks only), then the
    pairs go to :func:`rescu.evaluation.core.paired_wilcoxon`. Returns 1.0 when all the
    paired differences are zero or no pair remains.

    Parameters
    ----------
    errors_a, errors_b : (n,) float
        The two methods' errors on the same images (pixels or degrees).
    """
    a = np.asarray(errors_a, float).reshape(-1)
    b = np.asarray(errors_b, float).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"errors_a and errors_b must have the same length, "
                         f"got {a.shape} and {b.shape}")
    ok = ~(np.isnan(a) | np.isnan(b))
    a, b = a[ok], b[ok]
    fin = np.concatenate([a[np.isfinite(a)], b[np.isfinite(b)]])
    big = (float(np.abs(fin).max()) if len(fin) else 0.0) * 2 + 1.0
    a = np.where(np.isinf(a), np.sign(a) * big, a)
    b = np.where(np.isinf(b), np.sign(b) * big, b)
    p, n = paired_wilcoxon(a, b)
    return p if n and np.isfinite(p) else 1.0
