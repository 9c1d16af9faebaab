"""The monitor study (``monitor:`` in a run file): a monitor over the image history,
trained on recorded real-loop runs of training environments, calibrated on other
environments of the same random family (Platt scaling, then a conformal threshold
that bounds the expected miss rate on a new environment of the family), and judged on
held-out environments of it, and on named environments outside the family, as a
system: misses at the fallback's lead, needless flags, AUROC of "fails within 4 s",
calibration, beside the oracle monitor and the controller's prediction error; then in
the guarded real loop with braking against the loop alone.

Environment ``i`` of the family depends only on the family's seed and ``i``: the
first ``train`` are for training, the next ``calibrate`` for calibration, the rest
held out, so the split and the threshold are fixed before a held-out environment is
seen. Every real-loop batch is cached by content: a rerun with other training
settings renders nothing.

The loop is the application's (`reachwatch.reach.application.Application`): its
`starts` in its `grid`'s box, its `recorded_runs` and its guarded and unguarded
`missions`; the study's schema (`MonitorStudySpec`, with the environment family) is
the run file's (`reachwatch.pipeline.spec`)."""

import dataclasses as dc
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from reachwatch.diagrams import save_checkpoint
from reachwatch.reach.application import application_key, load_application
from reachwatch.systems import HistoryMonitorConfig, HistoryRiskEnsemble
from reachwatch.systems.files import atomic_write_bytes, cache_location, file_hash, strict_json
from reachwatch.training.conformal import NoConformalThreshold
from reachwatch.training.history_train import (HistoryTrainConfig, encode_runs,
                                               encoder_settings, run_risks, tick_labels,
                                               train_encoder, train_head)
from reachwatch.training.monitor_eval import oracle_risks

from .monitor_guarded import guarded_rows
from .slot_defaults import DEFAULT_APPLICATION
from .monitor_judge import (_judge_monitor, check_calibration_bounds, choose_flag_rule,  # noqa: F401
                            judge_environments, prediction_error_aurocs, watch_s)
from .monitor_runs import (STARTS_STREAM, alone_reads_recordings, each_named,  # noqa: F401
                           merged_runs, record_split, record_splits, recorded_frames,
                           starts_seed)
from .monitor_saved import checkpoint_file, clear_previous_result, save_risks, study_outputs
from .monitor_sections import rate_text
from .monitor_spec import (DETECTOR_ROW, MONITOR_KINDS, MonitorStudySpec,  # noqa: F401
                           MonitorVariant, default_variants, study_lead)

__all__ = ["DETECTOR_ROW", "MONITOR_KINDS", "MonitorStudySpec", "MonitorVariant", "checkpoint_file",
           "choose_flag_rule", "default_variants", "judge_environments", "run_monitor_study",
           "stage_monitor"]


def _member_mean(per_member):
    """The members' raw risks averaged per tick: ``per_member[m][env][run]`` (one
    array per run) -> ``[env][run]`` (one member: its own risks)."""
    return [[np.mean(runs, axis=0) for runs in zip(*groups)] for groups in zip(*per_member)]


def _judged(name, spec, data, raw, **kwargs):
    """`_judge_monitor` of the row ``name``; where no threshold reaches alpha, the error
    says whose. A risk that is not a finite number refuses the row in one line, naming
    where: it would flag or not depending on the figure computed (the online flag, the
    calibration fit, the AUROC and the ECE each read it differently)."""
    for split, groups in raw.items():
        for env, runs in zip(data[split], groups):
            bad = sum(int(np.sum(~np.isfinite(np.asarray(r, float)))) for r in runs)
            if bad:
                raise ValueError(f"monitor: {name}: {bad} of the risks along the runs of "
                                 f"{env['name']} ({split}) are not finite numbers (a network "
                                 f"that diverged, or a score that is NaN): no figure of it "
                                 f"would mean what it says")
    try:
        return _judge_monitor(spec, data, raw, **kwargs)
    except NoConformalThreshold as e:
        raise NoConformalThreshold(f"monitor: {name}: {e}") from None


