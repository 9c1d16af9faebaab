"""A monitor study's files on disk: the names of its checkpoints (`checkpoint_file`),
what its stage's record checks (`study_outputs`), a previous result cleared before a
study writes (`clear_previous_result`), and its per-tick risks (``risks.npz``): written
by the study (`save_risks`), read back by the benchmarks that judge other flag rules,
splits and means without rendering or training again (`saved_risks`), with the checks
that what they are given matches the study (`check_same_runs`, `check_run_length`)."""

import io
import json
import re
import sys
import zipfile
from pathlib import Path

import numpy as np

from reachwatch.diagrams import tick_times
from reachwatch.systems.files import atomic_write_bytes

from .monitor_judge import fails_after


class StudyFileError(ValueError):
    """A finished study's file (``monitor.json``, ``risks.npz``) that is missing, damaged
    or not one: said in one line naming the file."""


def open_saved_risks(path):
    """The ``risks.npz`` at ``path`` (`save_risks`'s), open (``np.load``: close it, or use
    it in a ``with``), or a `StudyFileError` naming the file."""
    try:
        saved = np.load(path, allow_pickle=False)
    except OSError as e:
        raise StudyFileError(f"{path}: cannot read a study's saved risks "
                             f"({e.strerror or e}); give a finished study's folder") from None
    except (ValueError, zipfile.BadZipFile, EOFError) as e:
        why = e if zipfile.is_zipfile(path) else "not an .npz archive"
        raise StudyFileError(f"{path}: not a study's saved risks ({why})") from None
    if not isinstance(saved, np.lib.npyio.NpzFile):
        raise StudyFileError(f"{path}: not a study's saved risks (not an .npz archive)")
    if not any(name.endswith("/ticks") for name in saved.files):
        saved.close()
        raise StudyFileError(f"{path}: not a study's saved risks (no runs' ticks in it)")
    return saved


def study_script(main):
    """Runs ``main``, a script that reads finished studies (the monitor benchmarks): a
    `StudyFileError` is one line on stderr and exit status 2, not a traceback."""
    try:
        return main()
    except StudyFileError as e:
        print(f"{Path(sys.argv[0]).name}: error: {e}", file=sys.stderr)
        sys.exit(2)


def checkpoint_file(variant: str, taken=()) -> str:
    """The file a study saves ``variant``'s monitor as: named after the variant
    (``single frame`` -> ``monitor_single-frame.pt``), so that no one takes one
    variant's file for another's; a name already in ``taken`` gets a number."""
    slug = re.sub(r"[^a-z0-9]+", "-", variant.lower()).strip("-")[:48].strip("-") or "variant"
    file, k = f"monitor_{slug}.pt", 2
    while file in taken:
        file, k = f"monitor_{slug}-{k}.pt", k + 1
    return file


def clear_previous_result(out_dir: Path) -> None:
    """Removes a previous study's ``monitor.json`` from ``out_dir``, and the checkpoints
    and figure it names, before a study writes its own there: a study killed while it
    writes (its guarded runs take hours) then leaves no result beside files of other
    settings, and no checkpoint of a variant the new study does not keep stays behind to
    be deployed. ``monitor.json`` is written last, so its absence marks a study that
    did not finish; the checkpoints such a study wrote (`checkpoint_file`'s names, a
    study's checkpoints by their metadata) are removed too, which no ``monitor.json``
    names."""
    previous = Path(out_dir) / "monitor.json"
    try:
        old = json.loads(previous.read_text())
    except (OSError, ValueError):
        old = {}
    previous.unlink(missing_ok=True)
    named = [*dict(old.get("checkpoints") or {}).values(), old.get("reliability_figure")]
    for name in named:
        if isinstance(name, str) and name and Path(name).name == name:
            (Path(out_dir) / name).unlink(missing_ok=True)
    for path in Path(out_dir).glob("monitor_*.pt"):
        if _saved_by_a_study(path):
            path.unlink(missing_ok=True)


def _saved_by_a_study(path: Path) -> bool:
    """Whether ``path`` is a history monitor's checkpoint a study saved under the name
    it gives (its metadata names the variant and the study's lead, and the file is
    `checkpoint_file`'s name for that variant), not another file of that form (a copy
    renamed to be kept)."""
    from reachwatch.diagrams.checkpoints import CheckpointError, checkpoint_metadata
    try:
        metadata = checkpoint_metadata(path, kinds=("history_monitor",))
    except (CheckpointError, OSError, ValueError):
        return False
    if "lead_s" not in metadata or not isinstance(metadata.get("variant"), str):
        return False
    named = checkpoint_file(metadata["variant"])[:-len(".pt")]
    return re.fullmatch(re.escape(named) + r"(-\d+)?\.pt", path.name) is not None


