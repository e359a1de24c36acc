"""Failed images of a run: the ``*.failed.json`` records as a table and as Markdown."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from ..io import InputError
from .core import frame_markdown


def collect_failures(folder: str | Path, dataset: str | None = None) -> pd.DataFrame:
    """Rows ``dataset, image, stage, message, file`` from ``*.failed.json`` files.

    Searched recursively under ``folder``; ``dataset`` is the record's own ``dataset``
    field, else the argument, else the name of the file's parent folder. An unreadable
    record becomes a row with stage ``"unreadable"``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: failures folder not found")
    rows = []
    for p in sorted(folder.rglob("*.failed.json")):
        try:
            d = json.loads(p.read_text())
            if not isinstance(d, dict):
                raise ValueError("not a JSON object")
            rows.append({"dataset": str(d.get("dataset") or dataset or p.parent.name),
                         "image": str(d.get("image", p.name[:-len(".failed.json")])),
                         "stage": str(d.get("stage", "")),
                         "message": str(d.get("message", "")), "file": str(p)})
        except (ValueError, OSError) as e:
            rows.append({"dataset": dataset or p.parent.name,
                         "image": p.name[:-len(".failed.json")], "stage": "unreadable",
                         "message": f"unreadable failure record ({e})", "file": str(p)})
    return pd.DataFrame(rows, columns=["dataset", "image", "stage", "message", "file"])


def failures_markdown(df: pd.DataFrame) -> str:
    """Markdown table of :func:`collect_failures` (messages on one line)."""
    d = df.drop(columns=["file"], errors="ignore").copy()
    d["message"] = d["message"].str.replace(r"\s+", " ", regex=True).str.replace("|", "\\|")
    if d.empty:
        return "No failures.\n"
    return frame_markdown(d)