def run_monitor_study(spec: MonitorStudySpec, scenario, out_dir, *, cache_dir, executor=None,
                      progress=True, log=print, application=None, detector=None) -> dict:
    """The whole study (see the module) of ``application``'s loop (an `Application`;
    None: the default, the taxi); writes ``monitor.json`` and the checkpoints of the kept
    variant and of the first one (``variants[0]``, by default the single frame) to
    ``out_dir``; returns the results. With ``spec.ensemble`` > 1 each variant is that
    many trainings (`member_settings`) whose raw risks are averaged per tick, then
    calibrated and thresholded as one monitor; its checkpoint holds every member.
    ``detector`` (a single-image detector's checkpoint, e.g. the run's): its scores along
    the same runs (`DETECTOR_ROW`) are judged beside the variants, with a threshold and
    flag rule fixed on the calibration environments the same way, and it guards the
    loop beside them; it is never the kept variant."""
    spec.validate()
    out_dir, cache_dir = cache_location(out_dir), cache_location(cache_dir)
    for what, where in (("out_dir", out_dir), ("cache_dir", cache_dir)):
        if not isinstance(where, Path):
            raise ValueError(f"the monitor study's {what} must be a local folder (it reads its "
                             f"trainings and checkpoints back as files), got {where}")
    application = load_application(DEFAULT_APPLICATION) if application is None else application
    started = time.time()
    period = scenario.controller.period
    lead = study_lead(spec, application, scenario)
    split = spec.environments()
    first = {"train": 0, "calibrate": spec.train, "held_out": spec.train + spec.calibrate,
             "also_held_out": spec.train + spec.calibrate + spec.held_out}
    runs = {"train": spec.runs, "calibrate": spec.calibration_environment_runs,
            "held_out": spec.judged_runs,
            "also_held_out": spec.judged_runs}
    judged = ("calibrate", "held_out", "also_held_out")
    # every split's environments together; the judged runs carry the detector's score
    # along them: one run, both recorded
    # the judged runs' frames are read back an environment at a time when encoded
    data = record_splits(spec, application, scenario,
                         {k: (list(envs), first[k], runs[k], detector if k in judged else None)
                          for k, envs in split.items()},
                         cache_dir=cache_dir / "runs", executor=executor, progress=progress,
                         frames_read_back=judged)
    log(f"monitor: recorded {sum(len(g['ticks']) for v in data.values() for g in v)} runs, "
        f"{sum(int(g['ticks'].sum()) for v in data.values() for g in v)} ticks; lead "
        f"{lead:.2f} s, risk of failing within {spec.within:g} s")
    failing = {k: {g["name"]: [int(np.isfinite(g["failure_time"]).sum()), len(g["ticks"])]
                   for g in groups} for k, groups in data.items()}
    check_calibration_bounds(spec, data["calibrate"], period=period, lead=lead)

    detector_raw = (None if detector is None else
                    {k: [[np.asarray(g["score"][i, :int(n)], float)
                           for i, n in enumerate(g["ticks"])] for g in data[k]]
                     for k in judged})

    train = merged_runs(data["train"])
    # labels from the longer watch: every recorded tick's is known
    labels = tick_labels({**train, "failure_time": train["watched_failure_time"]},
                         period=period, duration=watch_s(spec), within=spec.within)
    base = HistoryMonitorConfig(height=spec.height, width=spec.width, within=spec.within,
                                input_norm=spec.input_norm, pool=list(spec.pool))
    # each member of the ensemble: its own encoder (`member_settings`) and features
    encoders, trainings = [], _Trainings(cache_dir / "trainings", train, labels, log)
    for m, settings in enumerate(member_settings(spec, application)):
        where = f"member {m + 1}/{spec.ensemble}: " if spec.ensemble > 1 else ""
        # kept by, and trained with, what an encoder reads: the heads' settings do not
        # train it again
        reads = encoder_settings(settings)
        encoders.append((*trainings.kept(
            f"{where}encoder", (base, reads), lambda where=where, reads=reads:
            train_encoder(train, labels, base, reads, progress=(
                lambda text: log(f"monitor: {where}{text}")) if progress else None)), settings))
    # every environment's frames encoded by every member, then let go: what follows
    # reads features, states and outcomes, for the hours of guarded runs
    features = [{k: [] for k in data} for _ in encoders]
    with tqdm(total=sum(len(g["ticks"]) for groups in data.values() for g in groups),
              unit="run", desc="monitor: frames encoded", disable=not progress) as bar:
        for k, groups in data.items():
            for group in groups:
                frames = {"frames": recorded_frames(group), "ticks": group["ticks"]}
                for member, (encoder, _, _) in zip(features, encoders):
                    member[k].append(encode_runs(encoder, frames))
                group.pop("frames", None)
                bar.update(len(group["ticks"]))
    train.pop("frames")
    members = [(encoder, settings, f, np.concatenate(f["train"]), trained_as)
               for (encoder, trained_as, settings), f in zip(encoders, features)]

    results, models, all_risks = {}, {}, {}
    for variant in spec.variants:
        config = dc.replace(base, frames=variant.frames, stride=variant.stride,
                            temporal=variant.temporal,
                            signals=train["signals"].shape[-1] if variant.signals else 0)
        heads = [trainings.kept(f"{variant.name} head", (config, settings, encoder_key),
                                lambda encoder=encoder, settings=settings, f=train_features:
                                train_head(encoder, f, train, labels, config, settings))[0]
                 for encoder, settings, _, train_features, encoder_key in members]
        per_member = [{k: [run_risks(head, f, g) for f, g in zip(features[k], data[k])]
                       for k in judged} for head, (_, _, features, _, _) in zip(heads, members)]
        raw = {k: _member_mean([p[k] for p in per_member]) for k in judged}
        model = heads[0] if len(heads) == 1 else HistoryRiskEnsemble.of(heads)
        row, platt, chosen, rule, risks = _judged(variant.name, spec, data, raw,
                                                  period=period, lead=lead)
        all_risks[variant.name] = risks
        results[variant.name] = row
        models[variant.name] = (model, platt, chosen.threshold, rule)
        log(f"monitor: {variant.name}: threshold {chosen.threshold:.3f}; {judged_text(row)}")
    if detector is not None:        # the run's single-image detector, judged the same way
        row, platt, chosen, rule, risks = _judged(DETECTOR_ROW, spec, data, detector_raw,
                                                  period=period, lead=lead, calibrated=False)
        row["kind"] = "detector"
        all_risks[DETECTOR_ROW] = risks
        results[DETECTOR_ROW] = row
        models[DETECTOR_ROW] = (None, platt, chosen.threshold, rule)
        log(f"monitor: {DETECTOR_ROW}: threshold {chosen.threshold:.3f} (its own score); "
            f"{judged_text(row)}")

    oracle = {}
    baseline = prediction_error_aurocs(application, scenario,
                                       {k: data[k] for k in ("held_out", "also_held_out")},
                                       period=period, duration=watch_s(spec))
    for k in ("held_out", "also_held_out"):
        groups = data[k]
        risks = [oracle_risks(g["ticks"], g["failure_time"], period=period, lead=lead)
                 for g in groups]
        per_env, pooled = judge_environments(groups, risks, threshold=0.5, period=period,
                                             lead=lead, watch=watch_s(spec))
        oracle[k] = {"environments": per_env, "pooled": pooled}

    # fixed in advance (the bound is exact for it), or chosen on the calibration
    # environments (`MonitorStudySpec.keep`)
    kept = spec.kept_in_advance or min((n for n in results if n != DETECTOR_ROW),
                                       key=lambda n: results[n]["calibration_needless"])
    out_dir.mkdir(parents=True, exist_ok=True)
    clear_previous_result(out_dir)
    save_risks(out_dir / "risks.npz", data, all_risks, judged)
    checkpoints = {}
    for name in dict.fromkeys([kept, spec.variants[0].name]):
        model, platt, threshold, rule = models[name]
        path = out_dir / checkpoint_file(name, {Path(p).name for p in checkpoints.values()})
        save_checkpoint(path, kind="history_monitor", model=model, model_config=model.config,
                        preprocess_config=None,
                        metadata={"calibration": [platt.a, platt.b], "threshold": threshold,
                                  "within_s": spec.within, "lead_s": lead, "variant": name,
                                  "period_s": scenario.controller.period,
                                  "speed_mps": scenario.controller.speed,
                                  "brake_deceleration": spec.brake_deceleration,
                                  **camera_size(scenario),
                                  **({"flag_rule": rule} if rule != [1, 1] else {})})
        checkpoints[name] = str(path)
    read_alone = spec.guarded_runs > 0 and alone_reads_recordings(
        application, dc.replace(scenario, environment=split["train"][0]))
    guarding = {**checkpoints, **({DETECTOR_ROW: str(detector)} if detector is not None else {})}
    guarded = {k: guarded_rows(spec, application, scenario, data[k], models, guarding,
                               risks={name: all_risks[name][k] for name in guarding},
                               cache_dir=cache_dir / "missions", executor=executor,
                               progress=progress, log=log, lead=lead, read_alone=read_alone)
               if spec.guarded_runs and data[k] else {} for k in ("held_out", "also_held_out")}
    candidates = len(spec.variants) * len(spec.flag_rules)
    result = {"lead_s": lead, "within_s": spec.within, "alpha": spec.alpha, "kept": kept,
              # 0: fixed in advance, or the one candidate there was
              "kept_chosen_among": 0 if spec.kept_in_advance or candidates == 1 else candidates,
              "ensemble": spec.ensemble,
              "failing_runs": failing, "variants": results, "oracle": oracle,
              "prediction_error_auroc_4s": baseline, "guarded": guarded["held_out"],
              "guarded_also_held_out": guarded["also_held_out"],
              "checkpoints": {k: Path(v).name for k, v in checkpoints.items()},
              **({"detector": str(detector)} if detector is not None else {}),
              "seconds": round(time.time() - started, 1)}
    from reachwatch.training.figures import plot_reliability
    result["reliability_figure"] = Path(plot_reliability(
        {name: row["held_out"]["reliability"] for name, row in results.items()
         if row["held_out"]["reliability"]}, out_dir / "reliability.png",
        title=f"held-out environments: risk of failing within {spec.within:g} s")).name
    # strict JSON: a rate of nothing (NaN) or a run no rule can warn in time (-inf) is
    # null; `read_study_result` reads nulls back (as -inf in the lists of scores)
    atomic_write_bytes(out_dir / "monitor.json",
                       strict_json(result, indent=1, default=float).encode())
    return result


