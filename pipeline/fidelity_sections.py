"""The report's fidelity section: the BRT, its swept table and the labels against the
real Drake loop per environment, and the label target each environment is judged
against (the whole run's report and a slice's page both draw it)."""

import numpy as np

from reachwatch.reach import wilson_interval
from reachwatch.reach.application import load_application
from reachwatch.training.dataset import label_frames
from reachwatch.training.labels import labels_every_state_by_its_run


def _rate(record, name):
    """``"x.x [lo, hi]"`` (%) of a `Fidelity.as_dict` rate with its interval."""
    lo, hi = record[f"{name}_ci95"]
    return f"{100 * record[f'{name}_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def monte_carlo(record) -> str:
    """The failure set over the check's starts of a `fidelity_env` record: the BRT
    map's share of the check starts and the real loop's (a Monte-Carlo estimate), each with its 95 %
    Wilson interval."""
    n, brt = record["brt"]["n"], record["brt"]
    (a, b), (c, d) = (wilson_interval(brt["predicted_failures"], n),
                      wilson_interval(brt["real_failures"], n))
    return (f"map {100 * brt['predicted_failures'] / n:.1f} [{100 * a:.1f}, {100 * b:.1f}] %, "
            f"real loop {100 * brt['real_failures'] / n:.1f} [{100 * c:.1f}, {100 * d:.1f}] % "
            f"({brt['real_failures']} of {n} starts)")


def map_selection_section(page, spec, solved: dict):
    """Which map each environment kept (``map_selection``) and how every candidate did
    on the selection's real-loop runs (nothing when the run does not select maps)."""
    chosen = {n: r["map_selection"] for n, r in solved.items() if r.get("map_selection")}
    if not chosen:
        return
    selection, starts = spec.map_selection, load_application(spec.application).starts_text()
    page.text(f"Each environment's map was chosen among its refinement levels and robust "
              f"variants by {selection.starts} real-loop runs from seeded {starts} "
              f"(seed {selection.seed}): the fewest false-unsafe + "
              f"{selection.false_safe_weight:g} x false-safe verdicts there, then the fewest "
              f"renders. The fidelity check below judges the kept map on other starts.")
    page.table(["environment", "map", "nodes rendered", "agreement % [95 % CI]",
                "false-safe % [95 % CI]", "false-unsafe % [95 % CI]", "kept"],
               [[n, c["map"], c["nodes_rendered"], _rate(c, "agree"), _rate(c, "false_safe"),
                 _rate(c, "false_unsafe"), "yes" if c["map"] == record["kept"] else ""]
                for n, record in chosen.items() for c in record["candidates"]])


