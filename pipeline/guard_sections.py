"""The report's section on the guard stage: the failure sets of each fallback with
what they cost in liveness, the same figures with a perfect detector, the real-loop
check beside the tables, and the showcase nominal-vs-guarded run."""

import numpy as np

from reachwatch.reach.liveness import UNGUARDED, percent

from .detector_sections import percent_text as _pct


def _x(value):
    return "-" if value is None else f"{value:.2f}"


def _share(entry):
    """``"12.3 (45/367)"`` for a `liveness_figures` rate (``"-"`` when absent or empty)."""
    if entry is None or entry.get("rate") is None:
        return "-"
    return f"{100 * entry['rate']:.1f} ({entry['count']}/{entry['of']})"


def _ticks(figures):
    return "-" if figures["flagged_ticks"] is None else f"{100 * figures['flagged_ticks']:.1f}"


def _cut_inside(figures):
    """The failure cut over the starts inside the safe set: at the same distance when
    judged so, else within the horizon (``"-"`` for runs from before these figures)."""
    cut = figures.get("same_distance_failure_cut_inside", figures.get("failure_cut_inside"))
    return "-" if cut is None else f"{100 * cut:.0f}"


def guard_section(page, env, g, spec, application, *, alone_checked=None):
    """Failure sets with their liveness per fallback, the trade-off curve, the real-loop
    check and the showcase run of one guard environment (the stage record ``g``), in
    ``application``'s words; ``alone_checked``: ``(starts, text)``, the controller
    alone's failure set in the real loop from the fidelity stage, when it ran."""
    fail, starts_text = application.fail_words, application.starts_text()
    cut_column = f"cut, {application.start_word or 'unfailed'} starts %"
    page.text(f"{env}: fraction of grid starts that {fail} within "
              f"{spec.horizon:g} s (detector threshold {g['threshold']:.3g}), and what each "
              f"fallback costs: starts ended stopped, needless stops (of the starts the "
              f"controller alone survives, those the fallback ends stopped), harmed (of those, "
              f"the ones it makes fail), saves that keep moving (of the starts the controller "
              f"alone fails, less those failed before their first tick), distance travelled "
              f"relative to the controller alone, and ticks flagged. 'oracle' steers with the "
              f"true state: a privileged reference, not a result. "
              f"Slowing down does not change the path of a plant whose turn rate scales with "
              f"its speed (a car, say), only when it gets somewhere: slowed "
              f"runs can {fail} after the horizon instead of within it. So the last two columns "
              f"judge the same runs by distance: the share of runs that {fail} before covering "
              f"the distance "
              f"the controller alone covers in {spec.horizon:g} s (the runs going on past the "
              f"horizon), and the share that never covers it (parked or crawling). Grid "
              f"nodes that have already failed fail before the first tick and no fallback can "
              f"save them, yet they count in every failure set; the column "
              f"'{cut_column[:-2]}' gives the cut at the same distance over the other nodes.")
    budget = g.get("flag_budget")
    if budget:
        page.text(f"The threshold {g['threshold']:.3g} was set here, without labels, from a "
                  f"flag budget: the threshold at which {budget['fallback']} flags "
                  f"{100 * budget['budget']:g} % of its control ticks in the tables "
                  f"({'with' if budget['score_noise'] else 'without'} the score noise; "
                  f"{100 * budget['flagged_ticks']:.1f} % at the threshold chosen, from "
                  f"{budget['starts']} {starts_text}), instead of the training's "
                  f"{budget['scenario_threshold']:.3g}. A budget bounds how often the guard "
                  f"intervenes, not how many of its interventions are saves: the columns "
                  f"below say that.")
    first = next(iter(g.get("liveness", {}).values()), {})
    alone_same = first.get("alone_same_distance_failure_set")
    rows = [["controller alone", _pct(g["volumes"][UNGUARDED]), "-", "-", "-", "-", "1.00", "-",
             _share(alone_same), "-", "-"]]
    noisy = g.get("liveness_with_noise") or {}
    for f, plain in g.get("liveness", {}).items():
        for name, v in ((f, plain), (f"{f}, + score noise", noisy.get(f))):
            if v is None:
                continue
            rows.append([name, _pct(v["failure_set"]["rate"]), _share(v["ended_stopped"]),
                         _share(v["needless_stops"]), _share(v["harmed"]),
                         _share(v.get("saved_moving_inside")),        # "-": an older run
                         _x(v["distance_ratio"]), _ticks(v),
                         _share(v.get("same_distance_failure_set")),
                         _share(v.get("short_of_distance")), _cut_inside(v)])
    page.table(["closed loop", "failure set %", "ended stopped %", "needless stops %",
                "harmed %", "saved, moving %", "distance / alone", "ticks flagged %",
                "fails at the same distance %", "short of the distance %", cut_column], rows)
    perfect = g.get("perfect_detector")
    if perfect:
        page.text("The same fallbacks with a perfect detector, one that flags exactly the "
                  "states the BRT holds (the label the detector learns): what is left here no "
                  "better detector can remove, and the gap between the two tables is the "
                  "detector's share.")
        page.table(["fallback, perfect detector", "failure set %", "ended stopped %",
                    "needless stops %", "ticks flagged %", "fails at the same distance %",
                    "short of the distance %", cut_column],
                   [[f, _share(v["failure_set"]), _share(v["ended_stopped"]),
                     _share(v["needless_stops"]), _ticks(v),
                     _share(v.get("same_distance_failure_set")), _share(v.get("short_of_distance")),
                     _cut_inside(v)]
                    for f, v in perfect.items()])
    if alone_checked:
        starts, text = alone_checked
        page.text(f"The controller alone in the real loop, from {starts} random "
                  f"{starts_text} (the grid figures above count every node, failed ones "
                  f"too): {text}.")
    if noisy:
        page.text("Rows '+ score noise' and, in the trade-off figure, the dashed curves and "
                  "hollow stars: the same tables rolled out with the detector's variation "
                  "between grid nodes (the score noise fitted for the real-loop check below, "
                  "one draw). Interpolated between nodes, the score is smoother than the real "
                  "one, so the plain rows stop more and save more than the real loop; the "
                  "check below shows which of the two the real loop follows.")
    page.images([g["figure"], g.get("tradeoff_figure")])
    check = g.get("check")
    if check:
        page.text(f"The same figures in the real Drake loops (rendering and the detector at "
                  f"every tick) from {check['starts']} seeded random {starts_text} (seed "
                  f"{check['seed']}), beside the tables' rollouts from the same starts; "
                  f"95 % Wilson intervals.")
        noise = check.get("score_noise")
        if noise and "error" in noise:
            page.text(f"The detector's variation between grid nodes could not be fitted on "
                      f"{noise['runs']} real runs of the controller alone: {noise['error']}.")
        elif noise:
            page.text(f"The tables interpolate the detector's score between grid nodes; the "
                      f"real score departs from that in patches a few metres long. Fitted on "
                      f"{noise['runs']} other real runs of the controller alone (seed "
                      f"{noise['seed']}), the departure is noise in the score's logit with mean "
                      f"{noise['mean']:+.2f}, standard deviation {noise['sigma']:.2f} and "
                      f"correlation length {noise['length']:.1f} m of travel; the rows 'table + "
                      f"score noise' roll the tables out with it (one draw).")
        sources = {"table": "table", "table_with_noise": "table + score noise", "real": "real"}
        rows = []
        for f, both in check["fallbacks"].items():
            for source, label in sources.items():
                if source not in both:
                    continue
                v = both[source]
                rows.append([f, label, percent(v["alone_failure_set"]), percent(v["failure_set"]),
                             percent(v["ended_stopped"]), percent(v["needless_stops"]),
                             _x(v["distance_ratio"]),
                             percent(v.get("alone_same_distance_failure_set")),
                             percent(v.get("same_distance_failure_set")),
                             percent(v.get("short_of_distance"))])
        page.table(["fallback", "figures from", "alone fails", "guarded fails", "ended stopped",
                    "needless stops", "distance / alone", "alone fails, same distance",
                    "guarded fails, same distance", "short of the distance"], rows)
    r = g["run"]
    if not r.get("files"):
        page.text("No grid start where the tables say the controller alone fails and an honest "
                  "fallback saves it, so no nominal-vs-guarded run to show.")
        return
    save = r.get("save")
    units = tuple(application.axis_units) + ("",) * len(application.axes)
    axes = ", ".join(f"{a} {u}".strip() for a, u in zip(application.axes, units))
    verdict = ("a save that keeps moving, confirmed in the real Drake loops" if save == "moving"
               else "confirmed in the real Drake loops, but the only save found is a stop: the "
                    "guarded loop ends at standstill" if save == "stop"
               else f"NOT a save: in the real Drake loops the guarded run only goes on to "
                    f"{fail} later, past the horizon, on the same path" if any(
                        t.get("guarded_fails_later") for t in r["tried"])
               else "NOT confirmed in the real Drake loops (the tables are coarse)")
    page.text(f"Nominal vs guarded ({r['strategy']}) from the start {np.round(r['start'], 2)} "
              f"[{axes}], chosen from the tables ({len(r['tried'])} tried), "
              f"{verdict}: the controller alone {'fails' if r['nominal_fails'] else 'does not fail'}, "
              f"guarded {'fails' if r['guarded_fails'] else 'does not fail'}; lowest speed "
              f"{r['lowest_speed']:.2f} m/s, final speed {r.get('final_speed', float('nan')):.2f} "
              f"m/s, {r['flagged_ticks']} of {r.get('ticks', '?')} ticks flagged.")
    page.images([p for p in r["files"] if p.endswith(".png")])
    for p in r["files"]:
        if p.endswith(".html"):
            page.link(p, "Meshcat replay of the guarded run (standalone HTML)")