def judged_text(row: dict) -> str:
    """A variant's row (`_judge_monitor`) in one line: per judged group of environments,
    pooled misses and needless flags, ECE and the worst environment's AUROC of failing
    within the risk's horizon."""
    parts = []
    for group, name in (("held_out", "held out"), ("also_held_out", "outside the family")):
        r = row.get(group)
        if not r or not r["environments"]:
            continue
        aurocs = [e["auroc_4s"] for e in r["environments"] if np.isfinite(e["auroc_4s"])]
        parts.append(f"{name}: miss {rate_text(r['pooled']['miss'])}, needless "
                     f"{rate_text(r['pooled']['needless'])}, ECE {r['ece']:.3f}, worst AUROC "
                     f"{min(aurocs) if aurocs else float('nan'):.3f}")
    return "; ".join(parts)


class _Trainings:
    """The study's trained encoders and heads, each saved under ``folder`` once trained
    and read back by a study that trains the same again (a resumed protocol, another
    flag rule): keyed by the digest of the training runs and labels, the settings, the
    encoder a head reads (its own key), the source of the training code
    (`TRAINING_CODE`) and the versions of torch, numpy and reachwatch
    (`reach.fingerprint.STACK`). What is read back is the model saved, weights bit for
    bit."""

    def __init__(self, folder, runs, labels, log):
        import hashlib
        from reachwatch.reach.fingerprint import STACK, modules_source_digest
        data = hashlib.sha256()
        for key in ("frames", "signals", "ticks", "state"):
            value = np.ascontiguousarray(runs[key])
            data.update(f"{key}{value.dtype}{value.shape}".encode())
            data.update(memoryview(value).cast("B"))
        data.update(np.ascontiguousarray(labels).tobytes())
        self.folder, self.log = Path(folder), log
        self.base = [data.hexdigest(), modules_source_digest(*TRAINING_CODE), STACK]

    def kept(self, what: str, parts, train):
        """``(model, key)``: the model ``train()`` gives for ``parts`` (configs and
        settings, and the keys of models this one was trained from), trained or read
        back, and its key."""
        from reachwatch.diagrams.checkpoints import CheckpointError, load_history_monitor
        from .keys import digest
        key = digest(*self.base, *[p if isinstance(p, str) else dc.asdict(p) for p in parts])
        path = self.folder / f"{key}.pt"
        model = None
        if path.is_file():
            try:
                model, _, _ = load_history_monitor(path)
                self.log(f"monitor: {what}: the trained model read back ({path.name})")
            except CheckpointError as e:    # unreadable (or NaN weights): trained again
                self.log(f"monitor: {what}: training again: {e}")
        if model is None:
            model = train()
            save_checkpoint(path, kind="history_monitor", model=model,
                            model_config=model.config, preprocess_config=None,
                            metadata={"trained": what})
        return model, key


