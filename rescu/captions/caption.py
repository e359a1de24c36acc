"""Captions enhanced with what the recurring patterns tell about the scene.

RESCU turns a generic caption such as "A group of babies sitting on the couch." into
"Six similar babies sitting on the couch." and, when detected, adds the 3D findings:
"The bottles have a potential translation symmetry in 3D and form a vanishing point
outside of the image."

Two parts:

* A *captioner* writes the base caption (protocol :class:`Captioner`):
  :class:`TemplateCaptioner` (offline default, generic nouns since RPs carry no class
  label), :class:`TransformersCaptioner` (a ``transformers`` image-to-text model such as
  BLIP or GIT, only when the package and the model are available) and
  :class:`CsvCaptioner` (captions written beforehand, ``image,caption`` columns).
  :func:`make_captioner` builds the configured one and falls back to the template
  captioner, with a logged message, when it cannot be loaded.
* The *enhancement grammar* :func:`enhance_caption` rewrites the base caption with the
  count of the dominant recurring pattern (RP) and appends the translation-symmetry and
  vanishing-point sentence.

Enhancement grammar (:mod:`rescu.captions.grammar`: a light part-of-speech heuristic,
small word lists of determiners, prepositions, conjunctions and verbs mark noun-phrase
boundaries; no NLP package is used):

1. A collective phrase "<det> <adjectives> <collective noun> of <noun phrase>" (group,
   herd, row, set ...) is replaced by "<count word> similar": "A large herd of llamas"
   -> "Six similar llamas".
2. Otherwise, with an "of", the count goes after the first "of" and before the noun
   phrase it governs (indefinite article after "of" dropped, the rest kept): "An old
   picture of stone statues" -> "An old picture of six similar stone statues".
3. Otherwise the count goes before the subject noun phrase, whose indefinite article or
   quantifier is dropped and whose head noun is made plural (with "is"/"was"/"has" and
   a few common verbs agreeing): "A bottle is on a shelf" -> "Eight similar bottles are
   on a shelf".

The head noun of a noun phrase is its last noun: adjectives, colour and nationality words
and -ing/-ed participles in front of it are modifiers, never pluralised ("A row of red
sleeping bags" -> "Four similar red sleeping bags"); an -ing/-ed word after a noun starts
a participle clause ("A dog eating food" -> "Two similar dogs eating food").

Count words are "two" ... "twenty", then digits; a count of one or no RP leaves the
caption unchanged. Several RPs: with a grounding function ``ground(rgb, noun) -> bbox``
each noun phrase head is grounded to a box and gets the RP whose total instance area
lies at least ``grounding_coverage`` (0.90) inside that box; without one (the offline
default) only the dominant RP is used, on the noun phrase chosen by rules 1-3.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ..io import InputError
from ..params import checked_mapping, config_section, schema_enum
from ..types import BBox, ImageResult, Pattern
from .grammar import (NounPhrase, capitalise, choose_phrase, noun_phrases, rewrite_phrase,
                      tokenize)

logger = logging.getLogger(__name__)

Grounder = Callable[[np.ndarray, str], "BBox | None"]
"""``ground(rgb, noun) -> (x, y, w, h)`` box in original pixels, or None if not found;
``noun`` is a lower-case noun-phrase head as it appears in the caption."""


class CaptionerUnavailable(RuntimeError):
    """The configured captioner cannot be used here (message says what is missing)."""


class CaptionMissing(KeyError):
    """A CSV captioner has no caption for the image."""


# ----------------------------------------------------------------------------- params
CAPTIONERS: tuple[str, ...] = schema_enum("caption", "captioner")
"""The captioners ``caption.captioner`` may name."""


@dataclass(frozen=True)
@config_section("caption")
class CaptionParams:
    """Parameters of captioning.

    Attributes
    ----------
    captioner : str
        One of :data:`CAPTIONERS`: ``"template"`` (offline), ``"transformers"``
        (image-to-text model) or ``"csv"``.
    model : str
        Local folder or hub name of the ``transformers`` image-to-text model.
    csv_path : str
        CSV file with columns ``image,caption`` (``image`` = file name or stem).
    grounding_model : str
        Local folder or hub name of a ``transformers`` zero-shot object detector used to
        ground nouns to boxes; empty = no grounding (dominant RP on the first noun).
    grounding_coverage : float
        Share of an RP's total instance area that must lie inside a noun's box, [0, 1].
    max_new_tokens : int
        Length limit of a generated caption, tokens.
    seed : int
        Seed of the caption generator (torch).
    """

    captioner: str
    model: str
    csv_path: str
    grounding_model: str
    grounding_coverage: float
    max_new_tokens: int
    seed: int

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "CaptionParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        d = checked_mapping(cls, d, "caption parameter")
        for k in ("csv_path", "grounding_model", "model"):
            if k in d and d[k] is None:
                d[k] = ""
        return cls(**d)


# ----------------------------------------------------------------------------- patterns
def dominant_pattern(result: ImageResult) -> Pattern | None:
    """The dominant RP: ``result.dominant_pattern`` (a pattern id, else an index), else
    the pattern with the most instances (ties: the first); None without patterns."""
    if not result.patterns:
        return None
    d = result.dominant_pattern
    if d is not None:
        for p in result.patterns:
            if p.id == d:
                return p
        if 0 <= int(d) < len(result.patterns):
            return result.patterns[int(d)]
    return max(result.patterns, key=lambda p: p.count)


def _area_inside(pattern: Pattern, box: Sequence[float]) -> float:
    """Share of the pattern's total instance area inside ``box`` ([x, y, w, h])."""
    bx, by, bw, bh = (float(v) for v in box)
    tot = inside = 0.0
    for inst in pattern.instances:
        x, y, w, h = inst.bbox
        a = max(w, 0.0) * max(h, 0.0)
        tot += a
        iw = max(0.0, min(x + w, bx + bw) - max(x, bx))
        ih = max(0.0, min(y + h, by + bh) - max(y, by))
        inside += iw * ih
    return inside / tot if tot > 0 else 0.0


