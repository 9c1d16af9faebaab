"""A run file's environments are the application's own type: the schema's slots
(`reachwatch.diagrams.schemas`) take the environment and random family the application
names, with its defaults, its field errors and its notion of one environment; the
taxi's runways are only the default application's."""

import dataclasses as dc
import pickle
import re
import textwrap

import pytest

from reachwatch.diagrams import ScenarioError
from reachwatch.diagrams.schemas import ApplicationEnvironment, typed_schema, untyped
from reachwatch.pipeline.spec import RunSpec, dump_run_spec, load_run_spec
from reachwatch.systems import Environment, RandomEnvironments

from test_examples import ROOT, _run_to_report, _tiny
from tiny_run import TINY

LAB = '''
import dataclasses as dc

from reachwatch.reach import Grid
from reachwatch.reach.application import Application


@dc.dataclass
class Lab:
    """A lab's light: how bright, and whether the blinds are down."""
    name: str = "lab"
    brightness: float = 1.0
    blinds: bool = False

    def validate(self):
        if not 0.0 <= self.brightness <= 1.0:
            raise ValueError(f"brightness must be in [0, 1], got {self.brightness}")
        return self


class LabApplication(Application):
    """Known by its run file's types alone (no loop is built here)."""
    name = "lab"
    axes = ("y", "theta")
    environment_type = Lab

    def default_environment(self, role):
        return Lab(name=f"{role}_lab", brightness=0.5)

    def loop_diagram(self, scenario, *, guarded=False):
        raise AssertionError("no loop here")

    def probe(self, scenario, *, guarded=False):
        raise AssertionError("no loop here")

    def dynamics(self, scenario):
        raise AssertionError("no loop here")

    def grid(self, scenario, shape, **widen):
        return Grid(lo=[-1.0, -1.0], hi=[1.0, 1.0], shape=shape)

    def rolls_out_fallbacks(self, scenario):
        return False                    # the guard stage is skipped


class Untyped(LabApplication):
    environment_type = None


class AnInstance(LabApplication):
    environment_type = Lab()


@dc.dataclass
class Needy:
    name: str


class NeedsAName(LabApplication):
    environment_type = Needy
'''

RUN = """
application: labapp:LabApplication
train: [{name: bright, brightness: 0.9}, {name: dim, brightness: 0.2, blinds: true}]
test: [{name: dark, brightness: 0.0}]
grid: [5, 5]
ensemble: {seeds: []}
incremental: {enabled: false}
"""


@pytest.fixture
def lab(tmp_path, monkeypatch):
    (tmp_path / "labapp").mkdir()
    (tmp_path / "labapp" / "__init__.py").write_text(textwrap.dedent(LAB))
    monkeypatch.syspath_prepend(str(tmp_path))
    import labapp
    return labapp


def test_a_run_files_environments_are_the_applications_type(lab):
    spec = load_run_spec(data=RUN)
    assert type(spec) is RunSpec                 # the generic classes, not the typed ones
    assert [type(e) for e in spec.train + spec.test] == [lab.Lab] * 3
    assert spec.train[1] == lab.Lab("dim", 0.2, True)
    assert [e.name for e in spec.all_environments()] == ["bright", "dim", "dark"]
    assert spec.incremental.environment == lab.Lab("incremental_lab", 0.5)   # its default
    assert spec.train_random.count == 0 and spec.train_random.environments() == []
    assert load_run_spec(data=dump_run_spec(spec)) == spec
    pickle.loads(pickle.dumps(spec))            # what travels to workers


