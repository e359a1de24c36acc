"""How RESCU-I takes its RPs from more than one source: stage I's keypoint RPs and the
dense source's (:mod:`rescu.extension.dense`), with the ``dense`` config section.

Kept apart from the dense source itself so that stage I's step does not depend on the
backbone code: the RESCU-I step only combines the RPs the ``dense`` step wrote.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..boxes import cover_matrix, greedy_keep
from ..params import checked_mapping, config_section, schema_enum
from ..types import ImageResult, Pattern, failure_record
from .tiling import share_inside

#: The modes of :func:`combine_sources`.
MODES: tuple[str, ...] = schema_enum("dense", "mode")


def is_whole_object(p: Pattern) -> bool:
    """Whether ``p`` is an RP of whole objects: RESCU-I took it from the dense source
    (``extra["source"] == "dense"``; an RP merged by RESCU-II keeps its higher-score
    part's source)."""
    return p.extra.get("source") == "dense"


@dataclass(frozen=True)
@config_section("dense")
class DenseParams:
    """Config section ``dense`` (see ``rescu/defaults/config.yaml`` for each key's meaning).

    Attributes
    ----------
    enabled : bool
        Run the dense source and give its RPs to RESCU-I.
    mode : str
        ``"objects"``, ``"both"`` or ``"dense"`` (:func:`combine_sources`).
    backbone : str
        Frozen backbone name (:data:`rescu.extension.backbone.BACKBONES`).
    max_side : int
        Longer side of the backbone input, pixels (the prepared image is downscaled to
        it when larger).
    min_side : int
        A prepared image whose longer side is shorter is upscaled to it (blob sizes are
        in feature cells, so small photos would leave small objects under the smallest
        size); ``<= max_side``.
    sizes : tuple of int
        Blob sides on the coarse map, feature cells (one cell = 8 backbone-input pixels).
    fine_scale : float
        The fine map (:func:`rescu.extension.dense.dense_levels`) is of the image
        enlarged this many times more than the coarse one, for objects too small for the
        coarse map; 1 leaves it out.
    fine_max_side : int
        Longer side of the fine map's input at most, pixels (bounds its cost).
    fine_sizes : tuple of int
        Blob sides on the fine map, feature cells.
    wide_scales : tuple of float
        Wide maps (:func:`rescu.extension.dense.dense_levels`) of the image reduced to
        these fractions of the coarse map's scale, for objects too large for the coarse
        map (its largest blob spans ``max(sizes)`` cells: about 7 % of the side of a photo
        seen at ``min_side``); each in (0, 0.95]; empty: none.
    wide_sizes : tuple of int
        Blob sides on the wide map, feature cells.
    rotations : int
        Backbone passes per map, 1, 2 or 4: each map is the mean of the image's maps
        turned by 0 and 90 degrees (2) or by every right angle (4), each turned back
        (:func:`rescu.extension.dense.hypercolumn`), so that objects seen from above at
        those orientations look alike.
    min_map_px : float
        A dense RP's instances must span this many pixels of its map's input (median box
        side; one cell of the stride-16 half is 16).
    min_object_px : float
        ... and this many pixels of the prepared image.
    surround : int
        Side of the surround window / blob side (odd, >= 3).
    max_blobs : int
        Strongest blobs kept before grouping.
    min_similarity : float
        Average-linkage cosine similarity at which blobs are one RP, in (0, 1).
    max_colour_distance : float
        ... and the average-linkage distance of the mean CIELAB colours of the blobs'
        central halves (OpenCV's 8-bit L, a, b) beyond which one group of alike features
        is split (:func:`rescu.extension.dense.split_by_colour`: the ImageNet features
        see a dark car and a white one, a black pawn and a white one alike; a person
        does not); 0 = not split.
    min_instances : int
        Smallest RP.
    max_patterns : int
        Dense RPs kept per image, by contrast x rarity x objectness
        (:func:`dense_patterns`).
    overlap_iod : float
        ``mode="both"``: a dense instance whose IOD with a stage-I instance (either way)
        exceeds this is dropped; ``mode="objects"``: the same for an RP's instance and a
        more confident reported RP's (:func:`split_by_confidence`).
    max_touching : float
        A dense RP whose instances abut others of the RP on more than this many sides
        on average (of 4; :func:`rescu.boxes.touching_sides`) tiles the plane
        (board squares, floor tiles, brick) and is dropped; 4 keeps every RP.
    touch_tolerance : float
        A neighbour abuts a side when its centre lies one median box side away in that
        direction, within this fraction of the side on each axis.
    objectness_crops : int
        Each RP's score is also multiplied by its objectness: the mean top-class
        probability of the backbone's ImageNet classifier on crops around this many of
        its instances, strongest first (:func:`rescu.extension.dense.objectness`); 0
        ranks by contrast x rarity alone.
    objectness_px : int
        Side of those crops when classified, pixels.
    objectness_context : float
        Side of a crop / the longer side of its instance box (>= 1: some context).
    whole_objects : bool
        Turn each ranked group into an RP of whole objects
        (:func:`rescu.extension.objects.whole_objects`); false: the groups' blobs as they
        are (the source before whole objects).
    max_candidates : int
        Ranked groups tried, best first, until ``max_patterns`` RPs are kept
        (``>= max_patterns``; groups that hold parts of a kept RP's objects are skipped).
    complete : bool
        Completion by exemplar correlation (:func:`rescu.extension.objects.complete_group`).
    completion_margin : float
        Its threshold: the group's members' 20th-percentile similarity to their prototype
        minus this ...
    completion_floor : float
        ... and never below this cosine similarity.
    completion_turn : bool
        The completion also looks for the group's objects lying the other way: its
        prototype correlated over the map of the image turned by 90 degrees
        (:func:`rescu.extension.turned.complete_turned`; one more backbone pass per map).
    extent : bool
        Refine each RP's box extent (:func:`rescu.extension.contrast_extent.refine_extent`).
    extent_scales, extent_aspects, extent_shifts : tuple of float
        Its candidate transforms: box side x scale, width / height, centre shift as a
        fraction of the box.
    extent_turn : bool
        Each box may take the RP's transform turned by 90 degrees where its contrast is
        larger turned (objects lying both ways, such as parked cars).
    extent_ring : float
        Width of the ring the extent's contrast compares each box with, x the box's
        sides (:func:`rescu.extension.contrast_extent.colour_contrast`).
    extent_edges : float
        Weight of the edges on the boxes' outlines in the extent's score
        (:func:`rescu.extension.contrast_extent.edge_contrast`); 0: the colour contrast alone.
    part_cover : float
        A box lying inside a kept RP's box (or around one) by more than this fraction of
        the smaller is a part of the same object (:func:`rescu.extension.objects.suppress_parts`).
    part_area, part_reach : float
        Mode ``objects``: a dense RP holds parts of a stage-I RP's objects when at least
        ``part_cover`` of its boxes have their centre in a stage-I box grown
        ``part_reach`` times and at most ``part_area`` of its area (:func:`parts_of`);
        such a dense RP is dropped and the stage-I RP of whole objects stays
        (:func:`combine_sources`).
    confidence_gap_scale, confidence_n_scale, confidence_contrast_scale : float
        Scales of :func:`rescu.extension.objects.pattern_confidence`.
    confidence_score_scale : float
        Its scale of a dense RP's ranking score; 0: the score is not counted.
    confidence_stage1_score_scale : float
        Its scale of a stage-I RP's score on the feature map (its boxes' centre-surround
        contrast x their rarity, the dense ranking score without the objectness);
        0: not counted.
    min_confidence : float
        RPs whose confidence is below this are not reported: RESCU-I moves them to the
        result's ``candidate_patterns`` (:func:`split_by_confidence`); 0 reports all.
    min_separation : float or None
        A stage-I RP whose neighbouring instances are joined by more of the same (its
        :func:`rescu.extension.boxmaps.separation` below this) samples one structure (a
        ledge, a board's frame, a rim, a road marking), not separate objects: not
        reported (``"one structure"``); None: off, every RP reported.
    min_object_separation : float or None
        The same for an RP of whole objects (the dense source's), its separation measured
        on the central third of its boxes (:data:`rescu.extension.boxmaps.OBJECT_PROBE`):
        a cup's rim or a band of texture sampled by abutting boxes; None: off, every RP
        reported and every box kept.
    separation_reach : float
        Neighbours farther apart than this x their mean box side are not compared.
    checkerboard_min_corners : int
        A stage-I RP with half or more of its instances on a checkerboard (a board's
        squares: :func:`rescu.discovery.tiling.checkerboard_outline`, at least this
        many X-corners) samples a tiling: not reported (``"tiling"``); 0: not looked for.
    checkerboard_border : int
        Squares the board extends beyond its outermost corners found, on every side.
    checkerboard_min_alternation : float
        A grid of corners is a board when its cells' grey levels alternate as a
        checkerboard's on at least this share of them
        (:func:`rescu.discovery.tiling.grid_cells`).
    checkerboard_seed : int
        Seed of OpenCV's generator, which the board's detector draws from.
    """

    enabled: bool
    mode: str
    backbone: str
    max_side: int
    min_side: int
    sizes: tuple[int, ...]
    fine_scale: float
    fine_max_side: int
    fine_sizes: tuple[int, ...]
    wide_scales: tuple[float, ...]
    wide_sizes: tuple[int, ...]
    rotations: int
    min_map_px: float
    min_object_px: float
    surround: int
    max_blobs: int
    min_similarity: float
    max_colour_distance: float
    min_instances: int
    max_patterns: int
    overlap_iod: float
    max_touching: float
    touch_tolerance: float
    objectness_crops: int
    objectness_px: int
    objectness_context: float
    whole_objects: bool
    max_candidates: int
    complete: bool
    completion_margin: float
    completion_floor: float
    completion_turn: bool
    extent: bool
    extent_scales: tuple[float, ...]
    extent_aspects: tuple[float, ...]
    extent_shifts: tuple[float, ...]
    extent_turn: bool
    extent_ring: float
    extent_edges: float
    part_cover: float
    part_area: float
    part_reach: float
    confidence_gap_scale: float
    confidence_n_scale: float
    confidence_contrast_scale: float
    confidence_score_scale: float
    confidence_stage1_score_scale: float
    min_confidence: float
    min_separation: float | None
    min_object_separation: float | None
    separation_reach: float
    checkerboard_min_corners: int
    checkerboard_border: int
    checkerboard_min_alternation: float
    checkerboard_seed: int

    def __post_init__(self) -> None:
        if self.max_candidates < self.max_patterns:
            raise ValueError(f"dense.max_candidates ({self.max_candidates}) must be >= "
                             f"dense.max_patterns ({self.max_patterns})")
        if self.min_side > self.max_side:
            raise ValueError(f"dense.min_side must be at most max_side = {self.max_side}, "
                             f"got {self.min_side}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "DenseParams":
        """From the ``dense`` section (None: the defaults); unknown keys raise ValueError."""
        d = checked_mapping(cls, d, "dense parameter")
        for k in ("sizes", "fine_sizes", "wide_sizes"):
            if k in d:
                d[k] = tuple(int(s) for s in d[k])
        for k in ("extent_scales", "extent_aspects", "extent_shifts", "wide_scales"):
            if k in d:
                d[k] = tuple(float(v) for v in d[k])
        return cls(**d)


#: The ``dense`` keys the workflow's dense step runs under fixed values, whatever the
#: configuration says. ``enabled`` and ``mode``: the step always runs and makes what
#: every mode takes (mode ``both``). The others decide only which of its RPs RESCU-I
#: reports, after the step (its score of stage I's RPs, what it sets aside as one
#: structure or as a board's squares): the step
#: (:func:`rescu.extension.dense.find_dense`) reads none of them
#: (``tests/test_dense.py``). So changing one of them reruns RESCU-I, not the dense step.
DENSE_STEP_FIXED: dict[str, Any] = {
    "enabled": True, "mode": "both", "confidence_stage1_score_scale": 0.0,
    "min_separation": None, "min_object_separation": None, "checkerboard_min_corners": 0,
    "checkerboard_border": 0, "checkerboard_min_alternation": 0.75, "checkerboard_seed": 0}


def dense_step_section(dense: Mapping[str, Any]) -> dict[str, Any]:
    """The ``dense`` section as the dense step gets it: ``dense`` with the keys of
    :data:`DENSE_STEP_FIXED` at their fixed values (the workflow's ``dense`` rule).

    >>> s = dense_step_section({"min_separation": 0.3, "max_side": 640, "mode": "objects"})
    >>> s["min_separation"], s["max_side"], s["mode"]
    (None, 640, 'both')
    """
    return {**dense, **DENSE_STEP_FIXED}


def combine_sources(sparse: list[Pattern], dense: list[Pattern], params: DenseParams
                    ) -> list[Pattern]:
    """Stage I's RPs and the dense ones as one list (ids renumbered 0..).

    Each dense RP first keeps one box per object (:func:`_one_box_per_object`: of two
    boxes covering more than ``params.part_cover`` of each other, the stronger).
    ``params.mode == "dense"``: the dense RPs only. ``"both"``: stage I's RPs first, then
    each dense RP without its instances that overlap a stage-I instance (IOD above
    ``params.overlap_iod`` either way), kept when ``params.min_instances`` remain.
    ``"objects"``: the dense RPs (whole objects), less those that hold parts of a
    stage-I RP's objects (:func:`parts_of`: objects larger than the dense source's
    blobs, found whole by stage I), then stage I's RPs as they are: which of two
    overlapping RPs keeps the objects is decided by their confidence, once they are
    scored (:func:`split_by_confidence`).
    """
    dense = [q for q in (_one_box_per_object(d, params) for d in dense) if q is not None]
    if params.mode == "dense":
        out = list(dense)
    elif params.mode == "objects":
        out = [d for d in dense if not any(parts_of(d, s, params) for s in sparse)]
        out += list(sparse)
    else:
        out = list(sparse) + _without_overlap(dense, sparse, params)
    for k, p in enumerate(out):
        p.id = k
    return out


def parts_of(part: Pattern, whole: Pattern, params: DenseParams,
             any_size: bool = False) -> bool:
    """Whether the RP ``part`` holds parts of the objects of the RP ``whole``: at least
    ``params.part_cover`` of its boxes have their centre inside a box of ``whole`` grown
    ``params.part_reach`` times about its centre (stage I's boxes hug the keypoints, so
    an object's corners stick out of them) and at most ``params.part_area`` of its area
    (``any_size``: of any area: the same objects, described again).

    >>> from rescu.types import Instance, Pattern
    >>> rp = lambda boxes: Pattern(id=0, score=1.0, instances=[
    ...     Instance(bbox=b, score=1.0, source="stage1") for b in boxes])
    >>> whole = rp([(0, 0, 40, 40), (60, 0, 40, 40)])
    >>> corners = rp([(-4, -4, 8, 8), (36, 36, 8, 8), (62, 2, 8, 8), (200, 0, 8, 8)])
    >>> p = DenseParams()
    >>> parts_of(corners, whole, p), parts_of(whole, corners, p), parts_of(whole, whole, p)
    (True, False, False)
    """
    a = np.array([i.bbox for i in part.instances], float).reshape(-1, 4)
    b = np.array([i.bbox for i in whole.instances], float).reshape(-1, 4)
    if not len(a) or not len(b):
        return False
    d = np.abs((a[:, None, :2] + a[:, None, 2:] / 2) - (b[None, :, :2] + b[None, :, 2:] / 2))
    near = (d <= params.part_reach / 2 * b[None, :, 2:]).all(2)
    if not any_size:
        near &= (a[:, 2] * a[:, 3])[:, None] <= params.part_area * (b[:, 2] * b[:, 3])[None, :]
    return bool(near.any(1).mean() >= params.part_cover)


def _without_overlap(patterns: list[Pattern], first: list[Pattern], params: DenseParams
                     ) -> list[Pattern]:
    """Each of ``patterns`` less its instances that overlap an instance of ``first`` (IOD
    above ``params.overlap_iod`` either way; :func:`_less_overlap`): those none of whose
    instances overlap, and those with ``params.min_instances`` left; feature points
    follow their instances."""
    taken = np.array([i.bbox for p in first for i in p.instances], float).reshape(-1, 4)
    out = [_less_overlap(p, taken, params) for p in patterns]
    return [p for p in out if p is not None]


def _one_box_per_object(p: Pattern, params: DenseParams) -> Pattern | None:
    """``p`` less each instance whose intersection with a stronger instance of ``p`` (a
    higher instance score) is more than ``params.part_cover`` of the smaller box: two
    boxes of one object (a plain and a turned box on one coin). None when fewer than
    ``params.min_instances`` remain."""
    b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    if len(b) < 2:
        return p
    order = np.argsort(-np.array([i.score for i in p.instances], float), kind="stable")
    ranked = b[order]
    ok = np.zeros(len(b), bool)
    ok[order[greedy_keep(cover_matrix(ranked, ranked) > params.part_cover)]] = True
    return _kept(p, ok, params.min_instances)


def _kept(p: Pattern, ok: np.ndarray, min_instances: int) -> Pattern | None:
    """``p`` with the instances where ``ok`` (feature points follow them: column n of
    ``p.feature_points`` belongs to instance n, and a RESCU-II RP's later instances, stage
    II's, have none): ``p`` itself when all are, None when fewer than ``min_instances``
    are.

    >>> from rescu.types import Instance
    >>> p = Pattern(id=0, score=1.0, feature_points=np.arange(12.0).reshape(2, 3, 2),
    ...             instances=[Instance(bbox=(10.0 * k, 0, 5, 5)) for k in range(5)])
    >>> q = _kept(p, np.array([1, 0, 1, 0, 1], bool), 2)
    >>> q.count, q.feature_points[0].tolist()
    (3, [[0.0, 1.0], [4.0, 5.0]])
    """
    if ok.all():
        return p
    if ok.sum() < min_instances:
        return None
    fp = p.feature_points
    if fp is not None and np.ndim(fp) == 3 and np.shape(fp)[1] <= len(ok):
        fp = np.asarray(fp)[:, ok[:np.shape(fp)[1]]]
    return Pattern(id=p.id, score=p.score, feature_points=fp, extra=dict(p.extra),
                   instances=[i for i, k in zip(p.instances, ok) if k])


def _less_overlap(p: Pattern, taken: np.ndarray, params: DenseParams) -> Pattern | None:
    """``p`` less its instances that overlap a box of ``taken`` (IOD above
    ``params.overlap_iod`` either way; feature points follow their instances): ``p``
    itself when none does, None when fewer than ``params.min_instances`` remain."""
    b = np.array([i.bbox for i in p.instances], float).reshape(-1, 4)
    ok = (np.ones(len(b), bool) if not len(taken)
          else (cover_matrix(b, taken) <= params.overlap_iod).all(1))
    return _kept(p, ok, params.min_instances)


def split_by_confidence(res: ImageResult, min_confidence: float,
                        params: DenseParams | None = None,
                        board: np.ndarray | None = None) -> None:
    """Report the confident RPs of ``res``, most confident first; the others go to
    ``res.extra["candidate_patterns"]`` (their JSON, for experts, with ``"dropped"``
    saying why; not analysed further), in place; ids of both lists renumbered 0.. .

    An RP whose ``extra["confidence"]`` is below ``min_confidence`` is dropped
    (``"low confidence"``). With ``params`` (:class:`DenseParams`), an RP whose
    ``extra["separation"]`` is below ``params.min_separation`` (stage I's) or
    ``params.min_object_separation`` (the dense source's, ``extra["source"]`` ``"dense"``)
    samples one structure and is dropped (``"one structure"``), and the more confident
    of two overlapping RPs keeps the objects: going down the confidences, an RP loses its
    instances that overlap a reported RP's (IOD above ``params.overlap_iod`` either way)
    and is dropped when fewer than ``params.min_instances`` remain (``"overlap"``); before
    that, it is dropped when its boxes sit on a reported RP's objects (:func:`parts_of`
    of any size: ``"same objects"``; e.g. the rims and gaps around coins found whole, or
    the halves of objects that stage I found whole): one RP per set of objects. An RP
    without a confidence is reported, after those with one. With ``board`` ((K, 2)
    outline of a checkerboard in the result's pixels,
    :func:`rescu.discovery.tiling.checkerboard_outline`), a stage-I RP with half or more
    of its instances' centres on it samples the board's squares, a tiling, and is
    dropped (``"tiling"``) whatever its confidence; RPs of whole objects (the pieces on
    the board) are not.
    ``res.extra["n_candidate_patterns"]`` counts the dropped ones.

    >>> from rescu.types import Instance, Pattern
    >>> rp = lambda c, boxes: Pattern(id=0, score=1.0, extra={"confidence": c},
    ...     instances=[Instance(bbox=b, score=1.0, source="stage1") for b in boxes])
    >>> coins = [(0, 0, 40, 40), (60, 0, 40, 40), (120, 0, 40, 40)]
    >>> rims = [(x + 15, -4, 10, 8) for x, _, _, _ in coins]
    >>> halves = [(x + dx, 0, 20, 40) for x, _, _, _ in coins for dx in (0, 20)]
    >>> r = ImageResult(image="x", width=160, height=40, method="rescu-i", patterns=[
    ...     rp(0.5, rims), rp(0.2, coins[:2]), rp(0.8, halves), rp(0.9, coins)])
    >>> split_by_confidence(r, 0.3, DenseParams())
    >>> [p.count for p in r.patterns], [c["dropped"] for c in r.extra["candidate_patterns"]]
    ([3], ['same objects', 'same objects', 'low confidence'])
    """
    order = sorted(range(len(res.patterns)), key=lambda k: (
        "confidence" not in res.patterns[k].extra,
        -float(res.patterns[k].extra.get("confidence", 0.0)), k))
    kept: list[Pattern] = []
    dropped: list[tuple[Pattern, str]] = []
    for k in order:
        p = res.patterns[k]
        c = p.extra.get("confidence")
        if c is not None and float(c) < min_confidence:
            dropped.append((p, "low confidence"))
            continue
        if board is not None and not is_whole_object(p) and share_inside(
                np.array([i.bbox for i in p.instances], float), board) >= 0.5:
            dropped.append((p, "tiling"))
            continue
        if params is not None and c is not None:
            sep = p.extra.get("separation")
            floor = (params.min_object_separation if is_whole_object(p)
                     else params.min_separation)
            if sep is not None and floor is not None and float(sep) < floor:
                dropped.append((p, "one structure"))
                continue
            if any(parts_of(p, q, params, any_size=True) for q in kept):
                dropped.append((p, "same objects"))
                continue
            taken = np.array([i.bbox for q in kept for i in q.instances],
                             float).reshape(-1, 4)
            less = _less_overlap(p, taken, params)
            if less is None:
                dropped.append((p, "overlap"))
                continue
            p = less
        kept.append(p)
    for k, p in enumerate(kept):
        p.id = k
    res.patterns = kept
    res.extra["candidate_patterns"] = [dict(p.to_json(), id=k, dropped=why)
                                       for k, (p, why) in enumerate(dropped)]
    res.extra["n_candidate_patterns"] = len(dropped)


def drop_second_boxes(res: ImageResult, second: Sequence[np.ndarray],
                      params: DenseParams) -> None:
    """One box per object: each reported RP of ``res`` loses its instances that
    ``second`` marks (one (n_k,) bool array per RP, in ``res.patterns``' order; a second
    box on an object that another box already holds,
    :func:`rescu.extension.boxmaps.second_boxes`), feature points following them, in
    place. An RP left with fewer than ``params.min_instances`` moves to
    ``res.extra["candidate_patterns"]`` (``"same objects"``); ids are renumbered.

    >>> from rescu.types import Instance, Pattern
    >>> rp = lambda n: Pattern(id=0, score=1.0, extra={"confidence": 0.5},
    ...     instances=[Instance(bbox=(20.0 * k, 0, 10, 10)) for k in range(n)])
    >>> r = ImageResult(image="x", width=99, height=9, method="rescu-i",
    ...                 patterns=[rp(4), rp(3)])
    >>> drop_second_boxes(r, [np.array([0, 0, 1, 0], bool), np.array([0, 1, 1], bool)],
    ...                   DenseParams())
    >>> [p.count for p in r.patterns], [c["dropped"] for c in r.extra["candidate_patterns"]]
    ([3], ['same objects'])
    """
    kept: list[Pattern] = []
    moved = []
    for p, flags in zip(res.patterns, second):
        q = _kept(p, ~np.asarray(flags, bool), params.min_instances)
        if q is None:
            moved.append(p)
        else:
            kept.append(q)
    for k, p in enumerate(kept):
        p.id = k
    res.patterns = kept
    cands = list(res.extra.get("candidate_patterns", []))
    cands += [dict(p.to_json(), dropped="same objects") for p in moved]
    res.extra["candidate_patterns"] = [dict(c, id=k) for k, c in enumerate(cands)]
    res.extra["n_candidate_patterns"] = len(cands)


def read_dense(path: str) -> ImageResult:
    """The dense step's result at ``path``. An unreadable one (missing, malformed, not a
    per-image result) reads as a failed dense step: no pattern, and ``extra["failure"]``
    naming the file and what is wrong, so RESCU-I keeps stage I's RPs as it does for any
    failed dense step."""
    from ..io import read_result

    try:
        return read_result(path)
    except (OSError, ValueError, KeyError, TypeError) as e:
        return ImageResult(image="", width=0, height=0, method="dense",
                           extra={"failure": failure_record("dense", e)})


def skips_stage1(found: ImageResult | None, params: DenseParams | None) -> bool:
    """Whether RESCU-I need not run the stage-I search: the ``dense`` parameters
    ``params`` keep the dense RPs alone (``mode: dense``) and the dense step's result
    ``found`` did not fail (a failed one leaves stage I's RPs in place, so the search
    runs)."""
    return (found is not None and not found.extra.get("failure") and params is not None
            and params.mode == "dense")


def add_dense(res: ImageResult, found: ImageResult, params: DenseParams | None) -> None:
    """``res.patterns`` (stage I's) combined in place with the dense step's result
    ``found`` (:func:`combine_sources` with the ``dense`` parameters ``params``, None:
    the defaults), and
    ``res.extra["n_dense_patterns"]``; a failed dense step (``found.extra["failure"]``)
    leaves the patterns alone and is recorded as ``res.extra["dense_failure"]``."""
    failure = found.extra.get("failure")
    if failure:
        res.extra["dense_failure"] = failure
        return
    res.patterns = combine_sources(res.patterns, found.patterns,
                                   params if params is not None else DenseParams())
    res.extra["n_dense_patterns"] = sum(map(is_whole_object, res.patterns))
