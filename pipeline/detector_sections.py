"""The report's text on the trained detector: Table 2 against the target, what its
operating threshold promised beside what it got, and one plain verdict per held-out
environment."""

import math

from reachwatch.training.evaluation import target_summary


def percent_text(x):
    """``0.1234`` -> ``"12.34"``; None or NaN -> ``"-"``."""
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.2f}"


def threshold_section(page, trained, rows, config):
    """What the operating threshold promised, beside the recall it got on each
    held-out environment (the detector's own row, all states, first label source)."""
    if not config.target_recall:
        return
    held_out = trained.get("held_out_threshold")
    if held_out:
        p = held_out["promised"]
        page.text(f"Operating threshold {trained['threshold']:.3g}, chosen on the training "
                  f"environments left out in {len(held_out['per_group'])} groups (a detector "
                  f"trained without each group scored it; rule '{held_out['rule']}'): it "
                  f"promised recall >= {percent_text(p['min_recall'])}% on every left-out "
                  f"group ({percent_text(p['pooled_recall'])}% pooled) at "
                  f"{percent_text(p['pooled_accuracy'])}% accuracy, flagging "
                  f"{percent_text(p['flagged'])}% of their images.")
        page.table(["left-out group", "images", "positives", "own threshold",
                    "recall at the threshold %", "accuracy %"],
                   [[name, g["n"], g["positives"],
                     "-" if g["own_threshold"] is None else f"{g['own_threshold']:.3g}",
                     percent_text(g["recall"]),
                     percent_text(g["accuracy"])] for name, g in held_out["per_group"].items()])
        promised = f"promised {percent_text(p['min_recall'])}% (every left-out group)"
        baseline = trained.get("prediction_error_held_out_threshold")
        if baseline:
            b = baseline["promised"]
            page.text(f"The prediction-error baseline's threshold "
                      f"{trained['prediction_error_detector_threshold']:.3g} was chosen the "
                      f"same way, on its own labels: it promised recall >= "
                      f"{percent_text(b['min_recall'])}% on every left-out group, flagging "
                      f"{percent_text(b['flagged'])}% of their images.")
    else:
        promised = (f"promised {percent_text(config.target_recall)}% on a random validation "
                    f"split of the training images: environments it trained on, which is no "
                    f"promise for a new one (set detector.threshold_folds)")
    mine = [r for r in rows if r["states"] == "all" and r["method"] == rows[0]["method"]
            and r["labels"] == rows[0]["labels"]]
    page.text(f"Recall {promised}; got on the held-out environments: " + ", ".join(
        f"{r['environment']} {percent_text(r['recall'])}%" for r in mine) + ".")


#: The accuracy the report's summary counts environments against (the recall is
#: ``DetectorTrainConfig.judged_recall``).
TARGET_ACCURACY = 0.95


def target_table(summary):
    """``(header, rows)`` of the target table from `target_summary`'s rows: one row
    per held-out group, label source and subset, min / median cells in percent."""
    pair = lambda v: f"{percent_text(v[0])} / {percent_text(v[1])}"   # noqa: E731
    header = ["held-out group", "labels", "states", "environments", "recall %", "accuracy %",
              "AUROC", "accuracy its ranking allows %", "flagged %", "recall on target",
              "both on target", "AUROC above every baseline", "lowest accuracy"]
    return header, [
        [s["group"], s["labels"], s["states"], s["environments"], pair(s["recall"]),
         pair(s["accuracy"]), pair(s["auroc"]), pair(s["accuracy_at_target_recall"]),
         pair(s["flagged"]), f"{s['meet_recall']} of {s['environments']}",
         f"{s['meet_both']} of {s['environments']}",
         "-" if s["beats_baselines"] is None else f"{s['beats_baselines']} of {s['environments']}",
         s["worst"]] for s in summary]


def target_section(page, rows, groups, config):
    """Table 2 against the target, before the per-environment rows: for each group of
    held-out environments (``groups``: {name: environment names}), label source and
    subset of states, the detector's min / median recall, accuracy, AUROC and the rest,
    and how many environments reach the target."""
    recall = config.judged_recall
    summary = target_summary(rows, groups, recall=recall, accuracy=TARGET_ACCURACY)
    if not summary:
        return
    page.text(f"The detector ({summary[0]['method']}) against the target of recall >= "
              f"{percent_text(recall)}% and accuracy >= {percent_text(TARGET_ACCURACY)}% on "
              f"every held-out environment: min / median over each group of environments. "
              f"The minimum is what the target is about. 'Accuracy its ranking allows' is "
              f"the accuracy at the recall target with a threshold set on each environment's "
              f"own labels (an oracle); 'AUROC above every baseline' counts the environments "
              f"where the detector ranks the images better than every other method.")
    page.table(*target_table(summary))


#: A detector flagging at least this share of a held-out environment's images is called
#: out as flagging nearly everything; below `CHANCE_AUROC` it is called near chance.
FLAGS_NEARLY_ALL = 0.9
CHANCE_AUROC = 0.6


def detector_verdicts(rows) -> list:
    """One plain sentence per held-out environment on the first method of ``rows`` (the
    detector), over all states with the first label source: the share of images it
    flags beside the share that are anomalous, its recall and accuracy, its AUROC beside
    the best other method's, the accuracy its ranking allows at the recall target (an
    oracle threshold, when the rows have ``accuracy_at_target_recall``), and a warning
    when it flags nearly everything, is near chance, or is beaten by a baseline."""
    if not rows:
        return []
    method, labels = rows[0]["method"], rows[0]["labels"]
    same = [r for r in rows if r["states"] == "all" and r["labels"] == labels]
    out = []
    for d in (r for r in same if r["method"] == method):
        others = [r for r in same if r["environment"] == d["environment"] and r is not d
                  and r.get("auroc") is not None]
        flagged = (d["tp"] + d["fp"]) / d["n"] if d["n"] else 0.0
        anomalous = d["positives"] / d["n"] if d["n"] else 0.0
        text = (f"{d['environment']}: the detector flags {percent_text(flagged)}% of the "
                f"images, while {percent_text(anomalous)}% are anomalous; it catches "
                f"{percent_text(d['recall'])}% of the anomalies at "
                f"{percent_text(d['accuracy'])}% accuracy, AUROC {percent_text(d['auroc'])}")
        best = max(others, key=lambda r: r["auroc"], default=None)
        if best is not None:
            text += f" (best other method: {best['method']}, {percent_text(best['auroc'])})"
        text += "."
        ceiling = d.get("accuracy_at_target_recall")
        if ceiling is not None and not math.isnan(ceiling):     # missing or NaN: say nothing
            text += (f" A threshold set on this environment's own labels for the recall "
                     f"target would give {percent_text(ceiling)}% accuracy (what its ranking "
                     f"allows).")
        if flagged >= FLAGS_NEARLY_ALL:
            text += " It flags nearly every image: here it is an alarm, not a detector."
        elif d["auroc"] is not None and d["auroc"] < CHANCE_AUROC:
            text += " Its scores barely separate the classes here (chance is 50)."
        elif best is not None and d["auroc"] is not None and d["auroc"] <= best["auroc"]:
            text += " A baseline ranks the images better here."
        out.append(text)
    return out
