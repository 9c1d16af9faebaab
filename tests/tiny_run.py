"""The tiny run file the ``reachwatch run`` tests share: every stage, at sizes that run
in seconds (a 5x3x5 grid, 40 images of 24x40, one epoch)."""

TINY = """
name: tiny
train: [{runway: KMWH, hour: 9.0, sky: clear}]
test: [{runway: KSFO, hour: 17.0, sky: clear}]
grid: [5, 3, 5]
horizon: 4.0
dataset: {samples: 40, height: 24, width: 40, chunk_size: 16}
detector:
  detector: {height: 24, width: 40, channels: [4, 8]}
  epochs: 1
  batch_size: 8
  device: cpu
ensemble: {seeds: [1, 2], samples: 48, epochs: 2}
guard: {candidates: 2, online_seconds: 0.2, meshcat_html: true, check_starts: 2, tradeoff_points: 3, noise_starts: 0}
fidelity: {starts: 3, max_box_exits: 1.0}
incremental:
  environment: {runway: KMWH, hour: 17.0, sky: clear}
  anomalies: 20
  replay: 20
  epochs: 2
"""


#: A tiny monitor study (``monitor: {kind: history}``) to append to `TINY`.
MONITOR_STUDY = """
monitor:
  kind: history
  family: {seed: 4}
  train: 1
  calibrate: 1
  held_out: 1
  alpha: 0.5
  runs: 6
  duration: 2.0
  within: 1.0
  height: 16
  width: 24
  pool: [2, 3]
  epochs: 1
  head_epochs: 2
  guarded_runs: 2
  variants:
    - {name: one frame}
    - {name: GRU 3 + signals, frames: 3, stride: 2, temporal: gru, signals: true}
"""


def taxi_application():
    """The taxi application, which the datasets of the tests are of."""
    from reachwatch.reach.application import load_application
    from reachwatch.taxi.application import TAXI_APPLICATION
    return load_application(TAXI_APPLICATION)
