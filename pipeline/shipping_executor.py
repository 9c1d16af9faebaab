"""The executor of ``--executor dask://...``: a Dask client's, whose tasks bring the
files their arguments name. Its own module because it imports ``distributed`` (an
extra), only when a cluster is asked for."""

from distributed.cfexecutor import ClientExecutor

from reachwatch.diagrams.shipping import Packer, run_shipped

#: Shipments whose futures the executor holds (a task in flight holds its own too).
KEPT = 8


class ShippingExecutor(ClientExecutor):
    """A Dask client's executor whose tasks bring the files their arguments name
    (checkpoints, a user's code: `reachwatch.diagrams.shipping`), so that no worker
    opens a path of the driver's. Each distinct set of files is scattered to the
    cluster once and handed to its tasks as a future."""

    def __init__(self, client, **kwargs):
        super().__init__(client, **kwargs)
        self._packer, self._sent = Packer(), {}

    def _scattered(self, shipment):
        """The cluster's future of ``shipment``: scattered once, again when the worker
        holding it was lost; the `KEPT` most recently used are held."""
        sent = self._sent.pop(shipment.digest, None)
        if sent is None or sent.status != "finished":
            sent = self._client.scatter(shipment, hash=False)
        self._sent[shipment.digest] = sent
        while len(self._sent) > KEPT:            # the oldest first (dicts keep order)
            self._sent.pop(next(iter(self._sent)))
        return sent

    def submit(self, fn, /, *args, **kwargs):
        shipment = self._packer.pack(fn, args, kwargs)
        if shipment is None:
            return super().submit(fn, *args, **kwargs)
        return super().submit(run_shipped, self._scattered(shipment), fn, *args, **kwargs)