#: Bumped when the study's results change for the same inputs (2: the oracle's and the
#: nights' guarded rows; 3: the encoder trains on colour-jittered frames; 4: the starts
#: have a random stream of their own, `STARTS_STREAM`; 5: runs are judged, and labelled,
#: on the loop alone watched ``within`` s past the recordings, `watched_failure_times`;
#: 6: risks are float64 sigmoids, calibrated without a 1e-7 clip, `history_model.platt`),
#: so that a run's monitor stage is run again.
STUDY_FORMAT = 6

#: The modules whose code trains and judges the study's monitors (the recorded runs
#: and guarded missions have keys of their own): part of the monitor stage's key. A
#: test (tests/test_import_graph.py) finds the training and monitor modules they
#: import, and the reach/ modules those import, and fails while one is missing here.
STUDY_CODE = ("reachwatch.systems.detector", "reachwatch.systems.history_model",
              "reachwatch.systems.history_monitor", "reachwatch.systems.risk_ensemble",
              "reachwatch.training.detector_train", "reachwatch.training.history_train",
              "reachwatch.training.monitor_eval", "reachwatch.training.conformal",
              "reachwatch.training.baselines", "reachwatch.training.metrics",
              "reachwatch.training.figures", "reachwatch.reach.outcomes",
              "reachwatch.reach.fidelity", "reachwatch.reach.liveness", "reachwatch.reach.chunks",
              "reachwatch.reach.chunk_jobs",
              "reachwatch.pipeline.monitor_study", "reachwatch.pipeline.monitor_saved",
              "reachwatch.pipeline.monitor_guarded", "reachwatch.pipeline.monitor_judge",
              "reachwatch.pipeline.monitor_runs",
              # its values enter the key, but its properties (the environments drawn
              # from the family and their roles, the runs judged) are code
              "reachwatch.pipeline.monitor_spec")


