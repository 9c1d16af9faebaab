"""`digest`: the content key of a stage or study, from the parts its result depends on."""

import dataclasses as dc
import hashlib
import json


def digest(*parts) -> str:
    """A short content key of JSON-able parts (dataclasses are expanded; numpy values
    by their content, `_keyed_value`)."""
    plain = [dc.asdict(p) if dc.is_dataclass(p) else p for p in parts]
    return hashlib.sha256(json.dumps(plain, sort_keys=True, default=_keyed_value).encode()
                          ).hexdigest()[:16]


def _keyed_value(value):
    """What `digest` keys a value JSON cannot hold by: a numpy array by its type, shape
    and every byte (its text abbreviates one of more than 1,000 numbers, so two arrays
    could share a key; a masked one with its mask; as `reach.fingerprint.canonical`
    keys them), a numpy scalar by its value, anything else by its text."""
    import numpy as np
    from reachwatch.reach.fingerprint import canonical
    if isinstance(value, np.ma.MaskedArray):
        return {"masked": _keyed_value(np.asarray(value.data)),
                "mask": _keyed_value(np.ma.getmaskarray(value))}
    if isinstance(value, np.ndarray) and value.dtype.hasobject:     # bytes: pointers
        return {"ndarray": "object", "shape": list(value.shape), "items": value.tolist()}
    if isinstance(value, (np.ndarray, np.integer, np.floating, np.bool_)):
        return canonical(value)
    if isinstance(value, np.generic):
        return value.item()
    return str(value)