@pytest.mark.parametrize("change, message", [
    ("train: [{name: a, runway: KMWH}]", r"run.train\[0\].runway: unknown field of Lab; "
                                         r"known fields: name, brightness, blinds"),
    ("train: [{name: a, brightness: 2.0}]", r"train\[0\]: brightness must be in \[0, 1\], got 2.0"),
    ("train_random: {count: 2}", r"train_random.count: this application draws no random "
                                 r"environments; list its environments instead"),
    ("monitor: {kind: history}", r"monitor: the study trains, calibrates and judges on "
                                 r"environments drawn from the application's random family, "
                                 r"and this application draws none"),
    ("test: [{name: bright, brightness: 0.1}]", r"train\[0\] and test\[0\] are both named "
                                                r"'bright' but differ; give one of them "
                                                r"another name"),
    ("application: labapp:Untyped", r"application 'lab' sets no environment_type"),
    ("application: labapp:AnInstance", r"application 'lab': environment_type must be a "
                                       r"dataclass \(the class itself\), got Lab"),
    ("application: labapp:NeedsAName", r"application 'lab': environment_type Needy must give "
                                       r"every field a default"),
])
def test_a_bad_environment_is_one_line_in_the_applications_terms(lab, change, message):
    key = change.partition(":")[0]
    text = "\n".join(line for line in RUN.splitlines() if not line.startswith(f"{key}:"))
    with pytest.raises(ScenarioError, match=message) as e:
        load_run_spec(data=f"{text}\n{change}\n")
    assert "\n" not in str(e.value)


def test_overlays_in_order_take_the_schema_of_the_application_they_name(lab, tmp_path):
    """An overlay that names another application checks the overlays after it, and a
    text overlay's own keys, against that application's environments."""
    from argparse import Namespace

    from reachwatch.pipeline.commands import scenario_from_args
    from reachwatch.pipeline.overlays import Overlay
    path = tmp_path / "taxi.yaml"
    path.write_text("train: [{runway: KMWH}]\ntest: [{runway: KSFO}]\n")
    lab_run = "{application: 'labapp:LabApplication', train: [{name: a}], test: [{name: b}], " \
              "grid: [5, 5], ensemble: {seeds: []}, incremental: {enabled: false}}"
    overlays = [Overlay("text", lab_run, "--run-text"),
                Overlay("set", "train[0].brightness=0.3", "--set")]
    spec = scenario_from_args(Namespace(scenario=str(path), overlays=overlays),
                              schema=RunSpec, root="run")
    assert spec.train == [lab.Lab("a", 0.3)] and spec.test == [lab.Lab("b")]


@pytest.mark.parametrize("change, message", [
    ("{incremental: {environment: {runway: KMWH, hour: 9.0}}}",
     r"incremental.environment 'KMWH_9h_clear' is a training environment; the fine-tuned "
     r"controller is judged on a held-out one"),
    ("{train_random: {count: 13, seed: 11}, monitor: {kind: history}}",
     r"monitor: the study would judge the detector on environments it trained on "
     r"\(\['RND11-12_"),
    ("{train: [{runway: KSFO, hour: 21.0}], test: [{runway: KMWH}], monitor: {kind: history, "
     "also_held_out: [{runway: KSFO, hour: 21.0}]}}",
     r"monitor: the study would judge the detector on environments it trained on "
     r"\(\['KSFO_21h_clear'\]\)"),
])
def test_environments_judged_as_held_out_must_not_be_trained_on(change, message):
    from reachwatch.diagrams import load_scenario
    from reachwatch.pipeline.overlays import Overlay, Overlays
    text = "train: [{runway: KMWH}]\ntest: [{runway: KSFO}]\n"
    with pytest.raises(ScenarioError, match=message):
        load_scenario(data=text, schema=RunSpec, root="run",
                      edit=Overlays([Overlay("text", change, "--run-text")]))


def test_an_environment_type_in_the_applications_own_file_is_refused(tmp_path):
    """Environments travel to workers inside scenarios, by their module's name: a class
    defined in the application's own file (imported by path) cannot."""
    (tmp_path / "own.py").write_text(textwrap.dedent(LAB))
    with pytest.raises(ScenarioError, match=r"application 'lab': environment_type Lab must be "
                                            r"a dataclass defined at the top of an importable "
                                            r"module"):
        load_run_spec(data=RUN.replace("labapp:LabApplication",
                                       f"{tmp_path / 'own.py'}:LabApplication"))


def test_the_taxi_is_the_default_applications_types():
    spec = load_run_spec(data="train: [{runway: KMWH}]\ntest: [{runway: KSFO, hour: 21.0}]\n")
    assert type(spec.train[0]) is Environment and type(spec.train_random) is RandomEnvironments
    assert spec.monitor.family == RandomEnvironments(seed=11)
    assert spec.incremental.environment == Environment("KMWH", 17.0, "clear")
    # a spec built in code takes the default application's defaults too
    assert RunSpec().monitor.family == spec.monitor.family
    with pytest.raises(ScenarioError, match=r"run.train\[0\].name: unknown field of Environment"):
        load_run_spec(data="train: [{name: lab}]\ntest: [{runway: KSFO}]\n")


