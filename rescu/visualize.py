"""Pictures of what was found: instances per RP in their own colour, each RP's vanishing
point with its supporting lines, the image's vanishing points (the joint estimator's
``vanishing_points``: VP1 the dominant one) and the caption."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .types import ImageResult

# Distinct colours (RGB) for up to 10 patterns, then they repeat.
PALETTE = [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 190), (0, 128, 128)]


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


def overlay(rgb: np.ndarray, scale_factor: float, result: ImageResult,
            picture_max_side: int = 1024) -> np.ndarray:
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

    Returns
    -------
    (H', W' + caption band, 3) uint8
        Stage-I instances drawn solid, stage-II dashed-looking (thinner) boxes; lines from
        each instance centre towards the pattern's VP (or an arrow when the VP is far
        away); the image's VPs (``result.extra["vanishing_points"]``, dominant first) as
        white rings labelled VP1, VP2, VP3, or, when outside the picture, white arrows
        from its centre towards them (:func:`_draw_image_vps`); the caption in a band
        below.
    """
    import cv2

    img = np.ascontiguousarray(rgb.copy())
    h, w = img.shape[:2]
    s = float(scale_factor)
    fit = min(1.0, picture_max_side / max(h, w))
    if fit < 1.0:
        img = cv2.resize(img, (round(w * fit), round(h * fit)), interpolation=cv2.INTER_AREA)
        s *= fit
        h, w = img.shape[:2]
    thick = max(1, round(max(h, w) / 400))
    for p in result.patterns:
        col = PALETTE[p.id % len(PALETTE)]
        centres = []
        for inst in p.instances:
            x, y, bw, bh = (v * s for v in inst.bbox)
            t = thick + 1 if inst.source == "stage1" else thick
            cv2.rectangle(img, (round(x), round(y)), (round(x + bw), round(y + bh)), col, t)
            centres.append((x + bw / 2, y + bh / 2))
        vp = p.vanishing_point
        if vp is not None and centres:
            hx, hy, hw = (float(v) for v in vp.homogeneous)
            if abs(hw) > 1e-12:
                tx, ty = hx / hw * s, hy / hw * s
                far = not (-w < tx < 2 * w and -h < ty < 2 * h)
            else:
                far, tx, ty = True, hx, hy
            for cx, cy in centres:
                if far:  # direction only: a short arrow towards the VP
                    d = _towards((hx, hy, hw), s, (cx, cy)) * 0.08 * max(h, w)
                    cv2.arrowedLine(img, (round(cx), round(cy)),
                                    (round(cx + d[0]), round(cy + d[1])), col, thick,
                                    tipLength=0.3)
                else:
                    cv2.line(img, (round(cx), round(cy)), (round(tx), round(ty)), col,
                             max(1, thick - 1), cv2.LINE_AA)
            if not far and 0 <= tx < w and 0 <= ty < h:
                cv2.drawMarker(img, (round(tx), round(ty)), col, cv2.MARKER_TILTED_CROSS,
                               6 * thick + 10, thick + 1)
        if p.instances:
            x, y = (v * s for v in p.instances[0].bbox[:2])
            label = f"RP{p.id}: {p.count}"
            if p.translation_symmetry is not None and p.translation_symmetry.detected:
                label += " TS"
            cv2.putText(img, label, (round(x), max(12, round(y) - 4)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.4 + 0.1 * thick, col, thick, cv2.LINE_AA)
    _draw_image_vps(img, result, s, thick)
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
        text = text or "No recurring pattern found."
    chars = max(20, w // 9)
    lines = _wrap(text, chars) or [""]
    band = np.full((18 * len(lines) + 10, w, 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(band, line, (6, 20 + 18 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                    cv2.LINE_AA)
    return np.vstack([img, band])


def _towards(vp: tuple[float, float, float], s: float, origin: Sequence[float]) -> np.ndarray:
    """Unit direction (2,) in the picture from ``origin`` (picture pixels) towards the
    homogeneous VP ``vp`` (original pixels; the picture is original * ``s``); a VP at
    infinity (``w`` = 0) gives its own direction. Both the RPs' arrows and the image's VP
    arrows point along it."""
    hx, hy, hw = vp
    d = (np.array([hx / hw * s - origin[0], hy / hw * s - origin[1]]) if abs(hw) > 1e-12
         else np.array([hx, hy]))
    return d / (np.linalg.norm(d) + 1e-12)


def _draw_image_vps(img: np.ndarray, result: ImageResult, s: float, thick: int) -> None:
    """Draw the image's VPs (``result.extra["vanishing_points"]``, original pixels) on
    ``img`` (original * ``s``) in place: a white ring with a black edge and the label
    ``VP<k>`` where the VP lies in the picture, else a white arrow from the picture's
    centre towards it (a VP at infinity: along its direction) with the label at its tip."""
    import cv2

    h, w = img.shape[:2]
    centre = np.array([w / 2.0, h / 2.0])
    for k, v in enumerate(result.extra.get("vanishing_points") or []):
        try:
            hx, hy, hw = (float(c) for c in v["homogeneous"])
        except (KeyError, TypeError, ValueError):
            continue
        label = f"VP{k + 1}"
        font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.45 + 0.1 * thick
        if abs(hw) > 1e-12 and 0 <= hx / hw * s < w and 0 <= hy / hw * s < h:
            p = (round(hx / hw * s), round(hy / hw * s))
            r = 5 * thick + 6
            cv2.circle(img, p, r, (0, 0, 0), thick + 3, cv2.LINE_AA)
            cv2.circle(img, p, r, (255, 255, 255), thick + 1, cv2.LINE_AA)
            tip = (p[0] + r + 2, p[1] - r)
        else:
            d = _towards((hx, hy, hw), s, centre) * 0.3 * min(h, w)
            a, b = tuple(round(c) for c in centre), tuple(round(c) for c in centre + d)
            cv2.arrowedLine(img, a, b, (0, 0, 0), thick + 3, cv2.LINE_AA, tipLength=0.15)
            cv2.arrowedLine(img, a, b, (255, 255, 255), thick + 1, cv2.LINE_AA,
                            tipLength=0.15)
            tip = (b[0] + 4, b[1] + 4)
        cv2.putText(img, label, tip, font, fs, (0, 0, 0), thick + 2, cv2.LINE_AA)
        cv2.putText(img, label, tip, font, fs, (255, 255, 255), thick, cv2.LINE_AA)
