"""The run report: one static HTML page (``report.html``) and the same tables as
Markdown (``report.md``), built from the stage records; figures are linked by
relative path, so the run directory can be moved or served as it is."""

import html

from reachwatch.diagrams import export_graph, write_png
from reachwatch.diagrams.contact_sheet import environment_sheet
from reachwatch.reach.application import load_application
from reachwatch.systems.files import atomic_write_bytes
from reachwatch.training.evaluation import COLUMNS, format_cell
from reachwatch.training.labels import label_source

from .brt_stages import sweep_rate
from .fidelity_sections import fidelity_section, map_selection_section, monte_carlo
from .detector_sections import (detector_verdicts, percent_text as _pct, target_section,
                                threshold_section)
from .guard_sections import guard_section
from .monitor_sections import monitor_section
from .summary_section import summary_section
from .stages import Run

CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;
color:#222}h1{border-bottom:2px solid #444}h2{margin-top:2em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:13px;margin:.5em 0}td,th{border:1px solid #ccc;
padding:3px 7px;text-align:right}th{background:#f0f0f0}td:first-child,td:nth-child(2){
text-align:left}img{max-width:100%;border:1px solid #ddd;margin:4px 0}.row{display:flex;
flex-wrap:wrap;gap:8px}.row img{max-width:48%}pre{background:#f6f6f6;padding:1em;
overflow:auto;font-size:12px}.note{color:#555;font-size:13px}"""


class Page:
    """HTML and Markdown written side by side."""

    def __init__(self, title):
        self.html = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>"
                     f"{html.escape(title)}</title><style>{CSS}</style></head><body>",
                     f"<h1>{html.escape(title)}</h1>"]
        self.md = [f"# {title}\n"]

    def section(self, title, anchor):
        self.html.append(f"<h2 id='{anchor}'>{html.escape(title)}</h2>")
        self.md.append(f"\n## {title}\n")

    def text(self, text):
        self.html.append(f"<p class='note'>{html.escape(text)}</p>")
        self.md.append(f"{text}\n")

    def table(self, header, rows):
        cells = lambda r, t: "".join(f"<{t}>{html.escape(str(c))}</{t}>" for c in r)  # noqa: E731
        self.html.append("<table><tr>" + cells(header, "th") + "</tr>" +
                         "".join("<tr>" + cells(r, "td") + "</tr>" for r in rows) + "</table>")
        self.md.append("| " + " | ".join(map(str, header)) + " |\n|" + "---|" * len(header) +
                       "\n" + "".join("| " + " | ".join(map(str, r)) + " |\n" for r in rows))

    def images(self, paths, caption="", wide=False):
        paths = [p for p in paths if p]
        self.html.append(("<div>" if wide else "<div class='row'>") + "".join(
            f"<a href='{html.escape(p)}'><img src='{html.escape(p)}' alt='{html.escape(p)}'></a>"
            for p in paths) + "</div>")
        self.md.append("".join(f"![{caption or p}]({p})\n" for p in paths))

    def link(self, path, text):
        self.html.append(f"<p><a href='{html.escape(path)}'>{html.escape(text)}</a></p>")
        self.md.append(f"[{text}]({path})\n")

    def pre(self, text):
        self.html.append(f"<pre>{html.escape(text)}</pre>")
        self.md.append(f"```yaml\n{text}```\n")

    def done(self):
        return "\n".join(self.html) + "</body></html>\n", "\n".join(self.md)


def view(application, scenario):
    """The application's camera view of ``scenario`` at its `view_state`."""
    return application.renderer(scenario).render(application.view_state(scenario))


def environment_roles(spec) -> dict:
    """``{name: "train" | "test"}`` of a run's labelled environments."""
    return {**{e.name: "test" for e in spec.held_out_environments()},
            **{e.name: "train" for e in spec.training_environments()}}


def graphs(run: Run):
    """SVG/PNG (or only .dot without graphviz) of the nominal and guarded diagrams."""
    scenario = run.scenario_for(run.spec.held_out_environments()[0])
    scenario.monitor.detector = str(run.path(run.outputs["train"]["detector"]))
    out = {}
    loop = run.application.loop_diagram     # the taxi's unless the run names another
    for name, diagram in (("closed_loop", loop(scenario)),
                          ("guarded", loop(scenario, guarded=True))):
        written = export_graph(diagram, run.path(f"figures/diagram_{name}"), formats=("dot", "svg"))
        out[name] = run.rel(written[-1])
    return out


