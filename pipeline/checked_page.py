"""The page a slice of a run writes (``OUT/checked.html`` and ``checked.md``): the
report's fidelity section over every environment of the run whose check is on record
for the run file as it is now, from this slice, an earlier one or a whole run, and the
environments still to check. A study run in slices so reads its per-environment
figures as they come, and they are the figures the whole run will report.

A record counts when its key is the one the run would compute now, all the way down:
the sweep's content key and its table as cached, the solve's, the dataset's
content-addressed folder (with a manifest) and the check's settings. Nothing is
rendered to find out."""

import json

from reachwatch.systems.files import atomic_write_bytes

from .brt_stages import solve_stage_key
from .fidelity_stages import fidelity_stage_key
from .dataset_stages import dataset_folder_for, ensemble_paths
from .fidelity_sections import fidelity_section, labels_meet_target
from .report import Page, environment_roles
from .stages import Run


def checked_environments(run: Run) -> dict:
    """Every environment of the run by what its fidelity record says now:
    ``{"checks": {name: fidelity_env outputs}, "labels": {name: the dataset's label
    record}, "stale": {name: why}, "unchecked": [names]}``. ``stale``: a record is
    there, but for other inputs (the run file changed since, or a file it names did),
    with the first input found different."""
    spec = run.spec
    labelled = {e.name for e in spec.training_environments() + spec.held_out_environments()}
    ensemble = ensemble_paths(run)
    ensemble_ready = all(p.is_file() for p in ensemble)
    checks, labels, stale, unchecked = {}, {}, {}, []
    for env in spec.all_environments():
        if not run.path(f"stages/fidelity_{env.name}.json").is_file():
            unchecked.append(env.name)
            continue
        solve = run.recorded(f"solve_{env.name}", solve_stage_key(run, env))
        folder, manifest = None, None
        if solve is None:
            stale[env.name] = "its BRT is not the run file's (sweep or solve inputs changed)"
            continue
        if env.name in labelled:
            if not ensemble_ready:
                stale[env.name] = "the ensemble's checkpoints, which its dataset's folder " \
                                  "depends on, are not in ensemble/"
                continue
            folder = dataset_folder_for(run, env, run.path(solve["outputs"]["value"]), ensemble)
            path = run.path(folder) / "manifest.json"
            if not path.is_file():
                stale[env.name] = f"its dataset ({folder}) is not there"
                continue
            manifest = json.loads(path.read_text())
        record = run.recorded(f"fidelity_{env.name}", fidelity_stage_key(run, solve, folder))
        if record is None:
            stale[env.name] = "the check's settings or its dataset changed"
            continue
        checks[env.name] = record["outputs"]
        if manifest is not None:
            labels[env.name] = {**manifest["labels"], "counts": manifest["label_counts"]}
    return {"checks": checks, "labels": labels, "stale": stale, "unchecked": unchecked}


def write_checked_page(run: Run) -> dict:
    """Write ``checked.html`` and ``checked.md`` (`checked_environments`); returns their
    paths (relative), the environments by state, those whose labels were checked
    (``labelled``) and those whose labels meet the report's target."""
    spec, found = run.spec, checked_environments(run)
    total = len(spec.all_environments())
    page = Page(f"reachwatch run '{spec.name}': the environments checked so far")
    page.text(f"{len(found['checks'])} of the run's {total} environments have a real-loop "
              f"check on record for the run file as it is now (from any slice of the run, or "
              f"a whole run, in this directory); their figures are the ones the whole run "
              f"reports.")
    if found["stale"]:
        page.text("On record for other inputs (the run file or a file a record names changed "
                  "since; running them again brings them up to date): " + "; ".join(
                      f"{n} ({why})" for n, why in found["stale"].items()) + ".")
    if found["unchecked"]:
        page.text(f"Not checked yet: {', '.join(found['unchecked'])}.")
    if found["checks"]:
        fidelity_section(page, spec, found["checks"], found["labels"], environment_roles(spec))
    text_html, text_md = page.done()
    labelled = [n for n, r in found["checks"].items() if "labels" in r]
    return {"html": run.rel(atomic_write_bytes(run.path("checked.html"), text_html.encode())),
            "md": run.rel(atomic_write_bytes(run.path("checked.md"), text_md.encode())),
            **{k: list(found[k]) for k in ("checks", "stale", "unchecked")},
            "labelled": labelled,
            "labels_meet_target": [n for n in labelled
                                   if labels_meet_target(found["checks"][n])]}