NO_PATTERN = "No recurring pattern found."
"""Caption and summary line of an image without a recurring pattern (no RP with two or
more instances in ``patterns``; RPs set apart in ``candidate_patterns`` do not count)."""


NOTHING_LIKE_EXAMPLE = "Nothing else like the example box was found."
"""Caption of a "count these" image where nothing but the one example box was found (its
prompted pattern has one instance): no recurring pattern, said of what the user asked."""


def no_pattern_caption(result: ImageResult) -> str:
    """The caption of an image whose dominant RP has fewer than two instances:
    :data:`NOTHING_LIKE_EXAMPLE` when the user gave an example box (a "count these"
    pattern, ``extra["source"] == "prompt"``) and nothing else was found like it, else
    :data:`NO_PATTERN`.

    >>> from rescu.types import ImageResult, Instance, Pattern
    >>> ex = Pattern(id=0, score=1.0, instances=[Instance(bbox=(0, 0, 9, 9))],
    ...              extra={"source": "prompt"})
    >>> no_pattern_caption(ImageResult(image="a.jpg", width=20, height=20, method="rescu-ii",
    ...                                 patterns=[ex]))
    'Nothing else like the example box was found.'
    >>> no_pattern_caption(ImageResult(image="a.jpg", width=20, height=20, method="rescu-ii"))
    'No recurring pattern found.'
    """
    if any(p.extra.get("source") == "prompt" for p in result.patterns):
        return NOTHING_LIKE_EXAMPLE
    return NO_PATTERN


def pattern_confidence(pattern: Pattern) -> tuple[str, float]:
    """``("confidence", c)`` when discovery gave the RP a confidence in [0, 1]
    (``pattern.extra["confidence"]``), else ``("score", pattern.score)``."""
    c = pattern.extra.get("confidence") if isinstance(pattern.extra, dict) else None
    if isinstance(c, (int, float)) and np.isfinite(c):
        return "confidence", float(c)
    return "score", float(pattern.score)


@dataclass(frozen=True)
class SceneFacts:
    """What the caption and the summary line may say about an image: only what its
    result supports (after :func:`rescu.scene.claims.supported_claims`).

    Attributes
    ----------
    n_patterns : int
        RPs with at least two instances.
    count : int
        Instances of the dominant RP (0 without one).
    layout : str
        The dominant RP's measured layout (:func:`infer_layout`): ``"row"``,
        ``"column"``, ``"grid"`` or ``"group"``.
    vp : str or None
        ``"inside"`` / ``"outside"``: the dominant RP's own (supported) VP lies inside /
        outside the image; None: it has none.
    ts : bool
        The dominant RP passed the translation-symmetry test.
    """

    n_patterns: int
    count: int
    layout: str
    vp: str | None
    ts: bool


