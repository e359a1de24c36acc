"""Pieces of the HTML pages the package writes: the gallery of ``rescu discover``
(:mod:`rescu.gallery`) and the report of a run (:mod:`rescu.evaluation.report`)."""

from __future__ import annotations

import base64
import html
from pathlib import Path


def img_tag(path: str | Path, width: int | None = None, height: int | None = None,
            alt: str | None = None) -> str:
    """An <img> with the picture embedded as a JPEG at twice the shown size (sharp on
    high-density screens, small enough to keep the report portable), shown ``width``
    wide or ``height`` high; the tag states both sizes, so the layout does not wait for
    the picture.

    Parameters
    ----------
    path : str or Path
        A picture OpenCV reads.
    width, height : int, optional
        Shown size in CSS pixels; ``height`` wins over ``width``; neither: the
        picture's own size.
    alt : str, optional
        Alternative text (default: the file name).

    Returns
    -------
    str
        The ``<img>`` tag, or a ``<p>`` saying the picture is unreadable.

    >>> img_tag("no/such/picture.png")
    '<p><em>(unreadable picture picture.png)</em></p>'
    """
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    name = html.escape(alt or Path(path).name)
    if img is None:
        return f"<p><em>(unreadable picture {name})</em></p>"
    h0, w0 = img.shape[:2]
    if height:
        w, h = max(1, round(w0 * height / h0)), height
    elif width:
        w, h = width, max(1, round(h0 * width / w0))
    else:
        w, h = w0, h0
    if w0 > 2 * w:
        img = cv2.resize(img, (2 * w, max(1, round(h0 * 2 * w / w0))),
                         interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    data = base64.b64encode(buf.tobytes()).decode("ascii")
    return f'<img src="data:image/jpeg;base64,{data}" width="{w}" height="{h}" alt="{name}">'