def labels_paragraph(spec, o) -> str:
    """What the datasets hold and where their labels come from, and the detector trained
    on them (the report's "Labels and the detector" text)."""
    labels, paths = spec.dataset.labels, spec.dataset.labels.paths
    states = load_application(spec.application).starts_text("states")
    return (f"{spec.dataset.samples} uniform states per environment, labels from "
            f"'{labels.source}' ({label_source(labels.source).text}); "
            + (f"besides them, the states that {paths} more real run{'s' * (paths != 1)} per "
               f"environment pass through (from uniform {states}, {labels.extend:g} s "
               f"past the horizon, every {labels.stride}th tick), labelled by those runs, and "
               f"each run's states kept on one side of the detector's validation split; "
               if paths else "") +
            (f"the held-out environments' labels from '{spec.held_out_labels.source}' "
             f"({label_source(spec.held_out_labels.source).text}; Table 2 scores against "
             f"them and against the BRT's verdicts on the same states); "
             if spec.held_out_labels is not None else "") +
            "positives per environment: " + ", ".join(
                f"{n} {_pct(p)}%" for n, p in o["dataset"]["positives"].items()) +
            f". Detector {spec.detector.detector.arch} "
            f"{spec.detector.detector.height}x{spec.detector.detector.width}, "
            f"{spec.detector.epochs} epochs, operating threshold "
            f"{o['train']['threshold']:.3g} (target recall {spec.detector.target_recall}).")