def scene_facts(result: ImageResult) -> SceneFacts:
    """The :class:`SceneFacts` of ``result``: the dominant RP's count, layout, own VP and
    translation symmetry (an image VP from lines alone is not a fact about the RP)."""
    dom = dominant_pattern(result)
    n = sum(1 for p in result.patterns if p.count >= 2)
    if dom is None or dom.count < 2:
        return SceneFacts(n, 0, "group", None, False)
    vp = dom.vanishing_point
    ts = dom.translation_symmetry is not None and dom.translation_symmetry.detected
    return SceneFacts(n, dom.count, infer_layout(dom),
                      None if vp is None else ("inside" if vp.inside_image else "outside"),
                      bool(ts))


def _scene_sentence(noun_plural: str, pattern: Pattern, result: ImageResult) -> str:
    facts = scene_facts(result)
    parts = []
    if facts.ts:
        parts.append("have a potential translation symmetry in 3D")
    if facts.vp is not None:
        parts.append("form a vanishing point " + ("inside the image" if facts.vp == "inside"
                                                   else "outside of the image"))
    if not parts:
        return ""
    return f"The {noun_plural} " + " and ".join(parts) + "."


def summary_line(result: ImageResult) -> str:
    """One line of what was found, stating the same facts as the caption
    (:func:`scene_facts`) plus each RP's count and confidence (or score), e.g.
    ``"2 RPs: 12 (confidence 0.83), 4 (confidence 0.41); grid; VP outside the image;
    translation symmetry"`` (a "count these" RP: ``"14 (like the example box)"``);
    :data:`NO_PATTERN` without an RP of two or more instances.
    A failure record is not handled here (the caller says it)."""
    facts = scene_facts(result)
    pats = [p for p in result.patterns if p.count >= 2]
    asked = [p for p in result.patterns if p.extra.get("source") == "prompt"]
    if asked and asked[0].count < 2:  # "count these" found nothing but the examples
        return f"{asked[0].count} instance: nothing else like the example box"
    if facts.count < 2 or not pats:
        return NO_PATTERN
    counts = []
    for p in pats:
        kind, v = pattern_confidence(p)
        if p.extra.get("source") == "prompt":
            k = int(p.extra.get("examples", 1))
            counts.append(f"{p.count} (like the example box{'es' if k != 1 else ''})")
        else:
            counts.append(f"{p.count} ({kind} {v:.2f})")
    parts = [f"{len(pats)} RP{'s' if len(pats) != 1 else ''}: " + ", ".join(counts)]
    if facts.layout in ("row", "column", "grid"):
        parts.append({"row": "in a row", "column": "in a column",
                      "grid": "grid"}[facts.layout])
    if facts.vp is not None:
        parts.append(f"VP {facts.vp} the image")
    if facts.ts:
        parts.append("translation symmetry")
    return "; ".join(parts)


def enhance_caption(base: str, result: ImageResult, grounding: Grounder | None = None,
                    rgb: np.ndarray | None = None, coverage: float = 0.90) -> str:
    """Rewrite ``base`` with the RP counts and append the 3D findings.

    Parameters
    ----------
    base : str
        The base caption (one or more sentences).
    result : ImageResult
        Patterns found in the image (instance boxes in original pixels).
    grounding : callable, optional
        ``ground(rgb, noun) -> [x, y, w, h] | None`` (original pixels). With it, every
        noun-phrase head is grounded and gets the RP with >= ``coverage`` of its total
        instance area inside the box (the largest such RP not yet used). Without it the
        dominant RP goes to one noun phrase only (module docstring, rules 1-3).
    rgb : (H, W, 3) uint8, optional
        The image, passed to ``grounding``.
    coverage : float
        Required share of instance area inside the grounded box, [0, 1].

    Returns
    -------
    str
        The enhanced caption; ``base`` unchanged when the dominant RP has fewer than two
        instances, there is no RP, or no noun phrase is found.
    """
    if not isinstance(base, str):
        raise TypeError(f"base must be a str, got {type(base).__name__}")
    dom = dominant_pattern(result)
    if dom is None or dom.count < 2:
        return base
    toks = tokenize(base)
    nps = noun_phrases(toks)
    if not nps:
        return base
    assignments: list[tuple[NounPhrase, Pattern]] = []
    if grounding is not None:
        used: set[int] = set()
        for p in nps:
            box = grounding(rgb if rgb is not None else np.zeros((0, 0, 3), np.uint8),
                            toks[p.head].low)
            if box is None:
                continue
            cands = [q for q in result.patterns if q.count >= 2 and id(q) not in used
                     and _area_inside(q, box) >= coverage]
            if not cands:
                continue
            best = sorted(cands, key=lambda q: (q is not dom, -q.count))[0]
            used.add(id(best))
            assignments.append((p, best))
    if not assignments:
        p = choose_phrase(toks, nps)
        if p is None:
            return base
        assignments = [(p, dom)]
    # rewrite from the last phrase to the first so that token indices stay valid
    nouns: dict[int, str] = {}
    for p, pat in sorted(assignments, key=lambda a: -a[0].start):
        toks, noun = rewrite_phrase(toks, p, pat.count)
        nouns[id(pat)] = noun
    text = "".join(t.text for t in toks)
    dom_noun = nouns.get(id(dom))
    if dom_noun is None:  # grounding gave the dominant RP no noun
        return text
    extra = _scene_sentence(dom_noun, dom, result)
    if extra:
        stripped = text.rstrip()
        sep = " " if stripped.endswith((".", "!", "?")) else ". "
        text = stripped + sep + extra
    return text


