"""Pictures of what was found: the instances of each RP in their own colour, labels that
neither overlap nor leave the picture, a legend with each RP's count and confidence,
optionally the vanishing points (thin lines), and the caption.

:func:`draw_overlay` returns the picture and the rectangles of the labels it placed (for
tests and checks); :func:`overlay` the picture only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .names import DRAW_MODES, OVERLAY_MODES  # noqa: F401  (OVERLAY_MODES: re-exported)
from .types import ImageResult

# Distinct colours (RGB) for up to 10 patterns, then they repeat.
PALETTE = [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 190), (0, 128, 128)]


MIN_BOX_PX = 8
"""A box smaller than this (picture pixels) is drawn at this size around its centre."""


@dataclass(frozen=True)
class Label:
    """A label drawn on the picture: its rectangle (picture pixels, ``x1``/``y1``
    exclusive) and text."""

    x0: int
    y0: int
    x1: int
    y1: int
    text: str

    def overlaps(self, other: "Label | tuple[float, float, float, float]") -> bool:
        """Whether the two rectangles share any pixel."""
        o = (other.x0, other.y0, other.x1, other.y1) if isinstance(other, Label) else other
        return self.x0 < o[2] and o[0] < self.x1 and self.y0 < o[3] and o[1] < self.y1


def _wrap(text: str, width: int) -> list[str]:
    words, lines, cur = text.split(), [], ""
    for w in words:
        if len(cur) + len(w) + 1 > width and cur:
            lines.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    if cur:
        lines.append(cur)
    return lines


class _Placer:
    """Greedy label placement: the first candidate position next to an anchor box that
    lies inside the picture and overlaps no label placed before (nor, when possible, an
    instance box); else the free position nearest to the anchor on a coarse grid."""

    def __init__(self, size: tuple[int, int], obstacles: Sequence[tuple[float, ...]]):
        self.w, self.h = size
        self.obstacles = list(obstacles)
        self.placed: list[Label] = []

    def _free(self, lab: Label, boxes: bool) -> bool:
        if lab.x0 < 0 or lab.y0 < 0 or lab.x1 > self.w or lab.y1 > self.h:
            return False
        if any(lab.overlaps(p) for p in self.placed):
            return False
        return not boxes or not any(lab.overlaps(o) for o in self.obstacles)

    def place(self, tw: int, th: int, anchor: tuple[float, float, float, float],
              text: str) -> Label | None:
        if tw > self.w or th > self.h:
            return None
        x0, y0, x1, y1 = (round(v) for v in anchor)
        cands = [(x0, y0 - th - 1), (x0, y1 + 1), (x1 - tw, y0 - th - 1), (x1 - tw, y1 + 1),
                 (x1 + 1, y0), (x0 - tw - 1, y0), (x0, y0)]
        cands = [(min(max(cx, 0), self.w - tw), min(max(cy, 0), self.h - th))
                 for cx, cy in cands]
        for boxes in (True, False):
            for cx, cy in cands:
                lab = Label(cx, cy, cx + tw, cy + th, text)
                if self._free(lab, boxes):
                    self.placed.append(lab)
                    return lab
        step = max(4, th // 2)
        grid = [(gx, gy) for gy in range(0, self.h - th + 1, step)
                for gx in range(0, self.w - tw + 1, step)]
        grid.sort(key=lambda p: (p[0] - x0) ** 2 + (p[1] - y0) ** 2)
        for gx, gy in grid:
            lab = Label(gx, gy, gx + tw, gy + th, text)
            if self._free(lab, False):
                self.placed.append(lab)
                return lab
        return None


def _draw_label(img: np.ndarray, lab: Label, colour: tuple[int, int, int], fs: float,
                pad: int) -> None:
    """A filled rectangle in ``colour`` (or white for light colours: dark text) with the
    label's text, in place."""
    import cv2

    light = sum(colour) > 500
    bg = (255, 255, 255) if light else colour
    fg = (0, 0, 0) if light or sum(colour) > 380 else (255, 255, 255)
    cv2.rectangle(img, (lab.x0, lab.y0), (lab.x1 - 1, lab.y1 - 1), bg, -1)
    cv2.rectangle(img, (lab.x0, lab.y0), (lab.x1 - 1, lab.y1 - 1), (0, 0, 0), 1)
    cv2.putText(img, lab.text, (lab.x0 + pad, lab.y1 - pad - 1), cv2.FONT_HERSHEY_SIMPLEX,
                fs, fg, 1, cv2.LINE_AA)


def _text_size(text: str, fs: float, pad: int) -> tuple[int, int]:
    import cv2

    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)
    return tw + 2 * pad, th + base + 2 * pad


