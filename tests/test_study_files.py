"""A finished study's files read by the monitor benchmarks (``monitor.json``,
``risks.npz``): one that is missing, damaged or not a study's is one line naming it and
exit status 2, not a traceback."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reachwatch.pipeline.monitor_saved import StudyFileError, open_saved_risks
from reachwatch.pipeline.monitor_sections import STUDY_RESULT_KEYS, read_study_result

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_a_study_result_missing_damaged_or_foreign_is_one_line(tmp_path):
    with pytest.raises(StudyFileError, match=r"monitor.json: cannot read a monitor study's "
                                             r"result \(No such file or directory\)"):
        read_study_result(tmp_path / "monitor.json")
    (tmp_path / "cut.json").write_text('{"lead_s": 1.6, "variants": {')   # cut off
    with pytest.raises(StudyFileError, match="cut.json: not a monitor study's result "
                                             r"\(not JSON: "):
        read_study_result(tmp_path / "cut.json")
    (tmp_path / "other.json").write_text('{"lead_s": 1.6, "variants": {}}')
    with pytest.raises(StudyFileError, match=r"other.json: not a monitor study's result \(it "
                                             r"has no within_s, alpha\)"):
        read_study_result(tmp_path / "other.json")
    (tmp_path / "whole.json").write_text(
        "{" + ", ".join(f'"{key}": {{}}' for key in STUDY_RESULT_KEYS) + "}")
    assert read_study_result(tmp_path / "whole.json")["variants"] == {}


def test_saved_risks_missing_damaged_or_foreign_are_one_line(tmp_path):
    path = tmp_path / "risks.npz"
    with pytest.raises(StudyFileError, match="cannot read a study's saved risks"):
        open_saved_risks(path)
    path.write_bytes(b"not an archive")
    with pytest.raises(StudyFileError, match=r"not a study's saved risks \(not an .npz"):
        open_saved_risks(path)
    with open(path, "wb") as f:
        np.save(f, np.zeros(3))                  # an .npy, not an archive of arrays
    with pytest.raises(StudyFileError, match=r"not a study's saved risks \(not an .npz"):
        open_saved_risks(path)
    with open(path, "wb") as f:
        np.savez(f, other=np.zeros(3))
    with pytest.raises(StudyFileError, match=r"\(no runs' ticks in it\)"):
        open_saved_risks(path)
    with open(path, "wb") as f:
        np.savez(f, **{"held_out/ticks": np.arange(3)})
    with open_saved_risks(path) as saved:
        assert saved["held_out/ticks"].tolist() == [0, 1, 2]


@pytest.mark.parametrize("script", ["monitor_rules.py", "monitor_mean.py"])
def test_a_benchmark_given_a_folder_that_is_no_study_says_so_in_one_line(tmp_path, script):
    done = subprocess.run([sys.executable, str(_BENCHMARKS / script), str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"{script}: error: {tmp_path / 'monitor.json'}: cannot read a monitor study's result "
        f"(No such file or directory); give a finished study's monitor.json"]
