"""pipeline layer.

Importing it is light (the command line's parser needs neither drake nor torch), so
it does not import `reachwatch.systems`; it makes the one process-wide setting of
`reachwatch.systems` that must come before torch loads, for its modules that import
torch themselves (the triton-before-renderer order needs no help here: every render
goes through `reachwatch.diagrams`, which imports `reachwatch.systems` first)."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
