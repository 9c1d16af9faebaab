"""The monitor over the image history on environments it has never seen: trains every
variant on recorded real-loop runs of training environments, calibrates each on other
environments of the same random family (Platt scaling, then a split-conformal
threshold that bounds the expected miss rate on a new environment), and judges them
on held-out environments of the family: miss rate, needless flags, AUROC of "fails
within 4 s", calibration; beside them the oracle monitor and TaxiNet's prediction
error. With ``--guarded-runs`` the kept variant (chosen on the calibration
environments only) and the single-frame one also run in the guarded real loop with
braking, against the loop alone from the same starts.

Environment ``i`` of the family depends only on ``--seed`` and ``i``; the first
``--train`` are for training, the next ``--calibrate`` for calibration, the rest held
out, so the split is fixed before anything is seen. Every real-loop batch is cached
by content under ``--cache``: a rerun with other training settings renders nothing.

    python benchmarks/monitor.py --train 2 --calibrate 9 --held-out 1 --runs 4 \\
        --duration 2 --epochs 1 --head-epochs 2      # a smoke run, minutes
"""

import argparse
import dataclasses as dc
import json
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import MonitorConfig, load_scenario, save_checkpoint
from reachwatch.reach.outcomes import fails_within, time_to_failure
from reachwatch.systems import HistoryMonitorConfig, RandomEnvironments
from reachwatch.taxi import on_runway_starts, paper_grid
from reachwatch.taxi.fidelity import real_missions
from reachwatch.taxi.history import recorded_runs
from reachwatch.training.baselines import prediction_error
from reachwatch.training.conformal import (PlattCalibration, brier_score, conformal_threshold,
                                           expected_calibration_error, per_environment_bound,
                                           warning_scores)
from reachwatch.training.history_train import (HistoryTrainConfig, encode_runs, run_risks,
                                               tick_labels, train_encoder, train_head)
from reachwatch.training.monitor_eval import (flag_outcomes, oracle_risks, rate, run_times,
                                              system_figures, tick_auroc)

#: name -> (frames, stride, temporal, with signals)
VARIANTS = {"single frame": (1, 1, "stack", False),
            "stacked 8 (1.6 s)": (8, 4, "stack", False),
            "GRU 16 (0.8 s)": (16, 1, "gru", False),
            "stacked 8 + signals": (8, 4, "stack", True),
            "GRU 16 + signals": (16, 1, "gru", True)}


def parse():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, help="scenario file (default: the built-in "
                   "one: the reference TaxiNet, 200x360 camera)")
    p.add_argument("--seed", type=int, default=11, help="the random environment family")
    p.add_argument("--train", type=int, default=12)
    p.add_argument("--calibrate", type=int, default=10)
    p.add_argument("--held-out", type=int, default=6)
    p.add_argument("--runs", type=int, default=30, help="recorded runs per environment")
    p.add_argument("--duration", type=float, default=8.0, help="s per recorded run")
    p.add_argument("--within", type=float, default=3.0, help="T of 'fails within T s'")
    p.add_argument("--brake", type=float, default=3.0, help="braking m/s^2: the fallback")
    p.add_argument("--alpha", type=float, default=0.1, help="target expected miss rate")
    p.add_argument("--size", type=int, nargs=2, default=[48, 80], help="frame height width")
    p.add_argument("--epochs", type=int, default=6)
    p.add_argument("--head-epochs", type=int, default=40)
    p.add_argument("--guarded-runs", type=int, default=0,
                   help="starts per held-out environment in the guarded real loop (0: skip)")
    p.add_argument("--cache", default="/tmp/reachwatch-monitor-cache")
    p.add_argument("--out", default="/tmp/reachwatch-monitor")
    args = p.parse_args()
    if min(args.train, args.calibrate, args.held_out, args.runs) < 1:
        p.error("--train, --calibrate, --held-out and --runs must be >= 1")
    if (args.calibrate + 1) * args.alpha < 1:
        p.error(f"--calibrate {args.calibrate} environments cannot bound the miss rate at "
                f"--alpha {args.alpha}: use at least {int(np.ceil(1 / args.alpha - 1))}")
    return args


