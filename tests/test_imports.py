"""rescu_workflow.code_deps: the package's import graph, and the library files each workflow step
runs (the rules' code dependencies)."""

from pathlib import Path

import pytest

from rescu_workflow.code_deps import import_closure, step_dependencies

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "workflow" / "scripts"


def _names(files):
    return {str(p.relative_to(REPO / "rescu")) for p in files}


def test_closure_follows_imports_at_any_depth():
    names = _names(import_closure(["rescu.scene.analyse"]))
    assert {"scene/analyse.py", "scene/symmetry.py", "layout.py", "types.py"} <= names
    assert not any(n.startswith(("discovery/", "extension/")) for n in names), names
    with pytest.raises(KeyError, match="rescu.nope"):
        import_closure(["rescu.nope"])


def test_each_step_depends_on_its_own_modules_only():
    dep = {s.stem: _names(step_dependencies(s)) for s in SCRIPTS.glob("*.py")}
    assert {"pipeline.py", "scene/analyse.py", "scene/completion.py",
            "scene/symmetry.py"} <= dep["scene"]
    assert not any(n.startswith(("discovery/", "extension/")) for n in dep["scene"])
    assert {"discovery/stage1.py", "discovery/search.py", "discovery/urp.py"} <= dep["stage1"]
    # RESCU-I scores its RPs with the dense source's backbone map (dense.mode objects),
    # nothing of stage II or the scene (the map itself, hypercolumn, is in the turned module)
    scoring = {"extension/dense.py", "extension/objects.py", "extension/contrast_extent.py",
               "extension/boxmaps.py", "extension/backbone.py", "extension/turned.py",
               "extension/linkage.py"}
    assert not any(n.startswith(("scene/", "extension/")) and n not in scoring
                   for n in dep["stage1"]), dep["stage1"]
    assert "discovery/features.py" in dep["features"]
    assert not any(n.startswith("extension/") for n in dep["features"] | dep["caption"])
    assert "extension/backbone.py" in dep["stage2_features"]
    assert "extension/train.py" in dep["stage2_features"]  # the head is trained in the same job
    assert "captions/caption.py" in dep["caption"]
    assert "data/synth.py" in dep["generate_synthetic"]
    for stem, files in dep.items():
        assert "pipeline.py" in files, stem  # every adapter logs through the pipeline


def test_evaluation_sits_above_the_stages():
    """Only the evaluation itself and the command line (which runs its tables) import
    ``rescu.evaluation``; the stages measure box overlaps with ``rescu.boxes``, which
    imports nothing of the package."""
    from rescu_workflow.code_deps import import_graph

    graph = import_graph()
    allowed = ("rescu.evaluation", "rescu.cli")
    bad = {m: sorted(t for t in edges if t == "rescu.evaluation"
                     or t.startswith("rescu.evaluation."))
           for m, edges in graph.items()
           if not (m == allowed[1] or m == allowed[0] or m.startswith(allowed[0] + "."))}
    assert not {m: t for m, t in bad.items() if t}, bad
    assert graph["rescu.boxes"] == {}
    assert "rescu.evaluation.diagnostics" not in graph     # lives in benchmarks/
