"""`MonitorConfig`: the runtime monitor of a guarded loop as a scenario describes it
(its checkpoint, threshold, k-of-n rule and fallback), and how a threshold or rule the
file leaves out is taken from the checkpoint."""

import dataclasses as dc
from typing import Optional

from reachwatch.systems.bounds import bounded, check_bounds
from reachwatch.systems.checks import clip, is_file, warn_once

MAX_FLAG_WINDOW = 1000      # control ticks of the k-of-n rule


#: How `MonitorConfig` stores a steering mode (`systems.STEERING`) where its name
#: changed: the controller keeping its steering is stored under its older name
#: ``taxinet``, as every cache key made before holds it, so that ``controller`` and
#: ``taxinet`` in a run file are one setting with one key.
STORED_STEERING = {"controller": "taxinet"}


@dc.dataclass
class MonitorConfig:
    """The runtime monitor of the guarded loop: detector checkpoint and threshold, fallback strategy
    (``slow_down`` | ``brake``), steering while flagged (``controller``: the controller
    keeps steering, stored as ``taxinet``, its older name, so that the cache keys of
    existing runs stay put | ``dead_reckoning``: the last trusted estimate carried
    forward | ``oracle``: the true state, privileged),
    brake deceleration (m/s^2), how fast the speed comes back once the image is clear
    (``resume_acceleration`` m/s^2; 0 = at once, the paper's rule), and the k-of-n rule
    that confirms flags: the loop counts a tick as flagged when at least ``flags_needed``
    of the last ``flag_window`` control ticks had a score at or above the threshold, or
    NaN (`flags_at`; 1 of 1: every raw flag). Left null, the threshold and the k-of-n
    rule are those the checkpoint records (its metadata's ``threshold`` and ``flag_rule``, else 1 of 1): a
    monitor study's checkpoint holds its conformal threshold and rule; a detector
    trained by a run holds the threshold its training chose on its validation split,
    which a run's train stage may replace (``detector.threshold_folds``): name that one
    here to use it. `with_checkpoint_defaults` fills them in. ``encoder_process: true``
    runs the monitor's frame work (a history monitor's resize and encoder, a detector's
    whole network) in a process of its own, on one thread, beside the controller's at
    each tick: the same flags, and a faster tick where a core is free and that thread
    keeps up with the controller (measure it: ``benchmarks/online.py --encoder-process``;
    `systems.HistoryMonitor`, `systems.AnomalyDetector`); batches of runs, which keep
    every core busy already, encode in the loop."""
    detector: str = ""
    threshold: Optional[float] = bounded(None, 0.0, 1.0)
    strategy: str = "slow_down"
    steering: str = "taxinet"
    brake_deceleration: float = bounded(1.0, 0.0, 100.0, low_open=True, unit="m/s^2")
    resume_acceleration: float = bounded(0.0, 0.0, unit="m/s^2")
    flags_needed: Optional[int] = bounded(None, 1, MAX_FLAG_WINDOW, whole=True,
                                          note="<= flag_window; both set or both null")
    flag_window: Optional[int] = bounded(None, 1, MAX_FLAG_WINDOW, whole=True, unit="ticks")
    encoder_process: bool = False

    @property
    def fallback(self):
        """The `systems.Fallback` this monitor switches to while flagged."""
        from reachwatch.systems import Fallback
        return Fallback(self.strategy, self.steering, brake_deceleration=self.brake_deceleration,
                        resume_acceleration=self.resume_acceleration)

    def with_fallback(self, fallback) -> "MonitorConfig":
        """A copy whose strategy and steering are those of ``fallback`` (a name such as
        ``"slow_down+dead_reckoning"``, or a `systems.Fallback`); the other settings
        are this monitor's."""
        from reachwatch.systems import Fallback
        chosen = Fallback.parse(fallback)
        return dc.replace(self, strategy=chosen.strategy,
                          steering=STORED_STEERING.get(chosen.steering, chosen.steering))

    @classmethod
    def watching(cls, detector: str) -> "MonitorConfig":
        """A monitor of ``detector`` with a fixed placeholder threshold (0.5) and rule (1
        of 1), for loops that read the detector's score and do not depend on what a
        threshold does (sweeps, runs that read the score along the loop alone): their
        cache keys hold the detector and nothing else of the monitor, and a checkpoint
        without a threshold of its own works there."""
        return cls(detector=detector, threshold=0.5 if detector else None,
                   flags_needed=1, flag_window=1)

    def with_checkpoint_defaults(self) -> "MonitorConfig":
        """A copy whose null ``threshold`` and k-of-n rule are the checkpoint's: its
        metadata's ``threshold`` and ``flag_rule`` ``[k, n]`` (1 of 1 when it has none,
        or when there is no checkpoint). A null threshold with a checkpoint that holds
        none is a one-line ValueError; with no checkpoint it stays null."""
        if (self.flags_needed is None) != (self.flag_window is None):
            raise ValueError("monitor.flags_needed / monitor.flag_window: set both or "
                             "neither (neither: the checkpoint's rule, else 1 of 1)")
        if self.threshold is not None and self.flag_window is not None:
            return self
        metadata = {}
        if self.detector:
            from .checkpoints import checkpoint_metadata
            try:
                metadata = checkpoint_metadata(self.detector)
            except ValueError as e:
                raise ValueError(f"monitor.detector: {e}") from None
        threshold = self.threshold
        if threshold is None and self.detector:
            if not isinstance(metadata.get("threshold"), (int, float)):
                raise ValueError(f"monitor.threshold: {clip(self.detector, 200)} holds no "
                                 f"threshold of its own; set monitor.threshold")
            threshold = float(metadata["threshold"])
        k, n = ((self.flags_needed, self.flag_window) if self.flag_window is not None
                else tuple(metadata.get("flag_rule", (1, 1))))
        own = [int(v) for v in metadata.get("flag_rule", (1, 1))]
        mixed = ((self.threshold is not None and self.flag_window is None and own != [1, 1])
                 or (self.threshold is None and self.flag_window is not None
                     and [int(k), int(n)] != own))
        if self.detector and isinstance(metadata.get("threshold"), (int, float)) and mixed:
            warn_once(f"monitor: {clip(self.detector, 120)} fixed its threshold "
                      f"{float(metadata['threshold']):.4g} together with its rule {own[0]} of "
                      f"{own[1]}; this loop flags at {threshold:.4g} with {int(k)} of {int(n)} "
                      f"(one of the pair set, the other the checkpoint's), a pair nothing "
                      f"judged: set both, or neither",
                      key=("monitor pair", self.detector, threshold, int(k), int(n)))
        full = dc.replace(self, threshold=threshold, flags_needed=int(k), flag_window=int(n))
        check_bounds(full, "monitor.")      # a checkpoint's own values, checked as a file's
        return full

    def validate(self):
        """Raise ValueError naming the first bad field, the checkpoint's own threshold
        and rule included; return self. A null threshold or rule stays null here, to be
        taken from whatever checkpoint the monitor names when a loop is built (a
        pipeline names its own trained detector later), so that a value read from one
        checkpoint never stays behind for another."""
        from reachwatch.systems import check_k_of_n
        check_bounds(self, "monitor.")      # each state keeps its window's flags
        if self.detector and not is_file(self.detector):
            raise ValueError(f"monitor.detector: file not found: {clip(self.detector, 200)}")
        full = self.with_checkpoint_defaults()
        try:
            check_k_of_n(full.flags_needed, full.flag_window)
        except ValueError as e:
            raise ValueError(f"monitor.flags_needed / monitor.flag_window: {e}") from None
        try:
            steering = self.fallback.steering
        except ValueError as e:
            raise ValueError(f"monitor.{e}") from None
        self.steering = STORED_STEERING.get(steering, steering)
        return self