def _box(inst_bbox: Sequence[float], s: float) -> tuple[float, float, float, float]:
    """The instance box in the picture (x0, y0, x1, y1), at least :data:`MIN_BOX_PX`."""
    x, y, bw, bh = (float(v) * s for v in inst_bbox)
    cx, cy = x + bw / 2, y + bh / 2
    bw, bh = max(bw, MIN_BOX_PX), max(bh, MIN_BOX_PX)
    return cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2


def legend_entries(result: ImageResult, mode: str = "boxes"
                   ) -> list[tuple[tuple[int, int, int], str]]:
    """``(colour, text)`` per RP: ``"RP0: 12 instances, confidence 0.83, translation
    symmetry, VP outside the image"`` (``score`` when it has no confidence); in
    ``full`` mode also one per image VP drawn (:func:`vp_legend_text`), white as its
    mark."""
    from .captions.caption import pattern_confidence

    out = []
    if mode == "full":
        for k, v in enumerate(result.extra.get("vanishing_points") or []):
            text = vp_legend_text(k, v)
            if text:
                out.append(((255, 255, 255), text))
    for p in result.patterns:
        kind, v = pattern_confidence(p)
        text = f"RP{p.id}: {p.count} instance{'s' if p.count != 1 else ''}, {kind} {v:.2f}"
        if p.extra.get("source") == "prompt":
            k = int(p.extra.get("examples", 1))
            text = (f"RP{p.id}: {p.count} instance{'s' if p.count != 1 else ''} like the "
                    f"{k} example box{'es' if k != 1 else ''} (white frame{'s' if k != 1 else ''}),"
                    f" least similarity {p.extra.get('threshold', 0):.2f}")
        if p.translation_symmetry is not None and p.translation_symmetry.detected:
            text += ", translation symmetry"
        if p.vanishing_point is not None:
            text += (", VP " + ("inside" if p.vanishing_point.inside_image else "outside")
                     + " the image")
        out.append((PALETTE[p.id % len(PALETTE)], text))
    n_vp = sum(1 for c, _ in out if c == (255, 255, 255))
    return out[n_vp:] + out[:n_vp]  # the RPs first, then the VPs


def vp_legend_text(k: int, v: dict) -> str | None:
    """What the mark ``VP<k+1>`` of an image VP stands for and what supports it, e.g.
    ``"VP1: vanishing point of 64 lines and 3 RP rows, outside the image (arrow towards
    it)"``; None for an entry without a usable point.

    >>> vp_legend_text(0, {"homogeneous": [1, 2, 0], "cues": {"lines": 64, "rp_rows": 0}})
    'VP1: vanishing point of 64 lines, at infinity (arrow along its direction)'
    """
    try:
        hx, hy, hw = (float(c) for c in v["homogeneous"])
    except (KeyError, TypeError, ValueError):
        return None
    cues = v.get("cues") or {}
    n_lines = int(cues.get("lines", v.get("support", 0)) or 0)
    n_rows = int(cues.get("rp_rows", 0) or 0)
    what = [f"{n_lines} line{'s' if n_lines != 1 else ''}"] if n_lines else []
    if n_rows:
        what.append(f"{n_rows} RP row{'s' if n_rows != 1 else ''}")
    where = ("at infinity (arrow along its direction)" if abs(hw) <= 1e-12 else
             "inside the image (ring)" if v.get("inside_image") else
             "outside the image (arrow towards it)")
    return (f"VP{k + 1}: vanishing point of {' and '.join(what) or 'its lines'}, {where}")