# ----------------------------------------------------------------------------- captioners
class Captioner(Protocol):
    """Writes a base caption for one image."""

    def caption(self, rgb: np.ndarray, result: ImageResult, image_name: str) -> str: ...


def _groups(v: np.ndarray, tol: float) -> np.ndarray:
    """Labels (K,) int of 1-D coordinates ``v`` (K,) split where consecutive sorted values
    are more than ``tol`` apart (same units)."""
    order = np.argsort(v)
    lab = np.empty(len(v), int)
    lab[order] = np.concatenate([[0], np.cumsum(np.diff(v[order]) > tol)])
    return lab


def infer_layout(pattern: Pattern, line_tolerance: float = 0.35,
                 min_fill: float = 0.6) -> str:
    """``"row"``, ``"column"``, ``"grid"`` or ``"group"``, measured from the instance
    centres.

    ``pattern.extra["layout"]`` wins when present. Centres lie on a line (``"row"`` when
    it is closer to horizontal, else ``"column"``) when their spread across the principal
    direction is below ``line_tolerance`` times the median instance side (pixels /
    pixels). ``"grid"`` only when rows *and* columns are measured: along the direction
    of the instances' nearest neighbours, the centres fall into at least two rows and
    two columns (coordinates split at gaps above half the median side), no cell holds
    two instances, and the instances fill at least ``min_fill`` of the cells. Anything
    else (scattered boxes) is a ``"group"``, which the captions give no layout words.
    """
    lay = pattern.extra.get("layout") if isinstance(pattern.extra, dict) else None
    if isinstance(lay, str) and lay:
        return lay
    if pattern.count < 3:
        return "group"
    b = np.array([i.bbox for i in pattern.instances], float)
    c = b[:, :2] + b[:, 2:] / 2.0
    side = max(float(np.median(np.minimum(b[:, 2], b[:, 3]))), 1e-9)
    cc = c - c.mean(axis=0)
    _, s, vt = np.linalg.svd(cc, full_matrices=False)
    spread = s[1] / np.sqrt(len(c)) if len(s) > 1 else 0.0  # std across the line
    if spread <= line_tolerance * side:
        d = vt[0]
        return "column" if abs(d[1]) > abs(d[0]) else "row"
    # the lattice direction: the folded (mod 180 degrees) angle to the nearest neighbours
    dist = np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c)) * 1e18
    nn = c[np.argmin(dist, axis=1)] - c
    ang = 2.0 * np.arctan2(nn[:, 1], nn[:, 0])
    a = 0.5 * np.arctan2(np.median(np.sin(ang)), np.median(np.cos(ang)))
    u = np.array([np.cos(a), np.sin(a)])
    along, across = c @ u, c @ np.array([-u[1], u[0]])
    rows, cols = _groups(across, 0.5 * side), _groups(along, 0.5 * side)
    n_rows = int(sum(np.bincount(rows) >= 2))
    n_cols = int(sum(np.bincount(cols) >= 2))
    cells = set(zip(rows.tolist(), cols.tolist()))
    fill = len(c) / float(len(set(rows.tolist())) * len(set(cols.tolist())))
    if n_rows >= 2 and n_cols >= 2 and len(cells) == len(c) and fill >= min_fill:
        return "grid"
    return "group"