def fidelity_section(page, spec, results: dict, made: dict, roles: dict):
    """The BRT, its table and the labels against the real loop, per environment:
    ``results`` the `fidelity_env` outputs by name, ``made`` the datasets' label records
    by name (their manifests' ``labels`` with ``counts``)."""
    page.section("Fidelity against the real Drake loop", "fidelity")
    if not results:
        page.text("Not checked (fidelity.starts: 0): nothing in this report says whether "
                  "the BRT, the labels and the failure sets match what the real loop does.")
        return
    by_check = [n for n, r in results.items()
                if r.get("extended") and r.get("extended_because", "check") == "check"]
    by_audit = [n for n, r in results.items() if r.get("extended_because") == "audit"]
    reasons = []
    if by_check:
        reasons.append(f"found wrong: {', '.join(by_check)}, whose rates lean slightly towards "
                       f"error, the extension having been chosen by it")
    if by_audit:
        reasons.append(f"distrusted by the audit: {', '.join(by_audit)}")
    more = "" if not spec.fidelity.more_starts else (
        f", {spec.fidelity.more_starts} where the first {spec.fidelity.starts} found the BRT or "
        f"the labels wrong or the labels' audit had distrusted the map (fidelity.more_starts; "
        f"{'; '.join(reasons) or 'none was'})")
    application = load_application(spec.application)
    open_axes = " or ".join(application.axes[i] for i in application.open_axes)
    page.text(f"The real closed loop (rendering and the controller at every tick) from "
              f"{spec.fidelity.starts} seeded uniform {application.starts_text()} per "
              f"environment{more} ({application.starts_note}), run for "
              f"{spec.horizon:g} s. False-safe: the BRT called the start safe and the real "
              f"loop {application.failure_words}, the error a safety tool must not make. "
              f"'Table rollouts = real': the swept table integrated from the same starts, i.e. "
              f"the table as a model of the loop; 'BRT = table rollouts': the solver against "
              f"its table; 'left the box': runs leaving the solved box"
              f"{f' in {open_axes}' if open_axes else ''}, where the "
              f"table is clamped to its edge. Every rate in % with its 95 % Wilson interval.")
    # the real runs' largest |heading| (Application.heading_axis; NaN without one)
    theta = any(np.isfinite(v) for r in results.values() for v in r["real_max_abs_theta_deg"])
    page.table(["environment", "role", "starts", "real failures", "BRT agreement",
                "false-safe", "false-unsafe", "table rollouts = real", "BRT = table rollouts",
                "real runs left the box", "table rollouts left the box",
                *(["real max |theta| deg (median / 90 % / max)"] if theta else []), "renders"],
               [[n, roles.get(n, "extra"), r["starts"], r["brt"]["real_failures"],
                 _rate(r["brt"], "agree"), _rate(r["brt"], "false_safe"),
                 _rate(r["brt"], "false_unsafe"), _rate(r["table_rollouts"], "agree"),
                 f"{100 * r['brt_vs_table_rollouts']:.1f}", _rate(r["brt"], "box_exits"),
                 _rate(r["table_rollouts"], "box_exits"),
                 *([" / ".join(f"{v:g}" for v in r["real_max_abs_theta_deg"])] if theta else []),
                 r["frames"]]
                for n, r in results.items()])
    page.text(f"The failure set over the same {application.starts_text()}: the share the BRT "
              "map puts in the BRT, and the share that failed in the real loop (a Monte-Carlo "
              "estimate of the true failure set, independent of the map): " + "; ".join(
                  f"{n}: {monte_carlo(r)}" for n, r in results.items()) + ".")
    crowded = [n for n, r in results.items()
               if r["brt"]["box_exits_rate"] > spec.fidelity.max_box_exits]
    if crowded:
        page.text(f"WARNING: in {', '.join(crowded)} more than "
                  f"{100 * spec.fidelity.max_box_exits:.0f} % of the real runs leave the solved "
                  f"box; there the BRT's verdicts rest on clamped table values.")
    labelled = {n: r["labels"] for n, r in results.items() if "labels" in r}
    if labelled:
        page.text("The labels of the datasets against the same real runs: where the "
                  "labelling rule rolls out, the label is the real outcome; elsewhere it is "
                  "the BRT's verdict.")
        page.text("Label renders: the frames the real loop rendered to label the dataset "
                  "(audit, rollouts, runs read along), over its labels.")
        page.table(["environment", "label source", "hybrid's audit", "agreement",
                    "false-safe", "false-unsafe", "labels", "label renders", "renders per label"],
                   [[n, r["source"], _audit_text(r), _rate(r, "agree"), _rate(r, "false_safe"),
                     _rate(r, "false_unsafe"), *label_renders(made.get(n, {}))]
                    for n, r in labelled.items()])
    along = {n: r["path_labels"] for n, r in results.items() if r.get("path_labels")}
    if along:
        page.text("The labels read along runs (trajectory labels, or dataset.labels.paths), "
                  "checked: states the runs passed through (not the uniform samples), each "
                  "run again from scratch for the horizon and compared with its label.")
        page.table(["environment", "states", "agreement", "false-safe", "false-unsafe",
                    "renders"],
                   [[n, r["n"], _rate(r, "agree"), _rate(r, "false_safe"),
                     _rate(r, "false_unsafe"), r.get("frames", "-")] for n, r in along.items()])
    if labelled:
        page.text(label_target_text(results))