def draw_overlay(rgb: np.ndarray, scale_factor: float, result: ImageResult,
                 picture_max_side: int = 1024, mode: str = "full"
                 ) -> tuple[np.ndarray, list[Label]]:
    """Draw ``result`` on the processed image.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Processed image (original * ``scale_factor``).
    scale_factor : float
        processed = original * scale_factor; result boxes are in original pixels.
    result : ImageResult
    picture_max_side : int
        The picture is resized so that its longer side is at most this, pixels.
    mode : str
        ``"boxes"`` or ``"full"`` (:data:`OVERLAY_MODES`; ``"none"`` is the callers').

    Returns
    -------
    picture : (H', W', 3) uint8
        The picture (longer side <= ``picture_max_side``) with, below it, a white band
        holding the legend (one line per RP: colour, count, confidence or score, TS, VP)
        and the caption. Every instance box has a black edge under its colour and is at
        least :data:`MIN_BOX_PX` wide (stage-I boxes and the user's example boxes thicker
        than stage-II / completed ones, the example boxes inside a white frame); each RP gets a label ``RP<id>: <count>`` with a filled background next to
        one of its boxes. In ``full`` mode an RP's VP is drawn as one thin line per row
        (from the row's first instance towards the VP) or, when the VP is far, one thin
        arrow from the RP's centre; the image's VPs (``extra["vanishing_points"]``) as
        white rings (inside) or arrows from the centre (outside), labelled VP1...
    labels : list of Label
        The labels placed on the picture (not the band): inside the picture, pairwise
        non-overlapping. An RP whose label finds no free place gets none (the legend
        still lists it).
    """
    import cv2

    if mode not in DRAW_MODES:
        raise ValueError(f"mode must be one of {DRAW_MODES}, got {mode!r}")
    img = np.ascontiguousarray(rgb.copy())
    h, w = img.shape[:2]
    s = float(scale_factor)
    fit = min(1.0, picture_max_side / max(h, w))
    if fit < 1.0:
        img = cv2.resize(img, (round(w * fit), round(h * fit)), interpolation=cv2.INTER_AREA)
        s *= fit
        h, w = img.shape[:2]
    thick = max(1, round(max(h, w) / 500))
    fs, pad = 0.35 + 0.1 * thick, 2 + thick
    boxes = {p.id: [_box(i.bbox, s) for i in p.instances] for p in result.patterns}
    if mode == "full":
        for p in result.patterns:
            _draw_pattern_vp(img, p, boxes[p.id], s)
    for p in result.patterns:
        col = PALETTE[p.id % len(PALETTE)]
        for inst, (x0, y0, x1, y1) in zip(p.instances, boxes[p.id]):
            t = thick + 1 if inst.source in ("stage1", "example") else thick
            a, b = (round(x0), round(y0)), (round(x1), round(y1))
            if inst.source == "example":  # the user's box: a white frame around it
                e = t + 2
                cv2.rectangle(img, (a[0] - e, a[1] - e), (b[0] + e, b[1] + e),
                              (255, 255, 255), t + 2)
            cv2.rectangle(img, a, b, (0, 0, 0), t + 2)
            cv2.rectangle(img, a, b, col, t)
    placer = _Placer((w, h), [b for bs in boxes.values() for b in bs])
    if mode == "full":
        _draw_image_vps(img, result, s, thick, placer, fs, pad)
    for p in sorted(result.patterns, key=lambda q: -q.count):
        if not boxes[p.id]:
            continue
        text = f"RP{p.id}: {p.count}"
        tw, th = _text_size(text, fs, pad)
        anchor = min(boxes[p.id], key=lambda b: (b[1], b[0]))  # the top-most box
        lab = placer.place(tw, th, anchor, text)
        if lab is not None:
            _draw_label(img, lab, PALETTE[p.id % len(PALETTE)], fs, pad)
    return np.vstack([img, _band(result, w, mode)]), list(placer.placed)


def overlay(rgb: np.ndarray, scale_factor: float, result: ImageResult,
            picture_max_side: int = 1024, mode: str = "full") -> np.ndarray:
    """The picture of :func:`draw_overlay` alone."""
    return draw_overlay(rgb, scale_factor, result, picture_max_side, mode)[0]