def record(args, scenario, environments, offset):
    """Recorded runs of each environment (a dict of arrays per environment)."""
    out = []
    for i, environment in enumerate(environments):
        sc = dc.replace(scenario, environment=environment)
        B = environment.half_width
        grid = paper_grid(B, (3, 3, 3))
        starts = on_runway_starts((grid.lo, grid.hi), args.runs, [args.seed, offset + i],
                                  half_width=B)
        runs = recorded_runs(sc, starts, duration=args.duration, height=args.size[0],
                             width=args.size[1], cache_dir=Path(args.cache) / "runs")
        out.append({**runs, "starts": starts, "name": environment.name})
    return out


def merged(groups):
    keys = ("frames", "signals", "ticks", "failure_time", "state")
    return {k: np.concatenate([g[k] for g in groups]) for k in keys}


def ticks_labelled(groups, risks_by_group, *, period, duration, within):
    labels, scores = [], []
    for g, risks in zip(groups, risks_by_group):
        for risk, n, failure in zip(risks, g["ticks"], g["failure_time"]):
            y = fails_within(*time_to_failure(np.arange(int(n)) * period, failure, duration),
                             within)
            labels.append(y[y >= 0])
            scores.append(np.asarray(risk)[y >= 0])
    return np.concatenate(labels), np.concatenate(scores)


def pct(r):
    return "-" if r["of"] == 0 else f"{100 * r['rate']:.1f} [{100 * r['lo']:.1f}, {100 * r['hi']:.1f}] ({r['count']}/{r['of']})"


