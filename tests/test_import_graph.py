"""The import graph, read from the source (every import statement, those inside
functions too): the layers systems -> diagrams -> reach -> training -> pipeline only
import downwards, and the generic core knows nothing about the taxi: no module of
reach/, training/, the generic parts of systems/ and diagrams/ or the pipeline's
stage engine imports `reachwatch.taxi` or a taxi-specific module of systems/ (in any
form: absolute, relative, ``from reachwatch import taxi``). What the taxi needs
there goes through its application (`reachwatch.reach.application`)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Lowest first; a module may import its own layer and those below it. The taxi is an
#: application beside training: built on reach, diagrams and systems, imported by none
#: of the generic core.
LAYERS = {"systems": 0, "diagrams": 1, "reach": 2, "taxi": 3, "training": 3, "pipeline": 4}

#: The modules of systems/ that are the taxi's: its plant and kinematics, TaxiNet and
#: its networks, the runway, its scene, lights and environments, the aircraft's camera.
TAXI_SYSTEMS = {"plant", "taxinet", "models", "runway", "environment", "random_environments",
                "scene", "lighting", "camera", "dead_reckoning"}

#: The pipeline's front ends (argument parsing and one-off commands), not its stage
#: engine: they may call the taxi directly.
FRONT_ENDS = {"cli", "commands", "reference", "guard_commands", "reach_commands",
              "simulate_commands", "taxinet_commands", "evaluate_commands", "run_commands"}

def _modules():
    for package in LAYERS:
        for path in sorted((ROOT / package).glob("*.py")):
            yield package, path.stem, path


def _exports(package: str) -> dict:
    """``{name: module}`` of what ``package/__init__.py`` re-exports from its modules."""
    tree = ast.parse((ROOT / package / "__init__.py").read_text())
    return {alias.asname or alias.name: node.module for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module
            for alias in node.names}


EXPORTS = {package: _exports(package) for package in LAYERS}


def _target(package: str, rest: str, names=()):
    """``(package, module)`` pairs an import of ``reachwatch.package[.rest]`` (names
    ``names`` from it) reaches; module None for the package alone."""
    if rest:
        return [(package, rest.split(".")[0])]
    found = []
    for name in names:
        if (ROOT / package / f"{name}.py").is_file():
            found.append((package, name))
        else:
            found.append((package, EXPORTS[package].get(name)))
    return found or [(package, None)]


def imports(package: str, path: Path):
    """``(line, package, module)`` of every reachwatch module ``path`` imports."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "reachwatch" and len(parts) > 1 and parts[1] in LAYERS:
                    out += [(node.lineno, *t) for t in _target(parts[1], ".".join(parts[2:]))]
        elif isinstance(node, ast.ImportFrom):
            names = [a.name for a in node.names]
            if node.level == 1:
                if node.module:
                    out += [(node.lineno, *t) for t in _target(package, node.module)]
                else:
                    out += [(node.lineno, *t) for t in _target(package, "", names)]
            elif node.level >= 2 or node.module == "reachwatch":
                # ``from ..taxi import x`` / ``from .. import taxi`` / ``from reachwatch
                # import taxi``: the package named first, or each package named (a level
                # above 2 is outside the package: nothing of it)
                parts = node.module.split(".") if node.level == 2 and node.module else []
                if parts and parts[0] in LAYERS:
                    out += [(node.lineno, *t) for t in _target(parts[0], ".".join(parts[1:]),
                                                              names)]
                elif not parts and node.level <= 2:
                    out += [(node.lineno, name, None) for name in names if name in LAYERS]
            elif node.module and node.module.split(".")[0] == "reachwatch":
                parts = node.module.split(".")
                if len(parts) > 1 and parts[1] in LAYERS:
                    out += [(node.lineno, *t) for t in _target(parts[1], ".".join(parts[2:]),
                                                              names)]
    return out


#: The modules of diagrams/ that build the taxi's diagrams (its world, camera, TaxiNet,
#: the built-in scenario) or read its checkpoints; the rest of diagrams/ is generic.
TAXI_DIAGRAMS = {"checkpoints", "closed_loop", "contact_sheet", "controller", "guarded",
                 "render", "scenario", "world"}


def _generic(package: str, module: str) -> bool:
    """Whether a module belongs to the generic core that must not know the taxi."""
    if package == "systems":
        return module not in TAXI_SYSTEMS and module != "__init__"
    if package == "diagrams":
        return module not in TAXI_DIAGRAMS and module != "__init__"
    if package in ("reach", "training"):
        return True
    return package == "pipeline" and module not in FRONT_ENDS


def _taxi(package: str, module) -> bool:
    return package == "taxi" or (package == "systems" and module in TAXI_SYSTEMS)


def test_the_layers_only_import_downwards():
    wrong = [f"{package}/{module}.py:{line} imports reachwatch.{to}"
             f"{'.' + str(what) if what else ''}"
             for package, module, path in _modules()
             for line, to, what in imports(package, path)
             if LAYERS[to] > LAYERS[package] or (package, to) in (("taxi", "training"),
                                                                    ("training", "taxi"))]
    assert not wrong, "\n".join(wrong)