def _band(result: ImageResult, w: int, mode: str = "boxes") -> np.ndarray:
    """The white band below the picture: the legend (``mode`` ``full``: the image's VPs
    too), then the caption (or the failure)."""
    import cv2

    from .captions.caption import NO_PATTERN

    text = ""
    if result.caption:
        text = result.caption.get("enhanced") or result.caption.get("base") or ""
    failure = result.extra.get("failure")
    if failure and failure.get("degraded_to"):  # a step failed; the previous result kept
        text = (f"{text} [{failure.get('stage')} failed; {failure.get('degraded_to')}'s "
                f"result shown]").strip()
    elif failure:
        text = f"FAILED in {failure.get('stage')}: {failure.get('message')}"
    if not result.patterns and not failure:
        text = text or NO_PATTERN
    fs = 0.5 if w >= 360 else 0.4
    lh = 18 if w >= 360 else 15
    chars = max(20, int(w / (18.5 * fs)))
    legend = legend_entries(result, mode)
    lines = [(col if k == 0 else (), ln) for col, t in legend
             for k, ln in enumerate(_wrap(t, chars - 3))]
    cap = [(None, ln) for ln in _wrap(text, chars)] or [(None, "")]
    band = np.full((lh * (len(lines) + len(cap)) + 12, w, 3), 255, np.uint8)
    y = 4
    for col, ln in lines + cap:
        x = 6 + lh if col is not None else 6  # (): a legend entry's next line
        if col:
            cv2.rectangle(band, (6, y + 3), (6 + lh - 6, y + lh - 3), col, -1)
            cv2.rectangle(band, (6, y + 3), (6 + lh - 6, y + lh - 3), (0, 0, 0), 1)
        cv2.putText(band, ln, (x, y + lh - 5), cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
        y += lh
    return band


def _towards(vp: tuple[float, float, float], s: float, origin: Sequence[float]) -> np.ndarray:
    """Unit direction (2,) in the picture from ``origin`` (picture pixels) towards the
    homogeneous VP ``vp`` (original pixels; the picture is original * ``s``); a VP at
    infinity (``w`` = 0) gives its own direction. Both the RPs' arrows and the image's VP
    arrows point along it."""
    hx, hy, hw = vp
    d = (np.array([hx / hw * s - origin[0], hy / hw * s - origin[1]]) if abs(hw) > 1e-12
         else np.array([hx, hy]))
    return d / (np.linalg.norm(d) + 1e-12)


def _draw_pattern_vp(img: np.ndarray, p: object, boxes: list[tuple[float, ...]],
                     s: float) -> None:
    """One thin line per row of ``p`` towards its VP (from the row's first instance), or,
    when the VP is far from the picture, one thin arrow from the RP's centre; in place."""
    import cv2

    vp = getattr(p, "vanishing_point", None)
    if vp is None or not boxes:
        return
    h, w = img.shape[:2]
    col = PALETTE[p.id % len(PALETTE)]  # type: ignore[attr-defined]
    hx, hy, hw = (float(v) for v in vp.homogeneous)
    centres = np.array([((b[0] + b[2]) / 2, (b[1] + b[3]) / 2) for b in boxes])
    near = abs(hw) > 1e-12 and -w < hx / hw * s < 2 * w and -h < hy / hw * s < 2 * h
    if near:
        t = (round(hx / hw * s), round(hy / hw * s))
        rows = [r for r in (p.extra.get("rows") or []) if r]  # type: ignore[attr-defined]
        starts = [min(r, key=lambda i: -np.hypot(*(centres[int(i)] - t)))
                  for r in rows if all(0 <= int(i) < len(centres) for i in r)] or [0]
        for i in starts:
            c = centres[int(i)]
            cv2.line(img, (round(c[0]), round(c[1])), t, col, 1, cv2.LINE_AA)
        if 0 <= t[0] < w and 0 <= t[1] < h:
            cv2.drawMarker(img, t, col, cv2.MARKER_TILTED_CROSS, 14, 2)
    else:
        c = centres.mean(axis=0)
        d = _towards((hx, hy, hw), s, c) * 0.12 * max(h, w)
        cv2.arrowedLine(img, (round(c[0]), round(c[1])), (round(c[0] + d[0]),
                                                          round(c[1] + d[1])),
                        col, 1, cv2.LINE_AA, tipLength=0.2)


def _draw_image_vps(img: np.ndarray, result: ImageResult, s: float, thick: int,
                    placer: _Placer, fs: float, pad: int) -> None:
    """Draw the image's VPs (``result.extra["vanishing_points"]``, original pixels) on
    ``img`` (original * ``s``) in place: a white ring with a black edge where the VP lies
    in the picture, else a thin white arrow from the picture's centre towards it (a VP at
    infinity: along its direction); the label ``VP<k>`` goes through ``placer``."""
    import cv2

    h, w = img.shape[:2]
    centre = np.array([w / 2.0, h / 2.0])
    for k, v in enumerate(result.extra.get("vanishing_points") or []):
        try:
            hx, hy, hw = (float(c) for c in v["homogeneous"])
        except (KeyError, TypeError, ValueError):
            continue
        if abs(hw) > 1e-12 and 0 <= hx / hw * s < w and 0 <= hy / hw * s < h:
            p = (round(hx / hw * s), round(hy / hw * s))
            r = 4 * thick + 4
            cv2.circle(img, p, r, (0, 0, 0), thick + 2, cv2.LINE_AA)
            cv2.circle(img, p, r, (255, 255, 255), thick, cv2.LINE_AA)
            anchor = (p[0] - r, p[1] - r, p[0] + r, p[1] + r)
        else:
            d = _towards((hx, hy, hw), s, centre) * 0.25 * min(h, w)
            a, b = tuple(round(c) for c in centre), tuple(round(c) for c in centre + d)
            cv2.arrowedLine(img, a, b, (0, 0, 0), thick + 3, cv2.LINE_AA, tipLength=0.12)
            cv2.arrowedLine(img, a, b, (255, 255, 255), thick + 1, cv2.LINE_AA,
                            tipLength=0.12)
            anchor = (b[0] - 3, b[1] - 3, b[0] + 3, b[1] + 3)
        text = f"VP{k + 1}"
        tw, th = _text_size(text, fs, pad)
        lab = placer.place(tw, th, anchor, text)
        if lab is not None:
            _draw_label(img, lab, (255, 255, 255), fs, pad)
