"""The report's opening: the few figures a reviewer wants first, each with its 95 %
interval, its target and whether it meets it: how true the labels are (the real loop
the judge), and, when the run has a monitor study, the monitor's miss rate on
held-out environments, the failures it prevents and the needless stops it causes in
the guarded real loop, and its calibration."""

import math

from reachwatch.training.monitor_eval import rate

from .fidelity_sections import LABEL_TARGET, labels_meet_target
from .monitor_sections import rate_text, read_study_result
from .monitor_spec import ORACLE

#: The monitor study's targets: a miss rate and a needless-stop rate of at most 10 %
#: whose 95 % upper bounds stay within 13 %, and a calibration error of at most 0.05.
MONITOR_TARGETS = {"miss": (0.10, 0.13), "needless": (0.10, 0.13), "ece": 0.05}


def _interval(count, of):
    """``(text, rate, upper bound)`` of ``count`` of ``of`` (Wilson 95 %)."""
    r = rate(count, of)
    return (rate_text(r), None, None) if not of else (rate_text(r), r["rate"], r["hi"])


def _verdict(ok):
    return "-" if ok is None else ("meets" if ok else "misses")


def summary_rows(run) -> list:
    """``[figure, value with interval, target, verdict]`` rows of the summary."""
    rows = []
    checked = {n: r for n, r in (run.outputs.get("fidelity") or {}).items()
               if isinstance(r, dict) and "labels" in r}
    if checked:
        agree = sum(round(r["labels"]["agree_rate"] * r["labels"]["n"]) for r in checked.values())
        false_safe = sum(round(r["labels"]["false_safe_rate"] * r["labels"]["n"])
                         for r in checked.values())
        n = sum(r["labels"]["n"] for r in checked.values())
        met = sum(labels_meet_target(r) for r in checked.values())
        rows.append(["labels agree with the real loop (pooled fresh starts)",
                     _interval(agree, n)[0],
                     f">= {100 * LABEL_TARGET['agree']:g} % in every environment",
                     f"{_verdict(met == len(checked))} ({met} of {len(checked)} environments meet "
                     f"every label target)"])
        rows.append(["labels false-safe (pooled fresh starts)", _interval(false_safe, n)[0],
                     f"<= {100 * LABEL_TARGET['false_safe']:g} % in every environment", "-"])
    else:
        rows.append(["labels against the real loop", "not checked (fidelity.starts: 0)", "-",
                     "-"])
    outputs = run.outputs.get("monitor") or {}
    if not outputs:
        rows.append(["monitor on unseen environments", "no monitor study (monitor.kind: "
                     "detector); see the safety pipeline section", "-", "-"])
        return rows
    result = read_study_result(run.path(outputs["result"]))
    kept = result["variants"][result["kept"]]
    miss = kept["held_out"]["pooled"]["miss"]
    text, rate, hi = _interval(miss["count"], miss["of"])
    target, upper = MONITOR_TARGETS["miss"]
    rows.append([f"monitor miss rate, held-out environments ({result['kept']}; a warnable "
                 f"failing run with no flag {result['lead_s']:.2f} s before it fails)", text,
                 f"<= {100 * target:g} % (upper bound <= {100 * upper:g} %); conformal bound "
                 f"{100 * result['alpha']:g} % expected",
                 _verdict(None if rate is None else rate <= target and hi <= upper)])
    guarded = result["guarded"].get(result["kept"])
    if guarded:
        text, rate, _ = _interval(guarded["prevented"], guarded["failed_alone"])
        oracle = result["guarded"].get(ORACLE) or {}
        prevented = oracle.get("prevented") or 0       # from the same starts, braking
        rows.append(["failures prevented, guarded real loop (braking)", text,
                     ">= 85 % of what the oracle monitor prevents" +
                     (f" (the oracle: {prevented} of {oracle['failed_alone']}; this monitor "
                      f"{guarded['prevented'] / prevented:.2f} of that)" if prevented else ""),
                     _verdict(guarded["prevented"] >= 0.85 * prevented if prevented else None)])
        text, rate, hi = _interval(guarded["needless_stops"], guarded["safe_alone"])
        target, upper = MONITOR_TARGETS["needless"]
        rows.append([f"needless stops, guarded real loop (of the runs the loop alone "
                     f"survives, and the {result['within_s']:g} s after them)",
                     text, f"<= {100 * target:g} % (upper bound <= {100 * upper:g} %)",
                     _verdict(None if rate is None else rate <= target and hi <= upper)])
    else:
        rows.append(["guarded real loop", "not run (monitor.guarded_runs: 0)", "-", "-"])
    ece = kept["held_out"]["ece"]
    known = ece is not None and math.isfinite(ece)           # NaN: no held-out tick
    rows.append(["calibration error (ECE) of the risk, held-out environments",
                 f"{ece:.3f}" if known else "-", f"<= {MONITOR_TARGETS['ece']:g}",
                 _verdict(ece <= MONITOR_TARGETS["ece"] if known else None)])
    return rows


def summary_section(page, run):
    """The report's first section: `summary_rows` as a table."""
    page.section("Summary", "summary")
    page.table(["figure", "value [95 % CI]", "target", "verdict"], summary_rows(run))