def write_report(run: Run) -> dict:
    """Write ``report.html`` and ``report.md``; returns their paths (relative)."""
    spec, o = run.spec, run.outputs
    page = Page(f"reachwatch run '{spec.name}'")
    summary_section(page, run)
    page.section("Environments", "environments")
    sheet = write_png(run.path("figures/environments.png"), environment_sheet(
        run.environments(), per_row=4, render=lambda env: view(run.application,
                                                               run.scenario_for(env))))
    page.text("Training: " + ", ".join(e.name for e in spec.training_environments()) +
              ". Held out: " + ", ".join(e.name for e in spec.held_out_environments()) + ".")
    page.images([run.rel(sheet)])
    page.section("Diagrams", "diagrams")
    for name, path in graphs(run).items():
        if path.endswith(".dot"):
            page.link(path, f"{name} diagram (Graphviz .dot; install graphviz for SVG)")
        else:
            page.images([path], f"{name} diagram", wide=True)
    page.section("Backward reachable tubes", "brts")
    application = run.application
    slices = application.slice_words.format(at=spec.slice_py)
    page.text(f"Grid {spec.grid} over {application.box_words}, horizon {spec.horizon:g} s, "
              f"solver {spec.accuracy}; 'BRT = table rollouts': sign agreement of the BRT with "
              f"RK4 rollouts of the swept table from every node (the solver against its own "
              f"model of the loop, not against the real loop: see the next section)"
              + (f"; {slices}." if slices else "."))
    roles = environment_roles(spec)
    if spec.refine.levels:
        page.text(f"Each table was refined adaptively {spec.refine.levels} time(s): each level "
                  f"halves the spacing and renders new nodes only in the cells where the BRT's "
                  f"boundary passes within {spec.refine.band:g} m" +
                  (f" or the steering varies by more than {spec.refine.variation_deg:g} deg"
                   if spec.refine.variation_deg is not None else "") +
                  "; every other node is interpolated. 'Nodes rendered' counts each level's "
                  "total.")
    if spec.robust.enabled:
        page.text(f"The BRTs are robust: where the swept steering ranges over more than "
                  f"{spec.robust.min_spread_deg:g} deg across the {spec.robust.neighbourhood}-node "
                  f"neighbourhood of a node, the solver lets it take the worst value in that "
                  f"range, since interpolating it there says little about the controller "
                  f"between the nodes. This can only grow the BRT, so it trades false-safe "
                  f"verdicts for false-unsafe ones: the fidelity section counts both.")
    page.table(["environment", "role", "grid solved", "nodes rendered", "BRT % (grid solved)",
                "BRT % (the box)", "BRT = table rollouts (all nodes) %", "sweep s",
                "states/s", "solve s"],
               [[n, roles.get(n, "extra"), "x".join(map(str, r.get("grid", spec.grid))),
                 " -> ".join(map(str, r.get("nodes_rendered", [r["states"]]))),
                 _pct(r["brt_fraction"]),
                 _pct(r["brt_fraction_box"]) if "brt_fraction_box" in r else "-",
                 _pct(r["rollout_agreement"]), r["sweep_seconds"],
                 sweep_rate(r), r["solve_seconds"]]
                for n, r in o["solve"].items()])
    page.images([r["figure"] for r in o["solve"].values()])
    map_selection_section(page, spec, o["solve"])
    fidelity_section(page, spec, o.get("fidelity") or {},
                     o.get("dataset", {}).get("labels", {}), roles)
    monitor_section(page, run)
    page.section("Labels and the detector", "labels")
    page.text(labels_paragraph(spec, o))
    page.images([f["overlay"] for f in o["evaluate"]["figures"].values()])
    page.section("Table 2: detector and baselines on held-out environments", "table2")
    target_section(page, o["evaluate"]["rows"], spec.held_out_groups(), spec.detector)
    for sentence in detector_verdicts(o["evaluate"]["rows"]):
        page.text(sentence)
    page.table(COLUMNS, [[format_cell(r.get(k), k) for k in COLUMNS] for r in o["evaluate"]["rows"]])
    page.link("table2.csv", "table2.csv")
    page.text("tp / fp / fn / tn: flagged anomalies, false alarms, missed anomalies and "
              "safe states left alone. ROC curves per held-out environment over all states, "
              "each method's operating point dotted; then the detector's most confident "
              "mistakes there: the anomalous images it scored lowest and the safe images it "
              "scored highest, with their value V and state.")
    figures = o["evaluate"]["figures"].values()
    page.images([f.get("roc") for f in figures])
    page.images([f.get("mistakes") for f in figures], wide=True)
    threshold_section(page, o["train"], o["evaluate"]["rows"], spec.detector)
    page.section("Failure modes: error rate against distance to the BRT boundary", "margin")
    page.images([f["error_vs_margin"] for f in o["evaluate"]["figures"].values()])
    page.section("Safety pipeline", "guard")
    if not o["guard"] and not application.rolls_out_fallbacks(
            application.resolved(spec.scenario)):
        page.text(f"Not run: the application '{application.name}' has no fallback rollouts "
                  f"(the guard stage rolls its fallbacks out on the guarded loop's swept "
                  f"tables, at the speed the fallback sets: its dynamics take no speed).")
    for env, g in o["guard"].items():
        checked = (o.get("fidelity") or {}).get(env)
        guard_section(page, env, g, spec, application,
                      alone_checked=checked and (checked["starts"], monte_carlo(checked)))
    if o.get("incremental"):
        inc = o["incremental"]
        page.section("Incremental training", "incremental")
        tuned, mined = inc["fine_tune"], application.starts_text("states")
        replayed = tuned.get("replayed_states")
        how = (f" on {tuned['mined_states']} anomalous {mined} mined from the training "
               f"datasets" + (f" plus {replayed} nominal frames" if replayed is not None else "")
               if tuned.get("mined_states") is not None else
               " on the training datasets' anomalies")
        page.text(f"{application.controller_words} fine-tuned{how}; BRT of {inc['environment']} "
                  f"(held out): {_pct(inc['before'])}% before, {_pct(inc['after'])}% after.")
        page.images([inc["figure"], inc.get("star", {}).get("figure")])
    page.section("Benchmarks, as each stage last ran", "benchmarks")
    rows = [[f"sweep {n}", f"{sweep_rate(r)} states/s ({r.get('rendered', r['states'])} "
             f"rendered in {r['sweep_seconds']:.1f} s)"]
            for n, r in o["solve"].items() if r.get("rendered", r["states"])]
    for env, g in o["guard"].items():
        on = g["online"]
        rows.append([f"online {env} {on['image'][0]}x{on['image'][1]}",
                     f"alone {on['alone_ticks_per_s']:.1f} ticks/s, guarded "
                     f"{on['guarded_ticks_per_s']:.1f} ticks/s (medians of 3 rounds, the two "
                     f"loops side by side in alternating 0.5 s blocks), "
                     f"median per-round ratio {on['ratio']:.2f}"])
    page.table(["what", "figure"], rows)
    page.section("Stage records", "stages")
    page.text("Stage records (OUT/stages/*.json); a re-run skips a stage whose key is "
              "unchanged, and keeps the time of the run that produced it.")
    page.table(["stage", "key", "seconds", "finished"],
               [[n, r["key"], f"{r['seconds']:.1f}", r["finished"]] for n, r in run.records.items()])
    page.section("Configuration", "configuration")
    page.pre((run.root / "run.yaml").read_text())
    text_html, text_md = page.done()
    return {"html": run.rel(atomic_write_bytes(run.path("report.html"), text_html.encode())),
            "md": run.rel(atomic_write_bytes(run.path("report.md"), text_md.encode()))}