def main():
    args = parse()
    started = time.time()
    scenario = load_scenario(args.scenario) if args.scenario else load_scenario(data="")
    period, speed = scenario.controller.period, scenario.controller.speed
    lead = speed / args.brake
    family = RandomEnvironments(count=args.train + args.calibrate + args.held_out,
                                seed=args.seed).environments()
    split = {"train": family[:args.train],
             "calibrate": family[args.train:args.train + args.calibrate],
             "held_out": family[args.train + args.calibrate:]}
    offsets = {"train": 0, "calibrate": args.train, "held_out": args.train + args.calibrate}
    data = {k: record(args, scenario, envs, offsets[k]) for k, envs in split.items()}
    print(f"recorded {sum(len(g['ticks']) for v in data.values() for g in v)} runs, "
          f"{sum(int(g['ticks'].sum()) for v in data.values() for g in v)} ticks in "
          f"{time.time() - started:.0f} s; lead {lead:.2f} s, T {args.within} s", flush=True)
    for k, groups in data.items():
        print(f"  {k}: " + ", ".join(f"{g['name']} {int(np.isfinite(g['failure_time']).sum())}"
                                     f"/{len(g['ticks'])} fail" for g in groups))

    train = merged(data["train"])
    labels = tick_labels(train, period=period, duration=args.duration, within=args.within)
    base = HistoryMonitorConfig(height=args.size[0], width=args.size[1], within=args.within)
    settings = HistoryTrainConfig(epochs=args.epochs, head_epochs=args.head_epochs)
    encoder = train_encoder(train, labels, base, settings, progress=print)
    features = {k: [encode_runs(encoder, g) for g in groups] for k, groups in data.items()}
    train_features = np.concatenate(features["train"])
    signals = train["signals"].shape[-1]

    results, models = {}, {}
    for name, (frames, stride, temporal, with_signals) in VARIANTS.items():
        config = dc.replace(base, frames=frames, stride=stride, temporal=temporal,
                            signals=signals if with_signals else 0)
        model = train_head(encoder, train_features, train, labels, config, settings)
        raw = {k: [run_risks(model, f, g) for f, g in zip(features[k], data[k])]
               for k in ("calibrate", "held_out")}
        y, q = ticks_labelled(data["calibrate"], raw["calibrate"], period=period,
                              duration=args.duration, within=args.within)
        try:
            platt = PlattCalibration.fit(q, y == 1)
        except ValueError as e:                  # one class among the calibration ticks
            print(f"{name}: no Platt scaling ({e})")
            platt = PlattCalibration()
        risks = {k: [[platt(r) for r in group] for group in v] for k, v in raw.items()}
        env_scores = [warning_scores(r, run_times(g["ticks"], period), g["failure_time"],
                                     lead=lead) for r, g in zip(risks["calibrate"], data["calibrate"])]
        chosen = conformal_threshold(env_scores, args.alpha)
        calibration = [system_figures(flag_outcomes(r, g["ticks"], g["failure_time"],
                                                    period=period, threshold=chosen.threshold,
                                                    lead=lead))
                       for r, g in zip(risks["calibrate"], data["calibrate"])]
        cal_miss = [c["miss"]["rate"] if c["miss"]["of"] else 0.0 for c in calibration]
        cal_needless = sum(c["needless"]["count"] for c in calibration) / max(
            1, sum(c["needless"]["of"] for c in calibration))
        per_env = []
        pooled = {"failed": [], "warned": [], "flagged": []}
        for r, g in zip(risks["held_out"], data["held_out"]):
            out = flag_outcomes(r, g["ticks"], g["failure_time"], period=period,
                                threshold=chosen.threshold, lead=lead)
            for key in pooled:
                pooled[key].append(out[key])
            per_env.append({"environment": g["name"], **system_figures(out),
                            "auroc_4s": tick_auroc(r, g["ticks"], g["failure_time"],
                                                   period=period, duration=args.duration,
                                                   within=4.0)})
        y, p = ticks_labelled(data["held_out"], risks["held_out"], period=period,
                              duration=args.duration, within=args.within)
        results[name] = {
            "threshold": chosen.threshold, "statement": chosen.statement(lead),
            "per_environment_bound_90": per_environment_bound(cal_miss, 0.1),
            "calibration_needless": cal_needless, "platt": [platt.a, platt.b],
            "held_out": per_env,
            "pooled": system_figures({k: np.concatenate(v) for k, v in pooled.items()}),
            "ece": expected_calibration_error(p, y == 1), "brier": brier_score(p, y == 1),
            "ticks": int(len(y))}
        models[name] = (model, platt, chosen.threshold)
        print(f"{name}: threshold {chosen.threshold:.3f}, calibration needless "
              f"{100 * cal_needless:.1f} %, held-out miss {pct(results[name]['pooled']['miss'])}, "
              f"needless {pct(results[name]['pooled']['needless'])}", flush=True)

    oracle_env, baseline = [], []
    pooled = {"failed": [], "warned": [], "flagged": []}
    for g in data["held_out"]:
        out = flag_outcomes(oracle_risks(g["ticks"], g["failure_time"], period=period, lead=lead),
                            g["ticks"], g["failure_time"], period=period, threshold=0.5, lead=lead)
        for key in pooled:
            pooled[key].append(out[key])
        oracle_env.append({"environment": g["name"], **system_figures(out)})
        errors = [prediction_error(g["state"][i, :n], g["signals"][i, :n, :2])
                  for i, n in enumerate(g["ticks"])]
        baseline.append(tick_auroc(errors, g["ticks"], g["failure_time"], period=period,
                                   duration=args.duration, within=4.0))
    oracle = system_figures({k: np.concatenate(v) for k, v in pooled.items()})

    # the deployed variant is chosen on the calibration environments only: fewest
    # needless flags there at its conformal threshold
    kept = min(results, key=lambda n: results[n]["calibration_needless"])
    print_tables(args, results, oracle, oracle_env, baseline, kept, lead)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    checkpoints = {}
    for name in {kept, "single frame"}:
        model, platt, threshold = models[name]
        path = out / f"monitor_{name.split()[0].lower()}_{'signals' if model.config.signals else 'image'}.pt"
        save_checkpoint(path, kind="history_monitor", model=model, model_config=model.config,
                        preprocess_config=None,
                        metadata={"calibration": [platt.a, platt.b], "threshold": threshold,
                                  "within_s": args.within, "lead_s": lead, "variant": name,
                                  "family_seed": args.seed})
        checkpoints[name] = str(path)
    guarded = guarded_real_loop(args, scenario, data["held_out"], split["held_out"], models,
                                checkpoints) if args.guarded_runs else {}
    (out / "monitor.json").write_text(json.dumps({
        "args": vars(args), "lead_s": lead, "kept": kept, "variants": results,
        "oracle": {"pooled": oracle, "held_out": oracle_env},
        "prediction_error_auroc_4s": baseline, "guarded": guarded,
        "seconds": time.time() - started}, indent=1, default=float))
    print(f"wrote {out / 'monitor.json'} in {time.time() - started:.0f} s")


