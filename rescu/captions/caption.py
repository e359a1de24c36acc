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

Enhancement grammar (a light part-of-speech heuristic: small word lists of
determiners, prepositions, conjunctions and verbs mark noun-phrase boundaries; no NLP
package is used):

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
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ..io import InputError
from ..types import BBox, ImageResult, Pattern
from ..params import checked_mapping

logger = logging.getLogger(__name__)

Grounder = Callable[[np.ndarray, str], "BBox | None"]
"""``ground(rgb, noun) -> (x, y, w, h)`` box in original pixels, or None if not found;
``noun`` is a lower-case noun-phrase head as it appears in the caption."""


class CaptionerUnavailable(RuntimeError):
    """The configured captioner cannot be used here (message says what is missing)."""


class CaptionMissing(KeyError):
    """A CSV captioner has no caption for the image."""


# ----------------------------------------------------------------------------- params
@dataclass(frozen=True)
class CaptionParams:
    """Parameters of captioning.

    Attributes
    ----------
    captioner : str
        ``"template"`` (offline), ``"transformers"`` (image-to-text model) or ``"csv"``.
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

    captioner: str = "template"
    model: str = "Salesforce/blip-image-captioning-base"
    csv_path: str = ""
    grounding_model: str = ""
    grounding_coverage: float = 0.90
    max_new_tokens: int = 30
    seed: int = 0

    def __post_init__(self) -> None:
        if self.captioner not in ("template", "transformers", "csv"):
            raise ValueError(f"CaptionParams.captioner must be 'template', 'transformers' "
                             f"or 'csv', got {self.captioner!r}")
        if not 0.0 <= float(self.grounding_coverage) <= 1.0:
            raise ValueError(f"CaptionParams.grounding_coverage must be in [0, 1], got "
                             f"{self.grounding_coverage}")
        if int(self.max_new_tokens) < 1:
            raise ValueError(f"CaptionParams.max_new_tokens must be >= 1, got "
                             f"{self.max_new_tokens}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "CaptionParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        d = checked_mapping(cls, d, "caption parameter")
        for k in ("csv_path", "grounding_model", "model"):
            if k in d and d[k] is None:
                d[k] = ""
        return cls(**d)


# ----------------------------------------------------------------------------- words
_NUMBER_WORDS = ("zero one two three four five six seven eight nine ten eleven twelve "
                 "thirteen fourteen fifteen sixteen seventeen eighteen nineteen twenty").split()


def count_word(n: int) -> str:
    """``2 -> "two"`` ... ``20 -> "twenty"``, then digits (``21 -> "21"``)."""
    n = int(n)
    if n < 0:
        raise ValueError(f"count must be >= 0, got {n}")
    return _NUMBER_WORDS[n] if n <= 20 else str(n)


COLLECTIVE_NOUNS = frozenset("""
group groups herd herds flock flocks row rows series set sets line lines stack stacks
pile piles bunch bunches pair pairs collection collections crowd crowds team teams
number numbers couple couples cluster clusters array arrays bank banks fleet fleets
swarm swarms school schools pack packs column columns bundle bundles batch batches
cluster clusters heap heaps assortment assortments variety display displays range
lot lots bevy band bands gaggle colony colonies troop troops litter litters grid grids
arrangement arrangements selection selections string strings chain chains queue
queues tier tiers cluster couple handful dozens dozen multitude plenty
""".split())

_DETERMINERS = frozenset("""
a an the this that these those some several many multiple few numerous various each
every its their his her our my your any all both another other lots
""".split())
_INDEFINITE = frozenset("""a an one some several many multiple few numerous various
any all both another lots""".split()) | frozenset(_NUMBER_WORDS)
_PREPOSITIONS = frozenset("""
on in at of with by near next to under over above below behind beside besides between
among along across around inside outside from into onto through against for during
without within up down off atop upon beneath underneath past toward towards like
opposite alongside amid amidst beyond throughout via
""".split())
_CONJUNCTIONS = frozenset("and or but while as that which who whom whose where when "
                          "than so nor".split())
_PRONOUNS = frozenset("it they them he she we you i there here someone something".split())
_VERBS = frozenset("""
is are was were be been being am has have had do does did can could will would may
might shall should must sit sits sat stand stands stood lie lies lay hang hangs hung
show shows showed shown hold holds held contain contains look looks walk walks run runs
fly flies grow grows wait waits rest rests eat eats play plays park parks sleep sleeps
line lines cover covers fill fills appear appears seem seems remain remains float
floats swim swims graze grazes face faces surround surrounds decorate decorates
overlook overlooks occupy occupies rise rises stretch stretches
""".split())
# Verbs that agree with a plural subject: singular form -> plural form.
_VERB_AGREEMENT = {"is": "are", "was": "were", "has": "have", "does": "do"}
for _v in ("sits stands lies hangs shows holds contains looks walks runs grows waits rests "
           "eats plays sleeps appears seems remains floats swims grazes faces surrounds "
           "decorates overlooks rises stretches").split():
    _VERB_AGREEMENT[_v] = _v[:-2] if _v.endswith(("ches", "shes", "sses", "xes")) else _v[:-1]
_VERB_AGREEMENT["flies"] = "fly"
_VERB_AGREEMENT["occupies"] = "occupy"

_ING_NOUNS = frozenset("""building painting ceiling clothing king ring thing string wing
spring swing something nothing evening morning ping wedding railing housing dwelling
sibling pudding awning""".split())
_ED_NOUNS = frozenset("bed shed sled red seed weed reed need feed bread thread".split())

# Modifiers that go in front of a head noun. An -ing / -ed word after modifiers only is
# part of the noun phrase ("red sleeping bags", "Italian racing cars"), after a noun it
# starts a participle clause ("a cat sleeping on a bed", "a dog eating food").
# Adjectives that are (practically) never the head noun of a caption's noun phrase:
_ADJECTIVES = frozenset("""
red blue green yellow purple pink brown black white gray grey beige teal turquoise
maroon violet magenta crimson scarlet colorful colourful
big small large little tiny huge enormous tall short long wide narrow thin thick
old new young ancient modern vintage empty full open bright pale dark shiny dirty
clean wet dry heavy pretty beautiful cute fancy wild electric wooden golden similar
identical same different various other
""".split())
# Modifiers that are also nouns ("an Italian", "an orange", "a metal"): a modifier in
# front of an -ing word followed by a noun, the head otherwise.
_NATIONALITIES = frozenset("""
italian french german spanish english british american canadian mexican chinese
japanese korean indian thai vietnamese russian polish dutch swedish norwegian danish
finnish irish scottish welsh greek turkish egyptian african european asian australian
brazilian argentinian portuguese swiss austrian belgian cuban persian moroccan
hungarian czech ukrainian arabian
""".split())
_NOUN_MODIFIERS = _NATIONALITIES | frozenset("""
orange gold silver cream olive lime tan navy ivory coral peach rose plum bronze lavender
metal plastic steel stone brick leather cardboard marble concrete iron rubber ceramic
porcelain wicker bamboo copper brass aluminum aluminium wood
""".split())

_IRREGULAR_PLURALS = {
    "person": "people", "child": "children", "man": "men", "woman": "women",
    "foot": "feet", "tooth": "teeth", "mouse": "mice", "goose": "geese", "ox": "oxen",
    "leaf": "leaves", "knife": "knives", "shelf": "shelves", "wolf": "wolves",
    "loaf": "loaves", "calf": "calves", "half": "halves", "wife": "wives",
    "life": "lives", "thief": "thieves", "elf": "elves", "scarf": "scarves",
    "potato": "potatoes", "tomato": "tomatoes", "hero": "heroes", "echo": "echoes",
    "mango": "mangoes", "volcano": "volcanoes", "torpedo": "torpedoes", "cactus": "cacti",
    "die": "dice", "louse": "lice", "fungus": "fungi", "criterion": "criteria",
}
_UNCHANGED_PLURALS = frozenset("""sheep fish deer moose bison salmon trout species series
aircraft swine shrimp squid offspring cattle people children men women feet teeth mice
geese data police""".split())
_KNOWN_PLURALS = frozenset(_IRREGULAR_PLURALS.values())
_S_SINGULARS = frozenset("""bus gas glass class grass boss dress mass cross bass lens
canvas bonus cactus virus campus circus octopus walrus iris tennis chess chassis
status atlas""".split())


def is_plural(noun: str) -> bool:
    """Heuristic: whether an English noun is already plural (or the same in both)."""
    w = noun.lower()
    if w in _UNCHANGED_PLURALS or w in _KNOWN_PLURALS:
        return True
    if w in _IRREGULAR_PLURALS or w in _S_SINGULARS:
        return False
    return w.endswith("s") and not w.endswith(("ss", "us", "is"))


def pluralize(noun: str) -> str:
    """Plural of an English noun (regular rules + common irregulars); plurals unchanged.

    Keeps the capitalisation of the first letter.
    """
    if not noun:
        return noun
    w = noun.lower()
    if is_plural(noun):
        return noun
    if w in _IRREGULAR_PLURALS:
        p = _IRREGULAR_PLURALS[w]
    elif re.search(r"[^aeiou]y$", w):
        p = w[:-1] + "ies"
    elif w.endswith(("s", "x", "z", "ch", "sh")):
        p = w + "es"
    else:
        p = w + "s"
    if noun[0].isupper():
        p = p[0].upper() + p[1:]
    return p


# ----------------------------------------------------------------------------- tokens
_TOKEN_RE = re.compile(r"[A-Za-z0-9]+(?:['’\-][A-Za-z0-9]+)*|\s+|[^\sA-Za-z0-9]")


@dataclass
class _Tok:
    text: str

    @property
    def low(self) -> str:
        return self.text.lower()

    @property
    def is_word(self) -> bool:
        return bool(self.text) and (self.text[0].isalnum())

    @property
    def is_space(self) -> bool:
        return self.text.isspace()


def _tokenize(text: str) -> list[_Tok]:
    return [_Tok(t) for t in _TOKEN_RE.findall(text)]


def _is_function_word(w: str) -> bool:
    return (w in _DETERMINERS or w in _PREPOSITIONS or w in _CONJUNCTIONS
            or w in _PRONOUNS or w in _VERBS)


def _is_verb_form(w: str) -> bool:
    return ((w.endswith("ing") and len(w) > 4 and w not in _ING_NOUNS)
            or (w.endswith("ed") and len(w) > 3 and w not in _ED_NOUNS))


@dataclass
class _NounPhrase:
    start: int        # token index of the first word (determiner included)
    body: int         # token index of the first word after determiner/quantifier
    head: int         # token index of the head noun
    collective: bool  # "<det> <adj> group of <np>": start..of is replaced
    of_index: int     # token index of "of" for a collective phrase, else -1


def _words(toks: list[_Tok]) -> list[int]:
    return [i for i, t in enumerate(toks) if t.is_word]


def _scan_np(toks: list[_Tok], widx: list[int], k: int) -> tuple[int, int, int] | None:
    """Noun phrase starting at word position ``k`` of ``widx``: (start, body, head).

    Determiners / quantifiers, then content words; the head is the last content word
    before a function word, punctuation or a participle clause. An -ing / -ed word
    after a noun starts a participle clause ("babies sitting on", "cars parked along",
    "a dog eating food"); after modifiers only (adjectives, colour and nationality
    words, participles: :data:`_ADJECTIVES`, :data:`_NOUN_MODIFIERS`) it is a modifier
    too when a noun follows ("red sleeping bags", "Italian racing cars", "old parked
    cars"), and after adjectives only it is always in the phrase ("a large gathering").
    """
    n = len(widx)
    if k >= n:
        return None
    start = widx[k]
    j = k
    while j < n and (toks[widx[j]].low in _DETERMINERS or toks[widx[j]].low in _INDEFINITE):
        j += 1
    if j >= n:
        return None
    body = widx[j]

    def joined(a: int, b: int) -> bool:
        # no punctuation (other than inside a hyphenated word) between tokens a and b
        return not any(not t.is_word and not t.is_space for t in toks[a + 1:b])

    head = -1
    mods_only = True  # every word taken so far is a modifier (adjective, participle ...)
    adjs_only = True  # every word taken so far is an adjective that is no noun
    while j < n:
        ti = widx[j]
        w = toks[ti].low
        if head >= 0 and not joined(widx[j - 1], ti):
            break
        if w in COLLECTIVE_NOUNS and j + 1 < n and toks[widx[j + 1]].low == "of":
            head = ti  # "a large group of": the adjectives belong to the collective
            break
        if _is_function_word(w):
            break
        verb_form = _is_verb_form(w)
        if verb_form and head >= 0 and not adjs_only:
            # a noun phrase word must follow for the participle to be a modifier
            nxt = toks[widx[j + 1]].low if j + 1 < n and joined(ti, widx[j + 1]) else ""
            if not nxt or _is_function_word(nxt):
                break  # "cars parked along", "a cat sleeping."
            if w.endswith("ing") and not mods_only:
                break  # "a dog eating food"; "old parked cars", "red sleeping bags" go on
        head = ti
        mods_only = mods_only and (verb_form or w in _ADJECTIVES or w in _NOUN_MODIFIERS)
        adjs_only = adjs_only and w in _ADJECTIVES
        j += 1
    if head < 0:
        return None
    return start, body, head


def _noun_phrases(toks: list[_Tok]) -> list[_NounPhrase]:
    """All noun phrases in order; a collective "X of Y" becomes one phrase headed by Y."""
    widx = _words(toks)
    pos = {ti: k for k, ti in enumerate(widx)}
    out: list[_NounPhrase] = []
    k = 0
    while k < len(widx):
        w = toks[widx[k]].low
        if _is_function_word(w) and w not in _DETERMINERS and w not in _INDEFINITE:
            k += 1
            continue
        np_ = _scan_np(toks, widx, k)
        if np_ is None:
            k += 1
            continue
        start, body, head = np_
        hk = pos[head]
        if (toks[head].low in COLLECTIVE_NOUNS and hk + 1 < len(widx)
                and toks[widx[hk + 1]].low == "of"):
            inner = _scan_np(toks, widx, hk + 2)
            if inner is not None:
                istart, ibody, ihead = inner
                out.append(_NounPhrase(start, ibody, ihead, True, widx[hk + 1]))
                k = pos[ihead] + 1
                continue
        out.append(_NounPhrase(start, body, head, False, -1))
        k = hk + 1
    return out


def _sentence_start(toks: list[_Tok], i: int) -> bool:
    """Whether token ``i`` begins the caption or a sentence."""
    for t in reversed(toks[:i]):
        if t.is_space:
            continue
        return t.text in ".!?"
    return True


def _capitalise(s: str) -> str:
    return s[:1].upper() + s[1:] if s else s


def _rewrite(toks: list[_Tok], np_: _NounPhrase, count: int) -> tuple[list[_Tok], str]:
    """Insert the count into one noun phrase; return new tokens and the plural head."""
    at_start = _sentence_start(toks, np_.start)
    widx = _words(toks)
    if np_.collective:  # "a bunch of bananas is" agrees with the collective noun
        coll = widx[widx.index(np_.of_index) - 1]
        head_was_singular = not is_plural(toks[coll].text)
    else:
        head_was_singular = not is_plural(toks[np_.head].text)
    body = np_.body
    if np_.collective:
        # replace "<det> <adj> group of [a|an|quantifier]" with "<count> similar"
        cut_from = np_.start  # np_.body skips the determiners after "of"
    else:
        # drop an indefinite article / quantifier, keep "the", "these", possessives ...
        k = widx.index(np_.start)
        while widx[k] < np_.body and toks[widx[k]].low not in _INDEFINITE:
            k += 1
        cut_from = widx[k] if widx[k] < np_.body else np_.body
    similar = toks[body].low == "similar"
    phrase = count_word(count) + ("" if similar else " similar")
    if at_start and cut_from == np_.start:
        phrase = _capitalise(phrase)
    rest = toks[body:]
    if at_start and cut_from == np_.start == body and rest and rest[0].is_word:
        first = rest[0].text
        # lower-case a capitalised common word that no longer starts the sentence
        # (a nationality adjective keeps its capital: "four similar Italian cars")
        if (first[:1].isupper() and not first.isupper()
                and first.lower() not in _NATIONALITIES):
            rest = [_Tok(first[0].lower() + first[1:])] + rest[1:]
    before = toks[:cut_from]
    if head_was_singular:
        # "There is a bottle" -> "There are eight similar bottles"
        w = [i for i, t in enumerate(before) if t.is_word][-2:]
        if (len(w) == 2 and before[w[0]].low == "there"
                and before[w[1]].low in ("is", "was", "'s")):
            rep = "are" if before[w[1]].low != "was" else "were"
            before = before[:w[1]] + [_Tok(rep)] + before[w[1] + 1:]
    new = before + [_Tok(phrase + " ")] + rest
    head_i = cut_from + 1 + (np_.head - body)
    keep_case = new[head_i].text
    new[head_i] = _Tok(pluralize(keep_case))
    head_plural = new[head_i].text
    if head_was_singular:
        # verb agreement right after the head noun ("bottle is" -> "bottles are")
        for j in range(head_i + 1, len(new)):
            if new[j].is_space:
                continue
            if new[j].is_word and new[j].low in _VERB_AGREEMENT:
                rep = _VERB_AGREEMENT[new[j].low]
                new[j] = _Tok(_capitalise(rep) if new[j].text[0].isupper() else rep)
            break
    return new, head_plural


def _choose_phrase(toks: list[_Tok], nps: list[_NounPhrase]) -> _NounPhrase | None:
    """The phrase the dominant RP goes to without grounding (rules 1-3)."""
    for p in nps:
        if p.collective:
            return p
    widx = _words(toks)
    of_positions = [i for i in widx if toks[i].low == "of"]
    if of_positions:
        for p in nps:
            if p.start > of_positions[0]:
                return p
    return nps[0] if nps else None


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


def _scene_sentence(noun_plural: str, pattern: Pattern, result: ImageResult) -> str:
    ts = pattern.translation_symmetry is not None and pattern.translation_symmetry.detected
    vp = pattern.vanishing_point or result.vanishing_point
    parts = []
    if ts:
        parts.append("have a potential translation symmetry in 3D")
    if vp is not None:
        parts.append("form a vanishing point " + ("inside the image" if vp.inside_image
                                                   else "outside of the image"))
    if not parts:
        return ""
    return f"The {noun_plural} " + " and ".join(parts) + "."


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
    toks = _tokenize(base)
    nps = _noun_phrases(toks)
    if not nps:
        return base
    assignments: list[tuple[_NounPhrase, Pattern]] = []
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
        p = _choose_phrase(toks, nps)
        if p is None:
            return base
        assignments = [(p, dom)]
    # rewrite from the last phrase to the first so that token indices stay valid
    nouns: dict[int, str] = {}
    for p, pat in sorted(assignments, key=lambda a: -a[0].start):
        toks, noun = _rewrite(toks, p, pat.count)
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


def infer_layout(pattern: Pattern, line_tolerance: float = 0.35) -> str:
    """``"row"``, ``"column"``, ``"grid"`` or ``"group"`` from the instance centres.

    ``pattern.extra["layout"]`` wins when present. Centres lie on a line when their
    spread across the principal direction is below ``line_tolerance`` times the median
    instance side (pixels / pixels).
    """
    lay = pattern.extra.get("layout") if isinstance(pattern.extra, dict) else None
    if isinstance(lay, str) and lay:
        return lay
    if pattern.count < 3:
        return "group"
    b = np.array([i.bbox for i in pattern.instances], float)
    c = b[:, :2] + b[:, 2:] / 2.0
    side = float(np.median(np.minimum(b[:, 2], b[:, 3])))
    cc = c - c.mean(axis=0)
    _, s, vt = np.linalg.svd(cc, full_matrices=False)
    spread = s[1] / np.sqrt(len(c)) if len(s) > 1 else 0.0  # std across the line
    if spread <= line_tolerance * max(side, 1e-9):
        d = vt[0]
        return "column" if abs(d[1]) > abs(d[0]) else "row"
    return "grid"


@dataclass
class TemplateCaptioner:
    """Offline captioner: a plain sentence from what was found (generic nouns).

    The base caption keeps a collective noun so that :func:`enhance_caption` turns it
    into a count: "A group of similar objects in a row." -> "Five similar objects in a
    row."
    """

    noun: str = "objects"

    def caption(self, rgb: np.ndarray, result: ImageResult, image_name: str) -> str:
        dom = dominant_pattern(result)
        if dom is None or dom.count < 2:
            return "A scene without repeated objects."
        lay = infer_layout(dom)
        where = {"row": " in a row", "column": " in a column",
                 "grid": " arranged in a grid"}.get(lay, "")
        n_rp = sum(1 for p in result.patterns if p.count >= 2)
        more = ", next to other repeated items" if n_rp > 1 else ""
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
        return _capitalise(text) + ("" if text.endswith((".", "!", "?")) else ".")


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
    enhanced = enhance_caption(base, result, grounding=grounding, rgb=rgb,
                               coverage=params.grounding_coverage)
    return {"base": base, "enhanced": enhanced}
