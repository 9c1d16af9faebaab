"""The executor of ``--executor dask://...``: a Dask client's, whose tasks bring the
files their arguments name. Its own module because it imports ``distributed`` (an
extra), only when a cluster is asked for."""

from distributed.cfexecutor import ClientExecutor

from reachwatch.diagrams.shipping import Packer, run_shipped


class ShippingExecutor(ClientExecutor):
    """A Dask client's executor whose tasks bring the files their arguments name
    (checkpoints, a user's code: `reachwatch.diagrams.shipping`), so that no worker
    opens a path of the driver's. Each distinct set of files is scattered to the
    cluster once and handed to its tasks as a future."""

    def __init__(self, client, **kwargs):
        super().__init__(client, **kwargs)
        self._packer, self._sent = Packer(), {}

    def submit(self, fn, /, *args, **kwargs):
        shipment = self._packer.pack(fn, args, kwargs)
        if shipment is None:
            return super().submit(fn, *args, **kwargs)
        sent = self._sent.get(shipment.digest)
        if sent is None:
            sent = self._sent[shipment.digest] = self._client.scatter(shipment, hash=False)
        return super().submit(run_shipped, sent, fn, *args, **kwargs)