def print_tables(args, results, oracle, oracle_env, baseline, kept, lead):
    print(f"\n## Held-out environments, pooled (lead {lead:.2f} s, alpha {args.alpha})\n")
    print("| monitor | threshold | miss % [CI] | needless flags % [CI] | worst AUROC 4 s | ECE | Brier |")
    print("|---|---|---|---|---|---|---|")
    for name, r in results.items():
        aurocs = [e["auroc_4s"] for e in r["held_out"] if np.isfinite(e["auroc_4s"])]
        mark = " (kept)" if name == kept else ""
        print(f"| {name}{mark} | {r['threshold']:.3f} | {pct(r['pooled']['miss'])} | "
              f"{pct(r['pooled']['needless'])} | {min(aurocs) if aurocs else float('nan'):.3f} | "
              f"{r['ece']:.3f} | {r['brier']:.3f} |")
    print(f"| oracle (privileged) | - | {pct(oracle['miss'])} | {pct(oracle['needless'])} | - | - | - |")
    finite = [b for b in baseline if np.isfinite(b)]
    print(f"| prediction error (privileged baseline) | - | - | - | "
          f"{min(finite) if finite else float('nan'):.3f} | - | - |")
    print(f"\n{results[kept]['statement']}\n")
    print(f"## Per held-out environment: {kept}\n")
    print("| environment | miss % [CI] | needless % [CI] | AUROC 4 s | prediction-error AUROC 4 s | oracle miss |")
    print("|---|---|---|---|---|---|")
    for e, b, o in zip(results[kept]["held_out"], baseline, oracle_env):
        print(f"| {e['environment']} | {pct(e['miss'])} | {pct(e['needless'])} | "
              f"{e['auroc_4s']:.3f} | {b:.3f} | {pct(o['miss'])} |")


def guarded_real_loop(args, scenario, held_out, environments, models, checkpoints):
    """The guarded real loop (braking at ``--brake``) with each saved monitor against
    the loop alone, from the first ``--guarded-runs`` recorded starts of each held-out
    environment."""
    rows = {}
    for name, path in checkpoints.items():
        threshold = models[name][2]
        counts = {"failed_alone": 0, "prevented": 0, "needless_stops": 0, "safe_alone": 0,
                  "failed_guarded": 0, "runs": 0, "distance_alone": 0.0, "distance_guarded": 0.0}
        for g, environment in zip(held_out, environments):
            sc = dc.replace(scenario, environment=environment, monitor=MonitorConfig(
                detector=path, threshold=threshold, strategy="brake",
                brake_deceleration=args.brake))
            starts = g["starts"][:args.guarded_runs]
            cache = Path(args.cache) / "missions"
            alone = real_missions(sc, starts, duration=args.duration, cache_dir=cache)
            guarded = real_missions(sc, starts, fallback="brake", duration=args.duration,
                                    cache_dir=cache)
            counts["runs"] += len(starts)
            counts["failed_alone"] += int(alone.failed.sum())
            counts["failed_guarded"] += int(guarded.failed.sum())
            counts["prevented"] += int(np.sum(alone.failed & ~guarded.failed))
            counts["safe_alone"] += int(np.sum(~alone.failed))
            counts["needless_stops"] += int(np.sum(~alone.failed & guarded.ever_stopped))
            counts["distance_alone"] += float(alone.distance.sum())
            counts["distance_guarded"] += float(guarded.distance.sum())
        counts["prevented_rate"] = rate(counts["prevented"], counts["failed_alone"])
        counts["needless_rate"] = rate(counts["needless_stops"], counts["safe_alone"])
        rows[name] = counts
        print(f"guarded real loop, {name}: {counts['runs']} runs; failures "
              f"{counts['failed_alone']} alone -> {counts['failed_guarded']} guarded; prevented "
              f"{pct(counts['prevented_rate'])}; needless stops {pct(counts['needless_rate'])}; "
              f"distance {counts['distance_guarded']:.0f} of {counts['distance_alone']:.0f} m",
              flush=True)
    return rows


if __name__ == "__main__":
    main()
