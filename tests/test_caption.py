"""Captions and the enhancement grammar (rescu.captions.caption)."""

from __future__ import annotations

import builtins
from pathlib import Path

import numpy as np
import pytest

from rescu.captions import caption as C
from rescu.captions import grammar as G
from rescu.io import InputError
from rescu.types import ImageResult, Instance, Pattern, TranslationSymmetry, VanishingPoint

RGB = np.zeros((40, 60, 3), np.uint8)


def pattern(n: int, pid: int = 0, x0: float = 0.0, y0: float = 0.0, ts: bool | None = None,
            vp_inside: bool | None = None, grid: bool = False) -> Pattern:
    if grid:
        k = int(np.ceil(np.sqrt(n)))
        boxes = [(x0 + 20 * (i % k), y0 + 20 * (i // k), 10, 10) for i in range(n)]
    else:
        boxes = [(x0 + 20 * i, y0, 10, 10) for i in range(n)]
    return Pattern(pid, 1.0, [Instance(b) for b in boxes],
                   vanishing_point=(None if vp_inside is None else
                                    VanishingPoint(np.array([0.0, 0.0, 1.0]), vp_inside)),
                   translation_symmetry=(None if ts is None else
                                         TranslationSymmetry(ts, 1.34 if ts else 1.9, 3)))


def result(*patterns: Pattern, dominant: int | None = 0) -> ImageResult:
    return ImageResult("images/x.jpg", 640, 480, "rescu", list(patterns),
                       dominant_pattern=dominant if patterns else None)


def enh(base: str, n: int, **kw) -> str:
    return C.enhance_caption(base, result(pattern(n, **kw)))


# ----------------------------------------------------------------------------- grammar
@pytest.mark.parametrize("base,n,expected", [
    ("A group of babies sitting on the couch.", 6, "Six similar babies sitting on the couch."),
    ("A herd of llamas standing in a field", 6, "Six similar llamas standing in a field"),
    ("A large group of people.", 12, "Twelve similar people."),
    ("a flock of birds flying over the sea", 7, "Seven similar birds flying over the sea"),
    ("Rows of windows on a building.", 20, "Twenty similar windows on a building."),
    ("A row of cars parked along the street.", 21, "21 similar cars parked along the street."),
    ("A set of the bottles on a table", 3, "Three similar bottles on a table"),
    ("A pair of shoes.", 2, "Two similar shoes."),
    ("A group of similar objects in a row.", 5, "Five similar objects in a row."),
    ("There is a bunch of bananas on a table.", 9,
     "There are nine similar bananas on a table."),
    ("A bunch of bananas is on a table.", 9, "Nine similar bananas are on a table."),
    ("Rows of seats are empty.", 9, "Nine similar seats are empty."),
    ("there was a car", 3, "there were three similar cars"),
    ("A cat sleeping next to a stack of books.", 8,
     "A cat sleeping next to eight similar books."),
    ("A group of Dalmatians", 30, "30 similar Dalmatians"),
])
def test_collective_noun_replaced(base: str, n: int, expected: str) -> None:
    assert enh(base, n) == expected


@pytest.mark.parametrize("base,n,expected", [
    ("An old picture of stone statues", 6, "An old picture of six similar stone statues"),
    ("A photo of a mouse, on a desk!", 3, "A photo of three similar mice, on a desk!"),
    ("A close up of the tomato.", 4, "A close up of the four similar tomatoes."),
    ("A view of leaf on the ground", 10, "A view of ten similar leaves on the ground"),
])
def test_count_after_of(base: str, n: int, expected: str) -> None:
    assert enh(base, n) == expected


@pytest.mark.parametrize("base,n,expected", [
    ("Bottles on a shelf.", 8, "Eight similar bottles on a shelf."),
    ("A bottle on a shelf", 8, "Eight similar bottles on a shelf"),
    ("A bottle is on a shelf.", 8, "Eight similar bottles are on a shelf."),
    ("A dog sits on a bench", 2, "Two similar dogs sit on a bench"),
    ("Three dogs sit on a couch.", 4, "Four similar dogs sit on a couch."),
    ("The red bottles on a shelf.", 4, "The four similar red bottles on a shelf."),
    ("A man holding a knife", 2, "Two similar men holding a knife"),
    ("A child with a kite", 3, "Three similar children with a kite"),
    ("A sheep in a meadow", 5, "Five similar sheep in a meadow"),
    ("A woman walking in the rain", 2, "Two similar women walking in the rain"),
    ("A box next to a wall", 13, "Thirteen similar boxes next to a wall"),
    ("A church", 3, "Three similar churches"),
    ("A bush", 3, "Three similar bushes"),
    ("A fox", 3, "Three similar foxes"),
    ("A puppy", 3, "Three similar puppies"),
    ("A toy", 3, "Three similar toys"),
    ("A knife", 3, "Three similar knives"),
    ("A shelf", 3, "Three similar shelves"),
    ("A goose", 3, "Three similar geese"),
    ("A tooth", 3, "Three similar teeth"),
    ("A foot", 3, "Three similar feet"),
    ("A deer", 3, "Three similar deer"),
    ("A fish", 3, "Three similar fish"),
    ("A person", 3, "Three similar people"),
    ("A potato", 3, "Three similar potatoes"),
    ("A photo", 3, "Three similar photos"),
    ("A bus", 3, "Three similar buses"),
    ("a car", 25, "25 similar cars"),
])
def test_subject_noun_and_plural(base: str, n: int, expected: str) -> None:
    assert enh(base, n) == expected


@pytest.mark.parametrize("base,n,expected", [
    # bug report: the modifier in front of an -ing compound was taken as the head
    ("A row of red sleeping bags on the floor.", 4,
     "Four similar red sleeping bags on the floor."),
    ("A group of Italian racing cars on a track.", 4,
     "Four similar Italian racing cars on a track."),
    # same cause: colour / material / adjective / participle before an -ing or -ed word
    ("A line of blue shopping carts", 4, "Four similar blue shopping carts"),
    ("Several white folding chairs.", 4, "Four similar white folding chairs."),
    ("A stack of green drinking glasses", 4, "Four similar green drinking glasses"),
    ("A row of metal folding chairs", 4, "Four similar metal folding chairs"),
    ("A wood burning stove", 3, "Three similar wood burning stoves"),
    ("A group of similar racing cars", 4, "Four similar racing cars"),
    ("Two red sleeping bags", 3, "Three similar red sleeping bags"),
    ("A red sleeping bag on the floor.", 3, "Three similar red sleeping bags on the floor."),
    ("A row of old parked cars", 4, "Four similar old parked cars"),
    ("An old parked car near a house", 2, "Two similar old parked cars near a house"),
    ("A row of polished racing cars", 4, "Four similar polished racing cars"),
    # an -ing/-ed word after adjectives only is the head when nothing follows it
    ("A large gathering on the lawn", 3, "Three similar large gatherings on the lawn"),
    ("A small flowerbed in a garden", 3, "Three similar small flowerbeds in a garden"),
    # -ing compounds without a modifier (already right) and -ing nouns as heads
    ("Washing machines.", 4, "Four similar washing machines."),
    ("A row of folding chairs", 4, "Four similar folding chairs"),
    ("A row of tall buildings", 4, "Four similar tall buildings"),
    ("A tall building", 3, "Three similar tall buildings"),
    ("A painting", 3, "Three similar paintings"),
    ("A painting on a wall", 3, "Three similar paintings on a wall"),
    ("A ceiling fan", 3, "Three similar ceiling fans"),
    ("A ceiling", 2, "Two similar ceilings"),
    ("A row of paintings hanging on a wall", 5, "Five similar paintings hanging on a wall"),
    # after a noun an -ing/-ed word still starts a participle clause
    ("A dog eating food", 2, "Two similar dogs eating food"),
    ("A black cat sleeping on a bed", 2, "Two similar black cats sleeping on a bed"),
    ("An orange sitting on a table", 3, "Three similar oranges sitting on a table"),
    ("An Italian sitting on a bench", 2, "Two similar Italians sitting on a bench"),
    ("A snow covered mountain", 3, "Three similar snow covered mountains"),
    # a participle before punctuation ends the phrase at the noun before it
    ("Cars parked, waiting.", 3, "Three similar cars parked, waiting."),
    # a nationality adjective keeps its capital when the count goes in front of it
    ("Italian racing cars on a track.", 4, "Four similar Italian racing cars on a track."),
])
def test_modifiers_before_head_not_pluralised(base: str, n: int, expected: str) -> None:
    assert enh(base, n) == expected


def test_ing_compound_scene_sentence_uses_head_noun() -> None:
    assert enh("A row of red sleeping bags on the floor.", 4, ts=True) == (
        "Four similar red sleeping bags on the floor. The bags have a potential "
        "translation symmetry in 3D.")


@pytest.mark.parametrize("n,word", [(2, "Two"), (3, "Three"), (11, "Eleven"),
                                    (15, "Fifteen"), (19, "Nineteen"), (20, "Twenty"),
                                    (21, "21"), (30, "30")])
def test_number_words_and_digits(n: int, word: str) -> None:
    assert enh("A group of cups.", n) == f"{word} similar cups."
    assert G.count_word(n).capitalize() == word


def test_count_one_or_no_pattern_leaves_caption_unchanged() -> None:
    base = "A group of babies sitting on the couch."
    assert enh(base, 1, ts=True, vp_inside=False) == base
    assert C.enhance_caption(base, result()) == base
    assert C.enhance_caption("", result(pattern(4))) == ""
    assert C.enhance_caption("It is here.", result(pattern(4))) == "It is here."


def test_ts_and_vp_sentences() -> None:
    base = "Bottles on a shelf."
    assert enh(base, 8, ts=True, vp_inside=False) == (
        "Eight similar bottles on a shelf. The bottles have a potential translation "
        "symmetry in 3D and form a vanishing point outside of the image.")
    assert enh(base, 8, vp_inside=True) == (
        "Eight similar bottles on a shelf. The bottles form a vanishing point inside "
        "the image.")
    assert enh(base, 8, ts=True) == (
        "Eight similar bottles on a shelf. The bottles have a potential translation "
        "symmetry in 3D.")
    assert enh(base, 8, ts=False) == "Eight similar bottles on a shelf."
    # no final punctuation in the base: a full stop is added before the new sentence
    assert enh("A bottle on a shelf", 8, vp_inside=True) == (
        "Eight similar bottles on a shelf. The bottles form a vanishing point inside "
        "the image.")


def test_image_level_vp_not_claimed_for_the_pattern() -> None:
    # a VP of the image (from lines) is no fact about the objects: no VP sentence
    r = result(pattern(4))
    r.vanishing_point = VanishingPoint(np.array([1.0, 0.0, 0.0]), False)
    assert C.enhance_caption("A row of lamps.", r) == "Four similar lamps."


def test_capitalisation_kept_mid_sentence_and_proper_nouns() -> None:
    # the collective phrase wins over the first noun phrase and starts a sentence
    assert enh("Two photos. A group of Dalmatians.", 4) == "Two photos. Four similar Dalmatians."
    assert enh("On the table, a group of cups.", 4) == "On the table, four similar cups."


def test_multiple_patterns_fallback_dominant_on_first_noun() -> None:
    r = result(pattern(3, pid=0), pattern(7, pid=1, y0=100), dominant=1)
    out = C.enhance_caption("Bottles and cans on a shelf.", r)
    assert out == "Seven similar bottles and cans on a shelf."


def test_multiple_patterns_with_grounding() -> None:
    bottles = pattern(5, pid=0, x0=0, y0=0, ts=True)
    cans = pattern(3, pid=1, x0=0, y0=200)
    r = result(bottles, cans, dominant=0)
    boxes = {"bottles": (-1, -1, 200, 50), "cans": (-5, 190, 100, 40)}
    seen = []

    def ground(rgb: np.ndarray, noun: str):
        seen.append(noun)
        return boxes.get(noun)

    out = C.enhance_caption("Bottles and cans on a shelf.", r, grounding=ground, rgb=RGB)
    assert out == ("Five similar bottles and three similar cans on a shelf. The bottles "
                   "have a potential translation symmetry in 3D.")
    assert seen == ["bottles", "cans", "shelf"]  # heads, lower case
    # a box holding < 90 % of the instance area assigns nothing -> fallback
    boxes["cans"] = (0, 200, 30, 10)
    boxes["bottles"] = (0, 0, 20, 10)
    out2 = C.enhance_caption("Bottles and cans on a shelf.", r, grounding=ground, rgb=RGB)
    assert out2 == ("Five similar bottles and cans on a shelf. The bottles have a "
                    "potential translation symmetry in 3D.")


def test_grounding_gives_dominant_no_noun_skips_scene_sentence() -> None:
    r = result(pattern(5, pid=0, ts=True), pattern(3, pid=1, y0=200), dominant=0)
    out = C.enhance_caption("A cat near cans.", r, grounding=lambda rgb, n:
                            (0, 190, 100, 40) if n == "cans" else None)
    assert out == "A cat near three similar cans."


def test_pluralize_and_is_plural() -> None:
    assert G.pluralize("City") == "Cities"
    assert G.pluralize("bottles") == "bottles"
    assert G.pluralize("glass") == "glasses"
    assert G.is_plural("people") and not G.is_plural("bus")
    with pytest.raises(ValueError):
        G.count_word(-1)


def test_enhance_rejects_non_string() -> None:
    with pytest.raises(TypeError, match="base"):
        C.enhance_caption(None, result(pattern(3)))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- captioners
def test_example_box_that_found_nothing_else_is_said_so() -> None:
    """"Count these" with one example box and no other find: the caption speaks of the
    example, not of a discovery that found no pattern; an unprompted pattern of one
    instance still reads "No recurring pattern found."."""
    asked = pattern(1)
    asked.extra["source"] = "prompt"
    t = C.TemplateCaptioner()
    r = result(asked)
    assert t.caption(RGB, r, "x.jpg") == "Nothing else like the example box was found."
    out = C.caption_result(RGB, r, "x.jpg", t, C.CaptionParams())
    assert out == {"base": "Nothing else like the example box was found.",
                   "enhanced": "Nothing else like the example box was found."}
    assert C.summary_line(r) == "1 instance: nothing else like the example box"
    # a captioner's own sentence keeps it, followed by what was (not) found
    other = C.caption_result(RGB, r, "x.jpg", type("Cap", (), {
        "caption": lambda self, *a: "A tank of fish."})(), C.CaptionParams())
    assert other["base"] == "A tank of fish. Nothing else like the example box was found."
    assert t.caption(RGB, result(pattern(1)), "x.jpg") == "No recurring pattern found."


def test_template_captioner_layouts() -> None:
    t = C.TemplateCaptioner()
    assert t.caption(RGB, result(pattern(5)), "x.jpg") == "A group of similar objects in a row."
    assert t.caption(RGB, result(pattern(9, grid=True)), "x.jpg") == \
        "A group of similar objects arranged in a grid."
    col = Pattern(0, 1.0, [Instance((0, 20 * i, 10, 10)) for i in range(4)])
    assert t.caption(RGB, result(col), "x.jpg") == "A group of similar objects in a column."
    assert t.caption(RGB, result(), "x.jpg") == "No recurring pattern found."
    lay = pattern(9, grid=True)
    lay.extra["layout"] = "row"
    assert C.infer_layout(lay) == "row"
    two = t.caption(RGB, result(pattern(5), pattern(3, pid=1, y0=100)), "x.jpg")
    assert two == "A group of similar objects in a row, next to other repeated items."
    r = result(pattern(5, ts=True))
    out = C.caption_result(RGB, r, "x.jpg", t, C.CaptionParams())
    assert out == {"base": "A group of similar objects in a row.",
                   "enhanced": "Five similar objects in a row. The objects have a "
                               "potential translation symmetry in 3D."}


def test_csv_captioner(tmp_path: Path) -> None:
    p = tmp_path / "caps.csv"
    p.write_text('image,caption\nimages/a.jpg,"A herd of llamas, standing."\nb,Bottles on '
                 'a shelf.\n\n')
    logs: list[str] = []
    c = C.CsvCaptioner(p, log=logs.append)
    assert c.caption(RGB, result(pattern(3)), "a.jpg") == "A herd of llamas, standing."
    assert c.caption(RGB, result(pattern(3)), "images/a.jpg") == "A herd of llamas, standing."
    assert c.caption(RGB, result(pattern(3)), "images/b.png") == "Bottles on a shelf."
    # missing image -> template fallback, logged
    assert c.caption(RGB, result(pattern(3)), "zzz.jpg") == \
        "A group of similar objects in a row."
    assert logs and "zzz.jpg" in logs[0] and str(p) in logs[0]
    strict = C.CsvCaptioner(p, fallback=None)
    strict.fallback = None
    with pytest.raises(C.CaptionMissing):
        strict.caption(RGB, result(), "zzz.jpg")
    out = C.caption_result(RGB, result(pattern(6)), "a.jpg", c)
    assert out == {"base": "A herd of llamas, standing.",
                   "enhanced": "Six similar llamas, standing."}


@pytest.mark.parametrize("text,msg", [
    ("name,text\na,b\n", "columns 'image' and 'caption'"),
    ("image,caption\na,b,c\n", "line 2 has 3 fields"),
    ('image,caption\n"a,b\n', "malformed caption CSV"),
    ("", "empty"),
    ("image,caption\n,cap\n", "empty 'image'"),
])
def test_csv_captioner_malformed_names_file(tmp_path: Path, text: str, msg: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        C.CsvCaptioner(p)
    assert str(p) in str(e.value) and msg in str(e.value)


def test_csv_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        C.make_captioner(C.CaptionParams(captioner="csv",
                                         csv_path=str(tmp_path / "none.csv")))


def test_transformers_unavailable_falls_back(monkeypatch: pytest.MonkeyPatch) -> None:
    real_import = builtins.__import__

    def fake_import(name, *a, **k):
        if name == "transformers" or name.startswith("transformers."):
            raise ImportError("No module named 'transformers'")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(C.CaptionerUnavailable, match="pip install transformers"):
        C.TransformersCaptioner("Salesforce/blip-image-captioning-base")
    logs: list[str] = []
    cap = C.make_captioner(C.CaptionParams(captioner="transformers"), log=logs.append)
    assert isinstance(cap, C.TemplateCaptioner)
    assert len(logs) == 1 and "falling back to the template captioner" in logs[0]
    assert C.make_grounder(C.CaptionParams(grounding_model="owlvit"), log=logs.append) is None
    assert len(logs) == 2 and "owlvit" in logs[1]
    assert C.make_grounder(C.CaptionParams()) is None


def test_params_from_dict() -> None:
    p = C.CaptionParams.from_dict({"captioner": "csv", "csv_path": "c.csv", "seed": 3,
                                   "grounding_model": None})
    assert (p.captioner, p.csv_path, p.seed, p.grounding_model) == ("csv", "c.csv", 3, "")
    with pytest.raises(ValueError, match="bogus"):
        C.CaptionParams.from_dict({"bogus": 1})
    with pytest.raises(ValueError, match="captioner"):
        C.CaptionParams(captioner="gpt")
    assert isinstance(C.make_captioner(C.CaptionParams()), C.TemplateCaptioner)


def test_caption_result_checks_rgb() -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        C.caption_result(np.zeros((4, 4)), result(), "x.jpg", C.TemplateCaptioner())


def test_deterministic() -> None:
    r = result(pattern(6, ts=True, vp_inside=False))
    outs = {C.enhance_caption("A herd of llamas.", r) for _ in range(3)}
    assert len(outs) == 1