def test_the_generic_core_imports_no_taxi_code():
    wrong = [f"{package}/{module}.py:{line} imports reachwatch.{to}.{what}"
             for package, module, path in _modules() if _generic(package, module)
             for line, to, what in imports(package, path) if _taxi(to, what)]
    assert not wrong, "\n".join(wrong)


def test_the_reader_sees_what_it_must(tmp_path):
    """The parser itself: re-exports, relative and lazy imports are resolved to the
    module that defines the name."""
    path = tmp_path / "probe.py"
    path.write_text("from reachwatch.systems import TaxiPlant, checks\n"
                    "from .stages import Run\n"
                    "def f():\n    import reachwatch.taxi.fidelity\n"
                    "from ..taxi import paper_grid\n"
                    "from ..systems.runway import RUNWAYS\n"
                    "from reachwatch import taxi, training\n"
                    "from .. import reach\n")
    found = {(to, what) for _, to, what in imports("pipeline", path)}
    assert found == {("systems", "plant"), ("systems", "checks"), ("pipeline", "stages"),
                     ("taxi", "fidelity"), ("taxi", "grid"), ("systems", "runway"),
                     ("taxi", None), ("training", None), ("reach", None)}
    assert all(_taxi(to, what) for to, what in [("taxi", None), ("taxi", "grid")])


#: Modules the monitor study's code imports that stay out of its key, and why.
OUTSIDE_STUDY_KEY = {
    "pipeline.monitor_sections": "the study uses its rate_text in log lines only",
    "reach.application": "the application's code has its own part of the key",
    "reach.fingerprint": "it computes the key",
}


def test_the_monitor_study_key_covers_the_training_code_it_imports():
    """`STUDY_CODE` (the source in the monitor stage's key) names every module of
    training/ and of the pipeline's monitor_* that its modules import, directly or
    through each other, and every module of reach/ those import (not further: reach/
    reaches the whole loop, keyed apart): such a module cannot stay outside the key by
    being forgotten there (`training.metrics`, its AUROC, and `reach.outcomes`, the
    time-to-failure labels, were). systems/ and diagrams/ are not walked."""
    from reachwatch.pipeline.monitor_study import STUDY_CODE
    code = {name.removeprefix("reachwatch.") for name in STUDY_CODE}
    seen = _walked(code, lambda to, what: to == "training" or (
        to == "pipeline" and what.startswith("monitor")), reach_once=True)
    missing = sorted(seen - code - set(OUTSIDE_STUDY_KEY))
    assert not missing, f"add to pipeline.monitor_study.STUDY_CODE: {missing}"
    assert set(OUTSIDE_STUDY_KEY) <= seen, "OUTSIDE_STUDY_KEY names a module no longer used"


def _walked(code, follows=lambda to, what: to == "training" or (
        to == "pipeline" and what.endswith(("_stage", "_stages"))), reach_once=False) -> set:
    """The modules ``code`` import, directly or through each other, where ``follows(to,
    module)`` (default: training/ and the pipeline's stage modules, ``*_stage``,
    ``*_stages``); with ``reach_once``, also each reach/ module those outside reach/
    import, not followed further (reach/ reaches the whole loop, keyed apart)."""
    seen, todo = set(), sorted(code)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        package, module = name.split(".")
        for _, to, what in imports(package, ROOT / package / f"{module}.py"):
            if what and follows(to, what):
                todo.append(f"{to}.{what}")
            elif what and reach_once and to == "reach" and package != "reach":
                seen.add(f"{to}.{what}")
    return seen


def _stage_codes():
    from reachwatch.pipeline.brt_stages import SOLVE_CODE
    from reachwatch.pipeline.detector_stages import DETECTOR_CODE, WEIGHTS_CODE
    from reachwatch.pipeline.fidelity_stages import FIDELITY_CODE
    from reachwatch.pipeline.incremental_stage import INCREMENTAL_CODE
    from reachwatch.pipeline.online_stages import GUARD_CODE
    return {"SOLVE_CODE": SOLVE_CODE, "DETECTOR_CODE": DETECTOR_CODE,
            "WEIGHTS_CODE": WEIGHTS_CODE, "FIDELITY_CODE": FIDELITY_CODE,
            "INCREMENTAL_CODE": INCREMENTAL_CODE, "GUARD_CODE": GUARD_CODE}


def test_every_stage_key_covers_the_training_and_stage_code_it_imports():
    """Each stage's code tuple (the source in its key) names every module of training/
    and every stage module of the pipeline that its modules import, directly or through
    each other, so that an edit there runs the stage again instead of keeping figures
    of the old code. reach/, systems/ and diagrams/ are not walked: they are loop code,
    in every BRT's key."""
    missing = {name: sorted(_walked({m.removeprefix("reachwatch.") for m in code})
                            - {m.removeprefix("reachwatch.") for m in code})
               for name, code in _stage_codes().items()}
    assert not any(missing.values()), f"add to the stage's code tuple: {missing}"


def test_the_stage_walk_finds_what_a_tuple_misses():
    """The walk itself: `pipeline.detector_stages` alone reaches the training modules
    `DETECTOR_CODE` lists beside it, and the incremental stage reaches the stages it
    calls."""
    assert {"training.detector_train", "training.metrics", "training.evaluation"} <= \
        _walked({"pipeline.detector_stages"})
    assert {"pipeline.brt_stages", "pipeline.online_stages"} <= \
        _walked({"pipeline.incremental_stage"})
