"""The executor of ``--executor dask://...``: a Dask client's, whose tasks bring the
files their arguments name. Its own module because it imports ``distributed`` (an
extra), only when a cluster is asked for."""

import threading

from distributed.cfexecutor import ClientExecutor

from reachwatch.diagrams.shipping import Packer, run_shipped
from reachwatch.reach.executors import WorkerLost, run_portably
from reachwatch.systems.files import keyed_by_driver, keyed_digests

from .executors import describe_identity, process_identity

#: Shipments whose futures the executor holds (a task in flight holds its own too).
KEPT = 8


def run_on_worker(expected: dict, keyed, shipment, fn, /, *args, **kwargs):
    """A task on a worker: refused, in one line, when the worker's versions, reachwatch
    source or render stack (`process_identity`) differ from the driver's ``expected`` (a
    worker that joined after the driver checked those connected); else ``fn(*args, **kwargs)``,
    with ``shipment``'s files (`run_shipped`) when it brings some; a checkpoint or a
    user's code it loads must be content the driver keyed (``keyed``, its
    `keyed_digests`: `keyed_by_driver`), not a file shipped after an edit."""
    mine = process_identity()
    if mine != expected:
        raise WorkerLost(f"this worker has {describe_identity(mine)}, the driver "
                           f"{describe_identity(expected)}: it joined with another install; "
                           f"stop it, or install the same reachwatch, versions and GL driver there")
    with keyed_by_driver(keyed):
        if shipment is None:
            return run_portably(fn, *args, **kwargs)
        return run_portably(run_shipped, shipment, fn, *args, **kwargs)


class ShippingExecutor(ClientExecutor):
    """A Dask client's executor whose tasks bring the files their arguments name
    (checkpoints, a user's code: `reachwatch.diagrams.shipping`), so that no worker
    opens a path of the driver's. Each distinct set of files is scattered to the
    cluster once and handed to its tasks as a future. Every task checks first that its
    worker has the driver's versions and render stack (`run_on_worker`): a worker that
    joins after the driver's check is refused at its first task, before any result."""

    def __init__(self, client, **kwargs):
        super().__init__(client, **kwargs)
        self._packer, self._sent = Packer(), {}
        self._sending = threading.Lock()         # `run_together`'s jobs submit from threads
        self._expected = process_identity()

    def _scattered(self, shipment):
        """The cluster's future of ``shipment``: scattered once, again when the worker
        holding it was lost; the `KEPT` most recently used are held."""
        with self._sending:
            sent = self._sent.pop(shipment.digest, None)
            if sent is None or sent.status != "finished":
                try:
                    sent = self._client.scatter(shipment, hash=False)
                except TimeoutError as e:       # Dask's, when the cluster has no workers
                    raise WorkerLost(f"the files a task needs could not be sent to the "
                                     f"cluster ({e}): it has no workers; start them, then "
                                     f"run again (finished chunks are kept)") from e
            self._sent[shipment.digest] = sent
            while len(self._sent) > KEPT:            # the oldest first (dicts keep order)
                self._sent.pop(next(iter(self._sent)))
            return sent

    def submit(self, fn, /, *args, **kwargs):
        shipment = self._packer.pack(fn, args, kwargs)
        sent = None if shipment is None else self._scattered(shipment)
        return super().submit(run_on_worker, self._expected, keyed_digests(), sent, fn,
                              *args, **kwargs)
