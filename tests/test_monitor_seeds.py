"""benchmarks/monitor_seeds.py on two fake trainings of one study's runs: it runs
through (it once stopped on a spec field the study's threshold code had gained), prints
each training's rows and the mean's, and refuses a training whose saved threshold its
own reading does not give."""

import importlib.util
import json
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "monitor_seeds.py"
_SPEC = importlib.util.spec_from_file_location("monitor_seeds", _PATH)
seeds = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(seeds)

PERIOD, DURATION, TICKS = 0.05, 1.0, 21          # runs that survive: 1 s at 0.05 s a tick
ENVIRONMENTS = {"calibrate": 6, "held_out": 3, "also_held_out": 0}


def _arrays(rng, noise: float) -> dict:
    """Every split's runs: in each environment one run fails at its 12th tick (its risk
    rising before), three survive (low risk), plus ``noise``."""
    arrays = {}
    for split, count in ENVIRONMENTS.items():
        ticks, failure, env, risks = [], [], [], []
        for e in range(count):
            for r in range(4):
                fails = r == 0
                n = 12 if fails else TICKS
                ticks.append(n)
                failure.append((n - 1) * PERIOD if fails else np.nan)
                env.append(e)
                base = np.linspace(0.1, 0.9, n) if fails else np.full(n, 0.1)
                risks.append(np.clip(base + noise * rng.uniform(-1, 1, n), 0, 1))
        arrays[f"{split}/ticks"] = np.array(ticks, int)
        arrays[f"{split}/failure_time"] = np.array(failure, float)
        arrays[f"{split}/watched_failure_time"] = np.array(failure, float)
        arrays[f"{split}/environment"] = np.array(env, int)
        arrays[f"{split}/names"] = np.array([f"{split}-{e}" for e in range(count)])
        arrays[f"v/{split}/risk"] = (np.concatenate(risks) if risks
                                     else np.zeros(0)).astype(np.float32)
    return arrays


def _study(folder: Path, noise: float, seed: int, threshold=None) -> Path:
    folder.mkdir()
    arrays = _arrays(np.random.default_rng(seed), noise)
    np.savez(folder / "risks.npz", **arrays)
    if threshold is None:       # what the study's own threshold code fixes on them
        saved = np.load(folder / "risks.npz")
        groups, risks = seeds._groups(saved, {s: saved[f"v/{s}/risk"].astype(float)
                                             for s in seeds.SPLITS})
        spec = types.SimpleNamespace(alpha=0.3, flag_rules=[[1, 1]], given_failures=False,
                                     duration=DURATION, within=0.2)
        threshold = seeds.choose_flag_rule(spec, groups["calibrate"], risks, period=PERIOD,
                                           lead=0.1)[2].threshold
    (folder / "monitor.json").write_text(json.dumps(
        {"alpha": 0.3, "lead_s": 0.1, "within_s": 0.2,
         "variants": {"v": {"threshold": threshold, "given_failures": False}}}))
    return folder


def _main(monkeypatch, capsys, *outs):
    monkeypatch.setattr(sys, "argv", ["monitor_seeds.py", *map(str, outs), "--period",
                                      str(PERIOD), "--duration", str(DURATION)])
    seeds.main()
    return capsys.readouterr().out


def test_two_trainings_and_their_mean_are_read(tmp_path, monkeypatch, capsys):
    one = _study(tmp_path / "one", 0.05, 0)
    two = _study(tmp_path / "two", 0.08, 0)
    out = _main(monkeypatch, capsys, one, two)
    rows = [Path(line.split()[0]).name for line in out.splitlines()
            if line.startswith((str(one) + " ", str(two) + " ", "mean "))]
    assert rows == ["one", "one", "two", "two", "mean", "mean"], out
    assert "fails within 0.2 s; lead 0.10 s; alpha 0.3" in out


def test_a_training_whose_threshold_it_does_not_give_is_refused(tmp_path, monkeypatch,
                                                                 capsys):
    wrong = _study(tmp_path / "wrong", 0.05, 0, threshold=0.999)
    with pytest.raises(SystemExit) as stop:
        _main(monkeypatch, capsys, wrong)
    assert stop.value.code == 2
    assert re.search(r"threshold 0\.\d{4} here, 0\.9990 in its study", capsys.readouterr().err)