#: The modules whose code trains a monitor's encoder and heads: part of the key of a
#: study's saved trainings (`_Trainings`).
TRAINING_CODE = tuple(name for name in STUDY_CODE if name.startswith(
    ("reachwatch.systems.", "reachwatch.training."))) + ("reachwatch.diagrams.checkpoints",)


def train_settings(spec: MonitorStudySpec, application=None) -> HistoryTrainConfig:
    """The optimisation settings the study trains its monitors with: the run file's
    ``epochs``, ``head_epochs``, ``augment``, ``seed``, ``lr_schedule``,
    ``state_targets`` (left out: ``application``'s `estimated_state`; None: the default
    application's), ``state_weight`` and ``weight_average``, the rest
    `HistoryTrainConfig`'s."""
    targets = spec.state_targets
    if targets is None:
        targets = (load_application(DEFAULT_APPLICATION) if application is None
                   else application).estimated_state
    return HistoryTrainConfig(epochs=spec.epochs, head_epochs=spec.head_epochs,
                              augment=spec.augment, seed=spec.seed,
                              lr_schedule=spec.lr_schedule, state_targets=tuple(targets),
                              state_weight=spec.state_weight,
                              weight_average=spec.weight_average)


def member_settings(spec: MonitorStudySpec, application=None) -> list:
    """`train_settings` of each of the ``spec.ensemble`` (K) members: seeds ``K * seed``
    to ``K * seed + K - 1``, so that studies with other seeds share no member (an
    ensemble of one is the training of ``spec.seed``)."""
    settings, k = train_settings(spec, application), spec.ensemble
    return [dc.replace(settings, seed=k * settings.seed + m) for m in range(k)]