def study_outputs(result: dict, folder: str = "monitor") -> dict:
    """The monitor stage's outputs: the study's ``monitor.json`` (``result``) and every
    other file it wrote (``files``), so that the stage's record checks them all and a
    folder whose checkpoints or saved risks another study rewrote is not up to date."""
    files = ["risks.npz", *result["checkpoints"].values(), result["reliability_figure"]]
    return {"result": f"{folder}/monitor.json", "files": [f"{folder}/{f}" for f in files]}


def save_risks(path, data, all_risks, judged):
    """Every variant's calibrated risk (the detector's row: its raw score, which its
    threshold reads) at every tick of the judged environments' runs,
    with the runs' ticks, failure times and environments, so that another flag rule can
    be read off the study without rendering again: ``{split}/ticks``,
    ``{split}/failure_time``, ``{split}/watched_failure_time`` (`watched_failure_times`),
    ``{split}/environment`` (index into ``{split}/names``) per run and
    ``{variant}/{split}/risk`` (the runs' ticks, concatenated)."""
    arrays = {}
    for k in judged:
        groups = data[k]
        arrays[f"{k}/ticks"] = np.concatenate([g["ticks"] for g in groups] + [np.zeros(0, int)])
        for key in ("failure_time", "watched_failure_time"):
            arrays[f"{k}/{key}"] = np.concatenate([g[key] for g in groups] + [np.zeros(0)])
        arrays[f"{k}/environment"] = np.concatenate(
            [np.full(len(g["ticks"]), i) for i, g in enumerate(groups)] + [np.zeros(0, int)])
        arrays[f"{k}/names"] = np.array([g["name"] for g in groups], dtype=str)
        for name, risks in all_risks.items():
            arrays[f"{name}/{k}/risk"] = np.concatenate(
                [np.asarray(r, np.float32) for group in risks[k] for r in group]
                + [np.zeros(0, np.float32)])
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def saved_groups(saved, split: str, flat) -> tuple:
    """Per environment of ``split`` in the open ``risks.npz`` ``saved`` (`save_risks`'s):
    ``(groups, risks)``, its group (``ticks``, ``failure_time``, ``watched_failure_time``,
    ``name``) and its risks per run, cut from ``flat`` (the split's risk at every tick,
    concatenated, as `save_risks` writes a variant's; or a mean of such). A study saved
    before the longer watch has no watched times: its failure times stand in."""
    ticks, failure = saved[f"{split}/ticks"], saved[f"{split}/failure_time"]
    watched = (saved[f"{split}/watched_failure_time"]
               if f"{split}/watched_failure_time" in saved.files else failure)
    env, names = saved[f"{split}/environment"], saved[f"{split}/names"]
    runs = np.split(np.asarray(flat, float), np.cumsum(ticks)[:-1]) if len(ticks) else []
    groups = [{"ticks": ticks[env == e], "failure_time": failure[env == e],
               "watched_failure_time": watched[env == e], "name": str(names[e])}
              for e in range(len(names))]
    return groups, [[runs[i] for i in np.flatnonzero(env == e)] for e in range(len(names))]


def saved_risks(saved, variant: str, split: str) -> list:
    """What `save_risks` wrote of ``variant`` in ``split``, read back from the open
    ``risks.npz`` ``saved``, per environment: ``(risks per run, ticks, failure times,
    fails_after)``; ``fails_after``: survived the recording, failed within the study's
    longer watch (all False for a study saved before it watched longer)."""
    groups, risks = saved_groups(saved, split, saved[f"{variant}/{split}/risk"])
    return [(runs, g["ticks"], g["failure_time"], fails_after(g))
            for g, runs in zip(groups, risks)]


def check_same_runs(saved: dict, splits=("calibrate", "held_out", "also_held_out")):
    """Raises ValueError unless the open ``risks.npz`` files ``saved`` (by name) hold the
    same runs: ticks, failure times and environments in every one of ``splits``."""
    names = list(saved)
    for name in names[1:]:
        for split in splits:
            for key in ("ticks", "failure_time", "environment"):
                if not np.array_equal(saved[name][f"{split}/{key}"],
                                      saved[names[0]][f"{split}/{key}"],
                                      equal_nan=key == "failure_time"):
                    raise ValueError(f"{name} and {names[0]} did not record the same runs "
                                     f"({split}/{key} differ)")


def check_run_length(saved, *, period: float, duration: float):
    """Raises ValueError unless the runs of the open ``risks.npz`` ``saved`` that did not
    fail last ``duration`` s at ``period`` s a tick: a benchmark given another period
    or duration than its study's would read every warning and label wrong."""
    lengths = {int(n) for split in ("calibrate", "held_out", "also_held_out")
               if f"{split}/ticks" in saved.files
               for n in saved[f"{split}/ticks"][~np.isfinite(saved[f"{split}/failure_time"])]}
    ticks = len(tick_times(duration, period))                 # as the recordings count
    if lengths and lengths != {ticks}:
        raise ValueError(f"runs that did not fail have {sorted(lengths)} ticks, not "
                         f"{ticks}: give the study's period and "
                         f"duration (now {period:g} s and {duration:g} s)")
