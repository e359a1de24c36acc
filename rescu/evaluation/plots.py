"""PNG figures of the evaluation: metric-vs-h curves and VP success-rate curves.

matplotlib is imported where used (Agg backend); figures are written atomically with no
software metadata, so the same tables give the same bytes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from ..io import atomic_path
from .core import METRIC_LABELS
from .metrics import METRICS


def _savefig(fig: Any, path: str | Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, metadata={"Software": None})


def _finish_rate_figure(fig: Any, axes: Any, path: str | Path, title: str | None) -> None:
    """The common end of the curve plotters: every axis a rate in [0, 1] with a grid,
    the legend on the first, the title; saved as PNG to ``path`` and closed."""
    import matplotlib.pyplot as plt

    for ax in axes[0]:
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _savefig(fig, path)
    plt.close(fig)


def plot_metric_curves(curves: pd.DataFrame, path: str | Path,
                       title: str | None = None) -> None:
    """PNG with one panel per metric: mean vs h, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(4 * len(METRICS), 3.4),
                             squeeze=False)
    for ax, met in zip(axes[0], METRICS):
        g = curves[curves["metric"] == met]
        for method, gm in g.groupby("method", sort=False):
            gm = gm.sort_values("h")
            ax.plot(gm["h"], gm["mean"], marker="o", ms=3, label=str(method))
        ax.set_title(METRIC_LABELS.get(met, met))
        ax.set_xlabel("IOD threshold h")
    _finish_rate_figure(fig, axes, path, title)


def plot_vp_curves(success: pd.DataFrame, path: str | Path,
                   title: str | None = None) -> None:
    """PNG: success rate vs threshold (point and angle error), one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), squeeze=False)
    for ax, (kind, xl) in zip(axes[0], (("point_px", "point error threshold (px)"),
                                        ("angle_deg", "angle error threshold (°)"))):
        g = success[success["kind"] == kind]
        for (dsn, method), gm in g.groupby(["dataset", "method"], sort=False):
            gm = gm.sort_values("threshold")
            ax.plot(gm["threshold"], gm["success_rate"], marker="o", ms=3,
                    label=f"{method}" if success["dataset"].nunique() == 1
                    else f"{dsn}: {method}")
        ax.set_xlabel(xl)
        ax.set_ylabel("success rate")
    _finish_rate_figure(fig, axes, path, title)