#: The label target each environment's check is judged against, the real loop's outcome
#: being the truth: at least this agreement and at most this false-safe share.
LABEL_TARGET = {"agree": 0.99, "false_safe": 0.01}


def _meets(check) -> bool:
    return (check["agree_rate"] >= LABEL_TARGET["agree"]
            and check["false_safe_rate"] <= LABEL_TARGET["false_safe"])


def _label_checks(record) -> list:
    """``[(check, what)]`` of a `fidelity_env` record's labels: the fresh starts and,
    where the dataset reads along runs, the re-run read-along states."""
    return [(record["labels"], "starts")] + (
        [(record["path_labels"], "read-along states")] if record.get("path_labels") else [])


def labels_meet_target(record) -> bool:
    """Whether a `fidelity_env` record's labels meet `LABEL_TARGET` on every check."""
    return all(_meets(check) for check, _ in _label_checks(record))


def label_target_text(results) -> str:
    """One sentence on the labels of `fidelity_env` records ``results`` (by environment)
    against `LABEL_TARGET`: in how many environments both the fresh starts and, where
    the dataset reads along runs, the re-run read-along states meet it, and which miss
    it, with their figures. Empty when no record checks labels."""
    def figures(check, what):
        return (f"{what}: agreement {100 * check['agree_rate']:.1f} %, false-safe "
                f"{100 * check['false_safe_rate']:.1f} % of {check['n']}")

    labelled = {n: r for n, r in results.items() if "labels" in r}
    if not labelled:
        return ""
    missed = []
    for name, r in labelled.items():
        wrong = [figures(c, what) for c, what in _label_checks(r) if not _meets(c)]
        if wrong:
            missed.append(f"{name} ({'; '.join(wrong)})")
    starts = [r["labels"]["n"] for r in labelled.values()]
    span = f"{min(starts)}" if min(starts) == max(starts) else f"{min(starts)}-{max(starts)}"
    by_run = [n for n, r in labelled.items() if labels_every_state_by_its_run(r["labels"])]
    note = ""
    if by_run:
        unchecked = ("" if all(labelled[n].get("path_labels") for n in by_run)
                     else " (none where a dataset has no such states)")
        note = (f" In {len(by_run)} of them ({', '.join(by_run)}) a fresh start is labelled "
                f"by its own real run and agrees by construction: there only the re-run "
                f"read-along states test the labels{unchecked}.")
    return (f"Labels against the target (agreement >= {100 * LABEL_TARGET['agree']:g} % and "
            f"false-safe <= {100 * LABEL_TARGET['false_safe']:g} % on the fresh starts, and on "
            f"the re-run read-along states where the dataset has them): met in "
            f"{len(labelled) - len(missed)} of {len(labelled)} environments, checked on "
            f"{span} starts each" +
            (f"; missed in {', '.join(missed)}." if missed else ".") + note)


def label_renders(info) -> list:
    """``[labels, frames, frames per label]`` of a dataset's label record (its manifest's
    ``labels`` with ``counts``; frames as `label_frames` counts them; "-" where
    unknown)."""
    labels = sum((info.get("counts") or {}).values())
    if not labels:
        return ["-", "-", "-"]
    frames = label_frames(info)
    return [labels, frames, f"{frames / labels:.1f}"]


def _audit_text(record):
    """What the hybrid's audit decided, for the label-fidelity table."""
    if record.get("map_trusted") is None:
        return "-"
    runs = f" after {record['audit_runs']} runs" if record.get("audit_runs") else ""
    if record["map_trusted"]:
        return f"map trusted{runs}, band {record['band']:.2f} m"
    if record.get("labelled_by") == "trajectory":
        return f"map not trusted{runs}: trajectory labels"
    return f"map not trusted{runs}"