def _ksfo(slot, role):
    return lambda: Environment(runway="KSFO")


def test_typed_schema_replaces_slots_and_nothing_else():
    @dc.dataclass
    class Inner:
        where: ApplicationEnvironment = dc.field(default_factory=lambda: "generic",
                                                 metadata={"reachwatch.application_role": "x"})
        count: int = 3

    @dc.dataclass
    class Outer:
        inner: Inner = dc.field(default_factory=Inner)
        plain: int = 1

    types = ((ApplicationEnvironment, Environment),)
    typed = typed_schema(Outer, types, _ksfo)
    assert typed is typed_schema(Outer, types, _ksfo)       # made once
    assert issubclass(typed, Outer) and typed.__name__ == "Outer"
    assert [f.name for f in dc.fields(typed)] == ["inner", "plain"]
    made = typed()
    assert made.inner.where == Environment(runway="KSFO") and made.inner.count == 3
    back = untyped(made)
    assert type(back) is Outer and type(back.inner) is Inner and back.inner.where.runway == "KSFO"
    assert typed_schema(Inner, (), _ksfo) is Inner     # nothing to replace: the class itself


def _guide_code(name: str) -> str:
    """The Python block of the own-plant guide that defines ``name``: the test runs the
    code the guide shows."""
    text = (ROOT / "docs" / "guides" / "own-plant.md").read_text()
    return next(b for b in re.findall(r"```python\n(.*?)```", text, re.S) if name in b)


ROOM_CART = _guide_code("class RoomCart(")


def test_an_application_with_environments_of_its_own_runs_to_a_report(tmp_path, monkeypatch):
    """The pipeline and the report know an environment by its name alone: the cart
    with rooms for environments (no runway anywhere in its run file) goes from its run
    file to a report."""
    monkeypatch.chdir(ROOT)                    # the cart's paths are relative
    (tmp_path / "roomcart").mkdir()
    (tmp_path / "roomcart" / "__init__.py").write_text(ROOM_CART)
    monkeypatch.syspath_prepend(str(tmp_path))
    text = (ROOT / "examples" / "cart" / "run.yaml").read_text().replace(
        "application: examples/cart/application.py:CartApplication",
        "application: roomcart:RoomCart")
    start, end = text.index("\ntrain:\n"), text.index("\ngrid:")
    text = (text[:start] + "\ntrain: [{name: morning, hour: 9.0}]\n"
            "test: [{name: evening, hour: 19.5, sky: overcast}]" + text[end:])
    assert not [line for line in text.splitlines()
                if "runway" in line and not line.startswith("#")]
    spec = _tiny(load_run_spec(data=text))
    assert type(spec.test[0]).__name__ == "Room"
    spec.grid, spec.horizon, spec.dataset.samples = [5, 5], 2.0, 10
    spec.scenario.camera.height, spec.scenario.camera.width = 24, 48
    spec.guard.candidates = spec.guard.noise_starts = spec.guard.check_starts = 0
    spec.fidelity.starts = 0
    out = _run_to_report(spec, tmp_path)
    report = (out / "report.md").read_text()
    assert "| evening | test | 5x5 | 25 |" in report and "KMWH" not in report
    assert (out / "stages" / "guard_evening.json").is_file()


@pytest.mark.parametrize("scenario, said", [
    ("{monitor: {threshold: 1.5}}", r"^<yaml>: scenario\.monitor\.threshold must be"),
    ("{camera: {width: -3}}", r"^<yaml>: scenario\.camera\.width must be"),
    ("{duration: -1}", r"^<yaml>: scenario\.duration must be"),
])
def test_a_run_files_scenario_errors_name_the_key_from_the_files_top(scenario, said):
    """A run file has a ``monitor:`` of its own (the study) beside
    ``scenario.monitor`` (the guard's): a scenario's error names its key from the
    run file's top, so the reader looks in the right block."""
    with pytest.raises(ValueError, match=said):
        load_run_spec(data=TINY + f"scenario: {scenario}\n")