def camera_size(scenario) -> dict:
    """``{"image_size": [height, width]}`` of the frames the study's loop renders (its
    ``scenario.camera``), which a history monitor's checkpoint enforces online; nothing
    for a scenario without a camera."""
    camera = getattr(scenario, "camera", None)
    return {} if camera is None else {"image_size": [camera.height, camera.width]}


def study_key(spec: MonitorStudySpec, application, scenario, detector=None) -> str:
    """The monitor stage's key: the study's settings (by content: a file an environment
    of ``also_held_out`` names is keyed by its bytes, `reach.fingerprint`) and every
    training setting (`train_settings`), the scenario's content (checkpoints and
    controller code included), the application's key, the source of `STUDY_CODE`, the
    lead (`study_lead`), and the content of the ``detector`` judged beside (when one
    is)."""
    from reachwatch.reach.fingerprint import fingerprint, modules_source_digest
    from .keys import digest
    own = application_key(application)
    return digest(fingerprint(dc.asdict(spec)), dc.asdict(train_settings(spec, application)),
                  fingerprint(application.without_monitor(scenario)), own,
                  {"study": STUDY_FORMAT, "code": modules_source_digest(*STUDY_CODE),
                   "lead_s": study_lead(spec, application, scenario)},
                  *([file_hash(detector)] if detector is not None else []))


def stage_monitor(run) -> dict:
    """The run's ``monitor`` stage: the study when ``monitor.kind`` is ``history``
    (keyed by `study_key`), with the run's trained detector judged beside its variants
    when ``monitor.compare_detector``; nothing (no record) otherwise."""
    spec = run.spec.monitor
    if not spec.enabled:
        return {}
    application = run.application
    detector = (run.path(run.outputs["train"]["detector"]) if spec.compare_detector else None)
    key = study_key(spec, application, run.spec.scenario, detector)

    def study():
        return study_outputs(run_monitor_study(
            spec, run.spec.scenario, run.path("monitor"), cache_dir=run.path("monitor_cache"),
            executor=run.executor, progress=run.progress, log=run.log,
            application=application, detector=detector))
    return run.stage("monitor", key, study)
