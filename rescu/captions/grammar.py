"""The enhancement grammar's words and noun phrases: count words, plurals, tokens, and
the noun-phrase search and rewrite that :func:`rescu.captions.caption.enhance_caption`
applies to a base caption.

A light part-of-speech heuristic: small word lists of determiners, prepositions,
conjunctions and verbs mark noun-phrase boundaries; no NLP package is used. The rules
(collective phrase, "of" phrase, subject noun phrase) are described in
:mod:`rescu.captions.caption`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

# ----------------------------------------------------------------------------- words
_NUMBER_WORDS = ("zero one two three four five six seven eight nine ten eleven twelve "
                 "thirteen fourteen fifteen sixteen seventeen eighteen nineteen twenty").split()


def count_word(n: int) -> str:
    """``2 -> "two"`` ... ``20 -> "twenty"``, then digits (``21 -> "21"``).

    >>> count_word(2), count_word(20), count_word(21)
    ('two', 'twenty', '21')
    """
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
    """Heuristic: whether an English noun is already plural (or the same in both).

    >>> [is_plural(w) for w in ("windows", "glass", "sheep", "cell")]
    [True, False, True, False]
    """
    w = noun.lower()
    if w in _UNCHANGED_PLURALS or w in _KNOWN_PLURALS:
        return True
    if w in _IRREGULAR_PLURALS or w in _S_SINGULARS:
        return False
    return w.endswith("s") and not w.endswith(("ss", "us", "is"))


def pluralize(noun: str) -> str:
    """Plural of an English noun (regular rules + common irregulars); plurals unchanged.

    Keeps the capitalisation of the first letter.

    >>> [pluralize(w) for w in ("window", "Box", "person", "cars")]
    ['windows', 'Boxes', 'people', 'cars']
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
class Token:
    """One token of a caption: a word, a run of white space or one other character
    (the caption is the concatenation of its tokens' ``text``)."""

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


def tokenize(text: str) -> list[Token]:
    """The tokens of ``text`` (words with inner apostrophes or hyphens, white space,
    other characters); ``"".join(t.text for t in tokenize(s)) == s``.

    >>> [t.text for t in tokenize("Two cars, parked.")]
    ['Two', ' ', 'cars', ',', ' ', 'parked', '.']
    """
    return [Token(t) for t in _TOKEN_RE.findall(text)]


def _is_function_word(w: str) -> bool:
    return (w in _DETERMINERS or w in _PREPOSITIONS or w in _CONJUNCTIONS
            or w in _PRONOUNS or w in _VERBS)


def _is_verb_form(w: str) -> bool:
    return ((w.endswith("ing") and len(w) > 4 and w not in _ING_NOUNS)
            or (w.endswith("ed") and len(w) > 3 and w not in _ED_NOUNS))


@dataclass
class NounPhrase:
    """A noun phrase of a token list: token indices of its start, body and head noun."""

    start: int        # token index of the first word (determiner included)
    body: int         # token index of the first word after determiner/quantifier
    head: int         # token index of the head noun
    collective: bool  # "<det> <adj> group of <np>": start..of is replaced
    of_index: int     # token index of "of" for a collective phrase, else -1


def _words(toks: list[Token]) -> list[int]:
    return [i for i, t in enumerate(toks) if t.is_word]


def _scan_np(toks: list[Token], widx: list[int], k: int) -> tuple[int, int, int] | None:
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


def noun_phrases(toks: list[Token]) -> list[NounPhrase]:
    """All noun phrases in order; a collective "X of Y" becomes one phrase headed by Y."""
    widx = _words(toks)
    pos = {ti: k for k, ti in enumerate(widx)}
    out: list[NounPhrase] = []
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
                out.append(NounPhrase(start, ibody, ihead, True, widx[hk + 1]))
                k = pos[ihead] + 1
                continue
        out.append(NounPhrase(start, body, head, False, -1))
        k = hk + 1
    return out


def _sentence_start(toks: list[Token], i: int) -> bool:
    """Whether token ``i`` begins the caption or a sentence."""
    for t in reversed(toks[:i]):
        if t.is_space:
            continue
        return t.text in ".!?"
    return True


def capitalise(s: str) -> str:
    """``s`` with its first character upper-cased (the rest unchanged).

    >>> capitalise("five windows"), capitalise("")
    ('Five windows', '')
    """
    return s[:1].upper() + s[1:] if s else s


def rewrite_phrase(toks: list[Token], np_: NounPhrase, count: int) -> tuple[list[Token], str]:
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
        phrase = capitalise(phrase)
    rest = toks[body:]
    if at_start and cut_from == np_.start == body and rest and rest[0].is_word:
        first = rest[0].text
        # lower-case a capitalised common word that no longer starts the sentence
        # (a nationality adjective keeps its capital: "four similar Italian cars")
        if (first[:1].isupper() and not first.isupper()
                and first.lower() not in _NATIONALITIES):
            rest = [Token(first[0].lower() + first[1:])] + rest[1:]
    before = toks[:cut_from]
    if head_was_singular:
        # "There is a bottle" -> "There are eight similar bottles"
        w = [i for i, t in enumerate(before) if t.is_word][-2:]
        if (len(w) == 2 and before[w[0]].low == "there"
                and before[w[1]].low in ("is", "was", "'s")):
            rep = "are" if before[w[1]].low != "was" else "were"
            before = before[:w[1]] + [Token(rep)] + before[w[1] + 1:]
    new = before + [Token(phrase + " ")] + rest
    head_i = cut_from + 1 + (np_.head - body)
    keep_case = new[head_i].text
    new[head_i] = Token(pluralize(keep_case))
    head_plural = new[head_i].text
    if head_was_singular:
        # verb agreement right after the head noun ("bottle is" -> "bottles are")
        for j in range(head_i + 1, len(new)):
            if new[j].is_space:
                continue
            if new[j].is_word and new[j].low in _VERB_AGREEMENT:
                rep = _VERB_AGREEMENT[new[j].low]
                new[j] = Token(capitalise(rep) if new[j].text[0].isupper() else rep)
            break
    return new, head_plural


def choose_phrase(toks: list[Token], nps: list[NounPhrase]) -> NounPhrase | None:
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