@dataclass
class TemplateCaptioner:
    """Offline captioner: a plain sentence from what was found (generic nouns).

    The base caption keeps a collective noun so that :func:`enhance_caption` turns it
    into a count: "A group of similar objects in a row." -> "Five similar objects in a
    row."
    """

    noun: str = "objects"

    def caption(self, rgb: np.ndarray, result: ImageResult, image_name: str) -> str:
        facts = scene_facts(result)
        if facts.count < 2:
            return no_pattern_caption(result)
        where = {"row": " in a row", "column": " in a column",
                 "grid": " arranged in a grid"}.get(facts.layout, "")
        more = ", next to other repeated items" if facts.n_patterns > 1 else ""
        return f"A group of similar {self.noun}{where}{more}."


class TransformersCaptioner:
    """A ``transformers`` image-to-text model (BLIP, GIT ...) from a folder or hub name.

    Raises :class:`CaptionerUnavailable` at construction when ``transformers`` is not
    installed or the model cannot be loaded.
    """

    def __init__(self, model: str, seed: int = 0, max_new_tokens: int = 30) -> None:
        try:
            import transformers  # noqa: F401
        except ImportError:
            raise CaptionerUnavailable(
                "captioner 'transformers' needs the Python package 'transformers', which "
                "is not installed; install it (pip install transformers) or set "
                "caption.captioner to 'template' or 'csv'") from None
        self.seed = int(seed)
        self.max_new_tokens = int(max_new_tokens)
        try:
            from transformers import pipeline

            self._pipe = pipeline("image-to-text", model=model)
        except Exception as e:  # noqa: BLE001 - any loading failure means unavailable
            raise CaptionerUnavailable(
                f"image-to-text model {model!r} could not be loaded ({type(e).__name__}: "
                f"{e}); download it to a local folder and set caption.model to it") from None

    def caption(self, rgb: np.ndarray, result: ImageResult, image_name: str) -> str:
        import torch
        from PIL import Image

        torch.manual_seed(self.seed)
        out = self._pipe(Image.fromarray(np.asarray(rgb, np.uint8)),
                         generate_kwargs={"max_new_tokens": self.max_new_tokens,
                                          "do_sample": False})
        text = str(out[0]["generated_text"]).strip()
        return capitalise(text) + ("" if text.endswith((".", "!", "?")) else ".")


