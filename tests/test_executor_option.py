"""``--executor``: one option for every subcommand that runs chunks, its value checked
in one line before anything is loaded or connected."""

import re

import pytest

from reachwatch.pipeline import cli


@pytest.mark.parametrize("spec", ["dask://:::bad", "tcp://", "dask://host:notaport",
                                  "dask://host:0", "dask://host:99999", "dask://" + "x" * 5000,
                                  "dask://host:8786\n"])
def test_a_malformed_dask_address_is_one_line_naming_the_option(spec):
    """Dask answered these in its own words (not naming --executor: "missing port number
    in address ''"), or left a half-made client behind; now one line, no client made."""
    from reachwatch.pipeline.executors import make_executor
    with pytest.raises(ValueError, match=re.escape("--executor dask://HOST:PORT needs a host "
                                                   "and a port in [1, 65535]")) as e:
        make_executor(spec, connect_timeout=0.5)
    assert "\n" not in str(e.value) and len(str(e.value)) < 300


@pytest.mark.parametrize("command", [["run", "--scenario", "MISSING.yaml", "--out", "OUT"],
                                     ["guard", "--scenario", "MISSING.yaml"], ["sweep"], ["brt"],
                                     ["evaluate", "--scenario", "MISSING.yaml", "--out", "OUT"]])
@pytest.mark.parametrize("spec, message", [
    ("local:0", "local:N needs a whole number of workers N in [1, 256], got 'local:0'"),
    ("dask://host", "dask://HOST:PORT needs a host and a port in [1, 65535]"),
    ("threads", "must be local, local:N, inline or dask://HOST:PORT, got 'threads'")])
def test_every_executor_option_refuses_a_malformed_value_before_any_file_is_read(
        command, spec, message, capsys):
    """One ``--executor`` for every subcommand that runs chunks: a value that cannot
    name an executor is argparse's one-line error (exit 2), before the run file or
    scenario (missing here) is read; it was found only after the run file loaded."""
    with pytest.raises(SystemExit) as e:
        cli.main([*command, "--executor", spec])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"error: argument --executor: {message}" in err, err
    assert "MISSING" not in err


def test_saturation_advice_names_the_setting_only_where_chunks_would_queue():
    from reachwatch.pipeline.executors import SATURATION_VARIABLE, saturation_advice
    for quiet in (None, float("nan"), 1.0, 0.5):
        assert saturation_advice(quiet) == ""
    for queues in (1.1, float("inf")):
        advice = saturation_advice(queues)
        assert "\n" not in advice and f"{SATURATION_VARIABLE}=1 " in advice
        assert f"worker-saturation {queues:g}" in advice


def test_a_scheduler_without_workers_is_said_when_the_run_connects(caplog):
    """Before: a run started before any worker joined waited with nothing on screen."""
    import logging
    distributed = pytest.importorskip("dask.distributed")
    from reachwatch.pipeline.executors import make_executor
    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp",
                                  host="127.0.0.1", dashboard_address=None) as cluster, \
            caplog.at_level(logging.WARNING, logger="reachwatch"):
        spec = "dask://" + cluster.scheduler_address.removeprefix("tcp://")
        _, close = make_executor(spec, connect_timeout=5)
        close()
    assert (f"--executor {spec}: the scheduler has no workers yet: the run's chunks wait "
            f"until one joins") in caplog.text


def _first_rows(path, start, stop):
    import numpy as np
    return {"y": np.arange(start, stop)}


def test_files_for_a_cluster_without_workers_are_one_line(tmp_path):
    """Before: Dask's own ``TimeoutError: No valid workers found`` from sending a task's
    files to a cluster with no workers; now one line saying so."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("dask.distributed")
    from reachwatch.pipeline.shipping_executor import ShippingExecutor
    from reachwatch.reach.chunk_files import FolderStore, split
    from reachwatch.reach.chunks import run_chunks
    from reachwatch.reach.executors import WorkerLost
    data = tmp_path / "data.txt"
    data.write_text("x")
    with dask.config.set({"distributed.comm.timeouts.connect": "2s"}), \
            distributed.LocalCluster(n_workers=0, processes=False,
                                     dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        with pytest.raises(WorkerLost, match=r"^the files a task needs could not be sent to "
                                             r"the cluster \(.*\): it has no workers"):
            run_chunks(_first_rows, split(4, 2), FolderStore(tmp_path / "out"),
                       args=lambda chunk: (data, chunk.start, chunk.stop),
                       executor=ShippingExecutor(client), caller="job")
