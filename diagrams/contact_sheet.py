"""A labelled grid of camera images over environments (runways x hours x skies)."""

import cv2
import numpy as np

from reachwatch.systems import RUNWAYS, SKIES, CameraConfig, Environment

from .render import StateRenderer

DEFAULT_HOURS = (9.0, 17.0, 21.0)


def environment_sheet(environments, *, per_row: int, state=(0.0, 150.0, 0.0),
                      camera: CameraConfig = None, captions=None, progress=None,
                      render=None) -> np.ndarray:
    """RGB uint8 grid of the camera view of each `Environment` at ``state``
    [px m, py m, theta rad], ``per_row`` tiles a row (the last row padded black), each
    captioned (default: the environment's name); ``progress`` wraps the iterable.
    ``render``: a function of an environment returning its RGB view, in place of the
    taxi's wing camera at ``state`` (another plant's camera)."""
    environments = list(environments)
    captions = captions or [e.name for e in environments]
    render = render or (lambda env: StateRenderer(environment=env, camera=camera).render(state))
    tiles = []
    for env, caption in (progress(list(zip(environments, captions))) if progress
                         else zip(environments, captions)):
        tile = np.ascontiguousarray(render(env))
        cv2.putText(tile, caption, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 0, 255), 1,
                    cv2.LINE_AA)
        tiles.append(tile)
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % per_row)
    return np.vstack([np.hstack(tiles[i:i + per_row]) for i in range(0, len(tiles), per_row)])


def contact_sheet(*, state=(0.0, 150.0, 0.0), camera: CameraConfig = None,
                  runways=tuple(RUNWAYS), hours=DEFAULT_HOURS, skies=SKIES,
                  progress=None) -> np.ndarray:
    """RGB uint8 grid: one row per runway, one column per (hour, sky), each tile
    captioned. ``state = [px m, py m, theta rad]``; ``progress`` wraps the iterable."""
    combos = [(h, s) for h in hours for s in skies]
    envs = [Environment(r, h, s) for r in runways for h, s in combos]
    return environment_sheet(envs, per_row=len(combos), state=state, camera=camera,
                             captions=[f"{e.runway} {e.hour:g}h {e.sky}" for e in envs],
                             progress=progress)