class CsvCaptioner:
    """Captions read from a CSV file with columns ``image,caption``.

    ``image`` is a file name (``images/a.jpg`` or ``a.jpg``) or a stem (``a``). A missing
    image uses ``fallback`` (the template captioner by default) and is logged; with
    ``fallback=None`` it raises :class:`CaptionMissing`. A missing or malformed file
    raises :class:`~rescu.io.InputError` naming it.
    """

    def __init__(self, path: str | Path, fallback: Captioner | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        self.path = Path(path)
        self.fallback = fallback if fallback is not None else TemplateCaptioner()
        self.log = log or logger.info
        self.captions = self._read(self.path)

    @staticmethod
    def _read(path: Path) -> dict[str, str]:
        if not str(path) or not path.is_file():
            raise InputError(f"{path}: caption CSV file not found")
        try:
            text = path.read_text(encoding="utf-8-sig")
        except UnicodeDecodeError as e:
            raise InputError(f"{path}: caption CSV is not UTF-8 text ({e})") from None
        try:
            rows = list(csv.reader(text.splitlines(), strict=True))
        except csv.Error as e:
            raise InputError(f"{path}: malformed caption CSV ({e})") from None
        if not rows:
            raise InputError(f"{path}: caption CSV is empty; expected a header 'image,caption'")
        header = [h.strip().lower() for h in rows[0]]
        if "image" not in header or "caption" not in header:
            raise InputError(f"{path}: caption CSV header must have columns 'image' and "
                             f"'caption', got {rows[0]}")
        ii, ci = header.index("image"), header.index("caption")
        out: dict[str, str] = {}
        for ln, row in enumerate(rows[1:], start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputError(f"{path}: line {ln} has {len(row)} fields, the header "
                                 f"has {len(header)} (quote captions that contain commas)")
            name, cap = row[ii].strip(), row[ci].strip()
            if not name:
                raise InputError(f"{path}: line {ln} has an empty 'image' field")
            for key in {name, Path(name).name, Path(name).stem}:
                out.setdefault(key, cap)
        return out

    def lookup(self, image_name: str) -> str:
        """The CSV caption of ``image_name`` (path, file name or stem)."""
        for key in (image_name, Path(image_name).name, Path(image_name).stem):
            if key in self.captions:
                return self.captions[key]
        raise CaptionMissing(f"{self.path}: no caption for image {image_name!r}")

    def caption(self, rgb: np.ndarray, result: ImageResult, image_name: str) -> str:
        try:
            return self.lookup(image_name)
        except CaptionMissing as e:
            if self.fallback is None:
                raise
            self.log(f"{e.args[0]}; using the template captioner")
            return self.fallback.caption(rgb, result, image_name)


def make_captioner(params: CaptionParams,
                   log: Callable[[str], None] | None = None) -> Captioner:
    """The configured captioner; the template one (logged) when it is unavailable.

    A malformed or missing caption CSV is a configuration error and raises
    :class:`~rescu.io.InputError`; an unavailable ``transformers`` model falls back.
    """
    log = log or logger.warning
    if params.captioner == "template":
        return TemplateCaptioner()
    if params.captioner == "csv":
        return CsvCaptioner(params.csv_path, fallback=TemplateCaptioner(), log=log)
    try:
        return TransformersCaptioner(params.model, seed=params.seed,
                                     max_new_tokens=params.max_new_tokens)
    except CaptionerUnavailable as e:
        log(f"caption: {e}; falling back to the template captioner")
        return TemplateCaptioner()


def make_grounder(params: CaptionParams,
                  log: Callable[[str], None] | None = None) -> Grounder | None:
    """A grounding function from ``params.grounding_model`` (a ``transformers``
    zero-shot object detector such as OWL-ViT), or None when none is configured or it
    cannot be loaded (logged; the dominant-RP-on-first-noun fallback is used)."""
    log = log or logger.warning
    if not params.grounding_model:
        return None
    try:
        from transformers import pipeline

        pipe = pipeline("zero-shot-object-detection", model=params.grounding_model)
    except Exception as e:  # noqa: BLE001
        log(f"caption: grounding model {params.grounding_model!r} unavailable "
            f"({type(e).__name__}: {e}); the dominant RP goes to the first noun")
        return None

    def ground(rgb: np.ndarray, noun: str) -> BBox | None:
        from PIL import Image

        dets = pipe(Image.fromarray(np.asarray(rgb, np.uint8)), candidate_labels=[noun])
        if not dets:
            return None
        b = max(dets, key=lambda d: d["score"])["box"]
        return (float(b["xmin"]), float(b["ymin"]), float(b["xmax"] - b["xmin"]),
                float(b["ymax"] - b["ymin"]))

    return ground


_GROUNDERS: dict[str, Grounder | None] = {}


def caption_result(rgb: np.ndarray, result: ImageResult, image_name: str,
                   captioner: Captioner, params: CaptionParams | None = None,
                   grounding: Grounder | None = None) -> dict[str, str]:
    """Base and enhanced caption of one image: ``{"base": ..., "enhanced": ...}``.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The image.
    result : ImageResult
        The patterns found (boxes in original pixels).
    image_name : str
        File name of the image (used by the CSV captioner).
    captioner : Captioner
        Without an RP of two or more instances both captions end with
        :data:`NO_PATTERN`, or :data:`NOTHING_LIKE_EXAMPLE` where an example box found
        nothing else (:func:`no_pattern_caption`; the template captioner's caption is
        just that).
        From :func:`make_captioner`.
    params : CaptionParams, optional
        For ``grounding_coverage``.
    grounding : callable, optional
        From :func:`make_grounder`; when None and ``params.grounding_model`` is set, the
        grounder is built once per model (None when it cannot be loaded).
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    params = params or CaptionParams()
    if grounding is None and params.grounding_model:
        if params.grounding_model not in _GROUNDERS:
            _GROUNDERS[params.grounding_model] = make_grounder(params)
        grounding = _GROUNDERS[params.grounding_model]
    base = captioner.caption(rgb, result, image_name)
    if scene_facts(result).count < 2:  # nothing recurs: both captions say so
        none = no_pattern_caption(result)
        if none not in base:
            base = base.rstrip() + (" " if base.rstrip().endswith((".", "!", "?"))
                                    else ". " if base.strip() else "") + none
        return {"base": base, "enhanced": base}
    enhanced = enhance_caption(base, result, grounding=grounding, rgb=rgb,
                               coverage=params.grounding_coverage)
    return {"base": base, "enhanced": enhanced}
